"""Tests for the ``C3BFReach-v0`` environment (c3bf_gym/envs/reach.py): API conformance, physics
health, determinism, reward and cost signals, observation layout, input validation, rendering,
pickling/vectorisation and gravity compensation.

Obstacles are placed by hand with the environment's ``place_obstacle`` (mocap position,
velocity, radius and the model's geom size, then ``mujoco.mj_forward``), so that the distance
sensors see them before the next step.
"""

from __future__ import annotations

import inspect
import os
import pickle
import time
import warnings
from functools import partial
from importlib import resources

import gymnasium as gym
import mujoco
import numpy as np
import pytest

from c3bf_gym import SCENARIOS, C3BFReachEnv, ObstacleSpec, Scenario
from c3bf_gym.envs.reach import DISTANCE_CUTOFF, OBSERVATION_LAYOUT
from c3bf_gym.scenarios import MAX_OBSTACLES

from conftest import ENV_ID

N_WARNINGS = int(mujoco.mjtWarning.mjNWARNING)
K = MAX_OBSTACLES
# Observation slices, from the documented layout (checked against OBSERVATION_LAYOUT below).
JOINT_POS, JOINT_VEL = slice(0, 6), slice(6, 12)
TOOL_POS, TOOL_VEL, GOAL_REL = slice(12, 15), slice(15, 18), slice(18, 21)
OBS_REL = slice(21, 21 + 3 * K)
OBS_VEL = slice(21 + 3 * K, 21 + 6 * K)
OBS_RADIUS = slice(21 + 6 * K, 21 + 7 * K)
OBS_SENSED = slice(21 + 7 * K, 21 + 8 * K)


# ----------------------------------------------------------------------------- helpers


def warnings_raised(data: mujoco.MjData) -> dict[str, int]:
    """MuJoCo warnings with a non-zero count (name -> count)."""
    return {
        mujoco.mjtWarning(i).name: int(data.warning[i].number)
        for i in range(N_WARNINGS)
        if data.warning[i].number != 0
    }


def geom_id(model: mujoco.MjModel, name: str) -> int:
    gid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name)
    assert gid >= 0, name
    return gid


def capsule_segment(model, data, gid: int) -> tuple[np.ndarray, np.ndarray, float]:
    """End points and radius of a capsule geom, from MuJoCo's world pose of the geom."""
    axis = data.geom_xmat[gid].reshape(3, 3)[:, 2]
    half = model.geom_size[gid, 1]
    centre = data.geom_xpos[gid]
    return centre - half * axis, centre + half * axis, float(model.geom_size[gid, 0])


def sphere_capsule_distance(centre, radius, a, b, capsule_radius) -> float:
    """Signed surface distance between a sphere and a capsule (segment a-b, radius)."""
    ab = b - a
    t = np.clip(np.dot(centre - a, ab) / np.dot(ab, ab), 0.0, 1.0)
    return float(np.linalg.norm(centre - (a + t * ab)) - capsule_radius - radius)


def independent_arm_distances(env, centre, radius) -> dict[str, float]:
    """Sphere-to-geom distances for every *capsule* arm geom, computed here from the geom poses."""
    u = env.unwrapped
    m, d = u.model, u.data
    out = {}
    for gid in u.arm_geom_ids:
        if m.geom_type[gid] != mujoco.mjtGeom.mjGEOM_CAPSULE:
            continue
        a, b, r = capsule_segment(m, d, gid)
        out[mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, gid)] = sphere_capsule_distance(
            np.asarray(centre), radius, a, b, r
        )
    return out


def put_obstacle(env, slot: int, centre, radius: float, velocity=(0.0, 0.0, 0.0)) -> None:
    """Place obstacle ``slot`` by hand (sensors and contacts brought up to date)."""
    env.unwrapped.place_obstacle(slot, centre, velocity, radius)


def beside_link(env, link: str, surface_gap: float, radius: float) -> np.ndarray:
    """A sphere centre ``surface_gap`` from the middle of ``link``'s capsule, horizontally off it."""
    u = env.unwrapped
    gid = geom_id(u.model, link)
    a, b, r = capsule_segment(u.model, u.data, gid)
    axis = (b - a) / np.linalg.norm(b - a)
    side = np.cross(axis, [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side)
    return 0.5 * (a + b) + side * (r + radius + surface_gap)


def state_snapshot(env) -> dict[str, np.ndarray]:
    d = env.unwrapped.data
    return {
        "qpos": d.qpos.copy(),
        "qvel": d.qvel.copy(),
        "time": np.array(d.time),
        "mocap_pos": d.mocap_pos.copy(),
        "ctrl": d.ctrl.copy(),
        "obstacle_vel": env.unwrapped.obstacle_vel.copy(),
    }


def gl_unavailable_reason() -> str | None:
    try:
        ctx = mujoco.GLContext(16, 16)
        ctx.make_current()
        ctx.free()
    except Exception as exc:  # noqa: BLE001 - any failure means no usable backend
        return f"no usable OpenGL backend for MUJOCO_GL={os.environ.get('MUJOCO_GL')!r}: {exc!r}"
    return None


# ----------------------------------------------------------------------------- 1. API checkers


def _pusher_unbounded_space_warnings() -> set[str]:
    """The warnings Gymnasium's checker gives Gymnasium's own Pusher-v5 for its observation space.

    Every Gymnasium MuJoCo environment declares ``Box(-inf, inf)`` observations (velocities have
    no a-priori bound), and so does ours by design; ``check_space_limit`` warns about that for
    all of them. Only these exact messages are tolerated below.
    """
    from gymnasium.utils.env_checker import check_space_limit

    pusher = gym.make("Pusher-v5")
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            check_space_limit(pusher.observation_space, "observation")
    finally:
        pusher.close()
    messages = {str(w.message) for w in caught}
    assert messages, "expected Gymnasium to warn about Pusher-v5's unbounded observation space"
    return messages


def test_gymnasium_check_env_passes(make_env):
    from gymnasium.utils.env_checker import check_env

    tolerated = _pusher_unbounded_space_warnings()
    env = make_env()
    # skip_render_check: check_env would instantiate every declared render mode, including
    # "human", which opens a GLFW window; on a headless machine GLFW aborts the whole process
    # (C assertion in glfwGetVideoMode). That is GLFW/Gymnasium's viewer, not this environment;
    # rgb_array and depth_array are checked with Gymnasium's render checker in test_render_*.
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped, skip_render_check=True)
    ours = [str(w.message) for w in caught if str(w.message) not in tolerated]
    assert ours == []


