"""Cartesian impedance control of the tool position (the paper's eq. 4), as a pure class.

    F = Λ (ẍ_d − J̇q̇) + D (ẋ_d − ẋ) + K (x_d − x)
    τ = Jᵀ F + b + N τ₀,   τ₀ = K_q (q₀ − q) − D_q q̇

with ``Λ = (J M⁻¹ Jᵀ)⁻¹`` the task-space inertia, ``b`` the bias forces (Coriolis, centrifugal,
gravity: MuJoCo's ``qfrc_bias``), and ``N = I − Jᵀ J̄ᵀ``, ``J̄ = M⁻¹ Jᵀ Λ`` the dynamically
consistent null-space projector, so the posture term ``τ₀`` (pulling the redundant joints
towards ``q₀``) does not disturb the tool. With ``damping=None`` the damping is critical for the
closed loop ``Λ ë + D ė + K e = 0``: ``D = 2 L U diag(ω) Uᵀ Lᵀ`` where ``Λ = L Lᵀ`` and
``L⁻¹ K L⁻ᵀ = U diag(ω²) Uᵀ`` (for ``K = k I`` this is ``2 √k Λ^{1/2}``).
"""

from __future__ import annotations

import mujoco
import numpy as np

__all__ = ["CartesianImpedance"]


def _spd(name: str, value: float | np.ndarray, size: int) -> np.ndarray:
    """A scalar, an (size,) positive diagonal, or a (size, size) symmetric positive-definite matrix."""
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        arr = np.full(size, float(arr))
    if arr.ndim == 1:
        if arr.shape != (size,):
            raise ValueError(f"{name} must be a scalar, a ({size},) diagonal or a ({size}, {size}) matrix, got shape {arr.shape}")
        arr = np.diag(arr)
    if arr.shape != (size, size) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be a finite scalar, ({size},) or ({size}, {size}) array, got {value!r}")
    if not np.allclose(arr, arr.T):
        raise ValueError(f"{name} must be symmetric")
    if np.linalg.eigvalsh(arr).min() <= 0.0:
        raise ValueError(f"{name} must be positive definite (all eigenvalues > 0)")
    return arr


