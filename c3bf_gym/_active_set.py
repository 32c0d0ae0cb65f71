"""Compiled dense dual active-set QP solver (Goldfarb & Idnani 1983) for :class:`~c3bf_gym.qp.TorqueQP`.

Solves the *hard* filter problem (n small, rows already normalised by
:func:`c3bf_gym._kernels.qp_prepare`), and on infeasible calls the elastic and per-row repair
problems (module docstring of :mod:`c3bf_gym.qp`)::

    minimise  ½ (x − x₀)ᵀ W (x − x₀)   s.t.   G_k x ≥ h_k   for the m rows and the bound rows

(hard: x = τ, bound rows = the 2n box rows; elastic and repair: x = (τ, t), W = blockdiag(W, I),
x₀ = (τ_nom, −1, …), bound rows = box and t ≥ 0; the repair in τ alone,
:func:`c3bf_gym._kernels.reduced_repair`: x = τ with a dense W and x₀ that fold in the soft rows).

GI starts at the unconstrained minimiser x₀ and adds violated constraints one at a time while
keeping every multiplier ≥ 0 (dual feasible), so the first primal-feasible iterate is the optimum.
Why it suits the filter: n = 6, so at most 6 rows are ever active and a solve takes a handful of
steps (each one scan of the rows plus O(n²) work), it is exact (it stops when no row is violated,
not on a residual tolerance; the strictly convex problem has one optimum, so the answer does not
depend on the warm start), and it proves infeasibility on its own (a violated row that is a
non-positive combination of the active ones).

Design:

* **Box = 2n rows.** The box is the rows ``G[M:M+2n]`` that :class:`~c3bf_gym.qp.TorqueQP`
  already keeps for its residuals (``(I | 0) ≥ τ_min``, ``(−I | 0) ≥ −τ_max``); the safety rows
  are ``G[:m]`` (columns past n, e.g. the elastic slack column, are ignored). One code path, and a
  box row costs n multiplications in the scan like any other. The slacks' t ≥ 0 are more such
  bound rows (``G[M:M+nbox]``).
* **Variable count.** n = len(x₀) may be less than the work arrays and ``[W; J₀]`` hold: the
  solver uses their leading blocks, so one set serves repairs with any number of slacks (the
  leading blocks of blockdiag(W, I) and of its J₀ = blockdiag(L⁻ᵀ, I) are those of fewer slacks).
* **Factorisation.** ``J = L⁻ᵀ Q`` and the upper-triangular ``R`` with ``Jᵀ N = [R; 0]``
  (N = active normals), updated by Givens reflections on each add and drop (GI's section 4).
  ``J₀ = L⁻ᵀ`` (W = L Lᵀ) is computed once per weight by the caller; a diagonal W gives a
  diagonal J₀ and nothing else changes (all loops are over n ≤ 6, so the dense form costs
  no more than a special case would).
* **Linear dependence.** A violated row p whose transformed normal ``d = Jᵀ n_p`` lies in the
  active span (‖d[q:]‖ ≤ ``_DEP_TOL`` ‖d‖) gets no primal step: GI's dual-only step drops the
  active row whose multiplier reaches 0 first; if no multiplier can decrease, p is a non-positive
  combination of the active rows while violated at a point where they hold with equality — the
  infeasibility certificate (``INFEASIBLE``).
* **Warm start.** Consecutive filter problems mostly share their active rows. With ``warm``, the
  rows active at the last ``OPTIMAL`` solve (row indices; box rows keep theirs) are factorised
  again and x is put at the optimum with them as equalities. If all their multipliers are ≥ 0
  this is a GI state (x optimal on its active set, dual feasible) and GI continues from it;
  usually no row is then violated and the solve ends after this one step. A negative multiplier
  means the set is no GI state: the solve starts cold from x₀.
  (``benchmarks/qp_micro.py`` prints the step counts: with 48 drifting rows, median 1 step.)
* **Ties.** A full step wins a tie with a partial one (p is added and the blocking row keeps a
  zero multiplier); multipliers are clamped at 0 against rounding.
* **Acceptance.** ``OPTIMAL`` only after a KKT check of the final point: finite, every row and
  the box within ``tol`` (the final scan), active rows within ``vtol`` of equality, and
  stationarity ``‖W (x − x₀) − N u‖∞ ≤ _STAT_TOL (1 + ‖W (x − x₀)‖∞ + Σ u)``. Otherwise
  ``TROUBLE``; ``max_iter`` steps without an answer give ``ITER_CAP``. The caller falls back to
  proxsuite on all three non-optimal outcomes.

Work arrays (no allocation per call), for up to N variables: ``work`` (2N + 5, N + 1) float64
holds J, R, x, d, z, r and the multipliers u (N + 1 entries: the active ones and the
candidate's); ``iwork`` (N + 2 + len(G)) int64 holds the warm start's row count, the active rows
(N + 1) and per-row "active" flags indexed like G.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from c3bf_gym import _compile_cache  # noqa: F401  (before any @njit(cache=True): the cache keys)

OPTIMAL = 0
INFEASIBLE = 1
ITER_CAP = 2
TROUBLE = 3

_DEP_TOL = 1e-10   # ‖d[q:]‖ / ‖d‖ below this: the row is in the span of the active rows
_STAT_TOL = 1e-8   # relative stationarity error accepted by the final KKT check

_opts = {"cache": True, "nogil": True, "error_model": "numpy", "boundscheck": False}


def work_shapes(n: int, n_rows: int) -> tuple[tuple[int, int], tuple[int]]:
    """Shapes of :func:`work_arrays`' ``(work, iwork)`` (float64, int64)."""
    return (2 * n + 5, n + 1), (n + 2 + n_rows,)


