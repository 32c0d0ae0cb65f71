"""Shared test setup.

``MUJOCO_GL`` must be set before ``mujoco`` is first imported: MuJoCo picks its OpenGL backend
(EGL for headless offscreen rendering here) at import time. ``setdefault`` lets a developer with
a display override it (``MUJOCO_GL=glfw pytest``).

When the tests import this checkout's package (``PYTHONPATH=.`` or ``python -m pytest``), numba's
cache of its kernels goes to :data:`CHECKOUT_KERNEL_CACHE`, outside the checkout, through
``NUMBA_CACHE_DIR`` (set before numba is first imported, and inherited by the tests' subprocesses).
Left to itself numba writes it beside the sources, into the checkout's ``c3bf_gym/**/_numba_cache``
folders (:mod:`c3bf_gym._compile_cache`). An installed package keeps its own cache, the one its
build compiled. Hypothesis keeps its example database beside the cache too
(``HYPOTHESIS_STORAGE_DIRECTORY``), not in a ``.hypothesis`` folder in the working directory.
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

REPO = Path(__file__).resolve().parents[1]
#: What the tests keep between sessions, outside the checkout.
TEST_CACHE = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "c3bf-gym"
#: numba's cache of this checkout's kernels (numba keys it on each source file's path and
#: contents, so checkouts do not share entries).
CHECKOUT_KERNEL_CACHE = TEST_CACHE / "numba"
os.environ.setdefault("HYPOTHESIS_STORAGE_DIRECTORY", str(TEST_CACHE / "hypothesis"))
_tested = importlib.util.find_spec("c3bf_gym")
if _tested is not None and _tested.origin and Path(_tested.origin).resolve().is_relative_to(REPO):
    os.environ.setdefault("NUMBA_CACHE_DIR", str(CHECKOUT_KERNEL_CACHE))

import gymnasium as gym  # noqa: E402
import pytest  # noqa: E402

import c3bf_gym  # noqa: E402,F401  (registers C3BFReach-v0)

ENV_ID = "C3BFReach-v0"


@pytest.fixture
def make_env():
    """``make_env(**kwargs)`` -> a ``gym.make`` environment, closed after the test."""
    envs = []

    def _make(**kwargs):
        env = gym.make(ENV_ID, **kwargs)
        envs.append(env)
        return env

    yield _make
    for env in envs:
        env.close()


@pytest.fixture
def checkout_env() -> dict[str, str]:
    """The environment of a subprocess that imports this checkout's package (``PYTHONPATH``):
    its kernels cached outside the checkout, also when the tests run an installed package."""
    return {**os.environ, "PYTHONPATH": str(REPO),
            "NUMBA_CACHE_DIR": os.environ.get("NUMBA_CACHE_DIR") or str(CHECKOUT_KERNEL_CACHE)}  # fmt: skip
