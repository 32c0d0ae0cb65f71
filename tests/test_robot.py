"""Tests for c3bf_gym/safety/dynamics.py: the arm's point dynamics against MuJoCo's own functions.

``ArmModel`` reads ``cdof``/``cdof_dot`` and does its own matrix products; every quantity is
checked here against an independent source: ``mj_jac`` / ``mj_jacSite`` / ``mj_jacDot`` for
Jacobians and velocities, a dense solve with ``M + h D`` (``mj_fullM`` plus the implicit joint
damping of MuJoCo's Euler step) for ``G = J (M + h D)⁻¹`` and the drift ``c``, a point-to-segment
computation on the capsule frames and MuJoCo's distance sensors for the closest points, and
physics steps for the accelerations ``Minv τ + qacc_free`` and ``G τ + c`` MuJoCo integrates.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from c3bf_gym.safety.dynamics import ArmModel, segment_closest_points
from c3bf_gym.scenarios import MAX_OBSTACLES

import reference

SEEDS = range(8)


# ----------------------------------------------------------------------------- helpers


@pytest.fixture
def env(make_env):
    e = make_env(scenario="none")
    e.reset(seed=0)
    return e.unwrapped


def random_state(u, rng, q_spread=np.pi, qd_spread=2.0) -> None:
    """A random joint state (positions around ``home``, velocities), kinematics up to date."""
    m, d = u.model, u.data
    d.qpos[:] = m.key_qpos[0] + rng.uniform(-q_spread, q_spread, m.nq)
    d.qvel[:] = rng.uniform(-qd_spread, qd_spread, m.nv)
    mujoco.mj_forward(m, d)
    u.state_version += 1


def mujoco_point(u, point, body):
    """(J, J̇) of ``point`` attached to ``body`` from mj_jac / mj_jacDot."""
    m, d = u.model, u.data
    jac = np.zeros((3, m.nv))
    jdot = np.zeros((3, m.nv))
    mujoco.mj_jac(m, d, jac, None, point, body)
    mujoco.mj_jacDot(m, d, jdot, None, point, body)
    return jac, jdot


def step_inertia(u):
    """``M + h D``: the matrix MuJoCo's Euler step solves with (joint damping is implicit)."""
    m = u.model
    assert m.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER and not m.opt.disableflags
    full = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, u.data, full)
    return full + m.opt.timestep * np.diag(m.dof_damping)


def solve_m(u, rhs):
    """(M + h D)⁻¹ rhs, dense (rhs (k, nv) or (nv,))."""
    return np.linalg.solve(step_inertia(u), np.asarray(rhs, dtype=float).T).T


def expected_dynamics(u, point, body):
    """Independent (pos, vel, J, G, c) of a material point, from MuJoCo's functions."""
    d = u.data
    jac, jdot = mujoco_point(u, point, body)
    G = solve_m(u, jac)  # rows M_h⁻¹ J_iᵀ = (J M_h⁻¹)_i since M_h = M + h D is symmetric
    c = jac @ solve_m(u, d.qfrc_passive - d.qfrc_bias) + jdot @ d.qvel
    return np.asarray(point, float), jac @ d.qvel, jac, G, c


def assert_point_matches(got, k, expected, atol=1e-10):
    pos, vel, jac, G, c = expected
    scale = max(1.0, float(np.abs(c).max()))
    np.testing.assert_allclose(got.pos[k], pos, rtol=0, atol=atol)
    np.testing.assert_allclose(got.vel[k], vel, rtol=0, atol=atol)
    if got.jac is not None:
        np.testing.assert_allclose(got.jac[k], jac, rtol=0, atol=atol)
    np.testing.assert_allclose(got.G[k], G, rtol=0, atol=atol * max(1.0, float(np.abs(G).max())))
    np.testing.assert_allclose(got.c[k], c, rtol=0, atol=atol * scale)


