"""The sidecar's request guard: foreign Host (400), cross-site writes (403), non-JSON writes (415), bodies over
64 KB (413, refused from the headers without reading the body). Pure rules first, then a tokenless sidecar
over real HTTP — the case a cross-site page could exploit — against a real classifier."""

from __future__ import annotations

from collections.abc import Iterator

import httpx
import pytest

from jitterguard.services.sidecar.guard import MAX_BODY_BYTES, HostPolicy, is_json_type, refusal, split_host

from .stack import Stack, start_stack

LOOPBACK = HostPolicy("127.0.0.1")


def _h(**headers: str) -> dict[str, str]:
    return {k.replace("_", "-"): v for k, v in headers.items()}


@pytest.mark.parametrize("host, bind, ok", [
    ("127.0.0.1:8000", "127.0.0.1", True), ("localhost:8000", "127.0.0.1", True), ("[::1]:8000", "127.0.0.1", True),
    ("attacker.example:8000", "127.0.0.1", False), ("127.0.0.1.nip.io", "127.0.0.1", False),
    ("10.0.0.5:8000", "10.0.0.5", True), ("10.0.0.6:8000", "10.0.0.5", False), ("localhost", "10.0.0.5", False),
    ("192.168.1.20:8000", "0.0.0.0", True), ("vehicle.local:8000", "0.0.0.0", False),
])
def test_host_policy(host: str, bind: str, ok: bool) -> None:
    assert HostPolicy(bind).host_allowed(split_host(host)) is ok
    refused = refusal("GET", _h(host=host), HostPolicy(bind))
    assert refused is None if ok else refused[0] == 400


def test_allowed_host_names_are_answered() -> None:
    policy = HostPolicy("0.0.0.0", frozenset({"vehicle.local"}))
    assert refusal("GET", _h(host="vehicle.local:8000"), policy) is None


@pytest.mark.parametrize("ctype, ok", [("application/json", True), ("application/json; charset=utf-8", True),
                                       ("application/merge-patch+json", True), ("text/plain", False),
                                       ("application/x-www-form-urlencoded", False), ("multipart/form-data", False),
                                       (None, False)])
def test_json_types(ctype: str | None, ok: bool) -> None:
    assert is_json_type(ctype) is ok


def test_write_rules_in_order() -> None:
    base = _h(host="127.0.0.1:8000", content_type="application/json", content_length="20")
    assert refusal("PATCH", base, LOOPBACK) is None
    assert refusal("PATCH", {**base, "origin": "http://127.0.0.1:8000"}, LOOPBACK) is None  # the sidecar's page
    assert refusal("PATCH", {**base, "origin": "https://evil.example"}, LOOPBACK)[0] == 403
    assert refusal("PATCH", {**base, "origin": "null"}, LOOPBACK)[0] == 403  # sandboxed frames, file:// pages
    status, why = refusal("PATCH", {**base, "sec-fetch-site": "cross-site"}, LOOPBACK)
    assert status == 403 and "(Sec-Fetch-Site: cross-site)" in why and "None" not in why  # had said "(Origin None)"
    assert refusal("PATCH", {**base, "content-type": "text/plain"}, LOOPBACK)[0] == 415
    assert refusal("POST", _h(host="127.0.0.1:8000"), LOOPBACK) is None  # bodyless, no Origin: not a browser
    assert refusal("POST", _h(host="127.0.0.1:8000", content_type="text/plain"), LOOPBACK)[0] == 415
    assert refusal("PATCH", {**base, "content-length": str(MAX_BODY_BYTES + 1)}, LOOPBACK)[0] == 413
    assert refusal("GET", {**base, "content-length": str(MAX_BODY_BYTES + 1)}, LOOPBACK)[0] == 413
    assert refusal("GET", _h(host="127.0.0.1:8000", origin="https://evil.example"), LOOPBACK) is None  # reads
    cors = HostPolicy("127.0.0.1", cors_origins=frozenset({"https://ops.example"}))
    assert refusal("PATCH", {**base, "origin": "https://ops.example"}, cors) is None


# ----------------------------------------------------------------------------------------- over real HTTP


@pytest.fixture(scope="module")
def open_stack() -> Iterator[Stack]:
    """A sidecar with no token (writes open to whoever may reach loopback): the guard is all that stops a page."""
    s = start_stack("sc-guard", token=None, window_ready=False)
    yield s
    s.close()


def _config(s: Stack) -> dict:
    with s.http() as c:
        return c.get("/v1/config").json()



@pytest.mark.integration
def test_cross_site_write_is_403_and_changes_nothing(open_stack: Stack) -> None:
    before = _config(open_stack)
    with open_stack.http() as c:
        # what a page on any site can send without a preflight: a "simple" POST
        r = c.post("/v1/config/preset/authors", content=b"x",
                   headers={"Origin": "https://evil.example", "Content-Type": "text/plain"})
        assert r.status_code == 403 and "cross-site" in r.json()["detail"]
        r = c.post("/v1/config/preset/authors", headers={"Sec-Fetch-Site": "cross-site"})
        assert r.status_code == 403
        assert _config(open_stack) == before
        r = c.post("/v1/config/preset/authors", headers={"Origin": open_stack.url})  # the sidecar's own page
        assert r.status_code == 200 and r.json()["alpha_per_class"]["car"] == 2.58
        assert c.put("/v1/config", json={}).status_code == 200


