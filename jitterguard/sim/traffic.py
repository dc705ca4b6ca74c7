"""Collision-free longitudinal traffic: every agent in a lane follows the Intelligent Driver Model (IDM).

Why IDM: stop-and-go, queues at red lights and platoons behind a slow leader emerge from one small rule, and
followers never drive through their leaders — so ground-truth boxes never overlap along a lane. Red lights
and scripted stops (a delivery van, a bus stop, a pedestrian waiting to cross) are virtual stationary
obstacles. An agent that cannot stop comfortably when a light turns red is committed and drives through.

The integration is semi-implicit Euler with the trapezoid rule for position, so ``s`` is the exact integral of
the sampled speed ``v``: finite differences of positions reproduce the reported velocities.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]

_HARD_DECEL = 4.0  # m/s²: braking an agent may use for a light that just turned red, else it is committed


@dataclass(frozen=True)
class StopLine:
    """A stop line at arc length ``s`` (where the agent's front stops) that is red during each interval."""

    s: float
    red: tuple[tuple[float, float], ...]

    def is_red(self, t: float) -> bool:
        return any(a <= t < b for a, b in self.red)


@dataclass(frozen=True)
class SpeedZone:
    """A stretch [s0, s1] of the lane (a curve) that agents take at no more than ``v_max``; they brake for it in
    advance."""

    s0: float
    s1: float
    v_max: float


@dataclass(frozen=True)
class ScriptedStop:
    """Stop with the front at ``s`` and wait ``dwell_s`` seconds once stationary (bus stop, delivery)."""

    s: float
    dwell_s: float


@dataclass
class LaneAgent:
    """One road user on a lane: centre position ``s0`` (m along the lane), speeds in m/s, IDM parameters."""

    s0: float
    v_desired: float
    length: float
    v0: float | None = None  # initial speed; defaults to v_desired
    a_max: float = 1.4
    b_comfort: float = 2.0
    headway_s: float = 1.3
    min_gap: float = 2.0
    stops: tuple[ScriptedStop, ...] = field(default_factory=tuple)
    start_delay_s: float = 0.0  # stays at rest until this time (a parked car pulling out, a waiting pedestrian)


def simulate_lane(
    agents: Sequence[LaneAgent], stop_lines: Sequence[StopLine], t_grid: F64, speed_zones: Sequence[SpeedZone] = ()
) -> tuple[F64, F64]:
    """Positions ``s`` (K, n) and speeds ``v`` (K, n) of ``agents`` on ``t_grid``; agents sorted leader first."""
    n = len(agents)
    k_steps = len(t_grid)
    s_out = np.zeros((k_steps, n))
    v_out = np.zeros((k_steps, n))
    if n == 0:
        return s_out, v_out
    s = np.array([a.s0 for a in agents], dtype=np.float64)
    if np.any(np.diff(s) > 0):
        raise ValueError("lane agents must be sorted leader first (descending s0)")
    half = np.array([a.length / 2 for a in agents])
    vdes = np.array([max(a.v_desired, 0.1) for a in agents])
    v = np.array([a.v_desired if a.v0 is None else a.v0 for a in agents], dtype=np.float64)
    a_max = np.array([a.a_max for a in agents])
    b = np.array([a.b_comfort for a in agents])
    tau = np.array([a.headway_s for a in agents])
    gap0 = np.array([a.min_gap for a in agents])
    delay = np.array([a.start_delay_s for a in agents])
    v = np.where(delay > t_grid[0], 0.0, v)
    sqrt_ab = 2.0 * np.sqrt(a_max * b)
    max_stops = max((len(a.stops) for a in agents), default=0)
    stop_s = np.full((n, max_stops + 1), np.inf)
    stop_dwell = np.zeros((n, max_stops + 1))
    for i, a in enumerate(agents):
        for j, st in enumerate(a.stops):
            stop_s[i, j] = st.s
            stop_dwell[i, j] = st.dwell_s
    stop_idx = np.zeros(n, dtype=np.int64)
    waited = np.zeros(n)
    lines = list(stop_lines)
    committed = np.zeros((n, len(lines)), dtype=bool)
    was_red = [line.is_red(float(t_grid[0]) - 1e-9) for line in lines]  # a red that began earlier commits no one
    rows = np.arange(n)

    def idm(gap: F64, dv: F64, v0: F64) -> F64:
        s_star = gap0 + np.maximum(0.0, v * tau + v * dv / sqrt_ab)
        return a_max * (1.0 - (v / v0) ** 4 - (s_star / np.maximum(gap, 0.05)) ** 2)

    s_out[0], v_out[0] = s, v
    for k in range(1, k_steps):
        t = t_grid[k - 1]
        dt = t_grid[k] - t
        front = s + half
        # leader following
        gap_lead = np.full(n, np.inf)
        dv_lead = np.zeros(n)
        gap_lead[1:] = (s[:-1] - half[:-1]) - front[1:]
        dv_lead[1:] = v[1:] - v[:-1]
        v0_eff = vdes
        brake_for_curve = np.zeros(n)
        for z in speed_zones:
            inside = (front >= z.s0) & (s - half <= z.s1)
            v0_eff = np.where(inside, np.minimum(v0_eff, z.v_max), v0_eff)
            # before the curve: constant deceleration to v_max at its start, begun once half of b is needed
            dist = z.s0 - front
            need = -(v * v - z.v_max**2) / (2.0 * np.maximum(dist, 0.5))
            brake_for_curve = np.where((dist > 0) & (v > z.v_max) & (need < -0.5 * b),
                                       np.minimum(brake_for_curve, need), brake_for_curve)
        acc = np.where(np.isfinite(gap_lead), idm(gap_lead, dv_lead, v0_eff),
                       a_max * (1.0 - (v / v0_eff) ** 4))
        acc = np.minimum(acc, np.where(brake_for_curve < 0, brake_for_curve, np.inf))
        # virtual obstacles: red lights and scripted stops (an obstacle at the stop point plus min_gap)
        obstacle = np.full(n, np.inf)
        for li, line in enumerate(lines):
            red = line.is_red(t)
            if red and not was_red[li]:
                committed[:, li] = (line.s - front) < v * v / (2.0 * _HARD_DECEL)
            if not red:
                committed[:, li] = False
            was_red[li] = red
            if red:
                ahead = (front < line.s + 0.5) & ~committed[:, li]
                obstacle = np.where(ahead, np.minimum(obstacle, line.s + gap0), obstacle)
        target = stop_s[rows, stop_idx]
        obstacle = np.minimum(obstacle, target + gap0)
        has_obs = np.isfinite(obstacle)
        if has_obs.any():
            acc = np.where(has_obs, np.minimum(acc, idm(obstacle - front, v, v0_eff)), acc)
        # scripted stops release after the dwell once the agent rests at its stop point
        resting = np.isfinite(target) & (v < 0.05) & (target - front < 1.0)
        waited = np.where(resting, waited + dt, 0.0)
        done = resting & (waited >= stop_dwell[rows, stop_idx])
        stop_idx = np.where(done, np.minimum(stop_idx + 1, max_stops), stop_idx)
        waited = np.where(done, 0.0, waited)
        acc = np.clip(acc, -9.0, a_max)
        acc = np.where(t < delay, 0.0, acc)
        v_new = np.maximum(v + acc * dt, 0.0)
        v_new = np.where(resting & ~done, 0.0, v_new)  # hold still while dwelling (no IDM creep)
        s = s + 0.5 * (v + v_new) * dt
        v = v_new
        s_out[k], v_out[k] = s, v
    return s_out, v_out
