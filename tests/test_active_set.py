"""Tests for c3bf_gym._active_set (the Goldfarb–Idnani solver) and its use in TorqueQP."""

import numpy as np
import pytest

from c3bf_gym import _active_set
from c3bf_gym.qp import TorqueQP

N, MAX_ROWS = 6, 92


def _problem(rng, m, W_kind, kind):
    """A random feasible problem with n = 6; ``kind`` adds duplicate / parallel rows or puts τ_nom
    far outside the box."""
    lo, hi = -rng.uniform(1, 10, N), rng.uniform(1, 10, N)
    tau_star = rng.uniform(0.9 * lo, 0.9 * hi)
    A = rng.normal(size=(m, N)) * rng.uniform(0.1, 10, (m, 1))
    b = A @ tau_star - rng.uniform(0, 1, m) * np.linalg.norm(A, axis=1) * (rng.uniform(size=m) < 0.7)
    if kind == "parallel" and m >= 4:
        k = m // 4
        A[-k:] = A[:k] * rng.uniform(0.1, 5, (k, 1))      # scaled copies (some bound exactly)
        b[-k:] = b[:k] * (A[-k:, 0] / A[:k, 0]) - rng.uniform(0, 0.1, k) * (rng.uniform(size=k) < 0.5)
        A[1], b[1] = A[0], b[0]                              # an exact duplicate
        A[2], b[2] = -A[3], -(A[3] @ tau_star)               # anti-parallel: together an equality
        b[3] = A[3] @ tau_star
    scale = 10.0 if kind == "far" else 2.0
    tau_nom = rng.uniform(scale * lo, scale * hi)
    return (tau_nom, A, b, *_weight(rng, W_kind), lo, hi)


def _weight(rng, W_kind):
    """``(W as given to TorqueQP, W as a matrix)``: a positive diagonal, or a dense SPD matrix."""
    if W_kind == "diag":
        W = rng.uniform(0.2, 5, N)
        return W, np.diag(W)
    L = rng.normal(size=(N, N))
    W = L @ L.T + 0.5 * np.eye(N)
    return W, W


def _kkt_error(qp, tau_nom, A, b, Wm, lo, hi):
    """Largest KKT violation of the layer's last active-set solve, checked in numpy from its
    multipliers and active rows (a certificate: independent of how they were found)."""
    m = A.shape[0]
    nrm = np.linalg.norm(A, axis=1)
    G = np.vstack([A / nrm[:, None], np.zeros((qp.max_rows - m, N)), np.eye(N), -np.eye(N)])
    h = np.concatenate([b / nrm, np.full(qp.max_rows - m, -np.inf), lo, -hi])
    return _gi_kkt_error(G, h, Wm, tau_nom, qp._as_work, qp._as_iwork, N)


@pytest.mark.parametrize("W_kind", ["diag", "dense"])
@pytest.mark.parametrize("kind", ["plain", "parallel", "far"])
def test_matches_proxsuite_and_kkt(W_kind, kind):
    """The active-set optimum passes an independent KKT check and equals proxsuite's "solved"
    torque. proxsuite's path reports some of these feasible problems "relaxed" (large multipliers:
    the elastic slack is not exact and its capped hard solve does not converge, module docstring
    of c3bf_gym.qp): its torque then violates rows, or costs no less."""
    rng = np.random.default_rng(10 * ["diag", "dense"].index(W_kind) + ["plain", "parallel", "far"].index(kind))
    checked = compared = 0
    for trial in range(40):
        m = int(rng.choice([0, 1, 5, 12, 30, 60, MAX_ROWS])) if trial else MAX_ROWS
        tau_nom, A, b, W, Wm, lo, hi = _problem(rng, m, W_kind, kind)
        qa = TorqueQP(N, MAX_ROWS, lo, hi, W=W)
        qp = TorqueQP(N, MAX_ROWS, lo, hi, W=W, solver="proxsuite")
        ra = qa.solve(tau_nom, A, b)
        if ra.iterations == 0:      # fast path (τ_nom feasible): nothing to check here
            continue
        checked += 1
        assert ra.status == "solved" and ra.feasible and qa.active_set_fallbacks == 0
        assert _kkt_error(qa, tau_nom, A, b, Wm, lo, hi) < 1e-9
        np.testing.assert_array_equal(ra.tau, np.clip(qa._as_x, lo, hi))
        rp = qp.solve(tau_nom, A, b)
        if rp.status == "solved":
            compared += 1
            np.testing.assert_allclose(ra.tau, rp.tau, atol=1e-5 * (1 + np.abs(rp.tau).max()))
        elif rp.slack <= 1e-6:
            cost = lambda t: 0.5 * (t - tau_nom) @ Wm @ (t - tau_nom)  # noqa: E731
            assert cost(ra.tau) <= cost(rp.tau) * (1 + 1e-6)
    assert checked >= 30 and compared >= checked - 3