def test_sb3_check_env_passes(make_env):
    from stable_baselines3.common.env_checker import check_env

    env = make_env()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, warn=True)
    assert [str(w.message) for w in caught] == []


def test_observation_layout_constant_matches_space(make_env):
    env = make_env()
    sizes = [size for _, size, _ in OBSERVATION_LAYOUT]
    assert sum(sizes) == env.observation_space.shape[0] == 85
    assert [name for name, _, _ in OBSERVATION_LAYOUT][-1] == "obstacle_sensed"
    assert OBS_SENSED.stop == 85
    assert env.action_space.shape == (6,)
    assert env.action_space.dtype == np.float32
    assert np.all(env.action_space.low == -1.0) and np.all(env.action_space.high == 1.0)


# ----------------------------------------------------------------------------- 2. physics health


@pytest.mark.parametrize("scenario", list(SCENARIOS))
def test_every_scenario_steps_one_second_cleanly(make_env, scenario):
    env = make_env(scenario=scenario)
    u = env.unwrapped
    n_steps = int(round(1.0 / u.dt))
    for seed in (0, 1, 2):
        obs, _ = env.reset(seed=seed)
        assert np.all(np.isfinite(obs))
        env.action_space.seed(seed)
        for _ in range(n_steps):
            obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
            assert np.all(np.isfinite(obs)), f"{scenario} seed {seed}: non-finite observation"
            assert np.isfinite(reward) and np.isfinite(info["min_distance"])
            assert not (terminated or truncated)
        assert u.data.time == pytest.approx(1.0, abs=1e-9)
        assert warnings_raised(u.data) == {}, f"{scenario} seed {seed}"


@pytest.mark.parametrize("keyframe", [None, "home"])
def test_raw_scene_holds_still_under_gravity_compensation(keyframe):
    path = str(resources.files("c3bf_gym.assets").joinpath("scene.xml"))
    model = mujoco.MjModel.from_xml_path(path)
    data = mujoco.MjData(model)
    assert model.opt.gravity[2] < -9.0  # gravity is on: holding still is gravcomp's doing
    if keyframe is not None:
        mujoco.mj_resetDataKeyframe(model, data, mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, keyframe))
    q0 = data.qpos.copy()
    data.ctrl[:] = 0.0
    while data.time < 1.0 - 1e-9:
        mujoco.mj_step(model, data)
    assert data.time == pytest.approx(1.0)
    assert np.max(np.abs(data.qpos - q0)) < 1e-3
    assert warnings_raised(data) == {}


# ----------------------------------------------------------------------------- 3. determinism


def _rollout(env, seed: int, actions: np.ndarray):
    obs, info = env.reset(seed=seed)
    trace = [(obs, None, info)]
    for action in actions:
        obs, reward, terminated, truncated, info = env.step(action)
        trace.append((obs, (reward, terminated, truncated), info))
    return trace


def test_same_seed_same_actions_bit_identical(make_env):
    actions = np.random.default_rng(123).uniform(-1.0, 1.0, size=(100, 6)).astype(np.float32)
    # "multi" has four obstacles, several of which leave the workspace and respawn (draws from
    # the env's generator) within 100 steps for some seeds; also the default mixture.
    for scenario in ("multi", "random"):
        a, b = make_env(scenario=scenario), make_env(scenario=scenario)
        ta, tb = _rollout(a, 7, actions), _rollout(b, 7, actions)
        for (oa, ra, ia), (ob, rb, ib) in zip(ta, tb, strict=True):
            assert oa.dtype == ob.dtype == np.float32
            assert oa.tobytes() == ob.tobytes()
            assert ra == rb
            assert ia == ib  # exact float equality of every info entry
        # and it is the seed, not the history, that fixes an episode
        tc = _rollout(a, 7, actions[:10])
        assert all(x[0].tobytes() == y[0].tobytes() for x, y in zip(tc, ta[:11], strict=True))


def test_different_seeds_different_goals(make_env):
    env = make_env()
    goals = []
    for seed in range(10):
        obs, _ = env.reset(seed=seed)
        goals.append(obs[GOAL_REL] + obs[TOOL_POS])
    goals = np.array(goals)
    # pairwise distinct goals
    gaps = np.linalg.norm(goals[:, None] - goals[None], axis=-1) + np.eye(len(goals))
    assert gaps.min() > 1e-3


# ----------------------------------------------------------------------------- 4. reward


def test_reward_terms_sum_to_reward_and_follow_the_spec(make_env):
    env = make_env(scenario="multi")
    u = env.unwrapped
    defaults = inspect.signature(C3BFReachEnv).parameters
    w_progress, w_effort = defaults["progress_weight"].default, defaults["effort_weight"].default
    env.reset(seed=11)
    rng = np.random.default_rng(0)
    goal = u.goal.copy()
    d_prev = float(np.linalg.norm(goal - u.data.site_xpos[u.ee_site_id]))
    for step in range(1, 251):
        action = rng.uniform(-1.0, 1.0, 6).astype(np.float32)
        _, reward, terminated, truncated, info = env.step(action)
        total = info["reward_progress"] + info["reward_success"] + info["reward_distance"] + info["reward_effort"]
        assert abs(total - reward) <= 1e-12
        assert info["reward_distance"] == 0.0, "the dense distance term is off by default"
        d = float(np.linalg.norm(goal - u.data.site_xpos[u.ee_site_id]))
        assert info["distance"] == pytest.approx(d, abs=1e-12)
        assert info["reward_progress"] == pytest.approx(w_progress * (d_prev - d), abs=1e-9)
        d_prev = d
        # effort: mean over joints of (torque / limit)^2 = mean(action^2) (no hooks installed)
        assert info["reward_effort"] == pytest.approx(-w_effort * np.mean(action.astype(float) ** 2), rel=1e-9)
        assert not terminated
        assert truncated == (step == 250), "episodes are truncated at exactly 250 steps"


def test_distance_weight_adds_a_dense_term_that_prefers_the_goal_centre(make_env):
    plain, dense = make_env(scenario="none"), make_env(scenario="none", distance_weight=2.0)
    plain.reset(seed=3)
    dense.reset(seed=3)
    action = np.full(6, 0.1, dtype=np.float32)
    _, r_plain, *_, info_plain = plain.step(action)
    _, r_dense, *_, info = dense.step(action)
    assert info["distance"] == info_plain["distance"] > 0.0
    assert info["reward_distance"] == pytest.approx(-2.0 * info["distance"], abs=1e-12)
    assert r_dense == pytest.approx(r_plain - 2.0 * info["distance"], abs=1e-12)


