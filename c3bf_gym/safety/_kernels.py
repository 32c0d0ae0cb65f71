"""Compiled (numba) kernels of the safety filter's hot path.

The filter runs at every physics step (500 Hz), and its numpy version spent most of its time in
the overhead of many small array calls (microseconds each), not in arithmetic: the arm has 6 joints
and 7 capsules, so every array holds tens of numbers. These kernels do the same arithmetic in
plain loops, compiled once by numba (``cache=True``: the machine code is cached on disk next to
this file, or in numba's user-wide cache when that folder is read-only, so later processes load
it instead of compiling). They allocate nothing and are compiled without numba's reference
counting (:data:`~c3bf_gym._compile_cache.STEP_KERNEL_OPTIONS`).

Each piece of math lives once, in an inner ``@njit`` function that works on one point or one row;
the public classes call it through small vectorised kernels, and the filter's fused kernel
(:func:`hook_rows_whole_arm`) calls the same inner functions directly:

* :func:`step_inverse`: ``(M + h D)⁻¹`` and ``qacc_free`` (:class:`~c3bf_gym.safety.dynamics.ArmModel`).
* :func:`point_dynamics` / :func:`capsule_ends`: position, velocity, ``c``, ``G`` and Jacobian of
  points on the arm, from ``cdof`` and ``cdof_dot`` (the formulas of :mod:`c3bf_gym.safety.dynamics`).
* :func:`closest_relative`: closest points on the capsule axes, relative to moving obstacles,
  with their sliding terms (:func:`_closest_pair`: one pair, its terms from :func:`_closest_terms`).
* :func:`c3bf_terms`, :func:`hocbf_terms`, :func:`rows_from_terms`, :func:`joint_limit_rows`: the
  barriers of :mod:`c3bf_gym.safety.barriers`.
* :func:`hook_rows_whole_arm`: every row of the whole-arm filter in one call, and
  :func:`hook_substep`: those rows, the QP (:func:`c3bf_gym.safety._daqp.solve_rows`),
  :func:`hook_post` and the report's running values (:func:`record` into a :class:`Tally`);
  :func:`hook_substep_at`: the same with its buffers by address, for calls from Python.

The floating-point operations follow the numpy code they replace (same formulas, same order where
it matters), so results agree with it to rounding (~1e-15 relative).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from c3bf_gym._compile_cache import STEP_KERNEL_OPTIONS  # (before any @njit(cache=True): the cache keys)
from c3bf_gym._capi import unpack

# hook_substep compiles _daqp.solve_rows into itself: _compile_cache keys the on-disk cache of both
# files' functions on both files.
from c3bf_gym.safety._daqp import ACTIVE_TOL, RELAXED, SOLVED, solve_rows

#: barrier kinds of the fused kernel
C3BF_KIND = 0
HOCBF_KIND = 1

_opts = STEP_KERNEL_OPTIONS


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
    """Fill ``packed[p, :, 1:]`` (velocity, ``c``, ``G``) and ``jac[p]`` of the point ``x`` (a 3-tuple)
    moving with the dofs where ``chain`` (nv,) is nonzero (:mod:`c3bf_gym.safety.dynamics`'s formulas:
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
    for p in range(packed.shape[0]):
        x = (packed[p, 0, 0], packed[p, 1, 0], packed[p, 2, 0])
        _one_point(p, x, chain[p], cdof, cdof_dot, com, qvel, Minv, qacc_free, packed, jac)


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
    for p in range(2 * s_count):
        x = (ends[p, 0, 0], ends[p, 1, 0], ends[p, 2, 0])
        _one_point(p, x, arm.chain[p % s_count], arm.cdof, arm.cdof_dot, arm.com, arm.qvel, arm.Minv, arm.qacc_free,
                   ends, arm.end_jac)
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
def _closest_terms(ends_a, ends_ab, a_dot_ab, length2, s, o, vo, ao):
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
def _closest_pair(ends_a, ends_ab, a_dot_ab, length2, s, o, vo, ao, G):
    """:func:`_closest_terms`, with the point's ``G`` (3, nv) written out: returns
    ``(t, p, v, c, slide)``."""
    t, tc, p, v, c, slide = _closest_terms(ends_a, ends_ab, a_dot_ab, length2, s, o, vo, ao)
    for i in range(3):
        for j in range(G.shape[1]):
            G[i, j] = tc * ends_ab[s, i, 3 + j] + ends_a[s, i, 3 + j]
    return t, p, v, c, slide


@njit(**_opts)
def closest_relative(ends_a, ends_ab, a_dot_ab, length2, centres, velocities, accelerations,
                     p, v, c, G, slide, t):
    """:func:`_closest_pair` for every (obstacle k, capsule s), obstacle-major (row k S + s):
    ``p, v, c, slide`` (K S, 3), ``G`` (K S, 3, nv), ``t`` (K, S)."""
    s_count = ends_a.shape[0]
    for k in range(centres.shape[0]):
        for s in range(s_count):
            row = k * s_count + s
            t[k, s], p[row], v[row], c[row], slide[row] = _closest_pair(
                ends_a, ends_ab, a_dot_ab, length2, s, centres[k], velocities[k], accelerations[k], G[row])


# ----------------------------------------------------------------------------- barriers


@njit(**_opts)
def _c3bf_point(p, v, r, gamma, eps, delta):
    """C3BF at one point (:class:`~c3bf_gym.safety.barriers.C3BF`), ``p``, ``v`` 3-tuples: returns
    ``(h, drift, inside, grad_v, grad_p)``, the gradients 3-tuples."""
    h0 = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]) - r * r
    inside = h0 <= 0.0
    pv = p[0] * v[0] + p[1] * v[1] + p[2] * v[2]
    if inside:
        h = pv + 0.5 * gamma * h0
        grad_v = p
        grad_p = (v[0] + gamma * p[0], v[1] + gamma * p[1], v[2] + gamma * p[2])
    else:
        s = math.sqrt(max(h0, delta * delta))
        vv = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
        vn = math.sqrt(vv + eps * eps)
        h = vn * s + pv
        sv = s / vn
        vs = vn / s
        grad_v = (v[0] * sv + p[0], v[1] * sv + p[1], v[2] * sv + p[2])
        grad_p = (p[0] * vs + v[0], p[1] * vs + v[1], p[2] * vs + v[2])
    drift = grad_p[0] * v[0] + grad_p[1] * v[1] + grad_p[2] * v[2]
    return h, drift, inside, grad_v, grad_p


