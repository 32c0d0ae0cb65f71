"""Joint-torque safety-filter QP layer (compiled active-set solver; proxsuite as its fallback).

Problem solved at every control step (n joints, m safety rows, torques in N·m)::

    minimise    ½ (τ − τ_nom)ᵀ W (τ − τ_nom)
    subject to  A τ ≥ b                 (m ≤ max_rows rows)
                τ_min ≤ τ ≤ τ_max       (hard actuator box)

Path of one call (``solver="active_set"``, the default; ``"proxsuite"`` skips the active set):

* **Data step** (:func:`c3bf_gym._kernels.qp_prepare`): validation (NaN or inf in ``τ_nom``,
  ``A`` or ``b`` raise ``ValueError``), row normalisation, residuals, and each row's reach
  ``max_{τ∈box} Â_k τ``.
* **Fast path.** If τ_nom lies in the box and satisfies every row it is the exact optimum and is
  returned without a solve (``iterations == 0``).
* **Hard problem, active set** (:mod:`c3bf_gym._active_set`, Goldfarb–Idnani dual active set,
  box as 2n rows, warm-started from the previous call's active rows). Its result is accepted
  only after a KKT check (rows, box, complementarity, stationarity); a proof that rows and box
  have no common point leads to the relaxation below; a step cap or failed check hands the call
  to proxsuite (``active_set_fallbacks``). Rows beyond the box's reach skip it.
* **Row normalisation.** Rows are divided by ‖A_k‖₂ before they reach a solver (an equivalent
  problem), so tolerances, ``slack`` and ``active_rows`` are in normalised units: the signed
  distance, in torque space (N·m), of τ to each row's half-space. Rows with ‖A_k‖ < 1e-12 are
  kept unscaled.
* **Elastic problem** (when the hard one is infeasible, or by proxsuite): one shared slack
  s ≥ 0, in the solver variable t = √ρ s (ρ = ``slack_weight``)::

      minimise  ½ (τ − τ_nom)ᵀ W (τ − τ_nom) + √ρ s + ½ ρ s²
      s.t.      Â τ + s·1 ≥ b̂,  τ_min ≤ τ ≤ τ_max,  s ≥ 0

  s ≤ ``active_tol`` means the hard problem is solved (its KKT conditions are then the hard
  problem's). Otherwise, by proxsuite, infeasibility is certified by a Farkas bound from the row
  multipliers y (y ≥ 0, Σy = 1: ``min_{τ∈box} max_k (b̂_k − Â_k τ) ≥ yᵀb̂ − Σ_i max(lo_i v_i,
  hi_i v_i)`` with ``v = Âᵀ y``), or decided by one capped hard solve. A proxsuite solve whose
  multipliers have the wrong sign (every row is a lower bound, so its multiplier must be ≤ 0)
  is repeated once from scratch. If even the elastic problem fails, ``status="failed"``: τ is
  its last iterate projected onto the box (the box projection of τ_nom if that is not finite);
  never τ_nom silently.
* **Relaxation: one slack per violated row.** The shared slack only bounds every row's
  violation by s, so the elastic torque τ* is repaired by one more QP in (τ, t_K)::

      minimise  ½ (τ − τ_nom)ᵀ W (τ − τ_nom) + Σ_{k∈K} (σ_k s_k + ½ σ_k² s_k²)
      s.t.      Â_k τ + s_k ≥ b̂_k (k ∈ K),   Â_k τ ≥ b̂_k (k ∉ K),   box,   s ≥ 0

  K = the rows τ* violates (residual < ``active_tol``), σ_k = ``row_slack_weight`` · weights[k].
  (τ*, its violations) is feasible, so the repair always has a solution; rows τ* satisfies stay
  satisfied, and the ℓ1 term is an exact penalty, so a row the conflict does not need returns
  to its bound; the violation is spread over the conflicting rows in proportion to 1/weights.
  The active-set path first solves it in τ alone
  (:func:`c3bf_gym._kernels.reduced_repair`: with the slacks eliminated the cost is piecewise
  quadratic; a guess of the rows with a positive slack is checked against the slack QP's KKT
  conditions and corrected at most ``repair_rounds`` times) before the slack QP takes over. If
  no solver delivers the repair, τ* itself is applied. ``slack`` is recomputed from the applied
  τ: the largest normalised row violation.
* **proxsuite data in place.** Each elastic row count (16, 32, 48, 64, 96, … up to
  ``max_rows``) has its own proxsuite QP, made on first use with native box constraints and
  warm-started from its own last result; unused rows are zero rows with infinite bounds
  (``PROXSUITE_INF``); ``mu_in`` is reset on every update; backend ``PrimalDualLDLT``.

Why each choice was made, with the measurements and the commands that repeat them:
``docs/design-decisions.md``, "QP layer".
"""

from __future__ import annotations

import math
import time
from typing import NamedTuple

import numpy as np
import proxsuite

from c3bf_gym import _active_set, _kernels

__all__ = ["QPResult", "TorqueQP", "PROXSUITE_INF", "SOLVERS"]

#: the ``solver`` choices of :class:`TorqueQP`
SOLVERS = ("active_set", "proxsuite")

_pq = proxsuite.proxqp
_SOLVED = _pq.QPSolverOutput.PROXQP_SOLVED

