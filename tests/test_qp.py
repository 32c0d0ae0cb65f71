"""Tests for c3bf_gym.qp (torque safety-filter QP layer)."""

import itertools

import numpy as np
import pytest

from c3bf_gym.qp import SOLVERS, TorqueQP

TOL = 1e-6
both_solvers = pytest.mark.parametrize("solver", SOLVERS)


def _brute_force(tau_nom, A, b, W, lo, hi):
    """Exact QP optimum by active-set enumeration (tiny problems only)."""
    n = tau_nom.size
    G = np.vstack([A, np.eye(n), -np.eye(n)])
    h = np.concatenate([b, lo, -hi])
    best = None
    for k in range(n + 1):
        for S in itertools.combinations(range(G.shape[0]), k):
            S = list(S)
            K = np.block([[W, -G[S].T], [G[S], np.zeros((k, k))]])
            rhs = np.concatenate([W @ tau_nom, h[S]])
            try:
                sol = np.linalg.solve(K, rhs)
            except np.linalg.LinAlgError:
                continue
            x, lam = sol[:n], sol[n:]
            if np.all(G @ x - h >= -1e-9) and np.all(lam >= -1e-9):
                f = 0.5 * (x - tau_nom) @ W @ (x - tau_nom)
                if best is None or f < best[0]:
                    best = (f, x)
    return best[1]


def _random_feasible(rng, n, m, W_kind="diag"):
    lo, hi = -rng.uniform(1, 10, n), rng.uniform(1, 10, n)
    tau_star = rng.uniform(0.9 * lo, 0.9 * hi)
    A = rng.normal(size=(m, n)) * rng.uniform(0.1, 10, (m, 1))
    b = A @ tau_star - rng.uniform(0, 1, m) * np.linalg.norm(A, axis=1)
    tau_nom = rng.uniform(2 * lo, 2 * hi)
    if W_kind == "diag":
        W = rng.uniform(0.5, 3, n)
        Wm = np.diag(W)
    else:
        L = rng.normal(size=(n, n))
        Wm = L @ L.T + n * np.eye(n)
        W = Wm
    return tau_nom, A, b, W, Wm, lo, hi


@both_solvers
@pytest.mark.parametrize("W_kind", ["diag", "dense"])
def test_random_feasible_matches_brute_force(W_kind, solver):
    rng = np.random.default_rng(1 if W_kind == "diag" else 2)
    n, M = 3, 4
    for _ in range(25):
        m = int(rng.integers(1, M + 1))
        tau_nom, A, b, W, Wm, lo, hi = _random_feasible(rng, n, m, W_kind)
        qp = TorqueQP(n, M, lo, hi, W=W, solver=solver)
        res = qp.solve(tau_nom, A, b)
        assert res.feasible and res.status == "solved" and res.slack == 0.0
        tau = res.tau
        assert np.all(tau >= lo) and np.all(tau <= hi)
        assert np.all((A @ tau - b) / np.linalg.norm(A, axis=1) >= -TOL)
        ref = _brute_force(tau_nom, A, b, Wm, lo, hi)
        np.testing.assert_allclose(tau, ref, atol=1e-5 * (1 + np.abs(ref).max()))


@both_solvers
def test_random_feasible_6dof_sequence_warm(solver):
    """n=6, many rows, slowly changing: feasible and as good as a fresh solve."""
    rng = np.random.default_rng(3)
    n, M = 6, 48
    tau_nom, A, b, W, Wm, lo, hi = _random_feasible(rng, n, 30)
    qp = TorqueQP(n, M, lo, hi, W=W, solver=solver)
    for k in range(30):
        A = A + 0.01 * rng.normal(size=A.shape)
        tau_star = np.clip(rng.normal(size=n), lo, hi) * 0.1
        b = np.minimum(b, A @ tau_star)  # keep tau_star feasible
        m = int(rng.integers(0, M + 1)) if k % 5 == 0 else A.shape[0]
        Ak, bk = (A[:m], b[:m]) if m <= A.shape[0] else (A, b)
        res = qp.solve(tau_nom, Ak, bk)
        assert res.feasible and res.status == "solved"
        if Ak.shape[0]:
            assert np.all((Ak @ res.tau - bk) / np.linalg.norm(Ak, axis=1) >= -TOL)
        fresh = TorqueQP(n, M, lo, hi, W=W, solver=solver).solve(tau_nom, Ak, bk)
        f = lambda t: 0.5 * (t - tau_nom) @ Wm @ (t - tau_nom)
        assert f(res.tau) <= f(fresh.tau) + 1e-6 * (1 + f(fresh.tau))


