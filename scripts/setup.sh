#!/usr/bin/env bash
# Install jitterguard and everything it needs into ./.venv (idempotent; safe to run again).
# Used by scripts/run.sh and scripts/test.sh, the two set-up commands README.md names.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
# shellcheck disable=SC1091
source .venv/bin/activate
python -m pip install -q --upgrade pip >/dev/null
# The CPU build of torch first (a bare `torch` requirement would pull a multi-GB CUDA build).
if ! python -c "import torch" >/dev/null 2>&1; then
  python -m pip install -q "torch==2.13.0" || python -m pip install -q --index-url https://download.pytorch.org/whl/cpu "torch>=2.2,<2.14"
fi
python -m pip install -q -e ".[all]"
# nuscenes-devkit: its metadata pins numpy<2 (it runs fine on numpy 2), so install it without its pins and
# add what it imports; used to cross-check nuScenes-format exports and detection AP.
if ! python -c "import nuscenes.nuscenes" >/dev/null 2>&1; then
  python -m pip install -q --no-deps "nuscenes-devkit>=1.1" \
    && python -m pip install -q cachetools descartes fire parameterized pycocotools pyquaternion scikit-learn shapely "opencv-python-headless>=4.10" \
    || echo "setup: nuscenes-devkit not installed; its cross-check tests will skip" >&2
fi
# Headless Chromium renders the sidecar page in its test; the test skips where it cannot be installed.
if [ "${JG_SKIP_SYSTEM_DEPS:-0}" != "1" ] && ! command -v chromium >/dev/null 2>&1 && [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) || echo "setup: chromium not installed; its page test will skip" >&2
fi
