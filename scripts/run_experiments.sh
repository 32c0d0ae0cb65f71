#!/usr/bin/env bash
# The main job: installs the project with its experiment extras into .venv and runs the paper's
# experiments (4 scenarios x no filter / HOCBF / C3BF, seeded), writing results/ (table, figures).
# Extra arguments go to `c3bf-gym experiments`, e.g. scripts/run_experiments.sh --num-seeds 10 --video
# (`--quick`: a smoke run of every output in about 20 s; `--help`: every option and default)
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/_venv.sh experiments
export MUJOCO_GL="${MUJOCO_GL:-egl}"
exec "$VENV/bin/c3bf-gym" experiments "$@"
