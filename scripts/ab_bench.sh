#!/usr/bin/env bash
# Back-to-back A/B of a benchmark: a base commit against the working tree, alternating (base, this, base, this…),
# one virtualenv, each side's source put first on PYTHONPATH (the bench's child processes inherit it).
#
#   bash scripts/ab_bench.sh BASE_REV ROUNDS -- jitterguard-args…
#   bash scripts/ab_bench.sh 3cead15 2 -- bench pipeline --json --duration 60
#   THIS_REV=5280b9d bash scripts/ab_bench.sh 5280b9d^1 2 -- bench classifier --json   # two commits
#
# Prints one JSON line per run ({"side", "round", "load1", "result"}) so the pairs can be compared; the base may
# need packages the project no longer lists (3cead15 needs msgspec: `.venv/bin/pip install msgspec`).
set -euo pipefail
cd "$(dirname "$0")/.."
[ $# -ge 3 ] && [ "$3" = "--" ] || { echo "usage: $0 BASE_REV ROUNDS -- jitterguard-args..." >&2; exit 2; }
base_rev=$1 rounds=$2
shift 3
base_dir=$(mktemp -d)
this_dir=$(mktemp -d)
trap 'rm -rf "$base_dir" "$this_dir"' EXIT
git archive "$base_rev" | tar -x -C "$base_dir"
py=$PWD/.venv/bin/python
here=$PWD
if [ -n "${THIS_REV:-}" ]; then  # a commit instead of the working tree
  git archive "$THIS_REV" | tar -x -C "$this_dir"
  here=$this_dir
fi
for ((r = 1; r <= rounds; r++)); do
  for side in base this; do
    src=$here
    [ "$side" = base ] && src=$base_dir
    load=$(cut -d' ' -f1 /proc/loadavg)
    out=$(cd "$src" && PYTHONPATH="$src" "$py" -m jitterguard.cli "$@" 2>/dev/null || true)
    # one line per run: the bench's JSON folded onto it
    out=$("$py" -c 'import json, sys; print(json.dumps(json.loads(sys.stdin.read() or "null")))' <<<"$out" || echo null)
    printf '{"side": "%s", "round": %d, "load1": %s, "result": %s}\n' "$side" "$r" "$load" "$out"
  done
done
