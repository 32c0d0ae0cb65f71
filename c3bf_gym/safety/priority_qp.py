"""The filter's QP: the torque closest to the nominal one that keeps every safety row, by priority.

In the scaled torque ``u = τ / s`` (``s`` the controller's scale, so the box is
``u_min ≤ u ≤ u_max``)::

    minimise    ½ ‖u − u_nom‖²
    subject to  â_k u ≥ b̂_k   (the rows A_k s u ≥ b_k divided by ‖A_k s‖: residuals in N·m)
                u_min ≤ u ≤ u_max

solved by DAQP (:mod:`c3bf_gym.safety._daqp`), a dual active-set solver for small dense QPs, from
compiled code. When no ``u`` in the box satisfies every row, the rows give way **by priority,
not by weights**: DAQP's hierarchical mode satisfies each level as well as the levels above it
allow (least squares of the level's violations), and only then minimises the cost. The levels:

0. the torque box: hard;
1. the joint position and speed limits, the floor and the distance guard;
2. the barrier's rows beside a guard (the C3BF's in the default filter), which give way first.

So with a guard the joint-speed bound holds whenever some torque within the limits can hold it
together with the floor and the guard. A filter without a guard has no level 2: its barrier's
rows are the only ones keeping obstacles off, so they share level 1 with the joint limits and the
floor, and a conflict spreads over all of them (least squares of the normalised violations). Rows whose scaled coefficients are all (numerically) zero cannot change
with the torque: with ``b_k ≤ 0`` they hold; with ``b_k > 0`` (a link the joints cannot move,
headed for by an obstacle) they can never hold, and are left out of the solve with their ``b_k``
counted in ``slack``.
"""

from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np

from c3bf_gym.safety import _daqp

__all__ = ["PriorityQP", "QPResult"]

#: :attr:`QPResult.status` by :func:`c3bf_gym.safety._daqp.solve_rows` outcome
STATUS = {_daqp.SOLVED: "solved", _daqp.RELAXED: "relaxed", _daqp.FAILED: "failed"}


class QPResult(NamedTuple):
    """One solve of :class:`PriorityQP`.

    Attributes:
        tau: (n,) the solution ``u`` (a view of a buffer the next solve overwrites; copy it to
            keep it), inside the box exactly.
        slack: 0.0 when every row holds; otherwise the largest row-normalised violation
            ``max_k (b̂_k − â_k u)`` [N·m], or a row no torque can change's ``b_k`` if larger.
        feasible: every row holds (status ``"solved"``).
        status: ``"solved"``; ``"relaxed"`` (rows gave way by priority); ``"failed"`` (DAQP
            found no solution even by priority: ``tau`` is the box projection of the nominal
            torque, never hidden: reported like any infeasible step).
        iterations: DAQP's active-set iterations, both solves together.
        active_rows: rows within 1e-6 of their bound (or violated).
        solve_time: wall time of the call [s].
    """

    tau: np.ndarray
    slack: float
    feasible: bool
    status: str
    iterations: int
    active_rows: int
    solve_time: float


class PriorityQP:
    """The filter's QP (module docstring) on DAQP, with workspaces set up once.

    Args:
        n: number of joints.
        tau_min, tau_max: (n,) box of the scaled torque ``u``.
        level1_rows: the largest number of priority-1 rows (guard, floor, joint limits).
        level2_rows: the largest number of priority-2 rows (the barrier's).

    Which row is which is given per solve: of the rows, those with index ``k <
    n_obstacle_rows`` and ``k % stride == 0`` are the barrier's (``stride`` 2 when each barrier
    row is followed by its guard's, else 1); every other row is priority 1.
    """

    def __init__(self, n: int, tau_min: np.ndarray, tau_max: np.ndarray, level1_rows: int, level2_rows: int) -> None:
        self.n = int(n)
        self._cols = np.arange(self.n, dtype=np.int64)  # the rows' columns are the torque's, in order
        self.tau_min = np.array(tau_min, dtype=np.float64)
        self.tau_max = np.array(tau_max, dtype=np.float64)
        self._levels = (int(level1_rows), int(level2_rows))
        rows = sum(self._levels)
        points = [n] + [n + level1_rows] * (level1_rows > 0) + [n + rows] * (level2_rows > 0)
        self._plain = _daqp.DaqpWorkspace(n, rows, self.tau_min, self.tau_max)
        self._hier = _daqp.DaqpWorkspace(n, rows, self.tau_min, self.tau_max, break_points=points)
        self.max_rows = rows
        self.buffers = _daqp.QPBuffers(self._plain.buffers, self._hier.buffers,
                                       np.array([level1_rows, level2_rows], np.int64), self.tau_min, self.tau_max,
                                       np.zeros(n), np.zeros(max(rows, 1)), np.zeros(max(rows, 1)),
                                       np.ones(2, np.int64), np.zeros(1, np.int64))

    def reset(self) -> None:
        """Forget the warm start: the next solve starts from an empty working set, so a sequence
        of solves after a reset gives the same answers, bit for bit, whatever came before."""
        self.buffers.cold[:] = 1
        self.buffers.last[0] = _daqp.SOLVED

    def __reduce__(self):
        """Pickled as its arguments: the copy sets up its own DAQP workspaces (cold)."""
        return PriorityQP, (self.n, self.tau_min, self.tau_max, *self._levels)

    def solve_scaled(self, tau_nom: np.ndarray, A: np.ndarray, b: np.ndarray, scale: np.ndarray,
                     n_obstacle_rows: int | None = None, stride: int = 1) -> QPResult:
        """Solve for ``u`` with rows ``(A s) u ≥ b``; ``tau_nom`` in torque units.

        Args:
            tau_nom: (n,) nominal torque [N·m].
            A, b: (m, n), (m,) the rows, ``m ≤`` the capacity.
            scale: (n,) ``s``.
            n_obstacle_rows, stride: which rows are the barrier's (class docstring); None: all m
                rows.

        Raises:
            ValueError: wrong shapes, more rows than the capacity, NaN or inf in the input.
        """
        start = time.perf_counter()
        tau_nom = np.ascontiguousarray(tau_nom, dtype=np.float64)
        A = np.ascontiguousarray(A, dtype=np.float64)
        b = np.ascontiguousarray(b, dtype=np.float64)
        scale = np.ascontiguousarray(scale, dtype=np.float64)
        m = len(b)
        if tau_nom.shape != (self.n,) or scale.shape != (self.n,) or A.shape != (m, self.n):
            raise ValueError(f"expected tau_nom and scale of shape ({self.n},) and A of shape (m, {self.n}) with "
                             f"b (m,); got {tau_nom.shape}, {scale.shape}, {A.shape}, {b.shape}")
        if m > self.max_rows:
            raise ValueError(f"{m} rows exceed the {self.max_rows} this QP was built for")
        if n_obstacle_rows is None:
            n_obstacle_rows = m
        code, iterations, active, slack = _daqp.solve_rows(tau_nom, A, b, scale, self._cols, int(n_obstacle_rows),
                                                           int(stride), self.buffers)
        raise_bad_input(code)
        return QPResult(self.buffers.u, slack, code == _daqp.SOLVED, STATUS[code], iterations, active,
                        time.perf_counter() - start)


def raise_bad_input(code: int) -> None:
    """Turn :func:`c3bf_gym.safety._daqp.solve_rows`' invalid-input codes into ``ValueError``."""
    if code == _daqp.BAD_NOMINAL:
        raise ValueError("tau_nom contains NaN or inf")
    if code == _daqp.BAD_ROWS:
        raise ValueError("the safety rows contain NaN or inf (the state or the obstacles are not finite)")
