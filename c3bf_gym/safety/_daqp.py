"""DAQP, the filter's QP solver, called from compiled (numba) code through its C API.

DAQP (Arnström, Bemporad, Axehill, IEEE TAC 2022; ``pip install daqp``, MIT licence) is a dual
active-set solver for small dense QPs. The filter solves, at every physics step, in the scaled
torque ``u = τ / s``::

    minimise    ½ ‖u − u_nom‖²
    subject to  u_min ≤ u ≤ u_max            (the torque limits: always hard)
                â_k u ≥ b̂_k,  k = 1 … m     (the safety rows, each normalised: ‖â_k‖ = 1)

and, when no ``u`` in the box satisfies every row, the same rows *by priority*
(:func:`solve_rows`): DAQP's hierarchical mode satisfies each priority level as well as the
levels above it allow (least squares of its rows' violations), then minimises the cost.

How the C API is reached. The ``daqp`` wheel ships no separate library: its extension module
exports the C API's symbols (``setup_daqp``, ``daqp_update_ldp``, ``daqp_solve``, ...). ctypes
opens it to set workspaces up (:class:`DaqpWorkspace`, once per filter) and to read the addresses of
``daqp_update_ldp`` and ``daqp_solve``. The compiled code receives those addresses as data, in the
workspace's ``addr`` array, and calls them through :func:`_call_update_ldp` and
:func:`c3bf_gym._capi.call_void` (numba intrinsics that emit an indirect call). No address is compiled in, so numba caches the
calling code on disk like every other kernel.

The structs are declared after ``csrc/include/types.h`` and ``api.h`` of the daqp **0.11.0**
sources (field order and C types; ctypes computes the x86-64 padding); their memory is numpy
buffers, so compiled code reads the result's exit flag through an int32 view. The layout is not an
ABI DAQP promises: importing this module with another daqp version raises ``ImportError``, and
:class:`DaqpWorkspace` checks the workspace fields it can see after setup.
"""

from __future__ import annotations

import ctypes as ct
import math
import weakref
from importlib.metadata import PackageNotFoundError, version
from typing import NamedTuple

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

from c3bf_gym._compile_cache import STEP_KERNEL_OPTIONS  # (before any @njit(cache=True): the cache keys)
from c3bf_gym._capi import call_void

__all__ = ["DAQP_VERSION", "DaqpBuffers", "DaqpWorkspace", "EXIT_FLAGS"]

#: the daqp release whose struct layouts are declared here
DAQP_VERSION = "0.11.0"
try:
    _installed = version("daqp")
except PackageNotFoundError as error:  # pragma: no cover - a declared dependency
    raise ImportError(f"the filter's QP solver needs daqp=={DAQP_VERSION}: pip install daqp=={DAQP_VERSION}") from error
if _installed != DAQP_VERSION:
    raise ImportError(f"c3bf_gym calls DAQP's C API with the struct layouts of daqp {DAQP_VERSION}; "
                      f"daqp {_installed} is installed: pip install daqp=={DAQP_VERSION}")
import daqp  # noqa: E402  (after the version check)

#: DAQP's "no bound" (constants.h)
INF = 1e30
UPDATE_M, UPDATE_V, UPDATE_D, UPDATE_SENSE = 2, 4, 8, 16
#: DAQP's exit flags (constants.h): positive = a solution
EXIT_FLAGS = {5: "feasible", 4: "optimal_inexact", 3: "constrained_point", 2: "soft_optimal", 1: "optimal",
              -1: "infeasible", -2: "cycle", -3: "unbounded", -4: "iterlimit", -5: "nonconvex",
              -6: "overdetermined_initial", -7: "timelimit", -8: "unsupported"}

_lib = ct.CDLL(daqp.__file__)
_p = ct.c_size_t  # every pointer, passed as an address


class _Problem(ct.Structure):  # DAQPProblem
    _fields_ = [("n", ct.c_int), ("m", ct.c_int), ("ms", ct.c_int), ("H", _p), ("f", _p), ("A", _p),
                ("bupper", _p), ("blower", _p), ("sense", _p), ("break_points", _p), ("nh", ct.c_int),
                ("problem_type", ct.c_int)]


