#!/usr/bin/env bash
# The test suite (unit, property and integration tests; data-dependent tests skip without ../shared).
#
# With no arguments the suite runs as two pytest processes side by side: the tests that start services, stacks
# and servers (they mostly wait on other processes) beside the rest (mostly one busy core: training, ray
# casting, evaluation), so a 2-core machine keeps both cores busy. Every test runs exactly once; the run fails
# if either half fails, and the service half's report is printed after the other's. With arguments, one plain
# pytest run of what they name.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
PYTEST=(.venv/bin/python -m pytest -q -p no:cacheprovider)
if [ "$#" -gt 0 ]; then
  exec "${PYTEST[@]}" --durations=25 "$@"
fi
# tests/cli runs CLI subprocesses, busy on a core the whole time: it goes with the busy half (6 Dec: the service half
# had run 8 minutes alone after the other half ended, 23.8 min in all); so do tests/integrations and tests/replay
# (7 Dec: the busy half ended after 14.4 min, the service half after 21.4; the two take ~2.6 min alone)
SERVICES=(tests/stack tests/sidecar tests/runtime
          tests/classifier/test_classifier_service.py tests/tracker/test_tracker_service.py)
IGNORE=()
for d in "${SERVICES[@]}"; do IGNORE+=("--ignore=$d"); done
log=$(mktemp)
trap 'rm -f "$log"' EXIT
"${PYTEST[@]}" --durations=15 "${SERVICES[@]}" >"$log" 2>&1 &
services=$!
rc=0
echo "== tests without services (${SERVICES[*]} run beside them)"
"${PYTEST[@]}" --durations=15 "${IGNORE[@]}" tests || rc=$?
wait "$services" || rc=$?
echo "== tests that start services: ${SERVICES[*]}"
cat "$log"
exit "$rc"
