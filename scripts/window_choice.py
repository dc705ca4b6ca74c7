"""How long a window the z-test should slide: issue 15's figures for several `window_size`s on the same tracks
(docs/results.md, "The window of 20"; docs/classifier.md, "The window").

    .venv/bin/python scripts/window_choice.py --seeds 0-3 [--windows 10,15,20,30] [--cache out/window-cache]

For each of the four runs — `mixed` and `diagonal-lot`, the shipped detector and the noise model — the seeds are
pooled as one drive (the online calibration carries over, as `jitterguard eval --runs`), and every window is
scored with metrics.json's own functions on the same detections: vehicle and pedestrian false- and
missed-dynamic rates of the z-test (the threshold's beside them), ghost rows called dynamic, recently stopped
vehicles called dynamic and the median time to call a moving object moving. For choosing on tuning seeds (0–3)
and checking on validation seeds (3000–3009) only; seeds 2000–2009 are for reporting (`jitterguard eval
--window-size`). Prints a table; no files but the optional detection cache.
"""

from __future__ import annotations

import argparse
from typing import Any

from ghost_breakdown import _seeds, detection_pairs
from jitterguard.eval.metrics import compute_metrics, planner_metrics
from jitterguard.eval.pipeline import concat_records, track_and_classify
from jitterguard.schemas.models import ClassifierConfig
from jitterguard.services.classifier.core import MotionClassifierCore

RUNS = (("mixed", "detector"), ("diagonal-lot", "detector"), ("mixed", "gt-noise"), ("diagonal-lot", "gt-noise"))


def _figures(pairs: dict[int, list[tuple[Any, bytes]]], window: int) -> dict[str, Any]:
    """metrics.json's motion, ghost and by-attribute blocks for one window over the pooled seeds."""
    cfg = ClassifierConfig(window_size=window)
    drive = MotionClassifierCore.make_online(cfg)
    rec = concat_records([track_and_classify(p, cfg, calibration=drive) for p in pairs.values()],
                         [str(s) for s in pairs])
    return {**compute_metrics(rec, intervals=False), **planner_metrics(rec, intervals=False)}


def _cell(z: float | None, speed: float | None = None) -> str:
    fmt = lambda x: "  —  " if x is None else f"{x:.3f}"  # noqa: E731
    return fmt(z) if speed is None else f"{fmt(z)} ({fmt(speed)})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-3")
    ap.add_argument("--windows", default="10,15,20,30")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--cache", default=None, help="folder for the per-seed detector payloads")
    args = ap.parse_args()
    windows = [int(w) for w in args.windows.split(",")]
    print("run | window | V false dyn z (thr) | V missed z (thr) | ghost V z | V stopped called dyn | "
          "P false dyn z | P missed z (thr) | ghost P z | s to call a moving vehicle moving")
    for scenario, source in RUNS:
        opts = argparse.Namespace(scenario=scenario, nuscenes=None, input=source, noise="jittery",
                                  threads=args.threads, cache=args.cache)
        pairs = {s: detection_pairs(opts, s) for s in _seeds(args.seeds)}
        for w in windows:
            m = _figures(pairs, w)
            v, p = m["vehicle"], m["pedestrian"]
            stopped = m["by_attribute"].get("vehicle.stopped", {})
            print(f"{scenario} {source} | {w} | {_cell(v['false_dynamic_z'], v['false_dynamic_speed'])} | "
                  f"{_cell(v['missed_dynamic_z'], v['missed_dynamic_speed'])} | "
                  f"{_cell(m['ghost']['vehicle']['false_dynamic_z'])} | {_cell(stopped.get('false_dynamic_z'))} | "
                  f"{_cell(p['false_dynamic_z'])} | {_cell(p['missed_dynamic_z'], p['missed_dynamic_speed'])} | "
                  f"{_cell(m['ghost']['pedestrian']['false_dynamic_z'])} | "
                  f"{_cell(v.get('time_to_dynamic_s_median_z'))}", flush=True)


if __name__ == "__main__":
    main()
