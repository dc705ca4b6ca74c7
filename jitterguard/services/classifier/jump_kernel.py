"""The jump veto's shape test as one compiled loop per window (numba): :func:`~.statistics.jump_ratio`'s arithmetic.

Why compiled: the veto looks at the windows the test rejects, and on a street most of those are movers — half of
1000 tracks in the classifier benchmark. As numpy expressions over (windows × slots) the line, the step's prefix
sums and the hinges' (windows × knots × slots) arrays cost 2–10 ms per frame there, more than the calibrated
statistic itself; one loop per window does the same arithmetic on a few scalars and three scratch rows (the hinges
only where the step beats the line, which a mover's ramp never lets it). The tests
(``tests/classifier/test_classifier_jump_veto.py``) hold it to a brute-force loop of least-squares fits. Compiled
and cached as :mod:`~.window_kernel`'s loop is.
"""

from __future__ import annotations

import math

import numpy as np

from .window_kernel import _compiled


@_compiled()
def _hinge_sse(xs, ys, ts, n, spp):  # noqa: ANN001, ANN202
    """The residual sum of squares about the best one-sided hinge of centred positions ``xs``, ``ys`` at centred
    stamps ``ts`` (first ``n`` slots): ``a + v·max(0, t − t_j)`` (a stand, then motion) or
    ``a + v·min(0, t − t_j)`` (motion, then a stand), each axis its own ``a`` and ``v``, the knot at one
    observation's stamp, two observations or more a side; inf where no knot qualifies."""
    best = math.inf
    for j in range(n):
        tj = ts[j]
        for kind in range(2):
            sh = shh = shx = shy = 0.0
            still = 0
            for i in range(n):
                lag = ts[i] - tj
                if kind == 0:
                    h = lag if lag > 0.0 else 0.0
                    if lag <= 0.0:
                        still += 1
                else:
                    h = lag if lag < 0.0 else 0.0
                    if lag >= 0.0:
                        still += 1
                sh += h
                shh += h * h
                shx += h * xs[i]
                shy += h * ys[i]
            shh -= sh * sh / n  # about the mean of h; the positions are centred, so Σ h·p needs no correction
            if still < 2 or n - still < 2 or not shh > 1e-12:
                continue
            sse = spp - (shx * shx + shy * shy) / shh
            best = min(best, max(sse, 0.0))
    return best


@_compiled()
def jump_ratios(win, count, min_count, out):  # noqa: ANN001, ANN201
    """``out[k]``: the residual sum of squares of window ``k``'s positions (channels 0, 1; stamps in channel 5; its
    ``count[k]`` newest observations in its last slots) about the best single step over that about the best
    motion (the constant-velocity line, or a one-sided hinge where the step beats the line); inf for fewer than
    ``min_count`` observations, non-finite input, one instant for every stamp or a line that fits exactly."""
    k_rows, w = win.shape[0], win.shape[1]
    xs = np.empty(w)
    ys = np.empty(w)
    ts = np.empty(w)
    for k in range(k_rows):
        out[k] = math.inf
        n = count[k]
        if n < min_count:
            continue
        off = w - n
        mx = my = mt = 0.0
        finite = True
        for i in range(n):
            x, y, t = win[k, off + i, 0], win[k, off + i, 1], win[k, off + i, 5]
            if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(t)):
                finite = False
            mx += x
            my += y
            mt += t
        if not finite:
            continue
        mx /= n
        my /= n
        mt /= n
        stt = stx = sty = spp = 0.0
        for i in range(n):  # centred: epoch stamps and UTM positions keep their precision
            xs[i] = win[k, off + i, 0] - mx
            ys[i] = win[k, off + i, 1] - my
            ts[i] = win[k, off + i, 5] - mt
            stt += ts[i] * ts[i]
            stx += ts[i] * xs[i]
            sty += ts[i] * ys[i]
            spp += xs[i] * xs[i] + ys[i] * ys[i]
        if not stt > 0.0:
            continue
        vx, vy = stx / stt, sty / stt
        line = 0.0
        for i in range(n):
            rx, ry = xs[i] - ts[i] * vx, ys[i] - ts[i] * vy
            line += rx * rx + ry * ry
        if not line > 1e-12:
            continue
        step = math.inf
        lx = ly = lsq = 0.0
        for s in range(1, n - 1):  # left: the first s observations (their sums so far), right: the rest
            lx += xs[s - 1]
            ly += ys[s - 1]
            lsq += xs[s - 1] * xs[s - 1] + ys[s - 1] * ys[s - 1]
            if s < 2 or n - s < 2:
                continue
            left = lsq - (lx * lx + ly * ly) / s
            right = (spp - lsq) - (lx * lx + ly * ly) / (n - s)  # the right sums are −left's (centred positions)
            step = min(step, left + right)
        motion = line
        if step < line:
            motion = min(line, _hinge_sse(xs, ys, ts, n, spp))
        out[k] = step / motion if motion > 0.0 else math.inf
