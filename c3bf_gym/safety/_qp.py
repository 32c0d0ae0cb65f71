"""The filter's QP in compiled (numba) code: the torque closest to the nominal one that keeps every
safety row, by priority (:func:`solve_rows`), on DAQP through its binding :mod:`c3bf_gym.safety._daqp`.

In the scaled torque ``u = τ / s`` (``s`` the controller's scale, so the box is
``u_min ≤ u ≤ u_max``)::

    minimise    ½ (u − u_nom)ᵀ H (u − u_nom),   H = I + KᵀK
    subject to  u_min ≤ u ≤ u_max            (the torque limits: always hard)
                â_k u ≥ b̂_k,  k = 1 … m     (the rows A_k s u ≥ b_k divided by ‖A_k s‖:
                                              residuals in N·m)

``K`` (``QPBuffers.metric``, (r, n)) is what the caller wants a correction to cost besides its
own size: with the filter's tool metric (``FilterConfig.weight="tool"``), ``K = G / a``, the tool's
acceleration per unit of ``u`` over the acceleration ``a`` that costs as much as a unit of ``u``.
A workspace with ``r = 0`` solves with ``H = I``, as DAQP was set up, and never refactors it.

When no ``u`` in the box satisfies every row, the rows give way **by priority, not by weights**:
DAQP's hierarchical mode satisfies each level as well as the levels above it allow (least squares
of the level's violations), and only then minimises the cost. DAQP measures a violation in its
own form of the problem, where each row is normalised in the metric: row ``k``'s violation ``s_k``
(row-normalised, as the residuals) counts as ``s_k / ‖â_k‖_{H⁻¹}``. With ``H = I`` that is
``s_k`` itself; with a metric, a level's conflict is spread differently over its rows (a row
along which the metric makes ``u`` dear, ``‖â_k‖_{H⁻¹}`` small, is held harder). The levels and
which rows give way at all are the same in every metric. The levels:

0. the torque box: hard;
1. the joint position and speed limits, the floor, the arm's own capsule pairs and the distance guard;
2. the joint range's reserve, when the filter keeps one (``FilterConfig.joint_range_reserve``):
   the joint position rows drawn that far inside the range, whose copies at the range itself are
   level 1's;
3. with an allowance level (``FilterConfig.allowance_level``): the barrier's rows, each loosened
   by its allowance (``QPBuffers.allowance``: how far it may give way and still hold the barrier
   condition with a raised gain, :func:`c3bf_gym.safety._step.set_allowances`);
4. the barrier's rows beside a guard (the C3BF's in the default filter) as written;
5. with a speed reserve (``FilterConfig.nominal_speed_fraction`` below ``joint_speed_fraction``):
   the joint speed rows at the nominal torque's bound, whose copies at the filter's bound are
   level 1's. They give way first.

A level with no rows is left out. So with a reserve the rows of level 1, the guard among them, can
take a joint into the last of its range, and the barrier's rows cannot; with an allowance level
the barrier's rows give way beyond their allowance only where the rows above leave no torque that
holds them within it, instead of a conflict being spread over all of them (least squares) while
some have room to spare; with a speed reserve the barrier's rows may take a joint past the
nominal torque's speed bound, up to the filter's, before they give way. Without any of them the
levels are 0, 1 and 4, named 1 and 2 below.

So with a guard the joint-speed bound holds whenever some torque within the limits can hold it
together with the floor and the guard. A filter without a guard has no level 2: its barrier's
rows are the only ones keeping obstacles off, so they share level 1 with the joint limits and the
floor, and a conflict spreads over all of them (least squares of the normalised violations). Rows
whose scaled coefficients are all (numerically) zero cannot change with the torque: with
``b_k ≤ 0`` they hold; with ``b_k > 0`` (a link the joints cannot move, headed for by an
obstacle) they can never hold, and are left out of the solve with their ``b_k`` counted in
``slack``.

:class:`~c3bf_gym.safety.priority_qp.PriorityQP` sets the workspaces up (:class:`QPBuffers`) and
calls :func:`solve_rows` from Python; the filter's fused step (:mod:`c3bf_gym.safety._step`)
compiles it into itself.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from c3bf_gym._compile_cache import STEP_KERNEL_OPTIONS  # (before any @njit(cache=True): the cache keys)
from c3bf_gym.safety._daqp import (
    INF,
    PROBLEM_M,
    UPDATE_D,
    UPDATE_M,
    UPDATE_RINV,
    UPDATE_SENSE,
    UPDATE_V,
    DaqpBuffers,
    daqp_call,
)

#: :func:`solve_rows` outcomes: every row held; rows gave way by priority; DAQP found no torque even
#: by priority (the box projection of the nominal torque is applied and reported); invalid input
SOLVED, RELAXED, FAILED = 0, 1, 2
BAD_NOMINAL, BAD_ROWS = -1, -2
#: rows whose coefficients (times the scale) are shorter than this cannot change with the torque
ROW_NORM_MIN = 1e-12
#: [row-normalised] a row counts as held (and, at the bound, as active) within this
ACTIVE_TOL = 1e-6
#: [row-normalised] a prioritised answer that violates a row by more than this proves that no
#: torque satisfies every row. DAQP's soft levels leave a feasible level's rows violated by
#: ``rho_soft · λ`` (1e-6 times the row's multiplier), far below it.
INFEASIBLE_TOL = 1e-3


class QPBuffers(NamedTuple):
    """Everything :func:`solve_rows` works in, allocated once by
    :class:`~c3bf_gym.safety.priority_qp.PriorityQP`.

    Attributes:
        plain: the one-level workspace (every row hard), warm-started call to call.
        hier: the prioritised workspace, solved when ``plain`` is infeasible, warm-started from
            its own previous solve's working set: level 1's rows first (with the copies of the
            reserve's rows at the range), then the reserve's, the barrier's loosened by their
            allowance and the barrier's as written, its problem and break points sized to the
            rows in use at every solve.
        capacity: int64 (5,) the row capacity of each of ``hier``'s levels, in its order: level 1,
            the range's reserve, the barrier's loosened by their allowance, the barrier's as written
            and the nominal speed bound (0: the workspace has no such level).
        lo, hi: (n,) the box of ``u``.
        u: (n,) the solution.
        norm: (rows,) each row's norm ``‖A_k s‖`` (0: left out).
        residual: (rows,) each row's normalised residual ``â_k u − b̂_k`` at the solution (> −tol:
            held); for a zero row, ``−b_k``; for a joint row with a reserve that gave way, the
            residual of its copy in level 1 when that is violated, else 0 (the reserve used, no
            row lost).
        cold: int64 (2,) 1: the next solve of ``plain`` (``cold[0]``) or ``hier`` (``cold[1]``)
            starts from an empty working set (then 0).
        last: int64 (1,) the previous call's status (:data:`SOLVED`, :data:`RELAXED`, ...).
        reserve: (4n,) for ``n`` joints, or empty: none. The last ``4n`` rows of a call are then
            the joint limits' (position upper and lower, then speed upper and lower, as
            :class:`~c3bf_gym.safety.barriers.JointLimits` orders them), and joint row ``i`` with
            ``reserve[i] > 0`` is held in a level of its own, with a copy in level 1 whose ``b``
            is lowered by ``reserve[i]``: a position row is drawn inside the range by the range's
            reserve (``γ₁γ₂ δ``; its level above the barrier's), a speed row lies at the nominal
            torque's bound below its copy at the filter's bound (``γ_v (q̇_max − q̇_nominal)``;
            its level below the barrier's). A zero entry: the row is level 1's alone.
        allowance: (rows,) how far each of the barrier's rows may give way [its ``b``'s units,
            ≥ 0], set by the caller before each solve when ``capacity[2] > 0`` (read only then;
            other rows' entries are ignored): the allowance level holds ``A_k τ ≥ b_k −
            allowance[k]``.
        metric: (r, n) ``K`` of the cost's ``H = I + KᵀK`` (the module docstring), set by the
            caller before each solve; (0, n): ``H = I``.
        u_nom: (n,) the last call's nominal ``u`` (the cost's linear term is ``−H u_nom``).
    """

    plain: DaqpBuffers
    hier: DaqpBuffers
    capacity: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    u: np.ndarray
    norm: np.ndarray
    residual: np.ndarray
    cold: np.ndarray
    last: np.ndarray
    reserve: np.ndarray
    allowance: np.ndarray
    metric: np.ndarray
    u_nom: np.ndarray


@njit(**STEP_KERNEL_OPTIONS)
def _clear(buffers, start, stop):
    """Rows ``start`` … ``stop`` of a workspace become unused (zero, no bound)."""
    n = buffers.x.shape[0]
    for k in range(start, stop):
        for j in range(n):
            buffers.A[k, j] = 0.0
        buffers.lower[n + k] = -INF


@njit(**STEP_KERNEL_OPTIONS)
def _load_cost(qp):
    """The cost of ``qp.u_nom``: ``f = −H u_nom`` into ``qp.plain``, and with a metric
    (``qp.metric`` (r, n), ``r > 0``) ``H = I + KᵀK`` into both workspaces (which then need
    :data:`~c3bf_gym.safety._daqp.UPDATE_RINV`, :func:`_cost_mask`). Returns False when the metric
    is not finite (nothing else is usable then)."""
    plain, K, u_nom = qp.plain, qp.metric, qp.u_nom
    n = u_nom.shape[0]
    if K.shape[0] == 0:
        for j in range(n):
            plain.f[j] = -u_nom[j]
        return True
    for i in range(n):
        for j in range(i, n):
            acc = 1.0 if i == j else 0.0
            for r in range(K.shape[0]):
                acc += K[r, i] * K[r, j]
            if not math.isfinite(acc):
                return False
            plain.H[i, j] = plain.H[j, i] = qp.hier.H[i, j] = qp.hier.H[j, i] = acc
    for i in range(n):
        acc = 0.0
        for j in range(n):
            acc += plain.H[i, j] * u_nom[j]
        plain.f[i] = -acc
    return True


@njit(**STEP_KERNEL_OPTIONS)
def _cost_mask(qp):
    """The update mask a solve's cost needs: :data:`~c3bf_gym.safety._daqp.UPDATE_RINV` with a
    metric (``H`` is new at every call), else none (``H = I``, factored at setup)."""
    return UPDATE_RINV if qp.metric.shape[0] > 0 else 0


@njit(**STEP_KERNEL_OPTIONS)
def _load_rows(tau_nom, A, b, scale, cols, qp):
    """Step 1 of :func:`solve_rows`: the cost (:func:`_load_cost`) and the scaled, normalised rows
    into ``qp.plain`` (its problem sized to them), each row's norm into ``qp.norm`` (0: a row the
    torque cannot change, left out). Returns ``(SOLVED, impossible)`` (the largest ``b_k`` of a
    row that can never hold, 0 if none), or ``(BAD_NOMINAL or BAD_ROWS, 0)`` for a non-finite
    input."""
    n = tau_nom.shape[0]
    m = b.shape[0]
    plain = qp.plain
    for j in range(n):
        u_nom = tau_nom[j] / scale[j]
        if not math.isfinite(u_nom):
            return BAD_NOMINAL, 0.0
        qp.u_nom[j] = u_nom
    if not _load_cost(qp):
        return BAD_ROWS, 0.0
    impossible = 0.0
    for k in range(m):
        sq = 0.0
        for j in range(n):
            a = A[k, cols[j]] * scale[j]
            plain.A[k, j] = a
            sq += a * a
        norm = math.sqrt(sq)
        if not (math.isfinite(norm) and math.isfinite(b[k])):
            return BAD_ROWS, 0.0
        if norm < ROW_NORM_MIN:
            qp.norm[k] = 0.0
            for j in range(n):
                plain.A[k, j] = 0.0
            plain.lower[n + k] = -INF
            impossible = max(impossible, b[k])
            continue
        qp.norm[k] = norm
        for j in range(n):
            plain.A[k, j] /= norm
        plain.lower[n + k] = b[k] / norm
    plain.problem[PROBLEM_M] = n + m
    return SOLVED, impossible


@njit(**STEP_KERNEL_OPTIONS)
def _active_and_slack(qp, b, status, impossible):
    """After :func:`solve_rows`' solves: the rows active within :data:`ACTIVE_TOL`, and the slack
    (the largest normalised violation or ``impossible``; only that when solved). A row left out
    gets the residual ``−b_k`` when it can never hold, else 0."""
    n_active = 0
    slack = impossible
    for k in range(b.shape[0]):
        if qp.norm[k] == 0.0:
            qp.residual[k] = -b[k] if b[k] > 0.0 else 0.0
            continue
        if qp.residual[k] <= ACTIVE_TOL:
            n_active += 1
        if status != SOLVED:
            slack = max(slack, -qp.residual[k])
    return n_active, slack


@njit(**STEP_KERNEL_OPTIONS)
def solve_rows(tau_nom, A, b, scale, cols, n_obstacle_rows, stride, qp):
    """The filter's QP (the module docstring) for the rows ``A[:, cols] τ ≥ b`` (``A`` (m, k), ``cols``
    (n,): the columns of the torque's dofs among ``A``'s ``k``) and nominal torque ``tau_nom``
    (n,), in ``u = τ / scale``; the solution goes to ``qp.u`` (:class:`QPBuffers`).

    1. Rows are scaled (``A_k s``) and normalised; a row shorter than :data:`ROW_NORM_MIN` cannot
       change with the torque: with ``b_k ≤ 0`` it holds, with ``b_k > 0`` it can never hold
       (``impossible``, its ``b_k``). Both are left out of the solves.
    2. All rows hard (``qp.plain``, its problem sized to the ``m`` rows: DAQP reads none past
       them), warm-started from its previous solve's working set. If DAQP finds the optimum and
       every row holds within :data:`ACTIVE_TOL`, that is the answer (:data:`SOLVED`).
    3. Otherwise, by priority (:data:`RELAXED`, ``qp.hier``): level 1 holds the rows that are not
       the barrier's (the guard's, the floor's, the joint limits'), then the joint range's
       reserve (``qp.reserve``: the position rows inside the range, their copies at the range in
       level 1), then (with ``capacity[2] > 0`` and some allowance above 0) the barrier's rows
       loosened by ``qp.allowance``, then the barrier's as written: rows ``k < n_obstacle_rows``
       with ``k % stride == 0``, then the speed rows at the nominal torque's bound (their copies at
       the filter's bound in level 1); its problem too is sized to the rows in use. Warm-started
       from its own previous solve's working set, and once more from an empty one if that fails. If
       it fails too, ``u`` is the box projection of ``u_nom`` (:data:`FAILED`).

    Right after a call that was not solved, step 3 comes first: if its answer violates some row
    by more than :data:`INFEASIBLE_TOL`, no torque satisfies every row (else both levels would
    hold up to DAQP's soft tolerance), so that answer stands without step 2. Otherwise step 2
    runs as usual. The answer is the same either way; a run of calls with no safe torque just
    does not prove infeasibility again at every call.

    After ``qp.cold[:] = 1`` (a reset), both solves start from an empty working set and the
    first call takes step 2 first, so a sequence of calls after a reset depends on nothing
    before it.

    Returns ``(status, iterations, active rows, slack)``: slack the largest normalised violation
    (or impossible ``b_k``), 0 when solved.
    """
    n = tau_nom.shape[0]
    m = b.shape[0]
    plain = qp.plain
    bad, impossible = _load_rows(tau_nom, A, b, scale, cols, qp)
    if bad != SOLVED:
        return bad, 0, 0, 0.0
    status = SOLVED
    iterations = 0
    by_priority = -1  # the prioritised solve's exit flag (-1: not run)
    if qp.last[0] != SOLVED and not qp.cold[0]:
        by_priority, iterations = _solve_by_priority(qp, m, n_obstacle_rows, stride)
        if by_priority >= 1 and _residuals(plain, qp, m) < -INFEASIBLE_TOL:
            status = RELAXED
    if status == SOLVED:
        mask = UPDATE_M | UPDATE_V | UPDATE_D | _cost_mask(qp)
        if qp.cold[0]:
            qp.cold[0] = 0
            for i in range(plain.sense.shape[0]):
                plain.sense[i] = 0
            mask |= UPDATE_SENSE
        flag, more = daqp_call(plain, mask)
        iterations += more
        if flag >= 1:
            for j in range(n):
                qp.u[j] = min(max(plain.x[j], qp.lo[j]), qp.hi[j])
            if _residuals(plain, qp, m) < -ACTIVE_TOL:
                flag = -1  # DAQP's answer does not hold every row: solve by priority
        if flag < 1:
            status = RELAXED
            if by_priority < 0:
                by_priority, more = _solve_by_priority(qp, m, n_obstacle_rows, stride)
                iterations += more
            if by_priority >= 1:
                for j in range(n):
                    qp.u[j] = min(max(qp.hier.x[j], qp.lo[j]), qp.hi[j])
            else:
                status = FAILED
                for j in range(n):
                    qp.u[j] = min(max(qp.u_nom[j], qp.lo[j]), qp.hi[j])
            _residuals(plain, qp, m)
        elif impossible > 0.0:
            status = RELAXED
    qp.last[0] = status
    if status != SOLVED:
        _reserve_residuals(qp, m)
    n_active, slack = _active_and_slack(qp, b, status, impossible)
    return status, iterations, n_active, slack


@njit(**STEP_KERNEL_OPTIONS)
def barrier_row(k, n_obstacle_rows, stride):
    """Whether row ``k`` is the barrier's: ``k < n_obstacle_rows`` and ``k % stride == 0`` (the
    obstacle rows come first, each barrier row followed by its guard's when ``stride`` is 2)."""
    return k < n_obstacle_rows and k % stride == 0


#: :func:`_row_level`'s levels of the prioritised solve: level 1, the joint range's reserve, the
#: barrier's (loosened by their allowance, then as written) and the nominal speed bound
LEVEL_1, LEVEL_RANGE, LEVEL_BARRIER, LEVEL_SPEED = range(4)


@njit(**STEP_KERNEL_OPTIONS)
def _row_level(k, m, n_obstacle_rows, stride, reserve):
    """The level of row ``k`` of ``m`` in the prioritised solve (:func:`solve_rows`, step 3):
    :data:`LEVEL_BARRIER` for the barrier's (:func:`barrier_row`); for joint row ``i`` (the last
    ``4n`` rows, ``reserve`` (4n,) non-empty) with ``reserve[i] > 0``, :data:`LEVEL_RANGE` (a
    position row, ``i < 2n``) or :data:`LEVEL_SPEED` (a speed row); else :data:`LEVEL_1`."""
    if barrier_row(k, n_obstacle_rows, stride):
        return LEVEL_BARRIER
    r = reserve.shape[0]
    i = k - (m - r)
    if r > 0 and i >= 0 and reserve[i] > 0.0:
        return LEVEL_RANGE if 2 * i < r else LEVEL_SPEED
    return LEVEL_1


@njit(**STEP_KERNEL_OPTIONS)
def _reserve_residuals(qp, m):
    """After a solve that was not :data:`SOLVED`: a joint row with a reserve that gave way reports
    its copy in level 1 instead, ``min(residual + reserve / norm, 0)``: 0 when the joint only went
    into its reserve (of range or speed), the copy's violation when it went past it."""
    r = qp.reserve.shape[0]
    for k in range(m - r, m):
        if qp.norm[k] != 0.0 and qp.residual[k] < 0.0 and qp.reserve[k - (m - r)] > 0.0:
            qp.residual[k] = min(qp.residual[k] + _reserve_offset(qp, k, m), 0.0)


@njit(**STEP_KERNEL_OPTIONS)
def _reserve_offset(qp, k, m):
    """How far joint row ``k`` (of ``m``) lies inside its copy in level 1 [row-normalised]."""
    return qp.reserve[k - (m - qp.reserve.shape[0])] / qp.norm[k]


@njit(**STEP_KERNEL_OPTIONS)
def _put_row(plain, hier, k, i, lower):
    """Row ``k`` of ``plain`` (scaled and normalised) as row ``i`` of ``hier``, bounded below by ``lower``."""
    n = plain.x.shape[0]
    for j in range(n):
        hier.A[i, j] = plain.A[k, j]
    hier.lower[n + i] = lower


@njit(**STEP_KERNEL_OPTIONS)
def _solve_by_priority(qp, m, n_obstacle_rows, stride):
    """Step 3 of :func:`solve_rows` on the rows ``qp.plain`` holds (scaled and normalised):
    returns ``(exit flag, iterations)``; on success (flag ≥ 1) ``qp.u`` is the answer, clipped
    to the box."""
    plain, hier = qp.plain, qp.hier
    n = plain.x.shape[0]
    # The problem is sized to the rows in use, level by level (DAQP reads its break_points, hier.levels,
    # at every solve): level 1's rows first (a joint row's copy with its reserve among them), then the
    # range's reserve, the barrier's loosened by their allowance, the barrier's as written and the speed
    # bound. A level the workspace has keeps at least one row, a zero one (which DAQP ignores) when it
    # has none this call.
    count1 = count_range = count_barrier = count_speed = 0
    loosened = False
    for k in range(m):
        if qp.norm[k] != 0.0:
            row_level = _row_level(k, m, n_obstacle_rows, stride, qp.reserve)
            if row_level == LEVEL_BARRIER:
                count_barrier += 1
                loosened = loosened or (qp.capacity[2] > 0 and qp.allowance[k] > 0.0)
            else:
                count1 += 1
                if row_level == LEVEL_RANGE:
                    count_range += 1
                elif row_level == LEVEL_SPEED:
                    count_speed += 1
    count_loose = count_barrier if loosened else 0
    i1, i_range = 0, max(count1, 1) if qp.capacity[0] > 0 else 0
    i_loose = i_range + (max(count_range, 1) if qp.capacity[1] > 0 else 0)
    i_barrier = i_loose + (max(count_loose, 1) if qp.capacity[2] > 0 else 0)
    i_speed = i_barrier + (max(count_barrier, 1) if qp.capacity[3] > 0 else 0)
    end_speed = i_speed + (max(count_speed, 1) if qp.capacity[4] > 0 else 0)
    _clear(hier, count1, i_range)
    _clear(hier, i_range + count_range, i_loose)
    _clear(hier, i_loose + count_loose, i_barrier)
    _clear(hier, i_barrier + count_barrier, i_speed)
    _clear(hier, i_speed + count_speed, end_speed)
    level, last = 1, 0
    for end in (i_range, i_loose, i_barrier, i_speed, end_speed):
        if end > last:
            hier.levels[level] = n + end
            level += 1
            last = end
    hier.problem[PROBLEM_M] = n + end_speed
    for k in range(m):
        if qp.norm[k] == 0.0:
            continue
        lower = plain.lower[n + k]
        row_level = _row_level(k, m, n_obstacle_rows, stride, qp.reserve)
        if row_level == LEVEL_1:
            _put_row(plain, hier, k, i1, lower)
            i1 += 1
        elif row_level == LEVEL_BARRIER:
            _put_row(plain, hier, k, i_barrier, lower)
            i_barrier += 1
            if loosened:
                _put_row(plain, hier, k, i_loose, lower - qp.allowance[k] / qp.norm[k])
                i_loose += 1
        else:  # inside the range, or at the speed bound; its copy with the reserve in level 1
            if row_level == LEVEL_RANGE:
                _put_row(plain, hier, k, i_range, lower)
                i_range += 1
            else:
                _put_row(plain, hier, k, i_speed, lower)
                i_speed += 1
            _put_row(plain, hier, k, i1, lower - _reserve_offset(qp, k, m))
            i1 += 1
    for j in range(n):
        hier.f[j] = plain.f[j]
    flag, iterations = 0, 0
    mask = UPDATE_M | UPDATE_V | UPDATE_D | _cost_mask(qp)
    if not qp.cold[1]:
        flag, iterations = daqp_call(hier, mask)
    if flag < 1:  # cold, or the warm start failed: again from an empty working set
        qp.cold[1] = 0
        for i in range(hier.sense.shape[0]):
            hier.sense[i] = 0
        flag, more = daqp_call(hier, mask | UPDATE_SENSE)
        iterations += more
    if flag >= 1:
        for j in range(n):
            qp.u[j] = min(max(hier.x[j], qp.lo[j]), qp.hi[j])
    return flag, iterations


@njit(**STEP_KERNEL_OPTIONS)
def _residuals(plain, qp, m):
    """``qp.residual[k] = â_k u − b̂_k`` for the first ``m`` (normalised) rows; returns their minimum
    over the rows that are not left out (inf without one)."""
    n = qp.u.shape[0]
    low = np.inf
    for k in range(m):
        if qp.norm[k] == 0.0:
            continue
        acc = 0.0
        for j in range(n):
            acc += plain.A[k, j] * qp.u[j]
        qp.residual[k] = acc - plain.lower[n + k]
        low = min(low, qp.residual[k])
    return low