@pytest.mark.integration
def test_non_json_write_is_415(open_stack: Stack) -> None:
    before = _config(open_stack)
    with open_stack.http() as c:
        r = c.patch("/v1/config", content=b'{"alpha_default": 0.5}', headers={"Content-Type": "text/plain"})
        assert r.status_code == 415 and "application/json" in r.json()["detail"]
        r = c.patch("/v1/config", content=b"alpha_default=0.5",
                    headers={"Content-Type": "application/x-www-form-urlencoded"})
        assert r.status_code == 415
    assert _config(open_stack) == before


@pytest.mark.integration
def test_one_megabyte_body_is_413_declared_or_chunked(open_stack: Stack) -> None:
    before = _config(open_stack)
    big = b'{"alpha_default": 0.5, "pad": "' + b"x" * (1 << 20) + b'"}'
    with open_stack.http() as c:
        r = c.patch("/v1/config", content=big, headers={"Content-Type": "application/json"})
        assert r.status_code == 413 and str(MAX_BODY_BYTES) in r.json()["detail"]

        def chunks() -> Iterator[bytes]:  # no Content-Length: the guard counts and cuts it off
            for i in range(0, len(big), 16384):
                yield big[i:i + 16384]

        r = c.patch("/v1/config", content=chunks(), headers={"Content-Type": "application/json"})
        assert r.status_code == 413
    with open_stack.http() as c:
        assert c.get("/healthz").status_code == 200
    assert _config(open_stack) == before


@pytest.mark.integration
def test_oversized_body_is_refused_before_it_is_sent(open_stack: Stack) -> None:
    """33 MB announced, none of it sent: the answer comes from the headers alone (a 33 MB body used to be read
    into memory, 4.5 GB of it, blocking /healthz for 35 s)."""
    port = int(open_stack.url.rsplit(":", 1)[1])
    reply = open_stack.raw(f"PATCH /v1/config HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Type: application/json\r\n"
                           f"Content-Length: {33 * 1024 * 1024}\r\n\r\n".encode())
    assert reply.startswith("HTTP/1.1 413"), reply


@pytest.mark.integration
def test_foreign_host_is_400_dns_rebinding(open_stack: Stack) -> None:
    port = open_stack.url.rsplit(":", 1)[1]
    with open_stack.http() as c:
        r = c.get("/v1/config", headers={"Host": f"attacker.example:{port}"})
        assert r.status_code == 400 and "Host" in r.json()["detail"]
        r = c.post("/v1/config/preset/authors", headers={"Host": f"attacker.example:{port}"})
        assert r.status_code == 400
        assert c.get("/healthz", headers={"Host": f"localhost:{port}"}).status_code == 200
    with httpx.Client(base_url=f"http://localhost:{port}", timeout=10) as c:  # by name, on loopback: fine
        assert c.get("/healthz").status_code == 200


@pytest.mark.integration
def test_a_small_content_length_beside_a_chunked_body_is_refused(open_stack: Stack) -> None:
    """``Content-Length: 2`` with ``Transfer-Encoding: chunked``: the server frames the body by the chunks, and the
    guard, trusting the small length, had let 32 MB of them be read and parsed (and applied) — no token needed.
    Both headers together are now a 400, and nothing is applied."""
    before = _config(open_stack)
    port = int(open_stack.url.rsplit(":", 1)[1])
    body = b'{"alpha_default": 0.5}'
    reply = open_stack.raw(f"PATCH /v1/config HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Type: application/json\r\n"
                       f"Content-Length: 2\r\nTransfer-Encoding: chunked\r\n\r\n{len(body):x}\r\n".encode()
                 + body + b"\r\n0\r\n\r\n")
    assert reply.startswith("HTTP/1.1 400") and "Transfer-Encoding" in reply, reply
    assert _config(open_stack) == before


@pytest.mark.integration
@pytest.mark.parametrize("first, second", [("text/plain", "application/json"), ("application/json", "text/plain")])
def test_a_header_given_twice_is_refused_whichever_value_comes_first(open_stack: Stack, first: str,
                                                                     second: str) -> None:
    """The guard read the last ``Content-Type`` and FastAPI the first: ``text/plain`` then ``application/json``
    passed the 415 and met the app as text. A header read as one value, given twice, is a 400 naming it."""
    before = _config(open_stack)
    port = int(open_stack.url.rsplit(":", 1)[1])
    body = b'{"alpha_default": 0.5}'
    reply = open_stack.raw(f"PATCH /v1/config HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Type: {first}\r\n"
                       f"Content-Type: {second}\r\nContent-Length: {len(body)}\r\n\r\n".encode() + body)
    assert reply.startswith("HTTP/1.1 400") and "Content-Type given more than once" in reply, reply
    assert _config(open_stack) == before


@pytest.mark.integration
def test_if_match_given_twice_is_a_422_naming_it(open_stack: Stack) -> None:
    """``If-Match: *`` then a stale tag: FastAPI read the first, and the write was applied unconditionally. Two
    headers are a list, refused as the one-line list is."""
    before = _config(open_stack)
    with open_stack.http() as c:
        r = c.patch("/v1/config", json={"alpha_default": 0.5},
                    headers=[("If-Match", "*"), ("If-Match", '"0000000000000000"')])
        assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["header", "If-Match"], r.text
    assert _config(open_stack) == before
