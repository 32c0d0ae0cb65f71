"""DAQP, the filter's QP solver, as compiled (numba) code reaches it: the binding to its C API and
the workspaces' setup, nothing of the filter's problem (which :mod:`c3bf_gym.safety._qp` states
and solves through :func:`daqp_call`).

DAQP (Arnström, Bemporad, Axehill, IEEE TAC 2022; ``pip install daqp``, MIT licence) is a dual
active-set solver for small dense QPs ``min ½ xᵀ H x + fᵀ x`` subject to bounds and general rows,
optionally in levels of priority (its hierarchical mode: each level is satisfied as well as the
levels above it allow).

How the C API is reached. The ``daqp`` wheel ships no separate library: its extension module
exports the C API's symbols (``setup_daqp``, ``daqp_update_ldp``, ``daqp_solve``, ...). ctypes
opens it to set workspaces up (:class:`DaqpWorkspace`, once per filter) and to read the addresses of
``daqp_update_ldp`` and ``daqp_solve``. The compiled code receives those addresses as data, in the
workspace's ``addr`` array, and calls them through :func:`_call_update_ldp` and
:func:`c3bf_gym._capi.call_void` (numba intrinsics that emit an indirect call). No address is compiled in, so numba caches the
calling code on disk like every other kernel.

What it relies on is what DAQP documents as its C interface: the structs ``DAQPProblem`` (the
problem, ``types.h``) and ``DAQPResult`` (``api.h``), declared here field for field (ctypes computes
the x86-64 padding; their memory is numpy buffers, so compiled code reads the result's exit flag
through an int32 view and writes the problem's constraint count through one), and the functions
of its workspace interface as its C documentation uses them: ``setup_daqp`` on a zeroed
``DAQPWorkspace``, ``daqp_update_ldp``, ``daqp_solve``, ``free_daqp_workspace`` and
``free_daqp_ldp``. Nothing reads or writes a field of the workspace, whose layout is DAQP's own:
the workspace is a zeroed buffer of :data:`WORKSPACE_BYTES` (twelve times ``sizeof`` in daqp
0.11.0), followed by :data:`GUARD_BYTES` more zeroed bytes that :class:`DaqpWorkspace` checks are
still zero after setup, so a DAQP whose workspace outgrew the buffer fails loudly instead of
running on memory it does not own. With no settings in the workspace, DAQP allocates its default
ones (``daqp_default_settings``, all the filter uses) and frees them with the workspace.

A DAQP whose structs or calls no longer mean what they meant is caught at import: the module
solves two small QPs through this binding (bounds and general rows on a workspace sized for more
rows than it is given; and two levels of priority that conflict; each also with a dense ``H``
written into the warm workspace) and compares them with
``daqp.solve``, DAQP's documented Python interface, on the same problems. A difference raises
``ImportError`` naming the installed daqp and what differed. (A change of ``DAQPProblem`` or
``DAQPResult`` themselves can crash that check instead: the layouts are what C code compiled
against the headers relies on too.)
"""

from __future__ import annotations

import ctypes as ct
import weakref
from importlib.metadata import PackageNotFoundError, version
from typing import NamedTuple

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

from c3bf_gym._compile_cache import STEP_KERNEL_OPTIONS  # (before any @njit(cache=True): the cache keys)
from c3bf_gym._capi import call_void

__all__ = ["DAQP_VERSION", "DaqpBuffers", "DaqpWorkspace", "EXIT_FLAGS", "daqp_call"]

try:
    #: the installed daqp's version (the binding checks itself against it at import, below)
    DAQP_VERSION = version("daqp")
except PackageNotFoundError as error:  # pragma: no cover - a declared dependency
    raise ImportError("the filter's QP solver needs daqp: pip install 'daqp>=0.11.0'") from error
import daqp  # noqa: E402

#: DAQP's "no bound" (constants.h)
INF = 1e30
#: ``daqp_update_ldp``'s mask bits (constants.h): the cost's ``H`` (refactored), the rows, the cost's
#: linear term, the bounds, the constraint flags
UPDATE_RINV, UPDATE_M, UPDATE_V, UPDATE_D, UPDATE_SENSE = 1, 2, 4, 8, 16
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


class _Result(ct.Structure):  # DAQPResult
    _fields_ = [("x", _p), ("lam", _p), ("fval", ct.c_double), ("soft_slack", ct.c_double),
                ("exitflag", ct.c_int), ("iter", ct.c_int), ("nodes", ct.c_int), ("solve_time", ct.c_double),
                ("setup_time", ct.c_double)]


