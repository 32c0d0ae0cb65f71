"""Compiled (numba) kernels of the safety rows ``A τ ≥ b``: the barriers' math at one point and
the filter's rows in one call. Imports the dynamics kernels (:mod:`c3bf_gym.safety._dynamics`)
and nothing of the QP, so computing ``h`` or a row loads no solver.

The filter runs at every physics step (500 Hz); at the arm's size (6 joints, 7 capsules: tens of
numbers an array) numpy would spend its time in per-call overhead, so the kernels do the arithmetic
in plain loops, compiled once by numba with :data:`~c3bf_gym._compile_cache.STEP_KERNEL_OPTIONS`
(cached on disk, keyed on every kernel source by :mod:`c3bf_gym._compile_cache`; no allocation,
no reference counting).

Each piece of math lives once, in an inner ``@njit`` function that works on one point or one row;
the classes of :mod:`c3bf_gym.safety.barriers` call it through small vectorised kernels, and the
fused :func:`filter_rows` calls the same inner functions directly:

* :func:`c3bf_terms`, :func:`hocbf_terms`, :func:`rows_from_terms`, :func:`joint_limit_rows`: the
  barriers of :mod:`c3bf_gym.safety.barriers`; :func:`floor_rows`, :func:`unmodelled_margin`:
  the controller's floor rows and the margin for forces it cannot predict.
* :func:`filter_rows`: every row of the filter with the built-in barriers in one call, the
  protected points the closest points of the link capsules or the tool site
  (:attr:`RowParams.points`), reading :class:`~c3bf_gym.safety._dynamics.ArmArrays`,
  :class:`ObstacleArrays` and :class:`RowParams`.

The floating-point operations follow the numpy code they replace (same formulas, same order where
it matters), so results agree with it to rounding (~1e-15 relative).

The pieces of :func:`filter_rows` that take the arm's or the obstacles' named structures (or the
rows' buffers) are inlined into it by numba (``inline="always"``): called instead, each call
passes every array of those structures, and LLVM does not inline them, which made the whole-arm
rows 5× slower.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from c3bf_gym._compile_cache import STEP_KERNEL_OPTIONS  # (before any @njit(cache=True): the cache keys)
from c3bf_gym.safety._dynamics import (ArmMotion, SparseMass, capsule_ends, closest_terms, joint_drift, step_inverse,
                                       surface_gap, tool_site_dynamics)

#: barrier kinds of the fused kernel
C3BF_KIND = 0
HOCBF_KIND = 1

_opts = STEP_KERNEL_OPTIONS


# ----------------------------------------------------------------------------- barriers at a point


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
def c3bf_terms(p, v, r, gamma, eps, delta, out):
    """:func:`_c3bf_point` for P points: ``p, v`` (P, 3), ``r`` (P,) into ``out``
    (:class:`~c3bf_gym.safety.barriers.BarrierTerms` of (P,) and (P, 3) arrays)."""
    h, grad_v, drift, inside, grad_p = out
    for k in range(p.shape[0]):
        h[k], drift[k], inside[k], grad_v[k], grad_p[k] = _c3bf_point(_vec3(p[k]), _vec3(v[k]), r[k], gamma, eps,
                                                                       delta)


@njit(**_opts)
def hocbf_terms(p, v, r, gamma1, out):
    """:func:`_hocbf_point` for P points: ``p, v`` (P, 3), ``r`` (P,) into ``out``
    (:class:`~c3bf_gym.safety.barriers.BarrierTerms` of (P,) and (P, 3) arrays)."""
    h, grad_v, drift, inside, grad_p = out
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
def _dot3(x, y):
    """``⟨x, y⟩`` of two 3-tuples."""
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]


@njit(inline="always", **_opts)
def _coefficients(g, grads, A, m, j, both):
    """Column ``j`` of the rows at one point, ``g`` (3-tuple) being that column of the point's
    ``G``: ``A[m, j] = ⟨grad_v, g⟩`` and, with ``both``, ``A[m + 1, j] = ⟨grad_w, g⟩`` (``grads``
    is ``(grad_v, grad_w)``, 3-tuples): :func:`_row`'s arithmetic, one column at a time."""
    grad_v, grad_w = grads
    A[m, j] = _dot3(grad_v, g)
    if both:
        A[m + 1, j] = _dot3(grad_w, g)


