"""The Cartesian impedance law in compiled code (numba): the one implementation of
:class:`~c3bf_gym.controllers.CartesianImpedance`'s per-step math.

* :func:`impedance_law`: the torque from the tool's state, its Jacobian, ``M⁻¹`` and the bias
  forces (the module docstring of :mod:`c3bf_gym.controllers.impedance` has the math);
  :func:`critical_damping`: its damping matrix for a given task inertia; :func:`task_inertia`: that
  inertia, regularised.
* :func:`impedance_substep`: the same law on an arm's ``MjData`` between ``mj_step1`` and
  ``mj_step2``: ``(M + h D)⁻¹`` (:func:`c3bf_gym.safety._dynamics.step_inverse`, on a new state),
  the tool site's Jacobian, velocity and ``J̇ q̇`` (:func:`c3bf_gym.safety._dynamics.tool_site_dynamics`),
  then :func:`impedance_law`. The environment's compiled policy step calls it at every physics
  step (:func:`c3bf_gym.envs._kernels.policy_steps`), and so does
  :class:`~c3bf_gym.controllers.ImpedanceHook` from Python.

The 3×3 symmetric eigen-decompositions the law needs (the task inertia regularised near
singularities, critical damping) are cyclic Jacobi rotations (:func:`_eigh3`), to rounding the
decomposition MuJoCo's ``mju_eig3`` and numpy's ``eigh`` give. The kernels allocate nothing: the
caller's :class:`ImpedanceWork` holds every intermediate array. They are compiled without reference
counting, like the filter's (:data:`~c3bf_gym._compile_cache.STEP_KERNEL_OPTIONS`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from c3bf_gym._compile_cache import STEP_KERNEL_OPTIONS  # (before any @njit(cache=True): the cache keys)
from c3bf_gym.safety._dynamics import ArmMotion, SparseMass, ToolSite, step_inverse, tool_site_dynamics

__all__ = ["BoundImpedance", "ImpedanceGains", "ImpedanceWork", "TaskState", "Target", "critical_damping", "impedance_law",
           "impedance_substep", "task_inertia"]  # fmt: skip

_opts = STEP_KERNEL_OPTIONS

#: Eigenvalues of the inverse task inertia ``J M⁻¹ Jᵀ`` are clamped from below to this
#: [(m/s²)/N], so that ``Λ`` stays finite near kinematic singularities.
MIN_INVERSE_INERTIA = 1e-9


class ImpedanceGains(NamedTuple):
    """The law's settings, built once by :meth:`~c3bf_gym.controllers.CartesianImpedance.gains`.

    Attributes:
        stiffness: (3, 3) K [N/m], symmetric positive definite.
        damping: (3, 3) D [N s/m]; read only with ``fixed_damping``.
        fixed_damping: use ``damping``; otherwise the damping is critical, from the current task
            inertia (times ``damping_ratio``).
        isotropic: K = k I with ``k = k_iso`` [N/m]: critical damping is ``2 ζ √k Λ^{1/2}``.
        k_iso: k [N/m] when ``isotropic``.
        damping_ratio: ζ (1: critical).
        posture: (n,) q₀ [rad] of the null-space posture task; read only with ``has_posture``.
        posture_stiffness, posture_damping: (n,) K_q [N m/rad], D_q [N m s/rad].
        has_posture: add the posture task.
        max_force: bound on ‖F‖ [N] (inf: none).
    """

    stiffness: np.ndarray
    damping: np.ndarray
    fixed_damping: bool
    isotropic: bool
    k_iso: float
    damping_ratio: float
    posture: np.ndarray
    posture_stiffness: np.ndarray
    posture_damping: np.ndarray
    has_posture: bool
    max_force: float


class TaskState(NamedTuple):
    """What the law reads of the arm (n joints): ``q``, ``qd`` (n,) [rad, rad/s]; the tool's
    position ``x`` and velocity ``xd`` (3,) [m, m/s]; its translational Jacobian ``J`` (3, n) and
    ``Jdot_qd`` = J̇ q̇ (3,) [m/s²]; ``Minv`` (n, n), the inverse joint-space inertia; ``bias``
    (n,), the bias forces b [N m] (Coriolis, centrifugal, gravity)."""

    q: np.ndarray
    qd: np.ndarray
    x: np.ndarray
    xd: np.ndarray
    J: np.ndarray
    Jdot_qd: np.ndarray
    Minv: np.ndarray
    bias: np.ndarray


class Target(NamedTuple):
    """The desired tool motion (3,) each: position [m], velocity [m/s], acceleration [m/s²]."""

    pos: np.ndarray
    vel: np.ndarray
    acc: np.ndarray


class ImpedanceWork(NamedTuple):
    """Scratch of the law (written at every call): ``mats`` (7, 3, 3) for ``J M⁻¹ Jᵀ`` and its
    eigenvectors, ``Λ``, ``D`` and three temporaries; ``vec`` (3, 3) for eigenvalues, the task
    force ``F`` and a temporary; ``G`` (3, n) for ``J M⁻¹``; ``tau0`` (n,) for the posture torque."""

    mats: np.ndarray
    vec: np.ndarray
    G: np.ndarray
    tau0: np.ndarray

    @classmethod
    def of(cls, n: int) -> ImpedanceWork:
        return cls(np.zeros((7, 3, 3)), np.zeros((3, 3)), np.zeros((3, n)), np.zeros(n))


# ----------------------------------------------------------------------------- 3×3 linear algebra


@njit(**_opts)
def _eigh3(A, w, V):
    """Eigen-decomposition of the symmetric 3×3 ``A`` (overwritten): ``A = V diag(w) Vᵀ``,
    eigenvectors in the columns of ``V``, by cyclic Jacobi rotations until the off-diagonal part is
    below 1e-15 of the matrix's size (quadratic convergence: a few sweeps)."""
    for i in range(3):
        for j in range(3):
            V[i, j] = 1.0 if i == j else 0.0
    scale = 0.0
    for i in range(3):
        for j in range(3):
            scale += A[i, j] * A[i, j]
    for _ in range(50):
        off = A[0, 1] * A[0, 1] + A[0, 2] * A[0, 2] + A[1, 2] * A[1, 2]
        if off <= 1e-30 * scale:
            break
        for p in range(2):
            for q in range(p + 1, 3):
                apq = A[p, q]
                if apq == 0.0:
                    continue
                theta = (A[q, q] - A[p, p]) / (2.0 * apq)
                t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for k in range(3):  # A ← Rᵀ A R, R the rotation in the (p, q) plane
                    akp, akq = A[k, p], A[k, q]
                    A[k, p] = c * akp - s * akq
                    A[k, q] = s * akp + c * akq
                for k in range(3):
                    apk, aqk = A[p, k], A[q, k]
                    A[p, k] = c * apk - s * aqk
                    A[q, k] = s * apk + c * aqk
                A[p, q] = A[q, p] = 0.0
                for k in range(3):
                    vkp, vkq = V[k, p], V[k, q]
                    V[k, p] = c * vkp - s * vkq
                    V[k, q] = s * vkp + c * vkq
    for i in range(3):
        w[i] = A[i, i]


