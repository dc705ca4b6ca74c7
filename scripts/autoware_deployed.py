"""The z-test against Autoware as deployed: the speed threshold held for its sustain time, and the two together
(docs/results.md, "Against Autoware as deployed").

    .venv/bin/python scripts/autoware_deployed.py --scenario mixed --seeds 2000-2009 [--input detector] [--cache DIR]
    .venv/bin/python scripts/autoware_deployed.py --nuscenes ../shared/data/nuscenes-scene-0523 --input detector
    .venv/bin/python scripts/autoware_deployed.py --nuscenes ../shared/data/nuscenes-scene-0523 --input gt-noise --noise clean
    ... [--preset hold]   (the z-test held before it says dynamic: the classifier's `hold` preset)
    ... [--hold S]        (every class held S seconds: how the preset's hold was chosen)

Autoware's static-obstacle avoidance calls an object moving once its speed has stayed above the class threshold
for ``th_moving_time`` (2 s vehicles, 1 s others). jitterguard's classifier in front of it zeroes the velocity
of the objects it calls static and passes the others through, so Autoware's timer then runs only while the z-test
says dynamic *and* the speed is above the threshold. Four rules over the same rows of one run of the evaluator's
pipeline (``jitterguard eval --runs``, the baseline with ``--speed-sustain``):

* ``threshold``: the speed above the class threshold, at once (metrics.json's ``*_speed`` without ``--speed-sustain``);
* ``sustained``: the same held for the sustain time (metrics.json's ``*_speed`` with ``--speed-sustain``);
* ``z-test``: the classifier's decision (metrics.json's ``*_z``);
* ``z-test → Autoware``: the sustained threshold on the speed the classifier passes on (zero while it says
  static; a dynamic or not yet decided track keeps the tracker's velocity);
* ``… th_moving_time 0``: the same with Autoware's sustain set to 0 — the speed over the class threshold on
  tracks the z-test does not call static.

Per group: static rows called dynamic, moving rows missed, ghost rows called dynamic (metrics.json's scored
rows), and the median time from a track's first row on a moving object to its first dynamic call, with the
share of such tracks never called dynamic. The timers run over the rows a track is observed in, as the
classifier sees them (a frame whose detection the tracker coasts through holds the timer, it does not reset it).
"""

from __future__ import annotations

import argparse

import numpy as np
from numpy.typing import NDArray

from ghost_breakdown import classify_seeds, input_arguments, seed_pairs
from jitterguard.eval.metrics import ghost_rows, scored_rows, time_to_first_correct
from jitterguard.eval.pipeline import Records, concat_records
from jitterguard.schemas.models import ClassifierConfig
from jitterguard.services.classifier.config import PRESETS
from jitterguard.services.classifier.core import DYNAMIC, STATIC


def held(rec: Records, fast: NDArray[np.bool_], sustain_s: NDArray[np.float64]) -> NDArray[np.int8]:
    """Per row, DYNAMIC where ``fast`` has held on every row of its track for at least ``sustain_s`` (the
    track's rows in time order; the timer restarts at the first fast row after a slow one), else STATIC."""
    out = np.full(len(rec), STATIC, dtype=np.int8)
    order = np.lexsort((rec.t_s, rec.track_id))
    since = np.nan
    prev = None
    for i in order.tolist():
        tid = rec.track_id[i]
        if tid != prev:
            since, prev = np.nan, tid
        if fast[i]:
            since = rec.t_s[i] if np.isnan(since) else since
            if rec.t_s[i] - since >= sustain_s[i] - 1e-9:
                out[i] = DYNAMIC
        else:
            since = np.nan
    return out


def _rules(rec: Records, sustain_of_label: NDArray[np.float64]) -> dict[str, NDArray[np.int8]]:
    fast = rec.speed > rec.speed_threshold
    sustain = sustain_of_label[rec.label]
    passed = rec.state_z != STATIC  # the classifier zeroes only the velocity of what it calls static
    return {
        "threshold": np.where(fast, DYNAMIC, STATIC).astype(np.int8),
        "sustained": held(rec, fast, sustain),
        "z-test": rec.state_z,
        "z-test → Autoware": held(rec, fast & passed, sustain),
        "… th_moving_time 0": np.where(fast & passed, DYNAMIC, STATIC).astype(np.int8),
    }


def _rate(state: NDArray[np.int8], mask: NDArray[np.bool_], want: int) -> str:
    return f"{np.mean(state[mask] == want):.3f}" if mask.any() else "—"


def report(rec: Records, sustain_of_label: NDArray[np.float64]) -> None:
    """Print the four rules' rates and latencies per group."""
    rules = _rules(rec, sustain_of_label)
    if not np.array_equal(rules["sustained"], rec.state_v):  # the classifier's own baseline, recomputed
        raise SystemExit(f"the sustained rule differs from the classifier's on "
                         f"{int(np.sum(rules['sustained'] != rec.state_v))} rows")
    for group in ("vehicle", "pedestrian"):
        m = scored_rows(rec, group)
        static, moving, ghost = m & ~rec.gt_dynamic, m & rec.gt_dynamic, ghost_rows(rec, group)
        on_moving = rec.subset((rec.group == group) & rec.gt_dynamic)
        print(f"{group}: static rows {static.sum()}, moving rows {moving.sum()}, ghost rows {ghost.sum()}, "
              f"moving tracks {len(np.unique(on_moving.track_id))}")
        for name, state in rules.items():
            lat = time_to_first_correct(on_moving, state[(rec.group == group) & rec.gt_dynamic])
            done = lat[np.isfinite(lat)]
            med = f"{np.median(done):.2f} s" if done.size else "—"
            never = f"{np.mean(~np.isfinite(lat)):.2f}" if lat.size else "—"
            print(f"  {name:19s} static called dynamic {_rate(state, static, DYNAMIC)} | moving missed "
                  f"{_rate(state, moving, STATIC)} | ghosts called dynamic {_rate(state, ghost, DYNAMIC)} | "
                  f"moving → dynamic median {med}, never {never}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    input_arguments(ap)
    ap.add_argument("--preset", default=None, choices=sorted(PRESETS),
                    help="classifier preset for the z-test, e.g. hold (its decisions held 0.3 s)")
    ap.add_argument("--hold", type=float, default=None,
                    help="hold every class's z-test decision this many seconds (dynamic_hold_s_per_class), after --preset")
    ap.add_argument("--window", type=int, default=None, help="window_size, after --preset")
    args = ap.parse_args()
    classes = PRESETS["hold"]["dynamic_hold_s_per_class"]  # every class the preset names
    hold = {} if args.hold is None else {"dynamic_hold_s_per_class": {c: args.hold for c in classes}}
    clf = ClassifierConfig.model_validate({**ClassifierConfig().model_dump(), **PRESETS["autoware-sustain"],
                                           **(PRESETS[args.preset] if args.preset else {}), **hold,
                                           **({} if args.window is None else {"window_size": args.window}),
                                           **({"jump_veto": False} if args.no_jump_veto else {})})
    pairs = seed_pairs(args)
    rec = concat_records(classify_seeds(pairs, clf), [str(s) for s in pairs])
    sustain = np.array([clf.sustain_for(label) for label in range(int(rec.label.max(initial=0)) + 1)])
    report(rec, sustain)


if __name__ == "__main__":
    main()