@njit(inline="always", **_opts)
def _pair_rows(ends_a, ends_ab, s, tc, grads, A, m, both):
    """:func:`_coefficients` of the rows at the point ``tc`` of capsule ``s``'s axis, its
    ``G = G_a + tc (G_b − G_a)`` taken column by column as the rows need it (the same arithmetic as
    :func:`~c3bf_gym.safety._dynamics._closest_pair`'s ``G``, without writing ``G`` out and reading
    it back)."""
    for j in range(A.shape[1]):
        g = (tc * ends_ab[s, 0, 3 + j] + ends_a[s, 0, 3 + j], tc * ends_ab[s, 1, 3 + j] + ends_a[s, 1, 3 + j],
             tc * ends_ab[s, 2, 3 + j] + ends_a[s, 2, 3 + j])
        _coefficients(g, grads, A, m, j, both)


@njit(**_opts)
def rows_from_terms(grad_v, drift, h, gamma, G, c, A, b):
    """:func:`_row` for P points: ``G`` (P, 3, n), ``c`` (P, 3) into ``A`` (P, n), ``b`` (P,)."""
    for k in range(h.shape[0]):
        b[k] = _row(_vec3(grad_v[k]), G[k], _vec3(c[k]), drift[k], h[k], gamma, A[k])


@njit(**_opts)
def joint_limit_rows(q, qd, Minv, c_q, limits, A, b):
    """The ``4n`` rows of :class:`~c3bf_gym.safety.barriers.JointLimits` into ``A`` (4n, k), ``b`` (4n,)
    (row blocks: position upper, position lower, speed upper, speed lower) for the ``n`` joints of
    ``limits`` (:class:`JointLimitParams`, or :class:`RowParams`, which has the same fields) at
    dofs ``limits.dofs`` (rows of ``Minv`` (·, k), entries of ``qd``, ``c_q``) and ``qpos``
    addresses ``limits.qpos_ids`` (entries of ``q``). An infinite limit's position row is
    ``0 τ ≥ −1``."""
    dofs, qpos_ids, q_lo, q_hi, qd_max = limits.dofs, limits.qpos_ids, limits.q_lo, limits.q_hi, limits.qd_max
    g1, g2, gv = limits.joint_gains[0], limits.joint_gains[1], limits.joint_gains[2]
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


class JointLimitParams(NamedTuple):
    """The joint limits as :func:`joint_limit_rows` reads them (the fields of :class:`RowParams`
    it uses): ``dofs``, ``qpos_ids`` (n,) int64, the arm's dofs and their ``qpos`` addresses;
    ``q_lo``, ``q_hi`` (n,) [rad] (±inf: none), ``qd_max`` (n,) [rad/s]; ``joint_gains`` (3,)
    γ₁, γ₂, γ_v [1/s]."""

    dofs: np.ndarray
    qpos_ids: np.ndarray
    q_lo: np.ndarray
    q_hi: np.ndarray
    qd_max: np.ndarray
    joint_gains: np.ndarray


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
def _segment_params(p1, d1, p2, d2):
    """The parameters ``(s, t)`` in [0, 1] of the closest points ``p1 + s d1`` and ``p2 + t d2`` of
    two segments (3-tuples: a start and its direction each), as in Ericson, *Real-Time Collision
    Detection*, 5.1.9; a segment of length 0 is its point."""
    r = (p1[0] - p2[0], p1[1] - p2[1], p1[2] - p2[2])
    a, e, f = _dot3(d1, d1), _dot3(d2, d2), _dot3(d2, r)
    tiny = 1e-12
    if a <= tiny and e <= tiny:
        return 0.0, 0.0
    if a <= tiny:
        return 0.0, min(max(f / e, 0.0), 1.0)
    c = _dot3(d1, r)
    if e <= tiny:
        return min(max(-c / a, 0.0), 1.0), 0.0
    bb = _dot3(d1, d2)
    denom = a * e - bb * bb
    s = min(max((bb * f - c * e) / denom, 0.0), 1.0) if denom > tiny * a * e else 0.0
    t = (bb * s + f) / e
    if t < 0.0:
        return min(max(-c / a, 0.0), 1.0), 0.0
    if t > 1.0:
        return min(max((bb - c) / a, 0.0), 1.0), 1.0
    return s, t