def capsule_frame(u, gid):
    """End points of a capsule axis from ``geom_xmat`` (row-major 3x3, axis = z column)."""
    m, d = u.model, u.data
    axis = d.geom_xmat[gid].reshape(3, 3)[:, 2]
    half = m.geom_size[gid, 1]
    return d.geom_xpos[gid] - half * axis, d.geom_xpos[gid] + half * axis


def closest_on_segment(a, b, x):
    ab = b - a
    t = np.clip(np.dot(x - a, ab) / np.dot(ab, ab), 0.0, 1.0)
    return a + t * ab


def arm_bodies(u):
    """The arm's moving bodies (those carrying a protected capsule: link1 ... link6)."""
    return sorted({int(u.model.geom_bodyid[g]) for g in u.arm.capsule_ids})


# ----------------------------------------------------------------------------- construction


def test_protected_capsules_are_the_movable_capsule_geoms(env):
    u = env
    arm = u.arm
    m = u.model
    # the base is a cylinder on the fixed body; link1 lies on the base's pan axis (nothing moves it away)
    expected = [g for g in u.arm_geom_ids if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE][1:]
    assert list(arm.capsule_ids) == expected == list(u.robot.geom_ids)
    assert arm.capsule_names == ["link2", "link3", "link4", "link5", "link6", "tool"]
    np.testing.assert_array_equal(arm.capsule_radius, m.geom_size[expected, 0])
    half = m.geom_size[expected, 1]
    np.testing.assert_array_equal(arm.capsule_local[:, 1, 2], half)  # capsules as they are: a, b = (0, 0, ∓half)
    np.testing.assert_array_equal(arm.capsule_local[:, 0, 2], -half)
    assert arm.site_id == u.ee_site_id


def test_model_without_moving_capsules_rejected(env):
    u = env
    with pytest.raises(ValueError, match="no protected geoms on moving arm bodies"):
        ArmModel(u.model, np.array([u.arm_geom_ids[0]]), u.ee_site_id)  # the base cylinder only


# ----------------------------------------------------------------------------- point dynamics


@pytest.mark.parametrize("seed", SEEDS)
def test_point_dynamics_matches_mj_jac_jacdot_and_solveM(env, seed):
    u = env
    rng = np.random.default_rng(seed)
    random_state(u, rng)
    arm = u.arm
    arm.update(u.data, u.state_version)
    bodies = arm_bodies(u)
    body_of = rng.choice(bodies, size=12)
    points = u.data.xpos[body_of] + rng.uniform(-0.3, 0.3, (12, 3))
    chain = np.array([ArmModel._chain_mask(u.model, b) for b in body_of])
    got = reference.point_dynamics(arm, u.data, points, chain)
    assert got.pos.shape == (12, 3) and got.jac.shape == (12, 3, 6) and got.G.shape == (12, 3, 6)
    for k, b in enumerate(body_of):
        assert_point_matches(got, k, expected_dynamics(u, points[k], b))
    # the state is really moving: the check is not 0 == 0
    assert np.abs(got.vel).max() > 0.1 and np.abs(got.c - np.einsum("pij,j->pi", got.jac, arm.qacc_free)).max() > 0.1


@pytest.mark.parametrize("seed", SEEDS)
def test_site_dynamics_matches_mj_jacsite(env, seed):
    u = env
    m, d = u.model, u.data
    rng = np.random.default_rng(seed)
    random_state(u, rng)
    arm = u.arm
    arm.update(d, u.state_version)
    got = arm.site_dynamics(d)
    jac_site = np.zeros((3, m.nv))
    mujoco.mj_jacSite(m, d, jac_site, None, u.ee_site_id)
    np.testing.assert_allclose(got.jac[0], jac_site, rtol=0, atol=1e-10)
    body = m.site_bodyid[u.ee_site_id]
    assert_point_matches(got, 0, expected_dynamics(u, d.site_xpos[u.ee_site_id].copy(), body))


