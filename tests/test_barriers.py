"""Tests for c3bf_gym.safety.barriers: gradients, time-derivative consistency, rows, limits."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from c3bf_gym.safety.barriers import (
    Floor,
    BARRIERS,
    C3BF,
    Barrier,
    DistanceHOCBF,
    JointLimits,
    Rows,
    make_barrier,
)

import reference

FAST = settings(max_examples=100, deadline=None)

# ----------------------------------------------------------------------------- strategies

_unit = arrays(np.float64, 3, elements=st.floats(-1.0, 1.0)).filter(
    lambda x: np.linalg.norm(x) > 0.1
)
_vel = arrays(np.float64, 3, elements=st.floats(-2.0, 2.0))


@st.composite
def outside_states(draw, max_points: int = 4):
    """(p, v, r) for P points with ‖p‖ in [1.05 r, 5 r], r in [0.05, 1] m."""
    n_pts = draw(st.integers(1, max_points))
    p, v, r = np.empty((n_pts, 3)), np.empty((n_pts, 3)), np.empty(n_pts)
    for k in range(n_pts):
        r[k] = draw(st.floats(0.05, 1.0))
        d = draw(_unit)
        p[k] = d / np.linalg.norm(d) * r[k] * draw(st.floats(1.05, 5.0))
        v[k] = draw(_vel)
    return p, v, r


def all_barriers() -> list[Barrier]:
    return [C3BF(gamma=3.0, eps=1e-2), DistanceHOCBF(gamma1=2.0, gamma2=4.0)]


# ----------------------------------------------------------------------------- gradients


def _central_diff(f, x: np.ndarray, step: float) -> np.ndarray:
    """d f(x) / d x for f: (P, 3) -> (P,), row-wise (points independent), shape (P, 3)."""
    grad = np.empty_like(x)
    for i in range(3):
        dx = np.zeros_like(x)
        dx[:, i] = step
        grad[:, i] = (f(x + dx) - f(x - dx)) / (2 * step)
    return grad


@FAST
@given(outside_states())
def test_c3bf_gradients_match_finite_differences(state):
    p, v, r = state
    bar = C3BF(gamma=1.0, eps=1e-2)
    h, grad_p, grad_v = reference.partials(bar, p, v, r)
    fd_p = _central_diff(lambda x: bar.terms(x, v, r).h, p, 1e-6)
    fd_v = _central_diff(lambda x: bar.terms(p, x, r).h, v, 1e-6)
    np.testing.assert_allclose(grad_p, fd_p, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(grad_v, fd_v, rtol=1e-5, atol=1e-6)
    t = bar.terms(p, v, r)
    np.testing.assert_allclose(t.h, h)
    np.testing.assert_allclose(t.grad_v, grad_v)
    np.testing.assert_allclose(t.drift, np.einsum("pi,pi->p", grad_p, v), rtol=1e-12, atol=1e-12)
    assert not t.inside.any()


@FAST
@given(outside_states())
def test_hocbf_partials_match_finite_differences(state):
    p, v, r = state
    bar = DistanceHOCBF(gamma1=2.0, gamma2=4.0)
    _, grad_p, grad_v = reference.partials(bar, p, v, r)
    np.testing.assert_allclose(
        grad_p, _central_diff(lambda x: bar.terms(x, v, r).h, p, 1e-6), rtol=1e-5, atol=1e-6
    )
    np.testing.assert_allclose(
        grad_v, _central_diff(lambda x: bar.terms(p, x, r).h, v, 1e-6), rtol=1e-5, atol=1e-6
    )


# ----------------------------------------------------------------------------- ḣ consistency


@pytest.mark.parametrize("bar", all_barriers(), ids=lambda b: b.name)
@FAST
@given(state=outside_states(), a=arrays(np.float64, (4, 3), elements=st.floats(-5.0, 5.0)))
def test_hdot_matches_double_integrator(bar, state, a):
    """(h(t+dt) − h(t−dt)) / 2dt ≈ drift + ⟨grad_v, a⟩ along p' = v, v' = a."""
    p, v, r = state
    a = a[: p.shape[0]]
    dt = 1e-6
    h_plus = bar.terms(p + v * dt + 0.5 * a * dt**2, v + a * dt, r).h
    h_minus = bar.terms(p - v * dt + 0.5 * a * dt**2, v - a * dt, r).h
    t = bar.terms(p, v, r)
    predicted = t.drift + np.einsum("pi,pi->p", t.grad_v, a)
    np.testing.assert_allclose((h_plus - h_minus) / (2 * dt), predicted, rtol=1e-5, atol=1e-5)


# ----------------------------------------------------------------------------- rows


@pytest.mark.parametrize("bar", all_barriers(), ids=lambda b: b.name)
@FAST
@given(state=outside_states(), n=st.integers(1, 7), seed=st.integers(0, 2**32 - 1))
def test_rows_match_barrier_condition(bar, state, n, seed):
    p, v, r = state
    n_pts = p.shape[0]
    rng = np.random.default_rng(seed)
    G = rng.normal(size=(n_pts, 3, n))
    c = rng.normal(size=(n_pts, 3))
    tau = rng.normal(size=n)

    rows = bar.rows(p, v, r, G, c)
    assert rows.A.shape == (n_pts, n) and rows.b.shape == (n_pts,)
    t = bar.terms(p, v, r)
    acc = np.einsum("pin,n->pi", G, tau) + c
    expected = t.drift + np.einsum("pi,pi->p", t.grad_v, acc) + bar.gamma * t.h
    np.testing.assert_allclose(rows.A @ tau - rows.b, expected, rtol=1e-9, atol=1e-9)

    extra = 3
    out = Rows(np.full((n_pts + extra, n), 7.0), np.full(n_pts + extra, 7.0))
    got = bar.rows(p, v, r, G, c, out=out)
    np.testing.assert_array_equal(got.A, rows.A)
    np.testing.assert_array_equal(got.b, rows.b)
    np.testing.assert_array_equal(out.A[:n_pts], rows.A)
    np.testing.assert_array_equal(out.b[:n_pts], rows.b)
    assert np.all(out.A[n_pts:] == 7.0) and np.all(out.b[n_pts:] == 7.0)
    assert np.shares_memory(got.A, out.A) and np.shares_memory(got.b, out.b)


@pytest.mark.parametrize("bar", all_barriers(), ids=lambda b: b.name)
def test_rows_shape_validation(bar):
    p, v, r = np.ones((2, 3)) * 2, np.zeros((2, 3)), np.full(2, 0.5)
    G, c = np.zeros((2, 3, 4)), np.zeros((2, 3))
    with pytest.raises(ValueError, match="p must have shape"):
        bar.terms(np.ones((2, 2)), v, r)
    with pytest.raises(ValueError, match="v must have"):
        bar.terms(p, np.zeros((3, 3)), r)
    with pytest.raises(ValueError, match="r must have"):
        bar.terms(p, v, np.ones(3))
    with pytest.raises(ValueError, match="G must have"):
        bar.rows(p, v, r, np.zeros((3, 3, 4)), c)
    with pytest.raises(ValueError, match="G must have"):
        bar.rows(p, v, r, np.zeros((2, 2, 4)), c)
    with pytest.raises(ValueError, match="c must have"):
        bar.rows(p, v, r, G, np.zeros((2, 4)))
    with pytest.raises(ValueError, match="out.A"):
        bar.rows(p, v, r, G, c, out=Rows(np.zeros((1, 4)), np.zeros(2)))
    with pytest.raises(ValueError, match="out.A"):
        bar.rows(p, v, r, G, c, out=Rows(np.zeros((2, 5)), np.zeros(2)))
    with pytest.raises(ValueError, match="out.b"):
        bar.rows(p, v, r, G, c, out=Rows(np.zeros((2, 4)), np.zeros(1)))


# ----------------------------------------------------------------------------- C3BF sign


def _ray_enters_open_ball_gap(p: np.ndarray, v: np.ndarray, r: float) -> float:
    """min_{t≥0} ‖p + t v‖² − r²: negative iff the ray enters the open ball."""
    t_star = max(0.0, -float(p @ v) / float(v @ v))
    closest = p + t_star * v
    return float(closest @ closest) - r * r


@settings(max_examples=300, deadline=None)
@given(
    r=st.floats(0.05, 1.0),
    d=_unit,
    k=st.floats(1.01, 5.0),
    v=_vel.filter(lambda x: np.linalg.norm(x) > 1e-3),
)
def test_c3bf_sign_matches_ray_sphere_test(r, d, k, v):
    p = d / np.linalg.norm(d) * r * k
    gap = _ray_enters_open_ball_gap(p, v, r)
    assume(abs(gap) > 1e-3 * r * r)  # skip near-tangent rays
    h = C3BF(gamma=1.0, eps=1e-9).terms(p[None], v[None], np.array([r])).h[0]
    assert (h >= 0.0) == (gap >= 0.0)


# ----------------------------------------------------------------------------- singular cases


def test_c3bf_at_rest_is_safe_and_finite():
    eps = 1e-2
    bar = C3BF(gamma=2.0, eps=eps)
    p = np.array([[0.3, 0.0, 0.4], [0.0, -2.0, 0.0]])
    r = np.array([0.2, 1.0])
    v = np.zeros((2, 3))
    t = bar.terms(p, v, r)
    s = np.sqrt(np.sum(p**2, axis=1) - r**2)
    np.testing.assert_allclose(t.h, eps * s)
    assert np.all(t.h > 0)
    np.testing.assert_allclose(t.grad_v, p)  # s v / ‖v‖_ε vanishes at v = 0
    np.testing.assert_allclose(t.drift, 0.0)
    _, grad_p, _ = reference.partials(bar, p, v, r)
    assert np.all(np.isfinite(grad_p))
    assert not t.inside.any()


@pytest.mark.parametrize("bar", all_barriers(), ids=lambda b: b.name)
def test_inside_and_on_ball_is_finite_and_flagged(bar):
    r = np.full(5, 0.5)
    p = np.array(
        [
            [0.1, 0.2, 0.0],  # inside
            [0.0, 0.0, 0.0],  # at the centre
            [0.5, 0.0, 0.0],  # exactly on the surface
            [0.0, 0.3, 0.4],  # on the surface (‖p‖ = 0.5)
            [0.0, 0.0, 0.0],  # centre, at rest
        ]
    )
    v = np.array(
        [[1.0, -1.0, 0.5], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
    )
    t = bar.terms(p, v, r)
    assert t.inside.all()
    for arr in t[:3]:
        assert np.all(np.isfinite(arr))
    G = np.ones((5, 3, 2))
    rows = bar.rows(p, v, r, G, np.zeros((5, 3)))
    assert np.all(np.isfinite(rows.A)) and np.all(np.isfinite(rows.b))


def test_c3bf_inside_falls_back_to_a_bounded_recovery_row():
    """On or inside the ball, moving inward: the row asks for a bounded push apart along p,
    and its value meets the C3BF's on the surface."""
    bar = C3BF(gamma=5.0)
    p, v, r = np.array([[0.5, 0.0, 0.0]]), np.array([[-1.0, 0.0, 0.0]]), np.array([0.5])
    rows = bar.rows(p, v, r, np.eye(3)[None], np.zeros((1, 3)))
    # h = <p,v> = -0.5, drift = |v|^2 + γ<p,v> = -1.5: <p, a> >= γ 0.5 + 1.5 = 4
    np.testing.assert_allclose(rows.A[0], p[0])
    np.testing.assert_allclose(rows.b[0], 4.0)
    outside = bar.terms(p * (1 + 1e-9), v, r).h[0]
    assert bar.terms(p, v, r).h[0] == pytest.approx(outside, abs=1e-4)
    deep = bar.rows(np.array([[0.1, 0.0, 0.0]]), v, r, np.eye(3)[None], np.zeros((1, 3)))
    assert 0 < deep.b[0] < 100  # well scaled, unlike a clamped cone


