#!/usr/bin/env bash
# The test command: installs the project (non-editable, with test extras) into .venv and runs the
# whole suite, slow tests (training smoke runs, pip install into a fresh venv) included; then, in a
# second environment (.venv-rllib: the rllib extra, so the gymnasium that Ray RLlib pins), the fast
# suite again and the Ray tests (tests/test_rllib.py). C3BF_SKIP_RLLIB=1 skips the second part.
# Extra arguments go to pytest, e.g. scripts/test.sh -m "not slow" -x
set -euo pipefail
cd "$(dirname "$0")/.."
repo="$(pwd)"
export MUJOCO_GL="${MUJOCO_GL:-egl}"
source scripts/_venv.sh test
# `pytest` (not `python -m pytest`) keeps the checkout off sys.path: the installed package is tested.
"$VENV/bin/pytest" -m "slow or not slow" -p no:cacheprovider "$@"
if [ "${C3BF_SKIP_RLLIB:-0}" != 1 ]; then
    VENV="$repo/.venv-rllib"  # set apart from `source`: an assignment prefixed to it would not outlast it
    source scripts/_venv.sh test,rllib
    "$VENV/bin/python" -c "import gymnasium, ray; print('RLlib environment: gymnasium', gymnasium.__version__, 'ray', ray.__version__)"
    "$VENV/bin/pytest" -m "not slow" -p no:cacheprovider "$@"
fi
