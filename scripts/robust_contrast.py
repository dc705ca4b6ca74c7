"""Experiment (docs/results.md, "What the detector's static false alarms are made of"; tuning seeds only): clip
each observation's residual about its window's constant-velocity fit at c calibrated σ along and across the line of
sight before the half-mean contrast, so that one wild box cannot move a half-mean; print vehicle and pedestrian
false / missed / ghost rates per c on the same tracks (the tracker does not depend on the classifier).

    .venv/bin/python scripts/robust_contrast.py --scenario mixed --seeds 0-3 --input detector --clips none,3,2,1.5

The clip is spliced into a copy of ``statistics._calibrated_statistics``'s source (before the contrast), so this
script follows that function's local names; it is a record of an experiment that was not kept, not a feature."""
from __future__ import annotations

import argparse
import inspect
import sys
import textwrap
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ghost_breakdown import _seeds, detection_pairs, input_arguments  # noqa: E402
from jitterguard.eval.metrics import ghost_rows, scored_rows  # noqa: E402
from jitterguard.eval.pipeline import concat_records, track_and_classify  # noqa: E402
from jitterguard.schemas.models import ClassifierConfig  # noqa: E402
from jitterguard.services.classifier import statistics  # noqa: E402
from jitterguard.services.classifier.core import DYNAMIC, MotionClassifierCore  # noqa: E402
from jitterguard.services.tracker.config import default_config  # noqa: E402

CLIP: dict[str, float | None] = {"c": None}
"""The clip in calibrated σ; None: the statistic as shipped."""

_CONTRAST = "    dx = (w * pos_x).sum(1)\n    dy = (w * pos_y).sum(1)\n"
_CLIPPED_CONTRAST = '''    _c = CLIP["c"]
    if _c is None:
        qx, qy = pos_x, pos_y
    else:  # residuals about the window's least-squares line, clipped at _c σ along and across the line of sight
        _vm = valid.astype(np.float64)
        _n = _vm.sum(1)
        _tc, _stt, _b1, _b2 = _line_basis(t, _vm, _n)
        _ex = _vm * pos_x - _b1 * _dot(_b1, pos_x)[:, None] - _b2 * _dot(_b2, pos_x)[:, None]
        _ey = _vm * pos_y - _b1 * _dot(_b1, pos_y)[:, None] - _b2 * _dot(_b2, pos_y)[:, None]
        _su, _sv = np.sqrt(np.maximum(auu, variance_floor)), np.sqrt(np.maximum(avv, variance_floor))
        _ru, _rv = (_ex * ux + _ey * uy) / _su, (_ex * vx + _ey * vy) / _sv
        _ok = (_n >= 4)[:, None] & valid  # three points or fewer: the line passes (nearly) through them
        _du = np.where(_ok, np.clip(_ru, -_c, _c) - _ru, 0.0) * _su
        _dv = np.where(_ok, np.clip(_rv, -_c, _c) - _rv, 0.0) * _sv
        qx, qy = pos_x + _du * ux + _dv * vx, pos_y + _du * uy + _dv * vy
    dx = (w * qx).sum(1)
    dy = (w * qy).sum(1)
'''


def _install_clip() -> None:
    """Replace the statistic with a copy whose half-mean contrast reads the clipped positions (the track's own
    scale, the means and everything else still read the positions as they are)."""
    src = textwrap.dedent(inspect.getsource(statistics._calibrated_statistics))
    if _CONTRAST not in src:
        raise SystemExit("statistics._calibrated_statistics changed: this experiment no longer applies")
    statistics.__dict__["CLIP"] = CLIP
    exec(compile(src.replace(_CONTRAST, _CLIPPED_CONTRAST), "robust_contrast", "exec"), statistics.__dict__)  # noqa: S102


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    input_arguments(ap)
    ap.add_argument("--clips", default="none,3,2,1.5")
    args = ap.parse_args()
    _install_clip()
    pairs = {s: detection_pairs(args, s) for s in _seeds(args.seeds)}
    for text in args.clips.split(","):
        CLIP["c"] = None if text == "none" else float(text)
        clf = ClassifierConfig()
        drive = MotionClassifierCore.make_online(clf)
        rec = concat_records([track_and_classify(iter(pairs[s]), clf, default_config(), calibration=drive)
                              for s in pairs], [str(s) for s in pairs])
        out = [f"clip {text:>4}"]
        for group in ("vehicle", "pedestrian"):
            m = scored_rows(rec, group)
            static, moving, ghost = m & ~rec.gt_dynamic, m & rec.gt_dynamic, ghost_rows(rec, group)

            def rate(mask: np.ndarray, state: np.ndarray, dynamic: bool) -> str:
                return f"{np.mean((state[mask] == DYNAMIC) == dynamic):.4f}" if mask.any() else "-"

            out.append(f"{group[0].upper()} false {rate(static, rec.state_z, True)} missed "
                       f"{rate(moving, rec.state_z, False)} ghost {rate(ghost, rec.state_z, True)} (threshold false "
                       f"{rate(static, rec.state_v, True)} missed {rate(moving, rec.state_v, False)})")
        print(" | ".join(out), flush=True)


if __name__ == "__main__":
    main()
