"""Tests for c3bf_gym/filter.py: the safety filter as a per-physics-step torque hook.

Rows are checked against an independent evaluation of the barrier condition ``ḣ + γ h`` (the
barrier written out here from DESIGN.md, its gradients by finite differences, the arm point's
acceleration from MuJoCo's own forward dynamics, ``mj_jac`` and ``mj_jacDot``); QP solutions
against the KKT conditions of the QP the filter claims to solve.
"""

from __future__ import annotations

import gymnasium as gym
import mujoco
import numpy as np
import pytest

from c3bf_gym import SafetyFilter
from c3bf_gym.safety.barriers import C3BF, DistanceHOCBF
from c3bf_gym.envs.reach import UR5E_JOINT_SPEED
from c3bf_gym.filter import SafetyHook
from c3bf_gym.safety import FilterConfig, SafetyInfeasibleError
from c3bf_gym.scenarios import ObstacleSample, ObstacleSpec

import reference

#: Several tests shrink the sensing radius or the joint speeds below what the scenarios' obstacles
#: need; the filter says so (tests/test_envelope.py checks that it does), which is not their subject.
pytestmark = pytest.mark.filterwarnings("ignore::c3bf_gym.safety.EnvelopeWarning")

# ----------------------------------------------------------------------------- helpers


def hook_for(u, **settings) -> SafetyHook:
    """The hook SafetyFilter builds: the default configuration with ``settings`` changed."""
    return SafetyHook(u, FilterConfig(**settings))


@pytest.fixture
def env(make_env):
    e = make_env(scenario="none")
    e.reset(seed=0)
    return e.unwrapped


def refresh(u) -> None:
    mujoco.mj_forward(u.model, u.data)
    u.state_version += 1


def capsule_frame(u, gid):
    axis = u.data.geom_xmat[gid].reshape(3, 3)[:, 2]
    half = u.model.geom_size[gid, 1]
    return u.data.geom_xpos[gid] - half * axis, u.data.geom_xpos[gid] + half * axis


def put_obstacle(u, slot, centre, radius, velocity=(0.0, 0.0, 0.0)) -> None:
    u._place(slot, ObstacleSample(np.asarray(centre, float), np.asarray(velocity, float), float(radius)))
    u._obstacle_specs[slot] = ObstacleSpec("static")


def beside_capsule(u, gid, clearance, radius, rng=None, t=0.5):
    """(centre, outward unit normal): a sphere ``clearance`` from capsule ``gid``, off its axis."""
    a, b = capsule_frame(u, gid)
    axis = (b - a) / np.linalg.norm(b - a)
    side = np.cross(axis, [0.0, 0.0, 1.0]) if rng is None else rng.normal(size=3)
    side -= (side @ axis) * axis
    side /= np.linalg.norm(side)
    return a + t * (b - a) + side * (u.model.geom_size[gid, 0] + radius + clearance), side


def random_scene(u, rng, n_obstacles, clearance=(0.02, 0.25), speed=0.4, qd=0.5):
    """A random arm state with obstacles near random links, none touching the arm, no contact."""
    m, d = u.model, u.data
    for _ in range(100):
        d.qpos[:] = m.key_qpos[0] + rng.uniform(-0.5, 0.5, m.nq)
        d.qvel[:] = rng.uniform(-qd, qd, m.nv)
        u._park_all()
        mujoco.mj_forward(m, d)
        for slot in range(n_obstacles):
            gid = rng.choice(u.arm.capsule_ids)  # link2 ... tool (link 1 is not protected)
            radius = rng.uniform(0.04, 0.08)
            centre, _ = beside_capsule(u, gid, rng.uniform(*clearance), radius, rng, t=rng.uniform(0.2, 0.8))
            put_obstacle(u, slot, centre, radius, rng.uniform(-speed, speed, 3))
        refresh(u)
        if d.nefc == 0 and u.obstacle_distances()[:n_obstacles].min() > 0.005:
            return
    raise AssertionError("could not draw a clean random scene")


def mujoco_accelerations(u, tau):
    """Joint acceleration for total actuator torque ``tau``: the one MuJoCo's next physics step
    integrates, ``(q̇⁺ − q̇) / h`` (Euler treats joint damping implicitly), on a copy of the data."""
    m = u.model
    d = mujoco.MjData(m)
    mujoco.mj_copyData(d, m, u.data)
    d.ctrl[:] = tau - d.qfrc_gravcomp  # the env's convention: the motors add gravity compensation
    mujoco.mj_step(m, d)
    assert d.nefc == 0
    np.testing.assert_allclose(d.qfrc_actuator, tau, atol=1e-9)  # no clamping happened
    return (d.qvel - u.data.qvel) / m.opt.timestep


def point_motion(u, x, body, qacc):
    m, d = u.model, u.data
    jac = np.zeros((3, m.nv))
    jdot = np.zeros((3, m.nv))
    mujoco.mj_jac(m, d, jac, None, x, body)
    mujoco.mj_jacDot(m, d, jdot, None, x, body)
    return jac @ d.qvel, jac @ qacc + jdot @ d.qvel


def barrier_value(barrier, p, v, r):
    """The barrier written out here (DESIGN.md section 2): C3BF h, or the HOCBF's ψ₁."""
    if isinstance(barrier, C3BF):
        return p @ v + np.sqrt(v @ v + barrier.eps**2) * np.sqrt(p @ p - r**2)
    return 2 * p @ v + barrier.gamma1 * (p @ p - r**2)  # ψ₁ = ḣ0 + γ₁ h0, h0 = ‖p‖² − r²


def barrier_values(u, hook):
    """Barrier value of every (sensed obstacle, protected point) pair at the current state, with
    the closest points found here from the capsule frames, in the filter's row order."""
    m, d = u.model, u.data
    values = []
    for k in sensed_slots(u, hook):
        o, vo, R = u.obstacle_pos[k], u.obstacle_vel[k], u.obstacle_radius[k]
        if hook.points == "whole_arm":
            for gid in u.arm.capsule_ids:
                a_end, b_end = capsule_frame(u, gid)
                ab = b_end - a_end
                x = a_end + np.clip((o - a_end) @ ab / (ab @ ab), 0, 1) * ab
                xd, _ = point_motion(u, x, m.geom_bodyid[gid], np.zeros(m.nv))
                r = R + m.geom_size[gid, 0] + hook.margin
                values.append(barrier_value(hook.barrier, x - o, xd - vo, r))
        else:
            x = d.site_xpos[u.ee_site_id].copy()
            xd, _ = point_motion(u, x, m.site_bodyid[u.ee_site_id], np.zeros(m.nv))
            values.append(barrier_value(hook.barrier, x - o, xd - vo, R + hook.ee_radius + hook.margin))
    return np.array(values)