#: proxsuite's infinite bound (``helpers::infinite_bound<double>``, sqrt(DBL_MAX)).
PROXSUITE_INF: float = float(np.sqrt(np.finfo(np.float64).max))
_ROW_NORM_MIN = 1e-12
_MU_IN_RESET = 1e-3  # reset proxsuite mu_in on every update (see module docstring)
_DUAL_SIGN_TOL = 1e-6  # wrong-signed multipliers above this (relative to 1 + max |z|) reject a solve
_NO_SCALE = np.empty(0)  # solve(): the rows are used as given
_AS_TOL = 1e-10  # active set: a row is violated below −_AS_TOL (1 + max |box|) [normalised N·m]
_AS_VTOL = 1e-8  # active set: active rows must hold to _AS_VTOL (1 + max |box|) in its KKT check
_REPAIR_ROUNDS = 16  # the per-row repair in τ alone: guesses of its soft rows before the slack QP takes over
# finish_step runs at every filter step: module-level names instead of attribute lookups
_STEP_SOLVED, _STEP_RELAXED, _STEP_RELAXED_AS_IS = _kernels.STEP_SOLVED, _kernels.STEP_RELAXED, _kernels.STEP_RELAXED_AS_IS
_perf_counter = time.perf_counter


def _raise_bad_data(code: int) -> None:
    """The data step's verdict on non-finite input (:func:`c3bf_gym._kernels.qp_prepare`)."""
    if code == _kernels.STEP_BAD_NOMINAL:
        raise ValueError("tau_nom contains NaN or inf")
    if code == _kernels.STEP_BAD_ROWS:
        raise ValueError("A or b contains NaN or inf (or entries beyond ~1e150)")


class QPResult(NamedTuple):
    """Result of :meth:`TorqueQP.solve`.

    Attributes:
        tau: (n,) torque [N·m].  A *view into an internal buffer of the layer*:
            it is overwritten by the next ``solve`` call; copy it to keep it.
            Always inside [tau_min, tau_max] exactly (clipped after the solve).
        slack: 0.0 when the hard problem was solved; otherwise the largest
            row-normalised violation max_k (b_k − A_k τ)/‖A_k‖ of ``tau`` [N·m].
        feasible: True iff the hard (unrelaxed) problem was solved to tolerance.
        status: ``"solved"``, ``"relaxed"`` (rows and box cannot all hold, or
            optimality of the hard problem could not be certified; slack used)
            or ``"failed"`` (even the elastic problem did not converge).
        iterations: active-set steps (one per row added or dropped, plus one for re-using the
            previous call's active rows) plus the proxsuite iterations of this call; 0 on the
            fast path.
        active_rows: number of rows k < m with (A_k τ − b_k)/‖A_k‖ ≤ ``active_tol``.
        solve_time: wall time of the ``solve()`` call [s].
    """

    tau: np.ndarray
    slack: float
    feasible: bool
    status: str
    iterations: int
    active_rows: int
    solve_time: float


# ----------------------------------------------------------------------------- validation


def _weight_matrix(W, n: int) -> np.ndarray:
    """Return W as a new (n, n) SPD float64 matrix; None → identity, (n,) → diag."""
    if W is None:
        return np.eye(n)
    Wa = np.asarray(W, dtype=np.float64)
    if Wa.shape == (n,):
        if not np.all(np.isfinite(Wa)) or not np.all(Wa > 0):
            raise ValueError("W as a diagonal must be (n,) finite and strictly positive")
        return np.diag(Wa)
    if Wa.shape != (n, n):
        raise ValueError(f"W must be None, an ({n},) positive diagonal or an ({n}, {n}) SPD matrix; got shape {Wa.shape}")
    if not np.all(np.isfinite(Wa)):
        raise ValueError("W must be finite")
    if not np.allclose(Wa, Wa.T, rtol=1e-10, atol=1e-12 * max(1.0, float(np.abs(Wa).max()))):
        raise ValueError("W must be symmetric positive definite (it is not symmetric)")
    try:
        np.linalg.cholesky(Wa)
    except np.linalg.LinAlgError:
        raise ValueError("W must be symmetric positive definite (Cholesky failed)") from None
    return np.array(0.5 * (Wa + Wa.T))


def _box(tau_min, tau_max, n: int) -> tuple[np.ndarray, np.ndarray]:
    lo = np.array(tau_min, dtype=np.float64).reshape(-1) if np.ndim(tau_min) else np.full(n, float(tau_min))
    hi = np.array(tau_max, dtype=np.float64).reshape(-1) if np.ndim(tau_max) else np.full(n, float(tau_max))
    if lo.shape != (n,) or hi.shape != (n,):
        raise ValueError(f"tau_min and tau_max must be scalars or shape ({n},); got {lo.shape}, {hi.shape}")
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ValueError("tau_min and tau_max must be finite")
    if not np.all(lo < hi):
        raise ValueError("tau_min must be strictly less than tau_max elementwise")
    return lo, hi


# ----------------------------------------------------------------------------- layer


def _plain(x: np.ndarray) -> np.ndarray:
    """``x`` as a C-contiguous, writeable float64 array (one type for the compiled kernels)."""
    if x.flags.c_contiguous and x.flags.writeable:
        return x
    return np.array(x, order="C")


def _step_buffer_shapes(n: int, M: int, K: int) -> list[tuple[str, tuple[int, ...], type]]:
    """``(attribute, shape, dtype)`` of :class:`TorqueQP`'s buffers of the compiled step, in
    :func:`c3bf_gym._kernels.qp_step`'s order (n joints, M rows, K repair slack columns); the
    kernel's :func:`~c3bf_gym._kernels.step_views` carves them in this order."""
    f, i = np.float64, np.int64
    as_w, as_i = _active_set.work_shapes(n, M + 2 * n)
    el_w, el_i = _active_set.work_shapes(n + 1, M + 2 * n + 1)
    rep_w, rep_i = _active_set.work_shapes(n + K, M + 2 * n + K)
    return [
        ("_Gx", (M + 2 * n + 1, n + 1), f), ("_hx", (M + 2 * n + 1,), f), ("_hcx", (M + 2 * n + 1,), f),
        ("_nrm", (M,), f), ("_r", (M + 2 * n,), f), ("_xe", (n + 1,), f), ("_nom", (n,), f), ("tau_min", (n,), f),
        ("tau_max", (n,), f), ("_reach", (M,), f), ("_negW", (n, n), f), ("_g", (n + 1,), f), ("_qp_f", (6,), f),
        ("_WJ", (2 * n, n), f), ("_as_work", as_w, f), ("_as_iwork", as_i, i), ("_x0r", (n + K,), f),
        ("_WJx", (2 * (n + K), n + K), f), ("_el_work", el_w, f), ("_el_iwork", el_i, i), ("_Kr", (K,), i),
        ("_Gr", (M + 2 * n + K, n + K), f), ("_hr", (M + 2 * n + K,), f), ("_rep_work", rep_w, f),
        ("_rep_iwork", rep_i, i), ("_WJp", (2 * n, n), f), ("_x0p", (n,), f), ("_hp", (M + 2 * n,), f),
        ("_pflag", (M,), i), ("_pw_work", as_w, f), ("_pw_iwork", as_i, i), ("_rep_stats", (3,), i),
    ]  # fmt: skip


