"""The jump veto measured (docs/classifier.md 'The jump veto'): the evaluator's tracker and classifier over each
seed's cached detections, with and without ``jump_veto``, one online calibration per variant; vehicle and
pedestrian false / missed / ghost rates (all scored rows, as ``jitterguard eval`` reports them; rows in brackets).

    .venv/bin/python scripts/jump_veto.py --scenario mixed --seeds 0-3 --input detector --cache DIR
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ghost_breakdown import _seeds, classify_seeds, detection_pairs, input_arguments  # noqa: E402
from jitterguard.eval.metrics import ghost_rows, scored_rows  # noqa: E402
from jitterguard.eval.pipeline import concat_records  # noqa: E402
from jitterguard.schemas.models import ClassifierConfig  # noqa: E402
from jitterguard.services.classifier.core import DYNAMIC  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    input_arguments(ap)
    args = ap.parse_args()
    pairs = {s: detection_pairs(args, s) for s in _seeds(args.seeds)}
    for veto in (False, True):
        rec = concat_records(classify_seeds(pairs, ClassifierConfig(jump_veto=veto)), [str(s) for s in pairs])
        out = [f"jump_veto {str(veto):5s}"]
        for group in ("vehicle", "pedestrian"):
            m = scored_rows(rec, group)
            static, moving, ghost = m & ~rec.gt_dynamic, m & rec.gt_dynamic, ghost_rows(rec, group)

            def rate(mask: np.ndarray, dynamic: bool) -> str:
                if not mask.any():
                    return "-"
                hit = (rec.state_z[mask] == DYNAMIC) == dynamic
                return f"{hit.mean():.4f} ({int(hit.sum())}/{int(mask.sum())})"

            out.append(f"{group[0].upper()} false {rate(static, True)} missed {rate(moving, False)} "
                       f"ghost {rate(ghost, True)}")
        print(" | ".join(out), flush=True)


if __name__ == "__main__":
    main()