@FAST
@given(outside_states(), st.floats(0.0, 0.999))
def test_hocbf_h0_negative_iff_inside(state, shrink):
    p, v, r = state
    bar = DistanceHOCBF()
    p_in = p.copy()
    p_in[0] *= shrink * r[0] / np.linalg.norm(p[0])  # first point strictly inside
    h0 = bar.h0(p_in, r)
    inside = bar.terms(p_in, v, r).inside
    np.testing.assert_array_equal(h0 < 0, inside)
    assert inside[0] and not inside[1:].any()


# ----------------------------------------------------------------------------- joint limits


def _joint_setup(n: int, seed: int):
    rng = np.random.default_rng(seed)
    q_lo = rng.uniform(-3.0, -0.5, n)
    q_hi = rng.uniform(0.5, 3.0, n)
    qd_max = rng.uniform(0.5, 3.0, n)
    L = rng.normal(size=(n, n))
    M = L @ L.T + n * np.eye(n)
    return q_lo, q_hi, qd_max, M, rng


@settings(max_examples=60, deadline=None)
@given(n=st.integers(1, 7), seed=st.integers(0, 2**32 - 1))
def test_joint_limit_rows_match_definitions(n, seed):
    q_lo, q_hi, qd_max, M, rng = _joint_setup(n, seed)
    g1, g2, gv = 3.0, 7.0, 11.0
    lim = JointLimits(q_lo, q_hi, qd_max, gamma1=g1, gamma2=g2, gamma_v=gv)
    Minv = np.linalg.inv(M)
    q, qd, c_q, tau = (rng.normal(size=n) for _ in range(4))

    rows = lim.rows(q, qd, Minv, c_q)
    assert rows.A.shape == (4 * n, n) and rows.b.shape == (4 * n,) and lim.n_rows == 4 * n
    qdd = Minv @ tau + c_q
    psi_u = -qd + g1 * (q_hi - q)
    psi_l = qd + g1 * (q - q_lo)
    expected = np.concatenate(
        [
            -qdd - g1 * qd + g2 * psi_u,
            qdd + g1 * qd + g2 * psi_l,
            -qdd + gv * (qd_max - qd),
            qdd + gv * (qd + qd_max),
        ]
    )
    np.testing.assert_allclose(rows.A @ tau - rows.b, expected, rtol=1e-9, atol=1e-9)

    out = Rows(np.full((4 * n + 2, n), 7.0), np.full(4 * n + 2, 7.0))
    got = lim.rows(q, qd, Minv, c_q, out=out)
    np.testing.assert_array_equal(got.A, rows.A)
    np.testing.assert_array_equal(got.b, rows.b)
    assert np.all(out.A[4 * n :] == 7.0) and np.all(out.b[4 * n :] == 7.0)