#: rows present whatever is sensed: 12 floor rows (both ends of the 6 capsules the pan joint
#: does not keep level) and 24 joint-limit rows
FIXED_ROWS = 12 + 24


def end_heights(u):
    """Heights of both ends of every capsule but link 1, ends a then ends b (the filter's order)."""
    ends = [capsule_frame(u, gid) for gid in u.arm.capsule_ids]
    return np.array([a[2] for a, _ in ends] + [b[2] for _, b in ends])


def sensed_slots(u, hook):
    return [k for k in range(len(u.obstacle_active))
            if u.obstacle_active[k] and u.obstacle_distances()[k] <= hook.sensing_radius]  # fmt: skip


def expected_rows(u, hook, qacc, delta=1e-5):
    """The filter's rows' ``A τ − b`` for the torque giving joint acceleration ``qacc``, evaluated
    independently: ``ḣ + γ h`` of every (obstacle, point) pair, with ``ḣ`` the central finite
    difference of ``h`` along the motion (joints at ``q̈``, obstacles at their velocity; the
    closest points found anew at each instant), then the floor conditions
    ``z̈ + 2γ ż + γ² (z − r − margin)`` (γ = 10) of both ends of every protected capsule (link 1,
    on the pan axis, is not one), ``ż`` and ``z̈`` differenced the same way, then
    the 24 joint-limit conditions."""
    m, d = u.model, u.data
    q0, qd0, pos0, version = d.qpos.copy(), d.qvel.copy(), u.obstacle_pos.copy(), u.state_version
    slots = sensed_slots(u, hook)
    h_now = barrier_values(u, hook)
    z_now = end_heights(u)
    shifted, z_shifted = [], []
    for sign in (1.0, -1.0):
        dt = sign * delta
        d.qpos[:] = q0 + dt * qd0 + 0.5 * dt**2 * qacc
        d.qvel[:] = qd0 + dt * qacc
        u.obstacle_pos[:] = pos0 + dt * u.obstacle_vel + 0.5 * dt**2 * u.obstacle_acc
        mujoco.mj_forward(m, d)
        assert sensed_slots(u, hook) == slots
        shifted.append(barrier_values(u, hook))
        z_shifted.append(end_heights(u))
    d.qpos[:], d.qvel[:], u.obstacle_pos[:] = q0, qd0, pos0
    mujoco.mj_forward(m, d)
    u.state_version = version
    h_dot = (shifted[0] - shifted[1]) / (2 * delta)
    values = list(h_dot + hook.barrier.gamma * h_now)
    z_dot = (z_shifted[0] - z_shifted[1]) / (2 * delta)
    z_ddot = (z_shifted[0] - 2.0 * z_now + z_shifted[1]) / delta**2
    radius = np.tile(m.geom_size[u.arm.capsule_ids, 0], 2)
    values += list(z_ddot + 20.0 * z_dot + 100.0 * (z_now - radius - hook.margin))
    # joint limits (JointLimits docstring; defaults γ₁ = γ₂ = 10, γ_v = 20)
    q, qd = d.qpos, d.qvel
    q_lo, q_hi = u.joint_range.T
    qd_max = hook.joint_limits.qd_max
    g1, g2, gv = 10.0, 10.0, 20.0
    values += list(-qacc - g1 * qd + g2 * (-qd + g1 * (q_hi - q)))
    values += list(qacc + g1 * qd + g2 * (qd + g1 * (q - q_lo)))
    values += list(-qacc + gv * (qd_max - qd))
    values += list(qacc + gv * (qd + qd_max))
    return np.array(values), len(slots)


def assert_kkt_optimal(tau, tau_nom, A, b, W, lo, hi, tol=1e-6):
    """τ solves min ½(τ−τ_nom)ᵀW(τ−τ_nom) s.t. Aτ ≥ b, lo ≤ τ ≤ hi (checked by its KKT conditions)."""
    nnls = pytest.importorskip("scipy.optimize").nnls
    norms = np.linalg.norm(A, axis=1)
    residual = (A @ tau - b) / np.maximum(norms, 1e-12)
    assert residual.min() >= -tol, residual.min()
    assert np.all(tau >= lo - 1e-9) and np.all(tau <= hi + 1e-9)
    span = hi - lo
    columns = [A[k] / norms[k] for k in np.flatnonzero(residual <= 1e-5)]
    columns += [np.eye(len(tau))[i] for i in np.flatnonzero(tau - lo <= 1e-7 * span)]
    columns += [-np.eye(len(tau))[i] for i in np.flatnonzero(hi - tau <= 1e-7 * span)]
    gradient = W @ (tau - tau_nom)
    if not columns:
        np.testing.assert_allclose(tau, tau_nom, atol=1e-9)
        return
    _, res = nnls(np.array(columns).T, gradient)  # gradient = Σ λ_k ∇g_k with λ ≥ 0
    assert res <= 1e-4 * max(1.0, np.linalg.norm(gradient)), (res, np.linalg.norm(gradient))


def toward_obstacles(u, scale=1.0):
    """A nominal torque that pushes the arm's points nearest to each obstacle towards it."""
    m, d = u.model, u.data
    tau = d.qfrc_gravcomp.copy()
    for k in np.flatnonzero(u.obstacle_active):
        best = None
        for gid in u.arm.capsule_ids:
            a, b = capsule_frame(u, gid)
            ab = b - a
            x = a + np.clip((u.obstacle_pos[k] - a) @ ab / (ab @ ab), 0, 1) * ab
            gap = np.linalg.norm(u.obstacle_pos[k] - x) - m.geom_size[gid, 0]
            if best is None or gap < best[0]:
                best = (gap, x, m.geom_bodyid[gid])
        jac = np.zeros((3, m.nv))
        mujoco.mj_jac(m, d, jac, None, best[1], best[2])
        direction = u.obstacle_pos[k] - best[1]
        tau += jac.T @ (200.0 * scale * direction / np.linalg.norm(direction))
    return np.clip(tau, -u.torque_limit, u.torque_limit)


