"""The filter's fused step in compiled (numba) code: the rows, the QP and the report, one call per
physics step. The top of the compiled layers: it imports the rows (:mod:`c3bf_gym.safety._rows`)
and the QP (:mod:`c3bf_gym.safety._qp`), and nothing below imports it.

The filter runs at every physics step (500 Hz); at the arm's size (6 joints, 7 capsules: tens of
numbers an array) numpy would spend its time in per-call overhead, so the kernels do the arithmetic
in plain loops, compiled once by numba with :data:`~c3bf_gym._compile_cache.STEP_KERNEL_OPTIONS`
(cached on disk, keyed on every kernel source by :mod:`c3bf_gym._compile_cache`; no allocation,
no reference counting).

* :func:`filter_substep`: the rows (:func:`~c3bf_gym.safety._rows.filter_rows`), the QP
  (:func:`~c3bf_gym.safety._qp.solve_rows`, priorities by :func:`low_priority_span`),
  :func:`hook_post` and the report's running values (:func:`record` into a :class:`Tally`);
  :func:`filter_substep_at`: the same with its buffers by address, for calls from Python. An
  environment's compiled policy step (:mod:`c3bf_gym.envs._kernels`) calls :func:`filter_substep`
  between physics steps.
* :func:`record`, :func:`violations_by_kind`, :func:`beyond_allowance`: what a policy step's calls
  accumulate for :class:`~c3bf_gym.safety.StepSafety`, the one implementation the fused step and
  :class:`~c3bf_gym.safety.SafetyController`'s per-class path share.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from c3bf_gym._compile_cache import KERNEL_OPTIONS, STEP_KERNEL_OPTIONS  # (before any @njit(cache=True): the cache keys)
from c3bf_gym._capi import unpack

# filter_substep compiles _rows.filter_rows and _qp.solve_rows into itself: _compile_cache keys
# the on-disk cache of every kernel file's functions on all of them.
from c3bf_gym.safety._dynamics import ArmMotion, tool_site_dynamics
from c3bf_gym.safety._qp import ACTIVE_TOL, RELAXED, SOLVED, barrier_row, solve_rows
from c3bf_gym.safety._rows import EE_POINTS, filter_rows

_opts = STEP_KERNEL_OPTIONS


# ----------------------------------------------------------------------------- the fused filter step


@njit(**_opts)
def hook_post(b, norm, residual, u, scale, tau_nom, limit, tau):
    """The filter's bookkeeping after the QP (:func:`c3bf_gym.safety._qp.solve_rows` on ``m``
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
    one, the barrier's; :func:`c3bf_gym.safety._qp.solve_rows`' ``n_obstacle_rows``). Beside a
    guard (``guarded``) the barrier's rows give way first: all obstacle rows. Without one every
    row has priority 1: 0."""
    return m - n_fixed if guarded else 0


@njit(**_opts)
def violations_by_kind(residual, norm, n_obstacle, stride, n_floor, n_self, tol, out):
    """Fold one call's row residuals into ``out`` (6,): for each kind of row, in the order of
    :data:`~c3bf_gym.safety.controller.ROW_KINDS` (barrier, guard, floor, joint limits,
    unmovable, self collision), the largest violation ``−residual[k]`` above ``tol`` and above
    what ``out`` holds.

    The rows are laid out as the filter builds them: the first ``n_obstacle`` are the obstacles'
    (the barrier's at ``k % stride == 0``, else the guard's), then ``n_floor`` floor rows, then
    ``n_self`` rows of the arm's own capsule pairs, then the joint limits'. A row with
    ``norm[k] == 0`` (no torque can change it) is "unmovable", whatever its place; its residual
    is then ``−b_k`` (:func:`c3bf_gym.safety._qp.solve_rows`).
    """
    for k in range(residual.shape[0]):
        if norm[k] == 0.0:
            kind = 4
        elif k < n_obstacle:
            kind = 0 if k % stride == 0 else 1
        elif k < n_obstacle + n_floor:
            kind = 2
        elif k < n_obstacle + n_floor + n_self:
            kind = 5
        else:
            kind = 3
        violation = -residual[k]
        if violation > out[kind] and violation > tol:
            out[kind] = violation


# ----------------------------------------------------------------------------- the policy step's report

#: Entries of :attr:`Tally.values`, the running values of a :class:`~c3bf_gym.safety.StepSafety`
#: over a policy step's calls; :data:`T_VIOLATION` starts the largest violation of each of the
#: six row kinds.
(T_SUBSTEPS, T_MIN_CONSTRAINT, T_MIN_H, T_INSIDE, T_SENSED, T_ACTIVE_ROWS, T_CORRECTION, T_INTERVENED,
 T_INFEASIBLE_STEPS, T_SLACK, T_GAIN_RAISED_STEPS, T_VIOLATION) = range(12)
TALLY_SIZE = T_VIOLATION + 6
#: Entries of :attr:`Tally.last`: the last recorded call's own values
L_STATUS, L_ITERATIONS, L_ACTIVE, L_SLACK = range(4)
#: Entries of :attr:`Tally.gains`: the barrier's gain γ and the largest gain γ_max its rows may
#: rise to where they give way at ``h > 0`` [1/s]
G_BARRIER, G_LIMIT = range(2)
#: A call's outcome beside :func:`c3bf_gym.safety._qp.solve_rows`' codes: only barrier rows gave
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
            (:data:`GAIN_RAISED` or a :func:`~c3bf_gym.safety._qp.solve_rows` code), DAQP
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
def _gain_room(gains):
    """``γ_max − γ`` (at least 0) of ``gains`` (:attr:`Tally.gains`): a barrier row at ``h > 0``
    may give way by this times ``h`` (:func:`beyond_allowance`)."""
    return max(gains[G_LIMIT] - gains[G_BARRIER], 0.0)


@njit(**_opts)
def set_allowances(allowance, row_h, gains, n_obstacle, stride):
    """Each row's allowance into ``allowance`` (m,), in its ``b``'s units: ``(γ_max − γ) h`` for a
    barrier row at ``h > 0`` (:func:`beyond_allowance`), 0 for every other row. The allowance
    level of the QP (``QPBuffers.allowance``, :mod:`c3bf_gym.safety._qp`) holds the barrier's
    rows loosened by it."""
    raise_by = _gain_room(gains)
    for k in range(allowance.shape[0]):
        allowance[k] = raise_by * max(row_h[k], 0.0) if barrier_row(k, n_obstacle, stride) else 0.0


@njit(**_opts)
def tool_metric(G, dofs, scale, weight, metric):
    """The filter's tool metric (``FilterConfig.weight="tool"``) into ``metric`` (3, n), the
    ``K`` of the QP's cost ``H = I + KᵀK`` (:mod:`c3bf_gym.safety._qp`): ``K = G[:, dofs]
    diag(scale) · weight``, with ``G`` (3, nv) the tool site's acceleration per unit of
    generalised force [m/s² per N m] (:func:`~c3bf_gym.safety._dynamics.tool_site_dynamics`),
    ``scale`` (n,) the torque scale and ``weight`` ``1/a`` [s²/m]. So a change of the scaled
    torque ``u`` that changes the tool's acceleration by ``a`` costs as much as a unit change of
    ``u`` itself."""
    for i in range(3):
        for j in range(dofs.shape[0]):
            metric[i, j] = G[i, dofs[j]] * scale[j] * weight


@njit(**_opts)
def solve_call(tau_nom, A, b, scale, dofs, layout, tally, qp):
    """The filter's QP on one call's ``m`` rows ``A τ ≥ b`` (``A`` (m, n), ``b`` (m,)), laid out
    as ``layout`` (:class:`RowLayout`) says: the allowances when the QP has an allowance level
    (:func:`set_allowances`, from ``tally``'s row ``h`` and gains, :class:`Tally`), then
    :func:`c3bf_gym.safety._qp.solve_rows` with the filter's priorities
    (:func:`low_priority_span`; a stride of 2 means a guard beside the barrier). ``scale`` (n,)
    is the torque scale and ``dofs`` the arm's columns. Returns ``solve_rows``' ``(status,
    iterations, n_active, slack)``; the solution is in ``qp`` (``QPBuffers``). The fused step
    (:func:`filter_substep`) and the controller's Python path for custom barriers both call
    this, so they solve the same problem."""
    m = b.shape[0]
    if qp.capacity[2] > 0:
        set_allowances(qp.allowance[:m], tally.row_h, tally.gains, layout.n_obstacle, layout.stride)
    span = low_priority_span(m, m - layout.n_obstacle, layout.stride == 2)
    return solve_rows(tau_nom, A, b, scale, dofs, span, layout.stride, qp)


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
    beyond :data:`~c3bf_gym.safety._qp.ACTIVE_TOL` (row-normalised)."""
    raise_by = _gain_room(gains)
    for k in range(residual.shape[0]):
        violation = -residual[k]
        if violation <= ACTIVE_TOL:
            continue
        if norm[k] == 0.0 or not barrier_row(k, n_obstacle, stride):
            return True
        if violation * norm[k] > raise_by * max(row_h[k], 0.0) + ACTIVE_TOL * norm[k]:
            return True
    return False


class CallSummary(NamedTuple):
    """One solved call of the filter, as :func:`record` folds it into the tally.

    Attributes:
        status: :func:`~c3bf_gym.safety._qp.solve_rows`' code (≥ 0: invalid input is not recorded).
        m: the call's rows.
        min_h, inside, n_sensed: the smallest ``h`` of the barrier's rows, whether a point was
            inside its margin, and the obstacles sensed
            (:func:`~c3bf_gym.safety._rows.filter_rows`).
        iterations, n_active, slack: DAQP's iterations, the active rows and the slack
            (:func:`~c3bf_gym.safety._qp.solve_rows`).
        residual, correction: the smallest row residual and the filter's change of the torque
            (:func:`hook_post`).
    """

    status: int
    m: int
    min_h: float
    inside: bool
    n_sensed: int
    iterations: int
    n_active: int
    slack: float
    residual: float
    correction: float


class RowLayout(NamedTuple):
    """Where each kind of row sits among a call's rows, as the filter builds them: the first
    ``n_obstacle`` are the obstacles' (the barrier's at ``k % stride == 0``, else the guard's),
    then ``n_floor`` floor rows, then ``n_self`` rows of the arm's own capsule pairs, then the
    joint limits'."""

    n_obstacle: int
    stride: int
    n_floor: int
    n_self: int


@njit(**_opts)
def record(tally, call, tau_nom, tau, qp, layout, intervention_tol):
    """Fold one solved call (:class:`CallSummary`; its rows laid out as ``layout`` says,
    :class:`RowLayout`) into ``tally``: the running extremes and counts of
    :class:`~c3bf_gym.safety.StepSafety`, the last call's torques ``tau_nom`` and ``tau``, status,
    iterations, active rows and slack, whether it changed the torque by more than
    ``intervention_tol``, and, when rows gave way, the largest violation of each kind
    (:func:`violations_by_kind` on the QP's residuals in ``qp``) and whether the call held every
    row with the barrier's gain raised (:func:`beyond_allowance`: counted in
    ``T_GAIN_RAISED_STEPS``) or not (``T_INFEASIBLE_STEPS``).

    Returns the call's outcome: ``call.status``, or :data:`GAIN_RAISED` for a relaxed call within
    the allowance."""
    status, m, min_h, inside, n_sensed, iterations, n_active, slack, residual, correction = call
    n_obstacle, stride, n_floor, n_self = layout
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
        violations_by_kind(qp.residual[:m], qp.norm[:m], n_obstacle, stride, n_floor, n_self, ACTIVE_TOL,
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


class StepBuffers(NamedTuple):
    """What :func:`filter_substep` works in besides a call's torques, gathered once by the filter
    (:class:`~c3bf_gym.safety.SafetyController`; all allocated once and updated in place).

    Attributes:
        arm, obstacles, params: :class:`~c3bf_gym.safety._dynamics.ArmArrays`,
            :class:`~c3bf_gym.safety._rows.ObstacleArrays`, :class:`~c3bf_gym.safety._rows.RowParams`.
        A, b: the rows' buffers (rows, nv), (rows,).
        scale, limit: (n,) the torque's scale and limits [N m].
        qp: :class:`~c3bf_gym.safety._qp.QPBuffers`.
        tally: :class:`Tally`.
        intervention_tol: the change of the torque [N m] above which a call counts as an
            intervention.
        tool_weight: ``1/a`` [s²/m] of the tool metric (:func:`tool_metric`), when the QP has
            metric rows (``qp.metric``); unused otherwise.
    """

    arm: tuple
    obstacles: tuple
    params: tuple
    A: np.ndarray
    b: np.ndarray
    scale: np.ndarray
    limit: np.ndarray
    qp: tuple
    tally: Tally
    intervention_tol: float
    tool_weight: float


@njit(**_opts)
def filter_substep(stage, tau_nom, tau, buffers):
    """One filter step in one call, in ``buffers`` (:class:`StepBuffers`; an
    environment's compiled policy step, and :meth:`~c3bf_gym.safety.SafetyController.__call__`
    through :func:`filter_substep_at`): the rows
    (:func:`~c3bf_gym.safety._rows.filter_rows`, whose arguments ``stage`` … ``b`` are),
    the tool metric when the QP has one (:func:`tool_metric`, on the tool site's dynamics), the
    QP (:func:`solve_call` on ``qp``) in the scaled torque ``τ / scale``, :func:`hook_post`, which writes
    the torque into ``tau``, and :func:`record` of the outcome into ``tally``.

    Returns the status, one of :func:`~c3bf_gym.safety._qp.solve_rows`' codes (invalid input, < 0,
    is not recorded), with a relaxed call that held every row with the barrier's gain raised
    (:func:`record`'s :data:`GAIN_RAISED`) returned as :data:`~c3bf_gym.safety._qp.SOLVED`: the
    callers (an environment's loop, ``on_infeasible="raise"``) stop on the others.
    """
    arm, obstacles, params, A, b, scale, limit, qp, tally, intervention_tol, tool_weight = buffers
    m, min_h, inside, n_sensed = filter_rows(stage, arm, obstacles, params, A, b, tally.row_h)
    if qp.metric.shape[0] > 0:
        if params.points != EE_POINTS:  # (filter_rows computed the site's dynamics for its own rows)
            tool_site_dynamics(arm.site, ArmMotion(arm.cdof, arm.cdof_dot, arm.com, arm.qvel, arm.Minv,
                                                   arm.qacc_free))
        tool_metric(arm.site.packed[0, :, 3:], params.dofs, scale, tool_weight, qp.metric)
    n_floor, n_self = params.floor_ends.shape[0], params.self_pairs.shape[0] + params.fixed_capsules.shape[0]
    n_fixed = n_floor + n_self + (4 * params.dofs.shape[0] if params.joint_rows else 0)
    stride = 2 if params.guard.present else 1  # obstacle rows: barrier, guard, barrier, guard, ... beside a guard
    layout = RowLayout(m - n_fixed, stride, n_floor, n_self)
    status, iterations, n_active, slack = solve_call(tau_nom, A[:m], b[:m], scale, params.dofs, layout, tally, qp)
    if status < 0:
        return status
    residual, correction = hook_post(b[:m], qp.norm[:m], qp.residual[:m], qp.u, scale, tau_nom, limit, tau)
    call = CallSummary(status, m, min_h, inside, n_sensed, iterations, n_active, slack, residual, correction)
    outcome = record(tally, call, tau_nom, tau, qp, layout, intervention_tol)
    return SOLVED if outcome == GAIN_RAISED else outcome


@njit(**KERNEL_OPTIONS)
def filter_substep_at(stage, tau_nom, tau, handle, bound):
    """:func:`filter_substep` with its :class:`StepBuffers` by address: ``handle`` is
    :func:`c3bf_gym._capi.pack` of them and ``bound`` their numba type. From Python, one array
    crosses into compiled code instead of the ~80 buffers, which numba would convert one by one.
    Compiled with numba's reference counting, unlike the step kernels: the rebuild
    (:func:`c3bf_gym._capi.unpack`, :func:`numba.carray`) needs it; the arrays it rebuilds have no
    reference count to change, and :func:`filter_substep`, compiled without, runs as in the
    environment's step."""
    return filter_substep(stage, tau_nom, tau, unpack(handle, bound))
