"""Tracking quality of the tracker core on the seeded synthetic sequences, as JSON (MOTA, IDF1, ID switches).

    python benchmarks/tracker_mot.py [--seeds 0,1,2,3,4] [--frames 150] [--measurement-covariance detector|class]

Uses the sequence generator and motmetrics harness of the tracker's tests (tests/tracker), so the figures
printed here are the ones the test suite asserts on (MOTA >= 0.9, IDF1 >= 0.9).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "tracker"))

from jitterguard.services.tracker.config import default_config  # noqa: E402
from tracker_mot import evaluate  # noqa: E402
from tracker_simseq import make_sequence  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--measurement-covariance", choices=("detector", "class"), default="detector")
    args = ap.parse_args()
    cfg = default_config(measurement_covariance=args.measurement_covariance)
    per_seed = {}
    for seed in (int(s) for s in args.seeds.split(",")):
        per_seed[f"seed_{seed}"] = evaluate(make_sequence(seed, n_frames=args.frames), cfg).as_dict()
    n = len(per_seed)
    summary = {
        "mota_mean": round(sum(r["mota"] for r in per_seed.values()) / n, 4),
        "idf1_mean": round(sum(r["idf1"] for r in per_seed.values()) / n, 4),
        "mota_min": min(r["mota"] for r in per_seed.values()),
        "idf1_min": min(r["idf1"] for r in per_seed.values()),
        "id_switches_total": sum(r["id_switches"] for r in per_seed.values()),
        "frames_per_seed": args.frames,
        "measurement_covariance": args.measurement_covariance,
    }
    print(json.dumps({"summary": summary, **per_seed}, indent=2))


if __name__ == "__main__":
    main()