# ----------------------------------------------------------------------------- rows


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize(
    "barrier, points",
    [(C3BF(gamma=3.0, eps=1e-2), "whole_arm"), (DistanceHOCBF(gamma1=2.0, gamma2=4.0), "whole_arm"),
     (C3BF(gamma=5.0, eps=1e-2), "ee")],  # fmt: skip
    ids=["c3bf-whole_arm", "hocbf-whole_arm", "c3bf-ee"],
)
def test_rows_equal_independent_barrier_condition(env, seed, barrier, points):
    """For any torque τ, the filter's ``A τ − b`` is ``ḣ + γ h`` of every (obstacle, point) pair
    followed by the 12 floor and 24 joint-limit conditions. ``ḣ`` is the true rate of ``h`` at the closest
    point, which slides along the link as the arm moves (not the rate of a material point)."""
    u = env
    rng = np.random.default_rng(seed)
    random_scene(u, rng, n_obstacles=1 + seed % 3)
    hook = hook_for(u, barrier=barrier, points=points, margin=0.015, guard=None)  # the guard's: test_kernels
    A, b, min_h, inside, n_sensed = hook.rows()
    A, b = A.copy(), b.copy()
    assert not inside and n_sensed == 1 + seed % 3
    per = len(u.arm.capsule_ids) if points == "whole_arm" else 1
    assert A.shape == (n_sensed * per + FIXED_ROWS, 6)
    for _ in range(3):
        tau = rng.uniform(-0.3, 0.3, 6) * u.torque_limit + u.data.qfrc_gravcomp
        qacc = mujoco_accelerations(u, tau)
        expected, _ = expected_rows(u, hook, qacc)
        got = A @ tau - b
        np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-5 * max(1.0, np.abs(expected).max()))
    assert np.abs(expected[: n_sensed * per]).max() > 0.01  # the obstacle rows are not trivial
    assert np.isfinite(min_h)


def test_min_h_and_sensed_count_reported(env):
    u = env
    rng = np.random.default_rng(3)
    random_scene(u, rng, n_obstacles=2)
    hook = hook_for(u, barrier=C3BF(gamma=5.0, eps=1e-2))
    _, _, min_h, inside, n_sensed = hook.rows()
    p_v_r = []
    m = u.model
    for k in range(2):
        for gid in u.arm.capsule_ids:
            a, b = capsule_frame(u, gid)
            ab = b - a
            x = a + np.clip((u.obstacle_pos[k] - a) @ ab / (ab @ ab), 0, 1) * ab
            xd, _ = point_motion(u, x, m.geom_bodyid[gid], np.zeros(6))
            p, v = x - u.obstacle_pos[k], xd - u.obstacle_vel[k]
            r = u.obstacle_radius[k] + m.geom_size[gid, 0] + 0.02
            p_v_r.append(p @ v + np.sqrt(v @ v + 1e-4) * np.sqrt(p @ p - r**2))
    assert n_sensed == 2 and not inside
    assert min_h == pytest.approx(min(p_v_r), rel=1e-9, abs=1e-12)


# ----------------------------------------------------------------------------- pass-through


@pytest.mark.parametrize("seed", range(4))
def test_no_sensed_obstacle_returns_nominal_unchanged(env, seed):
    u = env
    rng = np.random.default_rng(seed)
    hook = hook_for(u, on_infeasible="raise")
    for _ in range(5):
        u.data.qpos[:] = u.model.key_qpos[0] + rng.uniform(-0.3, 0.3, 6)
        u.data.qvel[:] = rng.uniform(-0.2, 0.2, 6)
        refresh(u)
        tau_nom = u.data.qfrc_gravcomp + rng.uniform(-0.02, 0.02, 6) * u.torque_limit
        hook.begin_step()
        tau = hook(tau_nom.copy())
        np.testing.assert_allclose(tau, tau_nom, rtol=1e-14, atol=1e-12)
        assert hook.report.sensed == 0 and hook.report.min_h == np.inf
        assert not hook.report.intervened and hook.report.feasible and hook.report.correction < 1e-9
        assert hook.last.status == "solved" and hook.last.active_rows == 0


def test_far_obstacle_pushing_nominal_is_not_filtered(env):
    """An obstacle beyond the sensing radius adds no row, so even a torque driving the arm
    straight at it passes unchanged; with a larger sensing radius the same torque is filtered."""
    u = env
    gid = u.arm.capsule_ids[1]
    centre, _ = beside_capsule(u, gid, 0.2, 0.06)
    put_obstacle(u, 0, centre, 0.06)
    u.data.qvel[:] = 0.0
    refresh(u)
    tau_nom = toward_obstacles(u, scale=0.2)
    near = hook_for(u, sensing_radius=0.1)
    A, b, *_ = near.rows()
    assert len(b) == FIXED_ROWS
    out = near(tau_nom.copy())
    np.testing.assert_allclose(out, tau_nom, rtol=1e-14, atol=1e-12)
    far = hook_for(u, sensing_radius=0.5)
    A, b, *_ = far.rows()
    assert len(b) == FIXED_ROWS + 2 * len(u.arm.capsule_ids)  # per link the C3BF's row and the guard's
    far.begin_step()
    out = far(tau_nom.copy())
    assert far.report.sensed == 1
    assert far.report.intervened and np.linalg.norm(out - tau_nom) > 1.0


def test_obstacles_beyond_sensing_radius_add_no_row(env):
    u = env
    rng = np.random.default_rng(0)
    s = 2 * len(u.arm.capsule_ids)  # rows per sensed obstacle: per link the C3BF's and the guard's
    hook = hook_for(u, sensing_radius=0.15)
    hook_ee = hook_for(u, sensing_radius=0.15, points="ee")
    clearances = [0.05, 0.1, 0.14, 0.16, 0.3, 0.6]
    for slot, clearance in enumerate(clearances):
        gid = u.arm.capsule_ids[1] if slot % 2 else u.arm.capsule_ids[0]
        centre, _ = beside_capsule(u, gid, clearance, 0.05, rng)
        put_obstacle(u, slot, centre, 0.05)
    refresh(u)
    distances = u.obstacle_distances()
    n_near = int(np.sum(distances[: len(clearances)] <= 0.15))
    assert n_near == 3  # by construction (nothing else is nearer than the chosen link)
    A, b, _, _, n_sensed = hook.rows()
    assert n_sensed == n_near and len(b) == n_near * s + FIXED_ROWS
    A, b, _, _, n_sensed = hook_ee.rows()
    assert n_sensed == n_near and len(b) == 2 * n_near + FIXED_ROWS
    # inactive (retired) obstacles add no row even when near
    u.obstacle_active[0] = False
    A, b, _, _, n_sensed = hook.rows()
    assert n_sensed == n_near - 1 and len(b) == (n_near - 1) * s + FIXED_ROWS
    # none sensed: only the floor and joint-limit rows
    u.obstacle_active[:] = False
    A, b, _, _, n_sensed = hook.rows()
    assert n_sensed == 0 and len(b) == FIXED_ROWS


