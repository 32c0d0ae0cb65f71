"""Tests for the compiled kernels (c3bf_gym/safety/_dynamics.py, _rows.py, _qp.py, _step.py): the compiled kernels against plain numpy reference math.

The references here are written independently of the kernels (vectorised numpy, the formulas of
the barrier and robot docstrings, the numpy code the kernels replaced), so a wrong index, sign or
operand in a kernel shows as a mismatch. Where the kernels follow the same operation order the
agreement is to rounding (1e-12 relative); the filter's rows are also checked end to end against
a numpy assembly of the same rows.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from numba.core.caching import NullCache

from c3bf_gym.safety import _dynamics, _qp, _rows, _step
from c3bf_gym.safety.barriers import C3BF, BarrierTerms, DistanceHOCBF, JointLimits
from c3bf_gym.filter import SafetyHook
from c3bf_gym.safety import FilterConfig
from c3bf_gym.safety.dynamics import ArmModel
from c3bf_gym.scenarios import ObstacleSample, ObstacleSpec

import reference

RTOL = 1e-12


def close(got, want, rtol=RTOL):
    """Equal to ``rtol`` relative to the largest magnitude of ``want`` (scale-aware)."""
    got, want = np.asarray(got, dtype=float), np.asarray(want, dtype=float)
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=0, atol=rtol * max(1.0, float(np.abs(want).max(initial=0.0))))


# ----------------------------------------------------------------------------- numpy references


def c3bf_reference(p, v, r, gamma, eps, delta=1e-6):
    """The C3BF terms in vectorised numpy (the formulas of :class:`C3BF`'s docstring)."""
    h0 = (p * p).sum(1) - r**2
    inside = h0 <= 0
    s = np.sqrt(np.maximum(h0, delta**2))
    vn = np.sqrt((v * v).sum(1) + eps**2)
    pv = (p * v).sum(1)
    h = pv + vn * s
    grad_v = p + v * (s / vn)[:, None]
    grad_p = v + p * (vn / s)[:, None]
    h = np.where(inside, pv + 0.5 * gamma * h0, h)
    grad_v = np.where(inside[:, None], p, grad_v)
    grad_p = np.where(inside[:, None], v + gamma * p, grad_p)
    return h, grad_v, (grad_p * v).sum(1), inside, grad_p


def hocbf_reference(p, v, r, gamma1):
    h0 = (p * p).sum(1) - r**2
    pv = (p * v).sum(1)
    return 2 * pv + gamma1 * h0, 2 * p, 2 * (v * v).sum(1) + 2 * gamma1 * pv, h0 <= 0, 2 * v + 2 * gamma1 * p


def random_points(rng, n, inside_share=0.3):
    r = rng.uniform(0.05, 0.3, n)
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    dist = np.where(rng.random(n) < inside_share, rng.uniform(0.0, 1.0, n), rng.uniform(1.0, 4.0, n)) * r
    return direction * dist[:, None], rng.normal(size=(n, 3)), r


# ----------------------------------------------------------------------------- barriers


@pytest.mark.parametrize("seed", range(5))
def test_c3bf_and_hocbf_terms_match_numpy(seed):
    rng = np.random.default_rng(seed)
    p, v, r = random_points(rng, 50)
    got = C3BF(gamma=4.0, eps=0.02).terms(p, v, r)
    want = c3bf_reference(p, v, r, 4.0, 0.02)
    assert got.inside.any() and not got.inside.all()  # both branches exercised
    for g, w in zip(got, want):
        close(g, w)
    got = DistanceHOCBF(gamma1=3.0, gamma2=7.0).terms(p, v, r)
    for g, w in zip(got, hocbf_reference(p, v, r, 3.0)):
        close(g, w)


def test_terms_accept_scalar_radius_and_strided_inputs():
    rng = np.random.default_rng(1)
    p, v, _ = random_points(rng, 6)
    big = np.zeros((6, 6))
    big[:, ::2] = p  # a strided (non-contiguous) view
    got = C3BF().terms(big[:, ::2], v, 0.1)
    close(got.h, c3bf_reference(p, v, np.full(6, 0.1), 5.0, 1e-2)[0])


@pytest.mark.parametrize("barrier", [C3BF(gamma=3.0), DistanceHOCBF(gamma1=2.0, gamma2=6.0)])
def test_rows_from_terms_match_numpy(barrier):
    rng = np.random.default_rng(2)
    p, v, r = random_points(rng, 9)
    G = rng.normal(size=(9, 3, 6))
    c = rng.normal(size=(9, 3))
    terms = barrier.terms(p, v, r)
    A, b = barrier.rows(p, v, r, G, c)
    close(A, np.einsum("pi,pij->pj", terms.grad_v, G))
    close(b, -((terms.grad_v * c).sum(1) + terms.drift + barrier.gamma * terms.h))


def test_joint_limit_rows_match_numpy():
    rng = np.random.default_rng(3)
    n = 6
    lo, hi = -rng.uniform(1, 3, n), rng.uniform(1, 3, n)
    jl = JointLimits(lo, hi, rng.uniform(1, 3, n), gamma1=4.0, gamma2=9.0, gamma_v=15.0)
    q, qd, c = rng.uniform(-2, 2, n), rng.normal(size=n), rng.normal(size=n)
    Minv = rng.normal(size=(n, n))
    A, b = jl.rows(q, qd, Minv, c)
    close(A, np.concatenate([-Minv, Minv, -Minv, Minv]))
    g1, g2, gv = 4.0, 9.0, 15.0
    close(b, np.concatenate([
        -(-c - g1 * qd + g2 * (-qd + g1 * (hi - q))),
        -(c + g1 * qd + g2 * (qd + g1 * (q - lo))),
        -(-c + gv * (jl.qd_max - qd)),
        -(c + gv * (qd + jl.qd_max)),
    ]))  # fmt: skip
    # the same joints as 3 of a larger model's: rows over all of its dofs' torques
    dofs, qpos_ids = np.array([1, 3, 4]), np.array([2, 4, 6])
    big = rng.normal(size=(6, 6))
    part = JointLimits(lo[:3], hi[:3], jl.qd_max[:3], gamma1=4.0, gamma2=9.0, gamma_v=15.0)
    q_full, qd_full, c_full = rng.normal(size=8), rng.normal(size=6), rng.normal(size=6)
    A2, b2 = part.rows(q_full, qd_full, big, c_full, dofs=dofs, qpos_ids=qpos_ids)
    A3, b3 = part.rows(q_full[qpos_ids], qd_full[dofs], big[dofs], c_full[dofs])
    assert A2.shape == (12, 6)
    close(A2, A3)
    close(b2, b3)


# ----------------------------------------------------------------------------- dynamics


def test_step_inverse_inverts_a_random_spd_matrix_in_mujoco_layout(make_env):
    u = make_env(scenario="none").unwrapped
    m = u.model
    rng = np.random.default_rng(4)
    nv = m.nv
    B = rng.normal(size=(nv, nv))
    full = B @ B.T + nv * np.eye(nv)
    csr = np.array([full[i, m.M_colind[m.M_rowadr[i] + k]] for i in range(nv) for k in range(m.M_rownnz[i])])
    damping = rng.uniform(0, 0.5, nv)
    passive, bias = rng.normal(size=nv), rng.normal(size=nv)
    Minv, free, work = np.zeros((nv, nv)), np.zeros(nv), np.zeros((nv, nv))
    mass = _dynamics.SparseMass(csr, m.M_rowadr.astype(np.int64), m.M_rownnz.astype(np.int64),
                                m.M_colind.astype(np.int64))
    _dynamics.step_inverse(mass, damping, passive, bias, work, Minv, free)
    want = np.linalg.inv(full + np.diag(damping))
    close(Minv, want, 1e-10)
    close(free, want @ (passive - bias), 1e-10)


def put_obstacle(u, slot, centre, radius, velocity=(0.0, 0.0, 0.0)):
    u._place(slot, ObstacleSample(np.asarray(centre, float), np.asarray(velocity, float), radius))
    u._obstacle_specs[slot] = ObstacleSpec("static")


def scene(u, rng, count):
    """A random arm state with ``count`` obstacles near the links (some beyond the capsule ends)."""
    m, d = u.model, u.data
    d.qpos[:] = m.key_qpos[0] + rng.uniform(-1.0, 1.0, m.nq)
    d.qvel[:] = rng.uniform(-1.5, 1.5, m.nv)
    mujoco.mj_forward(m, d)
    for slot in range(count):
        gid = rng.choice(u.arm.capsule_ids[1:])
        axis = d.geom_xmat[gid].reshape(3, 3)[:, 2] * m.geom_size[gid, 1]
        side = rng.normal(size=3)
        side -= (side @ axis) / (axis @ axis) * axis
        side /= np.linalg.norm(side)
        centre = d.geom_xpos[gid] + rng.uniform(-1.4, 1.4) * axis + side * rng.uniform(0.12, 0.3)
        put_obstacle(u, slot, centre, 0.05, rng.uniform(-0.3, 0.3, 3))
        u.obstacle_acc[slot] = rng.uniform(-1, 1, 3)
    mujoco.mj_forward(m, d)
    u.state_version += 1


@pytest.mark.parametrize("seed", range(3))
def test_closest_relative_matches_closest_dynamics_and_sliding(make_env, seed):
    """The compiled closest_relative against the numpy closest_dynamics + closest_sliding."""
    u = make_env(scenario="none").unwrapped
    u.reset(seed=seed)
    rng = np.random.default_rng(seed)
    scene(u, rng, 3)
    arm = u.arm
    arm.update(u.data, u.state_version)
    centres, vel, acc = u.obstacle_pos[:3].copy(), u.obstacle_vel[:3].copy(), u.obstacle_acc[:3].copy()
    s = len(arm.capsule_ids)
    rel, slide_p = arm.closest_relative(centres, vel, acc)
    mat = reference.closest_dynamics(arm, centres)
    p = mat.pos - np.repeat(centres, s, axis=0)
    v = mat.vel - np.repeat(vel, s, axis=0)
    slide_p_ref, slide_v_ref = reference.closest_sliding(arm, centres, p, v)
    close(rel.pos, p)
    close(rel.vel, v)
    close(rel.G, mat.G)
    close(rel.c, mat.c - np.repeat(acc, s, axis=0) + slide_v_ref)
    close(slide_p, slide_p_ref)
    assert np.abs(slide_p).max() > 1e-3  # the sliding terms are exercised


def test_point_dynamics_kernel_matches_mj_jac(make_env):
    u = make_env(scenario="none").unwrapped
    u.reset(seed=5)
    m, d = u.model, u.data
    d.qvel[:] = np.random.default_rng(6).uniform(-2, 2, m.nv)  # J̇q̇ needs motion
    mujoco.mj_forward(m, d)
    u.state_version += 1
    arm = u.arm
    arm.update(d, u.state_version)
    body = int(m.geom_bodyid[arm.capsule_ids[4]])
    points = d.xpos[body] + np.random.default_rng(5).normal(scale=0.1, size=(4, 3))
    chain = np.repeat(ArmModel._chain_mask(m, body)[None], 4, axis=0)
    got = reference.point_dynamics(arm, d, points, chain)
    for k, x in enumerate(points):
        jac, jdot = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        mujoco.mj_jac(m, d, jac, None, x, body)
        mujoco.mj_jacDot(m, d, jdot, None, x, body)
        close(got.jac[k], jac, 1e-10)
        close(got.vel[k], jac @ d.qvel, 1e-10)
        close(got.G[k], jac @ arm.Minv, 1e-10)
        close(got.c[k], jac @ arm.qacc_free + jdot @ d.qvel, 1e-9)


# ----------------------------------------------------------------------------- the fused filter rows


class _NumpyC3BF(C3BF):
    """C3BF with numpy terms: the filter cannot fuse it and takes the per-class path."""

    def terms(self, p, v, r):
        from c3bf_gym.safety.barriers import BarrierTerms

        r = np.broadcast_to(r, len(p))
        return BarrierTerms(*c3bf_reference(np.asarray(p), np.asarray(v), r, self.gamma, self.eps))


def numpy_rows(u, hook):
    """SafetyHook.rows assembled in numpy from closest_dynamics / closest_sliding (numpy code in
    robot.py), the reference barrier terms and the joint-limit formulas."""
    arm = u.arm
    arm.update(u.data, u.state_version)
    sensed = np.flatnonzero(u.obstacle_active & (u.obstacle_distances() <= hook.sensing_radius))
    s = len(arm.capsule_ids)
    centres, vel, acc = u.obstacle_pos[sensed], u.obstacle_vel[sensed], u.obstacle_acc[sensed]
    mat = reference.closest_dynamics(arm, centres)
    p = mat.pos - np.repeat(centres, s, axis=0)
    v = mat.vel - np.repeat(vel, s, axis=0)
    slide_p, slide_v = reference.closest_sliding(arm, centres, p, v)
    c = mat.c - np.repeat(acc, s, axis=0) + slide_v
    r = (u.obstacle_radius[sensed][:, None] + arm.capsule_radius[None] + hook.margin).reshape(-1)
    bar = hook.barrier
    if isinstance(bar, DistanceHOCBF):
        h, gv, drift, inside, gp = hocbf_reference(p, v, r, bar.gamma1)
    else:
        h, gv, drift, inside, gp = c3bf_reference(p, v, r, bar.gamma, bar.eps)
    A = np.einsum("pi,pij->pj", gv, mat.G)
    b = -((gv * c).sum(1) + drift + bar.gamma * h) - (gp * slide_p).sum(1)
    # floor rows: z'' + 2γ z' + γ² (z − z_min) ≥ 0 at the capsule ends the filter protects
    ends = arm.end_dynamics()
    idx, g = hook.floor.ends, FilterConfig().floor_gamma
    A_floor = ends.G[idx, 2]
    b_floor = -(ends.c[idx, 2] + 2 * g * ends.vel[idx, 2] + g * g * (ends.pos[idx, 2] - hook.floor.min_height))
    # the joint rows' drift carries the last physics step's constraint force (here mj_forward's)
    jl = hook.joint_limits.rows(u.data.qpos, u.data.qvel, arm.Minv, arm.qacc_free + arm.Minv @ u.data.qfrc_constraint)
    A_all, b_all = np.concatenate([A, A_floor, jl.A]), np.concatenate([b, b_floor, jl.b])
    return A_all, b_all, h.min(initial=np.inf), inside.any(), len(sensed)


@pytest.mark.parametrize("barrier", ["c3bf", "hocbf"])
@pytest.mark.parametrize("seed", range(4))
def test_fused_hook_rows_match_numpy_assembly(make_env, barrier, seed):
    u = make_env(scenario="none").unwrapped
    u.reset(seed=seed)
    rng = np.random.default_rng(10 + seed)
    scene(u, rng, 1 + seed % 4)
    hook = SafetyHook(u, FilterConfig(barrier=barrier, margin=0.01, joint_speed_fraction=1.0, guard=None))
    assert hook._fused
    A, b, min_h, inside, n_sensed = hook.rows()
    A_ref, b_ref, h_ref, inside_ref, sensed_ref = numpy_rows(u, hook)
    assert n_sensed == sensed_ref >= 1 and inside == inside_ref
    assert len(hook.floor.ends) == 12 and len(b) == 6 * n_sensed + 12 + 24  # 6 capsules: link1 (pan axis) is not one
    close(A, A_ref, 1e-10)
    close(b, b_ref, 1e-10)
    assert min_h == pytest.approx(h_ref, rel=1e-10)


@pytest.mark.parametrize("points", ["whole_arm", "ee"])
@pytest.mark.parametrize("guard", [None, DistanceHOCBF(gamma1=3.0, gamma2=4.0)])
def test_fused_rows_equal_the_per_class_path(make_env, guard, points):
    """A barrier the filter cannot fuse (a subclass changing terms) takes the per-class path;
    with the same math it must give the fused kernel's rows, the guard's included (one after each
    of the barrier's), at the capsules' closest points and at the tool site."""
    u = make_env(scenario="none").unwrapped
    u.reset(seed=3)
    scene(u, np.random.default_rng(3), 3)
    config = FilterConfig(sensing_radius=0.5, joint_speed_fraction=1.0, guard=guard, points=points)
    fused = SafetyHook(u, config.replace(barrier=C3BF(gamma=5.0, eps=1e-2)))
    generic = SafetyHook(u, config.replace(barrier=_NumpyC3BF(gamma=5.0, eps=1e-2)))
    assert fused._fused and not generic._fused
    A1, b1, h1, in1, n1 = (x.copy() if isinstance(x, np.ndarray) else x for x in fused.rows())
    A2, b2, h2, in2, n2 = generic.rows()
    assert n1 == n2 == 3 and in1 == in2 and h1 == pytest.approx(h2, rel=1e-12)
    assert len(b1) == (6 if points == "whole_arm" else 1) * 3 * (1 if guard is None else 2) + 12 + 24
    close(A1, A2, 1e-10)
    close(b1, b2, 1e-10)


@pytest.mark.parametrize("points", ["whole_arm", "ee"])
def test_the_tool_metric_is_the_same_on_the_fused_and_per_class_paths(make_env, points):
    """``weight="tool"``: a barrier the filter cannot fuse takes the per-class path, which weighs
    the QP with the tool site's dynamics from the arm model instead of the fused kernel's; with
    the same rows it takes the fused kernel's torque, and one the ``"limits"`` metric does not."""
    u = make_env(scenario="none").unwrapped
    u.reset(seed=5)
    scene(u, np.random.default_rng(5), 3)
    config = FilterConfig(sensing_radius=0.5, weight="tool", tool_acceleration=3.0, points=points)
    fused = SafetyHook(u, config.replace(barrier=C3BF(gamma=5.0, eps=1e-2)))
    generic = SafetyHook(u, config.replace(barrier=_NumpyC3BF(gamma=5.0, eps=1e-2)))
    limits = SafetyHook(u, config.replace(barrier=C3BF(gamma=5.0, eps=1e-2), weight="limits", tool_acceleration=None))
    assert fused._fused and not generic._fused
    tau_nom = u.data.qfrc_bias + np.array([10.0, -15.0, 7.5, 5.0, -5.0, 2.0])
    tau = [hook(tau_nom).copy() for hook in (fused, generic, limits)]
    assert fused.report.intervened
    close(tau[0], tau[1], 1e-8)
    assert np.linalg.norm(tau[0] - tau[2]) > 1e-3


@pytest.mark.parametrize("guard", [None, DistanceHOCBF(gamma1=3.0, gamma2=4.0)])
def test_fused_obstacle_rows_are_their_pieces_bit_for_bit(make_env, guard):
    """The fused kernel's obstacle rows are exactly the vectorised kernels' pieces put together:
    closest points (closest_relative, which writes each point's G), barrier terms, rows from G
    (rows_from_terms), less the sliding term. Not to rounding: the same operations in the same
    order, so a rewrite of the fused loop that changes any float shows here."""
    u = make_env(scenario="none").unwrapped
    u.reset(seed=4)
    scene(u, np.random.default_rng(4), 3)
    hook = SafetyHook(u, FilterConfig(barrier=C3BF(gamma=5.0, eps=1e-2), sensing_radius=0.5, guard=guard))
    A, b, _, _, n_sensed = (x.copy() if isinstance(x, np.ndarray) else x for x in hook.rows())
    arm, params = u.arm.kernel_arrays(u.data), hook._params
    sensed = np.flatnonzero(u.obstacle_active & (u.obstacle_distances() <= 0.5))
    assert n_sensed == len(sensed) == 3
    s_count, nv = len(arm.capsule_ids), u.model.nv
    pairs = len(sensed) * s_count
    p, v, c, slide = (np.zeros((pairs, 3)) for _ in range(4))
    G, t = np.zeros((pairs, 3, nv)), np.zeros((len(sensed), s_count))
    axes = _dynamics.CapsuleAxes(arm.ends[:s_count], arm.ends_ab, arm.a_dot_ab, arm.length2)
    _dynamics.closest_relative(axes, u.obstacle_pos[sensed], u.obstacle_vel[sensed], u.obstacle_acc[sensed],
                               _dynamics.ClosestPoints(p, v, c, G, slide, t))
    r = ((u.obstacle_radius[sensed][:, None] + arm.capsule_radius[None]) + params.margin).reshape(-1)
    barriers = [("c3bf", params.barrier.gamma)] + ([] if guard is None else [("guard", params.guard.gamma2)])
    for i, (kind, gain) in enumerate(barriers):
        h, drift, grad_v, grad_p = np.zeros(pairs), np.zeros(pairs), np.zeros((pairs, 3)), np.zeros((pairs, 3))
        inside = np.zeros(pairs, bool)
        if kind == "c3bf":
            terms = BarrierTerms(h, grad_v, drift, inside, grad_p)
            _rows.c3bf_terms(p, v, r, params.barrier.gamma, params.barrier.epsilon, params.barrier.delta, terms)
        else:
            _rows.hocbf_terms(p, v, r, params.guard.gamma1, BarrierTerms(h, grad_v, drift, inside, grad_p))
        A_ref, b_ref = np.zeros((pairs, nv)), np.zeros(pairs)
        _rows.rows_from_terms(grad_v, drift, h, gain, G, c, A_ref, b_ref)
        b_ref = [bk - (gp[0] * sl[0] + gp[1] * sl[1] + gp[2] * sl[2])
                 for bk, gp, sl in zip(b_ref.tolist(), grad_p.tolist(), slide.tolist())]
        np.testing.assert_array_equal(A[i:len(barriers) * pairs:len(barriers)], A_ref)
        np.testing.assert_array_equal(b[i:len(barriers) * pairs:len(barriers)], b_ref)


def test_guard_rows_are_the_distance_hocbfs(make_env):
    """With a guard, the obstacle rows alternate: the C3BF filter's row for a point, then the row
    a distance-HOCBF filter with the guard's gains has for it. Floor and joint rows follow once."""
    u = make_env(scenario="none").unwrapped
    u.reset(seed=5)
    scene(u, np.random.default_rng(5), 2)
    config = FilterConfig(sensing_radius=0.5, joint_speed_fraction=1.0, guard=None)
    guarded = SafetyHook(u, config.replace(barrier=C3BF(gamma=5.0), guard=DistanceHOCBF(gamma1=3.0, gamma2=4.0)))
    alone = SafetyHook(u, config.replace(barrier=C3BF(gamma=5.0)))
    hocbf = SafetyHook(u, config.replace(barrier=DistanceHOCBF(gamma1=3.0, gamma2=4.0)))
    A, b, h, _, n = (x.copy() if isinstance(x, np.ndarray) else x for x in guarded.rows())
    A1, b1, h1, _, _ = (x.copy() if isinstance(x, np.ndarray) else x for x in alone.rows())
    A2, b2, *_ = hocbf.rows()
    k = 6 * n
    assert n == 2 and len(b) == 2 * k + 36 and h == h1  # min h is the barrier's, not the guard's
    close(A[:2 * k:2], A1[:k], 0.0)
    close(b[:2 * k:2], b1[:k], 0.0)
    close(A[1:2 * k:2], A2[:k], 1e-12)
    close(b[1:2 * k:2], b2[:k], 1e-12)
    close(A[2 * k:], A1[k:], 0.0)
    close(b[2 * k:], b1[k:], 0.0)


# ----------------------------------------------------------------------------- QP layer


def test_hook_post():
    """The torque, the smallest residual ``A τ − b`` in the rows' units from the QP's normalised
    residuals (a row no torque can change counting ``−b_k``), and the correction."""
    rng = np.random.default_rng(9)
    A, b, u = rng.normal(size=(5, 3)), rng.normal(size=5), rng.normal(size=3)
    scale, limit = np.array([2.0, 3.0, 4.0]), np.array([1.0, 1.0, 1.0])
    norm = np.linalg.norm(A * scale, axis=1)
    residual_hat = ((A * scale) @ u - b) / norm  # what solve_rows leaves in qp.residual
    tau_nom = np.array([3.0, -0.5, -2.0])
    tau = np.zeros(3)
    residual, correction = _step.hook_post(b, norm, residual_hat, u, scale, tau_nom, limit, tau)
    close(tau, u * scale)
    assert residual == pytest.approx((A @ (u * scale) - b).min(), rel=1e-12)
    assert correction == pytest.approx(np.linalg.norm(u * scale - np.clip(tau_nom, -limit, limit)), rel=1e-14)
    # a row no torque can change (norm 0) counts -b_k, whatever its residual entry holds
    lowest = int(np.argmin(A @ (u * scale) - b))
    norm[lowest], b[lowest] = 0.0, 1e3
    assert _step.hook_post(b, norm, residual_hat, u, scale, tau_nom, limit, tau)[0] == -1e3
    assert _step.hook_post(np.zeros(0), np.zeros(0), np.zeros(0), u, scale, tau_nom, limit, tau)[0] == np.inf


def test_kernels_are_cached_on_disk():
    """Every kernel caches its machine code (cache=True): test and SubprocVecEnv worker processes
    load it instead of compiling again."""
    from numba.core.registry import CPUDispatcher

    from c3bf_gym.safety import _daqp

    modules = (_dynamics, _rows, _qp, _step, _daqp)
    dispatchers = [f for module in modules for f in vars(module).values() if isinstance(f, CPUDispatcher)]
    assert len(dispatchers) >= 15 and _qp.solve_rows in dispatchers
    assert all(not isinstance(f._cache, NullCache) for f in dispatchers)


class _GainC3BF(C3BF):
    """A subclass that changes only the gain, through the public property."""

    @property
    def gamma(self) -> float:
        return 2.0


def test_a_subclass_changing_only_gamma_is_honoured_on_the_fused_path(make_env):
    """The fused kernel reads the barrier's parameters through its public properties, as the
    per-class path does, so a subclass overriding ``gamma`` gets its own rows on both."""
    u = make_env(scenario="none").unwrapped
    u.reset(seed=3)
    scene(u, np.random.default_rng(3), 3)
    config = FilterConfig(sensing_radius=0.5, guard=None)
    fused = SafetyHook(u, config.replace(barrier=_GainC3BF()))
    assert fused._fused
    A1, b1, *_ = (x.copy() if isinstance(x, np.ndarray) else x for x in fused.rows())
    plain = SafetyHook(u, config.replace(barrier=C3BF(gamma=2.0)))
    A2, b2, *_ = plain.rows()
    close(A1, A2, 0.0)
    close(b1, b2, 0.0)
    base = SafetyHook(u, config.replace(barrier=C3BF()))  # gamma 5: other rows
    assert not np.allclose(base.rows()[1][:len(b1)], b1)


def test_a_barrier_row_may_give_way_only_within_its_raised_gain():
    """beyond_allowance: a barrier row at h > 0 may give way by (γ_max − γ) h (in ḣ's units:
    violation × row norm); not at h <= 0, and no other row may give way at all."""
    from c3bf_gym.safety._step import beyond_allowance

    gains = np.array([5.0, 25.0])  # γ, γ_max: allowance 20 h
    norm = np.array([2.0, 2.0, 3.0])  # barrier, guard (stride 2), floor
    row_h = np.array([0.01, 9.9, 9.9])
    held = np.array([0.0, 0.0, 0.0])

    def beyond(residual, h=row_h):
        return beyond_allowance(np.array(residual, dtype=float), norm, np.array(h, dtype=float), gains, 2, 2)

    assert not beyond(held)
    assert not beyond([-0.099, 0.0, 0.0])  # 0.099 * 2 = 0.198 <= 20 * 0.01 = 0.2
    assert beyond([-0.101, 0.0, 0.0])  # 0.202 > 0.2
    assert beyond([-0.001, 0.0, 0.0], h=[0.0, 9.9, 9.9])  # on the cone's surface: no allowance
    assert beyond([-0.001, 0.0, 0.0], h=[-0.01, 9.9, 9.9])
    assert beyond([0.0, -0.001, 0.0])  # the guard's row
    assert beyond([0.0, 0.0, -0.001])  # the floor's row
    assert not beyond([-5e-7, -5e-7, -5e-7])  # within the solver's tolerance
    norm[0] = 0.0  # an unmovable row
    assert beyond([-0.001, 0.0, 0.0])


def test_the_allowance_the_qp_gets_is_the_one_the_report_accepts():
    """set_allowances (the allowance level's input) gives each barrier row at h > 0 exactly what
    beyond_allowance accepts, (γ_max − γ) h, and every other row 0."""
    from c3bf_gym.safety._step import beyond_allowance, set_allowances

    gains = np.array([5.0, 25.0])
    row_h = np.array([0.01, 9.9, -0.02, 9.9, 9.9])  # barrier, guard, barrier (inside its cone), guard, floor
    allowance = np.full(5, np.nan)
    set_allowances(allowance, row_h, gains, 4, 2)
    np.testing.assert_allclose(allowance, [0.2, 0.0, 0.0, 0.0, 0.0])
    norm = np.full(5, 2.0)
    at = -allowance / norm  # each row given way by exactly its allowance
    assert not beyond_allowance(at, norm, row_h, gains, 4, 2)
    at[0] -= 1e-3  # the first row a little further
    assert beyond_allowance(at, norm, row_h, gains, 4, 2)