def test_success_bonus_when_tool_at_goal(make_env):
    env = make_env(scenario="none", success_bonus=2.5)
    u = env.unwrapped
    env.reset(seed=0)
    u.goal[:] = u.data.site_xpos[u.ee_site_id]  # goal on the tool
    _, reward, _, _, info = env.step(np.zeros(6, np.float32))
    assert info["is_success"] is True
    assert info["reward_success"] == 2.5
    assert info["reward_effort"] == 0.0
    assert abs(info["reward_progress"] + 2.5 - reward) <= 1e-12
    # full torque on every joint: effort term is exactly -effort_weight
    _, _, _, _, info = env.step(np.ones(6, np.float32))
    assert info["reward_effort"] == pytest.approx(-0.05, rel=1e-12)


# ----------------------------------------------------------------------------- 5. cost


def test_obstacle_on_a_link_costs_and_far_does_not(make_env):
    env = make_env(scenario="none")
    u = env.unwrapped
    env.reset(seed=0)
    link3 = geom_id(u.model, "link3")
    put_obstacle(env, 0, u.data.geom_xpos[link3].copy(), 0.05)  # centred on the capsule's axis
    assert u.obstacle_distances()[0] < 0
    _, _, terminated, _, info = env.step(np.zeros(6, np.float32))
    assert info["cost"] == 1.0
    assert info["min_distance"] < 0
    assert terminated is False  # terminate_on_collision defaults to False

    env.reset(seed=0)
    put_obstacle(env, 0, (-1.0, 1.0, 1.2), 0.05)  # far corner of the workspace
    _, _, _, _, info = env.step(np.zeros(6, np.float32))
    assert info["cost"] == 0.0
    assert info["min_distance"] > 0.5


def test_collision_terminates_when_asked(make_env):
    env = make_env(scenario="none", terminate_on_collision=True)
    u = env.unwrapped
    env.reset(seed=0)
    put_obstacle(env, 0, u.data.geom_xpos[geom_id(u.model, "link3")].copy(), 0.05)
    _, _, terminated, _, info = env.step(np.zeros(6, np.float32))
    assert info["cost"] == 1.0 and terminated is True


def test_cost_counts_contact_during_the_step_not_only_at_its_end(make_env):
    """A fast obstacle that passes through link3 between two policy steps still costs."""
    env = make_env(scenario="none")
    u = env.unwrapped
    env.reset(seed=0)
    radius, gap = 0.05, 0.15
    before = beside_link(env, "link3", gap, radius)
    after = beside_link(env, "link3", -gap - 2 * (0.045 + radius), radius)  # mirror side
    velocity = (after - before) / u.dt
    put_obstacle(env, 0, before, radius, velocity)
    _, _, _, _, info = env.step(np.zeros(6, np.float32))
    np.testing.assert_allclose(u.obstacle_pos[0], after, atol=1e-9)
    assert u.obstacle_distances()[0] > 0.1  # clear at the end of the step...
    assert info["cost"] == 1.0  # ...but it went through the link during it
    assert info["min_distance"] < 0


def test_min_distance_matches_independent_sphere_capsule_distance(make_env):
    env = make_env(scenario="none")
    u = env.unwrapped
    env.reset(seed=3)
    radius = 0.06
    centre = beside_link(env, "link3", 0.04, radius)
    put_obstacle(env, 0, centre, radius)
    expected = independent_arm_distances(env, centre, radius)
    nearest = min(expected, key=expected.get)
    assert nearest == "link3" and expected["link3"] == pytest.approx(0.04, abs=1e-12)
    # the base is a cylinder (not computed here); its capsule hull is a lower bound on its distance
    base_lower = sphere_capsule_distance(centre, radius, *capsule_segment(u.model, u.data, geom_id(u.model, "base")))
    assert base_lower > expected[nearest] + 0.05
    assert u.obstacle_distances()[0] == pytest.approx(expected[nearest], abs=1e-6)
    q0 = u.data.qpos.copy()
    _, _, _, _, info = env.step(np.zeros(6, np.float32))
    assert np.max(np.abs(u.data.qpos - q0)) < 1e-9  # gravity-compensated arm at rest stays put
    after = independent_arm_distances(env, centre, radius)
    assert info["cost"] == 0.0
    assert info["min_distance"] == pytest.approx(min(after.values()), abs=1e-6)
    # per-geom readings too (sensor matrix row 0, capsule geoms)
    for gid_index, gid in enumerate(u.arm_geom_ids):
        name = mujoco.mj_id2name(u.model, mujoco.mjtObj.mjOBJ_GEOM, gid)
        if name in after:
            assert u.distances[0, gid_index] == pytest.approx(min(after[name], DISTANCE_CUTOFF), abs=1e-6)


# ----------------------------------------------------------------------------- 6. observation


def test_observation_layout_matches_simulator_state(make_env):
    env = make_env(scenario="multi")
    u = env.unwrapped
    env.reset(seed=5)
    rng = np.random.default_rng(5)
    for _ in range(20):
        obs, *_ = env.step(rng.uniform(-0.5, 0.5, 6).astype(np.float32))
    d = u.data
    tool = d.site_xpos[u.ee_site_id]
    np.testing.assert_array_equal(obs[JOINT_POS], d.qpos.astype(np.float32))
    np.testing.assert_array_equal(obs[JOINT_VEL], d.qvel.astype(np.float32))
    np.testing.assert_array_equal(obs[TOOL_POS], tool.astype(np.float32))
    goal = u.goal
    np.testing.assert_allclose(obs[GOAL_REL], goal - tool, atol=1e-6)
    # tool velocity = site Jacobian times joint velocity (independent of mj_objectVelocity)
    jacp = np.zeros((3, u.model.nv))
    mujoco.mj_jacSite(u.model, d, jacp, None, u.ee_site_id)
    np.testing.assert_allclose(obs[TOOL_VEL], jacp @ d.qvel, rtol=1e-5, atol=1e-6)
    assert np.linalg.norm(obs[TOOL_VEL]) > 1e-3  # the arm is moving: the check is not 0 == 0
    sensed = u.sensed_mask()
    assert sensed.sum() >= 1
    np.testing.assert_array_equal(obs[OBS_SENSED], sensed.astype(np.float32))
    rel = obs[OBS_REL].reshape(K, 3)
    vel = obs[OBS_VEL].reshape(K, 3)
    for slot in range(K):
        if sensed[slot]:
            np.testing.assert_allclose(rel[slot], u.obstacle_pos[slot] - tool, atol=1e-6)
            np.testing.assert_allclose(vel[slot], u.obstacle_vel[slot], atol=1e-7)
            assert obs[OBS_RADIUS][slot] == np.float32(u.obstacle_radius[slot])
        else:
            assert not rel[slot].any() and not vel[slot].any() and obs[OBS_RADIUS][slot] == 0


