#!/usr/bin/env bash
# Install jitterguard and everything it needs into ./.venv (idempotent; safe to run again).
# Used by scripts/run.sh and scripts/test.sh, the two set-up commands README.md names.
#
# Quiet unless something fails: each installer's output goes to a temporary log that is printed only when the
# step fails (pip's expected notes, build-backend banners and the dependency-resolver complaint about
# nuscenes-devkit's numpy pin are not failures). When pyproject.toml and this script are unchanged since the
# last successful run, the install steps are skipped.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

quiet() {  # run "$@" with its output kept aside; show it (and fail) only if the command fails
  local log
  log=$(mktemp)
  if ! "$@" >"$log" 2>&1; then
    echo "setup: failed: $*" >&2
    cat "$log" >&2
    rm -f "$log"
    return 1
  fi
  rm -f "$log"
}

if [ ! -x .venv/bin/python ]; then
  quiet "$PY" -m venv .venv
fi
# shellcheck disable=SC1091
source .venv/bin/activate
stamp=".venv/.jitterguard-setup-$(cat pyproject.toml scripts/setup.sh | sha256sum | cut -c1-16)"
if [ -f "$stamp" ] && python -c "import importlib.util as u, sys; sys.exit(not (u.find_spec('jitterguard') and u.find_spec('torch')))" 2>/dev/null; then
  exit 0
fi
quiet python -m pip install --upgrade pip
# torch before the project (whose bare requirement would pull the index's default build, on PyPI a multi-GB CUDA
# one): the pinned 2.13.0 the machine's pip offers (the project's machines: the CPU build on disk), else the CPU
# index. A torch already in the venv is kept.
if ! python -c "import torch" >/dev/null 2>&1; then
  quiet python -m pip install "torch==2.13.0" \
    || quiet python -m pip install --index-url https://download.pytorch.org/whl/cpu "torch>=2.2,<2.14"
fi
quiet python -m pip install -e ".[all]"
# nuscenes-devkit: its metadata pins numpy<2 (it runs fine on numpy 2), so install it without its pins and
# add what it imports; used to cross-check nuScenes-format exports and detection AP. pip's resolver then
# reports the numpy pin as a conflict; that is expected, so only a failed install is shown.
if ! python -c "import nuscenes.nuscenes" >/dev/null 2>&1; then
  { quiet python -m pip install --no-deps "nuscenes-devkit>=1.1" \
      && quiet python -m pip install cachetools descartes fire parameterized pycocotools pyquaternion scikit-learn \
        shapely "opencv-python-headless>=4.10"; } \
    || echo "setup: nuscenes-devkit not installed; its cross-check tests will skip" >&2
fi
# Headless Chromium renders the sidecar page in its test; the test skips where it cannot be installed.
if [ "${JG_SKIP_SYSTEM_DEPS:-0}" != "1" ] && ! command -v chromium >/dev/null 2>&1 && [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  (quiet apt-get update -qq && DEBIAN_FRONTEND=noninteractive quiet apt-get install -y -qq chromium) \
    || echo "setup: chromium not installed; its page test will skip" >&2
fi
# Compile the classifier's calibrated statistic once now (numba caches it next to the module), so the first
# service start does not pay the seconds it takes.
quiet python -c "from jitterguard.services.classifier.statistics import warm_up; warm_up()"
rm -f .venv/.jitterguard-setup-*
touch "$stamp"
