"""Obstacle avoidance by modulating a motion's direction (Khansari-Zadeh and Billard, 2012).

A step ``v`` (3,) taken at ``x`` is reshaped around each sphere it comes near. For a sphere of
centre ``c``, radius ``R`` and velocity ``w``, with ``r = ‖x − c‖``, ``n = (x − c) / r`` and the
distance ratio ``Γ = max(1, r / R)``, the step relative to the sphere, ``u = v − w``, becomes

    u' = M u,   M = λ_t I + (λ_n − λ_t) n nᵀ,   λ_t = 1 + 1/Γ,
    λ_n = 1 − 1/Γ  if  n·u < 0  (heading into the sphere),  else 1,

and ``v' = u' + w``: the part of the step into the sphere shrinks to nothing at its surface, the
parts along it grow up to twice, so the motion flows round the sphere instead of stopping at it.
This is the modulation matrix ``E D E⁻¹`` of Khansari-Zadeh and Billard ("A dynamical system
approach to realtime obstacle avoidance", Autonomous Robots 32, 2012) for a sphere, whose
orthonormal basis makes ``E D Eᵀ`` the sum above, with the step relative to the moving sphere
(their section 5) and without the tail effect (the normal part is left alone once the motion
leaves the sphere behind). Spheres farther than :data:`REACH` radii from ``x`` leave the step as
it is; the modulations of the spheres within reach are applied one after another, in the order
given.

It shapes a nominal motion only and guarantees nothing: the safety filter keeps the arm off the
spheres. :class:`~c3bf_gym.wrappers.CartesianImpedanceAction` applies it (``modulate=True``) to
its residual step straight for the goal.
"""

from __future__ import annotations

import numpy as np

__all__ = ["REACH", "modulate"]

#: The distance ratio ``Γ = r / R`` beyond which a sphere leaves the step alone.
REACH = 4.0


def modulate(
    position: np.ndarray, step: np.ndarray, centers: np.ndarray, velocities: np.ndarray, radii: np.ndarray
) -> np.ndarray:
    """``step`` (3,) taken at ``position`` (3,) [m], reshaped round the spheres (the math is the
    module's docstring: :mod:`c3bf_gym.controllers.modulation`).

    Args:
        position: the point that moves [m], (3,).
        step: its motion, (3,), in any unit (a displacement [m] or a velocity [m/s]).
        centers: the spheres' centres [m], (k, 3).
        velocities: their velocities, (k, 3), in the unit of ``step`` (zeros for spheres at rest).
        radii: their radii [m], (k,), each > 0.

    Returns:
        The modulated step, a new (3,) array.

    Raises:
        ValueError: shapes other than these (k spheres, none for k = 0: ``centers`` of shape
            (0, 3)), a radius that is not > 0, or a value that is not finite.
    """
    x = np.asarray(position, dtype=float)
    v = np.array(step, dtype=float)
    centers, velocities, radii = (np.asarray(value, dtype=float) for value in (centers, velocities, radii))
    if x.shape != (3,) or v.shape != (3,):
        raise ValueError(f"position and step must have shape (3,), got {x.shape} and {v.shape}")
    k = len(radii) if radii.ndim == 1 else -1
    if centers.shape != (k, 3) or velocities.shape != (k, 3):
        raise ValueError(f"centers (k, 3), velocities (k, 3) and radii (k,) must describe the same spheres, got "
                         f"shapes {centers.shape}, {velocities.shape} and {radii.shape}")  # fmt: skip
    for name, value in (("position", x), ("step", v), ("centers", centers), ("velocities", velocities),
                        ("radii", radii)):  # fmt: skip
        if not np.isfinite(value).all():
            raise ValueError(f"{name} must be finite, got {value!r}")
    if (radii <= 0.0).any():
        raise ValueError(f"radii must be > 0 (m), got {radii!r}")
    return modulated(x, v, centers, velocities, radii)


def modulated(x: np.ndarray, v: np.ndarray, centers: np.ndarray, velocities: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """:func:`modulate` without its checks, for callers whose arrays are already valid float
    arrays of the right shapes (an environment's own state, at every policy step). It returns ``v``
    itself when no sphere is within reach."""
    for c, w, radius in zip(centers, velocities, radii):
        offset = x - c
        r = float(np.linalg.norm(offset))
        if r <= 1e-9 or r > REACH * radius:  # at the centre no direction is defined
            continue
        gamma = max(r / radius, 1.0)
        n = offset / r
        u = v - w
        into = float(n @ u)
        lam_t = 1.0 + 1.0 / gamma
        lam_n = 1.0 - 1.0 / gamma if into < 0.0 else 1.0
        v = lam_t * u + (lam_n - lam_t) * into * n + w
    return v
