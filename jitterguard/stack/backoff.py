"""Holding back a program that keeps crashing after it started (systemd's ``StartLimitBurst``/``RestartSec`` idea).

supervisord backs off only a program that dies before its ``startsecs``; one that crashes a few seconds after it
was called RUNNING (a bad weights file read lazily, a bug hit on the first message) is started again at once, for
ever: each restart of the detector is a Python start, a torch import and a weights load, seconds of CPU that the
rest of the pipeline needs. The stack's monitor (:mod:`.monitor`) asks :class:`CrashLoopGuard` each time it polls
supervisord, and does what it answers over supervisord's XML-RPC (``stopProcess`` / ``startProcess``).

A program that died unexpectedly :attr:`CrashLoopPolicy.exits` times within :attr:`CrashLoopPolicy.window_s`
after reaching RUNNING is stopped and held back, then started again after a back-off that doubles with every
loop in a row (10, 20, 40 … s, at most 300 s) and starts from the first step again once the program has stayed up
for a window. A program an operator stopped (STOPPED, not by the guard) or supervisord gave up on (FATAL) is left
alone, and its crashes before that are forgotten. Pure: no clock and no I/O; every time is epoch seconds given
by the caller.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from ..runtime.envvars import env_number

CRASH_LOOP_EXITS = 5
"""Unexpected exits (of a process that had reached RUNNING) within :data:`CRASH_LOOP_WINDOW_S` that make a loop."""
CRASH_LOOP_WINDOW_S = 60.0
CRASH_LOOP_BACKOFF_S = 10.0
"""The first hold; each further loop in a row doubles it."""
CRASH_LOOP_BACKOFF_MAX_S = 300.0
ENV_EXITS = "JG_CRASH_LOOP_EXITS"
ENV_WINDOW = "JG_CRASH_LOOP_WINDOW_S"
ENV_BACKOFF = "JG_CRASH_LOOP_BACKOFF_S"
ENV_BACKOFF_MAX = "JG_CRASH_LOOP_BACKOFF_MAX_S"
NEVER_HELD = frozenset({"monitor"})
"""The monitor never stops itself: it is the one that would start the program again."""
ACTIVE = frozenset({"STARTING", "RUNNING", "BACKOFF", "EXITED"})
"""States of a program supervisord is (re)starting: a program in one of them while held was started by someone
else (or the guard's stop has not taken yet)."""


@dataclass(frozen=True)
class CrashLoopPolicy:
    exits: int = CRASH_LOOP_EXITS
    window_s: float = CRASH_LOOP_WINDOW_S
    backoff_s: float = CRASH_LOOP_BACKOFF_S
    backoff_max_s: float = CRASH_LOOP_BACKOFF_MAX_S

    @property
    def enabled(self) -> bool:
        return self.exits > 0

    def hold_s(self, loop: int) -> float:
        """The hold after the ``loop``-th loop in a row (1-based): doubling, capped."""
        return min(self.backoff_max_s, self.backoff_s * 2.0 ** min(max(loop - 1, 0), 64))

    @classmethod
    def from_env(cls, env: Mapping[str, str] = os.environ) -> "CrashLoopPolicy":
        """The defaults, each overridden by its ``JG_CRASH_LOOP_*`` variable (``JG_CRASH_LOOP_EXITS=0`` turns the
        guard off). A malformed value is a startup error, as ``JG_WATCHDOG_S``'s is."""

        def number(name: str, default: float, *, minimum: float) -> float:
            return env_number(name, default, minimum, 1e9, env=env)

        exits = number(ENV_EXITS, CRASH_LOOP_EXITS, minimum=0)
        if exits != int(exits):
            raise ValueError(f"{ENV_EXITS}={env.get(ENV_EXITS)!r}: expected a whole number (0 turns it off)")
        first = number(ENV_BACKOFF, CRASH_LOOP_BACKOFF_S, minimum=0.1)
        return cls(exits=int(exits), window_s=number(ENV_WINDOW, CRASH_LOOP_WINDOW_S, minimum=1),
                   backoff_s=first, backoff_max_s=max(first, number(ENV_BACKOFF_MAX, CRASH_LOOP_BACKOFF_MAX_S,
                                                                    minimum=0.1)))


@dataclass(frozen=True)
class Action:
    """What the caller is to do about one program: ``stop`` it (``warn``: the first stop of this loop, the one to
    log) or ``start`` it."""

    kind: str  # "stop" | "start"
    name: str
    crashes: int = 0  # the exits that made the loop (stop)
    hold_s: float = 0.0  # how long it is held back (stop)
    until: float = 0.0  # when it is started again (stop)
    loop: int = 0  # loops in a row (stop)
    warn: bool = False


@dataclass
class _Program:
    counted_since: float  # exits before this are not counted (the guard's last start, or the operator's stop)
    loop: int = 0  # loops in a row; back to 0 once the program has stayed up for a window
    held_until: float | None = None
    stopped_seen: bool = False  # while held: supervisord has said STOPPED since the guard's stop
    start_asked_at: float | None = None
    backed_off: int = 0  # loops over the run


@dataclass
class CrashLoopGuard:
    """Per program: its unexpected exits after RUNNING in, what to do out (:meth:`step`)."""

    policy: CrashLoopPolicy = field(default_factory=CrashLoopPolicy)
    since: float = 0.0  # exits before this (the run's start, the monitor's) are not counted
    programs: dict[str, _Program] = field(default_factory=dict)

    def _prog(self, name: str) -> _Program:
        prog = self.programs.get(name)
        if prog is None:
            prog = self.programs[name] = _Program(counted_since=self.since)
        return prog

    def step(self, name: str, state: str, crashes: Iterable[float], now: float) -> Action | None:
        """One look at one program: its supervisord ``state`` and the times of its unexpected exits after it had
        reached RUNNING (any order; older ones are ignored). The caller does what the answer says; a stop or a
        start that fails is simply asked for again on the next step."""
        if not self.policy.enabled or name in NEVER_HELD:
            return None
        crashes = list(crashes)
        prog = self._prog(name)
        if prog.held_until is not None:
            return self._held(name, prog, state, now)
        if state in ("STOPPED", "STOPPING", "FATAL"):
            # an operator stopped it, or supervisord gave up on it: not ours; forget its crashes until then
            prog.counted_since = max(prog.counted_since, now)
            return None
        recent = [t for t in crashes if t >= prog.counted_since and now - t <= self.policy.window_s]
        if prog.loop and now - max([prog.counted_since, *crashes]) >= self.policy.window_s:
            prog.loop = 0  # it stayed up for a window since its last start or crash: the next hold is short again
        if len(recent) < self.policy.exits:
            return None
        prog.loop += 1
        prog.backed_off += 1
        hold = self.policy.hold_s(prog.loop)
        prog.held_until, prog.stopped_seen, prog.start_asked_at = now + hold, False, None
        return Action("stop", name, crashes=len(recent), hold_s=hold, until=now + hold, loop=prog.loop, warn=True)

    def _held(self, name: str, prog: _Program, state: str, now: float) -> Action | None:
        assert prog.held_until is not None
        if state == "STOPPED":
            prog.stopped_seen = True
            if now >= prog.held_until:
                prog.start_asked_at = now
                return Action("start", name)
            return None
        if state == "STOPPING":
            return None
        if state in ACTIVE and not prog.stopped_seen and prog.start_asked_at is None:
            # the stop has not taken yet (supervisord refuses to stop an EXITED program): ask again, quietly
            return Action("stop", name, hold_s=prog.held_until - now, until=prog.held_until, loop=prog.loop)
        # started (by the guard, or by an operator before the hold ran out), or given up on: the hold is over;
        # exits count again from the start on
        prog.counted_since = max(prog.counted_since, prog.start_asked_at or now)
        prog.held_until, prog.start_asked_at, prog.stopped_seen = None, None, False
        return None

    def held_back(self) -> dict[str, float]:
        """Program → when it is to be started again (epoch s), for every program held back now."""
        return {n: p.held_until for n, p in sorted(self.programs.items()) if p.held_until is not None}

    def backed_off(self) -> dict[str, int]:
        """Program → how many times it was held back over the run."""
        return {n: p.backed_off for n, p in sorted(self.programs.items()) if p.backed_off}

    def as_json(self) -> dict[str, Any]:
        return {"held_back_until_s": self.held_back(), "backed_off": self.backed_off(),
                "loops": {n: p.loop for n, p in sorted(self.programs.items()) if p.loop}}

    def restore(self, data: Mapping[str, Any], now: float) -> None:
        """Take back what :meth:`as_json` said (a restarted monitor): a program it held is still held, and the
        counts go on. Exits before ``now`` are not counted again."""
        self.since = max(self.since, now)
        for name, n in (data.get("backed_off") or {}).items():
            self._prog(name).backed_off = int(n)
        for name, n in (data.get("loops") or {}).items():
            self._prog(name).loop = int(n)
        for name, until in (data.get("held_back_until_s") or {}).items():
            prog = self._prog(name)
            prog.held_until, prog.stopped_seen = float(until), True
        for prog in self.programs.values():
            prog.counted_since = max(prog.counted_since, now)
