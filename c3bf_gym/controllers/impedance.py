"""Cartesian impedance control of the tool position (the paper's eq. 4), as a pure class.

    F = Λ (ẍ_d − J̇q̇) + D (ẋ_d − ẋ) + K (x_d − x)
    τ = Jᵀ F + b + N τ₀,   τ₀ = K_q (q₀ − q) − D_q q̇

with ``Λ = (J M⁻¹ Jᵀ)⁻¹`` the task-space inertia, ``b`` the bias forces (Coriolis, centrifugal,
gravity: MuJoCo's ``qfrc_bias``), and ``N = I − Jᵀ J̄ᵀ``, ``J̄ = M⁻¹ Jᵀ Λ`` the dynamically
consistent null-space projector, so the posture term ``τ₀`` (pulling the redundant joints
towards ``q₀``) does not disturb the tool. With ``damping=None`` the damping is critical for the
closed loop ``Λ ë + D ė + K e = 0``: ``D = 2 L U diag(ω) Uᵀ Lᵀ`` where ``Λ = L Lᵀ`` and
``L⁻¹ K L⁻ᵀ = U diag(ω²) Uᵀ`` (for ``K = k I`` this is ``2 √k Λ^{1/2}``).

Near a kinematic singularity ``J M⁻¹ Jᵀ`` loses rank: its eigenvalues are clamped from below at
:data:`~c3bf_gym.controllers._kernels.MIN_INVERSE_INERTIA` before it is inverted, so ``Λ`` stays
finite. ``M⁻¹`` is whatever the caller passes; the environment's hook passes the integrator's
``(M + h D)⁻¹`` (:class:`~c3bf_gym.safety.dynamics.ArmModel`).

The per-step math exists once, compiled: :func:`c3bf_gym.controllers._kernels.impedance_law`.
:meth:`CartesianImpedance.torque` calls it from Python; the environment calls it at every physics
step from its own compiled policy step (:class:`ImpedanceHook`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

import numpy as np

from c3bf_gym.controllers._kernels import (
    BoundImpedance,
    ImpedanceGains,
    ImpedanceWork,
    Target,
    TaskState,
    critical_damping,
    impedance_law,
    impedance_substep,
)
from c3bf_gym.safety._dynamics import ToolSite

if TYPE_CHECKING:
    from c3bf_gym.envs.reach import C3BFReachEnv

__all__ = ["CartesianImpedance", "ImpedanceHook", "Trajectory"]

#: ``t [s] -> (position, velocity, acceleration)`` of the tool target, (3,) each [m, m/s, m/s²].
Trajectory = Callable[[float], tuple[np.ndarray, np.ndarray, np.ndarray]]


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

    Raises:
        ValueError: a gain of the wrong shape, not finite, not symmetric positive definite (K,
            D), negative (K_q, D_q) or not > 0 (ζ, max_force); a posture that is not a finite 1-D
            array.
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

    def gains(self, n: int) -> ImpedanceGains:
        """The settings as the compiled law reads them, for an arm of ``n`` joints (new arrays:
        later changes to this object's attributes do not reach them).

        Raises:
            ValueError: the posture, K_q or D_q do not have ``n`` entries (or one, for K_q, D_q).
        """
        with_posture = self.posture is not None
        posture = self.posture if with_posture else np.zeros(n)
        if posture.shape != (n,):
            raise ValueError(f"the controller's posture has {posture.size} joint angles; the arm has {n}")
        stiffness, damping = [], []
        for name, value, out in (("posture_stiffness", self.Kq, stiffness), ("posture_damping", self.Dq, damping)):
            if value.ndim > 1 or value.size not in (1, n):
                raise ValueError(f"{name} must be a scalar or ({n},) for an arm of {n} joints, got shape {value.shape}")
            out.append(np.ascontiguousarray(np.broadcast_to(value, (n,)), dtype=np.float64))
        return ImpedanceGains(
            np.ascontiguousarray(self.K), np.ascontiguousarray(self.D if self.D is not None else np.zeros((3, 3))),
            self.D is not None, self._k_iso is not None, 0.0 if self._k_iso is None else self._k_iso,
            self.damping_ratio, np.ascontiguousarray(posture, dtype=np.float64), stiffness[0], damping[0],
            with_posture, np.inf if self.max_force is None else float(self.max_force),
        )  # fmt: skip

    def damping_for(self, Lambda: np.ndarray) -> np.ndarray:
        """The damping matrix (3, 3) [N s/m] used with task inertia ``Lambda`` (3, 3) [kg]: ``D``
        when given, else critical (times ζ) for ``Λ ë + D ė + K e = 0``
        (:func:`~c3bf_gym.controllers._kernels.critical_damping`; NaN for a ``Lambda`` that is not
        positive definite)."""
        if self.D is not None:
            return self.D
        Lambda = np.ascontiguousarray(Lambda, dtype=np.float64)
        if Lambda.shape != (3, 3):
            raise ValueError(f"Lambda must have shape (3, 3), got {Lambda.shape}")
        D = np.empty((3, 3))
        critical_damping(Lambda, self.K, self.damping_ratio, ImpedanceWork.of(1), D)
        return D

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
        """Joint torque [N m], (n,) (:func:`~c3bf_gym.controllers._kernels.impedance_law`).

        Args:
            q, qd: joint positions [rad] and velocities [rad/s], (n,).
            x, xd: tool position [m] and velocity [m/s], (3,).
            J: (3, n) tool translational Jacobian; Jdot_qd: (3,) J̇ q̇ [m/s²].
            Minv: (n, n) inverse joint-space inertia; bias: (n,) bias forces b [N m].
            x_des, xd_des, xdd_des: desired tool position, velocity, acceleration (3,)
                (velocity and acceleration default to zero: set-point regulation).

        Raises:
            ValueError: an argument of the wrong shape, or a posture of another length than ``q``.
        """
        f64 = np.ascontiguousarray
        J = f64(J, dtype=np.float64)
        if J.ndim != 2 or J.shape[0] != 3:
            raise ValueError(f"J must have shape (3, n), got {J.shape}")
        n = J.shape[1]
        zero = np.zeros(3)
        args = {"q": q, "qd": qd, "x": x, "xd": xd, "Jdot_qd": Jdot_qd, "Minv": Minv, "bias": bias, "x_des": x_des,
                "xd_des": zero if xd_des is None else xd_des, "xdd_des": zero if xdd_des is None else xdd_des}
        shapes = {"q": (n,), "qd": (n,), "Minv": (n, n), "bias": (n,)}
        for name, value in args.items():
            args[name] = value = f64(value, dtype=np.float64)
            if value.shape != shapes.get(name, (3,)):
                raise ValueError(f"{name} must have shape {shapes.get(name, (3,))}, got {value.shape}")
        a = args
        state = TaskState(a["q"], a["qd"], a["x"], a["xd"], J, a["Jdot_qd"], a["Minv"], a["bias"])
        tau = np.empty(n)
        impedance_law(self.gains(n), state, Target(a["x_des"], a["xd_des"], a["xdd_des"]), ImpedanceWork.of(n), tau)
        return tau


class ImpedanceHook:
    """The ``nominal`` torque hook of :class:`~c3bf_gym.envs.C3BFReachEnv`: a
    :class:`CartesianImpedance` law towards a tool target.

    The target is either fixed by its owner (``set_target``: position, velocity, acceleration,
    held until the next call) or, with ``trajectory``, evaluated at the simulation time of every
    physics step. The posture task's ``q₀`` can be moved the same way (``set_posture``). The
    commanded torque arriving at the hook is replaced by the controller's.

    The law is :func:`c3bf_gym.controllers._kernels.impedance_substep` on the environment's arm
    (its ``Minv``, shared with the filter, and the tool site's Jacobian and ``J̇ q̇``), called
    from Python through :meth:`__call__`, or, without a ``trajectory``, from the environment's
    compiled policy step (:meth:`compiled_call`), the safety filter's calls beside it: the same
    torques, to rounding. A ``trajectory`` is a Python function, so with one every physics step
    comes back to Python.

    Args:
        env: the unwrapped :class:`~c3bf_gym.envs.C3BFReachEnv`.
        controller: the law; its settings are read once, here (:meth:`CartesianImpedance.gains`):
            later changes to its attributes do not reach this hook.
        trajectory: ``t [s] -> (position, velocity, acceleration)`` (3,) each, or None.

    Raises:
        ValueError: the controller's posture (or posture gains) does not have one entry per dof.
    """

    def __init__(self, env: C3BFReachEnv, controller: CartesianImpedance, trajectory: Trajectory | None = None) -> None:
        n = env.model.nv
        gains = controller.gains(n)
        self.gains = gains._replace(posture=gains.posture.copy())  # set_posture writes it, not the controller's
        self.env = env
        self.controller = controller
        self.trajectory = trajectory
        self.arm = env.arm
        self.target_pos = env.data.site_xpos[env.ee_site_id].copy()
        self.target_vel = np.zeros(3)
        self.target_acc = np.zeros(3)
        self._target = Target(self.target_pos, self.target_vel, self.target_acc)  # views: set_target updates it
        self._site = ToolSite.of(env.data.site_xpos[env.ee_site_id], self.arm.site_chain)
        self._work = ImpedanceWork.of(n)
        self._bound: BoundImpedance | None = None

    def set_target(self, pos: np.ndarray, vel: np.ndarray | None = None, acc: np.ndarray | None = None) -> None:
        """Hold the tool target ``pos`` [m], ``vel`` [m/s], ``acc`` [m/s²] (3,) each (None: zero)."""
        self.target_pos[:] = pos
        self.target_vel[:] = 0.0 if vel is None else vel
        self.target_acc[:] = 0.0 if acc is None else acc

    def set_posture(self, posture: np.ndarray) -> None:
        """Hold the posture task's ``q₀`` (n,) [rad] until the next call (the controller's posture
        until the first).

        Raises:
            ValueError: the controller has no posture task, or ``posture`` is not n finite angles.
        """
        if not self.gains.has_posture:
            raise ValueError("this controller has no posture task to move: build it with posture=")
        q0 = np.asarray(posture, dtype=float)
        if q0.shape != self.gains.posture.shape or not np.isfinite(q0).all():
            raise ValueError(f"posture must be {self.gains.posture.size} finite joint angles (rad), got {posture!r}")
        self.gains.posture[:] = q0

    def _law(self) -> BoundImpedance:
        """The law bound to the environment's arrays (views), gathered once."""
        if self._bound is None:
            self._bound = BoundImpedance(self.arm.kernel_arrays(self.env.data), self._site, self.gains, self._target,
                                         self._work)  # fmt: skip
        return self._bound

    def compiled_call(self) -> BoundImpedance | None:
        """What the environment's compiled policy step
        (:func:`c3bf_gym.envs._kernels.policy_steps`) passes to
        :func:`~c3bf_gym.controllers._kernels.impedance_substep` at every physics step; None with a
        ``trajectory``, which only Python can evaluate."""
        return None if self.trajectory is not None else self._law()

    def __call__(self, tau: np.ndarray) -> np.ndarray:
        """The controller's total torque (n,) [N m] for the current state (``tau`` is ignored)."""
        env = self.env
        if self.trajectory is not None:
            self.set_target(*self.trajectory(env.data.time))
        self.arm.update(env.data, env.state_version)
        out = np.empty(env.model.nv)
        impedance_substep(0, self._law(), out)
        return out