@njit(**_opts)
def _hocbf_point(p, v, r, gamma1):
    """Distance HOCBF at one point (:class:`~c3bf_gym.safety.barriers.DistanceHOCBF`), ``p``, ``v``
    3-tuples: returns ``(ψ₁, drift, inside, grad_v, grad_p)``, the gradients 3-tuples."""
    h0 = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]) - r * r
    pv2 = (p[0] * v[0] + p[1] * v[1] + p[2] * v[2]) * 2.0
    h = h0 * gamma1 + pv2
    drift = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) * 2.0 + pv2 * gamma1
    g2 = 2.0 * gamma1
    grad_v = (2.0 * p[0], 2.0 * p[1], 2.0 * p[2])
    grad_p = (p[0] * g2 + 2.0 * v[0], p[1] * g2 + 2.0 * v[1], p[2] * g2 + 2.0 * v[2])
    return h, drift, h0 <= 0.0, grad_v, grad_p


@njit(**_opts)
def _vec3(x):
    """The 3-tuple of a (3,) array's entries."""
    return x[0], x[1], x[2]


@njit(**_opts)
def c3bf_terms(p, v, r, gamma, eps, delta, h, grad_v, drift, inside, grad_p):
    """:func:`_c3bf_point` for P points: ``p, v`` (P, 3), ``r`` (P,) into the outputs."""
    for k in range(p.shape[0]):
        h[k], drift[k], inside[k], grad_v[k], grad_p[k] = _c3bf_point(_vec3(p[k]), _vec3(v[k]), r[k], gamma, eps,
                                                                       delta)


@njit(**_opts)
def hocbf_terms(p, v, r, gamma1, h, grad_v, drift, inside, grad_p):
    """:func:`_hocbf_point` for P points: ``p, v`` (P, 3), ``r`` (P,) into the outputs."""
    for k in range(p.shape[0]):
        h[k], drift[k], inside[k], grad_v[k], grad_p[k] = _hocbf_point(_vec3(p[k]), _vec3(v[k]), r[k], gamma1)


@njit(**_opts)
def _row_rhs(grad_v, c, drift, h, gamma):
    """A torque row's ``b = −(⟨grad_v, c⟩ + drift + γ h)`` (``grad_v``, ``c`` 3-tuples)."""
    return -(((grad_v[0] * c[0] + grad_v[1] * c[1] + grad_v[2] * c[2]) + drift) + gamma * h)