def test_warm_start_across_changing_rows_matches_cold():
    """Warm starts (the previous active rows, box rows included, padding rows skipped when m
    shrinks) give the cold start's answer, in fewer steps on slowly varying problems."""
    rng = np.random.default_rng(7)
    tau_nom, A, _, W, Wm, lo, hi = _problem(rng, MAX_ROWS, "diag", "plain")
    tau_star, delta = 0.5 * (lo + hi), rng.uniform(0, 1, MAX_ROWS)
    qa = TorqueQP(N, MAX_ROWS, lo, hi, W=W)
    cold = TorqueQP(N, MAX_ROWS, lo, hi, W=W)
    warm_steps, cold_steps = [], []
    for k in range(60):
        A = A + 0.01 * rng.normal(size=A.shape)
        b = A @ tau_star - delta * np.linalg.norm(A, axis=1)   # τ* stays feasible
        tau_nom = tau_nom + 0.05 * rng.normal(size=N)
        m = MAX_ROWS if k % 10 < 7 else int(rng.integers(0, MAX_ROWS))
        ra = qa.solve(tau_nom, A[:m], b[:m])
        cold._as_iwork[0] = 0                                # forget the previous active set
        rc = cold.solve(tau_nom, A[:m], b[:m])
        assert ra.status == rc.status == "solved"
        np.testing.assert_allclose(ra.tau, rc.tau, atol=1e-9)
        assert _kkt_error(qa, tau_nom, A[:m], b[:m], Wm, lo, hi) < 1e-9
        warm_steps.append(ra.iterations)
        cold_steps.append(rc.iterations)
    assert qa.active_set_fallbacks == 0
    assert np.median(warm_steps) < np.median(cold_steps)


def _kernel(G, h, m, x0, W, max_iter=50):
    n = x0.size
    work, iwork = _active_set.work_arrays(n, G.shape[0])
    code, steps = _active_set.solve(G, h, m, G.shape[0] - 2 * n, 2 * n, x0, _active_set.weight_data(W), 1e-10, 1e-8,
                                    max_iter, False, work, iwork)
    return code, steps, work[2 * n, :n].copy()


def _stack(A, b, lo, hi, M):
    """G, h of the kernel: A, b padded to M rows, then the box rows."""
    m, n = A.shape
    G = np.zeros((M + 2 * n, n))
    h = np.full(M + 2 * n, -1e154)
    G[:m], h[:m] = A, b
    G[M:M + n], h[M:M + n] = np.eye(n), lo
    G[M + n:], h[M + n:] = -np.eye(n), -hi
    return G, h