def test_joint_limits_rest_mid_range_admits_zero_acceleration():
    n = 6
    q_lo, q_hi, qd_max, M, rng = _joint_setup(n, 0)
    lim = JointLimits(q_lo, q_hi, qd_max)
    c_q = rng.normal(size=n)  # e.g. gravity
    rows = lim.rows(0.5 * (q_lo + q_hi), np.zeros(n), np.linalg.inv(M), c_q)
    tau = -M @ c_q  # q̈ = Minv τ + c_q = 0
    assert np.all(rows.A @ tau - rows.b > 0)


def test_joint_limits_scalar_qd_max_and_readonly():
    lim = JointLimits([-1.0, -2.0], [1.0, 2.0], 1.5)
    np.testing.assert_array_equal(lim.qd_max, [1.5, 1.5])
    with pytest.raises(ValueError):
        lim.q_lo[0] = 0.0


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (dict(q_lo=[0.0, 0.0], q_hi=[1.0], qd_max=1.0), "q_hi must have shape"),
        (dict(q_lo=[[0.0]], q_hi=[1.0], qd_max=1.0), "q_lo must have shape"),
        (dict(q_lo=[0.0, 0.0], q_hi=[1.0, 1.0], qd_max=[1.0, 1.0, 1.0]), "qd_max must be"),
        (dict(q_lo=[0.0, 1.0], q_hi=[1.0, 1.0], qd_max=1.0), r"q_lo must be < q_hi.*\[1\]"),
        (dict(q_lo=[0.0, np.nan], q_hi=[1.0, 1.0], qd_max=1.0), "finite or -inf"),
        (dict(q_lo=[0.0, np.inf], q_hi=[1.0, np.inf], qd_max=1.0), "finite or -inf"),
        (dict(q_lo=[0.0, 0.0], q_hi=[1.0, 1.0], qd_max=[1.0, 0.0]), r"qd_max.*\(0, inf\)"),
        (dict(q_lo=[0.0], q_hi=[1.0], qd_max=1.0, gamma1=0.0), r"gamma1.*\(0, inf\)"),
        (dict(q_lo=[0.0], q_hi=[1.0], qd_max=1.0, gamma2=-1.0), r"gamma2.*\(0, inf\)"),
        (dict(q_lo=[0.0], q_hi=[1.0], qd_max=1.0, gamma_v=np.nan), r"gamma_v.*\(0, inf\)"),
    ],
)
def test_joint_limits_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        JointLimits(**kwargs)


