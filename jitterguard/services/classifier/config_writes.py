"""Who may change the classifier's config over Zenoh: the same token as the sidecar's HTTP API, or nobody.

A ``get`` on ``classifier/config`` with a payload is a write. Anyone who can reach the router can send one, so
the classifier checks it itself, whatever the transport does: with ``JG_API_TOKEN`` set, a write must carry
that token as the query's attachment (the sidecar sends its own ``JG_API_TOKEN``); without a token, writes are
refused unless the classifier was started with ``--open-config-writes`` (what ``jitterguard up`` does on one
host, where the router listens on loopback and the tokenless sidecar is loopback-only too). Reads (a ``get``
with no payload) stay open, like ``GET /v1/config``.
"""

from __future__ import annotations

import hmac
import os
from dataclasses import dataclass

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
            return "config writes over Zenoh need JG_API_TOKEN"
        return "config writes over Zenoh are open (no token)" if self.open_writes else \
            "config writes over Zenoh are off (no JG_API_TOKEN, no --open-config-writes)"

    def refusal(self, attachment: bytes | None) -> str | None:
        """Why a write carrying ``attachment`` is refused (None if it may go ahead)."""
        if self.token:
            if attachment is not None and hmac.compare_digest(attachment, self.token.encode()):
                return None
            return "unauthorised: a config write needs the classifier's JG_API_TOKEN as the query attachment"
        if self.open_writes:
            return None
        return ("config writes over Zenoh are off: set the same JG_API_TOKEN for the classifier and the sidecar, "
                "or start the classifier with --open-config-writes")
