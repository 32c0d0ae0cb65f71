"""The filter's QP as a Python object: :class:`PriorityQP` sets up the two DAQP workspaces once
(:mod:`c3bf_gym.safety._daqp`) and solves with the compiled priority algorithm
:func:`c3bf_gym.safety._qp.solve_rows`, whose module states the problem: the torque closest to the
nominal one (in the scaled torque, ``‖u − u_nom‖²``, or with a metric ``(u − u_nom)ᵀ (I + KᵀK)
(u − u_nom)``) within the torque box that keeps every safety row, the rows giving way by priority
(joint limits, floor and guard before the barrier's rows) when no torque keeps them all.
"""

from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np

from c3bf_gym import validation
from c3bf_gym.safety import _daqp, _qp

__all__ = ["PriorityQP", "QPResult"]

#: :attr:`QPResult.status` by :func:`c3bf_gym.safety._qp.solve_rows` outcome
STATUS = {_qp.SOLVED: "solved", _qp.RELAXED: "relaxed", _qp.FAILED: "failed"}


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
    """The filter's QP (:mod:`c3bf_gym.safety._qp`) on DAQP, with workspaces set up once.

    Args:
        n: number of joints.
        tau_min, tau_max: (n,) box of the scaled torque ``u``.
        level1_rows: the largest number of priority-1 rows (guard, floor, self-collision, joint limits).
        level2_rows: the largest number of priority-2 rows (the barrier's).
        reserve: the joint range's reserve for ``n`` joints, (2n,) ``γ₁γ₂ δ`` per position row
            (upper, then lower), or None: none (:class:`~c3bf_gym.safety._qp.QPBuffers`).
        speed_reserve: the joint speed reserve, (2n,) ``γ_v (q̇_max − q̇_nominal)`` per speed
            row (upper, then lower: the speed rows lie at the nominal bound, their copies at the
            filter's), or None: none.
        allowance_level: hold the barrier's rows in two levels below the reserve: loosened by the
            allowance each solve gives them (:meth:`solve_scaled`), then as written.
        metric_rows: ``r`` >= 0, the rows of the cost's ``K`` each solve gives
            (:meth:`solve_scaled`): the cost is ``½ (u − u_nom)ᵀ (I + KᵀK) (u − u_nom)``; 0 (the
            default): ``½ ‖u − u_nom‖²``.

    Which row is which is given per solve: of the rows, those with index ``k <
    n_obstacle_rows`` and ``k % stride == 0`` are the barrier's (``stride`` 2 when each barrier
    row is followed by its guard's, else 1). With either reserve the last ``4n`` rows of
    every solve are the joint limits' (position upper and lower, then speed upper and lower):
    a position row with a reserve (drawn ``δ`` inside the range) forms a level between priority
    1, which holds its copy at the range, and the barrier's; a speed row with a speed reserve (at
    the nominal bound) forms a level below the barrier's, its copy at the filter's bound in
    priority 1. Every other row is priority 1.

    Raises:
        ValueError: a reserve or speed reserve that is not (2n,), finite and >= 0, or one with
            fewer than 4n priority-1 rows; an allowance level without barrier rows; a
            ``metric_rows`` that is not an integer >= 0.
    """

    def __init__(self, n: int, tau_min: np.ndarray, tau_max: np.ndarray, level1_rows: int, level2_rows: int,
                 reserve: np.ndarray | None = None, allowance_level: bool = False,
                 speed_reserve: np.ndarray | None = None, metric_rows: int = 0) -> None:
        self.n = int(n)
        self.metric_rows = int(validation.integer("metric_rows", metric_rows, low=0))
        self._cols = np.arange(self.n, dtype=np.int64)  # the rows' columns are the torque's, in order
        self.tau_min = np.array(tau_min, dtype=np.float64)
        self.tau_max = np.array(tau_max, dtype=np.float64)
        self._levels = (int(level1_rows), int(level2_rows))
        self._given = tuple(None if value is None else np.array(value, dtype=np.float64)
                            for value in (reserve, speed_reserve))
        for name, array in zip(("reserve", "speed_reserve"), self._given):
            if array is not None and (array.shape != (2 * self.n,) or not np.all(np.isfinite(array))
                                      or np.any(array < 0.0) or 4 * self.n > level1_rows):
                raise ValueError(f"{name} must be ({2 * self.n},), finite and >= 0, with at least {4 * self.n} "
                                 f"priority-1 rows; got {array!r} and {level1_rows}")
        joint = [np.zeros(2 * self.n) if array is None else array for array in self._given]
        self._reserve = np.concatenate(joint) if any(array is not None for array in self._given) else np.zeros(0)
        if allowance_level and self._levels[1] == 0:
            raise ValueError("allowance_level needs barrier rows (level2_rows > 0): it splits them in two levels")
        self._allowance_level = bool(allowance_level)
        rows = sum(self._levels)
        # the prioritised workspace's levels, in order: priority 1 (with the joint rows' copies), the range's
        # reserve, the barrier's loosened by their allowance, the barrier's as written, the speed bound
        capacity = [self._levels[0], int(np.count_nonzero(joint[0])), self._levels[1] * self._allowance_level,
                    self._levels[1], int(np.count_nonzero(joint[1]))]
        points = [n + sum(capacity[: i + 1]) for i in range(len(capacity)) if capacity[i] > 0]
        self._plain = _daqp.DaqpWorkspace(n, rows, self.tau_min, self.tau_max)
        self._hier = _daqp.DaqpWorkspace(n, sum(capacity), self.tau_min, self.tau_max, break_points=[n] + points)
        self.max_rows = rows
        self.buffers = _qp.QPBuffers(self._plain.buffers, self._hier.buffers,
                                     np.array(capacity, np.int64), self.tau_min, self.tau_max,
                                     np.zeros(n), np.zeros(max(rows, 1)), np.zeros(max(rows, 1)),
                                     np.ones(2, np.int64), np.zeros(1, np.int64), self._reserve,
                                     np.zeros(max(rows, 1)), np.zeros((self.metric_rows, n)), np.zeros(n))

    def reset(self) -> None:
        """Forget the warm start: the next solve starts from an empty working set, so a sequence
        of solves after a reset gives the same answers, bit for bit, whatever came before."""
        self.buffers.cold[:] = 1
        self.buffers.last[0] = _qp.SOLVED

    def __reduce__(self):
        """Pickled as its arguments: the copy sets up its own DAQP workspaces (cold)."""
        return PriorityQP, (self.n, self.tau_min, self.tau_max, *self._levels, self._given[0], self._allowance_level,
                            self._given[1], self.metric_rows)

    def solve_scaled(self, tau_nom: np.ndarray, A: np.ndarray, b: np.ndarray, scale: np.ndarray,
                     n_obstacle_rows: int | None = None, stride: int = 1,
                     allowance: np.ndarray | None = None, metric: np.ndarray | None = None) -> QPResult:
        """Solve for ``u`` with rows ``(A s) u ≥ b``; ``tau_nom`` in torque units.

        Args:
            tau_nom: (n,) nominal torque [N·m].
            A, b: (m, n), (m,) the rows, ``m ≤`` the capacity.
            scale: (n,) ``s``.
            n_obstacle_rows, stride: which rows are the barrier's (class docstring); None: all m
                rows when the QP has barrier rows (``level2_rows > 0``), else none.
            allowance: (m,) how far each of the barrier's rows may give way [``b``'s units, ≥ 0],
                with an allowance level: when the rows conflict, the barrier's rows are held
                loosened by it (after the rows of priority 1 and the reserve), and as written only
                after that (entries of the other rows are ignored). None: 0 for every row.
            metric: (r, n) ``K`` of the cost ``½ (u − u_nom)ᵀ (I + KᵀK) (u − u_nom)``, ``r`` the
                QP's ``metric_rows`` (given exactly when that is above 0).

        Raises:
            ValueError: wrong shapes, more rows of either priority than the capacity, fewer than
                the joint limits' ``4n`` with a reserve, a stride below 1, NaN or inf in the input,
                an allowance that is negative, not finite, not (m,), or given to a QP without an
                allowance level; a metric that is not (r, n) or not finite, or one given to a QP
                built without metric rows (or none given to one with).
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
        if n_obstacle_rows is None:
            n_obstacle_rows = m if self._levels[1] > 0 else 0
        if int(stride) < 1:
            raise ValueError(f"stride must be >= 1, got {stride}")
        barrier = len(range(0, min(int(n_obstacle_rows), m), int(stride)))
        if barrier > self._levels[1] or m - barrier > self._levels[0]:
            raise ValueError(f"{barrier} barrier rows and {m - barrier} others exceed the {self._levels[1]} and "
                             f"{self._levels[0]} this QP was built for")
        if m - barrier < len(self._reserve):
            raise ValueError(f"this QP keeps a joint range or speed reserve: its last {len(self._reserve)} "
                             f"rows must be the joint limits', got {m - barrier} rows besides the barrier's")
        if allowance is not None:
            allowance = np.asarray(allowance, dtype=np.float64)
            if not self._allowance_level:
                raise ValueError("an allowance was given to a QP built without allowance_level=True")
            if allowance.shape != (m,) or not np.all(np.isfinite(allowance)) or np.any(allowance < 0.0):
                raise ValueError(f"allowance must be finite, >= 0 and of shape ({m},), got {allowance!r}")
        self.buffers.allowance[:m] = 0.0 if allowance is None else allowance
        if (metric is None) != (self.metric_rows == 0):
            raise ValueError(f"this QP was built with metric_rows={self.metric_rows}: pass metric (r, n) exactly "
                             "when that is above 0")  # fmt: skip
        if metric is not None:
            metric = np.asarray(metric, dtype=np.float64)
            if metric.shape != (self.metric_rows, self.n) or not np.all(np.isfinite(metric)):
                raise ValueError(f"metric must be finite and of shape ({self.metric_rows}, {self.n}), got "
                                 f"{metric!r}")  # fmt: skip
            self.buffers.metric[:] = metric
        code, iterations, active, slack = _qp.solve_rows(tau_nom, A, b, scale, self._cols, int(n_obstacle_rows),
                                                         int(stride), self.buffers)
        error = bad_input_error(code)
        if error is not None:
            raise error
        return QPResult(self.buffers.u, slack, code == _qp.SOLVED, STATUS[code], iterations, active,
                        time.perf_counter() - start)


def bad_input_error(code: int) -> ValueError | None:
    """The ``ValueError`` for :func:`c3bf_gym.safety._qp.solve_rows`' invalid-input codes, None
    for any other code."""
    if code == _qp.BAD_NOMINAL:
        return ValueError("tau_nom contains NaN or inf")
    if code == _qp.BAD_ROWS:
        return ValueError("the safety rows contain NaN or inf (the state or the obstacles are not finite)")
    return None
