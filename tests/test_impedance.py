"""Tests for c3bf_gym/controllers/impedance.py and its compiled law (controllers/_kernels.py),
and its hook/wrapper in c3bf_gym/wrappers.py.

The control law is checked algebraically on random inertias and Jacobians (the closed-loop task
dynamics, critical damping, the null-space property), against the numpy oracle of
tests/reference.py (on random problems, and on both arms' states from MuJoCo's own Jacobians and
mass matrix, inside the environment's compiled policy step and through the Python hook path), and in
closed loop on the real arm (a 0.15 m step is reached, without overshoot).
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from c3bf_gym import CartesianImpedance, CartesianImpedanceAction, SafetyFilter
from c3bf_gym.envs.reach import C3BFReachEnv
from c3bf_gym.experiments import MinimumJerk
from c3bf_gym.wrappers import ImpedanceHook, default_impedance
from reference import impedance_torque

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


@pytest.mark.parametrize(("robot", "stiffness"), [("ur5e", 20.0), ("panda", 2.0)])
def test_default_controller_pulls_to_home_with_the_arms_own_posture_stiffness(robot, stiffness):
    """The Panda's null-space pull is 2 N m/rad, not the UR5e's 20 (its wrist has 12 N m: at 20 the
    pull fought the filter's evasions); ``posture_stiffness`` overrides it, damped critically."""
    env = C3BFReachEnv(robot=robot)
    controller = default_impedance(env)
    np.testing.assert_array_equal(controller.posture, env.model.key_qpos[0])
    np.testing.assert_allclose(controller.Kq, stiffness)
    stronger = default_impedance(env, posture_stiffness=10 * stiffness)
    np.testing.assert_allclose((stronger.Kq, stronger.Dq), (10 * stiffness, 2 * np.sqrt(10 * stiffness)))
    env.close()


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


# ----------------------------------------------------------------------------- the compiled law against the oracle

SETTINGS = {
    "default": dict(),
    "anisotropic K": dict(stiffness=[100.0, 250.0, 400.0], damping_ratio=0.7),
    "full K": "random K",
    "fixed D, posture, max_force": dict(damping=[30.0, 40.0, 50.0], posture="random", max_force=20.0),
    "posture gains per joint": dict(posture="random", posture_stiffness="random", posture_damping=3.0),
}


def _settings(name, rng, n=6):
    kwargs = dict(stiffness=random_spd(rng)) if SETTINGS[name] == "random K" else dict(SETTINGS[name])
    for key in ("posture", "posture_stiffness"):
        if kwargs.get(key) == "random":
            kwargs[key] = rng.uniform(-1.0, 1.0, n) if key == "posture" else rng.uniform(1.0, 30.0, n)
    return kwargs


@pytest.mark.parametrize("name", list(SETTINGS))
@pytest.mark.parametrize("seed", range(5))
def test_compiled_law_matches_the_numpy_oracle(name, seed):
    rng = np.random.default_rng(seed)
    p = random_problem(rng)
    ctrl = CartesianImpedance(**_settings(name, rng))
    expected = impedance_torque(ctrl, **p)
    np.testing.assert_allclose(ctrl.torque(**p), expected, rtol=1e-10, atol=1e-10 * np.abs(expected).max())
    # set-point regulation: the desired velocity and acceleration default to zero
    p.pop("xd_des"), p.pop("xdd_des")
    expected = impedance_torque(ctrl, **p)
    np.testing.assert_allclose(ctrl.torque(**p), expected, rtol=1e-10, atol=1e-10 * np.abs(expected).max())


def test_max_force_binds_in_the_compiled_law():
    """With a bound far below the unbounded force, the torque is the oracle's (the force scaled
    down), and differs from the unbounded law's."""
    rng = np.random.default_rng(11)
    p = random_problem(rng)
    bounded, free = CartesianImpedance(max_force=1.0), CartesianImpedance()
    np.testing.assert_allclose(bounded.torque(**p), impedance_torque(bounded, **p), rtol=1e-10, atol=1e-10)
    assert np.abs(bounded.torque(**p) - free.torque(**p)).max() > 1.0


def test_singular_jacobian_gives_finite_torques():
    """A Jacobian of rank 2 (J M⁻¹ Jᵀ singular): the clamped eigenvalue keeps Λ finite."""
    rng = np.random.default_rng(4)
    p = random_problem(rng)
    p["J"][2] = p["J"][0] + p["J"][1]
    ctrl = CartesianImpedance(posture=np.zeros(6))
    tau = ctrl.torque(**p)
    assert np.all(np.isfinite(tau))
    np.testing.assert_allclose(tau, impedance_torque(ctrl, **p), rtol=1e-6, atol=1e-6 * np.abs(tau).max())


BAD_CALLS = [
    (dict(J=np.zeros((2, 6))), r"J must have shape \(3, n\)"),
    (dict(q=np.zeros(5)), r"q must have shape \(6,\)"),
    (dict(Minv=np.eye(5)), r"Minv must have shape \(6, 6\)"),
    (dict(x_des=np.zeros(2)), r"x_des must have shape \(3,\)"),
]


@pytest.mark.parametrize("change, message", BAD_CALLS, ids=[list(c)[0] for c, _ in BAD_CALLS])
def test_bad_torque_arguments_rejected(change, message):
    p = random_problem(np.random.default_rng(0))
    p.update(change)
    with pytest.raises(ValueError, match=message):
        CartesianImpedance().torque(**p)


def test_posture_of_another_length_rejected(make_env):
    p = random_problem(np.random.default_rng(0))
    with pytest.raises(ValueError, match="posture has 7 joint angles; the arm has 6"):
        CartesianImpedance(posture=np.zeros(7)).torque(**p)
    env = make_env(scenario="none")
    with pytest.raises(ValueError, match="posture has 7 joint angles; the arm has 6"):
        ImpedanceHook(env.unwrapped, CartesianImpedance(posture=np.zeros(7)))
    with pytest.raises(ValueError, match=r"posture_stiffness must be a scalar or \(6,\)"):
        ImpedanceHook(env.unwrapped, CartesianImpedance(posture=np.zeros(6), posture_stiffness=np.ones(4)))


def test_set_posture_checks_its_argument_and_leaves_the_controller_alone(make_env):
    env = make_env(scenario="none")
    controller = CartesianImpedance(posture=np.zeros(6))
    hook = ImpedanceHook(env.unwrapped, controller)
    hook.set_posture(np.full(6, 0.3))
    np.testing.assert_array_equal(hook.gains.posture, 0.3)
    np.testing.assert_array_equal(controller.posture, 0.0)  # the hook's copy moved, not the controller's
    for bad in (np.zeros(5), np.r_[np.zeros(5), np.nan]):
        with pytest.raises(ValueError, match="posture must be 6 finite joint angles"):
            hook.set_posture(bad)
    np.testing.assert_array_equal(hook.gains.posture, 0.3)
    with pytest.raises(ValueError, match="this controller has no posture task to move"):
        ImpedanceHook(make_env(scenario="none").unwrapped, CartesianImpedance()).set_posture(np.zeros(6))


def oracle_at(env: C3BFReachEnv, ctrl: CartesianImpedance, target) -> np.ndarray:
    """The oracle's total torque at ``env``'s current state, from MuJoCo's own site Jacobian,
    ``mj_jacDot`` and mass matrix (with the integrator's implicit joint damping, as the env's arm)."""
    m, d = env.model, env.data
    jac, jac_dot = np.zeros((3, m.nv)), np.zeros((3, m.nv))
    mujoco.mj_jacSite(m, d, jac, None, env.ee_site_id)
    mujoco.mj_jacDot(m, d, jac_dot, None, d.site_xpos[env.ee_site_id], m.site_bodyid[env.ee_site_id])
    M = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, M)
    Minv = np.linalg.inv(M + np.diag(m.opt.timestep * m.dof_damping))
    return impedance_torque(ctrl, d.qpos.copy(), d.qvel.copy(), d.site_xpos[env.ee_site_id].copy(), jac @ d.qvel, jac,
                            jac_dot @ d.qvel, Minv, d.qfrc_bias.copy(), *target)  # fmt: skip


