"""The classifier goes away: the sidecar stays up, says so clearly, and applies nothing."""

from __future__ import annotations

import json

import httpx
import pytest

from jitterguard.runtime import loopback_options
from jitterguard.schemas.models import ClassifierConfig
from jitterguard.services.classifier.config_writes import ConfigWritePolicy
from jitterguard.services.classifier.service import ClassifierService

from .stack import start_stack, wait_for

pytestmark = pytest.mark.integration


def test_503_when_the_classifier_is_gone_and_recovery() -> None:
    stack = start_stack("sc-down")  # no token: writes are open on loopback
    try:
        with stack.http() as c, httpx.Client(base_url=stack.url, timeout=20.0) as sse, \
                sse.stream("GET", "/v1/events") as events:
            assert c.get("/readyz").status_code == 200
            assert c.patch("/v1/config", json={"alpha_default": 1.5}).status_code == 200
            stack.classifier.close()  # the classifier process is gone

            # Open event streams hear about it.
            kind = None
            for line in events.iter_lines():
                if line.startswith("event: "):
                    kind = line[7:]
                elif line.startswith("data: ") and kind == "ready":
                    lost = json.loads(line[6:])
                    if not lost["ready"]:
                        break
            assert "liveliness" in lost["reason"]

            def not_ready() -> dict | None:
                r = c.get("/readyz")
                return r.json() if r.status_code == 503 else None
            body = wait_for(not_ready, "readyz to report the classifier gone")
            assert body["ready"] is False and body["liveliness"] is False
            assert "liveliness" in body["reason"] and "classifier" in body["reason"]

            for method, path, payload in (("PATCH", "/v1/config", {"alpha_default": 0.5}),
                                          ("PUT", "/v1/config", {"alpha_default": 0.5}),
                                          ("POST", "/v1/config/preset/authors", None)):
                r = c.request(method, path, json=payload)
                assert r.status_code == 503, (method, r.text)
                detail = r.json()["detail"]
                assert "classifier" in detail and "nothing was applied" in detail, detail
                assert r.headers["retry-after"] == "1"
            r = c.get("/v1/config")
            assert r.status_code == 503 and "unreachable" in r.json()["detail"]
            r = c.get("/v1/state")
            assert r.status_code == 503 and "not ready" in r.json()["detail"]
            assert c.get(f"/v1/state/{stack.tracks[0].track_id}").status_code == 503
            assert c.get("/healthz").status_code == 200  # the sidecar itself is fine
            assert c.head("/healthz").status_code == 200 and c.head("/readyz").status_code == 503
            metrics = c.get("/metrics").text
            assert "jitterguard_classifier_up 0.0" in metrics
            assert 'jitterguard_sidecar_config_writes_total{result="unavailable"} 3.0' in metrics

            # A new classifier on the same endpoint: the sidecar reconnects on its own, and the config in
            # force is the new process's own (the refused writes above never reached anything).
            stack.classifier = ClassifierService(loopback_options(stack.ns, stack.zport, listen_self=True),
                                                 config_writes=ConfigWritePolicy.open())
            wait_for(lambda: c.get("/readyz").status_code == 200, "readiness after restart", timeout=30)
            assert c.get("/v1/config").json()["alpha_default"] == ClassifierConfig().alpha_default
            stack.wait_state(lambda b: b["counts"]["total"] == len(stack.tracks), "state after restart",
                             timeout=30)
            r = c.patch("/v1/config", json={"alpha_default": 0.5})
            assert r.status_code == 200 and stack.classifier.core.config.alpha_default == 0.5
    finally:
        stack.close()


def test_a_write_the_classifier_does_not_confirm_in_time_is_a_503_not_a_refusal() -> None:
    """Zenoh answers a get that times out with an error reply of its own ("Timeout", from no replier). That is not
    the classifier refusing: the write may still be applied, so the sidecar must say it did not confirm (503) and
    point at GET, not report a refusal (502) of a config that then comes into force."""
    import threading
    import time

    import zenoh

    from jitterguard.runtime import free_tcp_port
    from jitterguard.runtime.zenoh_config import build_config
    from jitterguard.schemas import encode, keys
    from jitterguard.schemas.models import ConfigReply
    from jitterguard.services.sidecar.client import ClassifierClient, ClassifierRejected, ClassifierUnavailable

    ns, port = "sc-slow", free_tcp_port()
    slow = zenoh.open(build_config(loopback_options(ns, port, listen_self=True)))
    applied = threading.Event()

    def late(query: zenoh.Query) -> None:  # a classifier whose worker is busy: it applies the write after 1 s
        time.sleep(1.0)
        applied.set()
        query.reply(query.key_expr, encode(ConfigReply(ok=True, config=ClassifierConfig())))

    def refuse(query: zenoh.Query) -> None:
        query.reply_err(encode(ConfigReply(ok=False, config=ClassifierConfig(), error="no")))

    queryable = slow.declare_queryable(keys.classifier_config(ns), late)  # before the token: declared in order
    token = slow.liveliness().declare_token(keys.alive(ns, "classifier"))
    client = ClassifierClient(loopback_options(ns, port), query_timeout_s=0.3)
    try:
        wait_for(lambda: client.is_alive(), "the classifier's liveliness token")
        with pytest.raises(ClassifierUnavailable, match="did not confirm the write"):
            client.put_config(ClassifierConfig(alpha_default=3.3))
        assert applied.wait(5)  # ...and it was applied after all: a 502 "refused" would have been false
        queryable.undeclare()
        queryable = slow.declare_queryable(keys.classifier_config(ns), refuse)

        def refused() -> str | None:  # once the new queryable is known on the client's side
            try:
                client.put_config(ClassifierConfig(alpha_default=3.3))
            except ClassifierRejected as exc:
                return str(exc)
            except ClassifierUnavailable:
                return None
            raise AssertionError("a refusing classifier accepted the write")
        assert "refused" in wait_for(refused, "a real refusal, which is still one")
    finally:
        client.close()
        queryable.undeclare()
        token.undeclare()
        slow.close()