@njit(inline="always", **_opts)
def _pair_gap(ends, ends2, i, j, s, t, axis, col):
    """Column ``col`` of axis ``axis`` of the packed ends (:func:`floor_rows`' layout) at the point
    ``s`` along capsule ``i``'s axis of ``ends`` less that at ``t`` along capsule ``j``'s of
    ``ends2`` (each affine along its capsule: one rigid body)."""
    half, half2 = ends.shape[0] // 2, ends2.shape[0] // 2
    x1 = ends[i, axis, col] + s * (ends[half + i, axis, col] - ends[i, axis, col])
    return x1 - (ends2[j, axis, col] + t * (ends2[half2 + j, axis, col] - ends2[j, axis, col]))


@njit(inline="always", **_opts)
def _pair_row(first, second, d_min, gamma, A, b, k):
    """Row ``k`` of :func:`self_collision_rows` between two points, each ``(packed ends, capsule,
    parameter along its axis, the axis's direction)``: ``first`` the arm's capsule, ``second`` its
    partner, a capsule of the arm's ends or of other packed ends (the axes' directions, 3-tuples,
    for the sliding correction)."""
    ends, i, s, seg1 = first
    ends2, j, t, seg2 = second
    p = (_pair_gap(ends, ends2, i, j, s, t, 0, 0), _pair_gap(ends, ends2, i, j, s, t, 1, 0),
         _pair_gap(ends, ends2, i, j, s, t, 2, 0))
    v = (_pair_gap(ends, ends2, i, j, s, t, 0, 1), _pair_gap(ends, ends2, i, j, s, t, 1, 1),
         _pair_gap(ends, ends2, i, j, s, t, 2, 1))
    c = (_pair_gap(ends, ends2, i, j, s, t, 0, 2), _pair_gap(ends, ends2, i, j, s, t, 1, 2),
         _pair_gap(ends, ends2, i, j, s, t, 2, 2))
    nv = A.shape[1]
    d = math.sqrt(_dot3(p, p))
    if d < 1e-9:
        A[k, :nv] = 0.0
        b[k] = 0.0
        return
    n = (p[0] / d, p[1] / d, p[2] / d)
    d_dot = _dot3(n, v)
    for col in range(nv):
        A[k, col] = (n[0] * _pair_gap(ends, ends2, i, j, s, t, 0, 3 + col)
                     + n[1] * _pair_gap(ends, ends2, i, j, s, t, 1, 3 + col)
                     + n[2] * _pair_gap(ends, ends2, i, j, s, t, 2, 3 + col))
    inner1, inner2 = 0.0 < s < 1.0, 0.0 < t < 1.0  # (a segment of length 0 has s = 0 or t = 0)
    if inner1 and inner2:
        curvature = 0.0
    else:
        w = v
        if inner1 or inner2:  # v across the axis that holds the sliding point
            u = seg1 if inner1 else seg2
            along = _dot3(v, u) / _dot3(u, u)
            w = (v[0] - along * u[0], v[1] - along * u[1], v[2] - along * u[2])
        curvature = max(_dot3(w, w) - d_dot * d_dot, 0.0) / d
    b[k] = ((-gamma * gamma) * (d - d_min) - 2.0 * gamma * d_dot - _dot3(n, c)) - curvature


@njit(inline="always", **_opts)
def _axis(ends, i):
    """Capsule ``i``'s axis in the packed ``ends``: its end ``a`` and its direction ``b − a``
    (3-tuples)."""
    half = ends.shape[0] // 2
    a = (ends[i, 0, 0], ends[i, 1, 0], ends[i, 2, 0])
    return a, (ends[half + i, 0, 0] - a[0], ends[half + i, 1, 0] - a[1], ends[half + i, 2, 0] - a[2])