@njit(**_opts)
def _row(grad_v, G, c, drift, h, gamma, A_row):
    """One torque row: ``A_row = grad_vᵀ G`` and returns its ``b`` (:func:`_row_rhs`)."""
    for j in range(G.shape[1]):
        A_row[j] = grad_v[0] * G[0, j] + grad_v[1] * G[1, j] + grad_v[2] * G[2, j]
    return _row_rhs(grad_v, c, drift, h, gamma)


@njit(**_opts)
def _sliding_rhs(grad_v, grad_p, slide, c, drift, h, gamma):
    """:func:`_row_rhs` for a closest point sliding by ``slide`` along its link: less the sliding
    term ``⟨grad_p, slide⟩`` (3-tuples)."""
    bk = _row_rhs(grad_v, c, drift, h, gamma)
    return bk - (grad_p[0] * slide[0] + grad_p[1] * slide[1] + grad_p[2] * slide[2])


@njit(**_opts)
def _pair_rows(ends_a, ends_ab, s, tc, grad_v, grad_w, A, m, both):
    """The coefficients ``A[m] = grad_vᵀ G`` (and, with ``both``, ``A[m + 1] = grad_wᵀ G``) of the
    rows at the point ``tc`` of capsule ``s``'s axis, ``G = G_a + tc (G_b − G_a)`` taken column by
    column as the rows need it (the same arithmetic as :func:`_closest_pair`'s ``G`` and
    :func:`_row`, without writing ``G`` out and reading it back)."""
    for j in range(A.shape[1]):
        g0 = tc * ends_ab[s, 0, 3 + j] + ends_a[s, 0, 3 + j]
        g1 = tc * ends_ab[s, 1, 3 + j] + ends_a[s, 1, 3 + j]
        g2 = tc * ends_ab[s, 2, 3 + j] + ends_a[s, 2, 3 + j]
        A[m, j] = grad_v[0] * g0 + grad_v[1] * g1 + grad_v[2] * g2
        if both:
            A[m + 1, j] = grad_w[0] * g0 + grad_w[1] * g1 + grad_w[2] * g2


@njit(**_opts)
def rows_from_terms(grad_v, drift, h, gamma, G, c, A, b):
    """:func:`_row` for P points: ``G`` (P, 3, n), ``c`` (P, 3) into ``A`` (P, n), ``b`` (P,)."""
    for k in range(h.shape[0]):
        b[k] = _row(_vec3(grad_v[k]), G[k], _vec3(c[k]), drift[k], h[k], gamma, A[k])


@njit(**_opts)
def joint_limit_rows(q, qd, Minv, c_q, dofs, qpos_ids, q_lo, q_hi, qd_max, g1, g2, gv, A, b):
    """The ``4n`` rows of :class:`~c3bf_gym.safety.barriers.JointLimits` into ``A`` (4n, k), ``b`` (4n,)
    (row blocks: position upper, position lower, speed upper, speed lower) for the ``n`` joints at
    dofs ``dofs`` (rows of ``Minv`` (·, k), entries of ``qd``, ``c_q``) and ``qpos`` addresses
    ``qpos_ids`` (entries of ``q``). An infinite limit's position row is ``0 τ ≥ −1``."""
    n = dofs.shape[0]
    ncol = Minv.shape[1]
    g12 = g1 * g2
    g1p2 = g1 + g2
    for i in range(n):
        d = dofs[i]
        for j in range(ncol):
            mij = Minv[d, j]
            A[i, j] = -mij
            A[n + i, j] = mij
            A[2 * n + i, j] = -mij
            A[3 * n + i, j] = mij
        qi, qdi, ci = q[qpos_ids[i]], qd[d], c_q[d]
        b[i] = ((g12 * qi + g1p2 * qdi) + ci) + (-g12 * q_hi[i])
        b[n + i] = ((-g12 * qi + -g1p2 * qdi) + -ci) + g12 * q_lo[i]
        for k, limit in ((i, q_hi[i]), (n + i, q_lo[i])):  # none on that side (a continuous joint): 0 τ ≥ −1
            if math.isinf(limit):
                A[k, :ncol] = 0.0
                b[k] = -1.0
        b[2 * n + i] = (gv * qdi + ci) + (-gv * qd_max[i])
        b[3 * n + i] = (-gv * qdi + -ci) + (-gv * qd_max[i])


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