class _Settings(ct.Structure):  # DAQPSettings
    _fields_ = [("primal_tol", ct.c_double), ("dual_tol", ct.c_double), ("zero_tol", ct.c_double),
                ("pivot_tol", ct.c_double), ("progress_tol", ct.c_double), ("cycle_tol", ct.c_int),
                ("iter_limit", ct.c_int), ("fval_bound", ct.c_double), ("eps_prox", ct.c_double),
                ("eta_prox", ct.c_double), ("rho_soft", ct.c_double), ("rel_subopt", ct.c_double),
                ("abs_subopt", ct.c_double), ("sing_tol", ct.c_double), ("refactor_tol", ct.c_double),
                ("time_limit", ct.c_double), ("w_soft", ct.c_double), ("eq_reduction", ct.c_int),
                ("presolve", ct.c_int)]


class _Result(ct.Structure):  # DAQPResult
    _fields_ = [("x", _p), ("lam", _p), ("fval", ct.c_double), ("soft_slack", ct.c_double),
                ("exitflag", ct.c_int), ("iter", ct.c_int), ("nodes", ct.c_int), ("solve_time", ct.c_double),
                ("setup_time", ct.c_double)]


class _Workspace(ct.Structure):  # DAQPWorkspace: filled by the library; declared for its size and offsets
    _fields_ = ([("qp", _p), ("n", ct.c_int), ("m", ct.c_int), ("ms", ct.c_int)]
                + [(k, _p) for k in "M dupper dlower Rinv v sense scaling RinvD x xold lam lam_star u".split()]
                + [("fval", ct.c_double)] + [(k, _p) for k in "L D xldl zldl".split()]
                + [("reuse_ind", ct.c_int), ("WS", _p), ("n_active", ct.c_int), ("iterations", ct.c_int),
                   ("sing_ind", ct.c_int), ("prox_mask", _p), ("n_prox", ct.c_int), ("soft_slack", ct.c_double),
                   ("settings", _p), ("bnb", _p), ("outer_iter", ct.c_int), ("hierarchy", _p), ("avi", _p),
                   ("eq", _p), ("timer", _p), ("Mu", _p), ("rho_ls", _p), ("rho_us", _p), ("w_ls", _p),
                   ("w_us", _p), ("state", ct.c_int)])


def _function(name: str, argtypes: list, restype):
    fn = getattr(_lib, name)
    fn.argtypes, fn.restype = argtypes, restype
    return fn


_default_settings = _function("daqp_default_settings", [_p], None)
_setup = _function("setup_daqp", [_p, _p, _p], ct.c_int)
_free_ldp = _function("free_daqp_ldp", [_p], None)
_free_workspace = _function("free_daqp_workspace", [_p], None)
_UPDATE_LDP = ct.cast(_function("daqp_update_ldp", [ct.c_int, _p, _p], ct.c_int), ct.c_void_p).value
_SOLVE = ct.cast(_function("daqp_solve", [_p, _p], None), ct.c_void_p).value

#: int32 index of the exit flag and of the iteration count in a result buffer
RESULT_EXITFLAG = _Result.exitflag.offset // 4
RESULT_ITER = _Result.iter.offset // 4
#: int32 index of the constraint count ``m`` in a problem buffer
PROBLEM_M = _Problem.m.offset // 4
#: the entries of ``DaqpBuffers.addr``
ADDR_WORK, ADDR_PROBLEM, ADDR_RESULT, ADDR_UPDATE_LDP, ADDR_SOLVE = range(5)


@intrinsic
def _call_update_ldp(typingctx, fn, mask, work, problem):
    """``int daqp_update_ldp(int mask, DAQPWorkspace*, DAQPProblem*)`` at address ``fn``."""
    sig = types.int32(types.uint64, types.int32, types.uint64, types.uint64)

    def codegen(context, builder, signature, args):
        fn_addr, mask_v, work_v, problem_v = args
        ptr = ir.IntType(8).as_pointer()
        fnty = ir.FunctionType(ir.IntType(32), [ir.IntType(32), ptr, ptr])
        callee = builder.inttoptr(fn_addr, fnty.as_pointer())
        return builder.call(callee, [mask_v, builder.inttoptr(work_v, ptr), builder.inttoptr(problem_v, ptr)])

    return sig, codegen