def test_sensing_radius_masks_far_obstacles(make_env):
    env = make_env(scenario="none", sensing_radius=0.1)
    u = env.unwrapped
    env.reset(seed=0)
    near = beside_link(env, "link3", 0.03, 0.05)  # 3 cm from the arm: sensed
    far = beside_link(env, "link3", 0.5, 0.07)  # 50 cm from link3: not
    put_obstacle(env, 0, near, 0.05, (0.0, 0.0, 0.01))
    put_obstacle(env, 1, far, 0.07, (0.1, 0.0, 0.0))
    assert u.obstacle_distances()[1] > 0.1
    obs, *_ = env.step(np.zeros(6, np.float32))
    rel, vel = obs[OBS_REL].reshape(K, 3), obs[OBS_VEL].reshape(K, 3)
    radius, sensed = obs[OBS_RADIUS], obs[OBS_SENSED]
    # slot 0: sensed, filled in
    assert sensed[0] == 1.0
    np.testing.assert_allclose(rel[0], u.obstacle_pos[0] - u.data.site_xpos[u.ee_site_id], atol=1e-6)
    np.testing.assert_allclose(vel[0], [0.0, 0.0, 0.01], atol=1e-7)
    assert radius[0] == np.float32(0.05)
    # slot 1: active and moving but beyond the sensing radius: all zeros
    assert u.obstacle_active[1]
    assert sensed[1] == 0.0 and not rel[1].any() and not vel[1].any() and radius[1] == 0.0
    # unused slots: all zeros
    assert not sensed[2:].any() and not rel[2:].any() and not vel[2:].any() and not radius[2:].any()
    # with the default sensing radius (1 m) the far one is sensed
    env2 = make_env(scenario="none")
    env2.reset(seed=0)
    put_obstacle(env2, 1, far, 0.07, (0.1, 0.0, 0.0))
    obs2, *_ = env2.step(np.zeros(6, np.float32))
    assert obs2[OBS_SENSED][1] == 1.0 and obs2[OBS_RADIUS][1] == np.float32(0.07)


# ----------------------------------------------------------------------------- 8. bad input

BAD_ACTIONS = {
    "too short": (np.zeros(5, np.float32), r"shape \(6,\)"),
    "too long": (np.zeros(7, np.float32), r"shape \(6,\)"),
    "batched": (np.zeros((1, 6), np.float32), r"shape \(6,\)"),
    "scalar": (0.0, r"shape \(6,\)"),
    "integer out of range": (np.array([0, 0, 2, 0, 0, 0]), r"\[-1, 1\]"),
    "1.5": (np.array([0, 0, 0, 0, 1.5, 0], np.float32), r"\[-1, 1\]"),
    "-1.5": (np.full(6, -1.5), r"\[-1, 1\]"),
    "nan": (np.array([0, np.nan, 0, 0, 0, 0], np.float32), r"(?s)NaN.*\[-1, 1\]|\[-1, 1\].*NaN"),
    "inf": (np.array([0, 0, 0, np.inf, 0, 0]), r"(?s)inf.*\[-1, 1\]|\[-1, 1\].*inf"),
    "-inf": (np.array([-np.inf, 0, 0, 0, 0, 0]), r"(?s)inf.*\[-1, 1\]|\[-1, 1\].*inf"),
    "complex": (np.zeros(6, complex), r"real"),
    "strings": (np.array(["0"] * 6), r"real"),
}


@pytest.mark.parametrize("name", list(BAD_ACTIONS))
def test_bad_action_rejected_and_state_untouched(make_env, name):
    action, message = BAD_ACTIONS[name]
    env, twin = make_env(scenario="multi"), make_env(scenario="multi")
    for e in (env, twin):
        e.reset(seed=2)
    rng = np.random.default_rng(2)
    warmup = rng.uniform(-1, 1, size=(5, 6)).astype(np.float32)
    for a in warmup:
        env.step(a)
        twin.step(a)
    before = state_snapshot(env)
    with pytest.raises(ValueError, match=message):
        env.step(action)
    after = state_snapshot(env)
    for key in before:
        np.testing.assert_array_equal(after[key], before[key], err_msg=key)
    # the rejected call left no trace: the env goes on exactly like a twin that never saw it
    a = np.full(6, 0.3, np.float32)
    out, twin_out = env.step(a), twin.step(a)
    assert out[0].tobytes() == twin_out[0].tobytes() and out[1:] == twin_out[1:]


def test_boundary_actions_accepted(make_env):
    env = make_env(scenario="none")
    env.reset(seed=0)
    for action in (np.ones(6, np.float32), -np.ones(6), [0.0] * 6, np.array([1, -1, 0, 1, 0, -1])):
        env.step(action)


