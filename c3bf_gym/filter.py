"""The safety filter as ``C3BFReachEnv``'s per-physics-step ``filter`` torque hook.

:class:`SafetyHook` is :class:`~c3bf_gym.safety.SafetyController` on the environment's model,
data, robot (``env.robot``) and obstacles (``env.obstacles``), sharing the environment's arm model
and its per-state cache (``env.state_version``), with the environment's sensing radius as the
default. The math, the path of one call and the failure modes are the controller's
(:mod:`c3bf_gym.safety.controller`).
"""

from __future__ import annotations

import warnings

from c3bf_gym.safety.config import FilterConfig
from c3bf_gym.safety.controller import SafetyController
from c3bf_gym.safety.envelope import EnvelopeWarning, FilterEnvelope, filter_envelope

__all__ = ["SafetyHook", "scenario_envelope"]


class SafetyHook(SafetyController):
    """The filter installed as the env's ``filter`` torque hook (``SafetyFilter`` does this).

    Args:
        env: the unwrapped :class:`~c3bf_gym.envs.C3BFReachEnv`.
        config: the filter's settings (:class:`~c3bf_gym.safety.FilterConfig`); a
            ``sensing_radius`` of None is the environment's.

    Warns:
        :class:`~c3bf_gym.safety.EnvelopeWarning`: the environment's obstacles (its
            ``obstacle_speed_range`` and ``obstacle_radius_range``, sensed at the filter's sensing
            radius) are outside the envelope the filter states (:func:`scenario_envelope`).
    """

    def __init__(self, env, config: FilterConfig) -> None:
        self.env = env
        envelope = scenario_envelope(env, config)
        super().__init__(env.model, env.data, env.robot, env.obstacles, config, arm=env.arm,
                         sensing_radius=env.sensing_radius, envelope=envelope)  # fmt: skip
        speed, radius = env.envelope.speed_range[1], env.envelope.radius_range[1]
        problems = envelope.problems(speed, radius)  # at the filter's sensing radius, as computed
        if problems:
            warnings.warn(EnvelopeWarning(f"the {env.task_robot.name}'s obstacles (up to {speed:g} m/s, radius up to "
                                          f"{radius:g} m) are outside the filter's envelope, where it guarantees "
                                          "nothing: " + "; ".join(problems)), stacklevel=3)  # fmt: skip

    def _version(self) -> int:
        return self.env.state_version


def scenario_envelope(env, config: FilterConfig) -> FilterEnvelope:
    """The envelope (:func:`~c3bf_gym.safety.filter_envelope`) the filter ``config`` states on the
    environment ``env``'s arm, for its largest obstacle radius, its keep-out cylinder
    (:class:`~c3bf_gym.scenarios.Envelope`) and the filter's sensing radius, from the arm's
    ``home`` keyframe and 128 drawn configurations. Computed once per process for each arm and
    the settings it depends on (margin, joint limits and speed fraction, barrier and guard by
    name, sensing radius); with a Barrier instance as barrier or guard, at every call."""
    sensing = env.sensing_radius if config.sensing_radius is None else config.sensing_radius
    scenario = env.envelope
    model, robot = env.model, env.robot
    key = (env.task_robot.name, scenario.radius_range[1], scenario.keep_out_radius, scenario.keep_out_height, sensing,
           config.margin, config.joint_limits, config.joint_speed_fraction, config.barrier, config.gamma, config.guard,
           config.guard_gamma)  # fmt: skip
    named = all(part is None or isinstance(part, (str, float, int, bool)) for part in key)
    if named and key in _ENVELOPES:
        return _ENVELOPES[key]
    home = model.key_qpos[model.key("home").id][model.jnt_qposadr[model.dof_jntid[robot.dof_ids]]]
    envelope = filter_envelope(model, robot, config, obstacle_radius=scenario.radius_range[1], sensing_radius=sensing,
                               keep_out_radius=scenario.keep_out_radius, keep_out_height=scenario.keep_out_height,
                               qpos=home)  # fmt: skip
    if named:
        _ENVELOPES[key] = envelope
    return envelope


_ENVELOPES: dict[tuple, FilterEnvelope] = {}  # scenario_envelope's, by arm and settings
