"""Tests for c3bf_gym/controllers/impedance.py (and its hook/wrapper in c3bf_gym/wrappers.py).

The control law is checked algebraically on random inertias and Jacobians (the closed-loop task
dynamics, critical damping, the null-space property) and in closed loop on the real arm (a
0.15 m step is reached, without overshoot).
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from c3bf_gym import CartesianImpedance, CartesianImpedanceAction
from c3bf_gym.wrappers import ImpedanceHook, default_impedance

STEP = 0.15  # m


# ----------------------------------------------------------------------------- helpers


def random_problem(rng, n=6):
    """A random SPD inertia, a full-rank 3 x n Jacobian and a state."""
    L = rng.normal(size=(n, n))
    M = L @ L.T + 0.5 * np.eye(n)
    J = rng.normal(size=(3, n))
    return dict(
        q=rng.normal(size=n), qd=rng.normal(size=n), x=rng.normal(size=3), xd=rng.normal(size=3), J=J,
        Jdot_qd=rng.normal(size=3), Minv=np.linalg.inv(M), bias=rng.normal(size=n),
        x_des=rng.normal(size=3), xd_des=rng.normal(size=3), xdd_des=rng.normal(size=3),
    )  # fmt: skip


def random_spd(rng, size=3, low=50.0, high=500.0):
    Q, _ = np.linalg.qr(rng.normal(size=(size, size)))
    return Q @ np.diag(rng.uniform(low, high, size)) @ Q.T


def sqrtm_spd(A):
    w, V = np.linalg.eigh(A)
    return (V * np.sqrt(w)) @ V.T


# ----------------------------------------------------------------------------- validation

BAD = [
    (dict(stiffness=-1.0), "stiffness.*positive definite"),
    (dict(stiffness=0.0), "stiffness.*positive definite"),
    (dict(stiffness=[[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), "stiffness.*positive definite"),
    (dict(stiffness=[[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), "stiffness.*symmetric"),
    (dict(stiffness=[100.0, 100.0]), r"stiffness.*\(3,\)"),
    (dict(stiffness=np.eye(4)), r"stiffness.*\(3, 3\)"),
    (dict(stiffness=np.ones((3, 4))), r"stiffness.*\(3, 3\)"),
    (dict(stiffness=[100.0, np.nan, 100.0]), "stiffness.*finite"),
    (dict(stiffness=[100.0, -5.0, 100.0]), "stiffness.*positive definite"),
    (dict(damping=-3.0), "damping.*positive definite"),
    (dict(damping=np.zeros((3, 3))), "damping.*positive definite"),
    (dict(damping=[1.0, 2.0, 3.0, 4.0]), r"damping.*\(3,\)"),
    (dict(damping_ratio=0.0), "damping_ratio"),
    (dict(damping_ratio=-1.0), "damping_ratio"),
    (dict(damping_ratio=np.nan), "damping_ratio"),
    (dict(posture_stiffness=-1.0), "posture_stiffness"),
    (dict(posture_stiffness=[1.0, np.inf]), "posture_stiffness"),
    (dict(posture_damping=-0.1), "posture_damping"),
    (dict(max_force=0.0), "max_force"),
    (dict(max_force=-10.0), "max_force"),
    (dict(max_force=np.inf), "max_force"),
]


@pytest.mark.parametrize("kwargs, message", BAD, ids=[f"{list(k)[0]}={list(k.values())[0]!r}"[:40] for k, _ in BAD])
def test_bad_parameters_rejected(kwargs, message):
    with pytest.raises(ValueError, match=message):
        CartesianImpedance(**kwargs)


def test_good_parameter_forms_accepted():
    rng = np.random.default_rng(0)
    for stiffness in (300.0, [100.0, 200.0, 300.0], random_spd(rng)):
        CartesianImpedance(stiffness=stiffness, damping=None)
        CartesianImpedance(stiffness=stiffness, damping=random_spd(rng, low=5, high=50))
    CartesianImpedance(posture=np.zeros(6), posture_stiffness=np.arange(6.0), posture_damping=0.0, max_force=1.0)


# ----------------------------------------------------------------------------- the law


@pytest.mark.parametrize("seed", range(10))
def test_task_space_closed_loop_without_posture(seed):
    """Without a posture task, ẍ = J M⁻¹(τ − b) + J̇q̇ = ẍ_d + Λ⁻¹ [D (ẋ_d − ẋ) + K (x_d − x)]."""
    rng = np.random.default_rng(seed)
    p = random_problem(rng)
    K = random_spd(rng) if seed % 2 else 300.0
    D = None if seed % 3 else random_spd(rng, low=5.0, high=50.0)
    ctrl = CartesianImpedance(stiffness=K, damping=D)
    tau = ctrl.torque(**p)
    J, Minv = p["J"], p["Minv"]
    Lambda = np.linalg.inv(J @ Minv @ J.T)
    Dm = ctrl.damping_for(Lambda) if D is None else D
    Km = np.eye(3) * K if np.ndim(K) == 0 else K
    acc = J @ Minv @ (tau - p["bias"]) + p["Jdot_qd"]
    expected = p["xdd_des"] + np.linalg.solve(Lambda, Dm @ (p["xd_des"] - p["xd"]) + Km @ (p["x_des"] - p["x"]))
    np.testing.assert_allclose(acc, expected, rtol=1e-7, atol=1e-7 * np.abs(expected).max())


@pytest.mark.parametrize("seed", range(10))
def test_default_damping_is_critical(seed):
    """D makes Λ ë + D ė + K e = 0 critically damped: in the coordinates where Λ = I,
    (L⁻¹ D L⁻ᵀ)² = 4 L⁻¹ K L⁻ᵀ (for K = k I this is D = 2 √k Λ^{1/2}); ζ scales D."""
    rng = np.random.default_rng(seed)
    Lambda = random_spd(rng, low=0.5, high=20.0)
    L = np.linalg.cholesky(Lambda)
    Linv = np.linalg.inv(L)
    for K, zeta in ((300.0, 1.0), (random_spd(rng), 1.0), (random_spd(rng), 0.7)):
        ctrl = CartesianImpedance(stiffness=K, damping_ratio=zeta)
        D = ctrl.damping_for(Lambda)
        np.testing.assert_allclose(D, D.T, atol=1e-9)
        Dn = Linv @ D @ Linv.T
        Kn = Linv @ ctrl.K @ Linv.T
        np.testing.assert_allclose(Dn @ Dn, 4 * zeta**2 * Kn, rtol=1e-8, atol=1e-8 * np.abs(Kn).max())
    np.testing.assert_allclose(CartesianImpedance(stiffness=300.0).damping_for(Lambda), 2 * np.sqrt(300.0) * sqrtm_spd(Lambda), rtol=1e-9)


@pytest.mark.parametrize("seed", range(10))
def test_isotropic_torque_uses_critical_damping(seed):
    """The torque with the default (critical) damping equals the torque with D given explicitly
    as 2 √k Λ^{1/2} (whatever fast path the law takes for K = k I)."""
    rng = np.random.default_rng(seed)
    p = random_problem(rng)
    Lambda = np.linalg.inv(p["J"] @ p["Minv"] @ p["J"].T)
    implicit = CartesianImpedance(stiffness=250.0).torque(**p)
    explicit = CartesianImpedance(stiffness=250.0, damping=2 * np.sqrt(250.0) * sqrtm_spd(Lambda)).torque(**p)
    np.testing.assert_allclose(implicit, explicit, rtol=1e-7, atol=1e-7 * np.abs(explicit).max())


@pytest.mark.parametrize("seed", range(10))
def test_posture_term_does_not_move_the_tool(seed):
    """The null-space posture torque changes no tool acceleration: J M⁻¹ (τ_with − τ_without) = 0."""
    rng = np.random.default_rng(seed)
    p = random_problem(rng)
    posture = rng.normal(size=6)
    with_posture = CartesianImpedance(posture=posture, posture_stiffness=rng.uniform(5, 50, 6)).torque(**p)
    without = CartesianImpedance().torque(**p)
    delta = with_posture - without
    joint_acc = p["Minv"] @ delta
    assert np.linalg.norm(joint_acc) > 1e-2  # the posture term does act on the joints
    np.testing.assert_allclose(p["J"] @ joint_acc, 0.0, atol=1e-7 * np.linalg.norm(joint_acc))


def test_posture_term_on_the_real_arm(make_env):
    env = make_env(scenario="none")
    env.reset(seed=1)
    u = env.unwrapped
    m, d = u.model, u.data
    rng = np.random.default_rng(1)
    for _ in range(5):
        d.qpos[:] = m.key_qpos[0] + rng.uniform(-0.6, 0.6, 6)
        d.qvel[:] = rng.uniform(-0.5, 0.5, 6)
        mujoco.mj_forward(m, d)
        u.state_version += 1
        u.arm.update(d, u.state_version)
        site = u.arm.site_dynamics(d)
        J = site.jac[0]
        args = (d.qpos, d.qvel, site.pos[0], site.vel[0], J, site.c[0] - J @ u.arm.qacc_free, u.arm.Minv, d.qfrc_bias,
                site.pos[0] + [0.05, 0.0, -0.05])  # fmt: skip
        delta = default_impedance(u).torque(*args) - CartesianImpedance(max_force=150.0).torque(*args)
        joint_acc = u.arm.Minv @ delta
        assert np.linalg.norm(joint_acc) > 1e-2
        np.testing.assert_allclose(J @ joint_acc, 0.0, atol=1e-7 * np.linalg.norm(joint_acc))


def test_max_force_keeps_the_force_direction():
    rng = np.random.default_rng(3)
    p = random_problem(rng)
    p["x_des"] = p["x"] + np.array([10.0, -5.0, 2.0])  # a huge error: F far beyond the bound
    p.update(xd_des=p["xd"], xdd_des=p["Jdot_qd"])  # only the stiffness term remains
    bounded = CartesianImpedance(stiffness=100.0, max_force=20.0).torque(**p)
    free = CartesianImpedance(stiffness=100.0).torque(**p)
    # τ − b = Jᵀ F; recover F by least squares
    F_bounded = np.linalg.lstsq(p["J"].T, bounded - p["bias"], rcond=None)[0]
    F_free = np.linalg.lstsq(p["J"].T, free - p["bias"], rcond=None)[0]
    assert np.linalg.norm(F_bounded) == pytest.approx(20.0, rel=1e-9)
    np.testing.assert_allclose(F_bounded / 20.0, F_free / np.linalg.norm(F_free), atol=1e-9)


# ----------------------------------------------------------------------------- closed loop


def run_step_response(env, direction, use_wrapper):
    """Command a fixed tool target STEP m away; return (times, tool positions, start, target)."""
    u = env.unwrapped
    start = u.data.site_xpos[u.ee_site_id].copy()
    target = start + STEP * np.asarray(direction, float) / np.linalg.norm(direction)
    trace = []

    def recorder(tau):  # runs at every physics step, after the nominal controller
        trace.append((u.data.time, u.data.site_xpos[u.ee_site_id].copy()))
        return tau

    u.add_torque_hook(recorder, "filter")
    try:
        if use_wrapper:
            wrapped = CartesianImpedanceAction(env)
            for _ in range(100):  # 2 s at 50 Hz
                tool = u.data.site_xpos[u.ee_site_id]
                action = np.clip((target - tool) / wrapped.max_offset, -1.0, 1.0).astype(np.float32)
                wrapped.step(action)
            u.remove_torque_hook("nominal")
        else:
            hook = ImpedanceHook(u, default_impedance(u))
            hook.set_target(target)
            u.add_torque_hook(hook, "nominal")
            for _ in range(100):
                env.step(np.zeros(6, np.float32))
            u.remove_torque_hook("nominal")
    finally:
        u.remove_torque_hook("filter")
    times = np.array([t for t, _ in trace])
    return times - times[0], np.array([x for _, x in trace]), start, target


@pytest.mark.parametrize("use_wrapper", [False, True], ids=["hook", "wrapper"])
@pytest.mark.parametrize("direction", [(1, 0, 0), (0, -1, 0), (0, 0, 1), (-1, 1, -1)])
def test_fixed_target_reached_without_overshoot(make_env, direction, use_wrapper):
    env = make_env(scenario="none")
    env.reset(seed=2)
    times, tool, start, target = run_step_response(env, direction, use_wrapper)
    assert times[-1] >= 1.95
    error = np.linalg.norm(tool - target, axis=1)
    assert error[-1] < 0.02, f"still {error[-1]:.3f} m from the target after 2 s"
    assert np.all(error[times >= 1.5] < 0.02)  # it stays there
    unit = (target - start) / STEP
    progress = (tool - start) @ unit
    overshoot = progress.max() - STEP
    assert overshoot < 0.1 * STEP, f"overshoot {overshoot:.4f} m"
    assert error[times <= 0.2].max() > 0.1  # it was a real step
