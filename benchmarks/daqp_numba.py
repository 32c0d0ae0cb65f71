"""DAQP's C API called from numba nopython code (evaluation prototype, see docs/qp_solver_evaluation.md).

The ``daqp`` wheel (PyPI, 0.11.0) ships no separate shared library and no headers: its Cython
extension module ``daqp.cpython-*.so`` exports the C API's symbols (``setup_daqp``,
``daqp_update_ldp``, ``daqp_solve``, ``daqp_default_settings``, ...) as ordinary dynamic symbols.
``ctypes.CDLL(daqp.__file__)`` opens it; numba's nopython mode calls ctypes function objects
directly (the function's address is baked into the compiled code). The structs are declared below
with ``ctypes.Structure`` after ``csrc/include/types.h`` and ``api.h`` of the daqp 0.11.0 sdist
(field order and C types only; ctypes computes the x86-64 padding). Their memory lives in numpy
buffers so the compiled code reads the result fields through plain array views. Every pointer is
passed as ``c_size_t`` (an integer in the same register as a pointer on x86-64 SysV), so numba needs
no pointer types.

One :class:`DaqpWorkspace` holds a workspace set up once for the largest row count (``n`` simple
bounds, ``max_rows`` general rows; unused rows are zero rows, which DAQP ignores until they become
nonzero). A call writes the linear term, rows and bounds into the problem's arrays, then calls
``daqp_update_ldp(M|v|d)`` and ``daqp_solve``: the working set of the previous solve (the ACTIVE
bits DAQP keeps in ``work->sense``) is refactorised and used as the start (warm start); no memory
is allocated per call. The version is checked at import: the layout is only known for 0.11.0.
"""

from __future__ import annotations

import ctypes as ct
from importlib.metadata import version

import daqp
import numba
import numpy as np

DAQP_VERSION = version("daqp")
if DAQP_VERSION != "0.11.0":
    raise ImportError(f"struct layouts are declared for daqp 0.11.0, installed: {DAQP_VERSION}")

LIB_PATH = daqp.__file__
_lib = ct.CDLL(LIB_PATH)

# constants (constants.h)
INF = 1e30
SOFT = 8
UPDATE_M, UPDATE_V, UPDATE_D, UPDATE_SENSE = 2, 4, 8, 16
EXIT = {5: "feasible", 4: "optimal_inexact", 3: "constrained_point", 2: "soft_optimal", 1: "optimal",
        -1: "infeasible", -2: "cycle", -3: "unbounded", -4: "iterlimit", -5: "nonconvex",
        -6: "overdetermined_initial", -7: "timelimit", -8: "unsupported"}

_p = ct.c_size_t  # every pointer


class Problem(ct.Structure):  # DAQPProblem
    _fields_ = [("n", ct.c_int), ("m", ct.c_int), ("ms", ct.c_int), ("H", _p), ("f", _p), ("A", _p),
                ("bupper", _p), ("blower", _p), ("sense", _p), ("break_points", _p), ("nh", ct.c_int),
                ("problem_type", ct.c_int)]


class Settings(ct.Structure):  # DAQPSettings (0.11.0: w_soft, eq_reduction, presolve at the end)
    _fields_ = [("primal_tol", ct.c_double), ("dual_tol", ct.c_double), ("zero_tol", ct.c_double),
                ("pivot_tol", ct.c_double), ("progress_tol", ct.c_double), ("cycle_tol", ct.c_int),
                ("iter_limit", ct.c_int), ("fval_bound", ct.c_double), ("eps_prox", ct.c_double),
                ("eta_prox", ct.c_double), ("rho_soft", ct.c_double), ("rel_subopt", ct.c_double),
                ("abs_subopt", ct.c_double), ("sing_tol", ct.c_double), ("refactor_tol", ct.c_double),
                ("time_limit", ct.c_double), ("w_soft", ct.c_double), ("eq_reduction", ct.c_int),
                ("presolve", ct.c_int)]


class Result(ct.Structure):  # DAQPResult
    _fields_ = [("x", _p), ("lam", _p), ("fval", ct.c_double), ("soft_slack", ct.c_double),
                ("exitflag", ct.c_int), ("iter", ct.c_int), ("nodes", ct.c_int), ("solve_time", ct.c_double),
                ("setup_time", ct.c_double)]


class Workspace(ct.Structure):  # DAQPWorkspace (0.11.0): the library fills it; declared for its size and offsets
    _fields_ = ([("qp", _p), ("n", ct.c_int), ("m", ct.c_int), ("ms", ct.c_int)]
                + [(k, _p) for k in "M dupper dlower Rinv v sense scaling RinvD x xold lam lam_star u".split()]
                + [("fval", ct.c_double)] + [(k, _p) for k in "L D xldl zldl".split()]
                + [("reuse_ind", ct.c_int), ("WS", _p), ("n_active", ct.c_int), ("iterations", ct.c_int),
                   ("sing_ind", ct.c_int), ("prox_mask", _p), ("n_prox", ct.c_int), ("soft_slack", ct.c_double),
                   ("settings", _p), ("bnb", _p), ("outer_iter", ct.c_int), ("hierarchy", _p), ("avi", _p),
                   ("eq", _p), ("timer", _p), ("Mu", _p), ("rho_ls", _p), ("rho_us", _p), ("w_ls", _p),
                   ("w_us", _p), ("state", ct.c_int)])


_WORK_BYTES = ct.sizeof(Workspace)
_WORK_SETTINGS_OFFSET = Workspace.settings.offset