@njit(**_opts)
def unmodelled_margin(A, b, bound):
    """Tighten rows ``A f ≥ b`` (m, nv), written for the generalised force ``f`` on every dof, for
    forces the filter cannot predict: ``b_k += Σ_j |A_kj| bound_j``.

    A force ``φ_j`` with ``|φ_j| ≤ bound_j`` (:attr:`~c3bf_gym.safety.RobotDescription.unmodelled_force`:
    joint dry friction, the actuators of dofs that are not the arm's) enters every row as the
    torque does, so ``A (τ + φ) ≥ b`` for every admissible ``φ`` exactly when the tightened row
    holds at ``τ``. A no-op when every bound is 0.

    The filter tightens the obstacle and floor rows, not the joint-limit rows: a joint's own
    friction opposes its motion, so it never drives the joint towards a position or speed limit,
    and the worst case over ``|φ_j| ≤ bound_j`` (a friction that accelerates a joint at rest) would
    leave a light arm no torque for them (robosuite's Jaco at rest). The other dofs' forces reach
    those rows only through the coupling of ``M⁻¹``, which they leave out."""
    nv = bound.shape[0]
    largest = 0.0
    for j in range(nv):
        largest = max(largest, bound[j])
    if largest <= 0.0:
        return
    for k in range(b.shape[0]):
        extra = 0.0
        for j in range(nv):
            extra += abs(A[k, j]) * bound[j]
        b[k] += extra


# ----------------------------------------------------------------------------- the fused filter rows


class ArmArrays(NamedTuple):
    """What the fused kernels read and write of an arm (:meth:`~c3bf_gym.safety.dynamics.ArmModel.kernel_arrays`):
    views, updated in place, never replaced. ``S`` protected geoms, ``nv`` dofs.

    Attributes:
        M, qfrc_passive, qfrc_bias, geom_xpos, geom_xmat, xpos, xmat, cdof, cdof_dot, com, qpos,
            qvel: the ``MjData`` arrays the dynamics read (``com``: the arm's root subtree centre of
            mass).
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
        ends, ends_ab, a_dot_ab: the capsule ends' packed dynamics (:func:`capsule_ends`).
    """

    M: np.ndarray
    qfrc_passive: np.ndarray
    qfrc_bias: np.ndarray
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
    ends: np.ndarray
    ends_ab: np.ndarray
    a_dot_ab: np.ndarray


class ObstacleArrays(NamedTuple):
    """The obstacles as the fused kernels read them (:class:`~c3bf_gym.safety.Obstacles`' arrays):
    ``active`` (K,) bool; ``distances`` (K, G) their surface distances to the arm's geoms [m]
    ((K, 0): none kept, the kernel measures them); ``position``, ``velocity``, ``acceleration``
    (K, 3) [m, m/s, m/s²]; ``radius`` (K,) [m]."""

    active: np.ndarray
    distances: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    radius: np.ndarray


class RowParams(NamedTuple):
    """The fused rows' settings (:class:`~c3bf_gym.safety.SafetyController` builds them once).

    Attributes:
        kind: :data:`C3BF_KIND` or :data:`HOCBF_KIND`, the barrier.
        gamma, p1, p2: the barrier's gains (its ``fused_spec``): C3BF γ, ε, δ; HOCBF γ₂, γ₁, unused.
        guard_gamma1, guard_gamma2: a distance-HOCBF guard's gains (0: no guard).
        sensing_radius, margin: [m].
        floor_gamma: the floor rows' gain [1/s]; ``floor_ends`` (F,) the capsule ends that get
            one, ``floor_min`` (F,) their lowest allowed heights [m].
        joint_rows: add the ``4 n`` joint-limit rows, with ``joint_gains`` (γ₁, γ₂, γ_v) and the
            limits ``q_lo``, ``q_hi``, ``qd_max`` (n,).
        dofs, qpos_ids: (n,) the arm's dofs and their ``qpos`` addresses.
        unmodelled_force: (nv,) bounds of the forces the filter cannot predict (:func:`unmodelled_margin`).
    """

    kind: int
    gamma: float
    p1: float
    p2: float
    guard_gamma1: float
    guard_gamma2: float
    sensing_radius: float
    margin: float
    floor_gamma: float
    floor_ends: np.ndarray
    floor_min: np.ndarray
    joint_rows: bool
    joint_gains: np.ndarray
    q_lo: np.ndarray
    q_hi: np.ndarray
    qd_max: np.ndarray
    dofs: np.ndarray
    qpos_ids: np.ndarray
    unmodelled_force: np.ndarray