# ----------------------------------------------------------------------------- QP


def tool_metric_in_torque(u, tool_acceleration=10.0):
    """The ``"tool"`` metric's W in torque units, ``S⁻¹ (I + GᵀG / a²) S⁻¹`` with ``S =
    diag(τ_max)`` and ``G = J (M + hD)⁻¹ S``, from MuJoCo's own site Jacobian and mass matrix
    (independent of the filter's kernels; the arm is the model's every dof)."""
    G = reference.tool_acceleration_gain(u.model, u.data, u.ee_site_id, u.torque_limit)
    S_inv = np.diag(1.0 / u.torque_limit)
    return S_inv @ (np.eye(u.model.nv) + G.T @ G / tool_acceleration**2) @ S_inv


def metric_in_torque(u, weight):
    """The QP metric ``weight`` in torque units: ``½ (τ − τ_nom)ᵀ W (τ − τ_nom)``."""
    if weight == "tool":
        return tool_metric_in_torque(u)
    return np.diag(1.0 / u.torque_limit**2) if weight == "limits" else np.eye(len(u.torque_limit))


@pytest.mark.parametrize("weight", ["limits", "identity", "tool"])
@pytest.mark.parametrize("seed", range(5))
def test_solution_satisfies_every_row_and_is_optimal(env, seed, weight):
    u = env
    rng = np.random.default_rng(100 + seed)
    hook = hook_for(u, weight=weight, on_infeasible="raise")
    for _ in range(50):  # close (outside the 2 cm margin), slow, inside the safe set (h > 0)
        random_scene(u, rng, n_obstacles=2 + seed % 3, clearance=(0.03, 0.08), speed=0.05, qd=0.1)
        A, b, min_h, *_ = hook.rows()
        if min_h > 0:
            break
    A, b = A.copy(), b.copy()
    assert min_h > 0
    tau_nom = toward_obstacles(u)
    assert np.min(A @ tau_nom - b) < 0  # the nominal torque is unsafe: the QP has work to do
    hook.begin_step()
    tau = hook(tau_nom.copy()).copy()
    assert hook.report.feasible and hook.report.slack == 0.0 and hook.report.intervened
    assert hook.report.active_rows >= 1
    assert_kkt_optimal(tau, tau_nom, A, b, metric_in_torque(u, weight), -u.torque_limit, u.torque_limit)


def test_weights_give_different_optima_in_their_own_metric(env):
    u = env
    rng = np.random.default_rng(7)
    for _ in range(50):
        random_scene(u, rng, n_obstacles=3, clearance=(0.03, 0.06), speed=0.05, qd=0.1)
        if hook_for(u).rows()[2] > 0:
            break
    tau_nom = toward_obstacles(u)
    out = {}
    for weight in ("limits", "identity", "tool"):
        hook = hook_for(u, weight=weight, on_infeasible="raise")
        A, b, *_ = hook.rows()
        A, b = A.copy(), b.copy()
        out[weight] = hook(tau_nom.copy()).copy()
        assert np.min(A @ out[weight] - b) >= -1e-6 * np.linalg.norm(A, axis=1).max()
    for weight, other in [("limits", "identity"), ("limits", "tool"), ("identity", "tool")]:
        assert np.linalg.norm(out[weight] - out[other]) > 1e-3
    for weight in out:  # each is optimal in its own metric
        W = metric_in_torque(u, weight)
        cost = {k: (v - tau_nom) @ W @ (v - tau_nom) for k, v in out.items()}
        assert all(cost[weight] <= value + 1e-9 for value in cost.values()), (weight, cost)


def test_the_tool_metric_spares_the_tool():
    """What the ``"tool"`` metric is for: in the episode of ``multi`` it was traced on (the
    recipe's evaluation episode 187: crossing spheres press on the upper arm while the tool holds
    the goal), the zero action keeps the tool at the goal under it and is pushed off it under
    ``"limits"``, with no collision under either (the environment's own distances)."""
    from c3bf_gym.training import FINAL_EVAL_SEED, TrainConfig, build_env

    final = {}
    for weight in ("limits", "tool"):
        env = build_env("random", **TrainConfig(filter_settings={"weight": weight}).env_options())
        env.reset(seed=FINAL_EVAL_SEED + 187)
        done, collisions = False, 0.0
        while not done:
            _, _, terminated, truncated, info = env.step(np.zeros(env.action_space.shape, np.float32))
            collisions += info["cost"]
            done = terminated or truncated
        assert env.unwrapped.episode_scenario.name == "multi" and collisions == 0.0
        final[weight] = info["distance"]
        env.close()
    assert final["tool"] < 0.02 and final["limits"] > 0.1, final


def test_torque_limits_are_never_exceeded(env):
    u = env
    big = np.array([500.0, -500.0, 300.0, 100.0, -100.0, 50.0])
    hook = hook_for(u)
    tau = hook(big)
    assert np.all(np.abs(tau) <= u.torque_limit + 1e-12)
    # without joint-limit rows and obstacles, and lifting the arm (so the floor rows do not
    # bind; ``big`` itself would slam the arm down), the box alone acts: plain saturation, which
    # is not counted as a safety intervention
    bare = SafetyHook(u, FilterConfig(barrier=C3BF(), guard=None, sensing_radius=1.0, joint_limits=False,
                                      on_infeasible="raise"))
    bare.begin_step()
    tau = bare(-big)
    np.testing.assert_allclose(tau, np.clip(-big, -u.torque_limit, u.torque_limit), atol=1e-12)
    assert bare.report.correction < 1e-9 and not bare.report.intervened


# ----------------------------------------------------------------------------- infeasible


def infeasible_scene(u, inside=False):
    """An obstacle 3 cm from link3 (or overlapping it), rushing at it at 3 m/s."""
    gid = u.arm.capsule_ids[1]
    centre, normal = beside_capsule(u, gid, -0.03 if inside else 0.03, 0.06)  # margin is 0.02
    put_obstacle(u, 0, centre, 0.06, -3.0 * normal)
    refresh(u)


def test_raise_in_infeasible_state(env):
    u = env
    infeasible_scene(u)
    hook = hook_for(u, on_infeasible="raise")
    with pytest.raises(SafetyInfeasibleError, match="relax"):
        hook(u.data.qfrc_gravcomp.copy())
    assert not hook.report.feasible and hook.report.infeasible_steps == 1 and hook.report.slack > 0