def test_unknown_scenario_lists_valid_choices():
    with pytest.raises(ValueError) as excinfo:
        C3BFReachEnv(scenario="head-on")
    message = str(excinfo.value)
    assert "head-on" in message
    for name in SCENARIOS:
        assert repr(name) in message


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"obstacle_radius_range": (0.0, 0.05)}, r"obstacle_radius_range must be .*both > 0"),
        ({"obstacle_radius_range": (-0.01, 0.05)}, r"obstacle_radius_range must be .*both > 0"),
        ({"obstacle_radius_range": (0.08, 0.04)}, "low <= high"),
        ({"obstacle_radius_range": (0.04, np.nan)}, "finite"),
        ({"obstacle_speed_range": (-0.1, 0.2)}, r"obstacle_speed_range must be .*both >= 0"),
        ({"obstacle_speed_range": (0.4, 0.1)}, "low <= high"),
        ({"obstacle_speed_range": (0.1, np.inf)}, "finite"),
        ({"frame_skip": 0}, "frame_skip"),
        ({"frame_skip": -3}, "frame_skip"),
        ({"frame_skip": 2.5}, "frame_skip"),
        ({"frame_skip": "10"}, "frame_skip"),
        ({"frame_skip": True}, "frame_skip"),
        ({"render_mode": "rgb"}, r"valid choices: None, 'human', 'rgb_array', 'depth_array'"),
        ({"sensing_radius": 0.0}, "sensing_radius"),
        ({"sensing_radius": -1.0}, "sensing_radius"),
        ({"success_tolerance": 0.0}, "success_tolerance"),
        ({"effort_weight": -1.0}, "effort_weight"),
        ({"progress_weight": np.nan}, "progress_weight"),
        ({"distance_weight": -1.0}, "distance_weight"),
        # bools and strings are not numbers, and only bools are booleans
        ({"sensing_radius": True}, r"sensing_radius must be a finite number > 0 \[m\], got True"),
        ({"success_tolerance": "0.05"}, r"success_tolerance must be a finite number > 0 \[m\], got '0.05'"),
        ({"effort_weight": True}, r"effort_weight must be a finite number >= 0, got True"),
        ({"obstacle_radius_range": (True, 0.08)}, r"obstacle_radius_range must be \(low, high\)"),
        ({"gravity_compensation": "false"}, r"gravity_compensation must be True or False, got 'false'"),
        ({"terminate_on_collision": "false"}, r"terminate_on_collision must be True or False, got 'false'"),
        ({"terminate_on_collision": 1}, r"terminate_on_collision must be True or False, got 1"),
        # ranges: exactly two numbers, and the message names the argument, the value and the form
        (
            {"obstacle_speed_range": (0.1, 0.2, 0.3)},
            r"obstacle_speed_range must be \(low, high\): two finite numbers with low <= high, both >= 0 "
            r"\[m/s\], got \(0.1, 0.2, 0.3\)",
        ),
        ({"obstacle_speed_range": 0.3}, r"obstacle_speed_range must be \(low, high\).*got 0.3"),
        ({"obstacle_radius_range": (0.05,)}, r"obstacle_radius_range must be \(low, high\).*both > 0 \[m\], got \(0.05,\)"),
        ({"obstacle_radius_range": "0.04, 0.08"}, r"obstacle_radius_range must be \(low, high\)"),
        ({"scenario": 3}, r"unknown scenario 3; valid choices: 'static', 'head_on', 'crossing', 'multi', 'random', "
                          r"'random_multi', 'none'"),
        ({"width": 0}, r"width must be an integer >= 1"),
        ({"height": 240.0}, r"height must be an integer >= 1"),
    ],
)
def test_bad_constructor_arguments_rejected(kwargs, message):
    with pytest.raises(ValueError, match=message):
        C3BFReachEnv(**kwargs)


def test_numpy_scalars_are_accepted_wherever_a_number_is():
    env = C3BFReachEnv(
        scenario="none",
        frame_skip=np.int64(5),
        gravity_compensation=np.bool_(True),
        sensing_radius=np.float32(0.5),
        terminate_on_collision=np.bool_(False),
        success_tolerance=np.float32(0.05),
        obstacle_speed_range=(np.float32(0.1), np.float64(0.3)),
        obstacle_radius_range=np.array([0.04, 0.06], np.float32),
        progress_weight=np.float32(50.0),
        success_bonus=np.int32(2),
        effort_weight=np.float16(0.05),
        distance_weight=np.float32(0.5),
        width=np.int64(64),
        height=np.int32(48),
    )
    try:
        assert env.frame_skip == 5 and type(env.frame_skip) is int
        assert env.sensing_radius == np.float32(0.5) and type(env.sensing_radius) is float
        assert env.gravity_compensation is True and env.terminate_on_collision is False
        assert env.envelope.speed_range == (float(np.float32(0.1)), 0.3)
        assert env.envelope.radius_range == (float(np.float32(0.04)), float(np.float32(0.06)))
        assert all(type(w) is float for w in env._weights) and env._weights[1] == 2.0
        env.reset(seed=0)
        env.step(np.zeros(6, np.float32))
    finally:
        env.close()


def test_scenario_with_too_many_obstacles_rejected():
    nine = Scenario("nine", tuple(ObstacleSpec("static") for _ in range(9)))
    with pytest.raises(ValueError, match=r"at most 8"):
        C3BFReachEnv(scenario=nine)
    eight = Scenario("eight", tuple(ObstacleSpec("static") for _ in range(8)))
    C3BFReachEnv(scenario=eight).close()  # the maximum itself is fine


def test_bad_values_through_gym_make_too(make_env):
    with pytest.raises(ValueError, match="valid choices"):
        make_env(scenario="nope")


# ----------------------------------------------------------------------------- 9. rendering


@pytest.fixture(scope="module")
def gl():
    reason = gl_unavailable_reason()
    if reason is not None:
        pytest.skip(reason)


def test_render_rgb_array(make_env, gl):
    from gymnasium.utils.passive_env_checker import env_render_passive_checker

    env = make_env(render_mode="rgb_array", width=320, height=240)
    u = env.unwrapped
    env.reset(seed=0)
    image = env.render()
    assert isinstance(image, np.ndarray)
    assert image.shape == (240, 320, 3) and image.dtype == np.uint8
    assert image.std() > 10.0, "blank image"
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 50
    # the arm moves -> the picture changes (shoulder pan by 1 rad)
    u.data.qpos[0] += 1.0
    mujoco.mj_forward(u.model, u.data)
    moved = env.render()
    changed = np.any(moved != image, axis=-1)
    assert changed.mean() > 0.01, "image did not change when the arm moved"
    # and stepping renders too (the arm falls a little under full torque)
    for _ in range(5):
        env.step(np.ones(6, np.float32))
    assert np.any(env.render() != moved)
    env_render_passive_checker(env.unwrapped)


def test_render_depth_array(make_env, gl):
    env = make_env(render_mode="depth_array", width=320, height=240)
    env.reset(seed=0)
    depth = env.render()
    assert isinstance(depth, np.ndarray)
    assert depth.shape == (240, 320)
    assert np.issubdtype(depth.dtype, np.floating)
    assert np.all(np.isfinite(depth))
    assert depth.std() > 0  # not a constant buffer: floor, arm and sky at different depths


# ----------------------------------------------------------------------------- 10. pickling, vectors