@njit(**_opts)
def _compose(V, w, out):
    """``out = V diag(w) Vᵀ`` (3×3)."""
    for i in range(3):
        for j in range(3):
            acc = 0.0
            for k in range(3):
                acc += V[i, k] * w[k] * V[j, k]
            out[i, j] = acc


@njit(**_opts)
def critical_damping(Lambda, K, zeta, work, D):
    """The damping ``D`` (3, 3) [N s/m] that makes ``Λ ë + D ė + K e = 0`` critically damped
    (times ``zeta``): ``D = 2 ζ L U diag(ω) Uᵀ Lᵀ`` with ``Λ = L Lᵀ`` (Cholesky) and
    ``L⁻¹ K L⁻ᵀ = U diag(ω²) Uᵀ``. ``Lambda`` (3, 3) symmetric positive definite; ``work``: an
    :class:`ImpedanceWork` (its ``mats[4:7]`` and ``vec[2]`` are used). A ``Lambda`` that is not
    positive definite gives NaN."""
    L, Linv, A = work.mats[4], work.mats[5], work.mats[6]
    w = work.vec[2]
    for i in range(3):  # Cholesky, Λ = L Lᵀ
        for j in range(3):
            L[i, j] = 0.0
        for j in range(i + 1):
            acc = Lambda[i, j]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            L[i, j] = math.sqrt(acc) if i == j else acc / L[j, j]
    for j in range(3):  # L⁻¹, lower triangular
        for i in range(3):
            acc = 1.0 if i == j else 0.0
            for k in range(i):
                acc -= L[i, k] * Linv[k, j]
            Linv[i, j] = acc / L[i, i] if i >= j else 0.0
    for i in range(3):  # A = L⁻¹ K L⁻ᵀ
        for j in range(3):
            acc = 0.0
            for a in range(3):
                for b in range(3):
                    acc += Linv[i, a] * K[a, b] * Linv[j, b]
            A[i, j] = acc
    _eigh3(A, w, D)  # D holds U for now
    for i in range(3):  # A = L U
        for j in range(3):
            acc = 0.0
            for k in range(3):
                acc += L[i, k] * D[k, j]
            A[i, j] = acc
    for k in range(3):
        w[k] = 2.0 * zeta * math.sqrt(max(w[k], 0.0))
    _compose(A, w, D)