def test_last_describes_the_last_valid_call(env):
    """``last`` is None before any call, describes the last call that did not raise, and a new
    policy step's report (``begin_step``) does not change it."""
    u = env
    infeasible_scene(u)
    hook = hook_for(u, on_infeasible="relax")
    assert hook.last is None
    hook.begin_step()
    hook(u.data.qfrc_gravcomp.copy())
    relaxed = hook.last
    assert relaxed.status == "relaxed" and not relaxed.feasible and relaxed.slack > 0 and relaxed.active_rows > 0
    assert relaxed.iterations > 0 and relaxed.solve_time > 0
    hook.begin_step()
    assert hook.last == relaxed
    with pytest.raises(ValueError, match="NaN"):
        hook(np.full(6, np.nan))
    assert hook.last == relaxed
    u.obstacle_active[:] = False  # nothing near: the next call is solved
    refresh(u)
    hook(u.data.qfrc_gravcomp.copy())
    assert hook.last.status == "solved" and hook.last.feasible and hook.last.slack == 0.0
    assert relaxed.status == "relaxed"  # an object read earlier keeps its call's values


@pytest.mark.parametrize("relaxed", [False, True])
def test_min_constraint_is_the_smallest_row_residual_at_the_applied_torque(env, relaxed):
    """The report's ``min_constraint`` is ``min_k A_k τ − b_k`` over the call's rows, in their
    own units, at the torque returned (up to rounding), whether the rows held or gave way."""
    u = env
    infeasible_scene(u)
    if not relaxed:
        u.obstacle_vel[:] = 0.0  # the same obstacle at rest: every row can hold
        refresh(u)
    hook = hook_for(u, on_infeasible="relax")
    hook.begin_step()
    tau = hook(u.data.qfrc_gravcomp + 5.0)
    assert hook.last.feasible is not relaxed
    A, b, *_ = hook.rows()  # the same state: the rows of that call
    want = (A @ tau - b).min()
    assert hook.report.min_constraint == pytest.approx(want, rel=1e-9, abs=1e-9 * np.abs(b).max())
    assert bool(want < -1e-3) is relaxed


def test_relax_reports_and_does_not_return_nominal(env):
    u = env
    infeasible_scene(u)
    hook = hook_for(u, on_infeasible="relax")
    tau_nom = u.data.qfrc_gravcomp.copy()
    hook.begin_step()
    tau = hook(tau_nom.copy())
    assert hook.last.status == "relaxed" and not hook.last.feasible  # beyond the raised gain's allowance
    assert not hook.report.inside
    assert np.linalg.norm(tau - tau_nom) > 1.0  # the least-violating torque, not the nominal one
    assert np.all(np.abs(tau) <= u.torque_limit + 1e-12)


def test_overlap_is_reported_and_the_recovery_row_pushes_apart(env):
    """An obstacle overlapping link3 by 3 cm, rushing in: the violation is reported (inside),
    and the applied torque accelerates the link's point away from the obstacle relative to the
    nominal torque. The sphere is not felt here: its contact force would shove the arm, and the
    joint rows, which take the last step's constraint force, could not then hold the speed bound
    (the contact is the test's construction; the recovery row is its subject)."""
    u = env
    u.model.geom_contype[u.obstacle_geom_ids[0]] = u.model.geom_conaffinity[u.obstacle_geom_ids[0]] = 0
    infeasible_scene(u, inside=True)
    assert not u.data.qfrc_constraint.any()
    hook = hook_for(u, on_infeasible="raise")  # the recovery row is satisfiable: no raise
    tau_nom = u.data.qfrc_gravcomp.copy()
    hook.begin_step()
    tau = hook(tau_nom.copy())
    assert hook.report.inside
    pd = reference.closest_dynamics(u.arm, u.obstacle_pos[:1])
    s = list(u.arm.capsule_ids).index(u.arm.capsule_ids[1])
    away = pd.pos[s] - u.obstacle_pos[0]
    assert away @ (pd.G[s] @ (tau - tau_nom)) > 0.0


def test_relax_through_the_wrapper_reports_in_info(make_env):
    # one physics step per env step, so the report is that of the constructed infeasible state
    env = SafetyFilter(make_env(scenario="none", frame_skip=1), on_infeasible="relax")
    env.reset(seed=0)
    infeasible_scene(env.unwrapped)
    _, _, _, _, info = env.step(np.zeros(6, np.float32))
    s = info["safety"]
    assert s["feasible"] is False and s["slack"] > 0 and s["infeasible_steps"] >= 1
    assert info["safety_infeasible"] == 1.0 and info["episode_infeasible"] == 1


def test_raise_through_the_wrapper(make_env):
    env = SafetyFilter(make_env(scenario="none", frame_skip=1), on_infeasible="raise")
    env.reset(seed=0)
    infeasible_scene(env.unwrapped)
    with pytest.raises(SafetyInfeasibleError):
        env.step(np.zeros(6, np.float32))


@pytest.mark.parametrize("clearance", [0.015, -0.003])
def test_point_inside_the_margin_gets_a_bounded_recovery_row(env, clearance):
    """Inside the margin-inflated ball (0.015 < margin) or truly penetrating (-0.003), moving in
    fast: the C3BF falls back to its recovery row, the violation is reported, and the QP stays
    well scaled (a clamped cone gave rows with b ~ 3e5 and 1e4-1e6 proxsuite iterations)."""
    u = env
    gid = u.arm.capsule_ids[1]
    centre, normal = beside_capsule(u, gid, clearance, 0.06)
    put_obstacle(u, 0, centre, 0.06, -3.0 * normal)
    refresh(u)
    hook = hook_for(u)
    hook.begin_step()
    tau = hook(u.data.qfrc_gravcomp.copy())
    assert hook.report.inside
    assert np.all(np.isfinite(tau))
    assert hook.last.iterations < 500


# ----------------------------------------------------------------------------- options


def test_joint_speed_fraction_sets_the_speed_rows(env):
    u = env
    for fraction in (0.25, 1.0):
        hook = hook_for(u, joint_speed_fraction=fraction)
        np.testing.assert_allclose(hook.joint_limits.qd_max, fraction * UR5E_JOINT_SPEED)
        np.testing.assert_array_equal(hook.joint_limits.q_lo, u.joint_range[:, 0])
        np.testing.assert_array_equal(hook.joint_limits.q_hi, u.joint_range[:, 1])