@njit(**_opts)
def self_collision_rows(ends, pairs, d_min, gamma, A, b):
    """Rows keeping pairs of the arm's own capsules apart (:class:`~c3bf_gym.safety.barriers.SelfCollision`),
    from the packed capsule ends ``ends`` (2S, 3, 3 + nv) (:func:`floor_rows`' layout): for pair
    ``k``, capsules ``pairs[k, 0]`` and ``pairs[k, 1]``, the distance ``d`` between the closest
    points ``x₁``, ``x₂`` of their axes (:func:`_segment_params`) stays at ``d ≥ d_min[k]`` as the
    second-order barrier ``d̈ + 2γ ḋ + γ² (d − d_min) ≥ 0``. With ``p = x₁ − x₂``, ``n = p / d``
    and the points' relative velocity ``v``, acceleration at zero torque ``c`` and acceleration
    per unit force ``G`` (each affine along a capsule's axis, one rigid body):
    ``ḋ = ⟨n, v⟩``, ``d̈ = ⟨n, G τ + c⟩ + (‖v‖² − ḋ²) / d``, so
    ``A_k = nᵀ G``, ``b_k = −γ² (d − d_min) − 2γ ḋ − ⟨n, c⟩ − (‖v‖² − ḋ²) / d``.

    A closest point inside its axis slides along it as the links move, and the distance then
    curves less than that of two material points: the curvature term takes the relative velocity
    across the axes that hold such a point (``v`` less its component along that axis; with both
    points inside, the term is 0, ``n`` being normal to both axes). The axes' turning rates are
    left out. Axes that touch (``d`` below 1e-9 m, no direction to part them along) get the row
    ``0 τ ≥ 0``: no torque can be asked of it, and it is never counted as given way."""
    for k in range(pairs.shape[0]):
        i, j = pairs[k, 0], pairs[k, 1]
        a1, d1 = _axis(ends, i)
        a2, d2 = _axis(ends, j)
        s, t = _segment_params(a1, d1, a2, d2)
        _pair_row((ends, i, s, d1), (ends, j, t, d2), d_min[k], gamma, A, b, k)


