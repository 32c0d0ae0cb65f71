"""Second-order (high-order) CBF on the squared distance to an obstacle sphere."""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from numpy.typing import ArrayLike

from .. import _rows
from .base import (
    Barrier,
    BarrierTerms,
    FloatArray,
    check_points,
    contiguous,
    distance_barrier,
    radii,
    require_positive,
)

__all__ = ["DistanceHOCBF"]


class DistanceHOCBF(Barrier):
    """Distance HOCBF: ``h0 = ‖p‖² − r²``, ``ψ₁ = ḣ0 + γ₁ h0 = 2⟨p, v⟩ + γ₁ h0``.

    The relative degree of ``h0`` w.r.t. torque is two, so the enforced condition
    is ``ψ̇₁ + γ₂ ψ₁ ≥ 0``. In the common form ``drift + ⟨grad_v, a⟩ + γ h ≥ 0``::

        h      = ψ₁ = 2⟨p, v⟩ + γ₁ (‖p‖² − r²)     [m²/s]
        grad_v = 2 p                                [m]
        drift  = 2‖v‖² + 2γ₁⟨p, v⟩                  [m²/s²]
        γ      = γ₂

    The distance barrier value ``h0`` itself is available from :meth:`h0`.
    Everything is polynomial, so there is no singular configuration; ``inside``
    flags ``‖p‖ ≤ r`` (``h0 ≤ 0``).

    Args:
        gamma1: gain γ₁ [1/s] of the first-order term, finite and > 0.
        gamma2: gain γ₂ [1/s] applied to ψ₁ in the row, finite and > 0.

    Raises:
        ValueError: if a gain is not finite and > 0.
    """

    name: ClassVar[str] = "hocbf"

    def __init__(self, gamma1: float = 5.0, gamma2: float = 5.0) -> None:
        self._gamma1 = require_positive("gamma1", gamma1)
        self._gamma2 = require_positive("gamma2", gamma2)

    gamma1 = property(lambda self: self._gamma1, doc="Gain γ₁ [1/s] inside ψ₁.")
    gamma2 = property(lambda self: self._gamma2, doc="Gain γ₂ [1/s] applied to ψ₁.")
    gamma = property(lambda self: self._gamma2, doc="Class-K gain applied to ψ₁ in the row (= γ₂) [1/s].")

    def __repr__(self) -> str:
        return f"DistanceHOCBF(gamma1={self._gamma1!r}, gamma2={self._gamma2!r})"

    @staticmethod
    def h0(p: ArrayLike, r: ArrayLike) -> FloatArray:
        """Distance barrier value ``h0 = ‖p‖² − r²`` [m²], shape (P,)."""
        return distance_barrier(p, r)

    def terms(self, p: ArrayLike, v: ArrayLike, r: ArrayLike) -> BarrierTerms:
        """HOCBF terms for P points.

        Args:
            p: (P, 3) relative positions [m].
            v: (P, 3) relative velocities [m/s].
            r: (P,) combined radii [m] (> 0).

        Returns:
            :class:`BarrierTerms`: ``h = ψ₁`` (P,) [m²/s], ``grad_v = 2p`` (P, 3)
            [m], ``drift`` (P,) [m²/s²], ``inside`` (P,) bool, ``grad_p = 2v + 2γ₁p``
            (P, 3) [m/s].
        """
        p, v, r = check_points(p, v, r)
        n_pts = p.shape[0]
        h, drift, inside = np.empty(n_pts), np.empty(n_pts), np.empty(n_pts, dtype=bool)
        grad_v, grad_p = np.empty((n_pts, 3)), np.empty((n_pts, 3))
        terms = BarrierTerms(h, grad_v, drift, inside, grad_p)
        _rows.hocbf_terms(contiguous(p), contiguous(v), radii(r, n_pts), float(self.gamma1), terms)
        return terms

    def fused_spec(self) -> _rows.BarrierGains | None:
        """This barrier as the filter's fused kernel reads it
        (:class:`c3bf_gym.safety._rows.BarrierGains`), or None for a subclass that changes
        :meth:`terms`. The gains are read through the public
        properties (:attr:`gamma`, the row's γ₂, and :attr:`gamma1`), as :meth:`terms` and
        :meth:`rows_from_terms` read them, so a subclass that overrides one is honoured on both
        paths."""
        if type(self).terms is not DistanceHOCBF.terms:
            return None
        return _rows.BarrierGains(_rows.HOCBF_KIND, gamma=float(self.gamma), epsilon=0.0, delta=0.0,
                                  gamma1=float(self.gamma1))