def test_joint_range_reserve_draws_the_position_rows_inside_the_range(env):
    """The reserve moves the filter's position limits inside the range (at most a quarter of it)
    and hands the QP the rows' offset back to the range, γ₁γ₂δ per position row."""
    u = env
    lo, hi = u.joint_range.T
    hook = hook_for(u, joint_range_reserve=0.3)
    delta = np.minimum(0.3, 0.25 * (hi - lo))
    np.testing.assert_allclose(hook.joint_limits.q_lo, lo + delta)
    np.testing.assert_allclose(hook.joint_limits.q_hi, hi - delta)
    g1, g2, _ = hook.joint_limits.gains
    n = len(lo)
    np.testing.assert_allclose(hook.qp.buffers.reserve, np.concatenate([g1 * g2 * delta] * 2 + [np.zeros(2 * n)]))
    assert hook_for(u).qp.buffers.reserve.shape == (0,)  # the default keeps none


def test_nominal_speed_fraction_lowers_the_speed_rows_below_their_copies_at_the_bound(env):
    """A lower bound for the nominal torque draws the speed rows there and hands the QP their
    offset to the filter's bound, γ_v (bound − nominal) per speed row; the position rows keep
    none, and the filter's bound is still ``joint_speed_fraction``."""
    u = env
    hook = hook_for(u, nominal_speed_fraction=0.4)
    n = len(u.joint_range)
    np.testing.assert_allclose(hook.joint_limits.qd_max, 0.4 * UR5E_JOINT_SPEED)
    np.testing.assert_allclose(hook.joint_speed_bound, 0.5 * UR5E_JOINT_SPEED)
    gamma_v = hook.joint_limits.gains[2]
    np.testing.assert_allclose(hook.qp.buffers.reserve,
                               np.concatenate([np.zeros(2 * n)] + [np.full(n, gamma_v * 0.1 * UR5E_JOINT_SPEED)] * 2))
    assert hook.qp.buffers.capacity[4] == 2 * n
    default = hook_for(u)
    assert default.qp.buffers.capacity[4] == 0 and default.qp.buffers.reserve.shape == (0,)
    np.testing.assert_allclose(default.joint_speed_bound, default.joint_limits.qd_max)


def test_joint_range_reserve_keeps_the_joints_inside_their_range_until_a_guard_needs_it():
    """Random torques on the Panda, nothing to avoid: with a 0.3 rad reserve no joint comes within
    0.3 rad of a limit, and no step counts as giving way; without one they come closer."""
    closest = {}
    for reserve in (0.0, 0.3):
        env = SafetyFilter(gym.make("C3BFReachPanda-v0", scenario="none"), joint_range_reserve=reserve)
        env.reset(seed=0)
        u = env.unwrapped
        lo, hi = u.joint_range.T
        rng = np.random.default_rng(0)
        closest[reserve] = np.inf
        for _ in range(250):
            _, _, _, _, info = env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
            q = u.data.qpos[:7]
            closest[reserve] = min(closest[reserve], float(np.min(np.minimum(q - lo, hi - q))))
            assert info["safety"]["gain_raised_steps"] == 0 and info["safety"]["infeasible_steps"] == 0
        env.close()
    assert closest[0.0] < 0.3 <= closest[0.3] + 1e-6, closest


def _largest_speed_ratio(scenario, seed, **settings):
    """The Panda under random actions for 250 policy steps: the largest ``|q̇| / q̇_nominal``
    over its policy steps (the nominal torque's bound, ``joint_limits.qd_max``), and the physics
    steps counted as giving way within an allowance or beyond."""
    env = SafetyFilter(gym.make("C3BFReachPanda-v0", scenario=scenario), **settings)
    env.reset(seed=seed)
    u, bound = env.unwrapped, env.hook.joint_limits.qd_max
    rng = np.random.default_rng(seed)
    largest, raised, infeasible = 0.0, 0, 0
    for _ in range(250):
        _, _, _, _, info = env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
        largest = max(largest, float(np.max(np.abs(u.data.qvel[:7]) / bound)))
        raised += info["safety"]["gain_raised_steps"]
        infeasible += info["safety"]["infeasible_steps"]
    env.close()
    return largest, raised, infeasible


def test_the_speed_reserve_above_the_nominal_bound_is_for_the_barriers_rows_alone():
    """Random torques on the Panda with the nominal torque held to 0.4 of the robot's speed and
    the filter's bound at 0.5: with nothing to avoid the joints keep the nominal bound; in
    ``multi`` (seed 2) the barrier's rows take some joint past it, never past the filter's bound
    (1.25 times the nominal one), and no step counts as giving way beyond an allowance."""
    settings = dict(joint_speed_fraction=0.5, nominal_speed_fraction=0.4)
    largest, raised, infeasible = _largest_speed_ratio("none", 0, **settings)
    assert largest <= 1.0 + 1e-3 and raised == 0 and infeasible == 0, largest
    largest, raised, infeasible = _largest_speed_ratio("multi", 2, **settings)
    assert 1.01 < largest <= 1.25 * (1.0 + 1e-3) and raised > 0 and infeasible == 0, (largest, raised, infeasible)


def test_allowance_level_holds_the_barriers_rows_within_their_allowance():
    """The Panda in ``multi`` under random actions (seed 1): with one level for the barrier's rows,
    least squares spreads the conflicts over all of them and some give way beyond their allowance;
    with ``allowance_level`` the same episode holds every row, the barrier's within a raised gain."""
    counts = {}
    for level in (False, True):
        env = SafetyFilter(gym.make("C3BFReachPanda-v0", scenario="multi"), allowance_level=level)
        env.reset(seed=1)
        hook = env.hook
        assert (hook.qp.buffers.capacity[2] > 0) == level
        rng = np.random.default_rng(1)
        infeasible = raised = 0
        for _ in range(250):
            _, _, _, _, info = env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
            infeasible += info["safety"]["infeasible_steps"]
            raised += info["safety"]["gain_raised_steps"]
        counts[level] = (infeasible, raised)
        env.close()
    assert counts[False][0] > 0 and counts[True][0] == 0, counts
    assert counts[True][1] > 0, counts


def test_gamma_reaches_the_barrier(env):
    u = env
    assert hook_for(u, gamma=2.5).barrier.gamma == 2.5
    hocbf = hook_for(u, barrier="hocbf", gamma=3.5).barrier
    assert (hocbf.gamma1, hocbf.gamma2) == (3.5, 3.5)
    assert hook_for(u).barrier.gamma == 5.0
    with pytest.raises(ValueError, match="gamma was given beside a Barrier instance"):
        hook_for(u, barrier=C3BF(gamma=1.0), gamma=2.0)