_default_settings = _lib.daqp_default_settings
_default_settings.argtypes, _default_settings.restype = [_p], None
_setup = _lib.setup_daqp
_setup.argtypes, _setup.restype = [_p, _p, _p], ct.c_int
update_ldp = _lib.daqp_update_ldp
update_ldp.argtypes, update_ldp.restype = [ct.c_int, _p, _p], ct.c_int
daqp_solve = _lib.daqp_solve
daqp_solve.argtypes, daqp_solve.restype = [_p, _p], None

_RES_EXIT = Result.exitflag.offset // 4   # int32 index of exitflag in the result buffer
_RES_ITER = Result.iter.offset // 4
_RES_SOFT = Result.soft_slack.offset // 8  # float64 index


def _buffer(struct_type) -> tuple[np.ndarray, ct.Structure]:
    buf = np.zeros((ct.sizeof(struct_type) + 7) // 8)
    return buf, struct_type.from_buffer(buf)


class DaqpWorkspace:
    """A DAQP workspace for ``min ½‖u‖² + fᵀu  s.t.  lo ≤ u ≤ hi, A u ≥ b`` with up to ``max_rows`` rows."""

    def __init__(self, n: int, max_rows: int, lo, hi, settings: dict | None = None) -> None:
        m = n + max_rows
        self.n, self.max_rows = n, max_rows
        self.H = np.eye(n)
        self.f = np.zeros(n)
        self.A = np.zeros((max_rows, n))
        self.bu = np.full(m, INF)
        self.bl = np.full(m, -INF)
        self.bu[:n], self.bl[:n] = hi, lo
        self.sense = np.zeros(m, np.int32)
        self.x = np.zeros(n)
        self.lam = np.zeros(m)
        self.prob_buf, prob = _buffer(Problem)
        prob.n, prob.m, prob.ms = n, m, n
        prob.H, prob.f, prob.A = self.H.ctypes.data, self.f.ctypes.data, self.A.ctypes.data
        prob.bupper, prob.blower, prob.sense = self.bu.ctypes.data, self.bl.ctypes.data, self.sense.ctypes.data
        self.set_buf, st = _buffer(Settings)
        _default_settings(self.set_buf.ctypes.data)
        for k, v in (settings or {}).items():
            setattr(st, k, v)
        self.settings = st
        self.res_buf, res = _buffer(Result)
        res.x, res.lam = self.x.ctypes.data, self.lam.ctypes.data
        self.work_buf = np.zeros(_WORK_BYTES // 8)
        ws = self.work_buf.view(np.uint64)
        ws[_WORK_SETTINGS_OFFSET // 8] = self.set_buf.ctypes.data  # our settings (not owned by DAQP)
        t = np.zeros(1)
        flag = _setup(self.prob_buf.ctypes.data, self.work_buf.ctypes.data, t.ctypes.data)
        if flag < 0:
            raise RuntimeError(f"setup_daqp failed: {flag}")
        # layout check: the workspace's n, m, ms (ints after the qp pointer) and settings pointer
        wi = self.work_buf.view(np.int32)
        if (wi[2], wi[3], wi[4]) != (n, m, n) or ws[_WORK_SETTINGS_OFFSET // 8] != self.set_buf.ctypes.data:
            raise RuntimeError("DAQPWorkspace layout differs from the one assumed")
        self.setup_time = float(t[0])
        self.addr = np.array([self.work_buf.ctypes.data, self.prob_buf.ctypes.data, self.res_buf.ctypes.data],
                             np.uint64)
        self.m_prev = np.zeros(1, np.int64)

    def args(self) -> tuple:
        """The arguments of :func:`solve` after the call data."""
        return (self.f, self.A, self.bl, self.x, self.res_buf.view(np.int32), self.m_prev, self.addr)


@numba.njit(nogil=True)  # not cacheable: the ctypes functions are compiled in as addresses
def solve(tau_nom, A, b, scale, m, f, Aw, bl, x, res_i32, m_prev, addr):
    """One call in u = τ / scale: rows (A diag(scale)) u ≥ b (the first m rows of A, b), cost
    ½‖u − τ_nom / scale‖². Writes u into x; returns (exitflag, iterations). Rows from m to the
    previous call's count are zeroed (DAQP ignores zero rows)."""
    n = tau_nom.shape[0]
    for j in range(n):
        f[j] = -tau_nom[j] / scale[j]
    for k in range(m):
        for j in range(n):
            Aw[k, j] = A[k, j] * scale[j]
        bl[n + k] = b[k]
    for k in range(m, m_prev[0]):
        for j in range(n):
            Aw[k, j] = 0.0
        bl[n + k] = -1e30
    m_prev[0] = m
    flag = update_ldp(UPDATE_M | UPDATE_V | UPDATE_D, addr[0], addr[1])
    if flag < 0:
        return flag, 0
    daqp_solve(addr[2], addr[0])
    return res_i32[_RES_EXIT], res_i32[_RES_ITER]


def _selftest() -> None:
    rng = np.random.default_rng(1)
    n, M = 6, 10
    ws = DaqpWorkspace(n, M, -np.ones(n), np.ones(n))
    for _ in range(5):
        m = int(rng.integers(0, M + 1))
        A = rng.normal(size=(m, n))
        b = rng.normal(size=m) - 1.0
        u_nom = rng.normal(size=n) * 2
        scale = np.ones(n)
        flag, it = solve(u_nom, A, b, scale, m, *ws.args())
        xr, _, fr, _ = daqp.solve(np.eye(n), -u_nom, A, np.r_[np.ones(n), np.full(m, INF)],
                                  np.r_[-np.ones(n), b], np.zeros(n + m, np.intc))
        print(m, flag, it, fr, float(np.abs(ws.x - xr).max()) if flag > 0 else None)


if __name__ == "__main__":
    _selftest()
