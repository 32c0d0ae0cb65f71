"""Reference implementations that only the tests use: the arm's closest-point dynamics in plain
numpy (the compiled kernels are checked against them, and they against MuJoCo), material point
dynamics, and a barrier's value and gradients.

They read an :class:`~c3bf_gym.safety.dynamics.ArmModel`'s packed capsule ends (``_ends_a``, ``_ends_ab``:
``[pos | vel | c | G]`` at end a and the difference to end b, (S, 3, 3 + nv)), computed by
``arm.update(data)`` in the same physics step."""

from __future__ import annotations

import mujoco
import numpy as np

from c3bf_gym.safety.dynamics import ArmModel, PointDynamics


def _axis_parameter(arm: ArmModel, centres: np.ndarray) -> np.ndarray:
    """(K, S) ``t = ((o − a) · (b − a)) / |b − a|²`` before clamping (0 at end a, 1 at b; 0 on a
    sphere)."""
    t = centres @ arm._ends_ab[:, :, 0].T
    t -= arm._a_dot_ab
    np.divide(t, arm._length2, out=t, where=arm._length2 > 0.0)
    t[:, arm._length2 == 0.0] = 0.0
    return t


def closest_dynamics(arm: ArmModel, centres: np.ndarray) -> PointDynamics:
    """:class:`PointDynamics` of the point on every capsule axis closest to every centre (K, 3):
    leading dimension ``K * S``, obstacle-major (row ``k * S + s``); ``jac`` is None."""
    arm._ensure_ends()
    t = np.clip(_axis_parameter(arm, centres), 0.0, 1.0)
    packed = t[:, :, None, None] * arm._ends_ab + arm._ends_a
    return arm._unpack(packed)