def test_pickle_roundtrip_keeps_configuration_and_steps(make_env):
    env = make_env(scenario="multi", sensing_radius=0.5, frame_skip=5, success_tolerance=0.02)
    env.reset(seed=3)
    env.step(np.zeros(6, np.float32))
    clone = pickle.loads(pickle.dumps(env))
    try:
        cu, u = clone.unwrapped, env.unwrapped
        assert cu.scenario == u.scenario and cu.frame_skip == 5 and cu.dt == pytest.approx(0.01)
        assert cu.sensing_radius == 0.5 and cu.success_tolerance == 0.02
        a = np.full(6, 0.2, np.float32)
        o1, _ = env.reset(seed=9)
        o2, _ = clone.reset(seed=9)
        assert o1.tobytes() == o2.tobytes()
        r1, r2 = env.step(a), clone.step(a)
        assert r1[0].tobytes() == r2[0].tobytes() and r1[1:] == r2[1:]
    finally:
        clone.close()
    # a custom Scenario instance survives pickling too
    custom = make_env(scenario=Scenario("two", (ObstacleSpec("crossing"), ObstacleSpec("static"))))
    copy = pickle.loads(pickle.dumps(custom))
    try:
        assert copy.unwrapped.scenario.name == "two"
        copy.reset(seed=0)
        assert copy.unwrapped.obstacle_active.sum() == 2
    finally:
        copy.close()


def test_gymnasium_async_vector_env_steps():
    envs = gym.vector.AsyncVectorEnv([partial(gym.make, ENV_ID, scenario="multi")] * 2)
    try:
        obs, _ = envs.reset(seed=0)
        assert obs.shape == (2, 85) and obs.dtype == np.float32
        # worker i is seeded with seed + i: same first observation as a local env
        local = gym.make(ENV_ID, scenario="multi")
        for i in range(2):
            assert obs[i].tobytes() == local.reset(seed=i)[0].tobytes()
        local.close()
        envs.action_space.seed(0)
        for _ in range(5):
            obs, reward, terminated, truncated, info = envs.step(envs.action_space.sample())
        assert obs.shape == (2, 85) and np.all(np.isfinite(obs))
        assert reward.shape == (2,) and "cost" in info and info["cost"].shape == (2,)
    finally:
        envs.close()


def test_sb3_subproc_vec_env_steps():
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import SubprocVecEnv

    # The "module:id" form makes each worker import c3bf_gym (which registers the id) whatever
    # the multiprocessing start method (SB3 defaults to forkserver, whose workers do not inherit
    # the parent's imports).
    venv = make_vec_env(f"c3bf_gym:{ENV_ID}", n_envs=2, seed=0, vec_env_cls=SubprocVecEnv)
    try:
        obs = venv.reset()
        assert obs.shape == (2, 85)
        for _ in range(3):
            obs, rewards, dones, infos = venv.step(np.stack([venv.action_space.sample() for _ in range(2)]))
        assert obs.shape == (2, 85) and np.all(np.isfinite(obs))
        assert rewards.shape == (2,) and all("cost" in info for info in infos)
    finally:
        venv.close()


# ----------------------------------------------------------------------------- 12. gravity


@pytest.mark.parametrize("compensated", [True, False])
def test_gravity_compensation(make_env, compensated):
    env = make_env(scenario="none", gravity_compensation=compensated)
    u = env.unwrapped
    env.reset(seed=0)
    q0 = u.data.qpos.copy()
    for _ in range(int(round(0.5 / u.dt))):
        env.step(np.zeros(6, np.float32))
    drift = np.abs(u.data.qpos - q0)
    if compensated:
        assert drift.max() < 1e-3
    else:
        assert drift[1] > 0.05, f"shoulder (joint 2) should sag without compensation, moved {drift[1]:.4f} rad"


# ----------------------------------------------------------------------------- 13. step order and errors


def test_bare_env_refuses_to_step_before_reset():
    env = C3BFReachEnv(scenario="none")
    try:
        with pytest.raises(gym.error.ResetNeeded, match=r"reset\(\)"):
            env.step(np.zeros(6, np.float32))
        assert env.data.time == 0.0 and env.state_version == 0  # nothing ran
        env.reset(seed=0)
        env.step(np.zeros(6, np.float32))  # and after reset it steps
    finally:
        env.close()


class RaisingHook:
    """A torque hook that returns its input unchanged, except that call ``fail_at`` (1-based,
    counting physics substeps) raises ``error``; every other call passes."""

    def __init__(self, fail_at: int | None = None, error: BaseException | None = None) -> None:
        self.calls = 0
        self.fail_at = fail_at
        self.error = error

    def __call__(self, tau: np.ndarray) -> np.ndarray:
        self.calls += 1
        if self.calls == self.fail_at:
            raise self.error
        return tau


def full_state(env) -> dict[str, np.ndarray]:
    """Everything a step reads or writes: MuJoCo's state and derived quantities, the obstacles'
    bookkeeping and the generator respawns draw from."""
    u = env.unwrapped
    d, m = u.data, u.model
    geoms = u.obstacle_geom_ids
    return {
        **state_snapshot(env),
        "qacc_warmstart": d.qacc_warmstart.copy(),
        "sensordata": d.sensordata.copy(),
        "site_xpos": d.site_xpos.copy(),
        "geom_xpos": d.geom_xpos.copy(),
        "qfrc_bias": d.qfrc_bias.copy(),
        "obstacle_acc": u.obstacle_acc.copy(),
        "obstacle_radius": u.obstacle_radius.copy(),
        "obstacle_active": u.obstacle_active.copy(),
        "geom_size": m.geom_size[geoms].copy(),
        "geom_rbound": m.geom_rbound[geoms].copy(),
        "specs": np.array([repr(s) for s in u._obstacle_specs]),
        "scalars": np.array([u._goal_distance, u._episode_cost]),
        "rng": np.array(repr(u.np_random.bit_generator.state)),
    }


