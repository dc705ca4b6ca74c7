#!/usr/bin/env bash
# The test suite (unit, property and integration tests; data-dependent tests skip without ../shared).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/python -m pytest -q -p no:cacheprovider --durations=25 "$@"
