"""c3bf-gym: safe robot-arm reinforcement learning with Collision Cone Control Barrier Functions.

Importing the package registers ``C3BFReach-v0`` (the UR5e) and ``C3BFReachPanda-v0`` (the
Franka Emika Panda, the same task) with Gymnasium. The names it re-exports are imported when first
read, so importing a submodule loads only that submodule's own imports.
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING

from gymnasium.envs.registration import register, registry

if TYPE_CHECKING:
    from c3bf_gym.controllers import CartesianImpedance
    from c3bf_gym.envs import C3BFReachEnv
    from c3bf_gym.safety import (
        DEFAULT_FILTER,
        FILTERS,
        FilterConfig,
        MocapSpheres,
        Obstacles,
        RobotDescription,
        SafetyController,
        SafetyInfeasibleError,
        UnsupportedModelError,
    )
    from c3bf_gym.scenarios import SCENARIOS, Envelope, ObstacleSpec, Scenario
    from c3bf_gym.wrappers import ActionPenalty, CartesianImpedanceAction, SafetyFilter

#: the module each re-exported name comes from, imported when the name is first read (PEP 562), so
#: that importing one submodule (``c3bf_gym.safety.barriers``, say) loads only what it imports
_EXPORTS = {
    "ActionPenalty": "c3bf_gym.wrappers",
    "C3BFReachEnv": "c3bf_gym.envs",
    "CartesianImpedance": "c3bf_gym.controllers",
    "CartesianImpedanceAction": "c3bf_gym.wrappers",
    "DEFAULT_FILTER": "c3bf_gym.safety",
    "Envelope": "c3bf_gym.scenarios",
    "FILTERS": "c3bf_gym.safety",
    "FilterConfig": "c3bf_gym.safety",
    "MocapSpheres": "c3bf_gym.safety",
    "ObstacleSpec": "c3bf_gym.scenarios",
    "Obstacles": "c3bf_gym.safety",
    "RobotDescription": "c3bf_gym.safety",
    "SCENARIOS": "c3bf_gym.scenarios",
    "SafetyController": "c3bf_gym.safety",
    "SafetyFilter": "c3bf_gym.wrappers",
    "SafetyInfeasibleError": "c3bf_gym.safety",
    "Scenario": "c3bf_gym.scenarios",
    "UnsupportedModelError": "c3bf_gym.safety",
}
#: spelt out, not ``list(_EXPORTS)``, for tools that read the source (griffe, for the API page)
__all__ = [
    "ActionPenalty",
    "C3BFReachEnv",
    "CartesianImpedance",
    "CartesianImpedanceAction",
    "DEFAULT_FILTER",
    "Envelope",
    "FILTERS",
    "FilterConfig",
    "MocapSpheres",
    "ObstacleSpec",
    "Obstacles",
    "RobotDescription",
    "SCENARIOS",
    "SafetyController",
    "SafetyFilter",
    "SafetyInfeasibleError",
    "Scenario",
    "UnsupportedModelError",
]
__version__ = "0.1.0"

if "C3BFReach-v0" not in registry:
    register(
        id="C3BFReach-v0",
        entry_point="c3bf_gym.wrappers:make_reach",
        max_episode_steps=250,
    )
if "C3BFReachPanda-v0" not in registry:
    register(
        id="C3BFReachPanda-v0",
        entry_point="c3bf_gym.wrappers:make_reach",
        kwargs={"robot": "panda"},
        max_episode_steps=250,
    )


def _lazy_attribute(package: str, exports: dict[str, str], name: str):
    """A package's ``__getattr__`` (PEP 562): the re-exported ``name`` from its module in ``exports``,
    or the package's submodule ``name``, imported now.

    Raises:
        AttributeError: neither.
    """
    if name in exports:
        return getattr(import_module(exports[name]), name)
    try:
        return import_module(f"{package}.{name}")
    except ModuleNotFoundError as error:
        if error.name != f"{package}.{name}":
            raise
    raise AttributeError(f"module {package!r} has no attribute {name!r}")


def __getattr__(name: str):
    return _lazy_attribute(__name__, _EXPORTS, name)


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
