"""Where the z-test misses: false- and missed-dynamic rates of both rules split by window length and by the
true speed, on the synthetic tuning seeds (docs/results.md, "Where the z-test still loses").

    .venv/bin/python scripts/by_window.py [--scenario mixed] [--seeds 0-3] [--config '{"effective_n": "cluster"}']

Runs the evaluator's pipeline (the live tracker and classifier cores, the honest noise model) over the seeds as
one drive, exactly like ``jitterguard eval --runs``; for diagnosis on tuning seeds only (never the test seeds
2000–2009). Prints a table; no files.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from jitterguard.eval.pipeline import NOISE_PRESETS, concat_records, run_pipeline
from jitterguard.schemas.models import ClassifierConfig
from jitterguard.services.classifier.core import DYNAMIC, MotionClassifierCore
from jitterguard.sim.world import make_scenario

WINDOW_BINS = ((2, 4), (4, 7), (7, 10), (10, 65))
SPEED_BINS = ((0.0, 0.5), (0.5, 1.0), (1.0, 2.0), (2.0, 99.0))


def _seeds(text: str) -> list[int]:
    lo, _, hi = text.partition("-")
    return list(range(int(lo), int(hi or lo) + 1))


def _rate(flags: np.ndarray) -> str:
    return f"{flags.mean():.3f}" if flags.size else "  —  "


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="mixed")
    ap.add_argument("--seeds", default="0-3")
    ap.add_argument("--noise", default="jittery")
    ap.add_argument("--config", default="{}", help="ClassifierConfig fields as JSON")
    args = ap.parse_args()
    cfg = ClassifierConfig(**json.loads(args.config))
    drive = MotionClassifierCore.make_online(cfg)
    seeds = _seeds(args.seeds)
    parts = [run_pipeline(make_scenario(args.scenario, s, 15.0, 10.0), NOISE_PRESETS[args.noise](), s, cfg,
                          calibration=drive) for s in seeds]
    r = concat_records(parts, [str(s) for s in seeds])
    scored = (r.gt_instance >= 0) & (r.window >= 2)
    for g in ("vehicle", "pedestrian"):
        m = scored & (r.group == g)
        dyn, st = m & r.gt_dynamic, m & ~r.gt_dynamic
        print(f"{g}: false dyn z {_rate(r.state_z[st] == DYNAMIC)} speed {_rate(r.state_v[st] == DYNAMIC)} | "
              f"missed dyn z {_rate(r.state_z[dyn] != DYNAMIC)} speed {_rate(r.state_v[dyn] != DYNAMIC)}")
        for lo, hi in WINDOW_BINS:
            d, s_ = dyn & (r.window >= lo) & (r.window < hi), st & (r.window >= lo) & (r.window < hi)
            print(f"   window {lo}-{min(hi - 1, cfg.window_size)}: moving n {d.sum()} missed z "
                  f"{_rate(r.state_z[d] != DYNAMIC)} speed {_rate(r.state_v[d] != DYNAMIC)} | static n {s_.sum()} "
                  f"false z {_rate(r.state_z[s_] == DYNAMIC)} speed {_rate(r.state_v[s_] == DYNAMIC)}")
        for lo, hi in SPEED_BINS:
            d = dyn & (r.gt_speed >= lo) & (r.gt_speed < hi)
            if d.any():
                print(f"   true speed {lo:.1f}-{hi:.1f} m/s: n {d.sum()} missed z {_rate(r.state_z[d] != DYNAMIC)} "
                      f"speed {_rate(r.state_v[d] != DYNAMIC)}")


if __name__ == "__main__":
    main()