def work_arrays(n: int, n_rows: int) -> tuple[np.ndarray, np.ndarray]:
    """``(work, iwork)`` for :func:`solve` with up to n variables and a G of ``n_rows`` rows."""
    work, iwork = work_shapes(n, n_rows)
    return np.zeros(work), np.zeros(iwork, dtype=np.int64)


def weight_data(W: np.ndarray, extra: int = 0) -> np.ndarray:
    """``(2N, N)`` array ``[W̃; J₀]`` for ``W̃ = blockdiag(W, I_extra)`` (N = n + extra) and
    ``J₀ = L⁻ᵀ`` (W̃ = L Lᵀ; W symmetric positive definite). Its leading blocks serve any problem
    in the first n + k ≤ N variables (:func:`solve`)."""
    n = W.shape[0]
    N = n + extra
    out = np.zeros((2 * N, N))
    out[:N, :N] = np.eye(N)
    out[N:, :N] = np.eye(N)
    out[:n, :n] = W
    out[N:N + n, :n] = np.linalg.solve(np.linalg.cholesky(W), np.eye(n)).T
    return out


@njit(**_opts)
def _add(q, d, J, R):
    """Append the row with transformed normal ``d`` to the factorisation; returns q + 1.

    Reflections of columns (j−1, j) of J fold d[q:] into d[q] (keeping Jᵀ N = [R; 0]), then d[:q+1]
    becomes column q of R."""
    n = d.shape[0]
    for j in range(n - 1, q, -1):
        hyp = math.hypot(d[j - 1], d[j])
        if hyp == 0.0:
            continue
        cc = d[j - 1] / hyp
        ss = d[j] / hyp
        d[j - 1] = hyp
        d[j] = 0.0
        for i in range(n):
            t1 = J[i, j - 1]
            t2 = J[i, j]
            J[i, j - 1] = cc * t1 + ss * t2
            J[i, j] = ss * t1 - cc * t2
    for i in range(q + 1):
        R[i, q] = d[i]
    return q + 1


@njit(**_opts)
def _drop(pos, q, act, u, J, R, flags):
    """Remove the active row at position ``pos`` (of q); returns q − 1.

    Shifts the active list and the multipliers (including the candidate's u[q]), deletes column pos
    of R and restores its triangle by reflections of rows (j, j+1), applied to J's columns too."""
    n = J.shape[0]
    flags[act[pos]] = 0
    for i in range(pos, q):
        act[i] = act[i + 1]
        u[i] = u[i + 1]
    for i in range(pos, q - 1):
        for j in range(n):
            R[j, i] = R[j, i + 1]
    for j in range(n):
        R[j, q - 1] = 0.0
    q -= 1
    for j in range(pos, q):
        hyp = math.hypot(R[j, j], R[j + 1, j])
        if hyp == 0.0:
            continue
        cc = R[j, j] / hyp
        ss = R[j + 1, j] / hyp
        R[j, j] = hyp
        R[j + 1, j] = 0.0
        for k in range(j + 1, q):
            t1 = R[j, k]
            t2 = R[j + 1, k]
            R[j, k] = cc * t1 + ss * t2
            R[j + 1, k] = ss * t1 - cc * t2
        for i in range(n):
            t1 = J[i, j]
            t2 = J[i, j + 1]
            J[i, j] = cc * t1 + ss * t2
            J[i, j + 1] = ss * t1 - cc * t2
    return q


