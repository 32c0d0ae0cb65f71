"""Compiled (numba) kernels of the safety filter's hot path.

The filter runs at every physics step (500 Hz), and its numpy version spent most of its time in
the overhead of many small array calls (0.3–4 µs each), not in arithmetic: the arm has 6 joints
and 7 capsules, so every array holds tens of numbers. These kernels do the same arithmetic in
plain loops, compiled once by numba (``cache=True``: the machine code is cached on disk next to
this file, or in numba's user-wide cache when that folder is read-only, so later processes load
it instead of compiling).

Each piece of math lives once, in an inner ``@njit`` function that works on one point or one row;
the public classes call it through small vectorised kernels, and the filter's fused kernel
(:func:`hook_rows_whole_arm`) calls the same inner functions directly:

* :func:`step_inverse`: ``(M + h D)⁻¹`` and ``qacc_free`` (:class:`~c3bf_gym.robot.ArmModel`).
* :func:`point_dynamics` / :func:`capsule_ends`: position, velocity, ``c``, ``G`` and Jacobian of
  points on the arm, from ``cdof`` and ``cdof_dot`` (the formulas of :mod:`c3bf_gym.robot`).
* :func:`closest_relative`: closest points on the capsule axes, relative to moving obstacles,
  with their sliding terms.
* :func:`c3bf_terms`, :func:`hocbf_terms`, :func:`rows_from_terms`, :func:`joint_limit_rows`: the
  barriers of :mod:`c3bf_gym.barriers`.
* :func:`qp_prepare`, :func:`qp_residuals`, ...: the bookkeeping of :class:`~c3bf_gym.qp.TorqueQP`
  around proxsuite (row normalisation, the fast path, residuals, dual sign check).

The floating-point operations follow the numpy code they replace (same formulas, same order where
it matters), so results agree with it to rounding (~1e-15 relative).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from c3bf_gym import _compile_cache  # noqa: F401  (before any @njit(cache=True): the cache keys)

# hook_step compiles _active_set.solve into itself: _compile_cache (imported by _active_set first)
# keys the on-disk cache of both files' functions on both files.
from c3bf_gym import _active_set

#: barrier kinds of the fused kernel
C3BF_KIND = 0
HOCBF_KIND = 1

#: outcomes of :func:`qp_step` and :func:`hook_step`: done (the hard optimum; a repaired relaxed torque; relaxed with
#: no row to repair), or where the Python layer takes over (the elastic QP or the per-row repair by
#: proxsuite, with or without rows beyond the box's reach), or invalid data
STEP_SOLVED, STEP_RELAXED, STEP_RELAXED_AS_IS = 0, 1, 2
STEP_TO_ELASTIC, STEP_TO_ELASTIC_IMPOSSIBLE, STEP_TO_REPAIR, STEP_TO_REPAIR_IMPOSSIBLE = 3, 4, 5, 6
STEP_BAD_NOMINAL, STEP_BAD_ROWS = -1, -2

_opts = {"cache": True, "nogil": True, "error_model": "numpy", "boundscheck": False}


# ----------------------------------------------------------------------------- dynamics


@njit(**_opts)
def step_inverse(M, rowadr, rownnz, colind, damping, qfrc_passive, qfrc_bias, work, Minv, qacc_free):
    """``Minv = (M + h D)⁻¹`` and ``qacc_free = Minv (τ_passive − b)``.

    ``M`` is MuJoCo's lower-triangular CSR mass matrix (``data.M`` with ``M_rowadr``,
    ``M_rownnz``, ``M_colind``; the diagonal is the last entry of each row) and ``damping`` the
    (nv,) ``h D`` added to its diagonal. The matrix is factored as ``Lᵀ D L`` from the last dof
    up (MuJoCo's ``mj_factorM`` order; no fill-in for a kinematic tree) in the (nv, nv) scratch
    ``work``, then solved for the identity.
    """
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
def _one_point(p, x, chain, cdof, cdof_dot, com, qvel, Minv, qacc_free, packed, jac):
    """Fill ``packed[p, :, 1:]`` (velocity, ``c``, ``G``) and ``jac[p]`` of the point ``x`` (3,)
    moving with the dofs where ``chain`` (nv,) is nonzero (:mod:`c3bf_gym.robot`'s formulas:
    ``J_j = chain_j (v_j + ω_j × r)``, ``J̇q̇ = Σ q̇_j v̇_j + (Σ q̇_j ω̇_j) × r + ω × ẋ``)."""
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
def point_dynamics(chain, cdof, cdof_dot, com, qvel, Minv, qacc_free, packed, jac):
    """Velocity, ``c``, ``G`` (``packed[:, :, 1:]``, (P, 3, 3 + nv)) and Jacobians ``jac``
    (P, 3, nv) of the points ``packed[:, :, 0]`` with dof masks ``chain`` (P, nv)."""
    x = np.empty(3)
    for p in range(packed.shape[0]):
        x[0], x[1], x[2] = packed[p, 0, 0], packed[p, 1, 0], packed[p, 2, 0]
        _one_point(p, x, chain[p], cdof, cdof_dot, com, qvel, Minv, qacc_free, packed, jac)


@njit(**_opts)
def capsule_ends(geom_xpos, geom_xmat, ids, half, chain, cdof, cdof_dot, com, qvel, Minv, qacc_free,
                 ends, ends_ab, a_dot_ab, jac):
    """The capsule axes' end points (a = centre − half z, b = centre + half z), packed
    ``[pos | vel | c | G]`` in ``ends`` (2S, 3, 3 + nv; a's then b's), their differences
    ``ends_ab = b − a`` (S, 3, 3 + nv) and ``a_dot_ab = ⟨a, b − a⟩`` (S,)."""
    s_count = ids.shape[0]
    ncol = ends.shape[2]
    x = np.empty(3)
    for s in range(s_count):
        g = ids[s]
        for i in range(3):
            axis = geom_xmat[g, 3 * i + 2] * half[s]
            ends[s, i, 0] = geom_xpos[g, i] - axis
            ends[s_count + s, i, 0] = geom_xpos[g, i] + axis
    for p in range(2 * s_count):
        x[0], x[1], x[2] = ends[p, 0, 0], ends[p, 1, 0], ends[p, 2, 0]
        _one_point(p, x, chain[p % s_count], cdof, cdof_dot, com, qvel, Minv, qacc_free, ends, jac)
    for s in range(s_count):
        dot = 0.0
        for i in range(3):
            for c in range(ncol):
                ends_ab[s, i, c] = ends[s_count + s, i, c] - ends[s, i, c]
            dot += ends[s, i, 0] * ends_ab[s, i, 0]
        a_dot_ab[s] = dot


@njit(**_opts)
def _axis_parameter(ends_ab, a_dot_ab, length2, s, o):
    """The parameter ``t`` (unclamped) of the point of capsule ``s``'s axis ``a + t (b − a)``
    closest to ``o``; 0 for a sphere (an axis of length 0)."""
    t = (o[0] * ends_ab[s, 0, 0] + o[1] * ends_ab[s, 1, 0] + o[2] * ends_ab[s, 2, 0]) - a_dot_ab[s]
    if length2[s] > 0.0:
        return t / length2[s]
    return 0.0


@njit(**_opts)
def _surface_gap(ends_a, ends_ab, a_dot_ab, length2, capsule_radius, o, radius):
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
def _closest_pair(ends_a, ends_ab, a_dot_ab, length2, s, o, vo, ao, p, v, c, G, slide):
    """Closest point of capsule ``s``'s axis to the centre ``o`` (moving with ``vo``, ``ao``):
    ``p = x* − o``, ``v = ẋ − vo``, ``c = (material c) − ao + ṫ (ḃ − ȧ)``, ``G`` (3, nv) and
    ``slide = ṫ (b − a)`` (:meth:`ArmModel.closest_relative`). Returns the unclamped axis
    parameter ``t``."""
    nv = G.shape[1]
    t = _axis_parameter(ends_ab, a_dot_ab, length2, s, o)
    tc = min(max(t, 0.0), 1.0)
    for i in range(3):
        p[i] = (tc * ends_ab[s, i, 0] + ends_a[s, i, 0]) - o[i]
        v[i] = (tc * ends_ab[s, i, 1] + ends_a[s, i, 1]) - vo[i]
        c[i] = (tc * ends_ab[s, i, 2] + ends_a[s, i, 2]) - ao[i]
        for j in range(nv):
            G[i, j] = tc * ends_ab[s, i, 3 + j] + ends_a[s, i, 3 + j]
    rate = (v[0] * ends_ab[s, 0, 0] + v[1] * ends_ab[s, 1, 0] + v[2] * ends_ab[s, 2, 0]) + (
        p[0] * ends_ab[s, 0, 1] + p[1] * ends_ab[s, 1, 1] + p[2] * ends_ab[s, 2, 1]
    )
    if length2[s] > 0.0:
        rate /= -length2[s]
    if not (t > 0.0 and t < 1.0):
        rate *= 0.0  # clamped to an end: the point does not slide
    for i in range(3):
        c[i] += rate * ends_ab[s, i, 1]
        slide[i] = rate * ends_ab[s, i, 0]
    return t


@njit(**_opts)
def closest_relative(ends_a, ends_ab, a_dot_ab, length2, centres, velocities, accelerations,
                     p, v, c, G, slide, t):
    """:func:`_closest_pair` for every (obstacle k, capsule s), obstacle-major (row k S + s):
    ``p, v, c, slide`` (K S, 3), ``G`` (K S, 3, nv), ``t`` (K, S)."""
    s_count = ends_a.shape[0]
    for k in range(centres.shape[0]):
        for s in range(s_count):
            row = k * s_count + s
            t[k, s] = _closest_pair(ends_a, ends_ab, a_dot_ab, length2, s, centres[k], velocities[k],
                                    accelerations[k], p[row], v[row], c[row], G[row], slide[row])


# ----------------------------------------------------------------------------- barriers


@njit(**_opts)
def _c3bf_point(p, v, r, gamma, eps, delta, grad_v, grad_p):
    """C3BF at one point (:class:`~c3bf_gym.barriers.C3BF`): fills ``grad_v``, ``grad_p`` (3,)
    and returns ``(h, drift, inside)``."""
    h0 = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]) - r * r
    inside = h0 <= 0.0
    pv = p[0] * v[0] + p[1] * v[1] + p[2] * v[2]
    if inside:
        h = pv + 0.5 * gamma * h0
        for i in range(3):
            grad_v[i] = p[i]
            grad_p[i] = v[i] + gamma * p[i]
    else:
        s = math.sqrt(max(h0, delta * delta))
        vv = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
        vn = math.sqrt(vv + eps * eps)
        h = vn * s + pv
        sv = s / vn
        vs = vn / s
        for i in range(3):
            grad_v[i] = v[i] * sv + p[i]
            grad_p[i] = p[i] * vs + v[i]
    drift = grad_p[0] * v[0] + grad_p[1] * v[1] + grad_p[2] * v[2]
    return h, drift, inside


@njit(**_opts)
def _hocbf_point(p, v, r, gamma1, grad_v, grad_p):
    """Distance HOCBF at one point (:class:`~c3bf_gym.barriers.DistanceHOCBF`): fills ``grad_v``,
    ``grad_p`` (3,) and returns ``(ψ₁, drift, inside)``."""
    h0 = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]) - r * r
    pv2 = (p[0] * v[0] + p[1] * v[1] + p[2] * v[2]) * 2.0
    h = h0 * gamma1 + pv2
    drift = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) * 2.0 + pv2 * gamma1
    g2 = 2.0 * gamma1
    for i in range(3):
        grad_v[i] = 2.0 * p[i]
        grad_p[i] = p[i] * g2 + 2.0 * v[i]
    return h, drift, h0 <= 0.0


@njit(**_opts)
def c3bf_terms(p, v, r, gamma, eps, delta, h, grad_v, drift, inside, grad_p):
    """:func:`_c3bf_point` for P points: ``p, v`` (P, 3), ``r`` (P,) into the outputs."""
    for k in range(p.shape[0]):
        h[k], drift[k], inside[k] = _c3bf_point(p[k], v[k], r[k], gamma, eps, delta, grad_v[k], grad_p[k])


@njit(**_opts)
def hocbf_terms(p, v, r, gamma1, h, grad_v, drift, inside, grad_p):
    """:func:`_hocbf_point` for P points: ``p, v`` (P, 3), ``r`` (P,) into the outputs."""
    for k in range(p.shape[0]):
        h[k], drift[k], inside[k] = _hocbf_point(p[k], v[k], r[k], gamma1, grad_v[k], grad_p[k])


@njit(**_opts)
def _row(grad_v, G, c, drift, h, gamma, A_row):
    """One torque row: ``A_row = grad_vᵀ G`` and returns ``b = −(⟨grad_v, c⟩ + drift + γ h)``."""
    for j in range(G.shape[1]):
        A_row[j] = grad_v[0] * G[0, j] + grad_v[1] * G[1, j] + grad_v[2] * G[2, j]
    return -(((grad_v[0] * c[0] + grad_v[1] * c[1] + grad_v[2] * c[2]) + drift) + gamma * h)


@njit(**_opts)
def _sliding_row(grad_v, grad_p, slide, G, c, drift, h, gamma, A_row):
    """:func:`_row` for a closest point sliding by ``slide`` along its link: its ``b`` less the
    sliding term ``⟨grad_p, slide⟩``."""
    bk = _row(grad_v, G, c, drift, h, gamma, A_row)
    return bk - (grad_p[0] * slide[0] + grad_p[1] * slide[1] + grad_p[2] * slide[2])


@njit(**_opts)
def rows_from_terms(grad_v, drift, h, gamma, G, c, A, b):
    """:func:`_row` for P points: ``G`` (P, 3, n), ``c`` (P, 3) into ``A`` (P, n), ``b`` (P,)."""
    for k in range(h.shape[0]):
        b[k] = _row(grad_v[k], G[k], c[k], drift[k], h[k], gamma, A[k])


@njit(**_opts)
def joint_limit_rows(q, qd, Minv, c_q, q_lo, q_hi, qd_max, g1, g2, gv, A, b):
    """The ``4n`` rows of :class:`~c3bf_gym.barriers.JointLimits` into ``A`` (4n, n), ``b`` (4n,)
    (row blocks: position upper, position lower, speed upper, speed lower)."""
    n = q.shape[0]
    g12 = g1 * g2
    g1p2 = g1 + g2
    for i in range(n):
        for j in range(n):
            mij = Minv[i, j]
            A[i, j] = -mij
            A[n + i, j] = mij
            A[2 * n + i, j] = -mij
            A[3 * n + i, j] = mij
        b[i] = ((g12 * q[i] + g1p2 * qd[i]) + c_q[i]) + (-g12 * q_hi[i])
        b[n + i] = ((-g12 * q[i] + -g1p2 * qd[i]) + -c_q[i]) + g12 * q_lo[i]
        b[2 * n + i] = (gv * qd[i] + c_q[i]) + (-gv * qd_max[i])
        b[3 * n + i] = (-gv * qd[i] + -c_q[i]) + (-gv * qd_max[i])


@njit(**_opts)
def floor_rows(ends, idx, z_min, gamma, A, b):
    """Floor rows of :class:`~c3bf_gym.safety.SafetyController`: capsule end ``idx[k]`` of the packed
    ``ends`` (2S, 3, 3 + nv) stays at ``z ≥ z_min[k]``, as the second-order barrier
    ``z̈ + 2γ ż + γ² (z − z_min) ≥ 0`` with ``z̈ = G_z τ + c_z``: ``A_k = G_z``,
    ``b_k = −γ² (z − z_min) − 2γ ż − c_z``."""
    nv = A.shape[1]
    for k in range(idx.shape[0]):
        e = idx[k]
        for j in range(nv):
            A[k, j] = ends[e, 2, 3 + j]
        b[k] = ((ends[e, 2, 0] - z_min[k]) * (-gamma * gamma) - 2.0 * gamma * ends[e, 2, 1]) - ends[e, 2, 2]


# ----------------------------------------------------------------------------- the fused filter rows


@njit(**_opts)
def hook_rows_whole_arm(stage, M, qfrc_passive, qfrc_bias, geom_xpos, geom_xmat, cdof, cdof_dot, com, qpos, qvel,
                        arm_i, arm_f, chain, scratch, Minv, qacc_free, ends, ends_ab, a_dot_ab,
                        active, distances, obs_pos, obs_vel, obs_acc, obs_radius, kind, floor_idx, floor_min,
                        joint_rows, hook_f, work, A, b):
    """All rows of the whole-arm filter (:meth:`~c3bf_gym.safety.SafetyController.rows`) in one call.

    1. ``stage`` 2: ``Minv``, ``qacc_free`` (:func:`step_inverse`), then (``stage`` ≥ 1) the
       capsule ends (:func:`capsule_ends`), into the :class:`~c3bf_gym.robot.ArmModel`'s arrays
       (``arm_i``, ``arm_f``, ``scratch``: its packed constants and scratch).
    2. For every sensed obstacle (active and ``distances[k].min() <= sensing_radius``, or with
       ``distances`` of shape (K, 0) its surface distance to the capsules), one row
       per capsule: closest point (:func:`_closest_pair`), barrier ``kind`` (:func:`_c3bf_point`
       or :func:`_hocbf_point`), row (:func:`_sliding_row`: the sliding term ``−⟨grad_p, ṫ (b − a)⟩``);
       with a guard (``hook_f``'s entries after ``qd_max``: gains γ₁, γ₂ of a distance HOCBF,
       > 0), the guard's row for the same point right after it.
    3. The floor rows of the capsule ends ``floor_idx`` (:func:`floor_rows`, heights
       ``floor_min``).
    4. With ``joint_rows``, the ``4n`` joint-limit rows (:func:`joint_limit_rows`).

    ``hook_f`` = ``[sensing_radius, margin, floor γ, γ, barrier params (2), γ₁, γ₂, γ_v,
    q_lo (n), q_hi (n), qd_max (n), guard γ₁, guard γ₂, the barrier rows' relaxation weight]``
    (guard gains 0: no guard; the weight is :func:`hook_step`'s); ``work`` a
    (3, 6 + nv) scratch. Returns ``(rows, min h of the barrier's rows (not the guard's), any
    inside, sensed count)``.
    """
    s_count = ends_ab.shape[0]
    nv = Minv.shape[0]
    ids = arm_i[:s_count]
    length2 = arm_f[nv + s_count:nv + 2 * s_count]
    capsule_radius = arm_f[nv + 2 * s_count:nv + 3 * s_count]
    if stage >= 2:
        step_inverse(M, arm_i[s_count:s_count + nv], arm_i[s_count + nv:s_count + 2 * nv], arm_i[s_count + 2 * nv:],
                     arm_f[:nv], qfrc_passive, qfrc_bias, scratch[:nv * nv].reshape((nv, nv)), Minv, qacc_free)
    if stage >= 1:
        capsule_ends(geom_xpos, geom_xmat, ids, arm_f[nv:nv + s_count], chain, cdof, cdof_dot, com, qvel, Minv,
                     qacc_free, ends, ends_ab, a_dot_ab, scratch[nv * nv:].reshape((2 * s_count, 3, nv)))
    ends_a = ends[:s_count]
    sensing_radius = hook_f[0]
    margin = hook_f[1]
    floor_gamma = hook_f[2]
    gamma = hook_f[3]
    guard_gamma1 = hook_f[9 + 3 * nv]
    guard_gamma2 = hook_f[10 + 3 * nv]
    guard = guard_gamma2 > 0.0
    p = work[0, :3]
    v = work[1, :3]
    c = work[2, :3]
    grad_v = work[0, 3:6]
    grad_p = work[1, 3:6]
    slide = work[2, 3:6]
    G = work[:, 6:6 + nv]
    m = 0
    n_sensed = 0
    min_h = np.inf
    inside_any = False
    for k in range(active.shape[0]):
        if not active[k]:
            continue
        dmin = np.inf
        for g in range(distances.shape[1]):
            dmin = min(dmin, distances[k, g])
        if distances.shape[1] == 0:  # no distances kept by the obstacles' owner: to the capsules
            dmin = _surface_gap(ends_a, ends_ab, a_dot_ab, length2, capsule_radius, obs_pos[k], obs_radius[k])
        if not dmin <= sensing_radius:
            continue
        n_sensed += 1
        for s in range(s_count):
            _closest_pair(ends_a, ends_ab, a_dot_ab, length2, s, obs_pos[k], obs_vel[k], obs_acc[k],
                          p, v, c, G, slide)
            r = (obs_radius[k] + capsule_radius[s]) + margin
            if kind == C3BF_KIND:
                h, drift, inside = _c3bf_point(p, v, r, gamma, hook_f[4], hook_f[5], grad_v, grad_p)
            else:
                h, drift, inside = _hocbf_point(p, v, r, hook_f[4], grad_v, grad_p)
            b[m] = _sliding_row(grad_v, grad_p, slide, G, c, drift, h, gamma, A[m])
            min_h = min(min_h, h)
            inside_any = inside_any or inside
            m += 1
            if guard:
                h, drift, inside = _hocbf_point(p, v, r, guard_gamma1, grad_v, grad_p)
                b[m] = _sliding_row(grad_v, grad_p, slide, G, c, drift, h, guard_gamma2, A[m])
                m += 1
    n_floor = floor_idx.shape[0]
    floor_rows(ends, floor_idx, floor_min, floor_gamma, A[m:m + n_floor], b[m:m + n_floor])
    m += n_floor
    if joint_rows:
        joint_limit_rows(qpos, qvel, Minv, qacc_free, hook_f[9:9 + nv], hook_f[9 + nv:9 + 2 * nv],
                         hook_f[9 + 2 * nv:9 + 3 * nv], hook_f[6], hook_f[7], hook_f[8],
                         A[m:m + 4 * nv], b[m:m + 4 * nv])
        m += 4 * nv
    return m, min_h, inside_any, n_sensed


# ----------------------------------------------------------------------------- QP layer


@njit(**_opts)
def qp_prepare(tau_nom, A, b, scale, G, h, nrm, r, xe, nom, m_prev, row_norm_min, inf, lo, hi, tol,
               l, l_clipped, reach, negW, g):
    """The data step of :meth:`~c3bf_gym.qp.TorqueQP.solve`, before proxsuite.

    With ``scale`` (n,) nonempty, first ``A *= scale`` (in place) and the nominal is
    ``tau_nom / scale``. Checks finiteness, writes the nominal into ``nom`` and ``xe[:n]``, the
    row-normalised rows into ``G[:m, :n]`` and ``h[:m]`` (norms in ``nrm``; rows below
    ``row_norm_min`` unscaled), pads rows ``m .. m_prev`` with ``(0, −inf)`` and puts the
    residuals ``G xe − h`` into ``r``. If one is negative (no fast path), also the rows' reach
    over the box (:func:`row_reach`, bounds ``l``, ``l_clipped``, ``reach``, tolerance ``tol``)
    and the elastic gradient ``g[:n] = negW nom``.

    Returns ``(code, min residual, impossible rows)``: code −1 if the nominal is not finite, −2
    if the rows are not (or beyond ~1e150), else 0.
    """
    m, n = A.shape
    scaled = scale.shape[0] > 0
    if scaled:
        for i in range(m):
            for j in range(n):
                A[i, j] *= scale[j]
    tt = 0.0
    for j in range(n):
        u = tau_nom[j] / scale[j] if scaled else tau_nom[j]
        nom[j] = u
        xe[j] = u
        tt += u * u
    if not math.isfinite(tt):
        return -1, 0.0, False
    if m:
        bb = 0.0
        aa = 0.0
        for i in range(m):
            bb += b[i] * b[i]
            for j in range(n):
                aa += A[i, j] * A[i, j]
        if not (math.isfinite(bb) and math.isfinite(aa)):
            return -2, 0.0, False
    for i in range(m):
        s = 0.0
        for j in range(n):
            s += A[i, j] * A[i, j]
        s = math.sqrt(s)
        if s < row_norm_min:
            s = 1.0
        nrm[i] = s
        h[i] = b[i] / s
        for j in range(n):
            G[i, j] = A[i, j] / s
    for i in range(m, m_prev):
        for j in range(n):
            G[i, j] = 0.0
        h[i] = -inf
    rmin = residuals(G, xe, h, r)
    if rmin >= 0.0:
        return 0, rmin, False
    impossible = row_reach(G, m, lo, hi, h, tol, l, l_clipped, reach)
    for i in range(n):
        acc = 0.0
        for j in range(n):
            acc += negW[i, j] * nom[j]
        g[i] = acc
    return 0, rmin, impossible


@njit(**_opts)
def residuals(G, x, h, r):
    """``r = G x − h`` (all rows); returns ``min r``."""
    rmin = np.inf
    for i in range(G.shape[0]):
        acc = 0.0
        for j in range(G.shape[1]):
            acc += G[i, j] * x[j]
        r[i] = acc - h[i]
        rmin = min(rmin, r[i])
    return rmin


@njit(**_opts)
def result_stats(G, x, h, r, m, tol, recompute):
    """``(rows k < m with r_k <= tol, max(0, −min_k r_k))`` of the residuals ``r = G x − h``
    (recomputed first if ``recompute``): the active rows and the largest violation."""
    if recompute:
        residuals(G, x, h, r)
    active = 0
    rmin = np.inf
    for i in range(m):
        if r[i] <= tol:
            active += 1
        rmin = min(rmin, r[i])
    return active, max(0.0, -rmin) if m else 0.0


@njit(**_opts)
def infeasibility_bound(z, G, h, m, lo, hi, y):
    """Farkas lower bound on ``min_{τ ∈ [lo, hi]} max_k (h_k − G_k τ)`` from the row multipliers
    ``z[:m]`` (``y = max(−z, 0) / Σ``; −inf when they are all zero), ``y`` (m,) scratch."""
    n = lo.shape[0]
    tot = 0.0
    for i in range(m):
        y[i] = max(-z[i], 0.0)
        tot += y[i]
    if not tot > 0.0:
        return -np.inf
    yh = 0.0
    for i in range(m):
        y[i] /= tot
        yh += y[i] * h[i]
    bound = 0.0
    for j in range(n):
        v = 0.0
        for i in range(m):
            v += y[i] * G[i, j]
        bound += max(v * lo[j], v * hi[j])
    return yh - bound


@njit(**_opts)
def row_reach(G, m, lo, hi, h, tol, l, l_clipped, reach):
    """Rows no torque in the box ``[lo, hi]`` can satisfy: ``h_k > reach_k + tol`` with
    ``reach_k = Σ_j max(G_kj lo_j, G_kj hi_j)`` (in ``reach`` (m,)). If there is one, fills
    ``l_clipped = l`` with every row's bound lowered to its reach, and returns True."""
    n = lo.shape[0]
    impossible = False
    for i in range(m):
        acc = 0.0
        for j in range(n):
            acc += max(G[i, j] * lo[j], G[i, j] * hi[j])
        reach[i] = acc
        if h[i] > acc + tol:
            impossible = True
    if impossible:
        for k in range(l.shape[0]):
            l_clipped[k] = l[k]
        for i in range(m):
            l_clipped[i] = min(l[i], reach[i])
    return impossible


@njit(**_opts)
def _row_sigma(weights, row_slack_weight, k):
    """σ_k = ``row_slack_weight`` · weights[k] (weights empty: all 1), the repair's cost of row k's slack."""
    return row_slack_weight * (1.0 if weights.shape[0] == 0 else weights[k])


@njit(**_opts)
def repair_rows(r, m, tol, G, l, weights, row_slack_weight, K, k_prev, Gr, hr, iwork):
    """Rows of the per-row repair QP (:meth:`~c3bf_gym.qp.TorqueQP._relax_rows`) for the active-set
    solver: ``K`` = the rows k < m with residual ``r_k < tol``; ``Gr[:m] = (G[:m, :n] | slack
    columns)`` with ``1 / (row_slack_weight · weights_k)`` (weights empty: all 1) in column
    n + i for the i-th row of K, ``hr[:m] = l[:m]``. ``K[:k_prev]`` are the previous call's slack
    rows (their entries are cleared first). Unless K is the previous K and ``iwork`` holds the
    optimal active rows of its solve (:func:`~c3bf_gym._active_set.solve`), ``iwork`` gets the
    solver's warm start "every slack at its bound t = 0": rows ``Gr[len(Gr) − len(K) + i]``.
    Returns len(K)."""
    n = G.shape[1] - 1
    for i in range(k_prev):
        Gr[K[i], n + i] = 0.0
    k = 0
    same = True
    for i in range(m):
        for j in range(n):
            Gr[i, j] = G[i, j]
        hr[i] = l[i]
        if r[i] < tol:
            same = same and k < k_prev and K[k] == i
            K[k] = i
            Gr[i, n + k] = 1.0 / _row_sigma(weights, row_slack_weight, i)
            k += 1
    if not (same and k == k_prev and iwork[0] > 0):
        first = Gr.shape[0] - K.shape[0]
        iwork[0] = k
        for i in range(k):
            iwork[1 + i] = first + i
    return k


@njit(**_opts)
def clip(x, lo, hi, out):
    """``out = min(max(x, lo), hi)`` over ``len(out)`` entries."""
    for j in range(out.shape[0]):
        out[j] = min(max(x[j], lo[j]), hi[j])


@njit(**_opts)
def dual_signs_ok(z, x, m, lo, hi, rel_tol):
    """:meth:`~c3bf_gym.qp.TorqueQP._dual_signs_ok`: row multipliers ``z[:m]`` ≤ tol, box
    multipliers (the last ``len(x)`` entries of ``z``) pointing to the nearer bound."""
    M = z.shape[0] - x.shape[0]
    zmax = 0.0
    for i in range(z.shape[0]):
        zmax = max(zmax, abs(z[i]))
    tol = rel_tol * (1.0 + zmax)
    for i in range(m):
        if z[i] > tol:
            return False
    for i in range(x.shape[0]):
        zb = z[M + i]
        upper = x[i] - lo[i] > hi[i] - x[i]
        if (zb > tol and not upper) or (zb < -tol and upper):
            return False
    return True


@njit(**_opts)
def hook_post(A, b, u, scale, tau_nom, limit, tau):
    """The filter's bookkeeping after the QP: ``tau = u · scale``; returns ``(min_k A_k u − b_k``
    (inf without rows), ``‖tau − clip(tau_nom, ±limit)‖``)."""
    m, n = A.shape
    residual = np.inf
    for i in range(m):
        acc = 0.0
        for j in range(n):
            acc += A[i, j] * u[j]
        residual = min(residual, acc - b[i])
    sq = 0.0
    for j in range(n):
        tau[j] = u[j] * scale[j]
        d = tau[j] - max(min(tau_nom[j], limit[j]), -limit[j])
        sq += d * d
    return residual, math.sqrt(sq)


# ----------------------------------------------------------------------------- the fused filter step


@njit(**_opts)
def _soft_quadratic(W, G, l, nom, pflag, m, weights, row_slack_weight, WJp, x0p, L):
    """The reduced repair's objective for the soft rows P (``pflag[k] == 1``, :func:`reduced_repair`):
    ``H = W + Σ_P σ_k² Â_kᵀ Â_k`` and ``J₀ = L⁻ᵀ`` (H = L Lᵀ, L in the (n, n) scratch ``L``) into
    ``WJp = [H; J₀]``, and the unconstrained minimiser ``x₀ = H⁻¹ (W τ_nom + Σ_P σ_k (1 + σ_k l_k)
    Â_kᵀ)`` into ``x0p``. Returns False if H is not numerically positive definite."""
    n = nom.shape[0]
    H = WJp[:n]
    J0 = WJp[n:2 * n]
    for i in range(n):
        acc = 0.0
        for j in range(n):
            H[i, j] = W[i, j]
            acc += W[i, j] * nom[j]
        x0p[i] = acc
    for k in range(m):
        if pflag[k]:
            s = _row_sigma(weights, row_slack_weight, k)
            c = s * (1.0 + s * l[k])
            for i in range(n):
                x0p[i] += c * G[k, i]
                gi = s * s * G[k, i]
                for j in range(n):
                    H[i, j] += gi * G[k, j]
    for j in range(n):  # Cholesky
        acc = H[j, j]
        for p in range(j):
            acc -= L[j, p] * L[j, p]
        if not acc > 0.0:
            return False
        L[j, j] = math.sqrt(acc)
        for i in range(j + 1, n):
            acc = H[i, j]
            for p in range(j):
                acc -= L[i, p] * L[j, p]
            L[i, j] = acc / L[j, j]
    for i in range(n):  # x₀: forward and back substitution
        acc = x0p[i]
        for p in range(i):
            acc -= L[i, p] * x0p[p]
        x0p[i] = acc / L[i, i]
    for i in range(n - 1, -1, -1):
        acc = x0p[i]
        for p in range(i + 1, n):
            acc -= L[p, i] * x0p[p]
        x0p[i] = acc / L[i, i]
    for c in range(n):  # row c of L⁻ᵀ = column c of L⁻¹ (L y = e_c, y_i = 0 for i < c)
        for i in range(c):
            J0[c, i] = 0.0
        for i in range(c, n):
            acc = 1.0 if i == c else 0.0
            for p in range(c, i):
                acc -= L[i, p] * J0[c, p]
            J0[c, i] = acc / L[i, i]
    return True


@njit(**_opts)
def reduced_repair(G, h, l, r, m, tol, weights, row_slack_weight, W, nom, WJp, x0p, hp, pflag, work, iwork,
                   as_tol, as_vtol, max_iter, max_rounds, stats):
    """The per-row repair (:meth:`~c3bf_gym.qp.TorqueQP._relax_rows`) solved in τ alone.

    Eliminating the slacks leaves ``min ½ (τ − τ_nom)ᵀ W (τ − τ_nom) + Σ_{k∈K} φ_k(l_k − Â_k τ)``
    over the hard rows (k ∉ K) and the box, with ``φ_k(v) = σ_k v + ½ σ_k² v²`` for v > 0 and 0
    otherwise: piecewise quadratic, with the same unique optimum. Its active set is the set P of
    rows of K with a positive slack; for a guess of P the problem is a QP in n variables (rows of P
    in the objective, every other row hard), solved by :func:`~c3bf_gym._active_set.solve`. The
    guess is right, and the point is the slack QP's optimum, when every row of P is violated (v_k
    ≥ −``as_tol``: t_k = σ_k v_k ≥ 0) and every hard row of K has a multiplier ≤ σ_k (a zero
    slack's KKT condition; the slack QP's multiplier of row k is σ_k (1 + t_k)); otherwise the
    rows that break it switch sides and the QP is solved again, at most ``max_rounds`` times.

    The first guess is last call's P (``pflag``) where its rows are still in K, else the rows τ*
    violates most (within 1e-6 of ``min r``: the elastic problem's conflict). When the hard rows
    of a guess conflict, the rows of K in the solver's certificate (active, or violated where it
    stopped) go soft. ``r`` holds τ*'s residuals; ``stats`` (3,) counts the repairs settled here,
    their rounds, and the repairs left to the slack QP. Returns ``(code, steps)``: 0 solved (τ
    in ``work[2n, :n]``, P in ``pflag``), 1 no row to repair, 2 not settled (the caller solves
    the slack QP).
    """
    n = nom.shape[0]
    cap = l.shape[0]
    rmin = np.inf
    nk = 0
    for k in range(m):
        if r[k] < tol:
            nk += 1
            rmin = min(rmin, r[k])
    if nk == 0:
        return 1, 0
    kept = 0  # the first guess: last call's soft rows still in K, or else the rows τ* violates most
    for k in range(m):
        pflag[k] = 1 if r[k] < tol and pflag[k] == 1 else 0
        kept += pflag[k]
    if kept == 0:
        near = rmin + 1e-6 * (1.0 + abs(rmin))
        for k in range(m):
            pflag[k] = 1 if r[k] <= near else 0
    for k in range(m, cap):
        pflag[k] = 0
    for k in range(cap, cap + 2 * n):
        hp[k] = h[k]
    N = work.shape[1] - 1
    steps = 0
    stats[2] += 1  # until it settles
    for rounds in range(1, max_rounds + 1):
        if not _soft_quadratic(W, G, l, nom, pflag, m, weights, row_slack_weight, WJp, x0p, work[:n, :n]):
            return 2, steps
        for k in range(m):
            hp[k] = -np.inf if pflag[k] else l[k]
        q = iwork[0]  # last solve's active rows, less the rows now soft (warm start)
        kept = 0
        for i in range(q):
            a = iwork[1 + i]
            if a >= cap or pflag[a] == 0:
                iwork[1 + kept] = a
                kept += 1
        iwork[0] = kept
        c, solve_steps = _active_set.solve(G, hp, m, cap, 2 * n, x0p, WJp, as_tol, as_vtol, max_iter, True, work,
                                           iwork)
        steps += solve_steps
        x = work[2 * N, :n]
        if c == _active_set.INFEASIBLE:  # the hard rows conflict: the rows of K among the certificate's
            flags = iwork[N + 2:]        # (active, or violated at the point where it stopped) go soft
            grew = False
            for k in range(m):
                if r[k] < tol and pflag[k] == 0 and (flags[k] or _active_set._slack(G, l, k, x) < -as_tol):
                    pflag[k] = 1
                    grew = True
            if not grew:
                return 2, steps
            continue
        if c != _active_set.OPTIMAL:
            return 2, steps
        u = work[2 * N + 4]
        settled = True
        for k in range(m):  # soft rows that the optimum satisfies: back to hard
            if pflag[k] and _active_set._slack(G, l, k, x) > as_tol:
                pflag[k] = 0
                settled = False
        for i in range(iwork[0]):  # hard rows of K whose multiplier exceeds σ_k: soft
            k = iwork[1 + i]
            if k < m and r[k] < tol:
                if u[i] > _row_sigma(weights, row_slack_weight, k) * (1.0 + 1e-9):
                    pflag[k] = 1
                    settled = False
        if settled:
            stats[0] += 1
            stats[1] += rounds
            stats[2] -= 1
            return 0, steps
    return 2, steps


@njit(**_opts)
def repair_step(G, xe, h, r, m, tol, l, weights, row_slack_weight, K, k_prev, Gr, hr, rep_iwork, x0r, nom, WJx,
                as_tol, as_vtol, max_iter, rep_work, lo, hi, u, W, WJp, x0p, hp, pflag, pw_work, pw_iwork,
                max_rounds, rep_stats):
    """The per-row repair of the elastic torque τ* in ``xe`` (:meth:`~c3bf_gym.qp.TorqueQP._relax_rows`)
    by the active-set solver: τ*'s residuals into ``r``, then the problem in τ alone
    (:func:`reduced_repair`, ``max_rounds`` > 0; ``W`` … ``pw_iwork`` and ``rep_stats`` its
    buffers) and, if it does not settle, in (τ, t_K): the repair rows (:func:`repair_rows`), x₀ = (``nom``, −1, …) and the
    solve. The repaired torque, clipped, goes into ``u``. Returns ``(code, steps, k)``: code 0
    repaired, 1 no row to repair (k = 0), 2 the solver stopped at its cap or failed its check (hand
    over to proxsuite); k is the slack QP's row count (unchanged when it was not needed)."""
    n = nom.shape[0]
    residuals(G, xe, h, r)
    steps = 0
    if max_rounds > 0:
        c, steps = reduced_repair(G, h, l, r, m, tol, weights, row_slack_weight, W, nom, WJp, x0p, hp, pflag,
                                  pw_work, pw_iwork, as_tol, as_vtol, max_iter, max_rounds, rep_stats)
        if c == 0:
            clip(pw_work[2 * (pw_work.shape[1] - 1)], lo, hi, u)
            return 0, steps, k_prev
    k = repair_rows(r, m, tol, G, l, weights, row_slack_weight, K, k_prev, Gr, hr, rep_iwork)
    if k == 0:
        return 1, steps, k
    for j in range(n):
        x0r[j] = nom[j]
    c, s = _active_set.solve(Gr, hr, m, G.shape[0] - 2 * n, 2 * n + k, x0r[:n + k], WJx, as_tol, as_vtol,
                             max_iter + 2 * k, True, rep_work, rep_iwork)
    steps += s
    if c != _active_set.OPTIMAL:
        return 2, steps, k
    clip(rep_work[2 * (rep_work.shape[1] - 1)], lo, hi, u)
    return 0, steps, k


@njit(**_opts)
def qp_step(tau_nom, A, b, scale, weights, m_prev, k_prev, max_iter, tol, row_slack_weight, diag_W,
            Gx, hx, hcx, nrm, r, xe, nom, lo, hi, reach, negW, g, qp_f,
            WJ, as_work, as_iwork, x0r, WJx, el_work, el_iwork, Kr, Gr, hr, rep_work, rep_iwork, WJp, x0p, hp,
            pflag, pw_work, pw_iwork, rep_stats):
    """:class:`~c3bf_gym.qp.TorqueQP`'s active-set call (``solver="active_set"``): the data step
    (:func:`qp_prepare`), the fast path, the hard solve and, after an infeasibility proof, the
    elastic solve and the per-row repair (:func:`repair_step`), then the result's statistics.

    ``Gx`` … ``rep_stats`` are the layer's buffers, ``qp_f`` = ``[row norm min, inf, active-set
    tol, active-set vtol, σ, the reduced repair's rounds]``, ``weights`` the relaxation weights
    (empty: all 1). The torque (in the scaled units) is ``xe[:n]``. Returns ``(status, steps, repair slack count, active rows,
    slack)``, status one of ``STEP_*``; the last two only when it is ≤ ``STEP_RELAXED_AS_IS``.
    """
    n = nom.shape[0]
    m = A.shape[0]
    cap = nrm.shape[0]
    G = Gx[:cap + 2 * n]
    h = hx[:cap + 2 * n]
    as_tol = qp_f[2]
    as_vtol = qp_f[3]
    code, rmin, impossible = qp_prepare(tau_nom, A, b, scale, G, h, nrm, r, xe, nom, m_prev, qp_f[0], qp_f[1],
                                        lo, hi, tol, h[:cap], hcx[:cap], reach, negW, g)
    if code < 0:
        return code, 0, k_prev, 0, 0.0
    u = xe[:n]
    status = STEP_SOLVED
    steps = 0
    k = k_prev
    elastic = impossible
    if rmin >= 0.0 or (m == 0 and diag_W):
        if rmin < 0.0:
            clip(nom, lo, hi, u)
    elif not impossible:
        c, steps = _active_set.solve(G, h, m, cap, 2 * n, nom, WJ, as_tol, as_vtol, max_iter, True, as_work,
                                     as_iwork)
        if c == _active_set.OPTIMAL:
            clip(as_work[2 * (as_work.shape[1] - 1)], lo, hi, u)
        elif c == _active_set.INFEASIBLE:
            elastic = True
        else:
            return STEP_TO_ELASTIC, steps, k, 0, 0.0
    if elastic:
        for j in range(n):
            x0r[j] = nom[j]
        c, s = _active_set.solve(Gx, hcx if impossible else hx, m, cap, 2 * n + 1, x0r[:n + 1], WJx, as_tol,
                                 as_vtol, max_iter, True, el_work, el_iwork)
        steps += s
        if c != _active_set.OPTIMAL:
            return (STEP_TO_ELASTIC_IMPOSSIBLE if impossible else STEP_TO_ELASTIC), steps, k, 0, 0.0
        el_x = el_work[2 * (el_work.shape[1] - 1)]
        clip(el_x, lo, hi, u)
        if impossible or el_x[n] / qp_f[4] > tol:  # the per-row repair (TorqueQP._relax_rows)
            out = STEP_TO_REPAIR_IMPOSSIBLE if impossible else STEP_TO_REPAIR
            if m == 0:
                residuals(G, xe, h, r)
                return out, steps, k, 0, 0.0
            l = hcx[:cap] if impossible else h[:cap]
            c, s, k = repair_step(G, xe, h, r, m, tol, l, weights, row_slack_weight, Kr, k_prev, Gr, hr, rep_iwork,
                                  x0r, nom, WJx, as_tol, as_vtol, max_iter, rep_work, lo, hi, u, WJ[:n], WJp, x0p,
                                  hp, pflag, pw_work, pw_iwork, int(qp_f[5]), rep_stats)
            steps += s
            if c == 2:
                return out, steps, k, 0, 0.0
            status = STEP_RELAXED if c == 0 else STEP_RELAXED_AS_IS
    n_active, violation = result_stats(G, xe, h, r, m, tol, rmin < 0.0)
    return status, steps, k, n_active, 0.0 if status == STEP_SOLVED else violation


@njit(**_opts)
def _vector(arena, layout, i):
    """Buffer ``i`` of :func:`step_views`, 1-D."""
    start = layout[i, 0]
    return arena[start:start + layout[i, 1]]


@njit(**_opts)
def _matrix(arena, layout, i):
    """Buffer ``i`` of :func:`step_views`, 2-D."""
    start = layout[i, 0]
    return arena[start:start + layout[i, 1] * layout[i, 2]].reshape((layout[i, 1], layout[i, 2]))


@njit(**_opts)
def step_views(qf, qi, layout):
    """:meth:`~c3bf_gym.qp.TorqueQP.step_buffers` (:func:`qp_step`'s ``Gx`` … ``rep_stats``) from
    :meth:`~c3bf_gym.qp.TorqueQP.packed_step_buffers`: views of the float64 arena ``qf`` and the
    int64 arena ``qi`` at the ``layout`` rows (``c3bf_gym.qp._step_buffer_shapes``' order)."""
    return (_matrix(qf, layout, 0), _vector(qf, layout, 1), _vector(qf, layout, 2), _vector(qf, layout, 3),
            _vector(qf, layout, 4), _vector(qf, layout, 5), _vector(qf, layout, 6), _vector(qf, layout, 7),
            _vector(qf, layout, 8), _vector(qf, layout, 9), _matrix(qf, layout, 10), _vector(qf, layout, 11),
            _vector(qf, layout, 12), _matrix(qf, layout, 13), _matrix(qf, layout, 14), _vector(qi, layout, 15),
            _vector(qf, layout, 16), _matrix(qf, layout, 17), _matrix(qf, layout, 18), _vector(qi, layout, 19),
            _vector(qi, layout, 20), _matrix(qf, layout, 21), _vector(qf, layout, 22), _matrix(qf, layout, 23),
            _vector(qi, layout, 24), _matrix(qf, layout, 25), _vector(qf, layout, 26), _vector(qf, layout, 27),
            _vector(qi, layout, 28), _matrix(qf, layout, 29), _vector(qi, layout, 30), _vector(qi, layout, 31))


@njit(**_opts)
def guard_weights(weights, n_obstacle_rows, barrier_weight):
    """The relaxation weights of a guarded filter's rows (:class:`~c3bf_gym.safety.SafetyController`):
    the first ``n_obstacle_rows`` alternate barrier row, guard row; the barrier's weigh
    ``barrier_weight``, every other row 1."""
    for i in range(weights.shape[0]):
        weights[i] = barrier_weight if i < n_obstacle_rows and i % 2 == 0 else 1.0


@njit(**_opts)
def hook_step(stage, tau_nom, m_prev, k_prev, max_iter, tol, row_slack_weight, diag_W, tau,
              M, qfrc_passive, qfrc_bias, geom_xpos, geom_xmat, cdof, cdof_dot, com, qpos, qvel,
              arm_i, arm_f, chain, scratch, Minv, qacc_free, ends, ends_ab, a_dot_ab,
              active, distances, obs_pos, obs_vel, obs_acc, obs_radius, kind, floor_idx, floor_min,
              joint_rows, hook_f, work, A, b, weights, scale, limit, qf, qi, layout):
    """One whole-arm filter step in one call (:meth:`~c3bf_gym.safety.SafetyController.__call__`): the
    rows (:func:`hook_rows_whole_arm`), :meth:`~c3bf_gym.qp.TorqueQP.solve_scaled`'s active-set
    call (:func:`qp_step`, the same code the layer runs) and :func:`hook_post`; what saves time
    is one dispatch instead of three and no Python in between.

    ``M`` … ``b`` are :func:`hook_rows_whole_arm`'s arguments (``M`` here is MuJoCo's mass
    matrix); ``qf``, ``qi``, ``layout`` hold :func:`qp_step`'s buffers (:func:`step_views`).
    With a guard (``hook_f[10 + 3 nv] > 0``), the relaxation weights go into ``weights[:rows]``
    (:func:`guard_weights`) and :func:`qp_step` gets them; without one, none (all rows weigh 1).
    Writes the torque into ``tau`` when done. Returns ``(status, rows, min h, any inside, sensed
    count, steps, repair slack count, active rows, slack, min row residual, correction)``, status
    one of ``STEP_*``; the last four are only set when done.
    """
    (Gx, hx, hcx, nrm, r, xe, nom, lo, hi, reach, negW, g, qp_f, WJ, as_work, as_iwork, x0r, WJx, el_work,
     el_iwork, Kr, Gr, hr, rep_work, rep_iwork, WJp, x0p, hp, pflag, pw_work, pw_iwork, rep_stats) = step_views(
        qf, qi, layout)
    m, min_h, inside, n_sensed = hook_rows_whole_arm(
        stage, M, qfrc_passive, qfrc_bias, geom_xpos, geom_xmat, cdof, cdof_dot, com, qpos, qvel, arm_i, arm_f,
        chain, scratch, Minv, qacc_free, ends, ends_ab, a_dot_ab, active, distances, obs_pos, obs_vel, obs_acc,
        obs_radius, kind, floor_idx, floor_min, joint_rows, hook_f, work, A, b)
    nv = Minv.shape[0]
    w = nrm[:0]
    if hook_f[10 + 3 * nv] > 0.0:
        n_fixed = floor_idx.shape[0] + (4 * nv if joint_rows else 0)
        guard_weights(weights[:m], m - n_fixed, hook_f[11 + 3 * nv])
        w = weights[:m]
    status, steps, k, n_active, slack = qp_step(
        tau_nom, A[:m], b[:m], scale, w, m_prev, k_prev, max_iter, tol, row_slack_weight, diag_W, Gx, hx, hcx,
        nrm, r, xe, nom, lo, hi, reach, negW, g, qp_f, WJ, as_work, as_iwork, x0r, WJx, el_work, el_iwork, Kr, Gr,
        hr, rep_work, rep_iwork, WJp, x0p, hp, pflag, pw_work, pw_iwork, rep_stats)
    if status < 0 or status > STEP_RELAXED_AS_IS:
        return status, m, min_h, inside, n_sensed, steps, k, 0, 0.0, 0.0, 0.0
    residual, correction = hook_post(A[:m], b[:m], xe[:nom.shape[0]], scale, tau_nom, limit, tau)
    return status, m, min_h, inside, n_sensed, steps, k, n_active, slack, residual, correction
