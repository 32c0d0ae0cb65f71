"""Shared test setup.

``MUJOCO_GL`` must be set before ``mujoco`` is first imported: MuJoCo picks its OpenGL backend
(EGL for headless offscreen rendering here) at import time. ``setdefault`` lets a developer with
a display override it (``MUJOCO_GL=glfw pytest``).
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

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
