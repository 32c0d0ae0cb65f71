"""Compiled (numba) kernels of the arm's dynamics at points on it: the bottom layer of the filter's
compiled path, which knows nothing of barriers or the QP.

The filter runs at every physics step (500 Hz); at the arm's size (6 joints, 7 capsules: tens of
numbers an array) numpy would spend its time in per-call overhead, so the kernels do the arithmetic
in plain loops, compiled once by numba with :data:`~c3bf_gym._compile_cache.STEP_KERNEL_OPTIONS`
(cached on disk, keyed on every kernel source by :mod:`c3bf_gym._compile_cache`; no allocation,
no reference counting).

* :func:`step_inverse`: ``(M + h D)⁻¹`` and ``qacc_free`` (:class:`~c3bf_gym.safety.dynamics.ArmModel`);
  :func:`joint_drift`: ``qacc_free`` with the last physics step's constraint force.
* :func:`point_dynamics` / :func:`capsule_ends` / :func:`tool_site_dynamics`: position, velocity,
  ``c``, ``G`` and Jacobian of points on the arm, from ``cdof`` and ``cdof_dot`` (the formulas of
  :mod:`c3bf_gym.safety.dynamics`): any points, the capsule ends (into :class:`ArmArrays`), the
  tool site (into a :class:`ToolSite`).
* :func:`closest_relative`: closest points on the capsule axes, relative to moving obstacles,
  with their sliding terms (:func:`_closest_pair`: one pair, its terms from :func:`closest_terms`);
  :func:`surface_gap`: an obstacle's surface distance to the capsules.

The row kernels (:mod:`c3bf_gym.safety._rows`) and the impedance controller
(:mod:`c3bf_gym.controllers._kernels`) call these functions directly. The floating-point
operations follow the numpy formulas they replace (same order where it matters), so results agree
with them to rounding (~1e-15 relative).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from c3bf_gym._compile_cache import STEP_KERNEL_OPTIONS  # (before any @njit(cache=True): the cache keys)

_opts = STEP_KERNEL_OPTIONS


class ArmArrays(NamedTuple):
    """What the fused kernels read and write of an arm (:meth:`~c3bf_gym.safety.dynamics.ArmModel.kernel_arrays`):
    views, updated in place, never replaced. ``S`` protected geoms, ``nv`` dofs.

    Attributes:
        M, qfrc_passive, qfrc_bias, qfrc_constraint, geom_xpos, geom_xmat, xpos, xmat, cdof,
            cdof_dot, com, qpos, qvel: the ``MjData`` arrays the dynamics read (``com``: the arm's
            root subtree centre of mass).
        capsule_ids: (S,) the protected geoms.
        capsule_body: (S,) -1 where a capsule is in its geom's frame, else the body in whose frame
            it is (:func:`~c3bf_gym.safety.geometry.protected_capsule`).
        M_rowadr, M_rownnz, M_colind: MuJoCo's sparse layout of ``M``.
        damping: (nv,) ``h D``, the integrator's implicit damping.
        capsule_local: (S, 2, 3) the capsule axes' end points in their geoms' frames [m].
        length2, capsule_radius: (S,) the axes' squared lengths, the radii [m].
        chain: (S, nv) bool, the dofs that move each geom.
        factor: (nv, nv) scratch for the factorisation of ``M + h D``.
        end_jac: (2S, 3, nv) scratch for the capsule ends' Jacobians.
        Minv, qacc_free: (nv, nv), (nv,) ``(M + h D)⁻¹`` and the joint acceleration at zero torque.
        qacc_joint: (nv,) the joint acceleration at zero torque under the last physics step's
            constraint force (:func:`joint_drift`), which the joint-limit rows use.
        ends, ends_ab, a_dot_ab: the capsule ends' packed dynamics (:func:`capsule_ends`).
        site: the tool site (:class:`ToolSite`; position zeros and no dofs for an arm without
            one), whose dynamics the filter's rows for ``points="ee"`` compute
            (:func:`tool_site_dynamics`).
    """

    M: np.ndarray
    qfrc_passive: np.ndarray
    qfrc_bias: np.ndarray
    qfrc_constraint: np.ndarray
    geom_xpos: np.ndarray
    geom_xmat: np.ndarray
    xpos: np.ndarray
    xmat: np.ndarray
    cdof: np.ndarray
    cdof_dot: np.ndarray
    com: np.ndarray
    qpos: np.ndarray
    qvel: np.ndarray
    capsule_ids: np.ndarray
    capsule_body: np.ndarray
    M_rowadr: np.ndarray
    M_rownnz: np.ndarray
    M_colind: np.ndarray
    damping: np.ndarray
    capsule_local: np.ndarray
    length2: np.ndarray
    capsule_radius: np.ndarray
    chain: np.ndarray
    factor: np.ndarray
    end_jac: np.ndarray
    Minv: np.ndarray
    qacc_free: np.ndarray
    qacc_joint: np.ndarray
    ends: np.ndarray
    ends_ab: np.ndarray
    a_dot_ab: np.ndarray
    site: ToolSite


class SparseMass(NamedTuple):
    """MuJoCo's lower-triangular CSR mass matrix: ``values`` (``data.M``) and the model's
    ``M_rowadr``, ``M_rownnz``, ``M_colind`` (``rowadr``, ``rownnz``, ``colind``; the diagonal is
    the last entry of each row)."""

    values: np.ndarray
    rowadr: np.ndarray
    rownnz: np.ndarray
    colind: np.ndarray


class ArmMotion(NamedTuple):
    """What the dynamics of a point on the arm are computed from (:func:`point_dynamics`):
    MuJoCo's ``cdof`` and ``cdof_dot`` (nv, 6), ``com`` (3,) the arm's root subtree centre of mass
    (their reference point) [m], ``qvel`` (nv,), ``Minv`` (nv, nv) and ``qacc_free`` (nv,) (the joint
    acceleration at zero torque; zeros give the point's ``J̇ q̇`` as its ``c``)."""

    cdof: np.ndarray
    cdof_dot: np.ndarray
    com: np.ndarray
    qvel: np.ndarray
    Minv: np.ndarray
    qacc_free: np.ndarray


class ToolSite(NamedTuple):
    """The tool site as :func:`tool_site_dynamics` reads and writes it.

    Attributes:
        pos: (3,) the site's position, a view of ``data.site_xpos`` [m].
        chain: (1, nv) 1.0 for the dofs that move the site's body, else 0.0.
        zero: (nv,) zeros: with them in place of the free joint acceleration (:class:`ArmMotion`),
            :func:`tool_site_dynamics` gives ``J̇ q̇`` itself as ``c`` (the impedance controller's use).
        packed: (1, 3, 3 + nv) the site's ``[pos | vel | c | G]`` and ``jac`` (1, 3, nv) its
            Jacobian, written by :func:`tool_site_dynamics`.
    """

    pos: np.ndarray
    chain: np.ndarray
    zero: np.ndarray
    packed: np.ndarray
    jac: np.ndarray

    @classmethod
    def of(cls, pos: np.ndarray, chain: np.ndarray) -> ToolSite:
        nv = chain.shape[0]
        return cls(pos, np.ascontiguousarray(chain, dtype=np.float64).reshape(1, nv), np.zeros(nv),
                   np.zeros((1, 3, 3 + nv)), np.zeros((1, 3, nv)))


class CapsuleAxes(NamedTuple):
    """The capsule axes as :func:`closest_relative` reads them: ``ends_a`` (S, 3, 3 + nv) the
    packed ``a`` ends, ``ends_ab`` (S, 3, 3 + nv) ``b − a``, ``a_dot_ab`` (S,) ``⟨a, b − a⟩`` and
    ``length2`` (S,) ``‖b − a‖²`` (:func:`capsule_ends`)."""

    ends_a: np.ndarray
    ends_ab: np.ndarray
    a_dot_ab: np.ndarray
    length2: np.ndarray


class ClosestPoints(NamedTuple):
    """:func:`closest_relative`'s outputs for K obstacles and S capsules, obstacle-major (row
    ``k S + s``): ``p``, ``v``, ``c``, ``slide`` (K S, 3), ``G`` (K S, 3, nv), ``t`` (K, S)."""

    p: np.ndarray
    v: np.ndarray
    c: np.ndarray
    G: np.ndarray
    slide: np.ndarray
    t: np.ndarray


@njit(**_opts)
def step_inverse(mass, damping, qfrc_passive, qfrc_bias, work, Minv, qacc_free):
    """``Minv = (M + h D)⁻¹`` and ``qacc_free = Minv (τ_passive − b)``.

    ``mass`` is ``M`` (:class:`SparseMass`) and ``damping`` the (nv,) ``h D`` added to its
    diagonal. The matrix is factored as ``Lᵀ D L`` from the last dof up (MuJoCo's ``mj_factorM``
    order; no fill-in for a kinematic tree) in the (nv, nv) scratch ``work``, then solved for the
    identity.
    """
    M, rowadr, rownnz, colind = mass
    nv = Minv.shape[0]
    for i in range(nv):
        for j in range(nv):
            work[i, j] = 0.0
    for i in range(nv):
        adr = rowadr[i]
        for k in range(rownnz[i]):
            work[i, colind[adr + k]] = M[adr + k]
        work[i, i] += damping[i]
    # L'DL: work[k, k] = D_k, work[k, i < k] = L_ki
    for k in range(nv - 1, -1, -1):
        inv_d = 1.0 / work[k, k]
        for i in range(k - 1, -1, -1):
            lki = work[k, i]
            if lki != 0.0:
                scl = -lki * inv_d
                for j in range(i + 1):
                    work[i, j] += work[k, j] * scl
                work[k, i] = lki * inv_d
    # Minv column c solves Lᵀ D L x = e_c
    for c in range(nv):
        for i in range(nv):
            Minv[i, c] = 1.0 if i == c else 0.0
        for k in range(nv - 1, -1, -1):  # Lᵀ w = e
            wk = Minv[k, c]
            if wk != 0.0:
                for i in range(k):
                    Minv[i, c] -= work[k, i] * wk
        for k in range(nv):  # z = w / D
            Minv[k, c] /= work[k, k]
        for k in range(nv):  # L x = z
            acc = Minv[k, c]
            for i in range(k):
                acc -= work[k, i] * Minv[i, c]
            Minv[k, c] = acc
    for i in range(nv):
        acc = 0.0
        for j in range(nv):
            acc += Minv[i, j] * (qfrc_passive[j] - qfrc_bias[j])
        qacc_free[i] = acc


@njit(**_opts)
def joint_drift(Minv, qacc_free, qfrc_constraint, out):
    """``out = qacc_free + Minv φ`` (nv,): the joint acceleration at zero torque, with ``φ`` the
    generalised constraint force of the last physics step (MuJoCo's ``qfrc_constraint``: contacts,
    joint limits, dry friction; ``mj_step1`` leaves the one ``mj_step2`` computed, ``mj_forward``
    computes it for the current state and controls).

    The constraint force depends on the torque about to be applied, which the filter chooses, so
    the last step's force is an estimate of the next one, exact while it changes slowly. Where no
    constraint is active ``φ = 0`` and ``out`` equals ``qacc_free`` exactly."""
    nv = out.shape[0]
    for i in range(nv):
        acc = qacc_free[i]
        for j in range(nv):
            acc += Minv[i, j] * qfrc_constraint[j]
        out[i] = acc


@njit(**_opts)
def _one_point(p, x, chain, motion, packed, jac):
    """Fill ``packed[p, :, 1:]`` (velocity, ``c``, ``G``) and ``jac[p]`` of the point ``x`` (a 3-tuple)
    moving with the dofs where ``chain`` (nv,) is nonzero, the arm moving as ``motion`` says
    (:class:`ArmMotion`; :mod:`c3bf_gym.safety.dynamics`'s formulas:
    ``J_j = chain_j (v_j + ω_j × r)``, ``J̇q̇ = Σ q̇_j v̇_j + (Σ q̇_j ω̇_j) × r + ω × ẋ``)."""
    cdof, cdof_dot, com, qvel, Minv, qacc_free = motion
    nv = qvel.shape[0]
    r0 = x[0] - com[0]
    r1 = x[1] - com[1]
    r2 = x[2] - com[2]
    om0 = om1 = om2 = 0.0  # Σ q̇_j ω_j
    ra0 = ra1 = ra2 = ra3 = ra4 = ra5 = 0.0  # Σ q̇_j (ω̇_j, v̇_j)
    for j in range(nv):
        ch = chain[j]
        w0, w1, w2 = cdof[j, 0], cdof[j, 1], cdof[j, 2]
        jac[p, 0, j] = (r1 * (-w2) + r2 * w1 + cdof[j, 3]) * ch
        jac[p, 1, j] = (r0 * w2 + r2 * (-w0) + cdof[j, 4]) * ch
        jac[p, 2, j] = (r0 * (-w1) + r1 * w0 + cdof[j, 5]) * ch
        qd = ch * qvel[j]
        om0 += qd * w0
        om1 += qd * w1
        om2 += qd * w2
        ra0 += qd * cdof_dot[j, 0]
        ra1 += qd * cdof_dot[j, 1]
        ra2 += qd * cdof_dot[j, 2]
        ra3 += qd * cdof_dot[j, 3]
        ra4 += qd * cdof_dot[j, 4]
        ra5 += qd * cdof_dot[j, 5]
    for i in range(3):
        vel = 0.0
        cc = 0.0
        for j in range(nv):
            vel += jac[p, i, j] * qvel[j]
            cc += jac[p, i, j] * qacc_free[j]
        packed[p, i, 1] = vel
        packed[p, i, 2] = cc
        for k in range(nv):
            g = 0.0
            for j in range(nv):
                g += jac[p, i, j] * Minv[j, k]
            packed[p, i, 3 + k] = g
    v0, v1, v2 = packed[p, 0, 1], packed[p, 1, 1], packed[p, 2, 1]
    packed[p, 0, 2] += ((ra1 * r2 + om1 * v2) - (ra2 * r1 + om2 * v1)) + ra3
    packed[p, 1, 2] += ((ra2 * r0 + om2 * v0) - (ra0 * r2 + om0 * v2)) + ra4
    packed[p, 2, 2] += ((ra0 * r1 + om0 * v1) - (ra1 * r0 + om1 * v0)) + ra5


@njit(**_opts)
def point_dynamics(chain, motion, packed, jac):
    """Velocity, ``c``, ``G`` (``packed[:, :, 1:]``, (P, 3, 3 + nv)) and Jacobians ``jac``
    (P, 3, nv) of the points ``packed[:, :, 0]`` with dof masks ``chain`` (P, nv), the arm moving
    as ``motion`` says (:class:`ArmMotion`)."""
    for p in range(packed.shape[0]):
        x = (packed[p, 0, 0], packed[p, 1, 0], packed[p, 2, 0])
        _one_point(p, x, chain[p], motion, packed, jac)


@njit(**_opts)
def tool_site_dynamics(site, motion):
    """The tool site's position, velocity, ``c`` and ``G`` (``site.packed[0]``, ``[pos | vel | c |
    G]``) and Jacobian (``site.jac[0]``), the site being ``site`` (:class:`ToolSite`) and the arm
    moving as ``motion`` says (:class:`ArmMotion`: with ``qacc_free``, ``c`` is the site's
    acceleration at zero torque; with ``site.zero``, ``J̇ q̇``)."""
    packed = site.packed
    for i in range(3):
        packed[0, i, 0] = site.pos[i]
    point_dynamics(site.chain, motion, packed, site.jac)


@njit(**_opts)
def capsule_ends(arm):
    """The capsule axes' end points (a, b: ``arm.capsule_local`` (S, 2, 3), in the frame of geom
    ``arm.capsule_ids[s]``, or of body ``arm.capsule_body[s]`` where that is >= 0), packed
    ``[pos | vel | c | G]`` in ``arm.ends`` (2S, 3, 3 + nv; a's then b's), their differences
    ``arm.ends_ab = b − a`` (S, 3, 3 + nv) and ``arm.a_dot_ab = ⟨a, b − a⟩`` (S,)
    (:class:`ArmArrays`)."""
    ids, local, ends, ends_ab = arm.capsule_ids, arm.capsule_local, arm.ends, arm.ends_ab
    s_count = ids.shape[0]
    ncol = ends.shape[2]
    for s in range(s_count):
        body = arm.capsule_body[s]
        pos = arm.geom_xpos[ids[s]] if body < 0 else arm.xpos[body]
        mat = arm.geom_xmat[ids[s]] if body < 0 else arm.xmat[body]
        for e in range(2):
            la0, la1, la2 = local[s, e, 0], local[s, e, 1], local[s, e, 2]
            for i in range(3):
                ends[e * s_count + s, i, 0] = pos[i] + (mat[3 * i] * la0 + mat[3 * i + 1] * la1 + mat[3 * i + 2] * la2)
    motion = ArmMotion(arm.cdof, arm.cdof_dot, arm.com, arm.qvel, arm.Minv, arm.qacc_free)
    for p in range(2 * s_count):
        x = (ends[p, 0, 0], ends[p, 1, 0], ends[p, 2, 0])
        _one_point(p, x, arm.chain[p % s_count], motion, ends, arm.end_jac)
    for s in range(s_count):
        dot = 0.0
        for i in range(3):
            for c in range(ncol):
                ends_ab[s, i, c] = ends[s_count + s, i, c] - ends[s, i, c]
            dot += ends[s, i, 0] * ends_ab[s, i, 0]
        arm.a_dot_ab[s] = dot


@njit(**_opts)
def _axis_parameter(ends_ab, a_dot_ab, length2, s, o):
    """The parameter ``t`` (unclamped) of the point of capsule ``s``'s axis ``a + t (b − a)``
    closest to ``o``; 0 for a sphere (an axis of length 0)."""
    t = (o[0] * ends_ab[s, 0, 0] + o[1] * ends_ab[s, 1, 0] + o[2] * ends_ab[s, 2, 0]) - a_dot_ab[s]
    if length2[s] > 0.0:
        return t / length2[s]
    return 0.0


@njit(**_opts)
def surface_gap(ends_a, ends_ab, a_dot_ab, length2, capsule_radius, o, radius):
    """The smallest signed surface distance [m] from the sphere (``o``, ``radius``) to the
    capsules (negative: overlapping)."""
    gap = np.inf
    for s in range(ends_ab.shape[0]):
        tc = min(max(_axis_parameter(ends_ab, a_dot_ab, length2, s, o), 0.0), 1.0)
        d0 = (tc * ends_ab[s, 0, 0] + ends_a[s, 0, 0]) - o[0]
        d1 = (tc * ends_ab[s, 1, 0] + ends_a[s, 1, 0]) - o[1]
        d2 = (tc * ends_ab[s, 2, 0] + ends_a[s, 2, 0]) - o[2]
        gap = min(gap, math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) - capsule_radius[s] - radius)
    return gap