@njit(**_opts)
def hook_rows_whole_arm(stage, arm, obstacles, params, A, b, row_h):
    """All rows of the whole-arm filter (:meth:`~c3bf_gym.safety.SafetyController.rows`) in one call.

    1. ``stage`` 2: ``Minv``, ``qacc_free`` (:func:`step_inverse`), then (``stage`` ≥ 1) the
       capsule ends (:func:`capsule_ends`), into ``arm`` (:class:`ArmArrays`).
    2. For every sensed obstacle (:class:`ObstacleArrays`: active and ``distances[k].min() <=
       sensing_radius``, or with ``distances`` of shape (K, 0) its surface distance to the
       capsules), one row per capsule: closest point (:func:`_closest_terms`), barrier
       ``params.kind`` (:func:`_c3bf_point` or :func:`_hocbf_point`), row (:func:`_sliding_rhs`,
       with the sliding term ``−⟨grad_p, ṫ (b − a)⟩``, and :func:`_pair_rows`); with a guard
       (``params.guard_gamma2 > 0``), the guard's row for the same point right after it.
    3. The floor rows of the capsule ends ``params.floor_ends`` (:func:`floor_rows`).
    4. With ``params.joint_rows``, the ``4 nv`` joint-limit rows (:func:`joint_limit_rows`).
    Before the joint-limit rows, the obstacle and floor rows are tightened for the forces the
    filter cannot predict (:func:`unmodelled_margin`).

    The rows are written for the generalised force on every dof of the model (``A`` (·, nv)); the
    QP reads the columns of the arm's dofs (``params.dofs``).

    The rows go to ``A``, ``b``, and each barrier row's ``h`` to ``row_h`` at the row's index (the
    guard's and the other rows' entries are left as they are). Returns ``(rows, min h of the
    barrier's rows (not the guard's), any inside, sensed count)``.
    """
    s_count = arm.ends_ab.shape[0]
    n = params.dofs.shape[0]
    if stage >= 2:
        step_inverse(arm.M, arm.M_rowadr, arm.M_rownnz, arm.M_colind, arm.damping, arm.qfrc_passive, arm.qfrc_bias,
                     arm.factor, arm.Minv, arm.qacc_free)
    if stage >= 1:
        capsule_ends(arm)
    ends_a = arm.ends[:s_count]
    ends_ab, a_dot_ab, length2, capsule_radius = arm.ends_ab, arm.a_dot_ab, arm.length2, arm.capsule_radius
    gamma = params.gamma
    guard = params.guard_gamma2 > 0.0
    distances = obstacles.distances
    m = 0
    n_sensed = 0
    min_h = np.inf
    inside_any = False
    for k in range(obstacles.active.shape[0]):
        if not obstacles.active[k]:
            continue
        dmin = np.inf
        for g in range(distances.shape[1]):
            dmin = min(dmin, distances[k, g])
        if distances.shape[1] == 0:  # no distances kept by the obstacles' owner: to the capsules
            dmin = _surface_gap(ends_a, ends_ab, a_dot_ab, length2, capsule_radius, obstacles.position[k],
                                obstacles.radius[k])
        if not dmin <= params.sensing_radius:
            continue
        n_sensed += 1
        o, vo, ao = obstacles.position[k], obstacles.velocity[k], obstacles.acceleration[k]
        for s in range(s_count):
            _, tc, p, v, c, slide = _closest_terms(ends_a, ends_ab, a_dot_ab, length2, s, o, vo, ao)
            r = (obstacles.radius[k] + capsule_radius[s]) + params.margin
            if params.kind == C3BF_KIND:
                h, drift, inside, grad_v, grad_p = _c3bf_point(p, v, r, gamma, params.p1, params.p2)
            else:
                h, drift, inside, grad_v, grad_p = _hocbf_point(p, v, r, params.p1)
            b[m] = _sliding_rhs(grad_v, grad_p, slide, c, drift, h, gamma)
            row_h[m] = h
            min_h = min(min_h, h)
            inside_any = inside_any or inside
            grad_w = grad_v
            if guard:
                h, drift, _, grad_w, grad_q = _hocbf_point(p, v, r, params.guard_gamma1)
                b[m + 1] = _sliding_rhs(grad_w, grad_q, slide, c, drift, h, params.guard_gamma2)
            _pair_rows(ends_a, ends_ab, s, tc, grad_v, grad_w, A, m, guard)
            m += 2 if guard else 1
    n_floor = params.floor_ends.shape[0]
    floor_rows(arm.ends, params.floor_ends, params.floor_min, params.floor_gamma, A[m:m + n_floor], b[m:m + n_floor])
    m += n_floor
    unmodelled_margin(A[:m], b[:m], params.unmodelled_force)
    if params.joint_rows:
        gains = params.joint_gains
        joint_limit_rows(arm.qpos, arm.qvel, arm.Minv, arm.qacc_free, params.dofs, params.qpos_ids, params.q_lo,
                         params.q_hi, params.qd_max,
                         gains[0], gains[1], gains[2], A[m:m + 4 * n], b[m:m + 4 * n])
        m += 4 * n
    return m, min_h, inside_any, n_sensed