@njit(**_opts)
def fixed_partner_rows(ends, capsules, fixed, d_min, gamma, A, b):
    """:func:`self_collision_rows` between capsule ``capsules[k]`` of the packed ``ends`` and
    capsule ``k`` of ``fixed`` (2K, 3, 3 + nv), parts of the arm that no joint moves (a base, a
    geom on the axes of the hinges that turn it), packed the same way with zero velocity,
    acceleration and ``G``."""
    for k in range(capsules.shape[0]):
        i = capsules[k]
        a1, d1 = _axis(ends, i)
        a2, d2 = _axis(fixed, k)
        s, t = _segment_params(a1, d1, a2, d2)
        _pair_row((ends, i, s, d1), (fixed, k, t, d2), d_min[k], gamma, A, b, k)


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
    those rows only through the coupling of ``M⁻¹``, which they leave out: charging their worst
    case too left the Jaco's joint rows infeasible at 11–17 % of its physics steps
    (docs/design-decisions.md)."""
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



# ----------------------------------------------------------------------------- the filter's rows

#: protected points of the fused kernel (:attr:`RowParams.points`): the closest point of every
#: link capsule, or a sphere at the tool site
WHOLE_ARM_POINTS = 0
EE_POINTS = 1


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


class BarrierGains(NamedTuple):
    """The barrier of the fused rows and its gains, each by its name (the built-in barriers'
    ``fused_spec``); the other kind's fields are 0.

    Attributes:
        kind: :data:`C3BF_KIND` (:class:`~c3bf_gym.safety.barriers.C3BF`) or :data:`HOCBF_KIND`
            (:class:`~c3bf_gym.safety.barriers.DistanceHOCBF`).
        gamma: the row's class-K gain [1/s]: the C3BF's γ, the distance HOCBF's γ₂.
        epsilon, delta: the C3BF's ε and δ [m].
        gamma1: the distance HOCBF's γ₁ [1/s].
    """

    kind: int
    gamma: float
    epsilon: float
    delta: float
    gamma1: float


class GuardGains(NamedTuple):
    """The distance-HOCBF guard beside the barrier (:data:`~c3bf_gym.safety.GUARD_GAMMA`), if any.

    Attributes:
        present: whether the rows have a guard row after each barrier row.
        gamma1, gamma2: its γ₁ and γ₂ [1/s] (0 without a guard).
    """

    present: bool
    gamma1: float
    gamma2: float


class RowParams(NamedTuple):
    """The fused rows' settings (:class:`~c3bf_gym.safety.SafetyController` builds them once).

    Attributes:
        barrier: :class:`BarrierGains`.
        guard: :class:`GuardGains`.
        points: :data:`WHOLE_ARM_POINTS` or :data:`EE_POINTS`, the protected points
            (:attr:`~c3bf_gym.safety.FilterConfig.points`); ``ee_radius`` [m] the tool sphere's radius.
        sensing_radius, margin: [m].
        floor_gamma: the floor rows' gain [1/s]; ``floor_ends`` (F,) the capsule ends that get
            one, ``floor_min`` (F,) their lowest allowed heights [m].
        self_pairs: (P, 2) the pairs of capsules kept apart (:func:`self_collision_rows`, gain
            ``floor_gamma``), ``self_min`` (P,) their smallest distances between axes [m];
            ``fixed_capsules`` (Q,), ``fixed_ends`` (2Q, 3, 3 + nv), ``fixed_min`` (Q,) the pairs
            of capsules and fixed parts of the arm (:func:`fixed_partner_rows`).
        joint_rows: add the ``4 n`` joint-limit rows, with ``joint_gains`` (γ₁, γ₂, γ_v) and the
            limits ``q_lo``, ``q_hi``, ``qd_max`` (n,).
        dofs, qpos_ids: (n,) the arm's dofs and their ``qpos`` addresses.
        unmodelled_force: (nv,) bounds of the forces the filter cannot predict (:func:`unmodelled_margin`).
    """

    barrier: BarrierGains
    guard: GuardGains
    points: int
    ee_radius: float
    sensing_radius: float
    margin: float
    floor_gamma: float
    floor_ends: np.ndarray
    floor_min: np.ndarray
    self_pairs: np.ndarray
    self_min: np.ndarray
    fixed_capsules: np.ndarray
    fixed_ends: np.ndarray
    fixed_min: np.ndarray
    joint_rows: bool
    joint_gains: np.ndarray
    q_lo: np.ndarray
    q_hi: np.ndarray
    qd_max: np.ndarray
    dofs: np.ndarray
    qpos_ids: np.ndarray
    unmodelled_force: np.ndarray


@njit(inline="always", **_opts)
def _point_rows(point, r, params, b, row_h, m):
    """The right-hand sides of the rows at one protected point: the barrier's (``params.barrier``:
    :func:`_c3bf_point` or :func:`_hocbf_point`, then :func:`_row_rhs`) into ``b[m]``, its ``h``
    into ``row_h[m]``, and with a guard (``params.guard``) the guard's into ``b[m + 1]``.
    ``point`` is ``(p, v, c)``, 3-tuples: the point's position, velocity and acceleration at zero
    torque relative to the obstacle; ``r`` the combined radius [m].

    Returns ``(h, inside, (grad_v, grad_w), (grad_p, grad_q))``: the barrier's value and overlap
    flag, and the barrier's and the guard's gradients (the barrier's twice without a guard), which
    the caller turns into the rows' coefficients and, for a sliding point, the sliding terms."""
    p, v, c = point
    barrier, guard = params.barrier, params.guard
    if barrier.kind == C3BF_KIND:
        h, drift, inside, grad_v, grad_p = _c3bf_point(p, v, r, barrier.gamma, barrier.epsilon, barrier.delta)
    else:
        h, drift, inside, grad_v, grad_p = _hocbf_point(p, v, r, barrier.gamma1)
    b[m] = _row_rhs(grad_v, c, drift, h, barrier.gamma)
    row_h[m] = h
    grad_w, grad_q = grad_v, grad_p
    if guard.present:
        h_guard, drift, _, grad_w, grad_q = _hocbf_point(p, v, r, guard.gamma1)
        b[m + 1] = _row_rhs(grad_w, c, drift, h_guard, guard.gamma2)
    return h, inside, (grad_v, grad_w), (grad_p, grad_q)


@njit(inline="always", **_opts)
def _capsule_rows(arm, obstacles, k, params, A, b, row_h, m):
    """The rows of obstacle ``k`` at the closest point of every capsule axis
    (:func:`~c3bf_gym.safety._dynamics.closest_terms`), from row ``m`` on: :func:`_point_rows`,
    less the sliding terms ``⟨grad_p, ṫ (b − a)⟩`` (the closest points slide along the links), and
    :func:`_pair_rows`. Returns the smallest ``h`` and whether a point was inside."""
    s_count = arm.ends_ab.shape[0]
    ends_a, ends_ab = arm.ends[:s_count], arm.ends_ab
    o, vo, ao = obstacles.position[k], obstacles.velocity[k], obstacles.acceleration[k]
    guard = params.guard.present
    min_h = np.inf
    inside_any = False
    for s in range(s_count):
        _, tc, p, v, c, slide = closest_terms(ends_a, ends_ab, arm.a_dot_ab, arm.length2, s, o, vo, ao)
        r = (obstacles.radius[k] + arm.capsule_radius[s]) + params.margin
        h, inside, grads, grads_p = _point_rows((p, v, c), r, params, b, row_h, m)
        b[m] -= _dot3(grads_p[0], slide)
        if guard:
            b[m + 1] -= _dot3(grads_p[1], slide)
        _pair_rows(ends_a, ends_ab, s, tc, grads, A, m, guard)
        min_h = min(min_h, h)
        inside_any = inside_any or inside
        m += 2 if guard else 1
    return min_h, inside_any


@njit(inline="always", **_opts)
def _site_rows(site, obstacles, k, params, A, b, row_h, m):
    """The rows of obstacle ``k`` at the tool site (a sphere of ``params.ee_radius``), row ``m``
    (and ``m + 1``, the guard's): :func:`_point_rows` and :func:`_coefficients` on the site's
    dynamics ``site.packed[0]`` (:func:`~c3bf_gym.safety._dynamics.tool_site_dynamics`, current).
    The site is a material point: no sliding terms. Returns its ``h`` and whether it was inside."""
    x = site.packed[0]
    o, vo, ao = obstacles.position[k], obstacles.velocity[k], obstacles.acceleration[k]
    point = ((x[0, 0] - o[0], x[1, 0] - o[1], x[2, 0] - o[2]), (x[0, 1] - vo[0], x[1, 1] - vo[1], x[2, 1] - vo[2]),
             (x[0, 2] - ao[0], x[1, 2] - ao[1], x[2, 2] - ao[2]))
    r = (obstacles.radius[k] + params.ee_radius) + params.margin
    h, inside, grads, _ = _point_rows(point, r, params, b, row_h, m)
    for j in range(A.shape[1]):
        _coefficients((x[0, 3 + j], x[1, 3 + j], x[2, 3 + j]), grads, A, m, j, params.guard.present)
    return h, inside


@njit(inline="always", **_opts)
def _sensed(arm, obstacles, k, sensing_radius):
    """Whether obstacle ``k`` is active and its surface within ``sensing_radius`` of the arm: its
    kept ``distances``, or, with none kept (shape (K, 0)), its distance to the capsules
    (:func:`~c3bf_gym.safety._dynamics.surface_gap`), whatever the protected points."""
    if not obstacles.active[k]:
        return False
    distances = obstacles.distances
    dmin = np.inf
    for g in range(distances.shape[1]):
        dmin = min(dmin, distances[k, g])
    if distances.shape[1] == 0:
        s_count = arm.ends_ab.shape[0]
        dmin = surface_gap(arm.ends[:s_count], arm.ends_ab, arm.a_dot_ab, arm.length2, arm.capsule_radius,
                           obstacles.position[k], obstacles.radius[k])
    return dmin <= sensing_radius


@njit(**_opts)
def filter_rows(stage, arm, obstacles, params, A, b, row_h):
    """All rows of the filter (:meth:`~c3bf_gym.safety.SafetyController.rows`) in one call, for the
    built-in barriers and either kind of protected points.

    1. ``stage`` 2: ``Minv``, ``qacc_free`` (:func:`~c3bf_gym.safety._dynamics.step_inverse`),
       then (``stage`` ≥ 1) the capsule ends (:func:`~c3bf_gym.safety._dynamics.capsule_ends`),
       into ``arm`` (:class:`~c3bf_gym.safety._dynamics.ArmArrays`); with ``params.points``
       :data:`EE_POINTS`, at every call, the tool site's dynamics
       (:func:`~c3bf_gym.safety._dynamics.tool_site_dynamics`, into ``arm.site``).
    2. For every sensed obstacle (:func:`_sensed`), the rows at the protected points
       (:func:`_capsule_rows`: one per capsule; :func:`_site_rows`: one at the tool site), each
       followed, with a guard (``params.guard``), by the guard's row for that point.
    3. The floor rows of the capsule ends ``params.floor_ends`` (:func:`floor_rows`), then the
       rows of the capsule pairs ``params.self_pairs`` (:func:`self_collision_rows`) and of the
       capsules and fixed parts ``params.fixed_capsules`` (:func:`fixed_partner_rows`).
    4. With ``params.joint_rows``, the ``4 n`` joint-limit rows (:func:`joint_limit_rows`), on the
       drift with the last physics step's constraint force
       (:func:`~c3bf_gym.safety._dynamics.joint_drift`).
    The obstacle, floor and pair rows are tightened for the forces the filter cannot predict
    (:func:`unmodelled_margin`); the joint-limit rows are not: they take the constraint force the
    last physics step applied as the next one's instead.

    The rows are written for the generalised force on every dof of the model (``A`` (·, nv)); the
    QP reads the columns of the arm's dofs (``params.dofs``).

    The rows go to ``A``, ``b``, and each barrier row's ``h`` to ``row_h`` at the row's index (the
    guard's and the other rows' entries are left as they are). Returns ``(rows, min h of the
    barrier's rows (not the guard's), any inside, sensed count)``.
    """
    n = params.dofs.shape[0]
    if stage >= 2:
        step_inverse(SparseMass(arm.M, arm.M_rowadr, arm.M_rownnz, arm.M_colind), arm.damping, arm.qfrc_passive,
                     arm.qfrc_bias, arm.factor, arm.Minv, arm.qacc_free)
    if stage >= 1:
        capsule_ends(arm)
    ee = params.points == EE_POINTS
    if ee:
        tool_site_dynamics(arm.site, ArmMotion(arm.cdof, arm.cdof_dot, arm.com, arm.qvel, arm.Minv, arm.qacc_free))
    per_obstacle = (1 if ee else arm.ends_ab.shape[0]) * (2 if params.guard.present else 1)
    m = 0
    n_sensed = 0
    min_h = np.inf
    inside_any = False
    for k in range(obstacles.active.shape[0]):
        if not _sensed(arm, obstacles, k, params.sensing_radius):
            continue
        n_sensed += 1
        if ee:
            h, inside = _site_rows(arm.site, obstacles, k, params, A, b, row_h, m)
        else:
            h, inside = _capsule_rows(arm, obstacles, k, params, A, b, row_h, m)
        min_h = min(min_h, h)
        inside_any = inside_any or inside
        m += per_obstacle
    n_floor = params.floor_ends.shape[0]
    floor_rows(arm.ends, params.floor_ends, params.floor_min, params.floor_gamma, A[m:m + n_floor], b[m:m + n_floor])
    m += n_floor
    n_self = params.self_pairs.shape[0]
    self_collision_rows(arm.ends, params.self_pairs, params.self_min, params.floor_gamma, A[m:m + n_self],
                        b[m:m + n_self])
    m += n_self
    n_fixed = params.fixed_capsules.shape[0]
    fixed_partner_rows(arm.ends, params.fixed_capsules, params.fixed_ends, params.fixed_min, params.floor_gamma,
                       A[m:m + n_fixed], b[m:m + n_fixed])
    m += n_fixed
    unmodelled_margin(A[:m], b[:m], params.unmodelled_force)
    if params.joint_rows:
        joint_drift(arm.Minv, arm.qacc_free, arm.qfrc_constraint, arm.qacc_joint)
        joint_limit_rows(arm.qpos, arm.qvel, arm.Minv, arm.qacc_joint, params, A[m:m + 4 * n], b[m:m + 4 * n])
        m += 4 * n
    return m, min_h, inside_any, n_sensed