@pytest.mark.parametrize("seed", SEEDS)
def test_minv_and_free_acceleration_match_mujoco(env, seed):
    """``Minv`` inverts ``M + h D``, and ``qacc_free`` is the joint acceleration a physics step
    integrates at zero actuator torque (not the continuous-time ``M⁻¹ f`` of ``mj_forward``)."""
    u = env
    m, d = u.model, u.data
    rng = np.random.default_rng(seed)
    for _ in range(50):  # a state without floor contact (constraint forces would enter qacc)
        random_state(u, rng, q_spread=1.0)
        if d.nefc == 0:
            break
    arm = u.arm
    arm.update(d, u.state_version)
    np.testing.assert_allclose(arm.Minv @ step_inertia(u), np.eye(m.nv), atol=1e-9)
    np.testing.assert_allclose(arm.Minv, arm.Minv.T, atol=1e-12)
    # qacc_free is the acceleration one Euler step integrates with zero net actuator torque
    d.ctrl[:] = -d.qfrc_gravcomp  # the motors add gravity compensation back: zero net actuator torque
    qvel = d.qvel.copy()
    mujoco.mj_step2(m, d)  # data holds mj_forward results for this state, as after mj_step1
    assert d.nefc == 0  # no contact or limit: q̇⁺ = q̇ + h (M + h D)⁻¹ (passive − bias)
    np.testing.assert_allclose(d.qfrc_actuator, 0.0, atol=1e-9)
    integrated = (d.qvel - qvel) / m.opt.timestep
    np.testing.assert_allclose(arm.qacc_free, integrated, rtol=0, atol=1e-9 * np.abs(integrated).max())
    # ... which is not mj_forward's M⁻¹(passive − bias): the check can tell them apart
    assert np.abs(d.qacc - integrated).max() > 1e-3 * np.abs(integrated).max()


def test_minv_without_implicit_damping_is_the_inverse_mass_matrix(env):
    """With ``mjDSBL_EULERDAMP`` (or RK4) the step is explicit in the damping: ``Minv = M⁻¹``."""
    u = env
    m, d = u.model, u.data
    random_state(u, np.random.default_rng(3), q_spread=1.0)
    full = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, full)
    for flags, integrator in ((mujoco.mjtDisableBit.mjDSBL_EULERDAMP, m.opt.integrator), (0, mujoco.mjtIntegrator.mjINT_RK4)):
        m.opt.disableflags, m.opt.integrator = flags, integrator
        arm = ArmModel(m, u.arm_geom_ids, u.ee_site_id)
        arm.update(d)
        np.testing.assert_allclose(arm.implicit_damping, 0.0)
        np.testing.assert_allclose(arm.Minv @ full, np.eye(m.nv), atol=1e-9)
    m.opt.disableflags, m.opt.integrator = 0, mujoco.mjtIntegrator.mjINT_EULER
    np.testing.assert_allclose(ArmModel(m, u.arm_geom_ids, u.ee_site_id).implicit_damping, m.opt.timestep * m.dof_damping)


# ----------------------------------------------------------------------------- closest points


@pytest.mark.parametrize("seed", SEEDS)
def test_closest_dynamics_matches_segment_geometry_and_mujoco(env, seed):
    u = env
    m, d = u.model, u.data
    rng = np.random.default_rng(seed)
    random_state(u, rng)
    arm = u.arm
    arm.update(d, u.state_version)
    # centres near the arm, including beyond both ends of every capsule
    centres = d.geom_xpos[rng.choice(arm.capsule_ids, 5)] + rng.uniform(-0.4, 0.4, (5, 3))
    got = reference.closest_dynamics(arm, centres)
    s = len(arm.capsule_ids)
    assert got.pos.shape == (5 * s, 3) and got.jac is None
    clamped = 0
    for k, centre in enumerate(centres):
        for j, gid in enumerate(arm.capsule_ids):
            a, b = capsule_frame(u, gid)
            x = closest_on_segment(a, b, centre)
            clamped += np.allclose(x, a) or np.allclose(x, b)
            row = k * s + j  # obstacle-major
            assert_point_matches(got, row, expected_dynamics(u, x, m.geom_bodyid[gid]), atol=1e-9)
    assert 0 < clamped < 5 * s  # both interior and end-point cases were exercised