# ----------------------------------------------------------------------------- the fused filter step


@njit(**_opts)
def hook_post(b, norm, residual, u, scale, tau_nom, limit, tau):
    """The filter's bookkeeping after the QP (:func:`c3bf_gym.safety._daqp.solve_rows` on ``m``
    rows ``A τ ≥ b``; ``norm``, ``residual`` (m,) its ``qp.norm`` and ``qp.residual``):
    ``tau = u · scale``; returns ``(min_k A_k tau − b_k`` in the rows' own units (inf without
    rows), ``‖tau − clip(tau_nom, ±limit)‖)``.

    ``A_k tau − b_k`` is taken as ``‖A_k s‖ (â_k u − b̂_k)``, the row's norm times its normalised
    residual at ``u``: the same value up to rounding, without a second pass over the rows. A row
    no torque can change (``norm[k] == 0``) counts ``−b_k``."""
    n = u.shape[0]
    sq = 0.0
    for j in range(n):
        tau[j] = u[j] * scale[j]
        d = tau[j] - max(min(tau_nom[j], limit[j]), -limit[j])
        sq += d * d
    low = np.inf
    for k in range(b.shape[0]):
        low = min(low, norm[k] * residual[k] if norm[k] > 0.0 else -b[k])
    return low, math.sqrt(sq)


@njit(**_opts)
def low_priority_span(m, n_fixed, guarded):
    """The priority rule of the filter's QP: of ``m`` rows whose last ``n_fixed`` are the floor's
    and the joint limits', how many leading (obstacle) rows hold the priority-2 rows (every other
    one, the barrier's; :func:`c3bf_gym.safety._daqp.solve_rows`' ``n_obstacle_rows``). Beside a
    guard (``guarded``) the barrier's rows give way first: all obstacle rows. Without one every
    row has priority 1: 0."""
    return m - n_fixed if guarded else 0


@njit(**_opts)
def violations_by_kind(residual, norm, n_obstacle, stride, n_floor, tol, out):
    """Fold one call's row residuals into ``out`` (5,): for each kind of row, in the order of
    :data:`~c3bf_gym.safety.controller.ROW_KINDS` (barrier, guard, floor, joint limits,
    unmovable), the largest violation ``−residual[k]`` above ``tol`` and above what ``out``
    holds.

    The rows are laid out as the filter builds them: the first ``n_obstacle`` are the obstacles'
    (the barrier's at ``k % stride == 0``, else the guard's), then ``n_floor`` floor rows, then the
    joint limits'. A row with ``norm[k] == 0`` (no torque can change it) is "unmovable", whatever
    its place; its residual is then ``−b_k`` (:func:`c3bf_gym.safety._daqp.solve_rows`).
    """
    for k in range(residual.shape[0]):
        if norm[k] == 0.0:
            kind = 4
        elif k < n_obstacle:
            kind = 0 if k % stride == 0 else 1
        elif k < n_obstacle + n_floor:
            kind = 2
        else:
            kind = 3
        violation = -residual[k]
        if violation > out[kind] and violation > tol:
            out[kind] = violation


# ----------------------------------------------------------------------------- the policy step's report

#: Entries of :attr:`Tally.values`, the running values of a :class:`~c3bf_gym.safety.StepSafety`
#: over a policy step's calls; :data:`T_VIOLATION` starts the largest violation of each of the
#: five row kinds.
(T_SUBSTEPS, T_MIN_CONSTRAINT, T_MIN_H, T_INSIDE, T_SENSED, T_ACTIVE_ROWS, T_CORRECTION, T_INTERVENED,
 T_INFEASIBLE_STEPS, T_SLACK, T_GAIN_RAISED_STEPS, T_VIOLATION) = range(12)
TALLY_SIZE = T_VIOLATION + 5
#: Entries of :attr:`Tally.last`: the last recorded call's own values
L_STATUS, L_ITERATIONS, L_ACTIVE, L_SLACK = range(4)
#: Entries of :attr:`Tally.gains`: the barrier's gain γ and the largest gain γ_max its rows may
#: rise to where they give way at ``h > 0`` [1/s]
G_BARRIER, G_LIMIT = range(2)
#: A call's outcome beside :func:`c3bf_gym.safety._daqp.solve_rows`' codes: only barrier rows gave
#: way, each by no more than its allowance (:func:`beyond_allowance`), so every row held with the
#: barrier's gain raised within ``[γ, γ_max]``.
GAIN_RAISED = 3


