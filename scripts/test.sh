#!/usr/bin/env bash
# The test command: installs the project (non-editable, with test extras) into .venv and runs the
# whole suite, slow tests (training smoke runs, pip install into a fresh venv) included.
# Extra arguments go to pytest, e.g. scripts/test.sh -m "not slow" -x
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/_venv.sh test
export MUJOCO_GL="${MUJOCO_GL:-egl}"
# `pytest` (not `python -m pytest`) keeps the checkout off sys.path: the installed package is tested.
exec "$VENV/bin/pytest" -m "slow or not slow" -p no:cacheprovider "$@"
