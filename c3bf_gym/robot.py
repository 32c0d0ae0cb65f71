"""Dynamics quantities of the arm at a set of points, read from MuJoCo without per-point calls.

For a point ``x`` rigidly attached (at this instant) to a body of the arm, MuJoCo's com-based
motion subspace ``cdof`` (rows ``[ω_j, v_j]`` expressed at the root's subtree centre of mass ``c``)
gives the translational Jacobian column of dof ``j`` on the body's chain as
``J_j = v_j + ω_j × (x − c)``, and ``cdof_dot`` its time derivative with ``c`` held fixed, so

    ẋ      = Σ_j q̇_j (v_j + ω_j × r)                          r = x − c
    J̇ q̇   = Σ_j q̇_j (v̇_j + ω̇_j × r) + ω_x × ẋ            ω_x = Σ_j q̇_j ω_j

(the same expressions as ``mj_jac`` and ``mj_jacDot``, which the tests compare against). With the
chain mask folded into ``q̇``, every sum is one small matrix product for all points at once.

Everything here needs ``data`` after ``mj_step1`` (or ``mj_forward``): positions, ``qM``, bias
and passive forces, ``cdof`` and ``cdof_dot`` of the state about to be integrated.
"""

from __future__ import annotations

from typing import NamedTuple

import mujoco
import numpy as np

__all__ = ["ArmModel", "PointDynamics", "segment_closest_points"]


class PointDynamics(NamedTuple):
    """Affine map from joint torque to the points' accelerations: ``ẍ = G τ + c``.

    Attributes:
        pos: (P, 3) point positions [m].
        vel: (P, 3) point velocities [m/s].
        jac: (P, 3, n) translational Jacobians (None where not computed).
        G: (P, 3, n) ``J M⁻¹`` [m/s² per N m].
        c: (P, 3) acceleration at zero actuator torque, ``J M⁻¹(τ_passive − b) + J̇ q̇`` [m/s²].
    """

    pos: np.ndarray
    vel: np.ndarray
    jac: np.ndarray | None
    G: np.ndarray
    c: np.ndarray