def test_no_active_rows_returns_tau_nom():
    rng = np.random.default_rng(4)
    n = 6
    qp = TorqueQP(n, 10, -5, 5)
    tau_nom = rng.uniform(-4, 4, n)
    A = rng.normal(size=(10, n))
    res = qp.solve(tau_nom, A, np.full(10, -1e3))
    np.testing.assert_array_equal(res.tau, tau_nom)
    assert res.active_rows == 0 and res.feasible and res.iterations == 0


def test_m_zero():
    qp = TorqueQP(3, 0, -1, 1)
    res = qp.solve([0.5, -2.0, 3.0], np.zeros((0, 3)), np.zeros(0))
    np.testing.assert_allclose(res.tau, [0.5, -1.0, 1.0])
    assert res.feasible and res.status == "solved"
    # dense W: W-metric projection onto the box via the solver
    Wd = np.array([[2.0, 0.5, 0.0], [0.5, 1.0, 0.0], [0.0, 0.0, 1.0]])
    qp = TorqueQP(3, 2, -1, 1, W=Wd)
    res = qp.solve([0.5, -2.0, 3.0], np.zeros((0, 3)), np.zeros(0))
    ref = _brute_force(np.array([0.5, -2.0, 3.0]), np.zeros((0, 3)), np.zeros(0), Wd, -np.ones(3), np.ones(3))
    np.testing.assert_allclose(res.tau, ref, atol=1e-6)
    assert res.feasible


def _max_violation(A, b, tau):
    return max(0.0, float(np.max((b - A @ tau) / np.linalg.norm(A, axis=1))))


@both_solvers
@pytest.mark.parametrize("case", ["rows", "box", "random"])
def test_infeasible_relaxed(case, solver):
    n = 4
    lo, hi = -np.full(n, 2.0), np.full(n, 2.0)
    tau_nom = np.array([0.3, -0.2, 0.1, 0.0])
    if case == "rows":  # x0 >= 1 and x0 <= 0
        A = np.array([[1.0, 0, 0, 0], [-1.0, 0, 0, 0]])
        b = np.array([1.0, 0.0])
    elif case == "box":  # x0 + x1 >= 10 impossible in the box
        A = np.array([[1.0, 1.0, 0, 0]])
        b = np.array([10.0])
    else:
        rng = np.random.default_rng(5)
        A = rng.normal(size=(8, n))
        A = np.vstack([A, -A])
        b = np.full(16, 0.5)
    qp = TorqueQP(n, 16, lo, hi, solver=solver)
    res = qp.solve(tau_nom, A, b)
    assert not res.feasible and res.status == "relaxed" and res.slack > 0
    assert np.all(res.tau >= lo) and np.all(res.tau <= hi)
    assert res.slack == pytest.approx(_max_violation(A, b, res.tau), abs=1e-9)
    assert _max_violation(A, b, res.tau) <= _max_violation(A, b, np.clip(tau_nom, lo, hi)) + 1e-9
    if case == "rows":
        assert res.tau[0] == pytest.approx(0.5, abs=1e-4)
        assert res.slack == pytest.approx(0.5, abs=1e-4)
    if case == "box":
        np.testing.assert_allclose(res.tau[:2], [2.0, 2.0], atol=1e-6)
    # back to a feasible problem: the layer recovers
    res2 = qp.solve(tau_nom, A[:1], np.array([-5.0]))
    assert res2.feasible and res2.slack == 0.0


def test_warm_start_not_more_iterations():
    rng = np.random.default_rng(6)
    n = 6
    tau_nom, A, b, W, Wm, lo, hi = _random_feasible(rng, n, 24)
    tau_nom = np.clip(tau_nom, lo, hi)
    b = b + 0.5 * np.linalg.norm(A, axis=1)  # make some rows bind
    qp = TorqueQP(n, 24, lo, hi, W=W)
    r1 = qp.solve(tau_nom, A, b)
    t1 = r1.tau.copy()
    r2 = qp.solve(tau_nom, A, b)
    assert r1.iterations > 0
    assert r2.iterations <= r1.iterations
    assert r1.status == r2.status
    np.testing.assert_allclose(r2.tau, t1, atol=1e-6)