def test_segment_closest_points_function():
    a = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    b = np.array([[1.0, 0.0, 0.0], [1.0, 1.0, 1.0]])  # second segment degenerate (a point)
    centres = np.array([[0.5, 2.0, 0.0], [-1.0, 0.0, 0.0], [3.0, 0.0, 1.0]])
    got = segment_closest_points(a, b, centres)
    assert got.shape == (3, 2, 3)
    np.testing.assert_allclose(got[:, 0], [[0.5, 0, 0], [0, 0, 0], [1, 0, 0]])
    np.testing.assert_allclose(got[:, 1], np.ones((3, 3)))


@pytest.mark.parametrize("seed", SEEDS)
def test_closest_points_reproduce_mujoco_distance_sensors(env, seed):
    """|closest point − centre| − capsule radius − obstacle radius is MuJoCo's signed distance."""
    u = env
    m, d = u.model, u.data
    rng = np.random.default_rng(seed)
    random_state(u, rng, q_spread=1.0)
    arm = u.arm
    radii = rng.uniform(0.03, 0.1, MAX_OBSTACLES)
    centres = np.empty((MAX_OBSTACLES, 3))
    for slot in range(MAX_OBSTACLES):
        # near a random capsule, sometimes overlapping it (but never on its axis)
        gid = rng.choice(arm.capsule_ids)
        a, b = capsule_frame(u, gid)
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        if slot == 0:  # certainly overlapping its capsule (off the axis)
            radii[slot] = 0.08
            centres[slot] = a + rng.uniform(0.2, 0.8) * (b - a) + direction * 0.04
        else:
            centres[slot] = a + rng.uniform(-0.2, 1.2) * (b - a) + direction * rng.uniform(0.02, 0.6)
        u.place_obstacle(slot, centres[slot], radius=radii[slot])
    arm.update(d, u.state_version)
    got = reference.closest_dynamics(arm, u.obstacle_pos.copy())
    s = len(arm.capsule_ids)
    columns = [list(u.arm_geom_ids).index(g) for g in arm.capsule_ids]
    gap = np.linalg.norm(got.pos - np.repeat(centres, s, axis=0), axis=1).reshape(MAX_OBSTACLES, s)
    gap -= arm.capsule_radius[None, :] + radii[:, None]
    sensors = u.distances[:, columns]
    assert np.all(sensors < 3.0)  # all within the sensors' cutoff: a real comparison
    np.testing.assert_allclose(gap, sensors, rtol=0, atol=1e-9)
    assert gap.min() < 0 < gap.max()  # penetrating and separated pairs both checked


# ----------------------------------------------------------------------------- caching


def test_update_caches_on_state_version(env):
    u = env
    m, d = u.model, u.data
    rng = np.random.default_rng(1)
    arm = u.arm
    centres = np.array([[0.3, 0.2, 0.4], [-0.2, 0.3, 0.6]])
    random_state(u, rng)
    arm.update(d, u.state_version)
    before = reference.closest_dynamics(arm, centres)
    site_before = arm.site_dynamics(d)
    minv_before = arm.Minv.copy()
    free_before = arm.qacc_free.copy()
    # move the arm but keep the version: nothing is recomputed
    d.qpos[:] += 0.3
    d.qvel[:] = 1.0
    mujoco.mj_forward(m, d)
    arm.update(d, u.state_version)
    np.testing.assert_array_equal(arm.Minv, minv_before)
    np.testing.assert_array_equal(arm.qacc_free, free_before)
    same = reference.closest_dynamics(arm, centres)
    for x, y in zip(before, same):
        if x is not None:
            np.testing.assert_array_equal(x, y)
    # a new version recomputes from the new state
    u.state_version += 1
    arm.update(d, u.state_version)
    after = reference.closest_dynamics(arm, centres)
    assert not np.allclose(after.pos, before.pos)
    s = len(arm.capsule_ids)
    for j, gid in enumerate(arm.capsule_ids):
        a, b = capsule_frame(u, gid)
        np.testing.assert_allclose(after.pos[s + j], closest_on_segment(a, b, centres[1]), atol=1e-12)
    np.testing.assert_allclose(arm.Minv @ step_inertia(u), np.eye(m.nv), atol=1e-9)
    site_after = arm.site_dynamics(d)
    assert_point_matches(site_after, 0, expected_dynamics(u, d.site_xpos[u.ee_site_id].copy(), m.site_bodyid[u.ee_site_id]))
    assert not np.allclose(site_after.G, site_before.G)
    # no version: always recompute
    d.qpos[:] -= 0.2
    mujoco.mj_forward(m, d)
    arm.update(d)
    again = reference.closest_dynamics(arm, centres)
    for j, gid in enumerate(arm.capsule_ids):
        a, b = capsule_frame(u, gid)
        np.testing.assert_allclose(again.pos[j], closest_on_segment(a, b, centres[0]), atol=1e-12)