class _StepArena:
    """Zeroed buffers of the given ``(attribute, shape, dtype)`` back to back in one float64 and one
    int64 array (``floats``, ``ints``), set as attributes of ``owner``; ``views`` in that order and
    ``layout`` (len, 3) int64 rows ``(offset into their array, shape[0], shape[1] or 0)``."""

    def __init__(self, owner, shapes: list[tuple[str, tuple[int, ...], type]]) -> None:
        sizes = [math.prod(shape) for _, shape, _ in shapes]
        ints = [dtype is np.int64 for _, _, dtype in shapes]
        self.floats = np.zeros(sum(k for k, is_int in zip(sizes, ints) if not is_int))
        self.ints = np.zeros(sum(k for k, is_int in zip(sizes, ints) if is_int), dtype=np.int64)
        self.layout = np.zeros((len(shapes), 3), dtype=np.int64)
        offsets = {False: 0, True: 0}
        views = []
        for row, ((name, shape, _), k, is_int) in enumerate(zip(shapes, sizes, ints)):
            start = offsets[is_int]
            view = (self.ints if is_int else self.floats)[start:start + k].reshape(shape)
            self.layout[row] = start, shape[0], shape[1] if len(shape) > 1 else 0
            offsets[is_int] = start + k
            setattr(owner, name, view)
            views.append(view)
        self.views = tuple(views)


def _make_qp(nvar: int, nrows: int, eps_abs: float, max_iter: int, max_iter_in: int | None = None):
    qp = _pq.dense.QP(nvar, 0, nrows, True, _pq.dense.HessianType.Dense, _pq.dense.DenseBackend.PrimalDualLDLT)
    s = qp.settings
    s.eps_abs = eps_abs
    s.eps_rel = 0.0
    s.max_iter = max_iter  # outer (proximal) iterations; each runs up to max_iter_in inner ones
    if max_iter_in is not None:
        s.max_iter_in = max_iter_in
    s.verbose = False
    s.initial_guess = _pq.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT
    return qp


