"""The multi-object tracker: batched CV/CTRV Kalman filters, Autoware-gated association, track lifecycle.

``core.TrackerCore`` is the pure per-frame update (numpy in, numpy out); ``service.TrackerService`` is its thin
Zenoh adapter (``detections`` in, ``tracks/{id}`` and ``tracked`` out); ``cli.register`` adds
``jitterguard tracker`` and ``jitterguard bench tracker``.
"""