def test_env_steps_advance_the_version_and_the_cache_follows(env):
    """Through the env: every physics step is a new version, the hook sees the current state."""
    u = env
    seen = []

    def hook(tau):
        u.arm.update(u.data, u.state_version)
        centre = np.array([[0.4, 0.1, 0.5]])
        a, b = capsule_frame(u, u.arm.capsule_ids[2])
        seen.append((u.state_version, reference.closest_dynamics(u.arm, centre).pos[2].copy(), closest_on_segment(a, b, centre[0])))
        return tau

    u.add_torque_hook(hook, "nominal")
    try:
        u.step(np.full(6, 0.3, np.float32))
        u.step(np.full(6, 0.3, np.float32))
    finally:
        u.remove_torque_hook("nominal")
    versions = [v for v, _, _ in seen]
    assert len(versions) == 2 * u.frame_skip and len(set(versions)) == len(versions)
    for _, cached, actual in seen:
        np.testing.assert_allclose(cached, actual, atol=1e-12)
    assert not np.allclose(seen[0][1], seen[-1][1])


# ----------------------------------------------------------------------------- one-step prediction


def material_point(u, point, body):
    """Body-frame coordinates of a world point on ``body``."""
    d = u.data
    return d.xmat[body].reshape(3, 3).T @ (point - d.xpos[body])


def world_point(u, local, body):
    d = u.data
    return d.xpos[body] + d.xmat[body].reshape(3, 3) @ local


