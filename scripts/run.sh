#!/usr/bin/env bash
# The main job on its embedded default: the whole stack on the built-in synthetic scenario.
# Extra arguments go to `jitterguard up` (see `jitterguard up --help`).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/jitterguard up "$@"