@pytest.mark.parametrize("case", ["contradiction", "with_box", "cone"])
def test_infeasible_is_reported_and_layer_relaxes(case):
    n = 4
    lo, hi = -np.full(n, 2.0), np.full(n, 2.0)
    tau_nom = np.array([0.3, -0.2, 0.1, 0.0])
    if case == "contradiction":   # x0 >= 1 and x0 <= 0
        A, b = np.array([[1.0, 0, 0, 0], [-1.0, 0, 0, 0]]), np.array([1.0, 0.0])
    elif case == "with_box":      # each row reachable in the box, together x0 >= 2.7 > 2
        s = 1 / np.sqrt(2)
        A, b = np.array([[s, s, 0, 0], [s, -s, 0, 0]]), np.array([3.5, 1.9]) * s
    else:                         # rows ±a_k >= 0.5: no point satisfies a row and its mirror
        A = np.random.default_rng(5).normal(size=(8, n))
        A /= np.linalg.norm(A, axis=1)[:, None]
        A, b = np.vstack([A, -A]), np.full(16, 0.5)
    G, h = _stack(A, b, lo, hi, 16)
    code, _, _ = _kernel(G, h, A.shape[0], tau_nom, np.eye(n))
    assert code == _active_set.INFEASIBLE
    qa = TorqueQP(n, 16, lo, hi)
    qp = TorqueQP(n, 16, lo, hi, solver="proxsuite")
    ra = qa.solve(tau_nom, A, b)
    assert ra.status == "relaxed" and not ra.feasible and ra.slack > 0
    assert qa.active_set_fallbacks == 0 and qa.active_set_troubles == 0 and qa.relax_calls == 1
    rp = qp.solve(tau_nom, A, b)
    assert rp.status == "relaxed" and rp.active_rows == ra.active_rows
    np.testing.assert_allclose(ra.tau, rp.tau, atol=1e-7)
    assert ra.slack == pytest.approx(rp.slack, abs=1e-7)


def _infeasible_problem(rng, m, W_kind):
    """A random problem with 1–3 contradicting row pairs (gaps 0.01–2 N·m), a fifth of them with
    a row no torque in the box reaches; plus relaxation weights on a third of them."""
    lo, hi = -rng.uniform(1, 10, N), rng.uniform(1, 10, N)
    c = rng.uniform(0.5 * lo, 0.5 * hi)
    A = rng.normal(size=(m, N)) * rng.uniform(0.1, 10, (m, 1))
    b = A @ c - rng.uniform(0, 1, m) * np.linalg.norm(A, axis=1)
    for _ in range(int(rng.integers(1, 4))):
        j, a = int(rng.integers(0, m - 1)), rng.normal(size=N)
        A[j], A[j + 1] = a, -a * rng.uniform(0.5, 2)
        gap = rng.uniform(0.01, 2)
        b[j:j + 2] = A[j:j + 2] @ c + gap * np.linalg.norm(A[j:j + 2], axis=1)
    if rng.uniform() < 0.2:
        A[0] = rng.normal(size=N)
        b[0] = 2 * np.abs(A[0]) @ np.maximum(-lo, hi)
    tau_nom = rng.uniform(2 * lo, 2 * hi)
    W, Wm = _weight(rng, W_kind)
    weights = rng.uniform(0.5, 5, m) if rng.uniform() < 0.3 else None
    return tau_nom, A, b, W, Wm, lo, hi, weights


def _gi_kkt_error(G, h, Wt, x0, work, iwork, nv):
    """KKT violation of an active-set solve with ``nv`` variables from its multipliers and active
    rows (``work``/``iwork``), against the problem ``G``, ``h``, ``W̃``, ``x₀`` built in numpy."""
    Nw = work.shape[1] - 1
    q = int(iwork[0])
    rows, u, x = iwork[1:1 + q], work[2 * Nw + 4, :q], work[2 * Nw, :nv]
    grad = Wt @ (x - x0)
    primal = max(0.0, float(np.max(h - G @ x)))
    dual = max(0.0, float(-u.min())) if q else 0.0
    complementarity = float(np.abs(G[rows] @ x - h[rows]).max()) if q else 0.0
    stationarity = float(np.abs(grad - G[rows].T @ u).max()) / (1 + np.abs(grad).max())
    return max(primal, dual, complementarity, stationarity)