def test_joint_limits_rows_shape_validation():
    lim = JointLimits([-1.0, -1.0], [1.0, 1.0], 1.0)
    z, Z = np.zeros(2), np.eye(2)
    with pytest.raises(ValueError, match="q must have shape"):
        lim.rows(np.zeros(3), z, Z, z)
    with pytest.raises(ValueError, match="Minv must have shape"):
        lim.rows(z, z, np.eye(3), z)
    with pytest.raises(ValueError, match="out.A"):
        lim.rows(z, z, Z, z, out=Rows(np.zeros((7, 2)), np.zeros(8)))


def test_floor_rows_are_the_second_order_barrier_on_each_end():
    """``Floor.rows``: ``A_k = G_z``, ``b_k = −γ² (z − z_min) − 2γ ż − c_z`` for the listed ends
    of packed end dynamics (per end and axis: position, velocity, acceleration at zero torque,
    then the acceleration per unit force)."""
    rng = np.random.default_rng(3)
    packed = rng.normal(size=(6, 3, 3 + 4))  # 3 capsules, ends a then b, nv = 4
    floor = Floor([0, 4, 5], [0.1, 0.2, -0.05], gamma=7.0)
    rows = floor.rows(packed)
    (z, zd, c), G = (packed[[0, 4, 5], 2, i] for i in range(3)), packed[[0, 4, 5], 2, 3:]
    assert floor.n_rows == 3 and rows.A.shape == (3, 4)
    np.testing.assert_allclose(rows.A, G, rtol=0, atol=0)
    np.testing.assert_allclose(rows.b, -(49.0 * (z - [0.1, 0.2, -0.05]) + 14.0 * zd + c), rtol=1e-14, atol=1e-14)
    assert Floor((), (), 5.0).rows(packed).A.shape == (0, 4)  # no floor plane: no rows


