"""The safety filter as ``C3BFReachEnv``'s per-physics-step ``filter`` torque hook.

:class:`SafetyHook` is :class:`~c3bf_gym.safety.SafetyController` on the environment's model,
data, robot (``env.robot``) and obstacles (``env.obstacles``), sharing the environment's arm model
and its per-state cache (``env.state_version``), with the environment's sensing radius as the
default. The math, the path of one call and the failure modes are the controller's
(:mod:`c3bf_gym.safety.controller`).
"""

from __future__ import annotations

from c3bf_gym.safety.config import FilterConfig
from c3bf_gym.safety.controller import SafetyController

__all__ = ["SafetyHook"]


class SafetyHook(SafetyController):
    """The filter installed as the env's ``filter`` torque hook (``SafetyFilter`` does this).

    Args:
        env: the unwrapped :class:`~c3bf_gym.envs.C3BFReachEnv`.
        config: the filter's settings (:class:`~c3bf_gym.safety.FilterConfig`); a
            ``sensing_radius`` of None is the environment's.
    """

    def __init__(self, env, config: FilterConfig) -> None:
        self.env = env
        super().__init__(env.model, env.data, env.robot, env.obstacles, config, arm=env.arm,
                         sensing_radius=env.sensing_radius)  # fmt: skip

    def _version(self) -> int:
        return self.env.state_version