class CartesianImpedance:
    """Impedance law for a 3-D tool position with a null-space posture task.

    Args:
        stiffness: K [N/m]: scalar, (3,) diagonal or (3, 3) SPD. Default 300 N/m.
        damping: D [N s/m] in the same forms, or None for critical damping (recomputed from the
            current task inertia at every call).
        damping_ratio: ζ used when ``damping`` is None (1.0 = critical).
        posture: q₀ [rad], (n,); None for no posture task.
        posture_stiffness: K_q [N m/rad] (scalar or (n,)); posture_damping: D_q [N m s/rad]
            (scalar or (n,)); None gives 2 √K_q.
        max_force: bound on ‖F‖ [N] (the task force is scaled down, not clipped per axis, so its
            direction is kept); None for no bound.
    """

    def __init__(
        self,
        stiffness: float | np.ndarray = 300.0,
        damping: float | np.ndarray | None = None,
        damping_ratio: float = 1.0,
        posture: np.ndarray | None = None,
        posture_stiffness: float | np.ndarray = 20.0,
        posture_damping: float | np.ndarray | None = None,
        max_force: float | None = None,
    ) -> None:
        self.K = _spd("stiffness", stiffness, 3)
        # Isotropic K = k I (the common case) admits a cheaper critical damping: D = 2ζ√k Λ^{1/2}.
        self._k_iso = float(self.K[0, 0]) if np.allclose(self.K, self.K[0, 0] * np.eye(3)) else None
        self._mu, self._V, self._quat = np.zeros(3), np.zeros((3, 3)), np.zeros(4)
        self.D = None if damping is None else _spd("damping", damping, 3)
        if not (np.isfinite(damping_ratio) and damping_ratio > 0):
            raise ValueError(f"damping_ratio must be a finite number > 0, got {damping_ratio!r}")
        self.damping_ratio = float(damping_ratio)
        self.posture = None if posture is None else np.array(posture, dtype=float)
        if self.posture is not None and (self.posture.ndim != 1 or not np.all(np.isfinite(self.posture))):
            raise ValueError(f"posture must be a finite 1-D array of joint angles (rad), got {posture!r}")
        kq = np.asarray(posture_stiffness, dtype=float)
        if not np.all(np.isfinite(kq)) or np.any(kq < 0):
            raise ValueError(f"posture_stiffness must be finite and >= 0, got {posture_stiffness!r}")
        self.Kq = kq
        dq = 2.0 * np.sqrt(kq) if posture_damping is None else np.asarray(posture_damping, dtype=float)
        if not np.all(np.isfinite(dq)) or np.any(dq < 0):
            raise ValueError(f"posture_damping must be finite and >= 0, got {posture_damping!r}")
        self.Dq = dq
        if max_force is not None and not (np.isfinite(max_force) and max_force > 0):
            raise ValueError(f"max_force must be a finite number > 0 or None, got {max_force!r}")
        self.max_force = max_force

    def damping_for(self, Lambda: np.ndarray) -> np.ndarray:
        """The damping matrix used with task inertia ``Lambda`` (3, 3)."""
        if self.D is not None:
            return self.D
        L = np.linalg.cholesky(Lambda)
        Linv = np.linalg.inv(L)
        omega2, U = np.linalg.eigh(Linv @ self.K @ Linv.T)
        LU = L @ U
        return 2.0 * self.damping_ratio * (LU * np.sqrt(np.maximum(omega2, 0.0))) @ LU.T

    def torque(
        self,
        q: np.ndarray,
        qd: np.ndarray,
        x: np.ndarray,
        xd: np.ndarray,
        J: np.ndarray,
        Jdot_qd: np.ndarray,
        Minv: np.ndarray,
        bias: np.ndarray,
        x_des: np.ndarray,
        xd_des: np.ndarray | None = None,
        xdd_des: np.ndarray | None = None,
    ) -> np.ndarray:
        """Joint torque [N m], (n,).

        Args:
            q, qd: joint positions [rad] and velocities [rad/s], (n,).
            x, xd: tool position [m] and velocity [m/s], (3,).
            J: (3, n) tool translational Jacobian; Jdot_qd: (3,) J̇ q̇ [m/s²].
            Minv: (n, n) inverse joint-space inertia; bias: (n,) bias forces b [N m].
            x_des, xd_des, xdd_des: desired tool position, velocity, acceleration (3,)
                (velocity and acceleration default to zero: set-point regulation).
        """
        Lambda_inv = J @ Minv @ J.T
        mu, V = self._mu, self._V
        mujoco.mju_eig3(mu, V.reshape(9), self._quat, Lambda_inv.ravel())  # eigenvectors in columns
        mu = np.maximum(mu, 1e-9)  # regularised near kinematic singularities
        Lambda = (V / mu) @ V.T
        if self.D is None and self._k_iso is not None:
            D = (2.0 * self.damping_ratio * np.sqrt(self._k_iso)) * ((V / np.sqrt(mu)) @ V.T)
        else:
            D = self.damping_for(Lambda)
        accel = -Jdot_qd if xdd_des is None else xdd_des - Jdot_qd
        vel_err = -xd if xd_des is None else xd_des - xd
        F = Lambda @ accel + D @ vel_err + self.K @ (x_des - x)
        if self.max_force is not None:
            norm = float(np.linalg.norm(F))
            if norm > self.max_force:
                F *= self.max_force / norm
        tau = J.T @ F + bias
        if self.posture is not None:
            tau0 = self.Kq * (self.posture - q) - self.Dq * qd
            Jbar = Minv @ J.T @ Lambda  # (n, 3)
            tau += tau0 - J.T @ (Jbar.T @ tau0)
        return tau