ROBOTS = ["ur5e", "panda"]


@pytest.mark.parametrize("robot", ROBOTS)
@pytest.mark.parametrize("residual", [False, True], ids=["target", "residual"])
@pytest.mark.parametrize("filtered", [False, True], ids=["alone", "filtered"])
def test_compiled_policy_step_applies_the_oracle_torque(robot, residual, filtered, monkeypatch):
    """One physics step per policy step: the torque the compiled policy step applied (``ctrl`` plus
    gravity compensation) is the oracle's at the state before the step, towards the wrapper's target
    (residual or not); behind the filter, the filter's nominal torque is. No Python hook runs."""
    monkeypatch.setattr(ImpedanceHook, "__call__", lambda self, tau: pytest.fail("the hook ran in Python"))
    base = C3BFReachEnv(scenario="multi", robot=robot, frame_skip=1)
    gains = dict(stiffness=[200.0, 300.0, 400.0], posture=base.model.key_qpos[0].copy())
    impedance = CartesianImpedanceAction(base, residual=residual, controller=CartesianImpedance(**gains, max_force=40.0))
    unbounded = CartesianImpedance(**gains)
    env = SafetyFilter(impedance) if filtered else impedance
    env.reset(seed=4)
    rng = np.random.default_rng(4)
    hook = impedance.hook
    binding = 0
    for _ in range(60):
        action = rng.uniform(-1, 1, 3).astype(np.float32)
        impedance.action(action)  # sets the target now, as step will from the same state
        target = (hook.target_pos.copy(), hook.target_vel.copy(), hook.target_acc.copy())
        expected = oracle_at(base, hook.controller, target)
        binding += not np.allclose(expected, oracle_at(base, unbounded, target), rtol=1e-6, atol=1e-6)
        gravity = base.data.qfrc_gravcomp.copy()
        env.step(action)
        applied = env.hook.report.tau_nominal if filtered else base.data.ctrl + gravity
        np.testing.assert_allclose(applied, expected, rtol=1e-8, atol=1e-8 * np.abs(expected).max())
    assert 0 < binding < 60  # max_force bound some steps, not all
    env.close()


