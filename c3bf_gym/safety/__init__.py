"""The safety filter as a library: any MuJoCo arm, any obstacles, with or without Gymnasium.

The data flow, one module each: the robot (:mod:`.robot`: what the filter needs to know about
an arm, read from its MuJoCo model; :mod:`.geometry`: the capsules that enclose its geoms;
:mod:`.dynamics`: its dynamics at points on it) → the
obstacles (:mod:`.obstacles`) → the settings (:mod:`.config`) → what they can guarantee
(:mod:`.envelope`: the obstacle speeds and sensing range within which the arm can still get out
of the way) → the constraint rows
(:mod:`.barriers` for their math; compiled in :mod:`._rows`, on the arm's dynamics kernels
:mod:`._dynamics`) → the QP (:mod:`.priority_qp`; its priority algorithm compiled in :mod:`._qp`,
on DAQP's C API bound in :mod:`._daqp`) → the controller (:mod:`.controller`: rows and QP, one
physics step per call; compiled as one call in :mod:`._step`, which a simulator's own compiled
loop calls through the seam :mod:`.substep`). The compiled modules import only
the layers below them (:mod:`._rows` the dynamics, :mod:`._qp` the binding, :mod:`._step` both), and
this package imports the names it exports when they are first read, so computing a barrier or
its rows loads no QP solver. ``c3bf_gym.filter.SafetyHook`` runs the controller inside
``C3BFReachEnv`` and ``c3bf_gym.SafetyFilter`` is the Gymnasium wrapper around that.

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

from __future__ import annotations

from typing import TYPE_CHECKING

from c3bf_gym import _lazy_attribute

if TYPE_CHECKING:
    from c3bf_gym.safety.config import DEFAULT_FILTER, FILTERS, GUARD_GAMMA, FilterConfig
    from c3bf_gym.safety.controller import SafetyController, SafetyInfeasibleError, StepSafety
    from c3bf_gym.safety.envelope import EnvelopeWarning, FilterEnvelope, filter_envelope
    from c3bf_gym.safety.geometry import (
        Capsule,
        UnsupportedGeomError,
        capsule_distances,
        enclosing_capsule,
        fit_capsule,
        protected_capsule,
        world_segments,
    )
    from c3bf_gym.safety.obstacles import MocapSpheres, Obstacles
    from c3bf_gym.safety.robot import RobotDescription, UnprotectedGeometryWarning, UnsupportedModelError
    from c3bf_gym.safety.substep import FilterCall

#: the module each name comes from, imported when the name is first read (PEP 562): importing
#: :mod:`.barriers` or the row kernels loads neither the controller nor the QP's solver
_EXPORTS = {
    "DEFAULT_FILTER": "c3bf_gym.safety.config",
    "FILTERS": "c3bf_gym.safety.config",
    "GUARD_GAMMA": "c3bf_gym.safety.config",
    "Capsule": "c3bf_gym.safety.geometry",
    "EnvelopeWarning": "c3bf_gym.safety.envelope",
    "FilterCall": "c3bf_gym.safety.substep",
    "FilterConfig": "c3bf_gym.safety.config",
    "FilterEnvelope": "c3bf_gym.safety.envelope",
    "MocapSpheres": "c3bf_gym.safety.obstacles",
    "Obstacles": "c3bf_gym.safety.obstacles",
    "RobotDescription": "c3bf_gym.safety.robot",
    "SafetyController": "c3bf_gym.safety.controller",
    "SafetyInfeasibleError": "c3bf_gym.safety.controller",
    "StepSafety": "c3bf_gym.safety.controller",
    "UnprotectedGeometryWarning": "c3bf_gym.safety.robot",
    "UnsupportedGeomError": "c3bf_gym.safety.geometry",
    "UnsupportedModelError": "c3bf_gym.safety.robot",
    "capsule_distances": "c3bf_gym.safety.geometry",
    "enclosing_capsule": "c3bf_gym.safety.geometry",
    "filter_envelope": "c3bf_gym.safety.envelope",
    "fit_capsule": "c3bf_gym.safety.geometry",
    "protected_capsule": "c3bf_gym.safety.geometry",
    "world_segments": "c3bf_gym.safety.geometry",
}
#: spelt out, not ``list(_EXPORTS)``, for tools that read the source (griffe, for the API page)
__all__ = [
    "DEFAULT_FILTER",
    "FILTERS",
    "GUARD_GAMMA",
    "Capsule",
    "EnvelopeWarning",
    "FilterCall",
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
    "capsule_distances",
    "enclosing_capsule",
    "filter_envelope",
    "fit_capsule",
    "protected_capsule",
    "world_segments",
]


def __getattr__(name: str):
    return _lazy_attribute(__name__, _EXPORTS, name)


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
