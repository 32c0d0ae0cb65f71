"""The safety filter on any MuJoCo arm: barrier rows + floor + joint limits -> QP, per physics step.

Its settings are one :class:`~c3bf_gym.safety.FilterConfig`; :data:`~c3bf_gym.safety.FILTERS` names the
configurations the project compares. At every physics step (between ``mj_step1`` and ``mj_step2``;
``C3BFReachEnv`` calls it as its ``filter`` torque hook, :class:`~c3bf_gym.filter.SafetyHook`):

1. the arm's dynamics at the protected points are refreshed (:class:`~c3bf_gym.safety.dynamics.ArmModel`):
   for a point ``x`` on the arm, ``ẍ = G τ + c`` with ``G = J M⁻¹`` (``M`` including the
   integrator's joint damping) and ``c = J M⁻¹ (τ_passive − b) + J̇ q̇``;
2. every *sensed* obstacle (active, surface within ``sensing_radius`` of the arm) contributes one
   row per protected point (``whole_arm``: the closest point of every link capsule, with the
   capsule radius added to the obstacle's; ``ee``: the tool site with ``ee_radius``), and with a
   guard one more, the guard barrier's, right after it. Closest points slide along their links;
   the rows include the sliding terms of ``ḣ``;
3. the floor contributes one row per capsule end that can move vertically (``2 S`` at most):
   the second-order barrier ``z̈ + 2γ ż + γ² (z − z_min) ≥ 0`` (γ = ``floor_gamma``), with
   ``z_min`` the floor plus the capsule radius plus ``margin``. Contact forces are not in the
   model ``ẍ = G τ + c``, so the arm must not lean on the floor; likewise, with
   ``self_collision``, every pair of the arm's capsules that the model lets collide gets one row,
   the same barrier on the distance between their axes
   (:class:`~c3bf_gym.safety.barriers.SelfCollision`), so that no link leans on another;
4. joint position and velocity limits contribute ``4 n`` rows
   (:class:`~c3bf_gym.safety.barriers.JointLimits`), the position rows drawn
   ``joint_range_reserve`` inside the range when the config keeps a reserve, the speed rows at
   ``nominal_speed_fraction`` of the robot's bound with their copies at ``joint_speed_fraction``
   when the config sets a lower bound for the nominal torque. The obstacle, floor and pair
   rows are tightened for the forces the filter cannot predict, each bounded
   (:attr:`~c3bf_gym.safety.RobotDescription.unmodelled_force`: joint dry friction, the actuators of
   dofs that are not the arm's, such as a gripper's): :func:`~c3bf_gym.safety._rows.unmodelled_margin`.
   The joint-limit rows instead take the generalised constraint force of the last physics step
   (MuJoCo's ``qfrc_constraint``: contacts, joint limits, dry friction) as the next step's
   (:func:`~c3bf_gym.safety._dynamics.joint_drift`), so a joint's friction, coupled to the others
   through ``M⁻¹``, does not carry a joint past its speed bound (a stiff contact's force follows
   the torque, and the last step's only estimates it);
5. :class:`~c3bf_gym.safety.priority_qp.PriorityQP` (DAQP) returns the torque closest to the
   nominal one (in the metric ``weight``) that satisfies every row within the actuator limits.
   When none does, the rows give way by priority: the barrier's rows first, while the joint
   limits, the floor, the arm's own pairs and the guard hold as well as the torque limits allow
   (with a reserve, the position rows inside the range give way after the barrier's and before
   the rows at the range itself; with a nominal speed bound, the speed rows at it give way before
   the barrier's, their copies at the filter's bound holding with level 1; with
   ``allowance_level``, the barrier's rows hold within their allowance before they give way
   beyond it: :mod:`c3bf_gym.safety._qp`). The step is reported with the largest violation of
   each kind of row (:attr:`StepSafety.violation`), and as infeasible unless only the barrier's
   rows within a raised gain, the reserve or the nominal speed bound gave way; with
   ``on_infeasible="raise"`` any call where rows gave way raises instead.

Steps 1–4 with the built-in barriers (:class:`~c3bf_gym.safety.barriers.C3BF`,
:class:`~c3bf_gym.safety.barriers.DistanceHOCBF`, and a distance-HOCBF guard or none), for either
kind of protected points, are one compiled kernel, :func:`c3bf_gym.safety._rows.filter_rows`, built
from the same per-point functions the barrier classes and :class:`~c3bf_gym.safety.dynamics.ArmModel`
call. A barrier or guard the kernel does not know (a user's own
:class:`~c3bf_gym.safety.barriers.Barrier` subclass, a guard other than a distance HOCBF) goes
through ``Barrier.terms`` and ``rows_from_terms`` from Python: that per-class path is the
extension point, and gives the built-in barriers' rows to rounding. On the fused path the
rows, the QP and the report's bookkeeping are one compiled call
(:func:`c3bf_gym.safety._step.filter_substep`), which an environment may also call from its own
compiled policy step (:meth:`SafetyController.compiled_call`, the seam of :mod:`c3bf_gym.safety.substep`;
``C3BFReachEnv`` uses it). Why each
of these choices was made, with the measurements and the commands that repeat them:
``docs/design-decisions.md``.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field

import mujoco
import numba
import numpy as np

from c3bf_gym._capi import pack
from c3bf_gym.safety import _dynamics, _qp, _rows, _step
from c3bf_gym.safety.barriers import Floor, JointLimits, Rows, SelfCollision
from c3bf_gym.safety.dynamics import ArmModel, segment_closest_points
from c3bf_gym.safety.envelope import EnvelopeWarning, FilterEnvelope, filter_envelope
from c3bf_gym.safety.config import FilterConfig
from c3bf_gym.safety.obstacles import Obstacles
from c3bf_gym.safety.priority_qp import STATUS, PriorityQP, QPResult, bad_input_error
from c3bf_gym.safety.robot import RobotDescription, UnprotectedGeometryWarning, UnsupportedModelError
from c3bf_gym.safety.substep import FilterCall

__all__ = ["MAX_GAIN_STEP", "RAISED_GAIN_STEP", "ROW_KINDS", "SafetyController", "SafetyInfeasibleError", "StepSafety"]

#: The largest product of a row's gain [1/s] and the physics timestep [s] the filter accepts without
#: an :class:`~c3bf_gym.safety.EnvelopeWarning`: a barrier condition ``ḣ ≥ −γ h`` held at the start of
#: each step lets ``h`` fall by about ``γ Δt h`` within it, so ``γ Δt`` must stay small for the
#: continuous-time argument to carry over (0.04 with the default gains at MuJoCo's 2 ms).
MAX_GAIN_STEP = 0.05
#: The largest product of a barrier row's raised gain γ' [1/s] and the physics timestep [s]: a row that
#: gives way at ``h > 0`` still holds ``ḣ ≥ −γ' h`` for some ``γ' ≤ RAISED_GAIN_STEP / Δt`` (250/s at
#: 2 ms) is counted as held with a raised gain, not as infeasible. It is the discrete-time barrier
#: condition ``h(t + Δt) ≥ (1 − λ) h(t)`` with ``λ = γ' Δt ≤ 1/2``: one physics step may at most
#: halve ``h``, and never takes it below zero.
RAISED_GAIN_STEP = 0.5

#: The kinds of safety rows, in :attr:`StepSafety.violation`: the barrier's (priority 2: they give
#: way first), the guard's, the floor's and the joint limits' (priority 1), rows no torque can
#: change that an obstacle violates ("unmovable"), and the arm's own capsule pairs' (priority 1).
ROW_KINDS = ("barrier", "guard", "floor", "joint_limits", "unmovable", "self_collision")

_perf_counter = time.perf_counter
#: :attr:`SafetyController.last`'s status names: the QP's, and a relaxed call that held every row
#: with the barrier's gain raised (:data:`~c3bf_gym.safety._step.GAIN_RAISED`)
_STATUS = {**STATUS, _step.GAIN_RAISED: "gain raised"}


class SafetyInfeasibleError(RuntimeError):
    """Raised with ``on_infeasible="raise"`` when no torque within the limits satisfies the rows."""


@dataclass
class StepSafety:
    """What the filter did over one policy step (all its physics steps).

    Attributes:
        feasible: every physics step's rows held: each with no slack, or (only the barrier's)
            with its gain raised within its allowance (``gain_raised_steps``).
        slack: the largest slack used [N m, row-normalised], at steps that were infeasible or
            held with a raised gain; 0.0 when every row held as written.
        min_h: the smallest barrier value over the barrier's rows (not the guard's) and physics
            steps (inf with no row).
        correction: the largest ``‖τ − τ_nom‖`` [N m] (``τ_nom`` clipped to the torque limits,
            so plain saturation is not counted as a safety intervention).
        active_rows: the largest number of binding rows.
        sensed: the largest number of sensed obstacles.
        solve_time: total wall time of the filter over the step's physics steps [s] (rows and
            QP), when its calls came through :meth:`SafetyController.__call__`; NaN when they ran
            inside a compiled policy step (``C3BFReachEnv`` with the filter as its only hook),
            which does not time them: :meth:`SafetyController.record_times` sends every call
            through ``__call__``, with the same torques. Not in :meth:`as_info`: wall-clock time
            would make ``info`` nondeterministic.
        intervened: some physics step changed the torque by more than ``intervention_tol``.
        inside: some protected point was already inside an obstacle's (margin-inflated) radius.
        infeasible_steps: number of physics steps where rows gave way beyond their allowance:
            a guard, floor, self-collision, joint-limit or unmovable row gave way, or a barrier
            row at ``h <= 0``, or one at ``h > 0`` by more than ``(γ_max − γ) h`` (the condition
            ``ḣ ≥ −γ' h`` failed for every gain ``γ'`` up to ``γ_max`` = :data:`RAISED_GAIN_STEP`
            / Δt; :func:`~c3bf_gym.safety._step.beyond_allowance`). On these steps the guarantee
            does not hold.
        gain_raised_steps: number of physics steps where only barrier rows gave way, each within
            that allowance, or joint position rows within the joint range's reserve
            (``FilterConfig.joint_range_reserve``), or joint speed rows between the nominal
            torque's bound and the filter's (``FilterConfig.nominal_speed_fraction``): every row
            held, the barrier's with a gain between γ and ``γ_max``, the joints within their range
            and the filter's speed bound.
        min_constraint: the smallest row residual ``A τ − b`` at the applied torque (the QP
            constraint value: >= 0 when every row holds) [row units]; inf with no row. Taken
            from the QP's row-normalised residuals times the rows' norms
            (:func:`~c3bf_gym.safety._step.hook_post`).
        violation: what gave way: for each of :data:`ROW_KINDS`, the largest row-normalised
            violation ``(b_k − A_k τ) / ‖A_k s‖`` over the step's infeasible physics steps [N m
            in the scaled torque], 0.0 where none (for "unmovable", the violated ``b_k``). In
            :meth:`as_info` as ``violation_<kind>`` floats.
        tau_nominal, tau: the last physics step's nominal and filtered torques [N m].
    """

    feasible: bool = True
    slack: float = 0.0
    min_h: float = np.inf
    correction: float = 0.0
    active_rows: int = 0
    sensed: int = 0
    solve_time: float = 0.0
    intervened: bool = False
    inside: bool = False
    infeasible_steps: int = 0
    gain_raised_steps: int = 0
    min_constraint: float = np.inf
    substeps: int = 0
    tau_nominal: np.ndarray | None = None
    tau: np.ndarray | None = None
    violation: dict[str, float] = field(default_factory=lambda: dict.fromkeys(ROW_KINDS, 0.0))

    def as_info(self) -> dict[str, float | bool | int]:
        """The report as ``info["safety"]``: every attribute but the torques and ``solve_time``, the
        violations as ``violation_<kind>`` floats."""
        return {
            "feasible": self.feasible,
            "slack": self.slack,
            "min_h": self.min_h,
            "correction": self.correction,
            "active_rows": self.active_rows,
            "sensed": self.sensed,
            "intervened": self.intervened,
            "inside": self.inside,
            "infeasible_steps": self.infeasible_steps,
            "gain_raised_steps": self.gain_raised_steps,
            "min_constraint": self.min_constraint,
            **{f"violation_{kind}": value for kind, value in self.violation.items()},
        }


def _checked_arguments(model: mujoco.MjModel, robot: RobotDescription, obstacles: Obstacles,
                       config: FilterConfig | None, envelope: FilterEnvelope | None) -> FilterConfig:
    """:class:`SafetyController`'s arguments checked (its Raises), and the config (None: the default)."""
    config = FilterConfig() if config is None else config
    if not isinstance(config, FilterConfig):
        raise TypeError(f"config must be a FilterConfig, got {type(config).__name__}")
    if not isinstance(robot, RobotDescription):
        raise TypeError(f"robot must be a RobotDescription, got {type(robot).__name__}")
    if not isinstance(obstacles, Obstacles):
        raise TypeError(f"obstacles must be an Obstacles, got {type(obstacles).__name__}")
    if robot.nv != model.nv:
        raise ValueError(f"robot was described from a model of {robot.nv} dofs, this one has {model.nv}: describe "
                         "this model")  # fmt: skip
    if config.points == "ee" and robot.site_id < 0:
        raise UnsupportedModelError("points='ee' protects the tool site, and the robot has none: pass site= to "
                                    "RobotDescription.from_model")  # fmt: skip
    if config.weight == "tool" and robot.site_id < 0:
        raise UnsupportedModelError("weight='tool' weighs the tool site's acceleration, and the robot has none: pass "
                                    "site= to RobotDescription.from_model, or choose weight='limits'")  # fmt: skip
    if envelope is not None and not isinstance(envelope, FilterEnvelope):
        raise TypeError(f"envelope must be a FilterEnvelope or None, got {type(envelope).__name__}")
    return config