def test_sensing_radius_defaults_to_the_env(make_env):
    e = make_env(scenario="none", sensing_radius=0.37)
    e.reset(seed=0)
    assert hook_for(e.unwrapped).sensing_radius == 0.37


# ----------------------------------------------------------------------------- relaxation

#: A recorded state (scenario "multi", random torques, seed 10, physics step 100) where no torque
#: satisfies every row: a cone row of obstacle 3 (0.7 m from link2) conflicts with the speed rows
#: of joints 0 and 1. The elastic QP's one shared slack let the speed rows of joints 3-5, which
#: take no part in the conflict, be violated as much as the conflicting rows (the nominal torque
#: pushes them); repeated over a few hundred steps the joint speeds reached 2-6x their limit, the
#: cone rows became infeasible on their own, and link3 touched an obstacle (-0.5 mm).
MULTI_SEED10_STEP100 = dict(
    qpos=[0.1345031012108953, -1.7705026570570717, 1.7054354950463855, -1.4335353759181693, -1.5785698449113568,
          -0.02325586952318217],
    qvel=[-0.6559897422797262, -1.479574067804223, -0.5637474835166877, 1.4735848089918464, 1.0799127085672886,
          -0.1513303530379898],
    obstacle_pos=[[0.5943143989548043, -0.15184202393812163, 0.4570185511150511],
                  [0.5901976780408892, -0.3156646902789156, 0.4826963672869392],
                  [0.7573595152802364, 0.11439015270866804, 0.4011645825333701],
                  [0.8039028970107978, 0.09421982301656578, 0.3585908696629526]],
    obstacle_vel=[[0.0, 0.0, 0.0],
                  [-0.11302922882046307, 0.3329818435638014, -0.034856594064680585],
                  [-0.16261752894900325, -0.1277505131927212, 0.03251445367910794],
                  [-0.13785896783334978, -0.1258955918559636, 0.06948930442532282]],
    tau_nom=[-0.457951158285141, 0.6493165522915322, -0.9972222507784312, 0.569900877370029, 0.7635147234178364,
             -0.15296721458435059],
)  # fmt: skip


def test_relaxed_solve_keeps_rows_outside_the_conflict(make_env):
    """Regression: when the rows conflict, only conflicting rows may give way. The old single
    shared slack violated the speed rows of joints 3, 4 and 5 by 0.03 (normalised torque) here."""
    u = make_env(scenario="multi").unwrapped
    u.reset(seed=10)
    state = MULTI_SEED10_STEP100
    u.data.qpos[:] = state["qpos"]
    u.data.qvel[:] = state["qvel"]
    u.obstacle_pos[:4] = state["obstacle_pos"]
    u.obstacle_vel[:4] = state["obstacle_vel"]
    refresh(u)
    hook = hook_for(u)
    tau = hook(np.asarray(state["tau_nom"]) * u.torque_limit)
    # the cone rows gave way within their allowance: held with the C3BF's gain raised
    assert hook.last.status == "gain raised" and hook.last.feasible and hook.last.slack > 0.0
    A, b, *_ = hook.rows()
    residual = (A @ tau - b) / np.linalg.norm(A, axis=1).clip(1e-12)
    n = u.model.nv
    speed_upper, speed_lower = residual[-2 * n : -n], residual[-n:]
    # the conflict: joints 0 and 1 (their lower speed rows) against the cone rows
    assert np.all(speed_upper >= -1e-6), speed_upper
    assert np.all(speed_lower[2:] >= -1e-6), speed_lower
    # at most the conflicting rows are violated: obstacle 3's row on link2 and joints 0-1
    assert np.count_nonzero(residual < -1e-6) <= 3
    assert np.all(np.abs(tau) <= u.torque_limit + 1e-9)


def _unfused_call(hook, tau_nom):
    """The hook's step as separate calls (rows, the QP, ``hook_post``): the path
    :func:`c3bf_gym.safety._step.filter_substep` fuses."""
    from c3bf_gym.safety import _step

    A, b, *_ = hook.rows()
    tau_nom = np.ascontiguousarray(tau_nom, dtype=np.float64)
    metric = None
    if hook.qp.metric_rows:  # the tool metric, from the site's dynamics as the per-class path computes them
        metric = np.zeros((3, len(tau_nom)))
        _step.tool_metric(hook.arm.site_dynamics(hook.data).G[0], hook._dofs, hook._scale, hook._tool_weight, metric)
    result = hook.qp.solve_scaled(tau_nom, A, b, hook._scale, hook._low_priority_span(len(b)), hook._stride,
                                  metric=metric)
    tau = np.empty_like(tau_nom)
    qp, m = hook.qp.buffers, len(b)
    _step.hook_post(b, qp.norm[:m], qp.residual[:m], result.tau, hook._scale, tau_nom, hook._limit, tau)
    n_obstacle = m - hook.floor.n_rows - hook._n_joint_rows
    if result.status == "relaxed" and not _step.beyond_allowance(qp.residual[:m], qp.norm[:m], hook._tally.row_h,
                                                                 hook._tally.gains, n_obstacle, hook._stride):
        result = result._replace(feasible=True, status="gain raised")  # the barrier's rows held, gain raised
    return tau, result


@pytest.mark.parametrize(("scenario", "name", "weight"), [("multi", "c3bf", "limits"), ("crossing", "c3bf", "limits"),
                                                     ("multi", "c3bf+hocbf", "limits"), ("multi", "c3bf+hocbf", "tool")])
def test_fused_step_replays_the_unfused_path(make_env, scenario, name, weight):
    """A seeded filtered rollout: the fused kernel gives the torques and outcomes (slack,
    status, iterations, active rows) of the unfused calls bit for bit, in either metric."""
    envs = [SafetyFilter(make_env(scenario=scenario), FilterConfig.named(name, weight=weight)) for _ in range(2)]
    hooks = [e.hook for e in envs]
    assert hooks[0]._fused
    seen = [[], []]
    fused, plain = hooks

    def fused_call(tau_nom):
        tau = fused(tau_nom)
        seen[0].append((tau.copy(), fused.last[1:-1]))
        return tau

    def plain_call(tau_nom):
        tau, result = _unfused_call(plain, tau_nom)
        seen[1].append((tau, result[1:-1]))
        return tau

    for e, call in zip(envs, (fused_call, plain_call)):
        e.unwrapped.remove_torque_hook("filter")
        e.unwrapped.add_torque_hook(call, "filter")
        e.reset(seed=3)
    rng = np.random.default_rng(3)
    for _ in range(60):
        action = rng.uniform(-1, 1, 6).astype(np.float32)
        for e in envs:
            e.step(action)
    assert len(seen[0]) == len(seen[1]) > 0
    for (tau_f, res_f), (tau_p, res_p) in zip(*seen):
        np.testing.assert_array_equal(tau_f, tau_p)
        assert res_f == res_p
    statuses = {res[2] for _, res in seen[0]}
    assert "solved" in statuses and (scenario == "crossing" or statuses & {"relaxed", "gain raised"})


