"""The jump veto measured (docs/classifier.md 'The jump veto'): the evaluator's tracker and classifier over each
seed's cached detections, with and without ``jump_veto``, one online calibration per variant; vehicle and
pedestrian false / missed / ghost rates (all scored rows, as ``jitterguard eval`` reports them; rows in brackets).

    .venv/bin/python scripts/jump_veto.py --scenario mixed --seeds 0-3 --input detector --cache DIR
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ghost_breakdown import classify_seeds, input_arguments, rates_line, seed_pairs  # noqa: E402
from jitterguard.eval.pipeline import concat_records  # noqa: E402
from jitterguard.schemas.models import ClassifierConfig  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    input_arguments(ap)
    args = ap.parse_args()
    pairs = seed_pairs(args)
    for veto in (False, True):
        rec = concat_records(classify_seeds(pairs, ClassifierConfig(jump_veto=veto)), [str(s) for s in pairs])
        print(f"jump_veto {str(veto):5s} | {rates_line(rec)}", flush=True)


if __name__ == "__main__":
    main()