class DaqpBuffers(NamedTuple):
    """The arrays of one :class:`DaqpWorkspace` that compiled code writes and reads (DAQP keeps
    pointers to them, so they are updated in place, never replaced).

    Attributes:
        f: (n,) the cost's linear term ``−u_nom``.
        A: (rows, n) the general rows (zero rows are ignored by DAQP).
        lower: (n + rows,) lower bounds: the box's, then the rows' (``−INF``: unused).
        sense: (n + rows,) int32 constraint flags (0: an ordinary inequality).
        x: (n,) the solution.
        result: int32 view of the ``DAQPResult`` (exit flag at :data:`RESULT_EXITFLAG`).
        problem: int32 view of the ``DAQPProblem`` (its constraint count ``n + rows`` at
            :data:`PROBLEM_M`).
        levels: int32 DAQP's ``break_points`` (the workspace's ``break_points`` argument, which DAQP
            reads at every solve; (0,) for one level).
        addr: uint64 addresses: workspace, problem, result, ``daqp_update_ldp``, ``daqp_solve``.
    """

    f: np.ndarray
    A: np.ndarray
    lower: np.ndarray
    sense: np.ndarray
    x: np.ndarray
    result: np.ndarray
    problem: np.ndarray
    levels: np.ndarray
    addr: np.ndarray


