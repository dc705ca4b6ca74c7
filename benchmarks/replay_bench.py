"""Replay ``--rate max`` into an in-process subscriber: scans/s and dropped count, as JSON lines.

    python benchmarks/replay_bench.py     # in-memory 35k-point scans, then the nuScenes scene if ../shared has it

Same as ``jitterguard bench replay --json`` (and ``--source ../shared/data/nuscenes-scene-0523``).
"""

from __future__ import annotations

import json
from pathlib import Path

from jitterguard.services.replay.bench import bench_replay_repeated

NUSCENES = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "nuscenes-scene-0523"

if __name__ == "__main__":
    print(json.dumps(bench_replay_repeated(3, frames=600, points=35_000)))
    if NUSCENES.is_dir():
        print(json.dumps(bench_replay_repeated(3, frames=400, source=str(NUSCENES))))