@pytest.mark.parametrize("seed", range(4))
def test_predicted_acceleration_matches_one_physics_step(make_env, seed):
    """``Minv τ + qacc_free`` and ``G τ + c`` are the accelerations the next physics step gives.

    MuJoCo's Euler integrator treats joint damping implicitly, ``q̇⁺ = q̇ + h (M + h D)⁻¹ f``
    (``f = τ + passive − bias``, the passive force holding the explicit ``−D q̇``). The joint
    acceleration it integrates, ``(q̇⁺ − q̇) / h``, must equal the prediction to rounding, and so
    must the material points' ``J q̈ + J̇ q̇`` at that ``q̈`` (``mj_jac``/``mj_jacDot`` before the
    step). The continuous-time ``M⁻¹ f`` is 2–4 % off here (D = 10 N m s/rad on the big joints,
    h = 2 ms), which the tolerances below would catch. Over the step the points' velocity changes
    by that acceleration up to O(h) (J changes along the step): 0.5 %.
    """
    e = make_env(scenario="none", frame_skip=1)
    e.reset(seed=seed)
    u = e.unwrapped
    m, d = u.model, u.data
    h = m.opt.timestep
    rng = np.random.default_rng(seed)
    d.qvel[:] = rng.uniform(-0.3, 0.3, m.nv)
    mujoco.mj_forward(m, d)
    u.state_version += 1
    delta = rng.uniform(-0.05, 0.05, m.nv) * u.torque_limit  # a small torque on top of gravity comp.
    arm = u.arm
    rec = {}

    def hook(tau_in):
        arm.update(d, u.state_version)
        tau = delta + d.qfrc_gravcomp  # total actuator torque
        site = arm.site_dynamics(d)
        centre = d.geom_xpos[arm.capsule_ids[2]] + np.array([0.0, 0.0, 0.2])
        closest = reference.closest_dynamics(arm, centre[None])
        bodies = [m.site_bodyid[u.ee_site_id]] + [m.geom_bodyid[g] for g in arm.capsule_ids]
        points = np.concatenate([site.pos, closest.pos])
        full = np.zeros((m.nv, m.nv))
        mujoco.mj_fullM(m, d, full)
        rec.update(
            tau=tau,
            qvel=d.qvel.copy(),
            qacc=arm.Minv @ tau + arm.qacc_free,
            qacc_explicit=np.linalg.solve(full, tau + d.qfrc_passive - d.qfrc_bias),
            jac=[mujoco_point(u, p, b) for p, b in zip(points, bodies)],
            bodies=bodies,
            local=[material_point(u, p, b) for p, b in zip(points, bodies)],
            vel=np.concatenate([site.vel, closest.vel]),
            pred=np.einsum("pij,j->pi", np.concatenate([site.G, closest.G]), tau) + np.concatenate([site.c, closest.c]),
        )
        return tau

    u.add_torque_hook(hook, "nominal")
    try:
        e.step(np.zeros(6, np.float32))
    finally:
        u.remove_torque_hook("nominal")
    assert d.nefc == 0
    np.testing.assert_allclose(d.qfrc_actuator, rec["tau"], rtol=0, atol=1e-9)  # applied as predicted
    integrated = (d.qvel - rec["qvel"]) / h
    scale = np.abs(integrated).max()
    np.testing.assert_allclose(rec["qacc"], integrated, rtol=0, atol=1e-9 * scale)
    assert np.abs(rec["qacc_explicit"] - integrated).max() > 1e-2 * scale  # M⁻¹ f would fail above
    point_acc = np.array([jac @ integrated + jdot @ rec["qvel"] for jac, jdot in rec["jac"]])
    np.testing.assert_allclose(rec["pred"], point_acc, rtol=0, atol=1e-9 * np.abs(point_acc).max())
    vel_after = np.array(
        [mujoco_point(u, world_point(u, loc, b), b)[0] @ d.qvel for loc, b in zip(rec["local"], rec["bodies"])]
    )
    fd = (vel_after - rec["vel"]) / h
    bodies_moving = [i for i, b in enumerate(rec["bodies"]) if np.linalg.norm(fd[i]) > 0.5]
    assert len(bodies_moving) >= 4  # real accelerations, not 0 == 0
    for i in bodies_moving:
        assert np.linalg.norm(rec["pred"][i] - fd[i]) <= 0.005 * np.linalg.norm(fd[i]) + 1e-3, (i, rec["pred"][i], fd[i])


# ----------------------------------------------------------------------------- sliding closest points


def scene_near_capsules(u, seed, count):
    """A random arm state (dynamics updated) and ``count`` centres near random capsules:
    (rng, arm, number of capsules, centres)."""
    d = u.data
    rng = np.random.default_rng(seed)
    random_state(u, rng, q_spread=1.0)
    arm = u.arm
    arm.update(d, u.state_version)
    centres = d.geom_xpos[rng.choice(arm.capsule_ids, count)] + rng.uniform(-0.3, 0.3, (count, 3))
    return rng, arm, len(arm.capsule_ids), centres


def closest_state(u, centre, centre_vel, gid):
    """(p, v) of the closest point of capsule ``gid`` to a moving centre, from the geom frame."""
    a, b = capsule_frame(u, gid)
    x = closest_on_segment(a, b, centre)
    jac, _ = mujoco_point(u, x, u.model.geom_bodyid[gid])
    return x - centre, jac @ u.data.qvel - centre_vel