@njit(**_opts)
def closest_terms(ends_a, ends_ab, a_dot_ab, length2, s, o, vo, ao):
    """Closest point of capsule ``s``'s axis to the centre ``o`` (3,) (moving with ``vo``, ``ao``):
    returns ``(t, tc, p, v, c, slide)``, the unclamped axis parameter ``t`` and the clamped one
    ``tc`` (the point is ``a + tc (b − a)``; its ``G`` is ``G_a + tc (G_b − G_a)``), and the
    3-tuples ``p = x* − o``, ``v = ẋ − vo``, ``c = (material c) − ao + ṫ (ḃ − ȧ)``,
    ``slide = ṫ (b − a)`` (:meth:`ArmModel.closest_relative`).

    The vectors are tuples, not arrays: the fused kernel calls this once per obstacle–capsule pair,
    and array views for them cost three times the arithmetic."""
    t = _axis_parameter(ends_ab, a_dot_ab, length2, s, o)
    tc = min(max(t, 0.0), 1.0)
    ab0, ab1, ab2 = ends_ab[s, 0, 0], ends_ab[s, 1, 0], ends_ab[s, 2, 0]
    ab_dot0, ab_dot1, ab_dot2 = ends_ab[s, 0, 1], ends_ab[s, 1, 1], ends_ab[s, 2, 1]
    p = ((tc * ab0 + ends_a[s, 0, 0]) - o[0], (tc * ab1 + ends_a[s, 1, 0]) - o[1], (tc * ab2 + ends_a[s, 2, 0]) - o[2])
    v = ((tc * ab_dot0 + ends_a[s, 0, 1]) - vo[0], (tc * ab_dot1 + ends_a[s, 1, 1]) - vo[1],
         (tc * ab_dot2 + ends_a[s, 2, 1]) - vo[2])
    c0 = (tc * ends_ab[s, 0, 2] + ends_a[s, 0, 2]) - ao[0]
    c1 = (tc * ends_ab[s, 1, 2] + ends_a[s, 1, 2]) - ao[1]
    c2 = (tc * ends_ab[s, 2, 2] + ends_a[s, 2, 2]) - ao[2]
    rate = (v[0] * ab0 + v[1] * ab1 + v[2] * ab2) + (p[0] * ab_dot0 + p[1] * ab_dot1 + p[2] * ab_dot2)
    if length2[s] > 0.0:
        rate /= -length2[s]
    if not (t > 0.0 and t < 1.0):
        rate *= 0.0  # clamped to an end: the point does not slide
    c = (c0 + rate * ab_dot0, c1 + rate * ab_dot1, c2 + rate * ab_dot2)
    return t, tc, p, v, c, (rate * ab0, rate * ab1, rate * ab2)