def test_set_weight_changes_solution():
    qp = TorqueQP(2, 1, -10, 10)
    A, b = np.array([[1.0, 1.0]]), np.array([2.0])
    r = qp.solve([0.0, 0.0], A, b)
    np.testing.assert_allclose(r.tau, [1.0, 1.0], atol=1e-6)
    qp.set_weight([1.0, 3.0])
    r = qp.solve([0.0, 0.0], A, b)
    np.testing.assert_allclose(r.tau, [1.5, 0.5], atol=1e-6)


def test_validation_errors():
    with pytest.raises(ValueError, match="tau_min"):
        TorqueQP(3, 2, 1.0, 1.0)
    with pytest.raises(ValueError, match="positive definite"):
        TorqueQP(2, 2, -1, 1, W=np.array([[1.0, 2.0], [2.0, 1.0]]))
    with pytest.raises(ValueError, match="symmetric"):
        TorqueQP(2, 2, -1, 1, W=np.array([[1.0, 0.5], [0.0, 1.0]]))
    with pytest.raises(ValueError, match="positive"):
        TorqueQP(2, 2, -1, 1, W=[1.0, -1.0])
    with pytest.raises(ValueError, match="max_rows"):
        TorqueQP(2, -1, -1, 1)
    with pytest.raises(ValueError, match="finite"):
        TorqueQP(2, 1, [-np.inf, -1], 1)
    qp = TorqueQP(3, 2, -1, 1)
    with pytest.raises(ValueError, match="max_rows=2"):
        qp.solve(np.zeros(3), np.zeros((3, 3)), np.zeros(3))
    with pytest.raises(ValueError, match="tau_nom"):
        qp.solve(np.zeros(2), np.zeros((1, 3)), np.zeros(1))
    with pytest.raises(ValueError, match="A must"):
        qp.solve(np.zeros(3), np.zeros((1, 2)), np.zeros(1))
    with pytest.raises(ValueError, match="b must"):
        qp.solve(np.zeros(3), np.zeros((1, 3)), np.zeros(2))
    with pytest.raises(ValueError, match="NaN"):
        qp.solve(np.array([0.0, np.nan, 0.0]), np.zeros((1, 3)), np.zeros(1))
    with pytest.raises(ValueError, match="NaN"):
        qp.solve(np.zeros(3), np.array([[0.0, np.inf, 0.0]]), np.zeros(1))
    with pytest.raises(ValueError, match="NaN"):
        qp.solve(np.zeros(3), np.ones((1, 3)), np.array([np.nan]))
    with pytest.raises(ValueError, match="positive definite"):
        qp.set_weight(-np.eye(3))


def test_nonfinite_inputs_raise_valueerror_not_warnings():
    qp = TorqueQP(2, 2, -1, 1)
    with pytest.raises(ValueError, match="NaN"):
        qp.solve(np.array([np.inf, -np.inf]), np.zeros((1, 2)), np.zeros(1))
    with pytest.raises(ValueError, match="NaN"):
        qp.solve(np.zeros(2), np.array([[np.inf, 1.0]]), np.array([np.inf]))
    with pytest.raises(ValueError, match="NaN"):
        qp.solve(np.zeros(2), np.array([[1e200, 1.0]]), np.array([0.0]))
    # zero row with b <= 0 is harmless, with b > 0 it is infeasible
    assert qp.solve(np.zeros(2), np.zeros((1, 2)), np.array([-1.0])).feasible
    res = qp.solve(np.zeros(2), np.zeros((1, 2)), np.array([1.0]))
    assert not res.feasible and res.status == "relaxed" and res.slack == pytest.approx(1.0)


