"""Signed config writes and signed replies (``jitterguard.runtime.config_auth``): the rules on their own."""

from __future__ import annotations

import pytest

from jitterguard.runtime.config_auth import (MAX_SKEW_S, NONCE_BYTES, WriteVerifier, challenge_attachment, nonce_of,
                                             reply_attachment, reply_is_authentic, write_attachment)
from jitterguard.services.classifier.config_writes import ConfigWritePolicy

TOKEN = "s3cret-token"
KEY = "jg/ns1/classifier/config"
NOW = 1_796_000_000 * 10**9
PAYLOAD = b"\x81\xa5alpha\xcb@\x04\x00\x00\x00\x00\x00\x00"


def nonce(i: int) -> bytes:
    return i.to_bytes(NONCE_BYTES, "big")


def signed(payload: bytes = PAYLOAD, *, token: str = TOKEN, key: str = KEY, if_match: str | None = None,
           at: int = NOW, n: int = 1) -> bytes:
    return write_attachment(token, key, if_match, payload, at, nonce(n))


def test_a_signed_write_is_accepted_once_and_never_carries_the_token() -> None:
    v = WriteVerifier(TOKEN)
    att = signed()
    assert TOKEN.encode() not in att
    assert v.refusal(att, KEY, None, PAYLOAD, NOW + 10**9) is None
    assert "replay" in (v.refusal(att, KEY, None, PAYLOAD, NOW + 2 * 10**9) or "")  # the same write again
    assert v.refusal(signed(n=2), KEY, None, PAYLOAD, NOW) is None  # a new nonce is a new write


@pytest.mark.parametrize(("what", "att", "key", "if_match", "payload"), [
    ("payload altered", signed(), KEY, None, PAYLOAD + b"\x00"),
    ("condition added", signed(), KEY, "0" * 16, PAYLOAD),
    ("condition changed", signed(if_match="0" * 16), KEY, "1" * 16, PAYLOAD),
    ("another namespace", signed(), "jg/ns2/classifier/config", None, PAYLOAD),
    ("another token", signed(token="s3cret-tokem"), KEY, None, PAYLOAD),
])
def test_a_write_altered_in_any_part_is_refused(what: str, att: bytes, key: str, if_match: str | None,
                                                payload: bytes) -> None:
    assert "signature does not match" in (WriteVerifier(TOKEN).refusal(att, key, if_match, payload, NOW) or ""), what


@pytest.mark.parametrize("att", [None, b"", TOKEN.encode(), b"JGW1" + b"\x00" * 10, challenge_attachment(nonce(3))])
def test_an_unsigned_write_is_refused(att: bytes | None) -> None:
    """The old attachment (the token itself) included: it is no longer how a write proves itself."""
    assert "must be signed" in (WriteVerifier(TOKEN).refusal(att, KEY, None, PAYLOAD, NOW) or "")


def test_a_write_signed_outside_the_clock_window_is_refused_either_way() -> None:
    skew = int(MAX_SKEW_S * 1e9)
    v = WriteVerifier(TOKEN)
    assert v.refusal(signed(n=1), KEY, None, PAYLOAD, NOW + skew) is None
    assert v.refusal(signed(n=2), KEY, None, PAYLOAD, NOW - skew) is None
    late = v.refusal(signed(n=3), KEY, None, PAYLOAD, NOW + skew + 1)
    early = v.refusal(signed(n=4), KEY, None, PAYLOAD, NOW - skew - 1)
    assert late and "-300 s from the classifier's clock" in late
    assert early and "+300 s from the classifier's clock" in early


def test_the_nonce_cache_is_bounded_and_forgets_only_what_the_clock_would_refuse() -> None:
    skew = int(MAX_SKEW_S * 1e9)
    v = WriteVerifier(TOKEN, capacity=3)
    for n in range(3):
        assert v.refusal(signed(n=n), KEY, None, PAYLOAD, NOW) is None
    full = v.refusal(signed(n=9), KEY, None, PAYLOAD, NOW)
    assert full and "try again later" in full  # all three still inside the window: none forgotten
    later = NOW + skew + 1  # the first three could no longer pass the time check: forgotten
    assert v.refusal(signed(n=10, at=later), KEY, None, PAYLOAD, later) is None
    assert "from the classifier's clock" in (v.refusal(signed(n=0), KEY, None, PAYLOAD, later) or "")  # the clock's


def test_a_reply_is_authentic_only_for_its_query_key_and_payload() -> None:
    n = nonce(7)
    att = reply_attachment(TOKEN, KEY, n, PAYLOAD)
    assert reply_is_authentic(TOKEN, KEY, n, PAYLOAD, att)
    assert not reply_is_authentic(TOKEN, KEY, nonce(8), PAYLOAD, att)  # a reply to another query
    assert not reply_is_authentic(TOKEN, KEY, n, PAYLOAD + b"\x00", att)
    assert not reply_is_authentic(TOKEN, "jg/ns1/classifier/state", n, PAYLOAD, att)
    assert not reply_is_authentic("other", KEY, n, PAYLOAD, att)
    assert not reply_is_authentic(TOKEN, KEY, n, PAYLOAD, None)
    assert nonce_of(challenge_attachment(n)) == n and nonce_of(signed(n=7)) == n
    assert nonce_of(None) is None and nonce_of(TOKEN.encode()) is None


def test_the_classifier_signs_replies_only_with_a_token_and_to_a_query_with_a_nonce() -> None:
    with_token, open_writes = ConfigWritePolicy(token=TOKEN), ConfigWritePolicy.open()
    n = nonce(5)
    att = with_token.reply_attachment(challenge_attachment(n), KEY, PAYLOAD)
    assert att is not None and reply_is_authentic(TOKEN, KEY, n, PAYLOAD, att)
    assert with_token.reply_attachment(None, KEY, PAYLOAD) is None
    assert open_writes.reply_attachment(challenge_attachment(n), KEY, PAYLOAD) is None


def test_a_classifier_without_a_token_refuses_a_signed_write_even_with_open_writes() -> None:
    """Its writer holds a token and takes no unsigned reply for the classifier's: the write must not land
    unconfirmed. An unsigned write still goes ahead under --open-config-writes."""
    why = ConfigWritePolicy.open().refusal(signed(), KEY, None, PAYLOAD, NOW)
    assert why and "this classifier has none" in why
    assert ConfigWritePolicy.open().refusal(None, KEY, None, PAYLOAD, NOW) is None
    assert "off" in (ConfigWritePolicy().refusal(None, KEY, None, PAYLOAD, NOW) or "")