@pytest.mark.parametrize("W_kind", ["diag", "dense"])
def test_infeasible_random_matches_proxsuite_and_kkt(W_kind):
    """Infeasible problems: the elastic and the per-row repair QP, both solved by the active-set
    solver, pass KKT checks of those problems built here in numpy (clipped bounds for impossible
    rows, slack rows K = rows the clipped elastic torque violates); the result equals proxsuite's
    (status, τ, slack, active rows). The repair solved in τ alone (the default) settles on every
    problem and gives the slack QP's torque (``repair_rounds=0``, whose KKT point is checked)."""
    rng = np.random.default_rng(20 + ["diag", "dense"].index(W_kind))
    M, n = MAX_ROWS, N
    rounds = []
    for trial in range(60):
        m = int(rng.choice([4, 12, 30, 60, MAX_ROWS]))
        tau_nom, A, b, W, Wm, lo, hi, weights = _infeasible_problem(rng, m, W_kind)
        qr = TorqueQP(N, MAX_ROWS, lo, hi, W=W)
        qa = TorqueQP(N, MAX_ROWS, lo, hi, W=W)
        qa.repair_rounds = 0
        qp = TorqueQP(N, MAX_ROWS, lo, hi, W=W, solver="proxsuite")
        rr = qr.solve(tau_nom, A, b, weights)
        ra = qa.solve(tau_nom, A, b, weights)
        rp = qp.solve(tau_nom, A, b, weights)
        assert rr.status == ra.status == rp.status == "relaxed" and qa.active_set_fallbacks == 0
        assert qr._kr == 0 and qr.active_set_fallbacks == 0  # settled in τ alone: no slack QP, no proxsuite
        np.testing.assert_allclose(rr.tau, ra.tau, rtol=0, atol=1e-9)
        np.testing.assert_allclose(ra.tau, rp.tau, atol=1e-6)
        assert ra.slack == pytest.approx(rp.slack, abs=1e-6) and ra.active_rows == rp.active_rows
        # elastic QP in (τ, t): rows (Â | 1/σ), box, t ≥ 0; bounds clipped to each row's reach
        nrm = np.linalg.norm(A, axis=1)
        An, bn = A / nrm[:, None], b / nrm
        reach = np.maximum(An * lo, An * hi).sum(axis=1)
        hc = np.minimum(bn, reach) if np.any(bn > reach + qa.active_tol) else bn
        sigma = np.sqrt(qa.slack_weight)
        box_G = np.vstack([np.eye(n), -np.eye(n)])
        G = np.zeros((M + 2 * n + 1, n + 1))
        G[:m, :n], G[:m, n], G[M:M + 2 * n, :n], G[-1, n] = An, 1 / sigma, box_G, 1.0
        h = np.concatenate([hc, np.full(M - m, -1e300), lo, -hi, [0.0]])
        Wt = np.eye(n + 1)
        Wt[:n, :n] = Wm
        x0 = np.append(tau_nom, -1.0)
        assert _gi_kkt_error(G, h, Wt, x0, qa._el_work, qa._el_iwork, n + 1) < 1e-9
        # per-row repair in (τ, t_K)
        tau_star = np.clip(qa._el_x[:n], lo, hi)
        K = np.flatnonzero(An @ tau_star - bn < qa.active_tol)
        k = K.size
        np.testing.assert_array_equal(qa._Kr[:k], K)
        w = np.ones(m) if weights is None else weights
        G = np.zeros((M + 2 * n + k, n + k))
        G[:m, :n], G[M:M + 2 * n, :n], G[M + 2 * n:, n:] = An, box_G, np.eye(k)
        G[K, n + np.arange(k)] = 1 / (qa.row_slack_weight * w[K])
        h = np.concatenate([hc, np.full(M - m, -1e300), lo, -hi, np.zeros(k)])
        Wt = np.eye(n + k)
        Wt[:n, :n] = Wm
        x0 = np.concatenate([tau_nom, -np.ones(k)])
        assert _gi_kkt_error(G, h, Wt, x0, qa._rep_work, qa._rep_iwork, n + k) < 1e-9
        np.testing.assert_array_equal(ra.tau, np.clip(qa._rep_x, lo, hi))