@pytest.mark.parametrize(
    ("env_id", "scenario", "settings"),
    [("C3BFReach-v0", "multi", {}), ("C3BFReach-v0", "crossing", {"barrier": "c3bf", "guard": None}),
     ("C3BFReach-v0", "head_on", {"margin": 0.05}), ("C3BFReach-v0", "multi", {"points": "ee"}),
     ("C3BFReachPanda-v0", "multi", {"points": "ee"}),
     ("C3BFReach-v0", "head_on", {"points": "ee", "barrier": "hocbf"}),
     ("C3BFReachPanda-v0", "crossing", {"points": "ee", "barrier": "c3bf", "guard": None})],  # fmt: skip
)
def test_the_compiled_policy_step_replays_the_hooks_loop(env_id, scenario, settings):
    """The filter's calls inside the env's compiled policy step (``policy_steps``) give what the
    same calls through the hooks' Python loop give (``record_times`` sends every call through
    ``__call__``), bit for bit: observations, rewards, every ``info`` entry (the safety report's
    included), the joints, and a step with no safe torque raising (rolled back) at the same call.
    The tool sphere (``points="ee"``) too, on both arms: its rows are compiled as the whole arm's."""
    envs = [SafetyFilter(gym.make(env_id, scenario=scenario), **settings) for _ in range(2)]
    envs[1].hook.record_times()
    n = envs[0].action_space.shape[0]
    rng = np.random.default_rng(11)
    raised = [0, 0]
    steps = intervened = 0
    for episode in range(3):
        for env in envs:
            env.reset(seed=20 + episode)
        for _ in range(80):
            action = (rng.choice([-1.0, 1.0], n) if episode % 2 else rng.uniform(-1, 1, n)).astype(np.float32)
            outcomes = []
            for i, env in enumerate(envs):
                try:
                    outcomes.append(env.step(action))
                except SafetyInfeasibleError as error:
                    raised[i] += 1
                    outcomes.append(str(error))
            if isinstance(outcomes[0], str) or isinstance(outcomes[1], str):
                assert outcomes[0] == outcomes[1]  # both raised, with the same message
                continue
            (obs_a, r_a, *_, info_a), (obs_b, r_b, *_, info_b) = outcomes
            steps += 1
            intervened += info_a["safety"]["intervened"]
            assert obs_a.tobytes() == obs_b.tobytes() and r_a == r_b and info_a == info_b
            assert np.array_equal(envs[0].unwrapped.data.qpos, envs[1].unwrapped.data.qpos)
            assert np.array_equal(envs[0].unwrapped.data.qvel, envs[1].unwrapped.data.qvel)
    assert steps > 100 and raised == [0, 0] and intervened > 0  # (the filter changed some torques)
    assert envs[0].hook.last.status == envs[1].hook.last.status
    # the compiled calls are not timed (NaN), the recorded ones are
    assert np.isnan(envs[0].hook.report.solve_time) and envs[1].hook.report.solve_time > 0.0
    for env in envs:
        env.close()


def test_the_compiled_policy_step_raises_where_the_hooks_loop_raises(make_env):
    """``on_infeasible="raise"``: the compiled policy step and the hooks' Python loop raise at the
    same policy step, with the same message, from the same state (a 10 cm margin in ``multi``,
    chattering torques: seed 2 finds a step with no safe torque at step 121)."""
    envs = [SafetyFilter(make_env(scenario="multi"), on_infeasible="raise", margin=0.1) for _ in range(2)]
    envs[1].hook.record_times()
    raised = []
    for env in envs:
        env.reset(seed=2)
        rng = np.random.default_rng(2)
        for step in range(250):
            try:
                env.step(rng.choice([-1.0, 1.0], size=6).astype(np.float32))
            except SafetyInfeasibleError as error:
                raised.append((step, str(error)))
                break
    assert len(raised) == 2 and raised[0] == raised[1]
    for a, b in (("qpos", "qpos"), ("qvel", "qvel")):
        np.testing.assert_array_equal(getattr(envs[0].unwrapped.data, a), getattr(envs[1].unwrapped.data, b))


def test_a_bound_hook_pickles_and_binds_again(make_env):
    """What a hook gathers when it binds (views of this process's arrays, a compiled entry point)
    is left out of its pickle: the copy binds again on its first call."""
    import pickle

    env = SafetyFilter(make_env(scenario="multi"), barrier="c3bf")
    env.reset(seed=5)
    env.step(np.zeros(6, np.float32))  # binds the hook
    tau = env.hook(np.zeros(6))  # a call from Python: its entry point and the buffers' handle
    assert env.hook._bound and env.hook._filter_substep is not None
    A = env.hook._A.copy()
    hook = pickle.loads(pickle.dumps(env.hook))  # the hook alone (a wrapped env pickles as its arguments)
    assert hook._bound == () and hook._filter_substep is None
    assert env.hook.last is not None and hook.last is None  # the copy's QP is new: it has no last call
    # the same state (its QP starts cold, the original's warm: the same torque up to rounding)
    np.testing.assert_allclose(hook(np.zeros(6)), tau, rtol=0, atol=1e-9)
    assert hook._bound and hook._bound[0] is not env.hook._bound[0] and hook.qp is not env.hook.qp
    np.testing.assert_array_equal(hook.last.tau, hook.qp.buffers.u)
    handle, original = hook._filter_substep[1][0], env.hook._filter_substep[1][0]
    assert not np.array_equal(handle, original)  # the copy's own buffers
    np.testing.assert_array_equal(env.hook._A, A)  # the original's buffers untouched by the copy's call


def test_nominal_of_the_wrong_shape_is_refused(make_env):
    """The fused kernel is called through its compiled entry point, which does not check shapes:
    the hook does."""
    env = SafetyFilter(make_env(scenario="multi"), barrier="c3bf")
    env.reset(seed=0)
    for bad in (np.zeros(7), np.zeros((1, 6)), 0.0):
        with pytest.raises(ValueError, match="tau_nom must have shape"):
            env.hook(bad)
    assert env.hook(np.zeros(6)).shape == (6,)
