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

The structs are declared after ``csrc/include/types.h`` and ``api.h`` of the daqp **0.11.0**
sources (field order and C types; ctypes computes the x86-64 padding); their memory is numpy
buffers, so compiled code reads the result's exit flag through an int32 view. The layout is not an
ABI DAQP promises: importing this module with another daqp version raises ``ImportError``, and
:class:`DaqpWorkspace` checks the workspace fields it can see after setup.
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
