"""Is the detector's own velocity (its twist) evidence of motion where the z-test has little — young windows?

    .venv/bin/python scripts/detector_twist.py --scenario mixed --seeds 0-3 [--input detector] [--cache DIR]

Runs the evaluator's pipeline (the live tracker and classifier cores; ``--input detector``: the detector service's
steps on ray-cast scans, payloads shared with ``scripts/ghost_breakdown.py``'s ``--cache``) and reads back, for every
scored row, the twists and twist variances of the detections in that row's window (from the ``tracks/{id}``
payloads the classifier receives). Prints per group, state and window length the median |mean twist| and its
reported σ, the z-test's and the speed threshold's calls, and the rows missed at the z-test's false-dynamic rate by
a threshold on |mean twist| and on the tracker's speed (docs/results.md, "Why the z-test misses young windows").
For diagnosis on tuning seeds only.
"""

from __future__ import annotations

import argparse

import numpy as np

import jitterguard.eval.pipeline as pipeline
from ghost_breakdown import classifier_config, input_arguments, seed_pairs
from jitterguard.eval.metrics import ghost_rows, scored_rows
from jitterguard.schemas import TrackObservation, decode
from jitterguard.services.classifier.core import DYNAMIC, MotionClassifierCore
from jitterguard.services.tracker.config import default_config

BANDS = ((2, 2), (3, 3), (4, 5), (6, 9), (10, 99))


def _rows(args: argparse.Namespace) -> list[tuple]:
    """(group, kind, window, |mean twist|, median reported σ of the twist, z-test dynamic, threshold dynamic,
    tracker speed) of every scored and ghost row."""
    clf = classifier_config(args)
    drive = MotionClassifierCore.make_online(clf)
    original = pipeline.observation_payloads
    out: list[tuple] = []
    for pairs in seed_pairs(args).values():
        log: dict[str, list[tuple[int, float, float, float]]] = {}

        def logged(*a, **k):  # noqa: ANN002, ANN003 - the pipeline's own call, passed through
            payloads = original(*a, **k)
            for tid, p in payloads:
                o = decode(TrackObservation, p)
                tw = o.detection.kinematics.twist_with_covariance
                log.setdefault(str(tid), []).append((o.header.seq, tw.twist.linear.x, tw.twist.linear.y,
                                                     tw.covariance[0]))
            return payloads

        pipeline.observation_payloads = logged
        try:
            rec = pipeline.track_and_classify(iter(pairs), clf, default_config(), calibration=drive)
        finally:
            pipeline.observation_payloads = original
        hist = {t: np.array(v) for t, v in log.items()}
        for g in ("vehicle", "pedestrian"):
            scored = scored_rows(rec, g)
            for kind, mask in (("static", scored & ~rec.gt_dynamic), ("moving", scored & rec.gt_dynamic),
                               ("ghost", ghost_rows(rec, g))):
                for i in np.flatnonzero(mask):
                    h = hist[str(rec.track_id[i])]
                    k = int(np.searchsorted(h[:, 0], rec.seq[i], side="right"))
                    win = h[max(0, k - int(rec.window[i])):k]
                    out.append((g, kind, int(rec.window[i]), float(np.hypot(win[:, 1].mean(), win[:, 2].mean())),
                                float(np.sqrt(np.median(win[:, 3]))), rec.state_z[i] == DYNAMIC,
                                rec.state_v[i] == DYNAMIC, float(rec.speed[i])))
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    input_arguments(ap)
    rows = _rows(ap.parse_args())
    g = np.array([r[0] for r in rows])
    kind = np.array([r[1] for r in rows])
    w, twist, sigma, z_dyn, v_dyn, speed = (np.array([r[j] for r in rows], dtype=float) for j in range(2, 8))
    for group in ("vehicle", "pedestrian"):
        print(f"== {group}")
        for lo, hi in BANDS:
            for k in ("static", "moving", "ghost"):
                m = (g == group) & (kind == k) & (w >= lo) & (w <= hi)
                if m.any():
                    print(f"  window {lo}-{hi} {k:7s} n {m.sum():5d}  z-test dynamic {z_dyn[m].mean():.3f}  threshold "
                          f"{v_dyn[m].mean():.3f}  |mean twist| median {np.median(twist[m]):.2f} m/s  twist σ median "
                          f"{np.median(sigma[m]):.2f} m/s  tracker speed median {np.median(speed[m]):.2f} m/s")
        for lo, hi in ((2, 3), (4, 9), (10, 99), (2, 99)):
            st = (g == group) & (kind == "static") & (w >= lo) & (w <= hi)
            mv = (g == group) & (kind == "moving") & (w >= lo) & (w <= hi)
            if not st.any() or not mv.any():
                continue
            false = z_dyn[st].mean()
            line = f"  windows {lo}-{hi}: z-test false {false:.3f} missed {1 - z_dyn[mv].mean():.3f}"
            for name, stat in (("|mean twist|", twist), ("tracker speed", speed)):
                cut = np.quantile(stat[st], 1 - max(false, 1e-9))
                line += f" | {name} at that false rate: missed {(stat[mv] <= cut).mean():.3f}"
            print(line)


if __name__ == "__main__":
    main()
