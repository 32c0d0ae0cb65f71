"""numba's on-disk cache for the package's compiled kernels, keyed on every kernel source file.

numba keys a cached function on a hash of the one file that defines it. The filter's kernels call
each other across files (``safety/_step.filter_substep`` compiles ``_rows.filter_rows`` and ``_qp.solve_rows`` into
itself), so an edit to ``_qp.py`` alone would leave the old solver inside the cached ``filter_substep``. Here
the cache stamp of every function defined in :data:`KERNEL_SOURCES` (the filter's kernels, the
scenarios' obstacle sampler and the environment's own) is the hash of all those files together:
changing any of them recompiles every kernel on its next use.

Importing this module installs cache locators in front of numba's own, for the places numba
would use (``NUMBA_CACHE_DIR`` when set, else beside the sources (in :data:`CACHE_FOLDER`), else
the user-wide cache when that folder is not writable), each in a subfolder named after that
hash, so that a cache written by other sources is never read;
functions defined anywhere else keep numba's behaviour. It must be imported before the kernel
modules define their functions, which they do by importing it first.
"""

from __future__ import annotations

import functools
import hashlib
import os
from pathlib import Path

from numba.core import caching, options

__all__ = ["CACHE_FOLDER", "KERNEL_OPTIONS", "KERNEL_SOURCES", "STEP_KERNEL_OPTIONS", "sources_digest"]

#: numba options of the package's kernels: cached on disk (by this module's locators), without the
#: GIL, numpy's floating-point error model (inf and NaN, no exceptions) and no bounds checks.
KERNEL_OPTIONS = {"cache": True, "nogil": True, "error_model": "numpy", "boundscheck": False}
#: :data:`KERNEL_OPTIONS` for the kernels that run at every physics step (the filter, its QP and the
#: environment's physics steps), which allocate nothing and only borrow their callers' arrays:
#: compiled without numba's reference counting (NRT, ``_nrt=False``). With it, every array argument
#: and every view taken in a loop costs an atomic increment and decrement, hundreds per physics
#: step (measured: docs/design-decisions.md, "No reference counting in the step kernels").
#: A kernel that allocates fails to compile with these options (numba: "NRT required but not
#: enabled"), so none can slip in unnoticed. ``_nrt`` is not one of numba's documented options but
#: one it keeps for its own use: a numba without it compiles the same kernels with the counting,
#: and ``tests/test_compile_cache.py`` fails to say so.
STEP_KERNEL_OPTIONS = {**KERNEL_OPTIONS, "_nrt": False} if hasattr(options.DefaultOptions, "_nrt") else KERNEL_OPTIONS

#: The folder beside the kernel sources that holds their cache (unless ``NUMBA_CACHE_DIR`` is set).
CACHE_FOLDER = "_numba_cache"

_PACKAGE = Path(__file__).resolve().parent
#: The modules (paths in the package) whose ``@njit(cache=True)`` functions this cache serves: the
#: filter's, compiled into each other, the obstacle sampler's and the environment's, and the C calls
#: compiled into them; and this one, whose options they are compiled with (numba's cache does not
#: key on options).
KERNEL_SOURCES = ("safety/_dynamics.py", "safety/_rows.py", "safety/_qp.py", "safety/_step.py", "safety/_daqp.py",
                  "scenarios.py", "envs/_kernels.py", "_capi.py", "_compile_cache.py", "controllers/_kernels.py")
_PATHS = tuple(str(_PACKAGE / name) for name in KERNEL_SOURCES)


@functools.lru_cache(maxsize=None)
def _digest(stats: tuple[tuple[float, int], ...]) -> bytes:
    # keyed on every file's (mtime, size), so an edit while the process runs is seen
    sha = hashlib.sha256()
    for path in _PATHS:
        with open(path, "rb") as fh:
            sha.update(hashlib.sha256(fh.read()).digest())
    return sha.digest()


def sources_digest() -> bytes:
    """SHA-256 over the contents of every file of :data:`KERNEL_SOURCES`, in that order."""
    return _digest(tuple((st.st_mtime, st.st_size) for st in map(os.stat, _PATHS)))


def _is_kernel_source(py_file: str) -> bool:
    return os.path.abspath(py_file) in _PATHS


class _KernelStamp:
    """Mixin: a locator that serves only :data:`KERNEL_SOURCES`, stamped with all of them."""

    @classmethod
    def from_function(cls, py_func, py_file):
        if not _is_kernel_source(py_file):
            return None
        return super().from_function(py_func, py_file)

    def get_source_stamp(self):
        return sources_digest()

    def get_cache_path(self):
        # one folder per version of the sources: numba unpickles a cached function's index before
        # it compares stamps, and an index written by other sources can name types of modules that
        # no longer exist (an import error, not a cache miss)
        return os.path.join(super().get_cache_path(), sources_digest().hex()[:16])


class _UserProvidedKernelLocator(_KernelStamp, caching.UserProvidedCacheLocator):
    """``NUMBA_CACHE_DIR``, when the user set it, as numba's first choice."""


class _InTreeKernelLocator(_KernelStamp, caching.InTreeCacheLocator):
    """Beside the sources, in the package's own ``_numba_cache`` folder (numba's default is
    ``__pycache__``, which a wheel does not carry): ``pip install .`` fills it at build time
    (``c3bf_gym/_precompile.py``), so the installed package ships its kernels' machine code."""

    def __init__(self, py_func, py_file):
        super().__init__(py_func, py_file)
        self._cache_path = os.path.join(os.path.dirname(py_file), CACHE_FOLDER)


class _UserWideKernelLocator(_KernelStamp, caching.UserWideCacheLocator):
    """numba's user-wide cache, for a package installed read-only."""


# numba documents neither its locators nor this list (only NUMBA_CACHE_DIR, process-wide, and a cache
# keyed on the defining file): docs/design-decisions.md, "The compiled kernels' disk cache", says why
# it is used anyway, and tests/test_compile_cache.py fails when numba changes it.
if _InTreeKernelLocator not in caching.CacheImpl._locator_classes:
    caching.CacheImpl._locator_classes[:0] = [_UserProvidedKernelLocator, _InTreeKernelLocator,
                                               _UserWideKernelLocator]
