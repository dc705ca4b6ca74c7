"""Ray-casting throughput of the synthetic LiDAR: full scans per second on one core, as JSON lines.

    python benchmarks/sim_raycast.py      # HDL-32E (≈35k rays) on a 60-object parking street, then every scenario

Same as ``jitterguard bench sim --json`` (options: --scans, --objects, --scenario, --lidar, --repeat).
"""

from __future__ import annotations

import json

from jitterguard.sim.bench import bench_raycast
from jitterguard.sim.world import SCENARIO_NAMES

if __name__ == "__main__":
    print(json.dumps(bench_raycast("hdl32e", "parking-street", objects=60, scans=40, repeat=3)))
    for name in SCENARIO_NAMES:
        print(json.dumps(bench_raycast("hdl32e", name, objects=120, scans=20, repeat=1)))
    for sensor in ("vlp16", "os1-64"):
        print(json.dumps(bench_raycast(sensor, "mixed", objects=60, scans=20, repeat=1)))