# ----------------------------------------------------------------------------- the law


@njit(**_opts)
def task_inertia(G, J, work):
    """The tool's task inertia ``Λ`` [kg] from ``G = J M⁻¹`` (3, n) [(m/s²)/(N m)] and the tool
    Jacobian ``J`` (3, n), regularised near kinematic singularities::

        Λ⁻¹ = G Jᵀ = V diag(μ) Vᵀ,  μ ← max(μ, MIN_INVERSE_INERTIA),  Λ = V diag(1/μ) Vᵀ

    Writes ``Λ`` to ``work.mats[2]``, ``V`` to ``work.mats[1]``, the clamped ``μ`` to
    ``work.vec[0]`` (``work``: :class:`ImpedanceWork`; ``work.mats[0]`` and ``work.vec[1]`` are
    overwritten as scratch). The one implementation of the controller's ``Λ``:
    :func:`impedance_law` calls it, and so does :class:`~c3bf_gym.wrappers.AppliedAction` to map
    a torque back to the task force."""
    n = J.shape[1]
    Linv_task, V, Lam = work.mats[0], work.mats[1], work.mats[2]
    mu, inv = work.vec[0], work.vec[1]
    for i in range(3):
        for j in range(3):
            acc = 0.0
            for k in range(n):
                acc += G[i, k] * J[j, k]
            Linv_task[i, j] = acc
    for i in range(3):  # symmetric to rounding; the eigen-solver reads both triangles
        for j in range(i):
            Linv_task[i, j] = Linv_task[j, i] = 0.5 * (Linv_task[i, j] + Linv_task[j, i])
    _eigh3(Linv_task, mu, V)
    for k in range(3):
        mu[k] = max(mu[k], MIN_INVERSE_INERTIA)
        inv[k] = 1.0 / mu[k]
    _compose(V, inv, Lam)


@njit(**_opts)
def impedance_law(gains, state, target, work, tau):
    """The impedance torque ``tau`` (n,) [N m] (``gains``: :class:`ImpedanceGains`, ``state``:
    :class:`TaskState`, ``target``: :class:`Target`, ``work``: :class:`ImpedanceWork`)::

        Λ⁻¹ = J M⁻¹ Jᵀ = V diag(μ) Vᵀ,  μ ← max(μ, MIN_INVERSE_INERTIA),  Λ = V diag(1/μ) Vᵀ
        F = Λ (ẍ_d − J̇q̇) + D (ẋ_d − ẋ) + K (x_d − x),   scaled to ‖F‖ ≤ max_force
        τ = Jᵀ F + b + τ₀ − Jᵀ J̄ᵀ τ₀,   J̄ = M⁻¹ Jᵀ Λ,   τ₀ = K_q (q₀ − q) − D_q q̇  (with a posture)

    with ``D`` given, ``2 ζ √k V diag(1/√μ) Vᵀ`` (= 2 ζ √k Λ^{1/2}) for ``K = k I``, or
    :func:`critical_damping` of ``Λ``. Non-finite inputs give non-finite torques (no exception)."""
    J, Minv = state.J, state.Minv
    n = J.shape[1]
    G = work.G
    V, Lam, D = work.mats[1], work.mats[2], work.mats[3]
    mu, F = work.vec[0], work.vec[1]
    for i in range(3):  # G = J M⁻¹, Λ⁻¹ = G Jᵀ
        for k in range(n):
            acc = 0.0
            for j in range(n):
                acc += J[i, j] * Minv[j, k]
            G[i, k] = acc
    task_inertia(G, J, work)
    if gains.fixed_damping:
        for i in range(3):
            for j in range(3):
                D[i, j] = gains.damping[i, j]
    elif gains.isotropic:
        scale = 2.0 * gains.damping_ratio * math.sqrt(gains.k_iso)
        for k in range(3):
            F[k] = scale / math.sqrt(mu[k])
        _compose(V, F, D)
    else:
        critical_damping(Lam, gains.stiffness, gains.damping_ratio, work, D)
    K, x, xd = gains.stiffness, state.x, state.xd
    norm2 = 0.0
    for i in range(3):
        acc = 0.0
        for j in range(3):
            acc += Lam[i, j] * (target.acc[j] - state.Jdot_qd[j])
            acc += D[i, j] * (target.vel[j] - xd[j])
            acc += K[i, j] * (target.pos[j] - x[j])
        F[i] = acc
        norm2 += acc * acc
    norm = math.sqrt(norm2)
    if norm > gains.max_force:
        shrink = gains.max_force / norm
        for i in range(3):
            F[i] *= shrink
    for j in range(n):
        tau[j] = J[0, j] * F[0] + J[1, j] * F[1] + J[2, j] * F[2] + state.bias[j]
    if gains.has_posture:
        tau0 = work.tau0
        for j in range(n):
            tau0[j] = gains.posture_stiffness[j] * (gains.posture[j] - state.q[j]) - gains.posture_damping[j] * state.qd[j]
        # J̄ᵀ τ₀ = Λ G τ₀ (G = J M⁻¹, M⁻¹ symmetric), then τ += τ₀ − Jᵀ (J̄ᵀ τ₀)
        for i in range(3):
            acc = 0.0
            for j in range(n):
                acc += G[i, j] * tau0[j]
            mu[i] = acc  # (mu is no longer needed)
        for i in range(3):
            acc = 0.0
            for k in range(3):
                acc += Lam[i, k] * mu[k]
            F[i] = acc
        for j in range(n):
            tau[j] += tau0[j] - (J[0, j] * F[0] + J[1, j] * F[1] + J[2, j] * F[2])