#: bytes of zeroed memory each workspace gets (``DAQPWorkspace`` is 328 in daqp 0.11.0; its layout
#: is DAQP's own, so none of its fields is read here)
WORKSPACE_BYTES = 4096
#: zeroed bytes after it that must still be zero after setup: a larger workspace, whose fields there
#: DAQP reads as NULL and then sets, fails loudly
GUARD_BYTES = 1024


def _function(name: str, argtypes: list, restype):
    fn = getattr(_lib, name)
    fn.argtypes, fn.restype = argtypes, restype
    return fn


_setup = _function("setup_daqp", [_p, _p, _p], ct.c_int)
_free_ldp = _function("free_daqp_ldp", [_p], None)
_free_workspace = _function("free_daqp_workspace", [_p], None)
_update_ldp = _function("daqp_update_ldp", [ct.c_int, _p, _p], ct.c_int)
_solve = _function("daqp_solve", [_p, _p], None)
_UPDATE_LDP = ct.cast(_update_ldp, ct.c_void_p).value
_SOLVE = ct.cast(_solve, ct.c_void_p).value

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
        H: (n, n) the cost's Hessian, the identity unless the caller writes another (symmetric,
            positive definite) and passes :data:`UPDATE_RINV`, which refactors it.
        f: (n,) the cost's linear term (``−H u_nom``).
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

    H: np.ndarray
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


def _release(work_buf: np.ndarray) -> None:
    """Free what ``setup_daqp`` allocated for the workspace in ``work_buf``, its settings included,
    in the order of DAQP's documentation (each call frees only what is still allocated and clears
    its pointers, so nothing is freed twice)."""
    address = work_buf.ctypes.data
    _free_workspace(address)
    _free_ldp(address)