@njit(**_opts)
def _closest_pair(axes, s, o, vo, ao, G):
    """:func:`closest_terms` on the capsule axes ``axes`` (:class:`CapsuleAxes`), with the point's
    ``G`` (3, nv) written out: returns ``(t, p, v, c, slide)``."""
    ends_a, ends_ab, a_dot_ab, length2 = axes
    t, tc, p, v, c, slide = closest_terms(ends_a, ends_ab, a_dot_ab, length2, s, o, vo, ao)
    for i in range(3):
        for j in range(G.shape[1]):
            G[i, j] = tc * ends_ab[s, i, 3 + j] + ends_a[s, i, 3 + j]
    return t, p, v, c, slide


@njit(**_opts)
def closest_relative(axes, centres, velocities, accelerations, out):
    """:func:`_closest_pair` for every (obstacle k, capsule s) of the capsule axes ``axes``
    (:class:`CapsuleAxes`) and the obstacles' ``centres``, ``velocities``, ``accelerations`` (K, 3),
    into ``out`` (:class:`ClosestPoints`)."""
    s_count = axes.ends_a.shape[0]
    p, v, c, G, slide, t = out
    for k in range(centres.shape[0]):
        for s in range(s_count):
            row = k * s_count + s
            t[k, s], p[row], v[row], c[row], slide[row] = _closest_pair(axes, s, centres[k], velocities[k],
                                                                        accelerations[k], G[row])