@njit(**_opts)
def _slack(G, h, k, x):
    """``G_k x − h_k`` over the first ``len(x)`` columns."""
    acc = 0.0
    for j in range(x.shape[0]):
        acc += G[k, j] * x[j]
    return acc - h[k]


@njit(**_opts)
def _transformed(J, G, k, q, d):
    """``d = Jᵀ G_k``; returns ``(‖d‖², ‖d[q:]‖²)`` (the part outside the active span)."""
    n = J.shape[0]
    dd = 0.0
    d2 = 0.0
    for j in range(n):
        acc = 0.0
        for i in range(n):
            acc += J[i, j] * G[k, i]
        d[j] = acc
        dd += acc * acc
        if j >= q:
            d2 += acc * acc
    return dd, d2


@njit(**_opts)
def _most_violated(G, h, x, m, M, nbox, flags, tol):
    """``(row, slack)`` of the inactive row (safety rows ``[0, m)``, bound rows ``[M, M+nbox)``)
    with the smallest slack below −tol; row −1 if there is none."""
    p = -1
    sp = -tol
    for k in range(m):
        if flags[k] == 0:
            s = _slack(G, h, k, x)
            if s < sp:
                sp = s
                p = k
    for k in range(M, M + nbox):
        if flags[k] == 0:
            s = _slack(G, h, k, x)
            if s < sp:
                sp = s
                p = k
    return p, sp


@njit(**_opts)
def _warm_start(G, h, m, M, x0, q_prev, act, u, J, R, flags, d, v, x):
    """Re-add the previous call's active rows (skipping padding rows and dependent ones) and put x
    at the optimum with them as equalities: ``v = R⁻ᵀ (h_A − N_Aᵀ x₀)``, ``u = R⁻¹ v``,
    ``x = x₀ + J[:, :q] v``. Returns q, or 0 (nothing changed but ``J``, ``flags``) if a multiplier
    is negative: then that set is no GI state and the solve starts cold."""
    n = x0.shape[0]
    q = 0
    for i in range(q_prev):
        k = act[i]
        if m <= k < M:
            continue
        dd, d2 = _transformed(J, G, k, q, d)
        if d2 > _DEP_TOL * _DEP_TOL * dd:
            q = _add(q, d, J, R)
            act[q - 1] = k
            flags[k] = 1
    for i in range(q):
        acc = -_slack(G, h, act[i], x0)
        for j in range(i):
            acc -= R[j, i] * v[j]
        v[i] = acc / R[i, i]
    ok = True
    for i in range(q - 1, -1, -1):
        acc = v[i]
        for j in range(i + 1, q):
            acc -= R[i, j] * u[j]
        u[i] = acc / R[i, i]
        ok = ok and u[i] >= 0.0
    if not ok:
        for i in range(q):
            flags[act[i]] = 0
        return 0
    for i in range(n):
        acc = x0[i]
        for j in range(q):
            acc += J[i, j] * v[j]
        x[i] = acc
    return q


@njit(**_opts)
def _kkt_ok(G, h, x0, W, q, act, u, x, z, vtol):
    """Final check: finite x, active rows at equality within ``vtol``, stationarity (module doc)."""
    n = x0.shape[0]
    for j in range(n):
        if not math.isfinite(x[j]):
            return False
    usum = 0.0
    for i in range(q):
        if not abs(_slack(G, h, act[i], x)) <= vtol:
            return False
        usum += u[i]
    gmax = 0.0
    for i in range(n):  # z = W (x − x₀) − N u
        acc = 0.0
        for j in range(n):
            acc += W[i, j] * (x[j] - x0[j])
        gmax = max(gmax, abs(acc))
        z[i] = acc
    for a in range(q):
        for i in range(n):
            z[i] -= u[a] * G[act[a], i]
    err = 0.0
    for i in range(n):
        err = max(err, abs(z[i]))
    return err <= _STAT_TOL * (1.0 + gmax + usum)