class Tally(NamedTuple):
    """What the filter's calls accumulate over a policy step, in compiled code (:func:`record`).

    Attributes:
        values: (TALLY_SIZE,) float64, laid out by the ``T_*`` indices (counts and flags as
            exact floats); a new policy step starts them from :data:`TALLY_START`.
        tau_nominal, tau: (n,) the last call's nominal and filtered torques [N m].
        last: (4,) float64, laid out by the ``L_*`` indices: the last recorded call's status
            (:data:`GAIN_RAISED` or a :func:`~c3bf_gym.safety._daqp.solve_rows` code), DAQP
            iterations, active rows and slack. A new policy step keeps them: they describe that
            call until the next one.
        row_h: (rows,) the barrier value ``h`` of each barrier row of the last call, at the row's
            index (written by the row kernels; other entries unused).
        gains: (2,) laid out by the ``G_*`` indices, set once by the filter.
    """

    values: np.ndarray
    tau_nominal: np.ndarray
    tau: np.ndarray
    last: np.ndarray
    row_h: np.ndarray
    gains: np.ndarray


#: :attr:`Tally.values` at the start of a policy step: no calls, the running minima at inf,
#: everything else 0 (``np.copyto`` it: a kernel call costs more than the copy).
TALLY_START = np.zeros(TALLY_SIZE)
TALLY_START[[T_MIN_CONSTRAINT, T_MIN_H]] = np.inf
TALLY_START.flags.writeable = False


@njit(**_opts)
def beyond_allowance(residual, norm, row_h, gains, n_obstacle, stride):
    """Whether some row of a call that gave way (``residual`` (m,), ``norm`` (m,): the QP's
    normalised residuals and row norms) gave way beyond its allowance.

    A barrier row (``k < n_obstacle`` and ``k % stride == 0``) is the condition
    ``ḣ ≥ −γ h`` (:data:`G_BARRIER`). Where ``h > 0``, giving way by ``δ`` (in ``ḣ``'s units,
    ``−residual·norm``) is that condition with the gain ``γ + δ/h``, which keeps ``h ≥ 0``
    invariant as any positive gain does; the filter accepts gains up to
    ``γ_max`` = :data:`~c3bf_gym.safety.controller.RAISED_GAIN_STEP` / Δt (:data:`G_LIMIT`),
    under which one physics step can at most halve ``h`` (the discrete-time barrier condition
    ``h(t + Δt) ≥ (1 − γ' Δt) h(t)``, ``γ' Δt ≤ 1/2``). So a barrier
    row's allowance is ``(γ_max − γ) h`` for ``h > 0`` and none for ``h ≤ 0``; every other row
    (the guard's, the floor's, the joint limits', an unmovable one) has none. Both are taken
    beyond :data:`~c3bf_gym.safety._daqp.ACTIVE_TOL` (row-normalised)."""
    raise_by = max(gains[G_LIMIT] - gains[G_BARRIER], 0.0)
    for k in range(residual.shape[0]):
        violation = -residual[k]
        if violation <= ACTIVE_TOL:
            continue
        if norm[k] == 0.0 or k >= n_obstacle or k % stride != 0:
            return True
        if violation * norm[k] > raise_by * max(row_h[k], 0.0) + ACTIVE_TOL * norm[k]:
            return True
    return False


