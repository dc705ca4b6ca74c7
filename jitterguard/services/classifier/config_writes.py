"""Who may change the classifier's config over Zenoh: the same token as the sidecar's HTTP API, or nobody.

A ``get`` on ``classifier/config`` with a payload is a write. Anyone who can reach the router can send one, so
the classifier checks it itself, whatever the transport does: with ``JG_API_TOKEN`` set, a write must be signed
with that token (:mod:`jitterguard.runtime.config_auth`: a MAC over the key, ``if_match``, the payload, a time and
a nonce; the token itself never travels), and the classifier signs its replies to the holder of the token;
without a token, writes are refused unless the classifier was started with ``--open-config-writes`` (what
``jitterguard up`` does on one host, where the router listens on loopback and the tokenless sidecar is
loopback-only too) — and even then a *signed* write is refused, since its writer expects a classifier that holds
its token and would take no unsigned reply for the classifier's. Reads (a ``get`` with no payload) stay open,
like ``GET /v1/config``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

from ...runtime.config_auth import WriteVerifier, is_write_attachment, nonce_of, reply_attachment

ENV_TOKEN = "JG_API_TOKEN"


def api_token_from_env() -> str | None:
    """``JG_API_TOKEN`` without surrounding whitespace; empty or blank counts as unset (a blank secret protects
    nothing, and a bearer token cannot carry the spaces or newline an env file may leave around one). The one
    reading of the variable, for the classifier and the sidecar alike: a blank token had passed the sidecar's
    "no public bind without a token" check."""
    return os.environ.get(ENV_TOKEN, "").strip() or None


@dataclass(frozen=True)
class ConfigWritePolicy:
    token: str | None = None
    open_writes: bool = False
    _verifier: WriteVerifier | None = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.token:  # the nonces this classifier accepted: one verifier for its life
            object.__setattr__(self, "_verifier", WriteVerifier(self.token))

    @classmethod
    def from_env(cls, open_writes: bool = False) -> "ConfigWritePolicy":
        """``JG_API_TOKEN`` (:func:`api_token_from_env`) and whether writes are open without one."""
        return cls(token=api_token_from_env(), open_writes=open_writes)

    @classmethod
    def open(cls) -> "ConfigWritePolicy":
        """Anyone connected may write (tests, and one host with a loopback-only router)."""
        return cls(open_writes=True)

    def describe(self) -> str:
        if self.token:
            return "config writes over Zenoh need a write signed with JG_API_TOKEN"
        return "config writes over Zenoh are open (no token)" if self.open_writes else \
            "config writes over Zenoh are off (no JG_API_TOKEN, no --open-config-writes)"

    def refusal(self, attachment: bytes | None, key: str, if_match: str | None, payload: bytes,
                now_ns: int) -> str | None:
        """Why a write of ``payload`` to ``key`` (the namespace's config key) carrying ``attachment`` is refused
        (None if it may go ahead). ``now_ns``: the classifier's clock (Unix time), for the write's time check."""
        if self._verifier is not None:
            return self._verifier.refusal(attachment, key, if_match, payload, now_ns)
        if is_write_attachment(attachment):
            return ("unauthorised: the write is signed with a JG_API_TOKEN and this classifier has none; set the "
                    "same JG_API_TOKEN for the classifier and the sidecar (nothing applied)")
        if self.open_writes:
            return None
        return ("config writes over Zenoh are off: set the same JG_API_TOKEN for the classifier and the sidecar, "
                "or start the classifier with --open-config-writes")

    def reply_attachment(self, attachment: bytes | None, key: str, payload: bytes) -> bytes | None:
        """What to attach to a reply ``payload`` to a query that carried ``attachment``: the reply's MAC when this
        classifier has a token and the query a nonce (a signed write, or a read's challenge); None otherwise."""
        nonce = nonce_of(attachment)
        if self.token is None or nonce is None:
            return None
        return reply_attachment(self.token, key, nonce, payload)
