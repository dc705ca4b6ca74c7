"""Numbers read from the environment (``JG_WATCHDOG_S``, ``JG_CRASH_LOOP_*``): one parser, one kind of message.

Why its own: a malformed value must stop a program at start with one line naming the variable — a watchdog or a
back-off that silently fell back to its default, or an ``inf`` no timer can wait (``faulthandler`` raised
OverflowError while arming it), had left a deployment unguarded without a word.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping

ENV_WATCHDOG = "JG_WATCHDOG_S"
DEFAULT_WATCHDOG_S = 10.0
HANG_GRACE_S = 5.0
"""The heartbeat thread silent this much longer than the watchdog period: a hard hang (faulthandler exits)."""
MAX_WATCHDOG_S = 1e9
"""The longest watchdog period: ``faulthandler``'s timer overflows a platform time_t beyond ~1e10 s."""


def env_number(name: str, default: float, lo: float, hi: float, *, env: Mapping[str, str] | None = None,
               unit: str = "", hint: str = "") -> float:
    """``env[name]`` (the process's environment by default) as a finite number in [lo, hi]; ``default`` when it is
    unset or blank. A ValueError naming the variable and its value otherwise; ``unit`` and ``hint`` (what 0 does,
    say) are added to the message."""
    raw = (os.environ if env is None else env).get(name, "").strip()
    if not raw:
        return default
    try:
        value = float(raw)
    except ValueError:
        raise ValueError(f"{name}={raw!r} is not a number" + (f" of {unit}" if unit else "")) from None
    if not (math.isfinite(value) and lo <= value <= hi):
        u = f" {unit[0]}" if unit else ""
        span = f"at most {_g(hi)}{u}" if lo == -math.inf else f"a number from {_g(lo)} to {_g(hi)}{u}"
        raise ValueError(f"{name}={raw!r}: expected {span}" + (f" ({hint})" if hint else ""))
    return value


def watchdog_period() -> float | None:
    """``JG_WATCHDOG_S`` (default 10 s; 0 or negative: no watchdog). A malformed value is a startup error, and so
    is one no timer can wait (inf, NaN, above ~10⁹ s: ``faulthandler`` had raised OverflowError on arming it, in
    the main and the heartbeat thread, and the process hung past SIGTERM). Here, beside the parser, not in
    :mod:`.service`: the stack's monitor-watch (:mod:`jitterguard.stack.watch`) reads it without importing Zenoh."""
    value = env_number(ENV_WATCHDOG, DEFAULT_WATCHDOG_S, -math.inf, MAX_WATCHDOG_S - HANG_GRACE_S,
                       unit="seconds", hint="0 turns the watchdog off")
    return value if value > 0 else None


def _g(x: float) -> str:
    """A bound as people write it: 1e9, not 1e+09."""
    return f"{x:g}".replace("e+0", "e").replace("e+", "e")
