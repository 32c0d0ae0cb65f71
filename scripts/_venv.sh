# Sourced by the scripts in this folder: create (or reuse) a virtual environment and install the
# project into it, non-editable, with the extras given as arguments.
#   VENV   where the environment lives (default: .venv in the repository)
set -euo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${VENV:-$repo/.venv}"
extras="${1:-}"
if [ ! -x "$VENV/bin/python" ]; then
    python3 -m venv "$VENV"
fi
"$VENV/bin/python" -m pip install --quiet --upgrade pip
# torch first, pinned: on this project's machines 2.13.0 is a local CPU wheel. Elsewhere, for a CPU
# build, run: pip install torch --index-url https://download.pytorch.org/whl/cpu
case ",$extras," in
    *,train,*|*,test,*) "$VENV/bin/python" -m pip install --quiet "torch==2.13.0" ;;
esac
"$VENV/bin/python" -m pip install --quiet "$repo${extras:+[$extras]}"