@pytest.mark.parametrize("scale", [1.0, 1e4, 3e5])
def test_impossible_rows_are_solved_in_bounded_iterations(scale):
    """Rows asking more than any torque in the box can give (here contradictory pairs, scaled up)
    are certain violations: reported 'relaxed' with their true slack, in few iterations."""
    rng = np.random.default_rng(3)
    qp = TorqueQP(6, 20, -np.ones(6), np.ones(6))
    A = rng.normal(size=(10, 6))
    A = np.vstack([A, -A])
    b = np.full(20, 0.5 * scale)
    for _ in range(5):
        result = qp.solve(rng.uniform(-1, 1, 6), A, b)
        assert result.status == "relaxed" and not result.feasible
        assert result.iterations < 200
        assert np.all(np.abs(result.tau) <= 1.0)
        normalized_violation = np.max((b - A @ result.tau) / np.linalg.norm(A, axis=1))
        assert result.slack == pytest.approx(normalized_violation, rel=1e-9)


def test_relaxed_rows_outside_the_conflict_keep_holding():
    """x0 >= 1 and x0 <= 0 conflict; x1 >= -0.5 takes no part in it. One shared slack (the min-max
    torque) let the nominal torque push x1 to -1.0 (violated by the same 0.5); the per-row repair
    keeps x1 >= -0.5 and splits the conflict evenly (equal weights)."""
    qp = TorqueQP(4, 8, -2.0, 2.0)
    A = np.array([[1.0, 0, 0, 0], [-1.0, 0, 0, 0], [0, 1.0, 0, 0]])
    b = np.array([1.0, 0.0, -0.5])
    res = qp.solve(np.array([0.3, -1.9, 0.1, 0.0]), A, b)
    assert res.status == "relaxed" and not res.feasible
    assert res.tau[1] == pytest.approx(-0.5, abs=1e-6)
    assert res.tau[0] == pytest.approx(0.5, abs=1e-3)
    np.testing.assert_allclose(res.tau[2:], [0.1, 0.0], atol=1e-6)
    # weights: a unit of violation of row 0 costs 10 times more, so row 1 gives way
    res = qp.solve(np.array([0.3, -1.9, 0.1, 0.0]), A, b, weights=np.array([10.0, 1.0, 1.0]))
    assert res.tau[0] > 0.95 and res.tau[1] == pytest.approx(-0.5, abs=1e-6)


@both_solvers
def test_solved_result_is_the_optimum_after_warm_starts(solver):
    """Warm-started solves of a changing problem return the unique optimum (a fresh, tightly
    converged solve), not a feasible point with wrong-signed multipliers."""
    import proxsuite

    rng = np.random.default_rng(11)
    n, M = 6, 40
    qp = TorqueQP(n, M, -np.ones(n), np.ones(n), solver=solver)
    worst = 0.0
    for _ in range(300):
        m = int(rng.integers(4, M + 1))
        A = rng.normal(size=(m, n))
        tau_nom = rng.uniform(-1.5, 1.5, n)
        b = A @ rng.uniform(-0.5, 0.5, n) - rng.uniform(0, 0.3, m) * np.linalg.norm(A, axis=1)
        res = qp.solve(tau_nom, A, b)
        assert res.feasible
        nrm = np.linalg.norm(A, axis=1)
        ref = proxsuite.proxqp.dense.QP(n, 0, m, True)
        ref.settings.eps_abs, ref.settings.eps_rel, ref.settings.max_iter = 1e-12, 0.0, 100000
        ref.init(np.eye(n), -tau_nom, None, None, A / nrm[:, None], b / nrm, np.full(m, 1e20), -np.ones(n), np.ones(n))
        ref.solve()
        worst = max(worst, float(np.abs(res.tau - ref.results.x).max()))
    assert worst < 1e-5


def test_packed_step_buffers_are_the_step_buffers():
    """The fused kernel's three-argument form of the step buffers (``packed_step_buffers``, carved
    by ``_kernels.step_views``) is the same memory, shapes and types as ``step_buffers``."""
    from c3bf_gym import _kernels

    qp = TorqueQP(6, 40, -2.0, 3.0)
    carved = _kernels.step_views(*qp.packed_step_buffers())
    buffers = qp.step_buffers()
    assert len(carved) == len(buffers) == 32
    for got, want in zip(carved, buffers):
        assert got.ctypes.data == want.ctypes.data and got.shape == want.shape and got.dtype == want.dtype
    np.testing.assert_array_equal(qp.tau_min, -2.0)
    np.testing.assert_array_equal(qp.tau_max, 3.0)
