"""The HTTP sidecar: live classifier state, tunable thresholds, metrics and a bird's-eye page over FastAPI.

It is its own process and talks to the classifier only over Zenoh. Layers, outermost first:

- ``app.py``    the FastAPI app (routes, auth, error bodies, SSE);
- ``client.py`` :class:`ClassifierClient`, the one Zenoh session: config get/put, a background poll of
  ``classifier/state`` into a pre-rendered cache, liveliness + heartbeat watch, change events;
- ``metrics.py`` the Prometheus collector, reading the cache at scrape time;
- ``core.py``   pure functions and the HTTP view models: snapshot → JSON, config merge/validation, change
  detection, metric aggregation. No I/O, so the unit tests need no network.
"""