def test_repair_in_tau_alone_follows_drifting_problems_and_hands_over_when_capped():
    """The repair in τ alone starts each call from the last call's soft rows: on a sequence of
    drifting infeasible problems it gives the slack QP's torque at every call, both when it
    settles (default rounds) and when one round is too few and the slack QP takes over."""
    rng = np.random.default_rng(40)
    for W_kind in ("diag", "dense"):
        tau_nom, A, b, W, Wm, lo, hi, weights = _infeasible_problem(rng, 30, W_kind)
        qps = {rounds: TorqueQP(N, MAX_ROWS, lo, hi, W=W) for rounds in (16, 1, 0)}
        for rounds, q in qps.items():
            q.repair_rounds = rounds
        handed_over = 0
        for _ in range(40):
            tau_nom = tau_nom + rng.normal(scale=0.3, size=N)
            A = A + rng.normal(scale=0.02, size=A.shape)
            results = {rounds: q.solve(tau_nom, A, b, weights) for rounds, q in qps.items()}
            assert all(r.status == "relaxed" for r in results.values())
            np.testing.assert_allclose(results[16].tau, results[0].tau, rtol=0, atol=1e-9)
            np.testing.assert_allclose(results[1].tau, results[0].tau, rtol=0, atol=1e-9)
            handed_over += qps[1]._kr > 0
        assert qps[16]._kr == 0 and handed_over > 0  # the capped one did hand over, the default never


@pytest.mark.parametrize("rounds", [-1, 2.5, True, "8"])
def test_bad_repair_rounds_rejected(rounds):
    with pytest.raises(ValueError, match="repair_rounds must be an integer >= 0"):
        TorqueQP(2, 4, -1.0, 1.0).repair_rounds = rounds


def test_infeasible_step_caps_fall_back_to_proxsuite():
    """With a negative step cap every active-set solve hands over to proxsuite (hard and repair):
    the same result as proxsuite's own."""
    rng = np.random.default_rng(30)
    for _ in range(5):
        tau_nom, A, b, W, Wm, lo, hi, weights = _infeasible_problem(rng, 30, "diag")
        qa = TorqueQP(N, MAX_ROWS, lo, hi, W=W)
        qa.active_set_max_iter = -100
        ra = qa.solve(tau_nom, A, b, weights)
        rp = TorqueQP(N, MAX_ROWS, lo, hi, W=W, solver="proxsuite").solve(tau_nom, A, b, weights)
        assert ra.status == rp.status == "relaxed" and qa.active_set_fallbacks == qa.active_set_troubles == 2
        np.testing.assert_allclose(ra.tau, rp.tau, atol=1e-12)


def test_repair_after_a_capped_hard_solve_uses_this_calls_nominal():
    """The hard solve reaches its cap (handed to proxsuite), the repair does not: the repair must
    pull towards this call's nominal, not the previous infeasible call's (a regression: joint 1,
    free of the rows, followed the old nominal)."""
    A = np.array([[1.0, 0.0], [-1.0, 0.0]])  # τ0 ≥ 0.5 and τ0 ≤ 0.2: no torque satisfies both
    b = np.array([0.5, -0.2])
    qa = TorqueQP(2, 4, -1.0, 1.0)
    qa.solve(np.array([0.0, -0.7]), A, b)  # an infeasible call: the repair's nominal is (0, -0.7)
    qa.active_set_max_iter = 1  # the hard solve needs 2 steps to prove infeasibility; the repair gets 1 + 2k
    ra = qa.solve(np.array([0.0, 0.9]), A, b)
    rp = TorqueQP(2, 4, -1.0, 1.0, solver="proxsuite").solve(np.array([0.0, 0.9]), A, b)
    assert ra.status == rp.status == "relaxed" and qa.active_set_fallbacks >= 1
    np.testing.assert_allclose(ra.tau, rp.tau, atol=1e-6)
    assert ra.tau[1] == pytest.approx(0.9)


