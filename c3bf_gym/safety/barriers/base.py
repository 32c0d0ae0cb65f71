"""Common interface of the per-point obstacle barriers and the torque-space row builder.

Every obstacle barrier reduces, per arm point ``k``, to the enforced condition

    ḣ_k + γ h_k ≥ 0,      ḣ_k = drift_k + ⟨grad_v_k, a_k⟩,

where ``a_k`` is the relative acceleration of the point with respect to the
obstacle. The controller supplies the affine map ``a_k = G_k τ + c_k`` from joint
torque ``τ ∈ R^n``, so each point yields one linear row ``A_k · τ ≥ b_k`` with

    A_k = grad_v_k @ G_k
    b_k = −γ h_k − drift_k − ⟨grad_v_k, c_k⟩.

Subclasses only implement :meth:`Barrier.terms` and :attr:`Barrier.gamma`; the row
assembly lives once, vectorised, in :meth:`Barrier.rows`.

Units: positions in m, velocities in m/s, accelerations in m/s², torques in N·m
(or whatever unit ``G`` maps from). The per-point arithmetic runs in compiled kernels
(:mod:`c3bf_gym.safety._rows`), which the filter's fused kernel shares.
"""

from __future__ import annotations

import abc
import math
from typing import ClassVar, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .. import _rows

__all__ = [
    "Barrier",
    "BarrierTerms",
    "Rows",
    "check_points",
    "contiguous",
    "distance_barrier",
    "radii",
    "require_positive",
    "row_buffers",
]

FloatArray = NDArray[np.float64]


class Rows(NamedTuple):
    """Linear constraints ``A @ tau >= b`` in torque space.

    Attributes:
        A: (m, n) constraint matrix, one row per constraint.
        b: (m,) lower bounds.
    """

    A: FloatArray
    b: FloatArray


class BarrierTerms(NamedTuple):
    """Per-point quantities defining ``drift + ⟨grad_v, a⟩ + γ h ≥ 0``.

    Attributes:
        h: (P,) value of the function the row enforces (C3BF: ``h``; HOCBF: ``ψ₁``).
            Units depend on the barrier (m²/s for both implemented ones).
        grad_v: (P, 3) gradient of ``h`` w.r.t. the relative velocity ``v``.
        drift: (P,) the part of ``ḣ`` not depending on the acceleration,
            ``⟨∂h/∂p, v⟩``.
        inside: (P,) bool, ``‖p‖ <= r`` (the point already overlaps the obstacle).
        grad_p: (P, 3) gradient of ``h`` w.r.t. the relative position ``p`` (so that a caller
            whose ``p`` moves by more than ``v``, e.g. a closest point sliding along a link,
            can add ``⟨grad_p, ṗ − v⟩`` to the drift).
    """

    h: FloatArray
    grad_v: FloatArray
    drift: FloatArray
    inside: NDArray[np.bool_]
    grad_p: FloatArray


def row_buffers(out: Rows | None, m: int, n: int) -> tuple[FloatArray, FloatArray]:
    """``(A, b)`` of shapes (m, n) and (m,) to write rows into: new arrays, or the first ``m``
    rows of ``out`` after checking it is large enough (ValueError otherwise)."""
    if out is None:
        return np.empty((m, n)), np.empty(m)
    if out.A.ndim != 2 or out.A.shape[0] < m or out.A.shape[1] != n:
        raise ValueError(f"out.A must have shape (>= {m}, {n}); got {out.A.shape}")
    if out.b.ndim != 1 or out.b.shape[0] < m:
        raise ValueError(f"out.b must have shape (>= {m},); got {out.b.shape}")
    return out.A[:m], out.b[:m]


def require_positive(name: str, value: float) -> float:
    """Return ``value`` as a float, or raise ``ValueError`` unless it is finite and > 0."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(
            f"{name} must be a finite number in (0, inf); got {value!r}"
        ) from None
    if not (math.isfinite(x) and x > 0.0):
        raise ValueError(f"{name} must be a finite number in (0, inf); got {value!r}")
    return x


def check_points(
    p: ArrayLike, v: ArrayLike, r: ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Validate (shapes only) and convert the relative state of ``P`` points.

    Args:
        p: (P, 3) relative positions ``x − p_o`` [m].
        v: (P, 3) relative velocities ``ẋ − v_o`` [m/s].
        r: (P,) combined radii [m], must be > 0 (not checked: per-element
            checks are too costly in the control loop); a scalar is broadcast.

    Returns:
        ``(p, v, r)`` as float64 arrays (no copy when already float64).

    Raises:
        ValueError: on wrong or inconsistent shapes.
    """
    p = np.asarray(p, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"p must have shape (P, 3); got {p.shape}")
    if v.shape != p.shape:
        raise ValueError(f"v must have the same shape as p {p.shape}; got {v.shape}")
    if r.shape not in ((), (p.shape[0],)):
        raise ValueError(f"r must have shape ({p.shape[0]},) or be a scalar; got {r.shape}")
    return p, v, r