class BoundImpedance(NamedTuple):
    """The law bound to one arm's ``MjData``: what :func:`impedance_substep` reads and writes
    besides the torque (views and buffers, made once by
    :class:`~c3bf_gym.controllers.ImpedanceHook`).

    Attributes:
        arm: the filter's :class:`~c3bf_gym.safety._dynamics.ArmArrays` (views of the
            ``MjData`` and the arm's ``Minv``, ``qacc_free``).
        site: the tool site (:class:`~c3bf_gym.safety._dynamics.ToolSite`; the law's own scratch).
        gains: :class:`ImpedanceGains`.
        target: :class:`Target`, read at every call.
        work: :class:`ImpedanceWork`.
    """

    arm: tuple
    site: ToolSite
    gains: ImpedanceGains
    target: Target
    work: ImpedanceWork


@njit(**_opts)
def impedance_substep(stage, law, tau):
    """:func:`impedance_law` on the arm's current ``MjData`` (after ``mj_step1``), into ``tau``
    (n,) [N m], with the views and buffers of ``law`` (:class:`BoundImpedance`).

    With ``stage`` 2 (a state whose dynamics are not yet computed) the arm's
    ``Minv = (M + h D)⁻¹`` and ``qacc_free`` are refreshed first
    (:func:`~c3bf_gym.safety._dynamics.step_inverse`), otherwise they are read as they are. The
    tool site's Jacobian ``J``, velocity ``J q̇`` and ``J̇ q̇`` come from
    :func:`~c3bf_gym.safety._dynamics.tool_site_dynamics` (MuJoCo's ``cdof`` and ``cdof_dot``: the
    values of ``mj_jacSite`` and ``mj_jacDot``, to rounding). The torque is the total joint torque
    (bias forces included), the law's ``M⁻¹`` the integrator's ``(M + h D)⁻¹``.
    """
    arm, site = law.arm, law.site
    if stage >= 2:
        step_inverse(SparseMass(arm.M, arm.M_rowadr, arm.M_rownnz, arm.M_colind), arm.damping, arm.qfrc_passive,
                     arm.qfrc_bias, arm.factor, arm.Minv, arm.qacc_free)
    tool_site_dynamics(site, ArmMotion(arm.cdof, arm.cdof_dot, arm.com, arm.qvel, arm.Minv, site.zero))
    packed = site.packed
    state = TaskState(arm.qpos, arm.qvel, packed[0, :, 0], packed[0, :, 1], site.jac[0], packed[0, :, 2], arm.Minv,
                      arm.qfrc_bias)
    impedance_law(law.gains, state, law.target, law.work, tau)
