"""Experiment (docs/results.md, "Why the z-test misses young windows and walkers"; tuning and validation seeds
only): what if a window too young for the z-test to see a walker deferred to Autoware's speed threshold?

    .venv/bin/python scripts/young_speed_rule.py --scenario mixed --seeds 0-3 --input detector --cache DIR
    .venv/bin/python scripts/young_speed_rule.py --scenario diagonal-lot --seeds 3000-3009 --input gt-noise --cache DIR

Runs the evaluator's tracker and classifier over each seed's detections (cached with ``--cache``, as
``scripts/ghost_breakdown.py`` does) and scores, per group, the rows of static, moving and ghost objects called
dynamic by the z-test, by the speed threshold, and by the z-test on windows of at least n observations with the
threshold's decision below n (``--below``, default 4,7,10). Prints a table; no files. Not a classifier option:
docs/results.md says why it was not adopted."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ghost_breakdown import classifier_config, classify_seeds, input_arguments, seed_pairs  # noqa: E402
from jitterguard.eval.metrics import ghost_rows, scored_rows  # noqa: E402
from jitterguard.eval.pipeline import concat_records  # noqa: E402
from jitterguard.services.classifier.core import DYNAMIC  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    input_arguments(ap)
    ap.add_argument("--below", default="4,7,10", help="window lengths below which the threshold decides")
    args = ap.parse_args()
    pairs = seed_pairs(args)
    rec = concat_records(classify_seeds(pairs, classifier_config(args)), [str(s) for s in pairs])
    z_dyn, v_dyn = rec.state_z == DYNAMIC, rec.state_v == DYNAMIC
    rules = [("z-test", z_dyn), ("threshold", v_dyn)]
    rules += [(f"z, threshold below {n}", np.where(rec.window < n, v_dyn, z_dyn)) for n in map(int, args.below.split(","))]
    for group in ("vehicle", "pedestrian"):
        m = scored_rows(rec, group)
        static, moving, ghost = m & ~rec.gt_dynamic, m & rec.gt_dynamic, ghost_rows(rec, group)
        print(f"{group}: rows static {static.sum()}, moving {moving.sum()}, ghost {ghost.sum()}")
        for name, dyn in rules:
            def rate(mask: np.ndarray, dynamic: bool) -> str:
                return f"{np.mean(dyn[mask] == dynamic):.3f}" if mask.any() else "  -  "
            print(f"  {name:26s} static called dynamic {rate(static, True)}  moving missed {rate(moving, False)}  "
                  f"ghost called dynamic {rate(ghost, True)}")


if __name__ == "__main__":
    main()
