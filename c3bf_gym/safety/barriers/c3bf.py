"""Collision Cone Control Barrier Function (C3BF) with a smoothed speed norm."""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from numpy.typing import ArrayLike

from .. import _rows
from .base import Barrier, BarrierTerms, check_points, contiguous, radii, require_positive

__all__ = ["C3BF"]


class C3BF(Barrier):
    """Collision-cone barrier ``h = ⟨p, v⟩ + ‖v‖_ε s``.

    With relative position ``p`` [m], relative velocity ``v`` [m/s] and combined
    radius ``r`` [m]::

        s      = √(‖p‖² − r²)            tangent length from the point to the ball [m]
        ‖v‖_ε  = √(‖v‖² + ε²)            smoothed speed [m/s]
        h      = ⟨p, v⟩ + ‖v‖_ε s         [m²/s]
        ∂h/∂p  = v + ‖v‖_ε p / s
        ∂h/∂v  = p + s v / ‖v‖_ε
        drift  = ⟨∂h/∂p, v⟩ = ‖v‖² + ‖v‖_ε ⟨p, v⟩ / s

    With ε = 0, ``h ≥ 0`` exactly when the relative velocity points outside the
    collision cone, i.e. the ray ``p + t v`` (t ≥ 0) never enters the open ball.

    Smoothing: the exact norm ``‖v‖`` is not differentiable at ``v = 0``; the
    smoothed ``‖v‖_ε`` is, everywhere. Since ``‖v‖ ≤ ‖v‖_ε ≤ ‖v‖ + ε``,
    ``h_exact ≤ h_ε ≤ h_exact + ε s``: the filter is slightly *less*
    conservative than the exact C3BF, by at most ``ε s``. At rest outside the
    ball, ``h_ε(v = 0) = ε s > 0``, i.e. being at rest is safe.

    Inside or on the ball (``‖p‖ ≤ r``, flagged by :attr:`BarrierTerms.inside`)
    the cone is undefined (``s`` is not real). There the point falls back to a
    recovery barrier, the second-order distance barrier with γ₁ = γ₂ = γ scaled to
    meet the C3BF on the surface::

        h_in = ⟨p, v⟩ + (γ/2)(‖p‖² − r²)      (= the C3BF's ⟨p, v⟩ at ‖p‖ = r)
        ∂h_in/∂p = v + γ p,   ∂h_in/∂v = p

    whose row asks for a bounded push apart (``ḣ_in + γ h_in ≥ 0``). No NaN or inf
    is produced. (Clamping ``s`` instead gives rows with ``b`` of order 1e5 that
    leave the QP badly conditioned.) The violation itself is reported upstream
    through ``inside``. Outside, ``s`` is floored at ``δ = 1e-6`` m.

    Args:
        gamma: class-K gain γ [1/s], finite and > 0.
        eps: speed smoothing ε [m/s], finite and > 0.

    Raises:
        ValueError: if ``gamma`` or ``eps`` is not finite and > 0.
    """

    name: ClassVar[str] = "c3bf"
    delta: ClassVar[float] = 1e-6
    """Floor on the tangent length ``s`` [m] (keeps ``1/s`` finite inside the ball)."""

    def __init__(self, gamma: float = 5.0, eps: float = 1e-2) -> None:
        self._gamma = require_positive("gamma", gamma)
        self._eps = require_positive("eps", eps)

    @property
    def gamma(self) -> float:
        """Class-K gain γ [1/s] applied to ``h``."""
        return self._gamma

    @property
    def eps(self) -> float:
        """Speed smoothing ε [m/s]."""
        return self._eps

    def __repr__(self) -> str:
        return f"C3BF(gamma={self._gamma!r}, eps={self._eps!r})"

    def terms(self, p: ArrayLike, v: ArrayLike, r: ArrayLike) -> BarrierTerms:
        """C3BF terms for P points (the recovery barrier for points inside the ball).

        Args:
            p: (P, 3) relative positions [m].
            v: (P, 3) relative velocities [m/s].
            r: (P,) combined radii [m] (> 0).

        Returns:
            :class:`BarrierTerms`: ``h`` (P,) [m²/s], ``grad_v`` (P, 3) [m],
            ``drift`` (P,) [m²/s²], ``inside`` (P,) bool, ``grad_p`` (P, 3) [m/s].
        """
        p, v, r = check_points(p, v, r)
        n_pts = p.shape[0]
        h, drift, inside = np.empty(n_pts), np.empty(n_pts), np.empty(n_pts, dtype=bool)
        grad_v, grad_p = np.empty((n_pts, 3)), np.empty((n_pts, 3))
        terms = BarrierTerms(h, grad_v, drift, inside, grad_p)
        _rows.c3bf_terms(contiguous(p), contiguous(v), radii(r, n_pts), float(self.gamma), float(self.eps), self.delta,
                         terms)
        return terms

    def fused_spec(self) -> _rows.BarrierGains | None:
        """This barrier as the filter's fused kernel reads it
        (:class:`c3bf_gym.safety._rows.BarrierGains`), or None for a subclass that changes
        :meth:`terms`. The parameters are read through the public
        properties (:attr:`gamma`, :attr:`eps`, :attr:`delta`), as :meth:`terms` and
        :meth:`rows_from_terms` read them, so a subclass that overrides one is honoured on both
        paths."""
        if type(self).terms is not C3BF.terms:
            return None
        return _rows.BarrierGains(_rows.C3BF_KIND, gamma=float(self.gamma), epsilon=float(self.eps),
                                  delta=float(self.delta), gamma1=0.0)
