"""The safety filter as a per-physics-step torque hook: barrier rows + joint limits -> QP.

At every physics step (``C3BFReachEnv`` calls the hook between ``mj_step1`` and ``mj_step2``):

1. the arm's dynamics at the protected points are refreshed (:class:`~c3bf_gym.robot.ArmModel`);
2. every *sensed* obstacle (active, surface within ``sensing_radius`` of the arm) contributes one
   row per protected point (``whole_arm``: the closest point of every link capsule, with the
   capsule radius added to the obstacle's; ``ee``: the tool site with ``ee_radius``), and with a
   ``guard`` one more, the guard barrier's, right after it. The C3BF bounds only the direction of
   approach: a link may graze an obstacle at speed, and from there, within the torque limits, it
   sometimes cannot turn away in time (8 of 2,400 adversarial episodes collided with the C3BF's
   rows alone, ``benchmarks/guarantee.py --guard none``). The distance HOCBF's rows (the default
   guard beside a C3BF, gains :data:`GUARD_GAMMA`) bound the approach speed by the distance left;
   with both, and the C3BF's rows giving way first when no torque satisfies every row
   (:data:`BARRIER_RELAXATION_WEIGHT`), none of 4,800 episodes collided (README, "The guarantee");
3. the floor contributes one row per capsule end (``2 S``): every capsule stays ``margin`` above
   it. The floor is the one fixed thing the arm can touch, and its contact forces are not in the
   filter's model (``ẍ = G τ + c``): a link pressed into it is pushed by an unmodelled force,
   which can drive another link through its obstacle row (found by a seed search: the tool
   touched the floor and link 5 hit an obstacle 0.19 s later, every QP solved);
4. joint position and velocity limits contribute ``4 n`` rows;
5. :class:`~c3bf_gym.qp.TorqueQP` returns the torque closest to the nominal one (weighted by
   ``W``) that satisfies all rows and the actuator limits, or reports that none does. Then it
   applies a repaired least-violating torque: only rows that conflict give way, each with its
   own slack; rows the conflict does not involve (e.g. the speed limit of an uninvolved joint)
   keep holding (:mod:`c3bf_gym.qp`, "Relaxation"). The joint, floor and guard rows weigh 1
   there, and so do the barrier's without a guard (with one: :data:`BARRIER_RELAXATION_WEIGHT`).
   Letting the speed rows give way first (obstacle rows weighted 30×) let joint speeds run to
   11× their limit, after which the cone rows alone had no solution and 3 of 20 random-torque
   multi episodes collided. The speed limits keep the cone rows satisfiable.

Steps 1–4 for ``whole_arm`` with the built-in barriers (:class:`~c3bf_gym.barriers.C3BF`,
:class:`~c3bf_gym.barriers.DistanceHOCBF`) are one compiled kernel,
:func:`c3bf_gym._kernels.hook_rows_whole_arm`, built from the same per-point functions the
barrier classes and :class:`~c3bf_gym.robot.ArmModel` call; other barriers (or ``points="ee"``)
go through ``Barrier.terms`` and ``rows_from_terms``. The barrier, ``margin``, ``sensing_radius``
and ``joint_limits`` are read when the hook is built. With the active-set QP, that kernel, the
QP's data step, fast path and active-set solves and the bookkeeping after them are one call too
(:func:`c3bf_gym._kernels.hook_step`: the rows kernel, then :func:`c3bf_gym._kernels.qp_step`, which
:meth:`TorqueQP.solve` runs too), not six compiled calls with Python between them as before (``PYTHONPATH=<tree> python benchmarks/filter_speed.py
--calls 3000 --obstacles 1 4 8 --no-throughput``, trees interleaved, 4 obstacles, median µs:
adversarial 42 / 42 before vs 33 / 36 fused, random 38 / 45 vs 30 / 28; noisy machine). Python
runs only what the active-set solver hands to proxsuite (rare).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal

import mujoco
import numba
import numpy as np

from c3bf_gym import _kernels
from c3bf_gym.barriers import BARRIERS, C3BF, Barrier, JointLimits, Rows, make_barrier
from c3bf_gym.qp import QPResult, TorqueQP
from c3bf_gym.robot import ArmModel

_perf_counter = time.perf_counter

__all__ = ["ON_INFEASIBLE", "POINTS", "WEIGHTS", "SafetyHook", "SafetyInfeasibleError", "StepSafety", "build_hook"]

POINTS = ("whole_arm", "ee")
ON_INFEASIBLE = ("relax", "raise")
WEIGHTS = ("limits", "identity")

#: UR5e joint speed limit, 180 deg/s on every joint (UR5e technical specifications).
UR5E_JOINT_SPEED = np.pi
#: Gain [1/s] of the floor rows' second-order barrier (both stages), as the joint position limits'.
FLOOR_GAMMA = 10.0
#: With a guard, the relaxation weight of the barrier's rows (every other row weighs 1): when no
#: torque satisfies every row, the C3BF's rows give way before the guard's, the floor's and the
#: joint limits'. Measured with the guard's first gains, 5 (``benchmarks/guarantee.py``, the README's
#: long sweeps, seeds 0–599; not re-measured with GUARD_GAMMA's 10):
#: against the adversary, with equal weights the guarded filter collided in 1 of 2,400 episodes
#: and came within 6–11 mm in four more; with 0.1, none collided and all but one kept 17.7 mm.
#: Random torques: 0 and 1 of 2,400 (README, "The long sweeps").
BARRIER_RELAXATION_WEIGHT = 0.1
#: The default guard's gains, γ₁ = γ₂ [1/s] of the distance HOCBF beside the C3BF (``guard="auto"``).
#: Measured against the first choice, the HOCBF's own default 5 (README, "The long sweeps" and
#: "Results: RL baselines"): over the 4,800 episodes of seeds 0–599 none collided with 10, one with
#: 5 (random torques, multi 66), and the adversary's lowest clearance was 17.8 mm against 1.6 mm;
#: agents trained under the filter reached 0.937 success against 0.886 (the C3BF alone: 0.952).
GUARD_GAMMA = 10.0


class SafetyInfeasibleError(RuntimeError):
    """Raised with ``on_infeasible="raise"`` when no torque within the limits satisfies the rows."""


@dataclass
class StepSafety:
    """What the filter did over one policy step (all its physics steps).

    Attributes:
        feasible: every physics step's QP was solved without slack.
        slack: the largest slack used [N m, row-normalised]; 0.0 when feasible.
        min_h: the smallest barrier value over the barrier's rows (not the guard's) and physics
            steps (inf with no row).
        correction: the largest ``‖τ − τ_nom‖`` [N m] (``τ_nom`` clipped to the torque limits,
            so plain saturation is not counted as a safety intervention).
        active_rows: the largest number of binding rows.
        sensed: the largest number of sensed obstacles.
        solve_time: mean wall time of the filter per physics step [s] (rows and QP).
        intervened: some physics step changed the torque by more than ``intervention_tol``.
        inside: some protected point was already inside an obstacle's (margin-inflated) radius.
        infeasible_steps: number of physics steps whose QP needed slack.
        min_constraint: the smallest row residual ``A τ − b`` at the applied torque (the QP
            constraint value: >= 0 when every row holds) [row units]; inf with no row.
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
    min_constraint: float = np.inf
    substeps: int = 0
    tau_nominal: np.ndarray | None = None
    tau: np.ndarray | None = None

    def as_info(self) -> dict[str, float | bool | int]:
        return {
            "feasible": self.feasible,
            "slack": self.slack,
            "min_h": self.min_h,
            "correction": self.correction,
            "active_rows": self.active_rows,
            "sensed": self.sensed,
            "solve_time": self.solve_time / max(self.substeps, 1),
            "intervened": self.intervened,
            "inside": self.inside,
            "infeasible_steps": self.infeasible_steps,
            "min_constraint": self.min_constraint,
        }


