"""Config writes and classifier replies authenticated with ``JG_API_TOKEN``, without ever sending the token.

Until 7 Dec 2026 the sidecar sent its ``JG_API_TOKEN`` itself as the attachment of every config write. A query
goes to every queryable whose key matches, so any node that declared a queryable on ``jg/**`` received the token
(and could then write the config as it pleased), and could answer "applied" to a write that never happened. Now
the token is only a key:

- a **write** carries ``JGW1 · time (8 bytes, ns) · nonce (16) · HMAC-SHA256`` over the config key, the
  ``if_match`` parameter, the time, the nonce and the payload (:func:`write_attachment`). The classifier checks
  the MAC, refuses a time more than :data:`MAX_SKEW_S` from its own clock, and refuses a nonce it has already
  accepted inside that window (:class:`WriteVerifier`): a captured write can be neither altered, replayed nor
  aimed at another namespace;
- a **read** from a holder of the token carries ``JGC1 · nonce`` (:func:`challenge_attachment`);
- the classifier, when it has a token, answers a query that carried a nonce (a write or a read) with
  ``JGR1 · HMAC-SHA256`` over the key, the nonce and its reply payload (:func:`reply_attachment`), which the
  sidecar checks (:func:`reply_is_authentic`): a reply from anything else is not taken for the classifier's.
  Zenoh's error replies carry no attachment, so a refusal cannot be authenticated; an authenticated success
  always wins over it.

Pure functions and one bounded cache: the time and the nonce are the caller's (no clock, no randomness here).
"""

from __future__ import annotations

import hashlib
import hmac
import threading
from collections import OrderedDict

WRITE_TAG = b"JGW1"
CHALLENGE_TAG = b"JGC1"
REPLY_TAG = b"JGR1"
NONCE_BYTES = 16
MAC_BYTES = 32
_TIME_BYTES = 8
WRITE_BYTES = len(WRITE_TAG) + _TIME_BYTES + NONCE_BYTES + MAC_BYTES
CHALLENGE_BYTES = len(CHALLENGE_TAG) + NONCE_BYTES
REPLY_BYTES = len(REPLY_TAG) + MAC_BYTES

MAX_SKEW_S = 300.0
"""How far a write's time may be from the classifier's clock (either way). Hosts of one vehicle keep time far
closer than this (NTP/PTP); it bounds how long a captured write could be replayed, which the nonce cache stops
inside the window."""

SEEN_CAPACITY = 4096
"""Nonces remembered at most. Only a holder of the token can fill it (each entry is a write with a valid MAC);
when every entry is still inside the window, writes are refused rather than the oldest nonce forgotten."""


def _mac(token: str, purpose: bytes, *parts: bytes) -> bytes:
    """HMAC-SHA256 keyed by the token over ``purpose`` and length-prefixed parts (no two inputs share bytes)."""
    mac = hmac.new(token.encode(), purpose, hashlib.sha256)
    for part in parts:
        mac.update(len(part).to_bytes(8, "big"))
        mac.update(part)
    return mac.digest()


def _write_mac(token: str, key: str, if_match: str | None, stamp_nonce: bytes, payload: bytes) -> bytes:
    return _mac(token, b"jitterguard config write", key.encode(), (if_match or "").encode(), stamp_nonce, payload)


def write_attachment(token: str, key: str, if_match: str | None, payload: bytes, now_ns: int,
                     nonce: bytes) -> bytes:
    """The attachment of a config write of ``payload`` to ``key`` (the namespace's ``classifier/config``, not
    the selector), conditional on ``if_match`` when given, made at ``now_ns`` (Unix time) with a fresh random
    ``nonce`` of :data:`NONCE_BYTES`."""
    if len(nonce) != NONCE_BYTES:
        raise ValueError(f"a nonce is {NONCE_BYTES} bytes, not {len(nonce)}")
    stamp_nonce = now_ns.to_bytes(_TIME_BYTES, "big", signed=True) + nonce
    return WRITE_TAG + stamp_nonce + _write_mac(token, key, if_match, stamp_nonce, payload)


def challenge_attachment(nonce: bytes) -> bytes:
    """The attachment of a read whose reply the classifier should authenticate."""
    if len(nonce) != NONCE_BYTES:
        raise ValueError(f"a nonce is {NONCE_BYTES} bytes, not {len(nonce)}")
    return CHALLENGE_TAG + nonce