@pytest.mark.parametrize(
    "args, match",
    [
        (([0, 1], [0.1], 5.0), "one entry each per row; got 2 and 1"),
        (([[0, 1]], [[0.1, 0.2]], 5.0), r"must be 1-D.*\(1, 2\)"),
        (([-1], [0.1], 5.0), "ends must be indices >= 0"),
        (([0], [np.nan], 5.0), "min_height finite"),
        (([0], [0.1], 0.0), r"gamma.*\(0, inf\)"),
    ],
)
def test_floor_validation(args, match):
    with pytest.raises(ValueError, match=match):
        Floor(*args)


# ----------------------------------------------------------------------------- registry / params


def test_registry_and_make_barrier():
    assert set(BARRIERS) == {"c3bf", "hocbf"}
    bar = make_barrier("c3bf", gamma=2.0, eps=1e-3)
    assert isinstance(bar, C3BF) and bar.gamma == 2.0 and bar.eps == 1e-3
    bar = make_barrier("hocbf", gamma1=1.0, gamma2=3.0)
    assert isinstance(bar, DistanceHOCBF) and bar.gamma == 3.0 and bar.gamma1 == 1.0
    assert all(BARRIERS[name].name == name for name in BARRIERS)


def test_make_barrier_unknown_name():
    with pytest.raises(ValueError, match=r"unknown barrier 'foo'; valid choices: 'c3bf', 'hocbf'"):
        make_barrier("foo")


def test_make_barrier_unknown_parameter():
    with pytest.raises(ValueError, match=r"valid parameters: gamma, eps"):
        make_barrier("c3bf", gamma1=1.0)


@pytest.mark.parametrize(
    ("name", "params", "bad"),
    [
        ("c3bf", dict(gamma=0.0), "gamma"),
        ("c3bf", dict(gamma=-1.0), "gamma"),
        ("c3bf", dict(gamma=np.inf), "gamma"),
        ("c3bf", dict(eps=0.0), "eps"),
        ("c3bf", dict(eps=np.nan), "eps"),
        ("c3bf", dict(eps="big"), "eps"),
        ("hocbf", dict(gamma1=-2.0), "gamma1"),
        ("hocbf", dict(gamma2=0.0), "gamma2"),
    ],
)
def test_bad_gains_raise(name, params, bad):
    with pytest.raises(ValueError, match=rf"^{bad} must be a finite number in \(0, inf\)"):
        make_barrier(name, **params)