class SafetyHook:
    """The filter itself, installed as the env's ``filter`` torque hook.

    Args:
        env: the unwrapped :class:`~c3bf_gym.envs.C3BFReachEnv`.
        barrier: a :class:`~c3bf_gym.barriers.Barrier` (e.g. ``C3BF(gamma=5)``).
        points: ``"whole_arm"`` or ``"ee"``.
        margin: extra clearance added to every combined radius [m].
        sensing_radius: obstacles whose surface is farther than this from the arm add no row [m].
        ee_radius: radius of the protected sphere at the tool site with ``points="ee"`` [m].
        joint_limits: the joint-limit barrier (None: no joint rows).
        weight: ``"limits"`` (W = diag(1/τ_max²): relative changes weigh the same on every joint)
            or ``"identity"`` (the paper's plain ‖τ − τ_nom‖²).
        on_infeasible: ``"relax"`` (apply the least-violating torque and report it) or
            ``"raise"`` (raise :class:`SafetyInfeasibleError`).
        intervention_tol: ‖τ − τ_nom‖ above which a step counts as an intervention [N m].
        guard: a second barrier whose row for every (sensed obstacle, point) holds beside the
            first one's (None: none). The fused whole-arm kernel computes a
            :class:`~c3bf_gym.barriers.DistanceHOCBF` guard's rows itself; any other guard takes
            the per-class path. ``min_h`` in the report is the first barrier's.

    Attributes:
        solve_times: when a list (set ``record_times=True``), every physics step's filter wall
            time [s] is appended, for latency percentiles.
    """

    def __init__(
        self,
        env,
        barrier: Barrier,
        points: Literal["whole_arm", "ee"],
        margin: float,
        sensing_radius: float,
        ee_radius: float,
        joint_limits: JointLimits | None,
        weight: Literal["limits", "identity"],
        on_infeasible: Literal["relax", "raise"],
        intervention_tol: float = 1e-3,
        guard: Barrier | None = None,
    ) -> None:
        self.env = env
        self.barrier = barrier
        self.points = points
        self.margin = float(margin)
        self.sensing_radius = float(sensing_radius)
        self.ee_radius = float(ee_radius)
        self.joint_limits = joint_limits
        self.guard = guard
        self.on_infeasible = on_infeasible
        self.intervention_tol = float(intervention_tol)
        self.arm: ArmModel = env.arm
        n = env.model.nv
        limit = env.torque_limit
        # rows per sensed obstacle: one per protected point, and its guard's
        points_count = len(self.arm.capsule_ids) if points == "whole_arm" else 1
        self._per_obstacle = points_count * (1 if guard is None else 2)
        n_obstacles = len(env.obstacle_radius)
        self._n_joint_rows = 0 if joint_limits is None else 4 * n
        self._floor_ends, self._floor_min = self._floor_setup(env.model)
        self._n_floor_rows = len(self._floor_ends)
        max_rows = n_obstacles * self._per_obstacle + self._n_floor_rows + self._n_joint_rows
        # The QP runs in normalised torque u = τ / s with s = τ_max ("limits": W = diag(1/τ_max²)
        # becomes the identity, box ±1) or s = 1 ("identity"): a well-conditioned problem either way.
        self._scale = limit.copy() if weight == "limits" else np.ones(n)
        self.qp = TorqueQP(n, max_rows, -limit / self._scale, limit / self._scale)
        self._limit = limit
        self._A = np.zeros((max_rows, n))
        self._b = np.zeros(max_rows)
        self._weights = np.ones(max_rows)  # the relaxation weights, with a guard (_kernels.guard_weights)
        self._capsule_radius = self.arm.capsule_radius
        # The whole-arm rows of the built-in barriers come from one compiled kernel
        # (c3bf_gym._kernels.hook_rows_whole_arm, sharing the barrier classes' per-point code);
        # any other barrier or points="ee" goes through Barrier.terms / rows_from_terms.
        spec = getattr(barrier, "fused_spec", None)
        spec = spec() if spec is not None and points == "whole_arm" else None
        # the kernel's guard gains (γ₁, γ₂) of a distance HOCBF (0: no guard) and the barrier rows'
        # relaxation weight
        guard_f = np.zeros(3)
        if guard is not None:
            guard_spec = guard.fused_spec() if hasattr(guard, "fused_spec") else None
            if guard_spec is not None and guard_spec[0] == _kernels.HOCBF_KIND:
                guard_f = np.array([guard_spec[1][1], guard_spec[1][0], BARRIER_RELAXATION_WEIGHT])
            else:
                spec = None
        self._fused = spec is not None
        self._kind, params = spec if spec is not None else (-1, np.zeros(3))
        if joint_limits is not None:
            jl = [np.array(joint_limits.gains), joint_limits.q_lo, joint_limits.q_hi, joint_limits.qd_max]
        else:
            jl = [np.ones(3), np.zeros(n), np.ones(n), np.ones(n)]
        # the fused kernel's float parameters (c3bf_gym._kernels.hook_rows_whole_arm)
        self._hook_f = np.concatenate([[self.sensing_radius, self.margin, FLOOR_GAMMA], params, *jl, guard_f])
        self._floor_idx = self._floor_ends.astype(np.int64)
        self._work = np.zeros((3, 6 + n))
        self._bound_qp: TorqueQP | None = None  # the QP whose buffers _bound holds (_bind)
        self._bound: tuple = ()
        self._hook_step = _kernels.hook_step  # its compiled entry point once bound (_bind)
        self.last: QPResult | None = None
        self.report = StepSafety()
        self.solve_times: list[float] | None = None

    def __getstate__(self) -> dict:
        """Pickled without what :meth:`_bind` gathered (views of this process's arrays and a compiled
        entry point): the unpickled hook binds again on its first call, to its own env's arrays."""
        state = self.__dict__.copy()
        state.update(_bound=(), _bound_qp=None, _hook_step=_kernels.hook_step)
        return state

    def record_times(self, enabled: bool = True) -> None:
        """Start (or stop) keeping every physics step's filter time in ``solve_times``."""
        self.solve_times = [] if enabled else None

    def begin_step(self) -> None:
        """Start a new policy step's report."""
        self.report = StepSafety()

    def rows(self) -> tuple[np.ndarray, np.ndarray, float, bool, int]:
        """Assemble the rows for the current state: (A, b, min h, any inside, sensed count)."""
        env, arm = self.env, self.arm
        data = env.data
        if self._fused:
            v = arm.views(data)
            m, min_h, inside, n_sensed = _kernels.hook_rows_whole_arm(
                arm.claim(data, env.state_version), v.M, v.qfrc_passive, v.qfrc_bias, v.geom_xpos, v.geom_xmat,
                v.cdof, v.cdof_dot, v.com, v.qpos, v.qvel, arm._arm_i, arm._arm_f, arm.capsule_chain, arm._scratch,
                arm.Minv, arm.qacc_free, arm._ends, arm._ends_ab, arm._a_dot_ab, env.obstacle_active, env.distances,
                env.obstacle_pos, env.obstacle_vel, env.obstacle_acc, env.obstacle_radius, self._kind,
                self._floor_idx, self._floor_min, self.joint_limits is not None, self._hook_f, self._work,
                self._A, self._b,
            )
            return self._A[:m], self._b[:m], min_h, inside, n_sensed
        arm.update(data, env.state_version)
        sensed = np.flatnonzero(env.obstacle_active & (env.obstacle_distances() <= self.sensing_radius))
        m = 0
        min_h, inside = np.inf, False
        if len(sensed):
            centres = env.obstacle_pos[sensed]
            radius = env.obstacle_radius[sensed]
            if self.points == "whole_arm":
                # The closest points slide along the links as things move, so their ḣ has the
                # terms ⟨∂h/∂p, ṗ_slide⟩ + ⟨∂h/∂v, v̇_slide⟩ besides the material point's; without
                # them ḣ is overestimated and links drift into obstacles (ArmModel.closest_sliding).
                # closest_relative puts v̇_slide into c and returns ṗ_slide.
                rel, slide_p = arm.closest_relative(centres, env.obstacle_vel[sensed], env.obstacle_acc[sensed])
                p, v, G, c = rel.pos, rel.vel, rel.G, rel.c
                r = radius[:, None] + self._capsule_radius
                r += self.margin
                r = r.reshape(-1)
            else:
                site = arm.site_dynamics(data)
                p = site.pos - centres
                v = site.vel - env.obstacle_vel[sensed]
                c = site.c - env.obstacle_acc[sensed]
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
                    min_h = float(terms.h.min())
                    inside = bool(terms.inside.any())
            m = len(barriers) * len(p)
        if self._n_floor_rows:
            m += self._floor_rows(self._A[m:], self._b[m:])
        if self.joint_limits is not None:
            self.joint_limits.rows(
                data.qpos, data.qvel, arm.Minv, arm.qacc_free, out=Rows(self._A[m:], self._b[m:])
            )
            m += self._n_joint_rows
        return self._A[:m], self._b[:m], min_h, inside, len(sensed)

    def relaxation_weights(self, m: int) -> np.ndarray | None:
        """The relaxation weights of :meth:`rows`' ``m`` rows: None without a guard (all rows weigh
        1), else :data:`BARRIER_RELAXATION_WEIGHT` for the barrier's rows and 1 for the others."""
        if self.guard is None:
            return None
        _kernels.guard_weights(self._weights[:m], m - self._n_floor_rows - self._n_joint_rows, BARRIER_RELAXATION_WEIGHT)
        return self._weights[:m]

    def _floor_setup(self, model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
        """Which capsule ends get a floor row, and their lowest allowed height (floor + capsule
        radius + margin); both empty without an upright plane geom in the world body. Capsules moved
        only by joints about vertical axes (link 1, on the base's pan joint) keep their height
        and get no row: theirs could only be a constant, possibly unsatisfiable, 0 ≥ b."""
        plane = mujoco.mjtGeom.mjGEOM_PLANE
        floors = [g for g in range(model.ngeom) if model.geom_type[g] == plane and model.geom_bodyid[g] == 0]
        floors = [g for g in floors if np.allclose(model.geom_quat[g], (1.0, 0.0, 0.0, 0.0))]
        if not floors:
            return np.zeros(0, dtype=int), np.zeros(0)
        scratch = mujoco.MjData(model)
        mujoco.mj_kinematics(model, scratch)
        vertical = np.abs(scratch.xaxis[:, 2]) > 1.0 - 1e-12  # (njnt,) joint axis along world z
        moving = []
        for chain in self.arm.capsule_chain:
            joints = model.dof_jntid[np.flatnonzero(chain)]
            moving.append(not vertical[joints].all())
        ends = np.flatnonzero(np.tile(moving, 2))
        radius = np.tile(self.arm.capsule_radius, 2)[ends]
        return ends, model.geom_pos[floors[0], 2] + radius + self.margin

    def _floor_rows(self, A: np.ndarray, b: np.ndarray) -> int:
        """Rows keeping every capsule end ``z ≥ z_min`` (floor + radius + margin): the
        second-order barrier ``z̈ + 2γ ż + γ² (z − z_min) ≥ 0`` with ``z̈ = G_z τ + c_z``.
        (The fused kernel's :func:`c3bf_gym._kernels.floor_rows`.)"""
        self.arm.end_dynamics()  # refreshes the packed capsule ends (arm._ends) if stale
        k = self._n_floor_rows
        _kernels.floor_rows(self.arm._ends, self._floor_idx, self._floor_min, FLOOR_GAMMA, A[:k], b[:k])
        return k

    def _bind(self, qp: TorqueQP) -> tuple:
        """The buffers :func:`c3bf_gym._kernels.hook_step` works in (env, arm and hook, then
        ``qp``'s :meth:`~c3bf_gym.qp.TorqueQP.packed_step_buffers`; all allocated once by their
        constructors and updated in place), gathered once per QP object: fetching them attribute
        by attribute on every call cost more than the kernel's dispatch."""
        env, arm = self.env, self.arm
        v = arm.views(env.data)
        self._bound = (
            v.M, v.qfrc_passive, v.qfrc_bias, v.geom_xpos, v.geom_xmat, v.cdof, v.cdof_dot, v.com, v.qpos, v.qvel,
            arm._arm_i, arm._arm_f, arm.capsule_chain, arm._scratch, arm.Minv, arm.qacc_free, arm._ends,
            arm._ends_ab, arm._a_dot_ab, env.obstacle_active, env.distances, env.obstacle_pos, env.obstacle_vel,
            env.obstacle_acc, env.obstacle_radius, self._kind, self._floor_idx, self._floor_min,
            self.joint_limits is not None, self._hook_f, self._work, self._A, self._b, self._weights, self._scale,
            self._limit,
            *qp.packed_step_buffers(),
        )
        self._bound_qp = qp
        # hook_step's compiled entry point for exactly these argument types, called directly: the
        # dispatcher's type resolution of its ~50 arguments cost ~1.5 µs per call. The types are
        # fixed: the buffers above, fresh C-contiguous float64 (n,) arrays tau_nom and tau
        # (__call__ checks the shape: the entry point takes any array as the type it was compiled
        # for), and for the scalars Python ints, floats and a bool (which the entry point converts
        # to its types, as the dispatcher does).
        vec = np.zeros(qp.n)
        args = (0, vec, qp._m_prev, qp._kr, qp.active_set_max_iter, qp.active_tol, qp.row_slack_weight,
                qp._diag_W, vec, *self._bound)
        self._hook_step = _kernels.hook_step.compile(tuple(numba.typeof(a) for a in args))
        return self._bound

    def _step(self, tau_nom: np.ndarray, tau: np.ndarray, start: float) -> tuple[QPResult, float, bool, int, float, float]:
        """Rows, QP and :func:`~c3bf_gym._kernels.hook_post` through the fused kernel
        (:func:`~c3bf_gym._kernels.hook_step`); Python only for what it hands back, through the
        layer's own :meth:`~c3bf_gym.qp.TorqueQP.finish_step` (proxsuite where the active-set
        solver did not finish)."""
        qp, env = self.qp, self.env
        bound = self._bound if qp is self._bound_qp else self._bind(qp)
        status, m, min_h, inside, n_sensed, steps, k, active, slack, residual, correction = self._hook_step(
            self.arm.claim(env.data, env.state_version), tau_nom, qp._m_prev, qp._kr, qp.active_set_max_iter,
            qp.active_tol, qp.row_slack_weight, qp._diag_W, tau, *bound)
        result = qp.finish_step(status, m, steps, k, active, slack, None if self.guard is None else self._weights[:m],
                                start)
        if status > _kernels.STEP_RELAXED_AS_IS:  # proxsuite's torque: the kernel did not finish the step
            residual, correction = _kernels.hook_post(self._A[:m], self._b[:m], result.tau, self._scale, tau_nom,
                                                      self._limit, tau)
        return result, min_h, inside, n_sensed, residual, correction

    def __call__(self, tau_nom: np.ndarray) -> np.ndarray:
        start = _perf_counter()
        # a copy of the caller's torque (float64; 1-D copies are contiguous): the kernels read it and the
        # report keeps it. Its shape is checked here: the compiled entry point (_bind) cannot.
        tau_nom = np.array(tau_nom, np.float64)
        shape = self._limit.shape
        if tau_nom.shape != shape:
            raise ValueError(f"tau_nom must have shape {shape}, got {tau_nom.shape}")
        tau = np.empty(shape)
        if self._fused and self.qp.solver == "active_set":
            result, min_h, inside, n_sensed, residual, correction = self._step(tau_nom, tau, start)
        else:
            A, b, min_h, inside, n_sensed = self.rows()
            result = self.qp.solve_scaled(tau_nom, A, b, self._scale, self.relaxation_weights(len(b)))  # (A s) u ≥ b
            # τ = u s, the smallest row residual A u − b and ‖τ − clip(τ_nom)‖ (the filter's change)
            residual, correction = _kernels.hook_post(A, b, result.tau, self._scale, tau_nom, self._limit, tau)
        elapsed = _perf_counter() - start
        if self.solve_times is not None:
            self.solve_times.append(elapsed)
        self.last = result
        # the running extremes as plain comparisons (what min / max do, without their call cost)
        report = self.report
        report.substeps += 1
        report.solve_time += elapsed
        if residual < report.min_constraint:
            report.min_constraint = residual
        report.tau_nominal, report.tau = tau_nom, tau
        if min_h < report.min_h:
            report.min_h = min_h
        if inside:
            report.inside = True
        if n_sensed > report.sensed:
            report.sensed = n_sensed
        if result.active_rows > report.active_rows:
            report.active_rows = result.active_rows
        if correction > report.correction:
            report.correction = correction
        if correction > self.intervention_tol:
            report.intervened = True
        if not result.feasible:
            report.feasible = False
            report.infeasible_steps += 1
            report.slack = max(report.slack, result.slack)
            if self.on_infeasible == "raise":
                raise SafetyInfeasibleError(
                    f"no torque within the limits satisfies the safety rows (status {result.status!r}, "
                    f"slack {result.slack:.3g}, min h {min_h:.3g}); pass on_infeasible='relax' to apply "
                    "the least-violating torque instead"
                )
        return tau


def _named_barrier(name: object, gamma: float | None, gamma_name: str) -> Barrier:
    """A barrier of :data:`~c3bf_gym.barriers.BARRIERS` by name, with ``gamma`` as all its gains
    (None: its defaults); errors name ``gamma_name``, the user's parameter."""
    if gamma is None:
        return make_barrier(name)
    if isinstance(gamma, bool) or not (isinstance(gamma, (int, float)) and np.isfinite(gamma) and gamma > 0):
        raise ValueError(f"{gamma_name} must be a finite number > 0 (1/s), got {gamma!r}")
    return make_barrier(name, **({"gamma1": gamma, "gamma2": gamma} if name == "hocbf" else {"gamma": gamma}))


def build_hook(
    env,
    barrier: str | Barrier,
    points: str,
    gamma: float | None,
    margin: float,
    sensing_radius: float | None,
    ee_radius: float,
    joint_speed_fraction: float,
    weight: str,
    on_infeasible: str,
    guard: str | Barrier | None = "auto",
    guard_gamma: float | None = None,
) -> SafetyHook:
    """Validate user-facing options and build a :class:`SafetyHook` (used by the wrappers).

    ``guard``: ``"auto"`` (a :class:`~c3bf_gym.barriers.DistanceHOCBF` beside a
    :class:`~c3bf_gym.barriers.C3BF`, nothing beside any other barrier), None (or ``"none"``), a
    name of :data:`~c3bf_gym.barriers.BARRIERS` or a Barrier. ``guard_gamma``: the named guard's
    gain(s), as ``gamma`` is the barrier's; None for :data:`GUARD_GAMMA` (``"auto"``) or the named
    barrier's default."""
    if points not in POINTS:
        raise ValueError(f"unknown points {points!r}; valid choices: {', '.join(map(repr, POINTS))}")
    if on_infeasible not in ON_INFEASIBLE:
        raise ValueError(f"unknown on_infeasible {on_infeasible!r}; valid choices: {', '.join(map(repr, ON_INFEASIBLE))}")
    if weight not in WEIGHTS:
        raise ValueError(f"unknown weight {weight!r}; valid choices: {', '.join(map(repr, WEIGHTS))}")
    for name, value, low, strict in (
        ("margin", margin, 0.0, False),
        ("ee_radius", ee_radius, 0.0, False),
        ("joint_speed_fraction", joint_speed_fraction, 0.0, True),
    ):
        if not (isinstance(value, (int, float)) and np.isfinite(value) and (value > low if strict else value >= low)):
            raise ValueError(f"{name} must be a finite number {'>' if strict else '>='} {low}, got {value!r}")
    if joint_speed_fraction > 1.0:
        raise ValueError(f"joint_speed_fraction must be in (0, 1] (a fraction of the UR5e's 180 deg/s), got {joint_speed_fraction!r}")
    if sensing_radius is None:
        sensing_radius = env.sensing_radius
    elif not (isinstance(sensing_radius, (int, float)) and sensing_radius > 0):
        raise ValueError(f"sensing_radius must be a number > 0 (m), got {sensing_radius!r}")
    if isinstance(barrier, Barrier):
        if gamma is not None:
            raise ValueError("pass gamma either to the Barrier instance or here, not both")
        barrier_obj = barrier
    else:
        barrier_obj = _named_barrier(barrier, gamma, "gamma")
    if guard == "none":  # the command-line spelling of None
        guard = None
    if guard == "auto":
        guard = "hocbf" if isinstance(barrier_obj, C3BF) else None
        if guard is not None and guard_gamma is None:
            guard_gamma = GUARD_GAMMA
        elif guard is None and guard_gamma is not None:
            raise ValueError("guard_gamma was given, but guard='auto' puts no guard beside this barrier (only beside the C3BF)")
    if isinstance(guard, Barrier) or guard is None:
        if guard_gamma is not None:
            raise ValueError("guard_gamma was given without a guard (guard=None)" if guard is None
                             else "pass guard_gamma either to the guard Barrier instance or here, not both")  # fmt: skip
        guard_obj = guard
    elif isinstance(guard, str) and guard in BARRIERS:
        guard_obj = _named_barrier(guard, guard_gamma, "guard_gamma")
    else:
        choices = ", ".join(map(repr, ("auto", None, "none", *BARRIERS)))
        raise ValueError(f"unknown guard {guard!r}; valid choices: {choices}, or a Barrier")
    q_lo, q_hi = env.joint_range.T
    joint_limits = JointLimits(q_lo, q_hi, joint_speed_fraction * UR5E_JOINT_SPEED)
    return SafetyHook(
        env, barrier_obj, points, margin, sensing_radius, ee_radius, joint_limits, weight, on_infeasible,
        guard=guard_obj,
    )