def is_write_attachment(attachment: bytes | None) -> bool:
    """Whether ``attachment`` has the shape of a signed write (its MAC not checked)."""
    return attachment is not None and len(attachment) == WRITE_BYTES and attachment.startswith(WRITE_TAG)


def nonce_of(attachment: bytes | None) -> bytes | None:
    """The nonce a query carried (a signed write's or a read's challenge), to answer with :func:`reply_attachment`;
    None for anything else."""
    if is_write_attachment(attachment):
        start = len(WRITE_TAG) + _TIME_BYTES
        return attachment[start:start + NONCE_BYTES]  # type: ignore[index]
    if attachment is not None and len(attachment) == CHALLENGE_BYTES and attachment.startswith(CHALLENGE_TAG):
        return attachment[len(CHALLENGE_TAG):]
    return None


def reply_attachment(token: str, key: str, nonce: bytes, payload: bytes) -> bytes:
    """What the classifier attaches to its reply ``payload`` on ``key`` to a query that carried ``nonce``."""
    return REPLY_TAG + _mac(token, b"jitterguard reply", key.encode(), nonce, payload)


def reply_is_authentic(token: str, key: str, nonce: bytes, payload: bytes, attachment: bytes | None) -> bool:
    """Whether a reply came from a holder of ``token`` answering the query that carried ``nonce``."""
    return (attachment is not None and len(attachment) == REPLY_BYTES
            and hmac.compare_digest(attachment, reply_attachment(token, key, nonce, payload)))


class WriteVerifier:
    """Checks signed writes against one token and remembers the nonces it accepted inside the time window."""

    def __init__(self, token: str, max_skew_s: float = MAX_SKEW_S, capacity: int = SEEN_CAPACITY) -> None:
        self._token = token
        self._skew_ns = int(max_skew_s * 1e9)
        self._capacity = capacity
        self._seen: OrderedDict[bytes, int] = OrderedDict()  # nonce -> when it may be forgotten (ns, insertion order)
        self._lock = threading.Lock()  # Zenoh may call the queryable from several threads at once

    def refusal(self, attachment: bytes | None, key: str, if_match: str | None, payload: bytes,
                now_ns: int) -> str | None:
        """Why the write is refused, or None (then its nonce is remembered: the same write is refused next time)."""
        if not is_write_attachment(attachment):
            return ("unauthorised: a config write must be signed with the classifier's JG_API_TOKEN "
                    "(the sidecar's write attachment)")
        assert attachment is not None
        stamp_nonce = attachment[len(WRITE_TAG):len(WRITE_TAG) + _TIME_BYTES + NONCE_BYTES]
        if not hmac.compare_digest(attachment[-MAC_BYTES:],
                                   _write_mac(self._token, key, if_match, stamp_nonce, payload)):
            return "unauthorised: the write's signature does not match the classifier's JG_API_TOKEN"
        sent_ns = int.from_bytes(stamp_nonce[:_TIME_BYTES], "big", signed=True)
        if abs(now_ns - sent_ns) > self._skew_ns:
            return (f"unauthorised: the write's time is {(sent_ns - now_ns) / 1e9:+.0f} s from the classifier's "
                    f"clock (at most ±{self._skew_ns / 1e9:.0f} s: a replay, or the hosts' clocks differ)")
        nonce = stamp_nonce[_TIME_BYTES:]
        with self._lock:
            self._forget_expired(now_ns)
            if nonce in self._seen:
                return "unauthorised: this signed write was received once already (a replay)"
            if len(self._seen) >= self._capacity:
                return (f"refused: {self._capacity} signed writes in the last {2 * self._skew_ns / 1e9:.0f} s; "
                        f"try again later")
            self._seen[nonce] = sent_ns + self._skew_ns
        return None

    def _forget_expired(self, now_ns: int) -> None:
        """Drop nonces whose write could no longer pass the time check (insertion order is nearly time order,
        so scan all: at most ``capacity`` entries, and only on a write)."""
        for nonce in [n for n, until in self._seen.items() if until < now_ns]:
            del self._seen[nonce]