@njit(**_opts)
def record(tally, status, m, min_h, inside, n_sensed, iterations, n_active, slack, residual, correction, tau_nom,
           tau, qp, n_obstacle, stride, n_floor, intervention_tol):
    """Fold one solved call (``status`` ≥ 0, :func:`c3bf_gym.safety._daqp.solve_rows`' codes; its
    ``m`` rows, the first ``n_obstacle`` the obstacles', ``n_floor`` floor rows after them) into
    ``tally``: the running extremes and counts of :class:`~c3bf_gym.safety.StepSafety`, the last
    call's torques, status, iterations, active rows and slack, and, when rows gave way, the largest
    violation of each kind (:func:`violations_by_kind` on the QP's residuals) and whether the call
    held every row with the barrier's gain raised (:func:`beyond_allowance`: counted in
    ``T_GAIN_RAISED_STEPS``) or not (``T_INFEASIBLE_STEPS``).

    Returns the call's outcome: ``status``, or :data:`GAIN_RAISED` for a relaxed call within the
    allowance."""
    values = tally.values
    values[T_SUBSTEPS] += 1.0
    if residual < values[T_MIN_CONSTRAINT]:
        values[T_MIN_CONSTRAINT] = residual
    for j in range(tau.shape[0]):
        tally.tau_nominal[j] = tau_nom[j]
        tally.tau[j] = tau[j]
    if min_h < values[T_MIN_H]:
        values[T_MIN_H] = min_h
    if inside:
        values[T_INSIDE] = 1.0
    if n_sensed > values[T_SENSED]:
        values[T_SENSED] = n_sensed
    if n_active > values[T_ACTIVE_ROWS]:
        values[T_ACTIVE_ROWS] = n_active
    if correction > values[T_CORRECTION]:
        values[T_CORRECTION] = correction
    if correction > intervention_tol:
        values[T_INTERVENED] = 1.0
    outcome = status
    if status != SOLVED:
        values[T_SLACK] = max(values[T_SLACK], slack)
        violations_by_kind(qp.residual[:m], qp.norm[:m], n_obstacle, stride, n_floor, ACTIVE_TOL,
                           values[T_VIOLATION:])
        if status == RELAXED and not beyond_allowance(qp.residual[:m], qp.norm[:m], tally.row_h, tally.gains,
                                                      n_obstacle, stride):
            outcome = GAIN_RAISED
            values[T_GAIN_RAISED_STEPS] += 1.0
        else:
            values[T_INFEASIBLE_STEPS] += 1.0
    tally.last[L_STATUS] = outcome
    tally.last[L_ITERATIONS] = iterations
    tally.last[L_ACTIVE] = n_active
    tally.last[L_SLACK] = slack
    return outcome


@njit(**_opts)
def hook_substep(stage, tau_nom, tau, arm, obstacles, params, A, b, scale, limit, qp, tally, intervention_tol):
    """One whole-arm filter step in one call (an environment's compiled policy step, and
    :meth:`~c3bf_gym.safety.SafetyController.__call__` through :func:`hook_substep_at`): the rows (:func:`hook_rows_whole_arm`, whose
    arguments ``stage`` … ``b`` are), the QP (:func:`c3bf_gym.safety._daqp.solve_rows` on ``qp``,
    priorities by :func:`low_priority_span`) in the scaled torque ``τ / scale``, :func:`hook_post`,
    which writes the torque into ``tau``, and :func:`record` of the outcome into ``tally``.

    Returns the status, one of :func:`~c3bf_gym.safety._daqp.solve_rows`' codes (invalid input, < 0,
    is not recorded), with a relaxed call that held every row with the barrier's gain raised
    (:func:`record`'s :data:`GAIN_RAISED`) returned as :data:`~c3bf_gym.safety._daqp.SOLVED`: the
    callers (an environment's loop, ``on_infeasible="raise"``) stop on the others.
    """
    m, min_h, inside, n_sensed = hook_rows_whole_arm(stage, arm, obstacles, params, A, b, tally.row_h)
    n_floor = params.floor_ends.shape[0]
    n_fixed = n_floor + (4 * params.dofs.shape[0] if params.joint_rows else 0)
    guarded = params.guard_gamma2 > 0.0
    stride = 2 if guarded else 1  # obstacle rows: barrier, guard, barrier, guard, ... beside a guard
    status, iterations, n_active, slack = solve_rows(tau_nom, A[:m], b[:m], scale, params.dofs,
                                                     low_priority_span(m, n_fixed, guarded), stride, qp)
    if status < 0:
        return status
    residual, correction = hook_post(b[:m], qp.norm[:m], qp.residual[:m], qp.u, scale, tau_nom, limit, tau)
    outcome = record(tally, status, m, min_h, inside, n_sensed, iterations, n_active, slack, residual, correction,
                     tau_nom, tau, qp, m - n_fixed, stride, n_floor, intervention_tol)
    return SOLVED if outcome == GAIN_RAISED else outcome


@njit(**_opts)
def hook_substep_at(stage, tau_nom, tau, handle, bound):
    """:func:`hook_substep` with its arguments after the first three by address: ``handle`` is
    :func:`c3bf_gym._capi.pack` of them and ``bound`` their numba type. From Python, one array
    crosses into compiled code instead of the ~80 buffers, which numba would convert one by one."""
    return hook_substep(stage, tau_nom, tau, *unpack(handle, bound))
