"""How many confirmed tracks an object gets, why a second one is born, and what the re-births cost the z-test
(docs/tracker.md, "Tracks per object").

    .venv/bin/python scripts/track_breakdown.py --scenario mixed --seeds 0-3 [--input gt-noise|detector]
    ... [--tracker-config FILE] [--cache DIR]

Runs the evaluator's pipeline (the live tracker and classifier cores, as ``jitterguard eval --runs``) and gives each
confirmed track the object it was matched to most often. An object's tracks in order of birth are then a first
track and re-births, each re-birth put in a bin by the frames between the previous track's last observed row and
the new track's first: ``overlap`` (the new track was confirmed while the old one was still observed — a
detection the old track's gate refused), ``1-5`` (a re-detection within half a second, while the old track still
coasted: refused by its gate too), ``6-10`` and ``>10`` (the object unseen longer than the tracker coasts,
``max_coast_s`` 1 s), with the object's mean ground-truth visibility over the gap. Last, the walkers' and moving
vehicles' rows the z-test misses, split by young (< 10 observations) and full windows and by the track's origin.
For diagnosis on tuning seeds; prints tables, writes nothing.
"""

from __future__ import annotations

import argparse
import collections
from typing import Any

import numpy as np

from ghost_breakdown import classify_seeds, classifier_config, input_arguments, seed_pairs
from jitterguard.eval.pipeline import Records
from jitterguard.services.classifier.core import DYNAMIC
from jitterguard.services.tracker.config import load_config

YOUNG = 10
GAP_BINS = (("overlap", -10**9, 0), ("1-5", 1, 5), ("6-10", 6, 10), (">10", 11, 10**9))


def origins(rec: Records) -> tuple[dict[str, str], dict[int, list[tuple[int, int]]]]:
    """Each matched track's origin (``first`` or its gap bin) and, per object, its tracks' (first, last) seq."""
    spans: dict[int, list[tuple[int, int, str]]] = collections.defaultdict(list)
    for t in np.unique(rec.track_id):
        m = rec.track_id == t
        ids, counts = np.unique(rec.gt_instance[m], return_counts=True)
        g = int(ids[np.argmax(counts)])
        if g >= 0:
            spans[g].append((int(rec.seq[m].min()), int(rec.seq[m].max()), str(t)))
    kind: dict[str, str] = {}
    for sp in spans.values():
        sp.sort()
        kind[sp[0][2]] = "first"
        for a, b in zip(sp, sp[1:]):
            gap = b[0] - a[1] - 1
            kind[b[2]] = next(name for name, lo, hi in GAP_BINS if lo <= gap <= hi)
    return kind, {g: [(a, b) for a, b, _ in sp] for g, sp in spans.items()}


def visibility_in(pairs: list[tuple[Any, bytes]]) -> dict[int, dict[int, float]]:
    """Object → seq → its ground-truth visibility (0 where the object is not in the frame)."""
    vis: dict[int, dict[int, float]] = collections.defaultdict(dict)
    for gt, _ in pairs:
        for i, v in zip(gt.instance_ids.tolist(), gt.visibility.tolist()):
            vis[int(i)][int(gt.seq)] = float(v)
    return vis


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    input_arguments(ap, default_input="gt-noise")
    ap.add_argument("--tracker-config", default=None, help="tracker YAML (as `jitterguard tracker --config`)")
    args = ap.parse_args()
    pairs = seed_pairs(args)
    runs = classify_seeds(pairs, classifier_config(args), load_config(args.tracker_config))
    n_tracks = n_ghost = n_objects = 0
    gaps: dict[str, list[float]] = collections.defaultdict(list)
    rows: collections.Counter[tuple[str, str, str]] = collections.Counter()
    missed: collections.Counter[tuple[str, str, str]] = collections.Counter()
    for rec, seed in zip(runs, pairs):
        kind, spans = origins(rec)
        vis = visibility_in(pairs[seed])
        n_tracks += len(np.unique(rec.track_id))
        n_ghost += len(np.unique(rec.track_id)) - len(kind)
        n_objects += len(spans)
        for g, sp in spans.items():
            for (_, last), (first, _) in zip(sp, sp[1:]):
                bin_ = next(name for name, lo, hi in GAP_BINS if lo <= first - last - 1 <= hi)
                between = [vis[g].get(q, 0.0) for q in range(last + 1, first)]
                gaps[bin_].append(float(np.mean(between)) if between else float("nan"))
        for group in ("pedestrian", "vehicle"):
            m = (rec.gt_instance >= 0) & (rec.window >= 2) & (rec.group == group) & rec.gt_dynamic
            for i in np.flatnonzero(m):
                key = (group, "young" if rec.window[i] < YOUNG else "full", kind.get(str(rec.track_id[i]), "first"))
                rows[key] += 1
                missed[key] += int(rec.state_z[i] != DYNAMIC)
    rebirths = sum(len(v) for v in gaps.values())
    print(f"confirmed tracks {n_tracks}: {n_ghost} matched to no object, {n_tracks - n_ghost} on {n_objects} objects "
          f"({(n_tracks - n_ghost) / max(n_objects, 1):.2f} a object: {n_objects} first tracks, {rebirths} re-births)")
    for name, _, _ in GAP_BINS:
        v = np.array(gaps.get(name, []))
        vis_txt = f", mean visibility over the gap {np.nanmean(v):.2f}" if v.size and np.isfinite(v).any() else ""
        print(f"   re-born after {name:>7} frames: {v.size}{vis_txt}")
    total = collections.Counter()
    for (group, _, _), n in missed.items():
        total[group] += n
    for group in ("pedestrian", "vehicle"):
        all_rows = sum(n for (g, _, _), n in rows.items() if g == group)
        print(f"moving {group} rows {all_rows}, missed by the z-test {total[group]} "
              f"({total[group] / max(all_rows, 1):.3f}); missed rows by window and track origin:")
        for age in ("young", "full"):
            parts = [f"{o} {missed[(group, age, o)]}/{rows[(group, age, o)]}"
                     for o in ("first", *(n for n, _, _ in GAP_BINS)) if rows[(group, age, o)]]
            print(f"   {age:>5}: " + ", ".join(parts))


if __name__ == "__main__":
    main()