def _buffer(struct_type) -> tuple[np.ndarray, ct.Structure]:
    buf = np.zeros((ct.sizeof(struct_type) + 7) // 8)
    return buf, struct_type.from_buffer(buf)


def _release(work_buf: np.ndarray, settings_buf: np.ndarray) -> None:
    """Free what ``setup_daqp`` allocated for the workspace in ``work_buf`` (its settings are
    ours, in ``settings_buf``: DAQP must not free them)."""
    work_buf.view(np.uint64)[_Workspace.settings.offset // 8] = 0
    address = work_buf.ctypes.data
    _free_ldp(address)
    _free_workspace(address)


class DaqpWorkspace:
    """A DAQP workspace for ``min ½‖u‖² + fᵀu`` with ``n`` simple bounds and up to ``rows`` rows.

    Set up once (``setup_daqp``; no allocation per solve); every solve then writes ``f``, the rows
    and their bounds into :attr:`buffers`, calls ``daqp_update_ldp`` and ``daqp_solve``. DAQP keeps
    the last working set, so consecutive solves start from it (warm start).

    Args:
        n: number of variables.
        rows: the largest number of rows.
        lo, hi: (n,) the box.
        break_points: None for one level; else DAQP's ``break_points`` (increasing, the last one
            ``n + rows``): level ``i`` holds the constraints from ``break_points[i-1]`` (0 for
            ``i = 0``) up to ``break_points[i]``, level 0 (the box, ``[n]`` first) is hard, and
            each further level is satisfied as well as the ones above it allow.

    Raises:
        RuntimeError: DAQP's setup failed, or the workspace it filled does not have the layout
            declared for daqp 0.11.0.
    """

    def __init__(self, n: int, rows: int, lo: np.ndarray, hi: np.ndarray, break_points=None) -> None:
        m = n + rows
        self.n, self.rows = n, rows
        self._H = np.eye(n)
        upper = np.full(m, INF)
        upper[:n] = hi
        lower = np.full(m, -INF)
        lower[:n] = lo
        self._upper = upper
        self._lam = np.zeros(m)
        self._break = None if break_points is None else np.ascontiguousarray(break_points, dtype=np.int32)
        self._prob_buf, prob = _buffer(_Problem)
        sense = np.zeros(m, np.int32)
        A = np.zeros((max(rows, 1), n))
        f, x = np.zeros(n), np.zeros(n)
        prob.n, prob.m, prob.ms = n, m, n
        prob.H, prob.f, prob.A = self._H.ctypes.data, f.ctypes.data, A.ctypes.data
        prob.bupper, prob.blower, prob.sense = upper.ctypes.data, lower.ctypes.data, sense.ctypes.data
        if self._break is not None and len(self._break) > 1:
            prob.break_points, prob.nh = self._break.ctypes.data, len(self._break)
        self._settings_buf, _ = _buffer(_Settings)
        _default_settings(self._settings_buf.ctypes.data)
        self._res_buf, res = _buffer(_Result)
        res.x, res.lam = x.ctypes.data, self._lam.ctypes.data
        self._work_buf = np.zeros((ct.sizeof(_Workspace) + 7) // 8)
        words = self._work_buf.view(np.uint64)
        words[_Workspace.settings.offset // 8] = self._settings_buf.ctypes.data  # ours, not DAQP's to free
        setup_time = np.zeros(1)
        flag = _setup(self._prob_buf.ctypes.data, self._work_buf.ctypes.data, setup_time.ctypes.data)
        if flag < 0:
            raise RuntimeError(f"DAQP's setup failed: exit flag {flag} ({EXIT_FLAGS.get(flag, 'unknown')})")
        ints = self._work_buf.view(np.int32)
        if ((ints[_Workspace.n.offset // 4], ints[_Workspace.m.offset // 4], ints[_Workspace.ms.offset // 4])
                != (n, m, n) or words[_Workspace.settings.offset // 8] != self._settings_buf.ctypes.data):
            raise RuntimeError("DAQP's workspace does not have the layout declared for daqp 0.11.0")
        weakref.finalize(self, _release, self._work_buf, self._settings_buf)
        addr = np.zeros(5, np.uint64)
        addr[ADDR_WORK], addr[ADDR_PROBLEM] = self._work_buf.ctypes.data, self._prob_buf.ctypes.data
        addr[ADDR_RESULT], addr[ADDR_UPDATE_LDP], addr[ADDR_SOLVE] = self._res_buf.ctypes.data, _UPDATE_LDP, _SOLVE
        levels = self._break if self._break is not None and len(self._break) > 1 else np.zeros(0, np.int32)
        self.buffers = DaqpBuffers(f, A, lower, sense, x, self._res_buf.view(np.int32), self._prob_buf.view(np.int32),
                                   levels, addr)

    def __getstate__(self):
        raise TypeError("a DaqpWorkspace holds C memory and cannot be pickled; build a new one")



@njit(**STEP_KERNEL_OPTIONS)
def daqp_call(buffers, mask):
    """``daqp_update_ldp(mask)`` then ``daqp_solve`` on the workspace of ``buffers``
    (:class:`DaqpBuffers`): returns ``(exit flag, iterations)``; a failed update's flag with 0."""
    addr = buffers.addr
    flag = _call_update_ldp(addr[ADDR_UPDATE_LDP], np.int32(mask), addr[ADDR_WORK], addr[ADDR_PROBLEM])
    if flag < 0:
        return flag, 0
    call_void(addr[ADDR_SOLVE], addr[ADDR_RESULT], addr[ADDR_WORK])  # daqp_solve(result, work)
    return buffers.result[RESULT_EXITFLAG], buffers.result[RESULT_ITER]


# ----------------------------------------------------------------------------- the filter's QP, compiled

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
            its own previous solve's working set: level 1's rows first, then level 2's (the
            barrier's), its problem and break points sized to the rows in use at every solve.
        capacity: int64 (2,) the row capacity of the two levels (0: the workspace has no such
            level).
        lo, hi: (n,) the box of ``u``.
        u: (n,) the solution.
        norm: (rows,) each row's norm ``‖A_k s‖`` (0: left out).
        residual: (rows,) each row's normalised residual ``â_k u − b̂_k`` at the solution (> −tol:
            held); for a zero row, ``−b_k``.
        cold: int64 (2,) 1: the next solve of ``plain`` (``cold[0]``) or ``hier`` (``cold[1]``)
            starts from an empty working set (then 0).
        last: int64 (1,) the previous call's status (:data:`SOLVED`, :data:`RELAXED`, ...).
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


@njit(**STEP_KERNEL_OPTIONS)
def _clear(buffers, start, stop):
    """Rows ``start`` … ``stop`` of a workspace become unused (zero, no bound)."""
    n = buffers.x.shape[0]
    for k in range(start, stop):
        for j in range(n):
            buffers.A[k, j] = 0.0
        buffers.lower[n + k] = -INF


@njit(**STEP_KERNEL_OPTIONS)
def solve_rows(tau_nom, A, b, scale, cols, n_obstacle_rows, stride, qp):
    """The filter's QP (module docstring) for the rows ``A[:, cols] τ ≥ b`` (``A`` (m, k), ``cols``
    (n,): the columns of the torque's dofs among ``A``'s ``k``) and nominal torque ``tau_nom``
    (n,), in ``u = τ / scale``; the solution goes to ``qp.u`` (:class:`QPBuffers`).

    1. Rows are scaled (``A_k s``) and normalised; a row shorter than :data:`ROW_NORM_MIN` cannot
       change with the torque: with ``b_k ≤ 0`` it holds, with ``b_k > 0`` it can never hold
       (``impossible``, its ``b_k``). Both are left out of the solves.
    2. All rows hard (``qp.plain``, its problem sized to the ``m`` rows: DAQP reads none past
       them), warm-started from its previous solve's working set. If DAQP finds the optimum and
       every row holds within :data:`ACTIVE_TOL`, that is the answer (:data:`SOLVED`).
    3. Otherwise, by priority (:data:`RELAXED`, ``qp.hier``): level 1 holds the rows that are not
       the barrier's (the guard's, the floor's, the joint limits'), level 2 the barrier's: rows
       ``k < n_obstacle_rows`` with ``k % stride == 0``; its problem too is sized to the rows in
       use. Warm-started from its own previous solve's working set, and once more from an empty
       one if that fails. If it fails too, ``u`` is the box projection of ``u_nom``
       (:data:`FAILED`).

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
    for j in range(n):
        u_nom = tau_nom[j] / scale[j]
        if not math.isfinite(u_nom):
            return BAD_NOMINAL, 0, 0, 0.0
        plain.f[j] = -u_nom
    impossible = 0.0
    for k in range(m):
        sq = 0.0
        for j in range(n):
            a = A[k, cols[j]] * scale[j]
            plain.A[k, j] = a
            sq += a * a
        norm = math.sqrt(sq)
        if not (math.isfinite(norm) and math.isfinite(b[k])):
            return BAD_ROWS, 0, 0, 0.0
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
    status = SOLVED
    iterations = 0
    by_priority = -1  # the prioritised solve's exit flag (-1: not run)
    if qp.last[0] != SOLVED and not qp.cold[0]:
        by_priority, iterations = _solve_by_priority(qp, m, n_obstacle_rows, stride)
        if by_priority >= 1 and _residuals(plain, qp, m) < -INFEASIBLE_TOL:
            status = RELAXED
    if status == SOLVED:
        mask = UPDATE_M | UPDATE_V | UPDATE_D
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
                    qp.u[j] = min(max(-plain.f[j], qp.lo[j]), qp.hi[j])
            _residuals(plain, qp, m)
        elif impossible > 0.0:
            status = RELAXED
    qp.last[0] = status
    n_active = 0
    slack = impossible
    for k in range(m):
        if qp.norm[k] == 0.0:
            qp.residual[k] = -b[k] if b[k] > 0.0 else 0.0
            continue
        if qp.residual[k] <= ACTIVE_TOL:
            n_active += 1
        if status != SOLVED:
            slack = max(slack, -qp.residual[k])
    return status, iterations, n_active, slack


@njit(**STEP_KERNEL_OPTIONS)
def _barrier_row(k, n_obstacle_rows, stride):
    """Whether row ``k`` is the barrier's, of priority 2 (:func:`solve_rows`, step 3)."""
    return k < n_obstacle_rows and k % stride == 0


@njit(**STEP_KERNEL_OPTIONS)
def _solve_by_priority(qp, m, n_obstacle_rows, stride):
    """Step 3 of :func:`solve_rows` on the rows ``qp.plain`` holds (scaled and normalised):
    returns ``(exit flag, iterations)``; on success (flag ≥ 1) ``qp.u`` is the answer, clipped
    to the box."""
    plain, hier = qp.plain, qp.hier
    n = plain.x.shape[0]
    # The problem is sized to the rows in use, level by level (DAQP reads its break_points, hier.levels,
    # at every solve): level 1's rows first, then level 2's. A level the workspace has keeps at least
    # one row, a zero one (which DAQP ignores) when it has none this call.
    count1 = count2 = 0
    for k in range(m):
        if qp.norm[k] != 0.0:
            if _barrier_row(k, n_obstacle_rows, stride):
                count2 += 1
            else:
                count1 += 1
    size1 = max(count1, 1) if qp.capacity[0] > 0 else 0
    size2 = max(count2, 1) if qp.capacity[1] > 0 else 0
    _clear(hier, count1, size1)
    _clear(hier, size1 + count2, size1 + size2)
    level, end = 1, n
    for size in (size1, size2):
        if size > 0:
            end += size
            hier.levels[level] = end
            level += 1
    hier.problem[PROBLEM_M] = end
    i1, i2 = 0, size1
    for k in range(m):
        if qp.norm[k] == 0.0:
            continue
        if _barrier_row(k, n_obstacle_rows, stride):
            i = i2
            i2 += 1
        else:
            i = i1
            i1 += 1
        for j in range(n):
            hier.A[i, j] = plain.A[k, j]
        hier.lower[n + i] = plain.lower[n + k]
    for j in range(n):
        hier.f[j] = plain.f[j]
    flag, iterations = 0, 0
    if not qp.cold[1]:
        flag, iterations = daqp_call(hier, UPDATE_M | UPDATE_V | UPDATE_D)
    if flag < 1:  # cold, or the warm start failed: again from an empty working set
        qp.cold[1] = 0
        for i in range(hier.sense.shape[0]):
            hier.sense[i] = 0
        flag, more = daqp_call(hier, UPDATE_M | UPDATE_V | UPDATE_D | UPDATE_SENSE)
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
