"""The safety filter as a library: any MuJoCo arm, any obstacles, with or without Gymnasium.

The data flow, one module each: the robot (:mod:`.robot`: what the filter needs to know about
an arm, read from its MuJoCo model; :mod:`.geometry`: the capsules that enclose its geoms;
:mod:`.dynamics`: its dynamics at points on it) → the
obstacles (:mod:`.obstacles`) → the settings (:mod:`.config`) → what they can guarantee
(:mod:`.envelope`: the obstacle speeds and sensing range within which the arm can still get out
of the way) → the constraint rows
(:mod:`.barriers` for their math, :mod:`._kernels` compiled) → the QP (:mod:`.priority_qp`, DAQP
through :mod:`._daqp`) → the controller (:mod:`.controller`: rows and QP, one physics step per
call). ``c3bf_gym.filter.SafetyHook`` runs the controller inside ``C3BFReachEnv`` and
``c3bf_gym.SafetyFilter`` is the Gymnasium wrapper around that.

Example, on a user's own arm (``model`` with torque motors, collision geoms of any type but
planes, height fields and SDFs, a mocap sphere ``ball``)::

    robot = RobotDescription.from_model(model, bodies=["upper_arm", "forearm"], site="tool",
                                        joint_speed_limit=2.0)
    obstacles = MocapSpheres(model, ["ball"])
    controller = SafetyController(model, data, robot, obstacles, FilterConfig(margin=0.03))
    # every physics step:
    mujoco.mj_step1(model, data)
    obstacles.velocity[0] = ball_velocity
    tau, report = controller.filter(tau_nominal)
    robot.write_ctrl(model, data, tau)
    mujoco.mj_step2(model, data)
"""

from c3bf_gym.safety.config import DEFAULT_FILTER, FILTERS, GUARD_GAMMA, FilterConfig
from c3bf_gym.safety.controller import SafetyController, SafetyInfeasibleError, StepSafety
from c3bf_gym.safety.envelope import EnvelopeWarning, FilterEnvelope, filter_envelope
from c3bf_gym.safety.geometry import (
    Capsule,
    UnsupportedGeomError,
    enclosing_capsule,
    fit_capsule,
    protected_capsule,
    world_segments,
)
from c3bf_gym.safety.obstacles import MocapSpheres, Obstacles
from c3bf_gym.safety.robot import RobotDescription, UnprotectedGeometryWarning, UnsupportedModelError

__all__ = [
    "DEFAULT_FILTER",
    "FILTERS",
    "GUARD_GAMMA",
    "Capsule",
    "EnvelopeWarning",
    "FilterConfig",
    "FilterEnvelope",
    "MocapSpheres",
    "Obstacles",
    "RobotDescription",
    "SafetyController",
    "SafetyInfeasibleError",
    "StepSafety",
    "UnprotectedGeometryWarning",
    "UnsupportedGeomError",
    "UnsupportedModelError",
    "enclosing_capsule",
    "filter_envelope",
    "fit_capsule",
    "protected_capsule",
    "world_segments",
]