class TorqueQP:
    """Preallocated, warm-started torque safety-filter QP (see module docstring).

    Args:
        n: number of joints (≥ 1).
        max_rows: maximum number of safety rows per call (≥ 0).
        tau_min, tau_max: scalars or (n,) finite actuator limits [N·m], tau_min < tau_max.
        W: None (identity), (n,) positive diagonal or (n, n) SPD weight.
        slack_weight: ρ > 0 of the elastic cost c s + ½ ρ s² (c = √ρ, s in normalised units).
        eps_abs: proxsuite absolute tolerance (> 0), on row-normalised data.
        max_iter: proxsuite's outer-iteration cap (≥ 1) of the elastic solve.
        solver: ``"active_set"`` (default: the compiled active-set solver first, proxsuite
            for what it hands over) or ``"proxsuite"`` (proxsuite only, the earlier behaviour).

    Attributes:
        active_tol: threshold [N·m, normalised] for counting ``active_rows`` and
            for deciding s ≈ 0; max(1e-6, 100·eps_abs).
        hard_max_iter, hard_max_iter_in: outer and inner iteration caps of the (rare)
            disambiguating hard solve.
        active_set_max_iter: step cap of the active-set solver (50), plus 2 per slack for the
            per-row repair: a repair with many slack rows (about 50, at 8 obstacles) can reach
            it and is then handed to proxsuite (``benchmarks/filter_speed.py`` counts these).
        active_set_fallbacks, active_set_troubles: QPs (hard or elastic, repair) the active-set
            solver handed to proxsuite, and its solves that ended in a step cap or failed check
            (the same count, since infeasible calls no longer go to proxsuite).
    """

    def __init__(self, n: int, max_rows: int, tau_min, tau_max, W=None,
                 slack_weight: float = 1e6, eps_abs: float = 1e-8, max_iter: int = 100,
                 row_slack_weight: float = 1e2, solver: str = "active_set"):
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise ValueError(f"n must be an integer >= 1; got {n!r}")
        if isinstance(max_rows, bool) or not isinstance(max_rows, (int, np.integer)) or max_rows < 0:
            raise ValueError(f"max_rows must be an integer >= 0; got {max_rows!r}")
        if not (math.isfinite(slack_weight) and slack_weight > 0):
            raise ValueError(f"slack_weight must be finite and > 0; got {slack_weight!r}")
        if not (math.isfinite(row_slack_weight) and row_slack_weight > 0):
            raise ValueError(f"row_slack_weight must be finite and > 0; got {row_slack_weight!r}")
        if not (math.isfinite(eps_abs) and eps_abs > 0):
            raise ValueError(f"eps_abs must be finite and > 0; got {eps_abs!r}")
        if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 1:
            raise ValueError(f"max_iter must be an integer >= 1; got {max_iter!r}")
        if solver not in SOLVERS:
            raise ValueError(f"solver must be one of {', '.join(map(repr, SOLVERS))}; got {solver!r}")
        n, M = int(n), int(max_rows)
        self.n, self.max_rows = n, M
        lo, hi = _box(tau_min, tau_max, n)
        self.slack_weight = float(slack_weight)
        self.eps_abs = float(eps_abs)
        self.max_iter = int(max_iter)
        self.solver = solver
        self.active_tol = max(1e-6, 100.0 * self.eps_abs)
        # The hard solve only disambiguates (elastic slack > 0 but infeasibility not certified):
        # when the hard problem is in fact infeasible proxsuite runs it to its caps, so they are
        # tight (≤ 10 x 20 inner iterations, ~2 ms); unconverged means "relaxed", i.e. the elastic
        # (least-violating) torque is applied and reported. Uncapped, it cost up to 1 s per call.
        self.hard_max_iter = min(self.max_iter, 10)
        self.hard_max_iter_in = 20

        # --- preallocated buffers (the hot path writes only into these). Those of the compiled
        # step (step_buffers) lie back to back in one float64 and one int64 array (_step_arena).
        K = max(M, 1)  # slack columns of the per-row repair (below)
        self._step_arena = _StepArena(self, _step_buffer_shapes(n, M, K))
        self.tau_min[:], self.tau_max[:] = lo, hi
        # G stacks the elastic rows and the box as rows so that ONE mat-vec gives every
        # residual:  rows [0, M): (Â_k | 1/σ), padded rows (0 | 1/σ) with h = -inf;
        # rows [M, M+n): (I | 0) with h = τ_min;  rows [M+n, M+2n): (−I | 0) with h = −τ_max.
        # G[:M] / h[:M] are contiguous row blocks and are handed to proxsuite as C / l.
        self._sigma = math.sqrt(self.slack_weight)    # slack scaling: QP variable t = σ s
        self.slack_linear_weight = math.sqrt(self.slack_weight)
        # (The elastic active-set solve uses one more row, t ≥ 0: _Gx / _hx, of which _G / _h are
        # the leading rows.)
        self._Gx[M + 2 * n, n] = 1.0
        self._G = self._Gx[:M + 2 * n]
        self._G[:M, n] = 1.0 / self._sigma
        self._G[M:M + n, :n] = np.eye(n)
        self._G[M + n:, :n] = -np.eye(n)
        # _nrm: the row norms ‖A_k‖
        self._hx.fill(-PROXSUITE_INF)
        self._hx[M + 2 * n] = 0.0
        self._h = self._hx[:M + 2 * n]
        self._h[M:M + n] = self.tau_min
        self._h[M + n:] = -self.tau_max
        self._Ce, self._l = self._G[:M], self._h[:M]
        self._hcx[:] = self._hx          # _hx with impossible rows clipped to their reach (_l_clipped)
        self._l_clipped = self._hcx[:M]
        self._u = np.full(M, PROXSUITE_INF)
        # _r: the residuals G·(τ, 0) − h; _xe: (τ, 0), whose τ part is the returned buffer; _nom: the
        # nominal (in u with solve_scaled); _reach: max over the box of each normalised row
        self._tau = self._xe[:n]
        self._H = np.zeros((n + 1, n + 1))            # elastic Hessian blockdiag(W, 1) (ρ s² = t²)
        self._H[n, n] = 1.0
        self._Wc = np.zeros((n, n))                   # W, contiguous (hard QP); _negW: −W (g = −W τ_nom)
        self._g[n] = self.slack_linear_weight / self._sigma  # _g: the elastic gradient (−W τ_nom, c/σ)
        self._Ch = np.zeros((M, n))                   # Â for the rare hard solve
        self._y = np.zeros(M)
        self._lbox = np.concatenate([self.tau_min, [0.0]])
        self._ubox = np.concatenate([self.tau_max, [PROXSUITE_INF]])
        self._m_prev = 0
        self._m_prev_hard = 0
        self._diag_W = True
        self._hard_h_dirty = False

        # The per-row repair of relaxed solves (_relax_rows): one QP per slack-count bucket.
        self.row_slack_weight = float(row_slack_weight)
        self.relax_max_iter, self.relax_max_iter_in = 200, 100  # outer, inner caps (≈ 25 typical)
        self._relax_caps = sorted({min(M, c) for c in (8, 16, 32, 64)} | {M}) if M else []
        self._relax: dict = {}
        self._relax_H: dict = {}
        self._relax_lo: dict = {}
        self._relax_hi: dict = {}
        self._relax_dirty: dict = {}
        self._relax_K: dict = {}  # the violated rows of the last repair per bucket
        #: counters: cold retries after a failed or wrongly signed warm start, per-row repairs,
        #: repairs that fell back to the min-max torque, and feasible results whose optimality
        #: neither the elastic nor the hard solve could confirm.
        self.retries = self.relax_calls = self.relax_fallbacks = self.suboptimal = 0

        # The active-set solver (module docstring, "Active-set solver first"): its work arrays
        # (_as_work, _as_iwork), the weight data [W; L⁻ᵀ] (_WJ, set_weight), its tolerances and step cap.
        self._as_x = self._as_work[2 * n, :n]
        # ... and for the elastic and per-row repair problems ("Infeasible calls"): x₀ = (τ_nom, −1, …)
        # (_x0r) and [W̃; J₀] (_WJx) for up to n + K variables (K = max_rows slack columns; each solve
        # uses the leading blocks); work arrays _el_work / _el_iwork and _rep_work / _rep_iwork; the
        # repair rows (Â_k | e_i / σ_k) in _Gr / _hr, then the box rows and the K rows t_i ≥ 0.
        self._x0r.fill(-1.0)
        self._el_x = self._el_work[2 * (n + 1), :n + 1]
        self._Gr[M:M + 2 * n, :n] = self._G[M:, :n]
        self._Gr[M + 2 * n:, n:] = np.eye(K)
        self._hr[M:M + 2 * n] = self._h[M:]
        self._kr = 0  # _Kr[:_kr]: the repair's slack rows
        self._rep_x = self._rep_work[2 * (n + K), :n]
        self._tau_star = np.zeros(n)
        box_scale = 1.0 + float(max(np.abs(self.tau_min).max(), np.abs(self.tau_max).max()))
        self._as_tol, self._as_vtol = _AS_TOL * box_scale, _AS_VTOL * box_scale
        self._qp_f[:] = _ROW_NORM_MIN, PROXSUITE_INF, self._as_tol, self._as_vtol, self._sigma, _REPAIR_ROUNDS
        self.active_set_max_iter = 50
        self.active_set_fallbacks = self.active_set_troubles = 0

        # The elastic QP comes in row-count sizes (one proxsuite QP per size, made on first use, each
        # warm-started from its own last result): proxsuite's cost grows with its row count, padding
        # rows included (a 31-row problem took ~25% less time in a 32-row QP than in an 80-row one).
        # A size change comes with a change of rows anyway (the rows of one obstacle appear or go),
        # after which the previous result was no useful warm start for the old size either.
        self._el_sizes = sorted({min(M, c) for c in (16, 32, 48, 64, 96, 128, 192, 256)} | {M})
        self._el_qps: dict = {}
        self._el_dirty: set = set()
        self._hard = _make_qp(n, M, self.eps_abs, self.hard_max_iter, self.hard_max_iter_in)
        self.set_weight(W)
        self._elastic(M)
        self._hard.init(self._Wc, self._g[:n], None, None, self._Ch, self._l, self._u,
                        self.tau_min, self.tau_max)
        self._hard_h_dirty = False
        if solver == "active_set":  # load the compiled solver now, not in a control loop's first binding call (~20 ms)
            _kernels.qp_step(np.zeros(n), np.zeros((0, n)), _NO_SCALE, _NO_SCALE, _NO_SCALE, 0, 0, 1, self.active_tol,
                             self.row_slack_weight, self._diag_W, *self.step_buffers())

    # ------------------------------------------------------------------ weight
    def set_weight(self, W) -> None:
        """Set W: None (identity), (n,) positive diagonal or (n, n) SPD matrix.

        The Hessians are pushed to proxsuite (with a preconditioner refresh) on the next solve.
        """
        Wm = _weight_matrix(W, self.n)
        self._H[:self.n, :self.n] = Wm
        self._Wc[...] = Wm
        np.negative(Wm, out=self._negW)
        self._WJ[...] = _active_set.weight_data(Wm)
        self._WJx[...] = _active_set.weight_data(Wm, self._WJx.shape[1] - self.n)
        self._diag_W = bool(np.count_nonzero(Wm - np.diag(np.diag(Wm))) == 0)
        self._el_dirty = set(getattr(self, "_el_qps", ()))
        self._hard_h_dirty = True
        for cap, H in getattr(self, "_relax_H", {}).items():
            H[:self.n, :self.n] = Wm
            self._relax_dirty[cap] = True

    @property
    def repair_rounds(self) -> int:
        """How many guesses of its soft rows the per-row repair gets in τ alone (module docstring,
        "Relaxation") before the QP in (τ, t_K) solves it; 0: that QP every time. Same optimum
        either way; ``benchmarks/filter_speed.py --qp-solver active_set slack_repair`` compares their
        cost."""
        return int(self._qp_f[5])

    @repair_rounds.setter
    def repair_rounds(self, rounds: int) -> None:
        if isinstance(rounds, bool) or not isinstance(rounds, (int, np.integer)) or rounds < 0:
            raise ValueError(f"repair_rounds must be an integer >= 0; got {rounds!r}")
        self._qp_f[5] = rounds

    @property
    def repair_stats(self) -> dict[str, int]:
        """Per-row repairs since construction: ``settled`` in τ alone, their summed ``rounds``,
        and ``slack_qp``: those left to the QP in (τ, t_K) (not counted when ``repair_rounds`` is 0)."""
        settled, rounds, slack_qp = (int(v) for v in self._rep_stats)
        return {"settled": settled, "rounds": rounds, "slack_qp": slack_qp}

    # ------------------------------------------------------------------ solve
    def solve(self, tau_nom, A, b, weights=None) -> QPResult:
        """Filter one nominal torque.

        Args:
            tau_nom: (n,) nominal torque [N·m], finite.
            A: (m, n) safety rows, finite, m ≤ max_rows (m = 0 allowed).
            b: (m,) right-hand side, finite;  rows mean A τ ≥ b.
            weights: None (all 1) or (m,) finite relaxation weights > 0: how much a unit of
                violation of row k costs relative to one of a weight-1 row when no torque
                satisfies every row (the per-row repair, module docstring). Unused otherwise.

        Returns:
            :class:`QPResult`; ``tau`` is a view of an internal buffer.

        Raises:
            ValueError: wrong shapes, m > max_rows, or non-finite input.
        """
        t0 = time.perf_counter()
        n, M = self.n, self.max_rows
        tau_nom = np.asarray(tau_nom, dtype=np.float64)
        A = np.asarray(A, dtype=np.float64)
        b = np.asarray(b, dtype=np.float64)
        if tau_nom.shape != (n,):
            raise ValueError(f"tau_nom must have shape ({n},); got {tau_nom.shape}")
        if A.ndim != 2 or A.shape[1] != n:
            raise ValueError(f"A must have shape (m, {n}); got {A.shape}")
        m = A.shape[0]
        if b.shape != (m,):
            raise ValueError(f"b must have shape ({m},) to match A; got {b.shape}")
        if m > M:
            raise ValueError(f"too many rows: m={m} > max_rows={M}")
        if weights is not None:
            if np.shape(weights) != (m,):
                raise ValueError(f"weights must have shape ({m},) to match A; got {np.shape(weights)}")
            w = np.asarray(weights, dtype=np.float64)
            if not (np.all(np.isfinite(w)) and np.all(w > 0)):
                raise ValueError(f"weights must be finite and > 0; got {w}")
        return self._solve(t0, _plain(tau_nom), _plain(A), _plain(b), weights, _NO_SCALE)

    def solve_scaled(self, tau_nom, A, b, scale, weights=None) -> QPResult:
        """:meth:`solve` in the normalised torque ``u = τ / scale``, for a caller that owns ``A``.

        Solves :meth:`solve`'s problem for ``(τ_nom / scale, A diag(scale), b)``: the weight and
        box given to the constructor are in ``u``. ``A`` ((m, n) C-contiguous float64, m ≤
        ``max_rows``) is scaled **in place** (``A *= scale``); ``tau_nom``, ``b``, ``scale`` are
        contiguous float64 of shapes (n,), (m,), (n,). Shapes are not checked (NaN and inf in the
        data still raise ValueError). The result's ``tau`` is ``u``. ``weights``: :meth:`solve`'s
        (not checked here either). (The safety filter's call.)
        """
        return self._solve(time.perf_counter(), tau_nom, A, b, weights, scale)

    def _solve(self, t0, tau_nom, A, b, weights, scale) -> QPResult:
        m = A.shape[0]
        if self.solver == "active_set":  # one compiled call (module docstring), Python for hand-overs
            w = _NO_SCALE if weights is None else _plain(np.asarray(weights, dtype=np.float64))
            status, steps, k, active, slack = _kernels.qp_step(
                tau_nom, A, b, scale, w, self._m_prev, self._kr, self.active_set_max_iter, self.active_tol,
                self.row_slack_weight, self._diag_W, *self.step_buffers())
            return self.finish_step(status, m, steps, k, active, slack, weights, t0)

        # ---- data step (compiled): finiteness, row normalisation into G / h (padding the rows left
        # over from the previous call), the fast-path residuals and, when they fail, the reach check
        # and the elastic gradient g = (−W τ_nom, c/σ). A sum of squares is finite iff every entry
        # is finite and below ~1e150 in magnitude (so the row norms cannot overflow).
        code, rmin, impossible = _kernels.qp_prepare(
            tau_nom, A, b, scale, self._G, self._h, self._nrm, self._r, self._xe, self._nom, self._m_prev,
            _ROW_NORM_MIN, PROXSUITE_INF, self.tau_min, self.tau_max, self.active_tol, self._l, self._l_clipped,
            self._reach, self._negW, self._g)
        _raise_bad_data(code)
        self._m_prev = m

        # ---- fast path: τ_nom inside the box and satisfying every row ⇒ it is the optimum
        if rmin >= 0.0:
            return self._result(m, 0.0, True, "solved", 0, t0, residuals_ready=True)
        if m == 0 and self._diag_W:                 # W-metric box projection of a diagonal W = clip
            self._clip(self._nom)
            return self._result(0, 0.0, True, "solved", 0, t0)

        # ---- rows no torque in the box can satisfy: max_{τ∈box} Â_k τ = Σ_j max(Â_kj lo_j, Â_kj hi_j).
        # Their violation is certain; proxsuite sees them clipped to that reach, which keeps the
        # elastic problem well scaled (rows asking for 1e4 times more than the motors can give
        # otherwise cost proxsuite 1e5-1e6 iterations) without changing where the least-violating
        # torque lies. The slack is still measured against the original rows. (The data step
        # found them and wrote every row's bound, clipped to its reach, into _l_clipped.)
        return self._proxsuite_elastic(m, weights, impossible, 0, t0)

    def step_buffers(self) -> tuple:
        """The buffers and constants :func:`c3bf_gym._kernels.qp_step` works in, in its order
        (allocated once by the constructor, updated in place; the solver tolerances and the slack
        scaling are fixed by it)."""
        return self._step_arena.views

    def packed_step_buffers(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`step_buffers` as ``(float64 arena, int64 arena, layout)``, which
        :func:`c3bf_gym._kernels.step_views` turns back into them inside a compiled kernel: three
        arguments instead of 32 (numba converts every array argument on every call)."""
        arena = self._step_arena
        return arena.floats, arena.ints, arena.layout

    def finish_step(self, status, m, steps, k, active, slack, weights, t0) -> QPResult:
        """The result of a :func:`c3bf_gym._kernels.qp_step` call (also run inside the filter's fused
        kernel): raise on bad data, keep the warm-start state, and run proxsuite where it handed over."""
        if status < 0:
            _raise_bad_data(status)
        self._m_prev, self._kr = m, k
        if status <= _STEP_RELAXED_AS_IS:  # done in the kernel (the common case: kept short)
            solved = status == _STEP_SOLVED
            if not solved:
                self.relax_calls += status == _STEP_RELAXED
            return QPResult(self._tau, slack, solved, "solved" if solved else "relaxed", steps, active,
                            _perf_counter() - t0)
        impossible = status in (_kernels.STEP_TO_ELASTIC_IMPOSSIBLE, _kernels.STEP_TO_REPAIR_IMPOSSIBLE)
        if status >= _kernels.STEP_TO_REPAIR:  # residuals of τ* are in _r
            if m:
                self.active_set_fallbacks += 1
                self.active_set_troubles += 1
            return self._proxsuite_repair(m, weights, self._l_clipped if impossible else self._l, self._nom, steps, t0)
        self.active_set_fallbacks += 1
        self.active_set_troubles += 1
        return self._proxsuite_elastic(m, weights, impossible, steps, t0)

    def _proxsuite_elastic(self, m, weights, impossible, iters, t0) -> QPResult:
        """The elastic QP by proxsuite and the decisions after it (module docstring): the layer
        with ``solver="proxsuite"``, or what the active-set solver handed over (``iters`` steps)."""
        n = self.n
        tau_nom = self._nom
        l = self._l_clipped if impossible else self._l
        g = self._g
        size = next(s for s in self._el_sizes if s >= m)
        el, C, l_all, l_clip = self._elastic(size)
        l_size = l_clip if impossible else l_all  # the first `size` rows of l
        if size in self._el_dirty:
            el.update(H=self._H, g=g, C=C, l=l_size, update_preconditioner=True, mu_in=_MU_IN_RESET)
            self._el_dirty.discard(size)
        else:
            el.update(g=g, C=C, l=l_size, mu_in=_MU_IN_RESET)
        el.solve()
        info = el.results.info
        iters += int(info.iter)
        # A bad warm start can stall proxsuite, or end "solved" at a point whose multipliers
        # have the wrong sign (not optimal: see "Dual sign check"): retry once from scratch.
        suspect = False
        if info.status != _SOLVED or not self._dual_signs_ok(el, m, self._lbox, self._ubox):
            el.settings.initial_guess = _pq.InitialGuess.NO_INITIAL_GUESS
            el.solve()
            info = el.results.info
            iters += int(info.iter)
            self.retries += 1
            # still a wrongly signed stop (rare): the hard QP below decides instead
            suspect = info.status == _SOLVED and not self._dual_signs_ok(el, m, self._lbox, self._ubox)
            el.settings.initial_guess = _pq.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT
        x = el.results.x
        if info.status != _SOLVED:
            self._clip(x[:n] if np.isfinite(x.sum()) else tau_nom)
            return self._result(m, None, False, "failed", iters, t0)
        self._clip(x[:n])
        if impossible:
            return self._relax_rows(m, weights, l, tau_nom, iters, t0)
        tol = self.active_tol
        feasible_el = float(x[n]) / self._sigma <= tol
        if feasible_el and not suspect:
            return self._result(m, 0.0, True, "solved", iters, t0)

        # ---- s > 0: certify infeasibility with the Farkas bound from the row multipliers
        if not feasible_el and self._infeasibility_bound(m, el.results.z) > tol:
            return self._relax_rows(m, weights, l, tau_nom, iters, t0)

        # ---- not certified (hard multipliers beyond c in l1): solve the hard problem
        hard = self._hard
        np.copyto(self._Ch[:m], self._G[:m, :n])
        if self._m_prev_hard > m:
            self._Ch[m:self._m_prev_hard] = 0.0
        self._m_prev_hard = m
        if self._hard_h_dirty:
            hard.update(H=self._Wc, g=g[:n], C=self._Ch, l=self._l, update_preconditioner=True,
                        mu_in=_MU_IN_RESET)
            self._hard_h_dirty = False
        else:
            hard.update(g=g[:n], C=self._Ch, l=self._l, mu_in=_MU_IN_RESET)
        hard.solve()
        iters += int(hard.results.info.iter)
        if hard.results.info.status == _SOLVED and self._dual_signs_ok(hard, m, self.tau_min, self.tau_max):
            self._clip(hard.results.x)
            return self._result(m, 0.0, True, "solved", iters, t0)
        if feasible_el:  # the elastic τ satisfies every row: feasible, possibly not optimal
            self.suboptimal += 1
            return self._result(m, 0.0, True, "solved", iters, t0)
        return self._relax_rows(m, weights, l, tau_nom, iters, t0)

    # ------------------------------------------------------------------ relaxed: per-row repair
    def _relax_rows(self, m, weights, l, tau_nom, iters, t0) -> QPResult:
        """No torque satisfies every row: repair the elastic (min-max) torque τ* row by row.

        Rows τ* satisfies (normalised residual ≥ ``active_tol``) stay hard; every other row k
        gets its own slack s_k, costed σ_k s_k + ½ σ_k² s_k² with σ_k = ``row_slack_weight`` ·
        weights[k] (module docstring, "Relaxation"). τ* with its violations is a feasible point of
        this QP, so it always has a solution. The active-set solver tries first (``solver=
        "active_set"``, :func:`c3bf_gym._kernels.repair_step`); if neither it nor proxsuite
        delivers it, τ* is applied.
        """
        if self.solver == "active_set" and m:
            w = _NO_SCALE if weights is None else _plain(np.asarray(weights, dtype=np.float64))
            code, steps, self._kr = _kernels.repair_step(
                self._G, self._xe, self._h, self._r, m, self.active_tol, l, w, self.row_slack_weight, self._Kr,
                self._kr, self._Gr, self._hr, self._rep_iwork, self._x0r, tau_nom, self._WJx, self._as_tol,
                self._as_vtol, self.active_set_max_iter, self._rep_work, self.tau_min, self.tau_max, self._tau,
                self._WJ[:self.n], self._WJp, self._x0p, self._hp, self._pflag, self._pw_work, self._pw_iwork,
                self.repair_rounds, self._rep_stats)
            iters += steps
            if code != 2:
                self.relax_calls += code == 0
                return self._result(m, None, False, "relaxed", iters, t0)
            self.active_set_fallbacks += 1
            self.active_set_troubles += 1
        else:
            _kernels.residuals(self._G, self._xe, self._h, self._r)  # of τ* (original, unclipped rows)
        return self._proxsuite_repair(m, weights, l, tau_nom, iters, t0)

    def _proxsuite_repair(self, m, weights, l, tau_nom, iters, t0) -> QPResult:
        """:meth:`_relax_rows` by proxsuite, from τ* in the result buffer and its residuals in
        ``_r``; τ* itself if that fails too."""
        n, M = self.n, self.max_rows
        r = self._r
        tau_star = self._tau_star
        np.copyto(tau_star, self._tau)
        K = np.flatnonzero(r[:m] < self.active_tol)
        k = len(K)
        cap = next((c for c in self._relax_caps if c >= k), None)
        if k == 0 or cap is None:
            return self._result(m, None, False, "relaxed", iters, t0)
        qp, C, g = self._relax_qp(cap)
        C[:, :n] = self._G[:M, :n]
        C[:, n:] = 0.0
        w = np.ones(k) if weights is None else np.asarray(weights, dtype=np.float64)[K]
        C[K, n + np.arange(k)] = 1.0 / (self.row_slack_weight * w)
        np.dot(self._negW, tau_nom, out=g[:n])
        H = self._relax_H[cap] if self._relax_dirty.pop(cap, False) else None
        qp.update(H=H, g=g, C=C, l=l, update_preconditioner=False, mu_in=_MU_IN_RESET)
        # relaxed calls come in stretches with the same violated rows: then the previous repair
        # is a good warm start (same variables); otherwise start from scratch.
        same = self._relax_K.get(cap)
        same = same is not None and len(same) == k and bool(np.array_equal(same, K))
        qp.settings.initial_guess = (_pq.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT if same
                                     else _pq.InitialGuess.NO_INITIAL_GUESS)
        qp.solve()
        res = qp.results
        iters += int(res.info.iter)
        ok = res.info.status == _SOLVED and self._dual_signs_ok(qp, m, self._relax_lo[cap], self._relax_hi[cap])
        if not ok and same:
            qp.settings.initial_guess = _pq.InitialGuess.NO_INITIAL_GUESS
            qp.solve()
            iters += int(res.info.iter)
            ok = res.info.status == _SOLVED and self._dual_signs_ok(qp, m, self._relax_lo[cap], self._relax_hi[cap])
        self._relax_K[cap] = K
        self.relax_calls += 1
        if ok:
            self._clip(res.x[:n])
        else:
            self.relax_fallbacks += 1
            self._tau[:] = tau_star
        return self._result(m, None, False, "relaxed", iters, t0)

    def _elastic(self, size):
        """``(qp, C, l, l_clipped)``: the elastic proxsuite QP with ``size`` rows (made and
        initialised on first use) and the first ``size`` rows of its data buffers."""
        if size not in self._el_qps:
            n = self.n
            qp = _make_qp(n + 1, size, self.eps_abs, self.max_iter)
            # initialised (and its preconditioner computed) from the same data whatever the rows
            # are at first use: padding rows (0 | 1/σ) with l = −inf, and g = (0, c/σ)
            C0 = np.zeros((size, n + 1))
            C0[:, n] = 1.0 / self._sigma
            g0 = np.zeros(n + 1)
            g0[n] = self.slack_linear_weight / self._sigma
            qp.init(self._H, g0, None, None, C0, np.full(size, -PROXSUITE_INF), self._u[:size], self._lbox,
                    self._ubox)
            self._el_qps[size] = (qp, self._G[:size], self._h[:size], self._l_clipped[:size])
        return self._el_qps[size]

    def _relax_qp(self, cap):
        """The proxsuite QP of the per-row repair with ``cap`` slack variables (built on first use)."""
        if cap not in self._relax:
            n, M = self.n, self.max_rows
            H = np.eye(n + cap)
            H[:n, :n] = self._Wc
            g = np.ones(n + cap)                      # (−W τ_nom, 1): cost ½ t² + t per slack
            C = np.zeros((M, n + cap))
            lo = np.concatenate([self.tau_min, np.zeros(cap)])
            hi = np.concatenate([self.tau_max, np.full(cap, PROXSUITE_INF)])
            qp = _make_qp(n + cap, M, self.eps_abs, self.relax_max_iter, self.relax_max_iter_in)
            qp.settings.initial_guess = _pq.InitialGuess.NO_INITIAL_GUESS
            qp.init(H, g, None, None, C, self._l, self._u, lo, hi)
            self._relax[cap] = (qp, C, g)
            self._relax_H[cap], self._relax_lo[cap], self._relax_hi[cap] = H, lo, hi
            self._relax_dirty[cap] = False
        return self._relax[cap]

    def _dual_signs_ok(self, qp, m, lo, hi) -> bool:
        """Are the multipliers of proxsuite's "solved" point of the right sign?

        Every row is a lower bound (its upper bound is infinite), so its multiplier must be
        ≤ 0 (proxsuite's sign convention); a box multiplier may be > 0 only nearer the upper
        bound and < 0 only nearer the lower one. proxsuite's stopping test (primal and dual
        residuals) does not check this, and after a warm start it can stop at such a point:
        feasible, but not the optimum (module docstring, "Dual sign check").
        """
        res = qp.results
        return _kernels.dual_signs_ok(res.z, res.x, m, lo, hi, _DUAL_SIGN_TOL)

    # ------------------------------------------------------------------ helpers
    def _clip(self, x) -> None:
        """``self._tau = clip(x, τ_min, τ_max)``."""
        _kernels.clip(x, self.tau_min, self.tau_max, self._tau)

    def _result(self, m, slack, feasible, status, iters, t0, residuals_ready=False) -> QPResult:
        """Pack a QPResult for the τ in the buffer; slack=None → recompute max row violation."""
        active, violation = _kernels.result_stats(self._G, self._xe, self._h, self._r, m, self.active_tol,
                                                  not residuals_ready)
        if slack is None:
            slack = violation
        return QPResult(self._tau, float(slack), feasible, status, iters, active, time.perf_counter() - t0)

    def _infeasibility_bound(self, m: int, z) -> float:
        """Farkas lower bound on min_{τ∈box} max_k (b̂_k − Â_k τ) from row multipliers z[:m].

        proxsuite's multiplier of an active *lower* bound is negative, so y = max(−z, 0).
        """
        if m == 0:
            return -math.inf
        return _kernels.infeasibility_bound(z, self._G, self._h, m, self.tau_min, self.tau_max, self._y)