def _cross(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (P, 3) arrays into ``out`` (faster than ``np.cross``)."""
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _lerp(base: np.ndarray, delta: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``base + t * delta`` for (S, ...) arrays and (K, S) weights, flattened to (K * S, ...)."""
    weights = t.reshape(t.shape + (1,) * (base.ndim - 1))
    return (base + weights * delta).reshape(-1, *base.shape[1:])


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
        arm_geom_ids: geoms of the arm; capsules among them on moving bodies become protected
            segments (the fixed base cannot move and is left to the scenario's keep-out zone).
        site_id: the tool site (``ee_site``).
    """

    def __init__(self, model: mujoco.MjModel, arm_geom_ids: np.ndarray, site_id: int) -> None:
        self.model = model
        self.nv = model.nv
        self.site_id = int(site_id)
        ids = [
            int(g)
            for g in arm_geom_ids
            if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE and self._chain_mask(model, model.geom_bodyid[g]).any()
        ]
        if not ids:
            raise ValueError("the model has no capsule geoms on moving arm bodies")
        self.capsule_ids = np.array(ids)
        self.capsule_radius = model.geom_size[self.capsule_ids, 0].copy()
        self.capsule_half = model.geom_size[self.capsule_ids, 1].copy()
        self.capsule_names = [model.geom(g).name for g in self.capsule_ids]
        roots = {int(model.body_rootid[model.geom_bodyid[g]]) for g in self.capsule_ids}
        if len(roots) != 1:
            raise ValueError("all arm capsules must belong to one kinematic tree")
        self._root = roots.pop()
        self.capsule_chain = np.array([self._chain_mask(model, model.geom_bodyid[g]) for g in self.capsule_ids])
        self.site_chain = self._chain_mask(model, model.site_bodyid[self.site_id])
        self._length2 = (2.0 * self.capsule_half) ** 2
        self._end_chain = np.concatenate([self.capsule_chain, self.capsule_chain])
        self._eye = np.eye(self.nv)
        self.Minv = np.zeros((self.nv, self.nv))
        self.qacc_free = np.zeros(self.nv)  # M⁻¹(τ_passive − b): joint acceleration at zero torque
        self._version: int | None = None
        self._ends_current = False
        self._site_body = int(model.site_bodyid[self.site_id])
        self._site_jac = np.zeros((1, 3, self.nv))
        self._site_jac_dot = np.zeros((3, self.nv))

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
        """Refresh ``Minv``, ``qacc_free`` and the capsule end points' dynamics for the current
        state (one ``mj_solveM`` and a handful of small matrix products).

        With ``version`` (the env's ``state_version``), a call for the version already computed
        returns at once, so several hooks in one physics step share the work.
        """
        if version is not None and version == self._version:
            return
        self._version = version
        self._ends_current = False
        self._data = data
        mujoco.mj_solveM(self.model, data, self.Minv, self._eye)
        np.matmul(self.Minv, data.qfrc_passive - data.qfrc_bias, out=self.qacc_free)

    def _update_ends(self) -> None:
        """The capsule end points' dynamics, computed on first use after :meth:`update`."""
        data = self._data
        self._ends_current = True
        a, b = self.capsule_segments(data)
        ends = self.point_dynamics(data, np.concatenate([a, b]), self._end_chain)
        s = len(self.capsule_ids)
        # Each capsule's axis lies on one rigid body, so position, velocity, J, G and c are all
        # affine along it: store the value at end a and the difference to end b.
        self.ends_a = PointDynamics(*(x[:s] for x in ends))
        self.ends_ab = PointDynamics(*(x[s:] - x[:s] for x in ends))
        self._a_dot_ab = (self.ends_a.pos * self.ends_ab.pos).sum(axis=1)

    def capsule_segments(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        """End points (S, 3), (S, 3) of the protected capsules' axes, in world coordinates [m]."""
        ids = self.capsule_ids
        axis = data.geom_xmat[ids][:, 2::3] * self.capsule_half[:, None]  # z column (xmat is row-major)
        centre = data.geom_xpos[ids]
        return centre - axis, centre + axis

    def _axis_parameter(self, centres: np.ndarray) -> np.ndarray:
        """(K, S) position along each capsule axis of the point nearest each centre, before
        clamping to the segment: ``t = ((o - a) . (b - a)) / |b - a|^2`` (0 at end a, 1 at b)."""
        t = centres @ self.ends_ab.pos.T
        t -= self._a_dot_ab
        t /= self._length2
        return t

    def closest_dynamics(self, centres: np.ndarray) -> PointDynamics:
        """:class:`PointDynamics` of the point on every capsule axis closest to every centre.

        Args:
            centres: (K, 3) query points [m] (obstacle centres).

        Returns:
            arrays of leading dimension ``K * S``, obstacle-major (row ``k * S + s`` is obstacle
            ``k`` and capsule ``s``); ``jac`` is None (the filter needs ``G`` and ``c`` only).
            Call :meth:`update` first in the same physics step.
        """
        if not self._ends_current:
            self._update_ends()
        a, ab = self.ends_a, self.ends_ab
        t = self._axis_parameter(centres)
        np.maximum(t, 0.0, out=t)
        np.minimum(t, 1.0, out=t)
        return PointDynamics(
            _lerp(a.pos, ab.pos, t), _lerp(a.vel, ab.vel, t), None, _lerp(a.G, ab.G, t), _lerp(a.c, ab.c, t)
        )

    def closest_sliding(self, centres: np.ndarray, p: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """How fast the closest points of :meth:`closest_dynamics` slide along their axes.

        A closest point is not a material point: while the arm and the obstacle move it slides
        along the capsule axis, ``x*(t) = a + t*(t) (b − a)``. Its offset ``p = x* − o`` and the
        velocity ``v`` of the arm point under it (relative to the obstacle) therefore change as

            ṗ = v + ṫ (b − a),        v̇ = (material acceleration) + ṫ (ḃ − ȧ),
            ṫ = −(⟨v, b − a⟩ + ⟨p, ḃ − ȧ⟩) / |b − a|²

        where the closest point lies inside the segment, and ``ṫ = 0`` where it is clamped to an
        end (``⟨b − a, ḃ − ȧ⟩ = 0``: the axis is rigid). A barrier on ``(p, v)`` that leaves these
        terms out overestimates its own rate (for the distance HOCBF by exactly
        ``2 (⟨v, b − a⟩ + ⟨p, ḃ − ȧ⟩)² / |b − a|²``), which lets a link drift into an obstacle.

        Args:
            centres: (K, 3) the centres given to :meth:`closest_dynamics` (same physics step).
            p, v: (K * S, 3) closest point minus centre, and that arm point's velocity minus the
                centre's, obstacle-major.

        Returns:
            ``(ṫ (b − a), ṫ (ḃ − ȧ))``: the sliding terms of ``ṗ`` and ``v̇``, both (K * S, 3).
        """
        if not self._ends_current:
            self._update_ends()
        ab = self.ends_ab
        k, s = len(centres), len(self.capsule_ids)
        t = self._axis_parameter(centres)
        rate = np.einsum("ksj,sj->ks", v.reshape(k, s, 3), ab.pos)
        rate += np.einsum("ksj,sj->ks", p.reshape(k, s, 3), ab.vel)
        rate /= -self._length2
        rate[(t <= 0.0) | (t >= 1.0)] = 0.0
        rate = rate[..., None]
        return (rate * ab.pos).reshape(-1, 3), (rate * ab.vel).reshape(-1, 3)

    def point_dynamics(self, data: mujoco.MjData, points: np.ndarray, chain: np.ndarray) -> PointDynamics:
        """:class:`PointDynamics` for ``points`` (P, 3) moving with bodies whose dof masks are
        ``chain`` (P, nv). ``Minv`` and ``qacc_free`` must be current (:meth:`update`)."""
        n, nv = len(points), self.nv
        cdof, cdof_dot = data.cdof, data.cdof_dot
        r = points - data.subtree_com[self._root]
        # J[p, :, j] = chain[p, j] (v_j + ω_j × r_p) = chain[p, j] (v_j - skew(r_p) ω_j)
        skew = np.zeros((n, 3, 3))
        skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -r[:, 2], r[:, 1], -r[:, 0]
        skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = r[:, 2], -r[:, 1], r[:, 0]
        skew2 = skew.reshape(3 * n, 3)
        jac = (skew2 @ -cdof[:, :3].T).reshape(n, 3, nv)
        jac += cdof[:, 3:].T
        jac *= chain[:, None, :]
        jac2 = jac.reshape(3 * n, nv)
        vel = (jac2 @ data.qvel).reshape(n, 3)
        qd_masked = chain * data.qvel
        omega = qd_masked @ cdof[:, :3]
        # J̇q̇ = Σ q̇_j v̇_j + (Σ q̇_j ω̇_j) × r + ω × ẋ ;  u × r = -skew(r) u
        bias = qd_masked @ cdof_dot[:, 3:]
        bias -= np.einsum("pij,pj->pi", skew, qd_masked @ cdof_dot[:, :3])
        bias += _cross(omega, vel, np.empty_like(r))
        G = (jac2 @ self.Minv).reshape(n, 3, nv)
        c = (jac2 @ self.qacc_free).reshape(n, 3)
        c += bias
        return PointDynamics(points, vel, jac, G, c)

    def site_dynamics(self, data: mujoco.MjData) -> PointDynamics:
        """:class:`PointDynamics` of the tool site (P = 1), from ``mj_jacSite`` and ``mj_jacDot``.
        ``Minv`` and ``qacc_free`` must be current (:meth:`update`)."""
        jac, jac_dot = self._site_jac[0], self._site_jac_dot
        mujoco.mj_jacSite(self.model, data, jac, None, self.site_id)
        pos = data.site_xpos[self.site_id]
        mujoco.mj_jacDot(self.model, data, jac_dot, None, pos, self._site_body)
        G = jac @ self.Minv
        c = jac @ self.qacc_free + jac_dot @ data.qvel
        return PointDynamics(pos[None].copy(), (jac @ data.qvel)[None], self._site_jac.copy(), G[None], c[None])
