"""The compiled kernels' on-disk cache follows their sources (c3bf_gym/_compile_cache.py).

numba keys a cached function on the file that defines it; the filter's kernels are compiled into
each other across files, so a stale cache could keep an edited solver's old machine code. These
tests run a kernel in fresh interpreters on a copy of the package and read numba's own cache
statistics."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import c3bf_gym

PROBE = """
import json, numpy as np
from c3bf_gym.safety import _step
out = np.empty(3)
_step.hook_post(np.zeros(0), np.zeros(0), np.zeros(0), np.array([2.0, -2.0, 0.5]), np.full(3, 0.5), np.zeros(3),
                np.ones(3), out)
stats = _step.hook_post.stats
print(json.dumps({"hits": sum(stats.cache_hits.values()), "misses": sum(stats.cache_misses.values()),
                  "file": _step.__file__, "out": out.tolist()}))
"""


def _probe(root: Path) -> dict:
    done = subprocess.run([sys.executable, "-c", PROBE], cwd=root, capture_output=True, text=True, timeout=300,
                          env={"PYTHONPATH": str(root), "PATH": "/usr/bin:/bin", "NUMBA_CACHE_DIR": ""})
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_an_edit_to_any_kernel_source_recompiles(tmp_path):
    package = Path(c3bf_gym.__file__).parent
    shutil.copytree(package, tmp_path / "c3bf_gym", ignore=shutil.ignore_patterns("__pycache__", "_numba_cache", "assets"))
    first = _probe(tmp_path)
    assert first["file"].startswith(str(tmp_path)) and first["out"] == [1.0, -1.0, 0.25]
    assert first["misses"] == 1 and first["hits"] == 0  # compiled, then saved
    assert _probe(tmp_path)["hits"] == 1  # unchanged sources: loaded from the cache
    # an edit to _daqp.py alone (the probed kernel is defined in _step.py) must invalidate the cache
    with open(tmp_path / "c3bf_gym" / "safety" / "_daqp.py", "a") as fh:
        fh.write("\n# edited\n")
    edited = _probe(tmp_path)
    assert edited["misses"] == 1 and edited["hits"] == 0
    assert _probe(tmp_path)["hits"] == 1


def test_the_numba_internals_the_package_relies_on_are_still_there():
    """Two things the package takes from numba are not its documented interface (the design
    decisions say why each is kept): the cache locators' list, where _compile_cache puts its own
    first, and the ``_nrt`` option that compiles the step kernels without reference counting."""
    from numba.core import caching, options

    from c3bf_gym import _compile_cache

    locators = getattr(caching.CacheImpl, "_locator_classes", None)
    assert isinstance(locators, list) and locators[0] is _compile_cache._UserProvidedKernelLocator, (
        "numba no longer keeps its cache locators in caching.CacheImpl._locator_classes: c3bf_gym/_compile_cache.py "
        "must find another way to key the kernels' cache on all of KERNEL_SOURCES (docs/design-decisions.md, "
        "'The compiled kernels' disk cache')")
    assert hasattr(options.DefaultOptions, "_nrt") and _compile_cache.STEP_KERNEL_OPTIONS.get("_nrt") is False, (
        "numba no longer has the _nrt option: the step kernels now compile with reference counting, which costs "
        "the filtered step time (docs/design-decisions.md, 'No reference counting in the step kernels'); find "
        "numba's replacement or accept the cost and drop STEP_KERNEL_OPTIONS")