@pytest.mark.parametrize("robot", ROBOTS)
def test_compiled_and_python_paths_step_alike(robot):
    """The recipe's stack through the compiled policy step and through the Python hooks (the filter
    timing its calls sends every call through Python): the same states and reports, to rounding."""
    runs = []
    for python in (False, True):
        env = SafetyFilter(CartesianImpedanceAction(C3BFReachEnv(scenario="multi", robot=robot), residual=True))
        if python:
            env.hook.record_times()
        env.reset(seed=7)
        rng = np.random.default_rng(7)
        states, corrections = [], []
        for _ in range(20):
            _, _, _, _, info = env.step(rng.uniform(-1, 1, 3).astype(np.float32))
            states.append(np.concatenate([env.unwrapped.data.qpos, env.unwrapped.data.qvel]))
            corrections.append(info["safety"]["correction"])
        assert (len(env.hook.solve_times) == 200) if python else env.hook.solve_times is None
        runs.append((np.array(states), np.array(corrections)))
        env.close()
    np.testing.assert_allclose(runs[0][0], runs[1][0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(runs[0][1], runs[1][1], rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("robot", ROBOTS)
def test_trajectory_and_user_hook_run_in_python(robot):
    """A trajectory target (a Python function of time) and a user's Python ``filter`` hook behind the
    controller: both run at every physics step, the hook receiving the oracle's torque towards the
    trajectory's point at that time, on both arms."""
    base = C3BFReachEnv(scenario="none", robot=robot)
    base.reset(seed=1)
    start = base.data.site_xpos[base.ee_site_id].copy()
    path = MinimumJerk(start, start + [0.1, -0.1, 0.05], 0.3)
    controller = default_impedance(base)
    hook = ImpedanceHook(base, controller, path)
    assert hook.compiled_call() is None
    seen = []

    def user_hook(tau):  # the extension point: any Python function of the total torque
        expected = oracle_at(base, controller, path(base.data.time))
        np.testing.assert_allclose(tau, expected, rtol=1e-8, atol=1e-8 * np.abs(expected).max())
        seen.append(base.data.time)
        return 0.5 * tau

    base.add_torque_hook(hook, "nominal")
    base.add_torque_hook(user_hook, "filter")
    for _ in range(20):
        base.step(np.zeros(base.action_space.shape, np.float32))
    assert len(seen) == 20 * base.frame_skip
    np.testing.assert_allclose(hook.target_pos, path(seen[-1])[0])


def test_user_nominal_hook_behind_the_filter(make_env):
    """A user's Python ``nominal`` hook in front of the compiled filter: called at every physics
    step, its torque what the filter receives."""
    env = SafetyFilter(make_env(scenario="multi"))
    base = env.unwrapped
    calls = []

    def nominal(tau):
        calls.append(tau.copy())
        return tau + 1.0

    base.add_torque_hook(nominal, "nominal")
    env.reset(seed=2)
    _, _, _, _, info = env.step(np.zeros(6, np.float32))
    assert len(calls) == base.frame_skip and env.hook.report.substeps == base.frame_skip
    np.testing.assert_allclose(env.hook.report.tau_nominal, calls[-1] + 1.0)
