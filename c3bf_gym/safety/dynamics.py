"""Dynamics quantities of the arm at a set of points, read from MuJoCo without per-point calls.

For a point ``x`` rigidly attached (at this instant) to a body of the arm, MuJoCo's com-based
motion subspace ``cdof`` (rows ``[ω_j, v_j]`` expressed at the root's subtree centre of mass ``c``)
gives the translational Jacobian column of dof ``j`` on the body's chain as
``J_j = v_j + ω_j × (x − c)``, and ``cdof_dot`` its time derivative with ``c`` held fixed, so

    ẋ      = Σ_j q̇_j (v_j + ω_j × r)                          r = x − c
    J̇ q̇   = Σ_j q̇_j (v̇_j + ω̇_j × r) + ω_x × ẋ            ω_x = Σ_j q̇_j ω_j

(the same expressions as ``mj_jac`` and ``mj_jacDot``, which the tests compare against). The
per-step work (these sums, the factorisation of ``M + h D``, the closest points) runs in compiled
kernels (:mod:`c3bf_gym.safety._dynamics`): at this size the cost of numpy is its per-call overhead.

The joint acceleration is the one the next physics step integrates, not the continuous-time
``M⁻¹ f``. MuJoCo's Euler integrator treats joint damping ``D`` implicitly (unless
``mjDSBL_EULERDAMP`` is set): it integrates ``q̇⁺ = q̇ + h (M + h D)⁻¹ f``, with ``f = τ + τ_passive
− b`` (``τ_passive`` holding the explicit damping force ``−D q̇``). ``implicitfast`` and
``implicit`` do the same for the damping (``implicit`` also differentiates the Coriolis forces,
which is left out here). So ``Minv`` is ``(M + h D)⁻¹``, and plain ``M⁻¹`` only for RK4 or with
``mjDSBL_EULERDAMP`` (with ``h D = 0``). With ``D = 10 N m s/rad`` on the big joints and
``h = 2 ms``, ``M⁻¹`` would mispredict the accelerations by 2–4 %.

Everything here needs ``data`` after ``mj_step1`` (or ``mj_forward``): positions, the mass
matrix, bias and passive forces, ``cdof`` and ``cdof_dot`` of the state about to be integrated.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import mujoco
import numpy as np

from c3bf_gym.safety import _dynamics
from c3bf_gym.safety.geometry import Capsule, protected_capsule, world_segments

__all__ = ["ArmModel", "PointDynamics", "segment_closest_points"]


class PointDynamics(NamedTuple):
    """Affine map from joint torque to the points' accelerations: ``ẍ = G τ + c``.

    Attributes:
        pos: (P, 3) point positions [m].
        vel: (P, 3) point velocities [m/s].
        jac: (P, 3, n) translational Jacobians (None where not computed).
        G: (P, 3, n) ``J M_h⁻¹`` [m/s² per N m], ``M_h = M + h D`` (:attr:`ArmModel.Minv`).
        c: (P, 3) acceleration at zero actuator torque, ``J M_h⁻¹(τ_passive − b) + J̇ q̇`` [m/s²].
    """

    pos: np.ndarray
    vel: np.ndarray
    jac: np.ndarray | None
    G: np.ndarray
    c: np.ndarray


class _DataViews(NamedTuple):
    """Numpy views of the ``MjData`` arrays :class:`ArmModel` reads (``com``: the kinematic
    tree's subtree centre of mass, the origin of ``cdof``)."""

    M: np.ndarray
    qfrc_passive: np.ndarray
    qfrc_bias: np.ndarray
    qfrc_constraint: np.ndarray
    qpos: np.ndarray
    qvel: np.ndarray
    cdof: np.ndarray
    cdof_dot: np.ndarray
    com: np.ndarray
    geom_xpos: np.ndarray
    geom_xmat: np.ndarray
    xpos: np.ndarray
    xmat: np.ndarray


def segment_closest_points(a: np.ndarray, b: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Closest points on segments ``a[s]``-``b[s]`` to every centre: (K, S, 3).

    Args:
        a, b: (S, 3) segment end points [m].
        centres: (K, 3) query points [m].
    """
    ab = b - a
    length2 = np.einsum("ij,ij->i", ab, ab)
    t = np.einsum("ksj,sj->ks", centres[:, None, :] - a[None], ab)
    np.divide(t, length2, out=t, where=length2 > 0.0)
    t[:, length2 == 0.0] = 0.0
    np.clip(t, 0.0, 1.0, out=t)
    return a[None] + t[..., None] * ab[None]


class ArmModel:
    """The arm's joints, capsules and dynamics as the safety filter and controllers need them.

    Args:
        model: the compiled MuJoCo model (``C3BFReachEnv.model``).
        arm_geom_ids: geoms of the arm; those on moving bodies become protected capsules, each
            the capsule that contains the geom (:func:`~c3bf_gym.safety.geometry.enclosing_capsule`:
            capsules and spheres as they are, cylinders, ellipsoids, boxes and meshes enclosed).
            Geoms on bodies no joint moves are left out (they cannot be moved away from an
            obstacle; the env leaves its fixed base to the scenario's keep-out zone).
        site_id: the tool site (``ee_site``), or -1 for none (then :meth:`site_dynamics` is
            unavailable).
        capsules: the capsule to protect for each of ``arm_geom_ids``, as
            :attr:`~c3bf_gym.safety.RobotDescription.capsules` holds them (a gripper's fingers
            swept over their range, :func:`~c3bf_gym.safety.geometry.protected_capsule`); None:
            computed here, with every dof the arm's.

    Raises:
        ValueError: no geom on a moving body, or geoms on more than one kinematic tree.
        ~c3bf_gym.safety.geometry.UnsupportedGeomError: a plane, height field or SDF geom among
            them, or one swept by joints it cannot sweep.
    """

    def __init__(self, model: mujoco.MjModel, arm_geom_ids: np.ndarray, site_id: int,
                 capsules: Sequence[Capsule] | None = None) -> None:
        self.model = model
        self.nv = model.nv
        self.site_id = int(site_id)
        if capsules is None:
            capsules = [None] * len(arm_geom_ids)
        elif len(capsules) != len(arm_geom_ids):
            raise ValueError(f"{len(capsules)} capsules for {len(arm_geom_ids)} geoms: give one per geom")
        kept = [(int(g), c) for g, c in zip(arm_geom_ids, capsules, strict=True)
                if self._chain_mask(model, model.geom_bodyid[g]).any()]  # fmt: skip
        if not kept:
            raise ValueError("the model has no protected geoms on moving arm bodies")
        ids = [g for g, _ in kept]
        self.capsule_ids = np.array(ids)
        every_dof = np.arange(model.nv)
        #: the capsule protected for each geom (in the geom's frame, or its mount body's)
        self.capsules = tuple(protected_capsule(model, g, every_dof) if c is None else c for g, c in kept)
        self.capsule_radius = np.array([c.radius for c in self.capsules])
        #: (S, 2, 3) each capsule's axis end points a, b in its frame [m]
        self.capsule_local = np.ascontiguousarray([(c.a, c.b) for c in self.capsules], dtype=np.float64)
        #: (S,) -1 for a capsule in its geom's frame, else the body whose frame holds it
        self.capsule_body = np.array([c.body for c in self.capsules], dtype=np.int64)
        frames = [model.geom_bodyid[g] if c.body < 0 else c.body for g, c in zip(ids, self.capsules, strict=True)]
        self.capsule_names = [model.geom(g).name for g in self.capsule_ids]
        roots = {int(model.body_rootid[body]) for body in frames}
        if len(roots) != 1:
            raise ValueError("all arm capsules must belong to one kinematic tree")
        self._root = roots.pop()
        self.capsule_chain = np.array([self._chain_mask(model, body) for body in frames])
        self.site_chain = self._chain_mask(model, model.site_bodyid[self.site_id]) if self.site_id >= 0 else None
        s, nv = len(self.capsule_ids), self.nv
        #: ``h D``, the implicit damping the integrator adds to the mass matrix's diagonal (nv,).
        implicit_damping = self._implicit_damping(model)
        # the model's constants as the compiled kernels read them
        self._capsule_ids = np.asarray(self.capsule_ids, dtype=np.int64)
        self._M_rowadr = np.asarray(model.M_rowadr, dtype=np.int64)
        self._M_rownnz = np.asarray(model.M_rownnz, dtype=np.int64)
        self._M_colind = np.asarray(model.M_colind, dtype=np.int64)
        self.implicit_damping = np.asarray(implicit_damping, dtype=np.float64)
        axis = self.capsule_local[:, 1] - self.capsule_local[:, 0]
        self._length2 = np.einsum("ij,ij->i", axis, axis)
        #: (S,) the capsules' axis lengths [m] (0: a sphere)
        self.capsule_length = np.sqrt(self._length2)
        self.capsule_radius = np.asarray(self.capsule_radius, dtype=np.float64)
        self._ends = np.zeros((2 * s, 3, 3 + nv))  # ends a then b, packed [pos | vel | c | G]
        self._ends_a = self._ends[:s]
        self._ends_ab = np.zeros((s, 3, 3 + nv))
        self._a_dot_ab = np.zeros(s)
        # scratch: the L'DL factorisation of M + h D (nv, nv), then the ends' Jacobians (2S, 3, nv).
        # M + h D is factored (from the last dof up, as mj_factorM) here, never in the env's data:
        # mj_step2 still needs that one's own factorisation of M.
        self._scratch = np.zeros(nv * nv + 2 * s * 3 * nv)
        self._factor = self._scratch[: nv * nv].reshape(nv, nv)
        self._end_jac = self._scratch[nv * nv :].reshape(2 * s, 3, nv)
        #: ``(M + h D)⁻¹``: the map from joint torque to the joint acceleration the next physics
        #: step integrates (module docstring); ``M⁻¹`` when the integrator has no implicit damping.
        self.Minv = np.zeros((nv, nv))
        self.qacc_free = np.zeros(nv)  # Minv (τ_passive − b): joint acceleration at zero torque
        #: ``qacc_free + Minv φ`` with ``φ`` the last physics step's constraint force
        #: (:func:`~c3bf_gym.safety._dynamics.joint_drift`): the joint-limit rows' drift.
        self.qacc_joint = np.zeros(nv)
        self._version: int | None = None
        self._ends_current = False
        self._views_of: mujoco.MjData | None = None

    @staticmethod
    def _implicit_damping(model: mujoco.MjModel) -> np.ndarray:
        """(nv,) ``h D`` if the integrator treats joint damping implicitly, else zeros."""
        integrator = mujoco.mjtIntegrator
        euler_damp = model.opt.integrator == integrator.mjINT_EULER and not (
            model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_EULERDAMP
        )
        implicit = model.opt.integrator in (integrator.mjINT_IMPLICIT, integrator.mjINT_IMPLICITFAST)
        if not (euler_damp or implicit):
            return np.zeros(model.nv)
        return model.opt.timestep * model.dof_damping.copy()

    @staticmethod
    def _chain_mask(model: mujoco.MjModel, body: int) -> np.ndarray:
        """(nv,) 1.0 for the dofs that move ``body`` (its own and its ancestors'), else 0.0."""
        mask = np.zeros(model.nv)
        while body > 0:
            start, num = model.body_dofadr[body], model.body_dofnum[body]
            mask[start : start + num] = 1.0
            body = model.body_parentid[body]
        return mask

    # ------------------------------------------------------------------ per physics step
    def update(self, data: mujoco.MjData, version: int | None = None) -> None:
        """Refresh ``Minv = (M + h D)⁻¹``, ``qacc_free`` and the capsule end points' dynamics for
        the current state (one sparse factorisation of ``M + h D``, one solve for its inverse, and
        a handful of small matrix products).

        With ``version`` (the env's ``state_version``), a call for the version already computed
        returns at once, so several hooks in one physics step share the work.
        """
        if version is not None and version == self._version:
            return
        self._version = version
        self._ends_current = False
        self._data = data
        v = self.views(data)
        mass = _dynamics.SparseMass(v.M, self._M_rowadr, self._M_rownnz, self._M_colind)
        _dynamics.step_inverse(mass, self.implicit_damping, v.qfrc_passive, v.qfrc_bias, self._factor, self.Minv,
                               self.qacc_free)

    def views(self, data: mujoco.MjData) -> _DataViews:
        """The arrays of ``data`` the kernels read, fetched once per ``MjData`` (MuJoCo never
        reallocates them; every attribute access would build a new numpy view)."""
        if data is not self._views_of:
            self._views = _DataViews(
                data.M, data.qfrc_passive, data.qfrc_bias, data.qfrc_constraint, data.qpos, data.qvel, data.cdof,
                data.cdof_dot,
                data.subtree_com[self._root], data.geom_xpos, data.geom_xmat, data.xpos, data.xmat,
            )
            self._views_of = data
            # the tool site as the kernels read it: a view of this data's position (zeros, moved by
            # no dof, without a site)
            pos = data.site_xpos[self.site_id] if self.site_id >= 0 else np.zeros(3)
            chain = self.site_chain if self.site_chain is not None else np.zeros(self.nv)
            self._tool_site = _dynamics.ToolSite.of(pos, chain)
        return self._views

    def kernel_arrays(self, data: mujoco.MjData) -> _dynamics.ArmArrays:
        """The arrays of this arm and of ``data`` that the fused filter kernels read and write
        (:class:`~c3bf_gym.safety._dynamics.ArmArrays`; views, valid while both live)."""
        v = self.views(data)
        return _dynamics.ArmArrays(
            v.M, v.qfrc_passive, v.qfrc_bias, v.qfrc_constraint, v.geom_xpos, v.geom_xmat, v.xpos, v.xmat, v.cdof,
            v.cdof_dot, v.com, v.qpos, v.qvel, self._capsule_ids, self.capsule_body, self._M_rowadr, self._M_rownnz, self._M_colind,
            self.implicit_damping,
            self.capsule_local, self._length2, self.capsule_radius, self.capsule_chain, self._factor, self._end_jac,
            self.Minv, self.qacc_free, self.qacc_joint, self._ends, self._ends_ab, self._a_dot_ab, self._tool_site,
        )

    def _ensure_ends(self) -> None:
        """The capsule end points' dynamics, computed on first use after :meth:`update` (a no-op
        while they are current).

        Each capsule's axis lies on one rigid body, so position, velocity, ``c`` and ``G`` are
        all affine along it: ``_ends_a`` holds them at end a and ``_ends_ab`` the difference to
        end b, packed as (S, 3, 3 + nv) arrays ``[pos | vel | c | G]`` so that one broadcast
        product evaluates all of them at any points of the axes.
        """
        if self._ends_current:
            return
        self._ends_current = True
        _dynamics.capsule_ends(self.kernel_arrays(self._data))

    def end_dynamics(self) -> PointDynamics:
        """:class:`PointDynamics` (views) of both ends of every capsule axis: rows ``0 … S-1``
        are the ends a, rows ``S … 2S-1`` the ends b; ``jac`` is None. The lowest point of a
        capsule over a horizontal plane is always at one of its ends (the floor rows use this).
        Call :meth:`update` first in the same physics step."""
        self._ensure_ends()
        return self._unpack(self._ends[None])

    def claim(self, data: mujoco.MjData, version: int | None = None) -> int:
        """For a fused kernel (:func:`c3bf_gym.safety._rows.filter_rows`) that refreshes the
        dynamics itself, in this object's arrays: which parts are stale, 2 (``Minv``,
        ``qacc_free`` and the capsule ends), 1 (the ends) or 0 (none), with :meth:`update`'s
        caching on ``version``. Marks them current: the caller must compute them now."""
        if version is None or version != self._version:
            stage = 2
        elif not self._ends_current:
            stage = 1
        else:
            return 0
        self._version = version
        self._data = data
        self._ends_current = True
        return stage

    def forget(self) -> None:
        """Hold no state as current: compiled code is about to overwrite the dynamics arrays with
        states this object does not track (a simulator's compiled loop), so the next
        :meth:`update` or :meth:`claim` computes its state afresh."""
        self._version = None
        self._ends_current = False

    def capsule_segments(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        """End points (S, 3), (S, 3) of the protected capsules' axes, in world coordinates [m]."""
        return world_segments(data, self.capsule_ids, self.capsule_local, self.capsule_body)

    @staticmethod
    def _unpack(packed: np.ndarray) -> PointDynamics:
        """:class:`PointDynamics` (views, leading dimension K * S) of a packed (K, S, 3, 3 + nv)."""
        flat = packed.reshape(-1, *packed.shape[2:])
        return PointDynamics(flat[:, :, 0], flat[:, :, 1], None, flat[:, :, 3:], flat[:, :, 2])

    def closest_relative(
        self, centres: np.ndarray, velocities: np.ndarray, accelerations: np.ndarray
    ) -> tuple[PointDynamics, np.ndarray]:
        """The dynamics of the point on every capsule axis closest to every centre, relative to
        moving obstacles: what a barrier row on the closest points needs.

        A closest point is not a material point: while the arm and the obstacle move it slides
        along the capsule axis, ``x*(t) = a + t*(t) (b − a)``. Its offset ``p = x* − o`` and the
        velocity ``v`` of the arm point under it (relative to the obstacle) therefore change as

            ṗ = v + ṫ (b − a),        v̇ = (material acceleration) + ṫ (ḃ − ȧ),
            ṫ = −(⟨v, b − a⟩ + ⟨p, ḃ − ȧ⟩) / |b − a|²

        where the closest point lies inside the segment, and ``ṫ = 0`` where it is clamped to an
        end (``⟨b − a, ḃ − ȧ⟩ = 0``: the axis is rigid), and always on a sphere (an axis of
        length 0). A barrier on ``(p, v)`` that leaves these terms out overestimates its own rate
        (for the distance HOCBF by exactly ``2 (⟨v, b − a⟩ + ⟨p, ḃ − ȧ⟩)² / |b − a|²``), which
        lets a link drift into an obstacle. Call :meth:`update` first in the same physics step.

        Args:
            centres, velocities, accelerations: (K, 3) the obstacles' [m, m/s, m/s²].

        Returns:
            ``(rel, slide_p)``: ``rel`` is a :class:`PointDynamics` (leading dimension K * S,
            obstacle-major) with ``pos = p = x* − o``, ``vel = v = ẋ − v_o``, ``G``, and
            ``c = (material c) − a_o + ṫ (ḃ − ȧ)`` (the sliding term of ``v̇`` included);
            ``slide_p = ṫ (b − a)`` (K * S, 3), the sliding term of ``ṗ``.
        """
        self._ensure_ends()
        k, s, nv = len(centres), len(self.capsule_ids), self.nv
        as_f64 = np.ascontiguousarray
        p, v, c, slide_p = np.empty((4, k * s, 3))
        G = np.empty((k * s, 3, nv))
        axes = _dynamics.CapsuleAxes(self._ends_a, self._ends_ab, self._a_dot_ab, self._length2)
        _dynamics.closest_relative(axes, as_f64(centres, dtype=np.float64), as_f64(velocities, dtype=np.float64),
                                   as_f64(accelerations, dtype=np.float64),
                                   _dynamics.ClosestPoints(p, v, c, G, slide_p, np.empty((k, s))))
        return PointDynamics(p, v, None, G, c), slide_p

    def site_dynamics(self, data: mujoco.MjData) -> PointDynamics:
        """:class:`PointDynamics` (copies) of the tool site (P = 1), Jacobian included, computed as
        the filter's compiled rows compute it (:func:`~c3bf_gym.safety._dynamics.tool_site_dynamics`,
        from ``cdof`` and ``cdof_dot``: ``mj_jacSite`` and ``mj_jacDot``'s values, to rounding).
        ``Minv`` and ``qacc_free`` must be current (:meth:`update`).

        Raises:
            ValueError: the arm was built without a tool site (``site_id`` -1)."""
        if self.site_id < 0:
            raise ValueError("this arm has no tool site: build it with the site's id (RobotDescription.from_model's "
                             "site=)")  # fmt: skip
        v = self.views(data)
        site = self._tool_site
        _dynamics.tool_site_dynamics(site, _dynamics.ArmMotion(v.cdof, v.cdof_dot, v.com, v.qvel, self.Minv,
                                                               self.qacc_free))
        packed = site.packed.copy()
        return PointDynamics(packed[:, :, 0], packed[:, :, 1], site.jac.copy(), packed[:, :, 3:], packed[:, :, 2])
