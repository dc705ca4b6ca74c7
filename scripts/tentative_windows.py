"""What the tracker's ``observe_tentative`` buys and costs: the classifier's windows starting with a track's first
detection instead of its confirmation (docs/tracker.md, "Tentative observations").

    .venv/bin/python scripts/tentative_windows.py --scenario mixed --seeds 0-3 [--input detector] [--cache DIR]
    .venv/bin/python scripts/tentative_windows.py --nuscenes ../shared/data/nuscenes-scene-0523 --input detector

Runs the evaluator's pipeline (the live tracker and classifier cores; ``--input detector``: the detector service's
steps on ray-cast scans, payloads shared with ``scripts/ghost_breakdown.py``'s ``--cache``) over the seeds as one
drive, once with ``observe_tentative`` off (the default) and once on, on identical detections. Prints

* **same rows**: the rows the default scores (track and frame; window ≥ 2 without the tentative detections)
  decided by each — track IDs are deterministic, so both runs hold the same tracks — the z-test's false-dynamic
  rate on static objects, its missed-dynamic rate on moving ones and on ghost rows, with the speed threshold's
  (identical in both: the tracker is unchanged);
* **as scored**: metrics.json's own figures, which also score the rows a longer window makes decidable earlier,
  with ``min_window`` 2 (the default) and 4 (the first decision one frame after confirmation, as without it).

For diagnosis and tuning on tuning seeds; the real scene's figures are reported for an option whose default
was decided before they were measured.
"""

from __future__ import annotations

import argparse

import numpy as np

from ghost_breakdown import classifier_config, classify_seeds, input_arguments, seed_pairs
from jitterguard.eval.metrics import compute_metrics, planner_metrics
from jitterguard.eval.pipeline import Records, concat_records
from jitterguard.services.classifier.core import DYNAMIC
from jitterguard.services.tracker.config import default_config


def _run(args: argparse.Namespace, pairs: dict[int, list], on: bool, min_window: int) -> Records:
    trk = default_config().model_copy(update={"observe_tentative": on})
    return concat_records(classify_seeds(pairs, classifier_config(args, min_window=min_window), trk),
                          [str(s) for s in pairs])


def _rate(flags: np.ndarray) -> str:
    return f"{flags.mean():.3f}" if flags.size else "  —  "


def _same_rows(off: Records, on: Records) -> None:
    key = lambda r: np.char.add(np.char.add(r.track_id, "@"), r.seq.astype(str))  # noqa: E731
    k_off, k_on = key(off), key(on)
    o_sort, n_sort = np.argsort(k_off), np.argsort(k_on)

    def pair(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        common = np.intersect1d(k_off[mask], k_on)
        return (o_sort[np.searchsorted(k_off[o_sort], common)], n_sort[np.searchsorted(k_on[n_sort], common)])

    scored = off.window >= off.min_window
    print("same rows (the default's scored rows): z-test off → on, speed threshold")
    for g in ("vehicle", "pedestrian"):
        oo, nn = pair(scored & (off.gt_instance >= 0) & (off.group == g))
        dyn = off.gt_dynamic[oo]
        st = ~dyn
        print(f"  {g}: static n {st.sum()} false dyn {_rate(off.state_z[oo][st] == DYNAMIC)} → "
              f"{_rate(on.state_z[nn][st] == DYNAMIC)} (speed {_rate(off.state_v[oo][st] == DYNAMIC)}) | moving n "
              f"{dyn.sum()} missed {_rate(off.state_z[oo][dyn] != DYNAMIC)} → {_rate(on.state_z[nn][dyn] != DYNAMIC)}"
              f" (speed {_rate(off.state_v[oo][dyn] != DYNAMIC)})")
        oo, nn = pair(scored & (off.gt_instance < 0) & (off.track_group == g))
        print(f"  {g} ghosts: n {oo.size} called dynamic {_rate(off.state_z[oo] == DYNAMIC)} → "
              f"{_rate(on.state_z[nn] == DYNAMIC)} (speed {_rate(off.state_v[oo] == DYNAMIC)})")


def _fmt(v: float | None) -> str:
    return "—" if v is None else f"{v:.3f}"


def _as_scored(label: str, rec: Records) -> None:
    motion, ghost = compute_metrics(rec, intervals=False), planner_metrics(rec, intervals=False)["ghost"]
    out = []
    for g in ("vehicle", "pedestrian"):
        m, gh = motion[g], ghost[g]
        gap = (None if m["missed_dynamic_z"] is None or m["missed_dynamic_speed"] is None
               else 100 * (m["missed_dynamic_z"] - m["missed_dynamic_speed"]))
        out.append(f"{g[0].upper()} false {_fmt(m['false_dynamic_z'])}/{_fmt(m['false_dynamic_speed'])} missed "
                   f"{_fmt(m['missed_dynamic_z'])}/{_fmt(m['missed_dynamic_speed'])} "
                   f"({'—' if gap is None else f'{gap:+.1f}'} points) ghosts {_fmt(gh['false_dynamic_z'])}/"
                   f"{_fmt(gh['false_dynamic_speed'])} ({gh['n']} rows)")
    print(f"  {label}: " + " | ".join(out))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    input_arguments(ap, default_input="gt-noise")
    args = ap.parse_args()
    pairs = seed_pairs(args)
    off = _run(args, pairs, False, 2)
    _same_rows(off, _run(args, pairs, True, 2))
    print("as scored (metrics.json; z-test / speed threshold):")
    _as_scored("off, min_window 2", off)
    _as_scored("on,  min_window 2", _run(args, pairs, True, 2))
    _as_scored("on,  min_window 4", _run(args, pairs, True, 4))


if __name__ == "__main__":
    main()
