"""Per-frame time of the tracker core at 50 / 200 / 500 objects, as JSON.

    python benchmarks/tracker_bench.py        # same as: jitterguard bench tracker --json
"""

from __future__ import annotations

import json

from jitterguard.services.tracker.bench import run

if __name__ == "__main__":
    print(json.dumps(run()))