def closest_sliding(arm: ArmModel, centres: np.ndarray, p: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The sliding terms ``(ṫ (b − a), ṫ (ḃ − ȧ))`` (K * S, 3) of the closest points' ``ṗ`` and
    ``v̇``, with ``ṫ = −(⟨v, b − a⟩ + ⟨p, ḃ − ȧ⟩) / |b − a|²`` inside the segment and 0 at a
    clamped end (:meth:`~c3bf_gym.safety.dynamics.ArmModel.closest_relative`'s derivation)."""
    arm._ensure_ends()
    k, s = len(centres), len(arm.capsule_ids)
    t = _axis_parameter(arm, centres)
    ab = arm._ends_ab
    rate = np.vecdot(v.reshape(k, s, 3), ab[:, :, 0]) + np.vecdot(p.reshape(k, s, 3), ab[:, :, 1])
    np.divide(rate, -arm._length2, out=rate, where=arm._length2 > 0.0)
    rate = (rate * ((t > 0.0) & (t < 1.0)))[..., None]
    return (rate * ab[:, :, 0]).reshape(-1, 3), (rate * ab[:, :, 1]).reshape(-1, 3)


def point_dynamics(arm: ArmModel, data, points: np.ndarray, chain: np.ndarray) -> PointDynamics:
    """:class:`PointDynamics` of ``points`` (P, 3) moving with bodies whose dof masks are
    ``chain`` (P, nv), through the compiled per-point kernel (``arm.update`` first)."""
    from c3bf_gym.safety import _dynamics

    n = len(points)
    packed = np.empty((n, 3, 3 + arm.nv))
    packed[:, :, 0] = points
    jac = np.empty((n, 3, arm.nv))
    view = arm.views(data)
    motion = _dynamics.ArmMotion(view.cdof, view.cdof_dot, view.com, view.qvel, arm.Minv, arm.qacc_free)
    _dynamics.point_dynamics(np.ascontiguousarray(chain, dtype=np.float64), motion, packed, jac)
    return PointDynamics(points, packed[:, :, 1], jac, packed[:, :, 3:], packed[:, :, 2])


def partials(barrier, p, v, r) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A barrier's value and both gradients ``(h (P,), ∂h/∂p (P, 3), ∂h/∂v (P, 3))`` from its
    :meth:`~c3bf_gym.safety.barriers.Barrier.terms`."""
    t = barrier.terms(p, v, r)
    return t.h, t.grad_p, t.grad_v


def _norm(x: np.ndarray) -> float:
    """The length of a 3-vector, its squares summed in order. The numpy loop used
    ``np.linalg.norm``, whose dot product goes through BLAS: its kernel, and with it the rounding,
    depends on the CPU (with AVX-512 about a fifth of such sums differ from the in-order one).
    numpy's sum of fewer than 8 numbers runs in order on every CPU, as the compiled sampler does."""
    return float(np.sqrt(np.sum(x * x)))


def sample_obstacle(envelope, spec, start, goal, rng, arm_a, arm_b, arm_radius, max_attempts=200):
    """The obstacle sampler's attempts (:meth:`c3bf_gym.scenarios.ObstacleSampler.sample`) as the
    numpy loop it was before it was compiled: ``(position, velocity, radius)`` or None. The compiled
    sampler must give the same draws and samples, bit for bit."""
    from c3bf_gym.safety.dynamics import segment_closest_points

    path = goal - start
    length = _norm(path)
    direction = path / length if length > 0 else np.array([1.0, 0.0, 0.0])
    for _ in range(max_attempts):
        radius = float(rng.uniform(*envelope.radius_range))
        target = start + rng.uniform(*spec.path_fraction) * path
        target = target + rng.normal(size=3) * spec.lateral_jitter
        if spec.kind == "static":
            velocity = np.zeros(3)
            position = target
        else:
            speed = float(rng.uniform(*envelope.speed_range))
            if spec.kind == "head_on":
                heading = -direction
            else:
                helper = np.array([0.0, 0.0, 1.0]) if abs(direction[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
                normal = np.cross(direction, helper)
                normal /= _norm(normal)
                binormal = np.cross(direction, normal)
                roll = rng.uniform(0.0, 2.0 * np.pi)
                side = np.cos(roll) * normal + np.sin(roll) * binormal
                angle = np.deg2rad(rng.uniform(*spec.crossing_angle))
                heading = np.cos(angle) * direction + np.sin(angle) * side
            velocity = speed * heading
            position = target - velocity * rng.uniform(*spec.meet_time)
        if len(arm_radius):
            closest = segment_closest_points(arm_a, arm_b, position[None])[0]
            clearance = float((np.linalg.norm(position - closest, axis=1) - arm_radius - radius).min())
        else:
            clearance = np.inf
        if envelope.contains(position) and envelope.path_ok(position, velocity, radius) and (
                clearance >= envelope.spawn_clearance):
            return position, velocity, radius
    return None


def impedance_torque(ctrl, q, qd, x, xd, J, Jdot_qd, Minv, bias, x_des, xd_des=None, xdd_des=None) -> np.ndarray:
    """The Cartesian impedance law of :class:`~c3bf_gym.controllers.CartesianImpedance` ``ctrl`` in
    plain numpy (its settings read from the object; the law's formula in the module docstring of
    :mod:`c3bf_gym.controllers.impedance`): the oracle of the compiled law. The task inertia's
    eigenvalues are clamped at 1e-9 as the law's; critical damping from ``numpy.linalg.eigh``."""
    mu, V = np.linalg.eigh(J @ Minv @ J.T)
    mu = np.maximum(mu, 1e-9)
    Lambda = (V / mu) @ V.T
    if ctrl.D is not None:
        D = ctrl.D
    else:
        L = np.linalg.cholesky(Lambda)
        Linv = np.linalg.inv(L)
        omega2, U = np.linalg.eigh(Linv @ ctrl.K @ Linv.T)
        LU = L @ U
        D = 2.0 * ctrl.damping_ratio * (LU * np.sqrt(np.maximum(omega2, 0.0))) @ LU.T
    accel = -Jdot_qd if xdd_des is None else xdd_des - Jdot_qd
    vel_err = -xd if xd_des is None else xd_des - xd
    F = Lambda @ accel + D @ vel_err + ctrl.K @ (x_des - x)
    if ctrl.max_force is not None:
        norm = float(np.linalg.norm(F))
        if norm > ctrl.max_force:
            F *= ctrl.max_force / norm
    tau = J.T @ F + bias
    if ctrl.posture is not None:
        tau0 = ctrl.Kq * (ctrl.posture - q) - ctrl.Dq * qd
        Jbar = Minv @ J.T @ Lambda
        tau += tau0 - J.T @ (Jbar.T @ tau0)
    return tau


def tool_acceleration_gain(model, data, site_id: int, scale: np.ndarray) -> np.ndarray:
    """(3, nv) ``G = J (M + hD)⁻¹ diag(scale)``, the tool site's acceleration per unit of the
    scaled torque, from MuJoCo's own ``mj_jacSite`` and ``mj_fullM`` (the filter's ``"tool"``
    metric, independent of its kernels; ``hD`` the implicit damping, the arm the model's every
    dof)."""
    jac, M = np.zeros((3, model.nv)), np.zeros((model.nv, model.nv))
    mujoco.mj_jacSite(model, data, jac, None, site_id)
    mujoco.mj_fullM(model, data, M)
    return jac @ np.linalg.inv(M + np.diag(model.opt.timestep * model.dof_damping)) * scale