def _new_tally(barrier, n: int, max_rows: int, timestep: float) -> _step.Tally:
    """The report's running values, in compiled code (:func:`_step.record`): with the barrier's
    gain and the largest it may rise to (:func:`_step.beyond_allowance`; a barrier without a gain
    gets no allowance)."""
    gain = getattr(barrier, "gamma", None)
    limit_gain = RAISED_GAIN_STEP / timestep
    gains = np.array([gain if isinstance(gain, float) else limit_gain, limit_gain])
    return _step.Tally(np.zeros(_step.TALLY_SIZE), np.zeros(n), np.zeros(n), np.zeros(4), np.zeros(max_rows), gains)


class SafetyController:
    """The safety filter on any MuJoCo arm, without Gymnasium: nominal torque in, safe torque out.

    Build it once per ``(model, data)``; then, at every physics step, after ``mj_step1`` (or
    ``mj_forward``) and with the obstacles current::

        controller = SafetyController(model, data, robot, obstacles, FilterConfig())
        tau, report = controller.filter(tau_nom)
        robot.write_ctrl(model, data, tau)   # gear, actuator order, gravity compensation
        mujoco.mj_step2(model, data)

    Args:
        model, data: the MuJoCo model and the data the filter reads (it never writes to it).
        robot: the arm (:class:`~c3bf_gym.safety.RobotDescription`).
        obstacles: the spheres to keep off the arm (:class:`~c3bf_gym.safety.Obstacles`); their
            ``refresh(data)`` runs before every call.
        config: the filter's settings (:class:`FilterConfig`; None: the default). A
            ``sensing_radius`` of None senses every active obstacle (``sensing_radius`` below).
        arm: an :class:`~c3bf_gym.safety.dynamics.ArmModel` of ``robot`` to share with other controllers
            (None: a new one).
        sensing_radius: the sensing radius [m] used when ``config.sensing_radius`` is None
            (default: inf, every active obstacle).
        envelope: the :class:`~c3bf_gym.safety.FilterEnvelope` :meth:`filter` checks the
            obstacles against (None: computed by :meth:`compute_envelope`, without a keep-out
            region, when :meth:`filter` first sees an obstacle, if the sensing radius is finite).

    The torque passed in and returned is the total joint torque [N m] (n,), in dof order, with
    the limits ``robot.torque_limit``. The fused kernel computes the C3BF's, the distance
    HOCBF's and a distance-HOCBF guard's rows itself, at either kind of protected points; any
    other barrier or guard takes the per-class path (``Barrier.terms``), the extension point for
    barriers the kernel does not know. ``min_h`` in the report is the barrier's, not the guard's.

    Warns:
        :class:`~c3bf_gym.safety.EnvelopeWarning`: a timestep too coarse for the filter's gains
            (:data:`MAX_GAIN_STEP`); from :meth:`filter`, once, obstacles outside :attr:`envelope`.
        :class:`~c3bf_gym.safety.UnprotectedGeometryWarning`: a protected geom in contact, at
            ``data``'s joint positions, with a geom of the same arm that no row keeps it from
            (its base, or geometry the filter does not protect), naming both.

    Raises:
        ValueError / :class:`~c3bf_gym.safety.UnsupportedModelError`: a config that needs what
            the robot lacks (joint limits, a tool site for ``points="ee"`` or ``weight="tool"``).

    Attributes:
        config: the settings it was built with.
        envelope: the :class:`~c3bf_gym.safety.FilterEnvelope` the obstacles are checked against
            (None until given, computed or first needed).
        report: the :class:`StepSafety` accumulated since :meth:`begin_step`.
        joint_limits: the :class:`~c3bf_gym.safety.barriers.JointLimits` whose rows the filter
            adds (None without ``config.joint_limits``); its ``qd_max`` is the nominal torque's
            speed bound (``config.nominal_speed_fraction``, else the filter's).
        joint_speed_bound: (n,) the speed bound the filter holds every joint to [rad/s]:
            ``config.joint_speed_fraction`` of the robot's own (None without joint limits).
        last: the last call's :class:`~c3bf_gym.safety.priority_qp.QPResult` (None before the first).
        solve_times: when a list (set ``record_times=True``), every call's wall time [s] is
            appended, for latency percentiles.
    """

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, robot: RobotDescription, obstacles: Obstacles,
                 config: FilterConfig | None = None, *, arm: ArmModel | None = None,
                 sensing_radius: float = np.inf, envelope: FilterEnvelope | None = None) -> None:
        config = _checked_arguments(model, robot, obstacles, config, envelope)
        self.model, self.data, self.robot, self.obstacles = model, data, robot, obstacles
        self._M_diagonal = int(model.M_rowadr[0] + model.M_rownnz[0] - 1)  # M[0, 0] in data.M's CSR layout
        self._refresh = type(obstacles).refresh is not Obstacles.refresh
        self._distances = obstacles.distances if obstacles.distances is not None else np.zeros((obstacles.capacity, 0))
        self.config = config
        self.barrier = barrier = config.barrier_object()
        self.guard = guard = config.guard_object()
        self.points = points = config.points
        self.margin = config.margin
        self.sensing_radius = float(sensing_radius) if config.sensing_radius is None else config.sensing_radius
        self.ee_radius = config.ee_radius
        self.on_infeasible = config.on_infeasible
        self.intervention_tol = config.intervention_tol
        self.envelope = envelope
        self._envelope_seen = (0.0, 0.0)  # the largest obstacle speed and radius checked so far
        self._envelope_active = np.zeros(obstacles.capacity, dtype=bool)  # the slots active at the last check
        self._envelope_warned = False
        joint_limits = None
        reserve = speed_reserve = None
        self.joint_speed_bound: np.ndarray | None = None
        if config.joint_limits:
            robot.require_joint_limits(model)
            q_lo, q_hi = robot.joint_range.T
            if config.joint_range_reserve > 0.0:
                # the position rows δ inside the range; the QP holds their copies at the range above them
                # (an infinite limit stays infinite: that side has no row to draw in)
                delta = np.minimum(config.joint_range_reserve, 0.25 * (q_hi - q_lo))
                q_lo, q_hi = q_lo + delta, q_hi - delta
            bound = config.joint_speed_fraction * robot.joint_speed_limit
            nominal = bound
            if config.nominal_speed_fraction is not None:
                nominal = config.nominal_speed_fraction * robot.joint_speed_limit
            joint_limits = JointLimits(q_lo, q_hi, nominal)
            if config.joint_range_reserve > 0.0:
                gain_1, gain_2, _ = joint_limits.gains
                reserve = np.concatenate([gain_1 * gain_2 * delta] * 2)  # b lowered by γ₁γ₂δ: the row at the range
            if np.any(nominal < bound):
                # the speed rows at the nominal bound; b lowered by γ_v (bound − nominal): their copies at the bound
                speed_reserve = np.concatenate([joint_limits.gains[2] * (bound - nominal)] * 2)
            self.joint_speed_bound = bound
        self.joint_limits = joint_limits
        self._check_timestep(model.opt.timestep)
        weight = config.weight
        self.arm: ArmModel = ArmModel(model, robot.geom_ids, robot.site_id, robot.capsules) if arm is None else arm
        if not np.array_equal(self.arm.capsule_ids, robot.geom_ids):
            raise ValueError(f"arm protects geoms {self.arm.capsule_ids.tolist()}, the robot {robot.geom_ids.tolist()}: "
                             "share an ArmModel built from this robot")  # fmt: skip
        n = robot.n
        limit = np.array(robot.torque_limit)
        # rows per sensed obstacle: one per protected point, and its guard's
        points_count = len(self.arm.capsule_ids) if points == "whole_arm" else 1
        self._per_obstacle = points_count * (1 if guard is None else 2)
        n_obstacles = obstacles.capacity
        self._n_joint_rows = 0 if joint_limits is None else 4 * n
        #: the floor's rows (:class:`~c3bf_gym.safety.barriers.Floor`; none without a floor plane)
        self.floor = Floor.of_model(model, self.arm, self.margin, config.floor_gamma)
        #: the rows of the arm's own capsule pairs (:class:`~c3bf_gym.safety.barriers.SelfCollision`;
        #: none without ``config.self_collision`` or when the model lets no two of them collide)
        self.self_collision = (SelfCollision.of_model(model, self.arm, self.margin, config.floor_gamma)
                               if config.self_collision else SelfCollision((), (), config.floor_gamma))  # fmt: skip
        self._n_fixed_rows = self.floor.n_rows + self.self_collision.n_rows + self._n_joint_rows
        self._check_resting_contacts(model, data)
        self._stride = 1 if guard is None else 2  # obstacle rows: barrier, guard, barrier, guard, ...
        # priority 2 (giving way first) only for the barrier's rows beside a guard: without one, the
        # barrier's rows are the only ones keeping obstacles off, and they share priority 1 with the
        # joint limits and the floor
        barrier_rows = n_obstacles * points_count if guard is not None else 0
        max_rows = n_obstacles * self._per_obstacle + self._n_fixed_rows
        # The QP runs in normalised torque u = τ / s with s = τ_max ("limits" and "tool": W = diag(1/τ_max²)
        # becomes the identity, box ±1) or s = 1 ("identity"): a well-conditioned problem either way. The
        # "tool" metric adds KᵀK, K = G/a in u, to the identity, its 3 rows written at every call (_step.tool_metric).
        self._scale = np.ones(n) if weight == "identity" else limit.copy()
        tool_acceleration = config.resolved_tool_acceleration()
        self._tool_weight = 0.0 if tool_acceleration is None else 1.0 / tool_acceleration
        self.qp = PriorityQP(n, -limit / self._scale, limit / self._scale, max_rows - barrier_rows, barrier_rows,
                             reserve, config.allowance_level and barrier_rows > 0, speed_reserve,
                             metric_rows=3 if weight == "tool" else 0)
        self._limit = limit
        # rows on the generalised force of every dof (the QP reads the arm's columns, self._dofs)
        self._A = np.zeros((max_rows, model.nv))
        self._b = np.zeros(max_rows)
        self._dofs = np.asarray(robot.dof_ids, dtype=np.int64)
        self._qpos_ids = np.asarray(model.jnt_qposadr[model.dof_jntid[robot.dof_ids]], dtype=np.int64)
        self._unmodelled = np.ascontiguousarray(robot.unmodelled_force, dtype=np.float64)
        self._capsule_radius = self.arm.capsule_radius
        self._fused, self._params, self._obstacle_arrays = self._kernel_settings(barrier, guard, joint_limits)
        self._tally = _new_tally(self.barrier, n, max_rows, model.opt.timestep)
        self._solve_time = 0.0
        self.begin_step()
        self._bound: tuple = ()  # filter_substep's arguments after the first three (_bind)
        self._filter_substep: tuple | None = None  # what __call__ calls (_substep_entry)
        self._last_time: float | None = None  # the last recorded call's wall time [s] (None: no call yet)
        self.solve_times: list[float] | None = None

    def _kernel_settings(self, barrier, guard, joint_limits: JointLimits | None) -> tuple[bool, _rows.RowParams, _rows.ObstacleArrays]:
        """Whether the fused kernel computes the rows, and its settings and obstacles
        (:func:`c3bf_gym.safety._rows.filter_rows`, sharing the barrier classes' per-point code).
        It does for the built-in barriers (their ``fused_spec``) with a distance-HOCBF guard or
        none, whatever the protected points (``"whole_arm"`` or ``"ee"``). Any other barrier or
        guard (a user's own :class:`~c3bf_gym.safety.barriers.Barrier`) goes through
        ``Barrier.terms`` / ``rows_from_terms`` (:meth:`rows`), the extension point for rows the
        kernel does not know."""
        n, obstacles = self.robot.n, self.obstacles
        spec = getattr(barrier, "fused_spec", None)
        spec = spec() if spec is not None else None
        guard_gains = _rows.GuardGains(False, 0.0, 0.0)
        if guard is not None:
            guard_spec = guard.fused_spec() if hasattr(guard, "fused_spec") else None
            if guard_spec is not None and guard_spec.kind == _rows.HOCBF_KIND:
                guard_gains = _rows.GuardGains(True, guard_spec.gamma1, guard_spec.gamma)
            else:
                spec = None
        if joint_limits is not None:
            jl = [np.array(joint_limits.gains, dtype=np.float64), joint_limits.q_lo, joint_limits.q_hi,
                  joint_limits.qd_max]
        else:
            jl = [np.ones(3), np.zeros(n), np.ones(n), np.ones(n)]
        joint_gains, q_lo, q_hi, qd_max = (np.ascontiguousarray(x, dtype=np.float64) for x in jl)
        row_params = _rows.RowParams(
            barrier=spec if spec is not None else _rows.BarrierGains(-1, 0.0, 0.0, 0.0, 0.0), guard=guard_gains,
            points=_rows.EE_POINTS if self.points == "ee" else _rows.WHOLE_ARM_POINTS,
            ee_radius=float(self.ee_radius), sensing_radius=float(self.sensing_radius), margin=float(self.margin),
            floor_gamma=self.floor.gamma, floor_ends=self.floor.ends, floor_min=self.floor.min_height,
            self_pairs=self.self_collision.pairs, self_min=self.self_collision.min_distance,
            fixed_capsules=self.self_collision.fixed_capsules, fixed_ends=self.self_collision.fixed_ends,
            fixed_min=self.self_collision.fixed_min,
            joint_rows=joint_limits is not None, joint_gains=joint_gains, q_lo=q_lo, q_hi=q_hi, qd_max=qd_max,
            dofs=self._dofs, qpos_ids=self._qpos_ids, unmodelled_force=self._unmodelled,
        )
        obstacle_arrays = _rows.ObstacleArrays(obstacles.active, self._distances, obstacles.position,
                                               obstacles.velocity, obstacles.acceleration, obstacles.radius)
        return spec is not None, row_params, obstacle_arrays

    def __getstate__(self) -> dict:
        """Pickled without what :meth:`_bind` gathered (views of this process's arrays, a compiled
        entry point and a handle of their addresses): the unpickled hook binds again on its first
        call, to its own env's arrays."""
        state = self.__dict__.copy()
        state.update(_bound=(), _filter_substep=None, _last_time=None)  # the copy's QP is new: no last call
        return state

    def _version(self) -> int | None:
        """A number that changes whenever ``data`` moves to a new state, for the arm model's
        per-state cache; None: unknown, so every call recomputes the dynamics."""
        return None

    def _clearance(self) -> np.ndarray:
        """(K,) each obstacle's smallest signed surface distance to the arm [m], for sensing: the
        obstacles' own ``distances`` when they keep them, else to the protected geoms."""
        if self.obstacles.distances is not None:
            return self.obstacles.distances.min(axis=1)
        a, b = self.arm.capsule_segments(self.data)
        closest = segment_closest_points(a, b, self.obstacles.position)  # (K, S, 3)
        gap = np.linalg.norm(self.obstacles.position[:, None] - closest, axis=2) - self.arm.capsule_radius
        return gap.min(axis=1) - self.obstacles.radius

    def filter(self, tau_nom: np.ndarray) -> tuple[np.ndarray, StepSafety]:
        """The safe torque for the current state of ``data`` and the obstacles, and the report of
        this one call (:class:`StepSafety`): :meth:`begin_step`, then :meth:`__call__`.

        Args:
            tau_nom: (n,) the nominal total joint torque [N m].

        Returns:
            ``(tau, report)``: tau (n,) [N m], within ``robot.torque_limit``.

        ``data`` must hold the state's kinematics and dynamics (``mj_step1`` or ``mj_forward`` since
        the state was last set): the filter reads them, it does not compute them.

        Warns:
            EnvelopeWarning: once per controller, an active obstacle faster or larger than
                :attr:`envelope` covers, or one that became active closer to the arm than the
                sensing range its speed needs (:meth:`FilterEnvelope.min_sensing_range
                <c3bf_gym.safety.FilterEnvelope.min_sensing_range>`: the envelope's escape argument
                assumes every obstacle is first sensed that far out); :attr:`envelope` is
                computed the first time an obstacle is active when none was given. Not with an
                infinite sensing radius.

        Raises:
            ValueError: ``tau_nom`` of the wrong shape, or with NaN or inf.
            RuntimeError: ``data`` has no mass matrix yet (a fresh or reset ``MjData`` before
                ``mj_forward``); nothing is computed.
            SafetyInfeasibleError: with ``on_infeasible="raise"``, when no torque within the
                limits satisfies every row.
        """
        if not self.data.M[self._M_diagonal] > 0.0:
            raise RuntimeError("data holds no dynamics yet (its mass matrix is zero): call mujoco.mj_forward(model, "
                               "data) or mujoco.mj_step1(model, data) before filter()")  # fmt: skip
        self.begin_step()
        tau = self(tau_nom)
        if not self._envelope_warned:
            self._check_envelope()
        return tau, self.report

    def compute_envelope(self, obstacle_radius: float | None = None, *, keep_out_radius: float = 0.0,
                         keep_out_height: float = 0.0, configurations: int = 128, seed: int = 0) -> FilterEnvelope:
        """The envelope this filter states for its robot (:func:`~c3bf_gym.safety.filter_envelope`
        with this controller's model, robot, config and sensing radius, and ``data``'s
        configuration among the sample), kept as :attr:`envelope`, which :meth:`filter` checks.

        Args:
            obstacle_radius: the largest obstacle radius [m] (None: the largest of the obstacles'
                ``radius``).
            keep_out_radius, keep_out_height, configurations, seed: as
                :func:`~c3bf_gym.safety.filter_envelope`'s.

        Raises:
            ValueError: the sensing radius is infinite (every obstacle is sensed wherever it is:
                an envelope needs a sensing radius), or as :func:`~c3bf_gym.safety.filter_envelope`.
        """
        radius = float(self.obstacles.radius.max(initial=0.0)) if obstacle_radius is None else obstacle_radius
        qpos = self.data.qpos[self._qpos_ids]
        self.envelope = filter_envelope(self.model, self.robot, self.config, obstacle_radius=radius,
                                        sensing_radius=self.sensing_radius, keep_out_radius=keep_out_radius,
                                        keep_out_height=keep_out_height, configurations=configurations,
                                        qpos=qpos if np.isfinite(qpos).all() else None, seed=seed)  # fmt: skip
        self._envelope_seen = (0.0, 0.0)
        return self.envelope

    def _check_envelope(self) -> None:
        """Warn once (:class:`~c3bf_gym.safety.EnvelopeWarning`) when an active obstacle is faster
        or larger than :attr:`envelope` covers at this sensing radius, or when an obstacle became
        active (since the last call) inside the sensing range its speed needs; the envelope is
        computed (no keep-out region) the first time an obstacle is active, if none was given. A
        speed and radius no larger than ones already checked are not checked again."""
        obstacles = self.obstacles
        appeared = obstacles.active & ~self._envelope_active
        np.copyto(self._envelope_active, obstacles.active)
        active = np.flatnonzero(obstacles.active)
        if not len(active) or not math.isfinite(self.sensing_radius):
            return
        speed = float(np.sqrt((obstacles.velocity[active] ** 2).sum(axis=1).max()))
        radius = float(obstacles.radius[active].max())
        faster = speed > self._envelope_seen[0] or radius > self._envelope_seen[1]
        if not faster and not appeared.any():
            return
        if self.envelope is None:
            self.compute_envelope(radius)
        problems = []
        if faster:
            self._envelope_seen = (max(speed, self._envelope_seen[0]), max(radius, self._envelope_seen[1]))
            problems = self.envelope.problems(speed, radius, self.sensing_radius)
        if appeared.any():
            problems += self._appeared_inside(np.flatnonzero(appeared))
        if problems:
            self._envelope_warned = True
            warnings.warn(EnvelopeWarning("the obstacles are outside the filter's envelope, where it guarantees "
                                          "nothing: " + "; ".join(problems)), stacklevel=3)  # fmt: skip

    def _appeared_inside(self, slots: np.ndarray) -> list[str]:
        """Why each obstacle of ``slots``, just become active, is outside :attr:`envelope`: its
        surface closer to the arm than the sensing range its speed needs (one sentence each)."""
        gaps = self._clearance()
        out = []
        for k in slots:
            if gaps[k] >= self.sensing_radius:
                continue  # sensed later, from the sensing radius in: the speed check covers it
            speed = float(np.linalg.norm(self.obstacles.velocity[k]))
            needed = self.envelope.min_sensing_range(speed)
            if gaps[k] < needed:
                out.append(f"obstacle {k} appeared {gaps[k]:.3g} m from the arm, moving at {speed:.3g} m/s, and the "
                           f"envelope's escape argument needs it sensed {needed:.3g} m out or farther")
        return out

    def _check_resting_contacts(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Warn (:class:`~c3bf_gym.safety.UnprotectedGeometryWarning`) for each protected geom in
        contact, at ``data``'s joint positions, with a geom of the arm's own kinematic tree that
        no row keeps it from (a base, a geom the filter does not protect): their contact forces
        are not in the rows' model, and nothing the filter does keeps them apart. Contacts are
        MuJoCo's own (``mj_forward`` on a copy of the positions; ``data`` is not written)."""
        scratch = mujoco.MjData(model)
        scratch.qpos[:] = data.qpos
        scratch.mocap_pos[:] = data.mocap_pos
        scratch.mocap_quat[:] = data.mocap_quat
        mujoco.mj_forward(model, scratch)
        protected = {int(g): k for k, g in enumerate(self.arm.capsule_ids)}
        rows = self.self_collision
        paired = {frozenset(map(int, pair)) for pair in rows.pairs}
        paired |= {frozenset((int(k), ~int(g))) for k, g in zip(rows.fixed_capsules, rows.fixed_geoms)}
        root = model.body_rootid[model.geom_bodyid[int(self.arm.capsule_ids[0])]]
        seen = set()
        for contact in scratch.contact[: scratch.ncon]:
            g1, g2 = int(contact.geom1), int(contact.geom2)
            for mine, other in ((g1, g2), (g2, g1)):
                if mine not in protected or model.body_rootid[model.geom_bodyid[other]] != root:
                    continue
                partner = protected[other] if other in protected else ~other  # (a fixed part: ~geom)
                if frozenset((protected[mine], partner)) in paired:
                    continue  # a row of its own pushes them apart
                key = frozenset((mine, other))
                if key in seen:
                    continue
                seen.add(key)
                bodies = (model.body(model.geom_bodyid[mine]).name, model.body(model.geom_bodyid[other]).name)
                names = (model.geom(mine).name, model.geom(other).name)
                warnings.warn(UnprotectedGeometryWarning(
                    f"geom {names[0]!r} touches geom {names[1]!r} of the same arm (contact distance "
                    f"{contact.dist:.3g} m at the joint positions the filter was built at): their contact forces "
                    "are not in the filter's model (its joint rows see only the last physics step's) and no row "
                    "keeps them apart, so they can push the arm past its rows; if the contact is an artefact of the "
                    "collision geometry, exclude it in the model "
                    f"(<contact><exclude body1=\"{bodies[0]}\" body2=\"{bodies[1]}\"/></contact>)"), stacklevel=3)

    def _check_timestep(self, timestep: float) -> None:
        """Warn when a row's gain times ``timestep`` exceeds :data:`MAX_GAIN_STEP`."""
        gains = {"floor_gamma": self.config.floor_gamma}
        for label, barrier in (("the barrier", self.barrier), ("the guard", self.guard)):
            for attribute in ("gamma", "gamma1", "gamma2"):
                value = getattr(barrier, attribute, None) if barrier is not None else None
                if isinstance(value, float):
                    gains[f"{label}'s {attribute}"] = value
        if self.joint_limits is not None:
            gains.update(zip(("the joint limits' gamma1", "the joint limits' gamma2", "the joint limits' gamma_v"),
                             self.joint_limits.gains))
        name, gain = max(gains.items(), key=lambda item: item[1])
        if gain * timestep > MAX_GAIN_STEP:
            warnings.warn(EnvelopeWarning(
                f"the physics timestep {timestep:g} s is too coarse for the filter's gains: {name} = {gain:g} 1/s "
                f"gives gain x timestep = {gain * timestep:.3g} > {MAX_GAIN_STEP} (MAX_GAIN_STEP); the rows hold at "
                f"the start of each step and may give way within it. Use a timestep <= {MAX_GAIN_STEP / gain:.3g} s "
                "or lower gains"), stacklevel=3)  # fmt: skip

    def record_times(self, enabled: bool = True) -> None:
        """Start (or stop) keeping every physics step's filter time in ``solve_times``. While on,
        every call comes through :meth:`__call__` and is timed (not inside an environment's
        compiled policy step, :meth:`compiled_call`): the same torques, more Python per call."""
        self.solve_times = [] if enabled else None

    def reset(self) -> None:
        """Start a new episode: the QP forgets its warm start (:meth:`PriorityQP.reset`), so a
        seeded episode gives the same torques, bit for bit, whatever ran before it."""
        self.qp.reset()

    def begin_step(self) -> None:
        """Start a new policy step's report."""
        np.copyto(self._tally.values, _step.TALLY_START)
        self._solve_time = 0.0

    def rows(self) -> tuple[np.ndarray, np.ndarray, float, bool, int]:
        """Assemble the rows for the current state: (A, b, min h, any inside, sensed count)."""
        arm, obstacles, data = self.arm, self.obstacles, self.data
        if self._refresh:
            obstacles.refresh(data)
        if self._fused:
            m, min_h, inside, n_sensed = _rows.filter_rows(
                arm.claim(data, self._version()), arm.kernel_arrays(data), self._obstacle_arrays, self._params,
                self._A, self._b, self._tally.row_h)
            return self._A[:m], self._b[:m], min_h, inside, n_sensed
        arm.update(data, self._version())
        sensed = np.flatnonzero(obstacles.active & (self._clearance() <= self.sensing_radius))
        m = 0
        min_h, inside = np.inf, False
        if len(sensed):
            centres = obstacles.position[sensed]
            radius = obstacles.radius[sensed]
            if self.points == "whole_arm":
                # The closest points slide along the links as things move, so their ḣ has the
                # terms ⟨∂h/∂p, ṗ_slide⟩ + ⟨∂h/∂v, v̇_slide⟩ besides the material point's; without
                # them ḣ is overestimated and links drift into obstacles (ArmModel.closest_sliding).
                # closest_relative puts v̇_slide into c and returns ṗ_slide.
                rel, slide_p = arm.closest_relative(centres, obstacles.velocity[sensed], obstacles.acceleration[sensed])
                p, v, G, c = rel.pos, rel.vel, rel.G, rel.c
                r = radius[:, None] + self._capsule_radius
                r += self.margin
                r = r.reshape(-1)
            else:
                site = arm.site_dynamics(data)
                p = site.pos - centres
                v = site.vel - obstacles.velocity[sensed]
                c = site.c - obstacles.acceleration[sensed]
                G = np.broadcast_to(site.G, (len(sensed),) + site.G.shape[1:])
                r = radius + self.ee_radius
                r += self.margin
            # one row per point, followed (as in the fused kernel) by the guard's row for that point
            barriers = (self.barrier,) if self.guard is None else (self.barrier, self.guard)
            for i, barrier in enumerate(barriers):
                terms = barrier.terms(p, v, r)
                rows = barrier.rows_from_terms(terms, G, c)
                if self.points == "whole_arm":
                    rows.b[:] -= np.vecdot(terms.grad_p, slide_p)
                self._A[i:len(barriers) * len(p):len(barriers)] = rows.A
                self._b[i:len(barriers) * len(p):len(barriers)] = rows.b
                if i == 0:
                    self._tally.row_h[: len(barriers) * len(p) : len(barriers)] = terms.h
                    min_h = float(terms.h.min())
                    inside = bool(terms.inside.any())
            m = len(barriers) * len(p)
        if self.floor.n_rows or self.self_collision.n_rows:
            arm.end_dynamics()  # refreshes the packed capsule ends (arm._ends) if stale
            m += len(self.floor.rows(arm._ends, Rows(self._A[m:], self._b[m:])).b)
            m += len(self.self_collision.rows(arm._ends, Rows(self._A[m:], self._b[m:])).b)
        _rows.unmodelled_margin(self._A[:m], self._b[:m], self._unmodelled)
        if self.joint_limits is not None:
            _dynamics.joint_drift(arm.Minv, arm.qacc_free, arm.views(data).qfrc_constraint, arm.qacc_joint)
            self.joint_limits.rows(data.qpos, data.qvel, arm.Minv, arm.qacc_joint, out=Rows(self._A[m:], self._b[m:]),
                                   dofs=self._dofs, qpos_ids=self._qpos_ids)
            m += self._n_joint_rows
        return self._A[:m], self._b[:m], min_h, inside, len(sensed)

    def _bind(self) -> tuple:
        """The buffers :func:`c3bf_gym.safety._step.filter_substep` works in (env, arm, hook, QP and
        tally; all allocated once by their constructors and updated in place) and the intervention
        tolerance, gathered once: fetching them attribute by attribute on every call cost more than
        the kernel's dispatch."""
        self._bound = _step.StepBuffers(self.arm.kernel_arrays(self.data), self._obstacle_arrays, self._params,
                                        self._A, self._b, self._scale, self._limit, self.qp.buffers, self._tally,
                                        float(self.intervention_tol), self._tool_weight)
        self._filter_substep = None  # its entry point and handle, if any, were for the buffers before
        return self._bound

    def _substep_entry(self) -> tuple:
        """What :meth:`__call__` calls: a compiled entry point and its arguments after the first three,
        and the structure they point into (kept with them: the handle borrows its memory).

        Normally the entry point of :func:`~c3bf_gym.safety._step.filter_substep_at` for exactly
        :meth:`_bind`'s buffers, with their handle (:func:`c3bf_gym._capi.pack`) and numba type:
        one array crosses into compiled code instead of every buffer, which numba would convert
        one by one (the speed page). When the buffers include an array ``pack`` cannot describe
        (obstacle arrays given as strided views of a simulator's state), the entry point of
        :func:`~c3bf_gym.safety._step.filter_substep` itself, with the buffers: the same torques.
        Called directly, an entry point skips the dispatcher's type resolution. The types are
        fixed: fresh C-contiguous float64 (n,) arrays tau_nom and tau (:meth:`__call__` checks the
        shape: the entry point takes any array as the type it was compiled for) and a Python int
        stage. Compiled on the first call from Python, not when binding: an environment that calls
        the kernel from its own compiled step never needs it (and compiling it costs seconds on an
        empty cache)."""
        vec = np.zeros(len(self._limit))
        bound = self._bound or self._bind()
        try:
            arguments = (pack(bound), numba.typeof(bound))
            kernel = _step.filter_substep_at
        except ValueError:  # an array pack() cannot describe
            arguments, kernel = (bound,), _step.filter_substep
        entry = kernel.compile(tuple(numba.typeof(a) for a in (0, vec, vec, *arguments)))
        self._filter_substep = (entry, arguments, bound)
        return self._filter_substep

    def compiled_call(self, version: int) -> FilterCall | None:
        """This filter for a simulator that calls it from its own compiled loop
        (:mod:`c3bf_gym.safety.substep`, whose protocol this is; ``C3BFReachEnv`` does), for one
        policy step starting from the state ``version``: a :class:`~c3bf_gym.safety.substep.FilterCall`
        with the buffers, the first call's stage and whether an infeasible call must stop the
        loop (``on_infeasible="raise"``). None when every call must come through
        :meth:`__call__`: the per-class rows, obstacles that refresh themselves, or timings being
        recorded (:meth:`record_times`).

        The calls in the loop write the arm's dynamics arrays, so the arm caches no state after
        it: the next call, compiled or not, computes its state's dynamics afresh. They are not
        timed: :attr:`report`'s ``solve_time`` and :attr:`last`'s are NaN for this policy step."""
        if not self._fused or self._refresh or self.solve_times is not None:
            return None
        bound = self._bound or self._bind()
        stage = self.arm.claim(self.data, version)
        self.arm.forget()
        self._solve_time = self._last_time = np.nan
        return FilterCall(bound, stage, self.on_infeasible == "raise")

    def failure(self, status: int) -> Exception | None:
        """The exception a call's ``status`` calls for, to be raised by the caller, or None:
        ``ValueError`` for invalid input (< 0: a non-finite torque, state or obstacle), and with
        ``on_infeasible="raise"`` :class:`SafetyInfeasibleError` for a call with no safe torque
        (> 0; its report recorded), naming the largest violation of each row kind."""
        if status < 0:
            return bad_input_error(status)
        if status != _qp.SOLVED and self.on_infeasible == "raise":
            values = self._tally.values
            violation = dict(zip(ROW_KINDS, values[_step.T_VIOLATION:].tolist()))
            return SafetyInfeasibleError(
                f"no torque within the limits satisfies the safety rows (status {STATUS[status]!r}, largest "
                f"violation by kind {self._violation_text(violation)}, min h {values[_step.T_MIN_H]:.3g}); pass "
                "on_infeasible='relax' to let the rows give way by priority instead"
            )
        return None

    def __call__(self, tau_nom: np.ndarray) -> np.ndarray:
        """The safe torque (n,) [N m] for ``tau_nom`` (n,) [N m], the report accumulating into
        :attr:`report` (the torque-hook protocol; :meth:`filter` for one call's own report).
        Raises as :meth:`filter` does."""
        start = _perf_counter()
        # a copy of the caller's torque (float64; 1-D copies are contiguous), which the kernels read.
        # Its shape is checked here: the compiled entry point (_substep_entry) cannot.
        tau_nom = np.array(tau_nom, np.float64)
        shape = self._limit.shape
        if tau_nom.shape != shape:
            raise ValueError(f"tau_nom must have shape {shape}, got {tau_nom.shape}")
        tau = np.empty(shape)
        if self._fused:
            if self._refresh:
                self.obstacles.refresh(self.data)
            substep, arguments, _ = self._filter_substep or self._substep_entry()
            status = substep(self.arm.claim(self.data, self._version()), tau_nom, tau, *arguments)
        else:
            A, b, min_h, inside, n_sensed = self.rows()
            m = len(b)
            qp = self.qp.buffers
            if self.qp.metric_rows:
                _step.tool_metric(self.arm.site_dynamics(self.data).G[0], self._dofs, self._scale, self._tool_weight,
                                  qp.metric)  # fmt: skip
            status, iterations, active, slack = _step.solve_call(tau_nom, A, b, self._scale, self._dofs,
                                                                 self._layout(m), self._tally, qp)  # fmt: skip
            if status >= 0:
                # τ = u s, the smallest row residual A τ − b and ‖τ − clip(τ_nom)‖ (the filter's change)
                residual, correction = _step.hook_post(b, qp.norm[:m], qp.residual[:m], qp.u, self._scale, tau_nom,
                                                       self._limit, tau)
                status = self._record(status, m, min_h, inside, n_sensed, iterations, active, slack, residual,
                                      correction, tau_nom, tau)
        elapsed = _perf_counter() - start
        if status >= 0:
            self._solve_time += elapsed
            if self.solve_times is not None:
                self.solve_times.append(elapsed)
        self._settle(status, elapsed)
        return tau

    def _record(self, status: int, m: int, min_h: float, inside: bool, n_sensed: int, iterations: int, active: int,
                slack: float, residual: float, correction: float, tau_nom: np.ndarray, tau: np.ndarray) -> int:
        """Fold one solved call of :meth:`rows`' ``m`` rows into the report
        (:func:`c3bf_gym.safety._step.record`, with this filter's row layout; the fused kernel
        does the same in compiled code). Returns the status as the fused kernel does: a call
        that held every row with the barrier's gain raised as solved."""
        call = _step.CallSummary(status, m, min_h, inside, n_sensed, iterations, active, slack, residual, correction)
        outcome = _step.record(self._tally, call, tau_nom, tau, self.qp.buffers, self._layout(m), self.intervention_tol)
        return _qp.SOLVED if outcome == _step.GAIN_RAISED else outcome

    def _settle(self, status: int, elapsed: float) -> None:
        """After a call from Python with ``status``: raise on invalid input; keep the call's wall
        time ``elapsed`` for :attr:`last` (its other values are in the tally); with
        ``on_infeasible="raise"``, raise on a call with no safe torque (its report recorded
        first). :meth:`failure` is the exception."""
        error = self.failure(status)
        if status >= 0:
            self._last_time = elapsed
        if error is not None:
            raise error

    @property
    def last(self) -> QPResult | None:
        """The :class:`~c3bf_gym.safety.priority_qp.QPResult` of the last call that did not raise on
        invalid input (None before the first, and in a pickled copy, whose QP is new). Built at
        every read from what the call recorded: keep the object, not the attribute, to hold one
        call's values (its ``tau`` is the QP's buffer all the same). After compiled calls
        (:meth:`compiled_call`) ``solve_time`` is NaN: they are not timed."""
        if self._last_time is None:
            return None
        status, iterations, active, slack = self._tally.last.tolist()
        status = int(status)
        return QPResult(self.qp.buffers.u, slack, status in (_qp.SOLVED, _step.GAIN_RAISED), _STATUS[status],
                        int(iterations), int(active),
                        self._last_time)

    @property
    def report(self) -> StepSafety:
        """The :class:`StepSafety` of the calls since :meth:`begin_step` (a new object at every
        read: keep it, it does not follow later calls)."""
        values = self._tally.values.tolist()  # Python floats: one conversion, not one per entry
        substeps = int(values[_step.T_SUBSTEPS])
        infeasible = int(values[_step.T_INFEASIBLE_STEPS])
        return StepSafety(
            feasible=infeasible == 0, slack=values[_step.T_SLACK], min_h=values[_step.T_MIN_H],
            correction=values[_step.T_CORRECTION], active_rows=int(values[_step.T_ACTIVE_ROWS]),
            sensed=int(values[_step.T_SENSED]), solve_time=self._solve_time,
            intervened=bool(values[_step.T_INTERVENED]), inside=bool(values[_step.T_INSIDE]),
            infeasible_steps=infeasible, gain_raised_steps=int(values[_step.T_GAIN_RAISED_STEPS]),
            min_constraint=values[_step.T_MIN_CONSTRAINT], substeps=substeps,
            tau_nominal=self._tally.tau_nominal.copy() if substeps else None,
            tau=self._tally.tau.copy() if substeps else None,
            violation=dict(zip(ROW_KINDS, values[_step.T_VIOLATION:])),
        )

    def _n_obstacle_rows(self, m: int) -> int:
        """How many of :meth:`rows`' ``m`` rows are the obstacles' (the barrier's and the guard's):
        the rest are the floor's, the arm's own pairs' and the joint limits'."""
        return m - self._n_fixed_rows

    def _layout(self, m: int) -> _step.RowLayout:
        """Where each kind of row sits among :meth:`rows`' ``m`` rows (:class:`~c3bf_gym.safety._step.RowLayout`)."""
        return _step.RowLayout(self._n_obstacle_rows(m), self._stride, self.floor.n_rows, self.self_collision.n_rows)

    def _low_priority_span(self, m: int) -> int:
        """:func:`~c3bf_gym.safety._step.low_priority_span` of :meth:`rows`' ``m`` rows."""
        return _step.low_priority_span(m, self._n_fixed_rows, self.guard is not None)

    def row_kinds(self, m: int) -> list[str]:
        """The kind (:data:`ROW_KINDS`, "unmovable" aside) of each of :meth:`rows`' ``m`` rows."""
        kinds = ["barrier" if k % self._stride == 0 else "guard" for k in range(self._n_obstacle_rows(m))]
        return (kinds + ["floor"] * self.floor.n_rows + ["self_collision"] * self.self_collision.n_rows
                + ["joint_limits"] * self._n_joint_rows)

    @staticmethod
    def _violation_text(violation: dict[str, float]) -> str:
        return ", ".join(f"{kind} {value:.3g}" for kind, value in violation.items() if value > 0.0) or "none"