@pytest.mark.parametrize("seed", range(6))
def test_closest_sliding_is_the_rate_of_the_moving_closest_point(env, seed):
    """ṗ = v + slide_p and v̇ = (material acceleration) + slide_v, where p, v are the closest
    point's offset and velocity found anew at every instant: checked by central differences
    along the motion (joints at a random q̈, centres at constant velocity)."""
    u = env
    m, d = u.model, u.data
    rng, arm, s, centres = scene_near_capsules(u, seed, 4)
    centre_vel = rng.uniform(-0.5, 0.5, (4, 3))
    qacc = rng.uniform(-5, 5, m.nv)
    got = reference.closest_dynamics(arm, centres)
    p = got.pos - np.repeat(centres, s, axis=0)
    v = got.vel - np.repeat(centre_vel, s, axis=0)
    slide_p, slide_v = reference.closest_sliding(arm, centres, p, v)
    assert slide_p.shape == slide_v.shape == (4 * s, 3)
    tau = step_inertia(u) @ qacc - (d.qfrc_passive - d.qfrc_bias)  # the torque giving q̈
    material_acc = np.einsum("pij,j->pi", got.G, tau) + got.c  # = J q̈ + J̇ q̇
    q0, qd0, delta = d.qpos.copy(), d.qvel.copy(), 1e-5
    states = []
    for sign in (1.0, -1.0):
        dt = sign * delta
        d.qpos[:] = q0 + dt * qd0 + 0.5 * dt**2 * qacc
        d.qvel[:] = qd0 + dt * qacc
        mujoco.mj_forward(m, d)
        states.append([closest_state(u, centres[k] + dt * centre_vel[k], centre_vel[k], g)
                       for k in range(4) for g in arm.capsule_ids])  # fmt: skip
    d.qpos[:], d.qvel[:] = q0, qd0
    mujoco.mj_forward(m, d)
    p_dot = np.array([(a[0] - b[0]) / (2 * delta) for a, b in zip(*states)])
    v_dot = np.array([(a[1] - b[1]) / (2 * delta) for a, b in zip(*states)])
    np.testing.assert_allclose(p_dot, v + slide_p, rtol=0, atol=1e-6)
    np.testing.assert_allclose(v_dot, material_acc + slide_v, rtol=0, atol=1e-5 * max(1.0, np.abs(v_dot).max()))
    sliding = np.linalg.norm(slide_p, axis=1) > 1e-3
    assert 0 < sliding.sum() < 4 * s  # interior (sliding) and clamped (end point) cases both seen



@pytest.mark.parametrize("seed", range(3))
def test_closest_relative_combines_dynamics_and_sliding(env, seed):
    """closest_relative is closest_dynamics relative to the obstacles, with closest_sliding's
    v̇ term folded into c and its ṗ term returned."""
    rng, arm, s, centres = scene_near_capsules(env, seed, 3)
    vel, acc = rng.uniform(-0.5, 0.5, (3, 3)), rng.uniform(-1.0, 1.0, (3, 3))
    rel, slide_p = arm.closest_relative(centres, vel, acc)
    pd = reference.closest_dynamics(arm, centres)
    p = pd.pos - np.repeat(centres, s, axis=0)
    v = pd.vel - np.repeat(vel, s, axis=0)
    want_p, want_v = reference.closest_sliding(arm, centres, p, v)
    np.testing.assert_allclose(rel.pos, p, rtol=0, atol=1e-14)
    np.testing.assert_allclose(rel.vel, v, rtol=0, atol=1e-14)
    np.testing.assert_allclose(rel.G, pd.G, rtol=0, atol=1e-14)
    np.testing.assert_allclose(rel.c, pd.c - np.repeat(acc, s, axis=0) + want_v, rtol=0, atol=1e-12)
    np.testing.assert_allclose(slide_p, want_p, rtol=0, atol=1e-14)
    assert np.abs(slide_p).max() > 1e-3 and rel.jac is None