def assert_same_state(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        assert a[key].tobytes() == b[key].tobytes(), key


def assert_same_rest_of_episode(env, twin, actions) -> int:
    """Step both through ``actions`` (until the episode ends); every output bit-identical."""
    n = 0
    for action in actions:
        out, twin_out = env.step(action), twin.step(action)
        assert out[0].tobytes() == twin_out[0].tobytes(), n
        assert out[1:] == twin_out[1:], n  # reward, flags, and exact equality of every info entry
        n += 1
        if out[2] or out[3]:
            break
    return n


# fast obstacles leave the workspace and respawn (drawing from np_random) within the episode
FAST_MULTI = {"scenario": "multi", "obstacle_speed_range": (0.6, 1.0)}


def test_error_in_a_hook_mid_step_leaves_the_env_as_before_the_call(make_env):
    """A hook raising at the 4th physics substep of step k: the env is as before step k, and the
    rest of the episode (step k retried) matches a twin whose hook never raised."""
    from c3bf_gym import SafetyInfeasibleError

    env, twin = make_env(**FAST_MULTI), make_env(**FAST_MULTI)
    frame_skip, k = env.unwrapped.frame_skip, 30
    error = SafetyInfeasibleError("no torque within the limits satisfies the safety rows (test)")
    env.unwrapped.add_torque_hook(RaisingHook((k - 1) * frame_skip + 4, error), "filter")
    twin.unwrapped.add_torque_hook(RaisingHook(), "filter")
    actions = np.random.default_rng(8).uniform(-1, 1, size=(250, 6)).astype(np.float32)
    env.reset(seed=8)
    twin.reset(seed=8)
    assert assert_same_rest_of_episode(env, twin, actions[: k - 1]) == k - 1
    before, version = full_state(env), env.unwrapped.state_version
    with pytest.raises(SafetyInfeasibleError) as excinfo:
        env.step(actions[k - 1])
    assert excinfo.value is error  # the very exception, unchanged
    after = full_state(env)
    assert_same_state(after, before)
    assert_same_state(after, full_state(twin))
    # a new version number: nothing keyed on a version seen before (or during) the call is current
    assert env.unwrapped.state_version > version + 3
    assert assert_same_rest_of_episode(env, twin, actions[k - 1 :]) == 250 - (k - 1)


def test_error_after_a_respawn_restores_obstacles_and_the_generator(make_env):
    """An error late in a step that respawned an obstacle (new draws, new radius in the model)
    rolls all of that back; the episode then goes on like a twin's."""
    env, twin = make_env(**FAST_MULTI), make_env(**FAST_MULTI)
    u = env.unwrapped
    respawn = u._respawn_departed
    failures = []

    def respawn_then_fail() -> None:
        state = repr(u.np_random.bit_generator.state)
        respawn()
        if not failures and repr(u.np_random.bit_generator.state) != state:  # it drew: a respawn
            failures.append(KeyboardInterrupt())
            raise failures[0]

    u._respawn_departed = respawn_then_fail
    actions = np.random.default_rng(3).uniform(-1, 1, size=(250, 6)).astype(np.float32)
    env.reset(seed=3)
    twin.reset(seed=3)
    for i, action in enumerate(actions):
        before = full_state(env)
        try:
            env.step(action)
        except KeyboardInterrupt as exc:
            assert exc is failures[0]
            break
        twin_out = twin.step(action)
    else:
        pytest.fail("no obstacle respawned in the episode: the test did not exercise a respawn")
    assert_same_state(full_state(env), before)
    assert_same_state(full_state(env), full_state(twin))
    assert assert_same_rest_of_episode(env, twin, actions[i:]) == 250 - i
    del twin_out


def test_error_message_and_type_come_through_unchanged(make_env):
    class Custom(Exception):
        pass

    env = make_env(scenario="static")
    env.unwrapped.add_torque_hook(RaisingHook(2, Custom("exact message, 42 N m")), "nominal")
    env.reset(seed=0)
    with pytest.raises(Custom) as excinfo:
        env.step(np.zeros(6, np.float32))
    assert type(excinfo.value) is Custom and str(excinfo.value) == "exact message, 42 N m"
    assert excinfo.value.__cause__ is None and excinfo.value.__context__ is None
    assert env.unwrapped.data.time == 0.0


# ----------------------------------------------------------------------------- 14. scenarios that cannot be placed


def test_scenario_the_envelope_can_never_place_is_rejected_at_construction():
    """An obstacle whose every spawn point lies within the envelope's spawn clearance of the tool's
    start cannot be placed: the env says so when it is made, not after seconds of sampling."""
    near_tool = Scenario("near_tool", (ObstacleSpec("crossing"), ObstacleSpec("static", path_fraction=(0.0, 0.02))))
    with pytest.raises(ValueError) as excinfo:
        C3BFReachEnv(scenario=near_tool)
    message = str(excinfo.value)
    for part in ("'near_tool'", "obstacle 1", "static", "path_fraction", "spawn_clearance", "must be >="):
        assert part in message, part
    # a moving obstacle at rest (speed range 0) that meets the path at the tool: the same
    at_rest = Scenario("at_rest", (ObstacleSpec("head_on", path_fraction=(0.0, 0.02)),))
    with pytest.raises(ValueError, match=r"(?s)'at_rest'.*obstacle 0.*path_fraction"):
        C3BFReachEnv(scenario=at_rest, obstacle_speed_range=(0.0, 0.0))
    C3BFReachEnv(scenario=at_rest).close()  # with the default speeds it spawns far enough away


def test_reset_fails_fast_when_a_spec_cannot_be_placed_from_this_start():
    env = C3BFReachEnv(scenario="static")
    try:
        env.scenario = Scenario("stuck", (ObstacleSpec("static", path_fraction=(0.0, 0.01)),))  # set after the check
        start = time.perf_counter()
        with pytest.raises(RuntimeError) as excinfo:
            env.reset(seed=0)
        assert time.perf_counter() - start < 0.5
        message = str(excinfo.value)
        assert "could not place scenario 'stuck'" in message and "obstacle 0" in message
        assert "path_fraction=(0.0, 0.01)" in message
        with pytest.raises(gym.error.ResetNeeded):  # a failed reset places nothing to step from
            env.step(np.zeros(6, np.float32))
    finally:
        env.close()


def test_panda_env_is_the_same_task_on_seven_joints():
    """``C3BFReachPanda-v0``: the task on the Panda, with its own observation layout (2 n + 73
    entries), torque limits and joint speed limits; Gymnasium's checker passes."""
    import warnings

    from gymnasium.utils.env_checker import check_env

    from c3bf_gym.envs.reach import ROBOTS, observation_slices

    env = gym.make("C3BFReachPanda-v0", scenario="multi")
    try:
        u = env.unwrapped
        obs, _ = env.reset(seed=0)
        assert obs.shape == (87,) and env.action_space.shape == (7,)
        assert u.observation_slices == observation_slices(7)
        np.testing.assert_array_equal(obs[u.observation_slices["joint_pos"]], u.data.qpos.astype(np.float32))
        np.testing.assert_array_equal(u.robot.torque_limit, [87.0] * 4 + [12.0] * 3)
        np.testing.assert_array_equal(u.robot.joint_speed_limit, ROBOTS["panda"].joint_speed_limit)
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*(infinity|different from the unwrapped).*")
            check_env(u, skip_render_check=True)
    finally:
        env.close()
    with pytest.raises(ValueError, match=r"unknown robot 'kuka'; valid choices: 'ur5e', 'panda'"):
        C3BFReachEnv(robot="kuka")


@pytest.mark.parametrize("scenario, seed", [("head_on", 16), ("multi", 10), ("multi", 29), ("multi", 593)])
def test_panda_resets_where_the_ur5e_keep_out_found_no_path(scenario, seed):
    """With the UR5e's 0.3 m keep-out cylinder these Panda resets found no obstacle path outside
    it (the Panda's tool starts 0.31 m from the base axis); the Panda's own 0.2 m places them."""
    env = C3BFReachEnv(robot="panda", scenario=scenario)
    env.reset(seed=seed)
    assert env.envelope.keep_out_radius == 0.2 and env.obstacle_active.any()
    env.close()


def test_a_source_checkout_on_sys_path_finds_its_assets(checkout_env):
    """Ray workers start in the driver's directory, so a checkout's ``c3bf_gym`` can shadow the
    installed one there: it finds the MJCF in the checkout's top-level assets/ folder. The kernels
    it compiles are cached outside the checkout (conftest.py's ``checkout_env``)."""
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    cached = set(repo.glob("c3bf_gym/**/_numba_cache/*"))
    code = ("import gymnasium as gym, c3bf_gym; env = gym.make('C3BFReachPanda-v0'); env.reset(seed=0); "
            "print(c3bf_gym.__file__, env.unwrapped.model.nu)")  # fmt: skip
    done = subprocess.run([sys.executable, "-c", code], cwd=repo, capture_output=True, text=True, timeout=300,
                          env=checkout_env)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    module, nu = done.stdout.split()
    assert Path(module).resolve().is_relative_to(repo / "c3bf_gym") and nu == "7"
    assert set(repo.glob("c3bf_gym/**/_numba_cache/*")) == cached


def test_compiled_physics_steps_are_the_bindings_steps(make_env):
    """The policy step's compiled physics (mj_step2, the obstacles' motion, mj_step1, through
    MuJoCo's C API) gives, bit for bit, what the same steps through the Python bindings give on a
    copy of the state, moving obstacles and the minimum distance reading included."""
    env = make_env(scenario="multi")
    u = env.unwrapped
    env.reset(seed=4)
    rng = np.random.default_rng(4)
    twin = mujoco.MjData(u.model)
    first = u.model.body_mocapid[u.model.geom_bodyid[u.obstacle_geom_ids[0]]]
    obstacles = slice(first, first + len(u.obstacle_geom_ids))
    for _ in range(40):
        mujoco.mj_copyData(twin, u.model, u.data)
        action = rng.uniform(-1, 1, 6).astype(np.float32)
        velocity = u.obstacle_vel.copy()
        _, _, _, _, info = env.step(action)
        twin.ctrl[:] = action * u.torque_limit
        lowest = DISTANCE_CUTOFF
        for _ in range(u.frame_skip):
            mujoco.mj_step2(u.model, twin)
            twin.mocap_pos[obstacles] += velocity * u.model.opt.timestep
            mujoco.mj_step1(u.model, twin)
            lowest = min(lowest, twin.sensordata[: u.distances.size].min())
        if not np.array_equal(velocity, u.obstacle_vel):
            continue  # an obstacle left the workspace and respawned: its slot moved on
        assert np.array_equal(twin.qpos, u.data.qpos) and np.array_equal(twin.qvel, u.data.qvel)
        assert np.array_equal(twin.mocap_pos, u.data.mocap_pos) and info["min_distance"] == lowest


def test_place_obstacle_puts_a_sphere_where_asked_and_refuses_bad_input(make_env):
    """``place_obstacle``: the sphere is active where asked, the distance sensors see it at once
    (MuJoCo's own signed distance to the nearest link), it moves at the given velocity over the
    next step, and bad input raises naming the valid range with nothing changed."""
    env = make_env(scenario="none")
    u = env.unwrapped
    env.reset(seed=3)
    link = u.arm.capsule_ids[2]
    centre = u.data.geom_xpos[link] + np.array([0.0, 0.0, 0.3])
    version = u.state_version
    u.place_obstacle(5, centre, velocity=(0.1, 0.0, 0.0), radius=0.04)
    assert u.obstacle_active[5] and np.array_equal(u.obstacle_pos[5], centre) and u.obstacle_radius[5] == 0.04
    assert u.state_version > version and 0.0 < u.obstacle_distances()[5] < 0.3
    env.step(np.zeros(6, np.float32))
    np.testing.assert_allclose(u.obstacle_pos[5], centre + [0.1 * u.dt, 0.0, 0.0], rtol=0, atol=1e-12)
    before = u.obstacle_pos.copy(), u.obstacle_active.copy()
    for bad, match in (({"slot": 8}, r"slot must be an integer in \[0, 7\]"), ({"slot": -1}, "slot must be"),
                       ({"position": (0.0, 1.0)}, "position must be three finite"),
                       ({"velocity": (np.nan, 0.0, 0.0)}, "velocity must be three finite"),
                       ({"radius": 0.0}, "radius must be"),
                       ({"respawn": "static"}, "respawn must be an ObstacleSpec")):  # fmt: skip
        arguments = {"slot": 0, "position": centre, "velocity": (0.0, 0.0, 0.0), "radius": 0.05} | bad
        with pytest.raises(ValueError, match=match):
            u.place_obstacle(**arguments)
    assert np.array_equal(u.obstacle_pos, before[0]) and np.array_equal(u.obstacle_active, before[1])


def test_torque_hooks_are_refused_by_name_and_read_back_by_stage(make_env):
    u = make_env(scenario="none").unwrapped
    hook = lambda tau: tau  # noqa: E731
    for call in (lambda: u.add_torque_hook(hook, "nominl"), lambda: u.torque_hook("filtre")):
        with pytest.raises(ValueError, match="unknown hook stage .*valid choices: 'nominal', 'filter'"):
            call()
    with pytest.raises(TypeError, match="hook must be callable"):
        u.add_torque_hook(None, "filter")
    u.add_torque_hook(hook, "filter")
    with pytest.raises(ValueError, match="a 'filter' torque hook is already installed"):
        u.add_torque_hook(hook, "filter")
    assert u.torque_hook("filter") is hook and u.torque_hook("nominal") is None
    u.remove_torque_hook("filter")
    assert u.torque_hook("filter") is None and not u.has_torque_hook("filter")
