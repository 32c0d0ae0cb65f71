"""The filter's QP with DAQP and priority levels (``FilterConfig(solver="daqp")``).

Problem, in the scaled torque ``u = τ / s`` (``s``: the controller's scale, so the box is
``u_min ≤ u ≤ u_max``)::

    minimise    ½ ‖u − u_nom‖²
    subject to  Â u ≥ b̂        (rows divided by their norms ‖A_k s‖: residuals in N·m)
                u_min ≤ u ≤ u_max

solved by DAQP, a dual active-set solver for small dense QPs (``daqp.solve``). When no ``u`` in
the box satisfies every row (DAQP's exit flag −1), the rows are solved by priority instead of by
weights: DAQP's hierarchical mode (``break_points``) satisfies each level as well as the levels
above it allow, in the least-squares sense of its rows' violations, and only then minimises the
cost. The levels:

0. the torque box: hard;
1. rows of priority 1: the joint position and speed limits, the floor and the distance guard;
2. rows of priority 2: the barrier's (the C3BF's) rows, which give way first.

So the joint-speed bound holds whenever some torque within the limits can hold it together with
the floor and the guard. Rows whose normalised coefficients are all zero cannot change with the
torque: those with ``b̂ ≤ 0`` hold and are left out; those with ``b̂ > 0`` can never hold (a link
the joints cannot move, headed for by an obstacle) and are left out of the solve, their violation
counted in ``slack``. The result is a :class:`~c3bf_gym.qp.QPResult` like
:class:`~c3bf_gym.qp.TorqueQP`'s: status ``"solved"``, ``"relaxed"`` (by priority; ``slack`` the
largest normalised violation) or ``"failed"`` (DAQP found no solution even by priority; the
torque is the box projection of the nominal one, reported infeasible, never silently).
"""

from __future__ import annotations

import time

import numpy as np

from c3bf_gym.qp import QPResult

__all__ = ["PriorityQP"]

_INF = 1e30  # DAQP's "no bound"
_ROW_NORM_MIN = 1e-12
_ACTIVE_TOL = 1e-6  # [N m, normalised]: a row within this of its bound counts as active


class PriorityQP:
    """DAQP on the filter's rows, by priority when they conflict (module docstring).

    Args:
        n: number of joints.
        tau_min, tau_max: (n,) box of the scaled torque.

    Raises:
        ModuleNotFoundError: without the ``daqp`` package (``pip install "c3bf-gym[daqp]"``).
    """

    solver = "daqp"

    def __init__(self, n: int, tau_min: np.ndarray, tau_max: np.ndarray) -> None:
        try:
            import daqp
        except ModuleNotFoundError as error:
            raise ModuleNotFoundError("solver='daqp' needs the daqp package: pip install 'c3bf-gym[daqp]'") from error
        self._solve = daqp.solve
        self.n = int(n)
        self.tau_min = np.array(tau_min, dtype=np.float64)
        self.tau_max = np.array(tau_max, dtype=np.float64)
        self._H = np.eye(self.n)
        self._tau = np.zeros(self.n)

    def solve_scaled(self, tau_nom: np.ndarray, A: np.ndarray, b: np.ndarray, scale: np.ndarray,
                     weights: np.ndarray | None = None, levels: np.ndarray | None = None) -> QPResult:
        """Solve for ``u`` with rows ``(A s) u ≥ b``; ``tau_nom`` in torque units, ``levels`` (m,)
        each row's priority (1 or 2; None: all 1). ``weights`` is accepted for the caller's
        interface and unused: priorities replace weights. Returns a :class:`QPResult` whose
        ``tau`` is ``u`` (a view of a buffer the next call overwrites)."""
        start = time.perf_counter()
        u_nom = np.asarray(tau_nom, dtype=np.float64) / scale
        if not np.all(np.isfinite(u_nom)):
            raise ValueError("tau_nom contains NaN or inf")
        rows = A * scale
        if not (np.all(np.isfinite(rows)) and np.all(np.isfinite(b))):
            raise ValueError("A or b contains NaN or inf")
        norm = np.linalg.norm(rows, axis=1)
        live = norm >= _ROW_NORM_MIN
        rows = rows[live] / norm[live, None]
        bounds = b[live] / norm[live]
        dead = b[~live]
        impossible = float(dead.max(initial=0.0))  # rows no torque can change, violated by b
        level = np.ones(len(bounds), dtype=int) if levels is None else np.asarray(levels)[live]
        n, m = self.n, len(bounds)
        upper = np.concatenate([self.tau_max, np.full(m, _INF)])
        lower = np.concatenate([self.tau_min, bounds])
        sense = np.zeros(n + m, dtype=np.intc)
        u, _, flag, info = self._solve(self._H, -u_nom, rows, upper, lower, sense)
        iterations = int(info.get("iterations", 0)) if isinstance(info, dict) else 0
        feasible = flag == 1 and impossible <= 0.0
        status = "solved"
        if flag != 1:
            order = np.concatenate([np.flatnonzero(level == 1), np.flatnonzero(level != 1)])
            first = int(np.count_nonzero(level == 1))
            points = [n] + ([n + first] if 0 < first < m else []) + [n + m]
            u, _, flag, info = self._solve(self._H, -u_nom, np.ascontiguousarray(rows[order]), upper[np.r_[:n, n + order]],
                                           lower[np.r_[:n, n + order]], sense, break_points=np.array(points, np.intc))  # fmt: skip
            iterations += int(info.get("iterations", 0)) if isinstance(info, dict) else 0
            status = "relaxed" if flag >= 1 else "failed"
            if flag < 1:
                u = u_nom
        elif impossible > 0.0:
            status = "relaxed"
        np.clip(u, self.tau_min, self.tau_max, out=self._tau)
        residual = rows @ self._tau - bounds
        slack = 0.0 if feasible else max(impossible, float(-residual.min(initial=0.0)))
        active = int(np.count_nonzero(residual <= _ACTIVE_TOL))
        return QPResult(self._tau, slack, feasible, status, iterations, active, time.perf_counter() - start)