@njit(**_opts)
def solve(G, h, m, M, nbox, x0, WJ, tol, vtol, max_iter, warm, work, iwork):
    """Goldfarb–Idnani on the rows ``G[:m]`` and the bound rows ``G[M:M+nbox]``, n = len(x0) variables.

    Args:
        G, h: (≥ M + nbox, ≥ n) rows and bounds, ``G_k x ≥ h_k`` (first n columns used).
        m: number of safety rows.
        M, nbox: the bound rows (box, slack ≥ 0) are ``G[M:M+nbox]``.
        x0: (n,) unconstrained minimiser (the nominal torque; (τ_nom, −1, …) for the elastic and
            repair problems, whose slack costs ½t² + t).
        WJ: ``[W; J₀]`` from :func:`weight_data` for N ≥ n variables (its leading n×n blocks are used).
        tol: a row is violated when ``G_k x − h_k < −tol``.
        vtol: active rows must hold with equality to within ``vtol`` at the end.
        max_iter: cap on steps (adds + drops, + 1 for an accepted warm start).
        warm: start from the active rows of the last ``OPTIMAL`` solve with these work arrays
            (module docstring); otherwise from x₀ with no active row.
        work, iwork: from :func:`work_arrays` for N ≥ n variables and len(G) rows; the solution
            is ``work[2N, :n]``, the multipliers ``work[2N + 4, :q]`` of the active rows
            ``iwork[1:1+q]``, q = ``iwork[0]``.

    Returns:
        ``(status, steps)``: status ``OPTIMAL``, ``INFEASIBLE``, ``ITER_CAP`` or ``TROUBLE``.
    """
    n = x0.shape[0]
    N = work.shape[1] - 1
    NW = WJ.shape[1]
    W = WJ[:n, :n]
    J = work[:n, :n]
    R = work[N:N + n, :n]
    x = work[2 * N, :n]
    d = work[2 * N + 1, :n]
    z = work[2 * N + 2, :n]
    r = work[2 * N + 3, :n]
    u = work[2 * N + 4]
    act = iwork[1:N + 2]
    flags = iwork[N + 2:]
    for i in range(n):
        x[i] = x0[i]
        for j in range(n):
            J[i, j] = WJ[NW + i, j]
    for k in range(m):
        flags[k] = 0
    for k in range(M, M + nbox):
        flags[k] = 0
    q = 0
    if warm and iwork[0] > 0:
        q = _warm_start(G, h, m, M, x0, iwork[0], act, u, J, R, flags, d, r, x)
        if q == 0:
            for i in range(n):
                for j in range(n):
                    J[i, j] = WJ[NW + i, j]
    iwork[0] = 0
    steps = 1 if q else 0  # the warm start counts as one step
    while True:
        # ---- step 1: the most violated row (none: x is optimal)
        p, sp = _most_violated(G, h, x, m, M, nbox, flags, tol)
        if p < 0:
            if _kkt_ok(G, h, x0, W, q, act, u, x, z, vtol):
                iwork[0] = q
                return OPTIMAL, steps
            return TROUBLE, steps
        u[q] = 0.0
        # ---- step 2: move until p is satisfied (add it) or a multiplier reaches 0 (drop that row)
        while True:
            if steps >= max_iter:
                return ITER_CAP, steps
            steps += 1
            dd, d2 = _transformed(J, G, p, q, d)
            full = d2 > _DEP_TOL * _DEP_TOL * dd
            t2 = np.inf
            if full:  # primal direction z = J[:, q:] d[q:], with G_pᵀ z = ‖d[q:]‖²
                for i in range(n):
                    acc = 0.0
                    for j in range(q, n):
                        acc += J[i, j] * d[j]
                    z[i] = acc
                t2 = max(-sp, 0.0) / d2
            for i in range(q - 1, -1, -1):  # dual direction r = R⁻¹ d[:q]
                acc = d[i]
                for j in range(i + 1, q):
                    acc -= R[i, j] * r[j]
                r[i] = acc / R[i, i]
            t1 = np.inf
            drop = -1
            for i in range(q):
                if r[i] > 0.0 and u[i] / r[i] < t1:
                    t1 = u[i] / r[i]
                    drop = i
            if not full and drop < 0:
                return INFEASIBLE, steps
            t = min(t1, t2)
            if full:
                for i in range(n):
                    x[i] += t * z[i]
            for i in range(q):
                u[i] = max(u[i] - t * r[i], 0.0)
            u[q] += t
            if full and t2 <= t1:  # full step: p joins the active set
                q = _add(q, d, J, R)
                act[q - 1] = p
                flags[p] = 1
                break
            q = _drop(drop, q, act, u, J, R, flags)
            if full:
                sp = min(_slack(G, h, p, x), 0.0)