def contiguous(a: FloatArray) -> FloatArray:
    """``a`` as a C-contiguous float64 array (no copy when it already is one)."""
    return np.ascontiguousarray(a, dtype=np.float64)


def radii(r: FloatArray, n_pts: int) -> FloatArray:
    """Combined radii as a contiguous (P,) array (a scalar is repeated)."""
    return np.full(n_pts, float(r)) if r.ndim == 0 else contiguous(r)


def distance_barrier(p: ArrayLike, r: ArrayLike, out: FloatArray | None = None) -> FloatArray:
    """Squared-distance barrier ``h0 = ‖p‖² − r²`` [m²], shape (P,).

    Negative strictly inside the ball, zero on its surface. Useful for logging the
    clearance independently of which barrier the filter enforces.
    """
    p = np.asarray(p, dtype=np.float64)
    out = np.vecdot(p, p, out=out)
    out -= np.square(r)
    return out


class Barrier(abc.ABC):
    """A per-point obstacle barrier turned into torque-space rows.

    Subclasses define :attr:`name`, :meth:`terms` and :attr:`gamma`.
    """

    name: ClassVar[str]

    @abc.abstractmethod
    def terms(self, p: ArrayLike, v: ArrayLike, r: ArrayLike) -> BarrierTerms:
        """Barrier value, velocity gradient, drift and overlap mask.

        Args:
            p: (P, 3) relative positions [m].
            v: (P, 3) relative velocities [m/s].
            r: (P,) combined radii [m] (> 0).

        Returns:
            :class:`BarrierTerms` with arrays of leading dimension P.
        """

    @property
    @abc.abstractmethod
    def gamma(self) -> float:
        """The class-K gain [1/s] applied to ``terms().h`` in the row."""

    def rows(
        self,
        p: ArrayLike,
        v: ArrayLike,
        r: ArrayLike,
        G: ArrayLike,
        c: ArrayLike,
        out: Rows | None = None,
    ) -> Rows:
        """Torque-space rows ``A @ τ >= b``, one per point.

        ``A_k = grad_v_k @ G_k`` and ``b_k = −γ h_k − drift_k − ⟨grad_v_k, c_k⟩``,
        so that ``A_k τ − b_k = ḣ_k + γ h_k`` when ``a_k = G_k τ + c_k``.

        Args:
            p: (P, 3) relative positions [m].
            v: (P, 3) relative velocities [m/s].
            r: (P,) combined radii [m].
            G: (P, 3, n) torque-to-relative-acceleration maps [m/s² per N·m].
            c: (P, 3) relative acceleration at zero torque [m/s²].
            out: optional preallocated :class:`Rows` with ``out.A`` of shape
                (>= P, n) and ``out.b`` of shape (>= P,); the first P rows are
                overwritten, the rest is left untouched.

        Returns:
            :class:`Rows` with ``A`` (P, n) and ``b`` (P,). With ``out`` these are
            views of the first P rows of ``out.A`` / ``out.b``.

        Raises:
            ValueError: on inconsistent shapes.
        """
        return self.rows_from_terms(self.terms(p, v, r), G, c, out)

    def rows_from_terms(
        self, terms: BarrierTerms, G: ArrayLike, c: ArrayLike, out: Rows | None = None
    ) -> Rows:
        """:meth:`rows` from already evaluated :meth:`terms` (which are left unchanged), so a
        caller that also reports ``h`` or ``inside`` evaluates the barrier once."""
        h, grad_v, drift = terms.h, terms.grad_v, terms.drift
        n_pts = h.shape[0]
        G = np.asarray(G, dtype=np.float64)
        c = np.asarray(c, dtype=np.float64)
        if G.ndim != 3 or G.shape[:2] != (n_pts, 3):
            raise ValueError(f"G must have shape ({n_pts}, 3, n); got {G.shape}")
        if c.shape != (n_pts, 3):
            raise ValueError(f"c must have shape ({n_pts}, 3); got {c.shape}")
        n = G.shape[2]

        A, b = row_buffers(out, n_pts, n)
        # compiled: A_k = grad_v_k G_k, b_k = −(⟨grad_v_k, c_k⟩ + drift_k + γ h_k)
        _rows.rows_from_terms(contiguous(grad_v), contiguous(drift), contiguous(h), float(self.gamma),
                              contiguous(G), contiguous(c), A, b)
        return Rows(A, b)