@pytest.mark.parametrize("weights", [[np.nan, 1.0], [0.0, 1.0], [-1.0, 1.0], [np.inf, 1.0]])
def test_bad_relaxation_weights_rejected(weights):
    A = np.array([[1.0, 0.0], [-1.0, 0.0]])
    with pytest.raises(ValueError, match="weights must be finite and > 0"):
        TorqueQP(2, 4, -1.0, 1.0).solve(np.zeros(2), A, np.array([0.5, -0.2]), weights)


def test_kernel_degenerate_duplicates_and_dense_box_projection():
    # ten copies of one binding row, a ridge of ties: the optimum is the projection on the row
    n = 3
    A = np.tile([[1.0, 1.0, 0.0]], (10, 1)) / np.sqrt(2)
    b = np.full(10, 1.0 / np.sqrt(2))
    G, h = _stack(A, b, -np.full(n, 5.0), np.full(n, 5.0), 12)
    code, steps, x = _kernel(G, h, 10, np.zeros(n), np.eye(n))
    assert code == _active_set.OPTIMAL and steps == 1
    np.testing.assert_allclose(x, [0.5, 0.5, 0.0], atol=1e-14)
    # no rows, dense W: the W-metric projection onto the box. With x0 = 1 at its bound,
    # x1 = argmin (x0 − 3)² + (x0 − 3) x1 + x1² = 1, exactly at its bound too (zero multiplier)
    Wd = np.array([[2.0, 1.0], [1.0, 2.0]])
    G, h = _stack(np.zeros((0, 2)), np.zeros(0), -np.ones(2), np.ones(2), 0)
    code, _, x = _kernel(G, h, 0, np.array([3.0, 0.0]), Wd)
    assert code == _active_set.OPTIMAL
    np.testing.assert_allclose(x, [1.0, 1.0], atol=1e-14)


def test_step_cap_falls_back_to_proxsuite():
    rng = np.random.default_rng(8)
    tau_nom, A, b, W, Wm, lo, hi = _problem(rng, 40, "diag", "far")
    qa = TorqueQP(N, MAX_ROWS, lo, hi, W=W)
    qa.active_set_max_iter = 1
    ra = qa.solve(tau_nom, A, b)
    assert ra.status == "solved" and qa.active_set_fallbacks == qa.active_set_troubles == 1
    ref = TorqueQP(N, MAX_ROWS, lo, hi, W=W).solve(tau_nom, A, b)
    np.testing.assert_allclose(ra.tau, ref.tau, atol=1e-5 * (1 + np.abs(ref.tau).max()))


def test_fast_path_and_proxsuite_solver_do_not_call_the_kernel(monkeypatch):
    def boom(*args):
        raise AssertionError("active-set kernel called")

    rng = np.random.default_rng(9)
    tau_nom, A, b, W, Wm, lo, hi = _problem(rng, 30, "diag", "plain")
    qa = TorqueQP(N, MAX_ROWS, lo, hi, W=W)
    qp = TorqueQP(N, MAX_ROWS, lo, hi, W=W, solver="proxsuite")
    monkeypatch.setattr(_active_set, "solve", boom)
    tau_safe = np.clip(tau_nom, lo, hi)
    res = qa.solve(tau_safe, A, np.minimum(b, A @ tau_safe - 0.1))   # τ_nom feasible: fast path
    assert res.iterations == 0 and res.status == "solved"
    np.testing.assert_array_equal(res.tau, tau_safe)
    res = qp.solve(tau_nom, A, b)                                    # binding: proxsuite only
    assert res.status == "solved" and res.iterations > 0 and qp.active_set_fallbacks == 0


def test_solver_name_is_validated():
    with pytest.raises(ValueError, match="'active_set', 'proxsuite'"):
        TorqueQP(N, 4, -1, 1, solver="qpoases")
    assert TorqueQP(N, 4, -1, 1).solver == "active_set"
