"""c3bf-gym: safe robot-arm reinforcement learning with Collision Cone Control Barrier Functions.

Importing the package registers ``C3BFReach-v0`` (the UR5e) and ``C3BFReachPanda-v0`` (the
Franka Emika Panda, the same task) with Gymnasium.
"""

from gymnasium.envs.registration import register, registry

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
