#!/usr/bin/env bash
# The docs command: installs the project with the docs extra into .venv (as scripts/test.sh does
# with the test extra) and builds the site strictly: a broken link, a page missing from the nav or
# a docstring that does not render fails it. CI runs it after the tests.
#   scripts/docs.sh               build into site/
#   scripts/docs.sh -d /tmp/site  extra arguments go to mkdocs build
set -euo pipefail
cd "$(dirname "$0")/.."
# the site is built from the sources (griffe reads them; nothing runs the filter), so the install
# skips compiling the kernels into the package (setup.py)
export C3BF_GYM_PRECOMPILE=0
source scripts/_venv.sh docs
# griffe reads the sources of this checkout (mkdocs.yml: paths [.]); the install brings the tools.
export NO_MKDOCS_2_WARNING=1
exec "$VENV/bin/mkdocs" build --strict "$@"