class DaqpWorkspace:
    """A DAQP workspace for ``min ½ uᵀHu + fᵀu`` with ``n`` simple bounds and up to ``rows`` rows,
    ``H`` the identity until the caller writes another.

    Set up once (``setup_daqp``; no allocation per solve: DAQP allocates its factor of ``H`` dense
    whatever ``H`` is, so a new ``H`` needs no new workspace); every solve then writes ``f`` (and
    ``H``, when it changes), the rows and their bounds into :attr:`buffers`, calls
    ``daqp_update_ldp`` and ``daqp_solve``. DAQP keeps the last working set, so consecutive solves
    start from it (warm start).

    Args:
        n: number of variables.
        rows: the largest number of rows.
        lo, hi: (n,) the box.
        break_points: None for one level; else DAQP's ``break_points`` (increasing, the last one
            ``n + rows``): level ``i`` holds the constraints from ``break_points[i-1]`` (0 for
            ``i = 0``) up to ``break_points[i]``, level 0 (the box, ``[n]`` first) is hard, and
            each further level is satisfied as well as the ones above it allow.

    Raises:
        RuntimeError: DAQP's setup failed (nothing is left allocated then), or it wrote past the
            :data:`WORKSPACE_BYTES` reserved for its workspace (what it allocated is not freed:
            the workspace cannot be trusted).
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
        self._res_buf, res = _buffer(_Result)
        res.x, res.lam = x.ctypes.data, self._lam.ctypes.data
        # zeroed (no settings: DAQP allocates its defaults), the guard too
        self._work_buf = np.zeros((WORKSPACE_BYTES + GUARD_BYTES) // 8)
        setup_time = np.zeros(1)
        flag = _setup(self._prob_buf.ctypes.data, self._work_buf.ctypes.data, setup_time.ctypes.data)
        if flag < 0:
            raise RuntimeError(f"DAQP's setup failed: exit flag {flag} ({EXIT_FLAGS.get(flag, 'unknown')})")
        self.check_guard()
        weakref.finalize(self, _release, self._work_buf)
        addr = np.zeros(5, np.uint64)
        addr[ADDR_WORK], addr[ADDR_PROBLEM] = self._work_buf.ctypes.data, self._prob_buf.ctypes.data
        addr[ADDR_RESULT], addr[ADDR_UPDATE_LDP], addr[ADDR_SOLVE] = self._res_buf.ctypes.data, _UPDATE_LDP, _SOLVE
        levels = self._break if self._break is not None and len(self._break) > 1 else np.zeros(0, np.int32)
        self.buffers = DaqpBuffers(self._H, f, A, lower, sense, x, self._res_buf.view(np.int32), self._prob_buf.view(np.int32),
                                   levels, addr)

    def check_guard(self) -> None:
        """Raises RuntimeError if DAQP wrote past the :data:`WORKSPACE_BYTES` reserved for its
        workspace."""
        if np.any(self._work_buf.view(np.uint8)[WORKSPACE_BYTES:]):
            raise RuntimeError(f"daqp {DAQP_VERSION} wrote past the {WORKSPACE_BYTES} bytes c3bf_gym reserves for its "
                               "workspace (DAQPWorkspace grew): raise WORKSPACE_BYTES in c3bf_gym/safety/_daqp.py")

    def __getstate__(self):
        raise TypeError("a DaqpWorkspace holds C memory and cannot be pickled; build a new one")


def _call_from_python(buffers: DaqpBuffers, mask: int) -> int:
    """What :func:`daqp_call` does, through ctypes: the exit flag."""
    addr = [int(a) for a in buffers.addr]
    flag = _update_ldp(mask, addr[ADDR_WORK], addr[ADDR_PROBLEM])
    if flag < 0:
        return flag
    _solve(addr[ADDR_RESULT], addr[ADDR_WORK])
    return int(buffers.result[RESULT_EXITFLAG])


def _self_check() -> None:
    """Raises ImportError unless the binding gives what ``daqp.solve`` gives (exit flag, and the
    solution within 1e-9) on: bounds and two general rows on a workspace with room for three (the
    problem's constraint count set as the filter sets it), cold and then warm-started with a new
    cost, then with a dense ``H`` written into the workspace (:data:`UPDATE_RINV`); and a box with
    two levels of rows that conflict (``break_points``), the second solve with a dense ``H``. The
    workspaces are built and freed as the filter's are."""
    n = 3
    lo, hi = np.full(n, -1.0), np.full(n, 1.0)
    dense = np.array([[2.0, 0.6, -0.3], [0.6, 1.5, 0.4], [-0.3, 0.4, 1.2]])  # symmetric positive definite
    cases = [  # (rows capacity, break points, rows, lower bounds of the rows, nominal torques, their H)
        (3, None, [[1.0, 1.0, 0.0], [0.0, 1.0, -1.0]], [0.8, 0.2], [[2.0, -0.5, 0.3], [-0.4, 0.9, 0.1],
                                                                   [0.5, 0.9, -0.8]], [None, None, dense]),
        (2, [n, n + 1, n + 2], [[1.0, 1.0, 0.0], [-1.0, -1.0, 0.0]], [1.5, -0.5], [[0.2, -0.7, 0.5]] * 2,
         [None, dense]),
    ]
    for capacity, levels, rows, bounds, nominals, hessians in cases:
        work = DaqpWorkspace(n, capacity, lo, hi, break_points=levels)
        buffers, r = work.buffers, len(rows)
        buffers.A[:r] = rows
        buffers.lower[n:n + r] = bounds
        buffers.problem[PROBLEM_M] = n + r
        mask = UPDATE_M | UPDATE_V | UPDATE_D | UPDATE_SENSE
        for nominal, hessian in zip(nominals, hessians):
            H = np.eye(n) if hessian is None else hessian
            buffers.f[:] = -np.asarray(nominal)
            if hessian is not None:
                buffers.H[:] = hessian
            flag = _call_from_python(buffers, mask | (UPDATE_RINV if hessian is not None else 0))
            mask = UPDATE_M | UPDATE_V | UPDATE_D  # then warm-started
            work.check_guard()
            x, _, expected, _ = daqp.solve(
                H, buffers.f.copy(), np.array(rows), np.concatenate([hi, np.full(r, INF)]),
                np.concatenate([lo, bounds]), np.zeros(n + r, np.intc),
                break_points=np.zeros(0, np.intc) if levels is None else np.array(levels, np.intc))
            what = f"{'two levels' if levels else 'one level'}, nominal {nominal}, H {H.tolist()}"
            if flag != expected or not np.allclose(buffers.x, x, rtol=0.0, atol=1e-9):
                raise ImportError(
                    f"c3bf_gym's binding of DAQP's C API disagrees with daqp.solve on daqp {DAQP_VERSION} ({what}): "
                    f"exit flag {flag} vs {expected}, x {buffers.x.tolist()} vs {x.tolist()}; "
                    "c3bf_gym/safety/_daqp.py needs updating for this daqp")
        del work


try:
    _self_check()
except RuntimeError as error:  # DAQP's setup failed or wrote past its workspace
    raise ImportError(f"c3bf_gym's binding of DAQP's C API fails its check on daqp {DAQP_VERSION}: {error}") from error


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
