"""Joint position and velocity limits as control-barrier rows in torque space."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from .. import _rows
from .base import FloatArray, Rows, contiguous, require_positive, row_buffers

__all__ = ["JointLimits"]


class JointLimits:
    """Box limits on ``q`` and ``q̇`` of an n-joint arm as ``4n`` rows ``A @ τ >= b``.

    The joint accelerations are affine in torque, ``q̈ = Minv τ + c_q``.

    Position limits ``q_lo ≤ q ≤ q_hi`` [rad] have relative degree two and are
    enforced as second-order barriers (gains γ₁, γ₂ [1/s])::

        upper:  ψ_u = −q̇ + γ₁ (q_hi − q),   −q̈ − γ₁ q̇ + γ₂ ψ_u ≥ 0
        lower:  ψ_l =  q̇ + γ₁ (q − q_lo),    q̈ + γ₁ q̇ + γ₂ ψ_l ≥ 0

    Velocity limits ``|q̇| ≤ qd_max`` [rad/s] are first-order barriers (gain γ_v)::

        upper:  −q̈ + γ_v (qd_max − q̇) ≥ 0
        lower:   q̈ + γ_v (q̇ + qd_max) ≥ 0

    Row order: ``[position upper (n), position lower (n), velocity upper (n),
    velocity lower (n)]``. The position row of an infinite limit (a continuous
    joint) is ``0 τ ≥ −1``, which always holds.

    Args:
        q_lo: (n,) lower position limits [rad], or -inf for none.
        q_hi: (n,) upper position limits [rad], or +inf for none, ``q_lo < q_hi``.
        qd_max: (n,) or scalar speed limits [rad/s], finite and > 0.
        gamma1: position-barrier gain γ₁ [1/s], finite and > 0.
        gamma2: position-barrier gain γ₂ [1/s], finite and > 0.
        gamma_v: velocity-barrier gain γ_v [1/s], finite and > 0.

    Raises:
        ValueError: on inconsistent shapes, NaN limits (or ``q_lo = +inf``,
            ``q_hi = -inf``), ``q_lo >= q_hi``,
            ``qd_max <= 0`` or a gain that is not finite and > 0.

    """

    def __init__(
        self,
        q_lo: ArrayLike,
        q_hi: ArrayLike,
        qd_max: ArrayLike,
        gamma1: float = 10.0,
        gamma2: float = 10.0,
        gamma_v: float = 20.0,
    ) -> None:
        q_lo = np.array(q_lo, dtype=np.float64)
        q_hi = np.array(q_hi, dtype=np.float64)
        if q_lo.ndim != 1 or q_lo.shape[0] == 0:
            raise ValueError(f"q_lo must have shape (n,) with n >= 1; got {q_lo.shape}")
        n = q_lo.shape[0]
        if q_hi.shape != (n,):
            raise ValueError(f"q_hi must have shape ({n},) like q_lo; got {q_hi.shape}")
        qd_arr = np.asarray(qd_max, dtype=np.float64)
        if qd_arr.shape not in ((), (n,)):
            raise ValueError(f"qd_max must be a scalar or have shape ({n},); got {qd_arr.shape}")
        qd_arr = np.broadcast_to(qd_arr, (n,)).copy()
        if np.any(np.isnan(q_lo) | np.isnan(q_hi) | (q_lo == np.inf) | (q_hi == -np.inf)):
            raise ValueError("q_lo must be finite or -inf, q_hi finite or +inf")
        bad = np.flatnonzero(~(q_lo < q_hi))
        if bad.size:
            raise ValueError(
                f"q_lo must be < q_hi for every joint; violated at joints {bad.tolist()}"
            )
        bad = np.flatnonzero(~(np.isfinite(qd_arr) & (qd_arr > 0.0)))
        if bad.size:
            raise ValueError(
                f"qd_max must be finite and in (0, inf); violated at joints {bad.tolist()}"
            )
        self._g1 = require_positive("gamma1", gamma1)
        self._g2 = require_positive("gamma2", gamma2)
        self._gv = require_positive("gamma_v", gamma_v)
        self._gains = np.array([self._g1, self._g2, self._gv])
        for arr in (q_lo, q_hi, qd_arr):
            arr.flags.writeable = False
        self._q_lo, self._q_hi, self._qd_max = q_lo, q_hi, qd_arr
        # The four row blocks of b, expanded (the kernel's formulas):
        #   b_pu =  γ₁γ₂ (q − q_hi) + (γ₁ + γ₂) q̇ + c_q      b_vu =  γ_v (q̇ − qd_max) + c_q
        #   b_pl = −γ₁γ₂ (q − q_lo) − (γ₁ + γ₂) q̇ − c_q      b_vl = −γ_v (q̇ + qd_max) − c_q

    @property
    def n(self) -> int:
        """Number of joints."""
        return self._q_lo.shape[0]

    @property
    def n_rows(self) -> int:
        """Number of rows produced by :meth:`rows` (``4n``)."""
        return 4 * self.n

    @property
    def q_lo(self) -> FloatArray:
        """(n,) lower position limits [rad] (read-only)."""
        return self._q_lo

    @property
    def q_hi(self) -> FloatArray:
        """(n,) upper position limits [rad] (read-only)."""
        return self._q_hi

    @property
    def qd_max(self) -> FloatArray:
        """(n,) speed limits [rad/s] (read-only)."""
        return self._qd_max

    @property
    def gains(self) -> tuple[float, float, float]:
        """``(gamma1, gamma2, gamma_v)`` [1/s]."""
        return self._g1, self._g2, self._gv

    def __repr__(self) -> str:
        return (
            f"JointLimits(n={self.n}, gamma1={self._g1!r}, gamma2={self._g2!r}, "
            f"gamma_v={self._gv!r})"
        )

    def rows(
        self,
        q: ArrayLike,
        qd: ArrayLike,
        Minv: ArrayLike,
        c_q: ArrayLike,
        out: Rows | None = None,
        *,
        dofs: ArrayLike | None = None,
        qpos_ids: ArrayLike | None = None,
    ) -> Rows:
        """The ``4n`` limit rows ``A @ τ >= b`` at state ``(q, q̇)``, for a torque ``τ`` on ``k``
        dofs (``k = n`` unless the limited joints are some of a larger model's).

        Args:
            q: (n,) joint positions [rad]; with ``qpos_ids``, a model's ``qpos`` (nq,).
            qd: (n,) joint velocities [rad/s]; with ``dofs``, a model's ``qvel`` (k,).
            Minv: (n, k) the map from the torque to the limited joints' accelerations
                (``q̈ = Minv τ + c_q``); with ``dofs``, the whole (k, k) inverse mass matrix.
            c_q: (n,) joint acceleration at zero torque [rad/s²]; with ``dofs``, (k,).
            out: optional preallocated :class:`Rows` with ``out.A`` (>= 4n, k) and
                ``out.b`` (>= 4n,); the first 4n rows are overwritten.
            dofs, qpos_ids: (n,) where the limited joints are in a larger model's arrays: their
                dofs (rows of ``Minv``, entries of ``qd`` and ``c_q``) and their ``qpos``
                addresses. None: the first ``n`` of each, in order.

        Returns:
            :class:`Rows` with ``A`` (4n, k) and ``b`` (4n,), in the row order of
            the class docstring (views of ``out`` when given).

        Raises:
            ValueError: on inconsistent shapes.
        """
        n = self.n
        m = 4 * n
        q = np.asarray(q, dtype=np.float64)
        qd = np.asarray(qd, dtype=np.float64)
        Minv = np.asarray(Minv, dtype=np.float64)
        c_q = np.asarray(c_q, dtype=np.float64)
        first = np.arange(n, dtype=np.int64)
        k = Minv.shape[1] if Minv.ndim == 2 else -1
        rows = n if dofs is None else k
        checks = [("qd", qd, (rows,)), ("Minv", Minv, (rows, max(k, n))), ("c_q", c_q, (rows,))]
        if qpos_ids is None:
            checks.append(("q", q, (n,)))
        else:
            qpos_ids = np.asarray(qpos_ids, dtype=np.int64)
            if q.ndim != 1 or qpos_ids.shape != (n,) or not np.all((qpos_ids >= 0) & (qpos_ids < len(q))):
                raise ValueError(f"qpos_ids must be {n} indices into q; got {qpos_ids!r} for q of shape {q.shape}")
        if dofs is not None:
            dofs = np.asarray(dofs, dtype=np.int64)
            if dofs.shape != (n,) or not np.all((dofs >= 0) & (dofs < k)):
                raise ValueError(f"dofs must be {n} indices into the rows of Minv; got {dofs!r}")
        for name, arr, shape in checks:
            if arr.shape != shape:
                raise ValueError(f"{name} must have shape {shape}; got {arr.shape}")
        dofs = first if dofs is None else dofs
        qpos_ids = first if qpos_ids is None else qpos_ids
        A, b = row_buffers(out, m, Minv.shape[1])
        # compiled: A = [−Minv; Minv; −Minv; Minv], b from the expansions in __init__'s comment
        limits = _rows.JointLimitParams(dofs, qpos_ids, self._q_lo, self._q_hi, self._qd_max, self._gains)
        _rows.joint_limit_rows(q, qd, contiguous(Minv), c_q, limits, A, b)
        return Rows(A, b)
