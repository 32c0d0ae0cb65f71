"""Tests for c3bf_gym/wrappers.py: composition, info for loggers, the gym.make shortcut, bad
input, and hook lifetime."""

from __future__ import annotations

import re
import warnings

import gymnasium as gym
import numpy as np
import pytest

import c3bf_gym
from c3bf_gym import DEFAULT_FILTER, FILTERS, ActionPenalty, CartesianImpedanceAction, FilterConfig, SafetyFilter
from c3bf_gym.safety.barriers import C3BF, DistanceHOCBF
from c3bf_gym.controllers import CartesianImpedance, modulate
from c3bf_gym.controllers.modulation import REACH
from c3bf_gym.wrappers import (AppliedAction, ArmClearance, ArmContactTime, ArmForecast, CorrectionPenalty, ElapsedTime,
                               FilterFeedback)
from c3bf_gym.safety import GUARD_GAMMA

from conftest import ENV_ID

#: info["safety"] entries every user may rely on, and their Python types.
SAFETY_TYPES = {
    "feasible": bool,
    "slack": float,
    "min_h": float,
    "correction": float,
    "active_rows": int,
    "sensed": int,
    "intervened": bool,
    "inside": bool,
    "infeasible_steps": int,
    "gain_raised_steps": int,
    **{f"violation_{kind}": float
       for kind in ("barrier", "guard", "floor", "joint_limits", "unmovable", "self_collision")},
}


# ----------------------------------------------------------------------------- helpers


def toward_nearest_obstacle(env) -> np.ndarray:
    """A tool-target action aiming at the nearest active obstacle (makes the filter work)."""
    u = env.unwrapped
    tool = u.data.site_xpos[u.ee_site_id]
    active = np.flatnonzero(u.obstacle_active)
    if not len(active):
        return np.zeros(3, np.float32)
    nearest = active[np.argmin(np.linalg.norm(u.obstacle_pos[active] - tool, axis=1))]
    return np.clip((u.obstacle_pos[nearest] - tool) / 0.1, -1.0, 1.0).astype(np.float32)


def snapshot(env) -> dict:
    u = env.unwrapped
    d = u.data
    return {
        "qpos": d.qpos.copy(),
        "qvel": d.qvel.copy(),
        "time": np.array(d.time),
        "mocap_pos": d.mocap_pos.copy(),
        "ctrl": d.ctrl.copy(),
        "obstacle_vel": u.obstacle_vel.copy(),
        "version": np.array(u.state_version),
    }


def rollout(env, seed, steps, policy):
    obs, _ = env.reset(seed=seed)
    trace = [obs]
    infos = []
    rng = np.random.default_rng(seed)
    for _ in range(steps):
        action = policy(env, rng)
        obs, reward, terminated, truncated, info = env.step(action)
        trace.append(obs)
        infos.append((reward, info))
    return np.array(trace), infos


def mixed_policy(env, rng):
    return toward_nearest_obstacle(env) if rng.random() < 0.7 else rng.uniform(-1, 1, 3).astype(np.float32)


# ----------------------------------------------------------------------------- composition


#: Trajectories through the filter agree to this, not bit for bit: replaying one sequence of QPs
#: on two fresh solver instances gave torques differing by ~1e-9 depending on earlier memory
#: allocations (alignment-dependent floating point), and the QP is only solved to 1e-8.
SAME = dict(rtol=0.0, atol=1e-6)


def assert_same_safety(ia, ib):
    sa, sb = ia["safety"], ib["safety"]
    for key in ("feasible", "intervened", "inside", "sensed"):
        assert sa[key] == sb[key], key
    for key in ("slack", "min_h", "correction"):
        assert sa[key] == pytest.approx(sb[key], rel=1e-5, abs=1e-6), key
    for key in ("cost", "safety_intervened", "safety_infeasible", "episode_interventions", "episode_infeasible"):
        assert ia[key] == ib[key], key
    assert ia["min_distance"] == pytest.approx(ib["min_distance"], abs=1e-6)


def test_both_wrapping_orders_give_identical_trajectories(make_env):
    filter_outside = SafetyFilter(CartesianImpedanceAction(make_env(scenario="multi")))
    filter_inside = CartesianImpedanceAction(SafetyFilter(make_env(scenario="multi")))
    assert filter_outside.action_space == filter_inside.action_space == gym.spaces.Box(-1, 1, (3,), np.float32)
    a, info_a = rollout(filter_outside, 4, 60, mixed_policy)
    b, info_b = rollout(filter_inside, 4, 60, mixed_policy)
    np.testing.assert_allclose(a, b, **SAME)
    interventions = 0
    for (reward_a, ia), (reward_b, ib) in zip(info_a, info_b):
        assert reward_a == pytest.approx(reward_b, abs=1e-6)
        assert_same_safety(ia, ib)
        interventions += ia["safety"]["intervened"]
    assert interventions > 0  # the filter did act: the comparison covers both stages


def test_filter_changes_the_trajectory_of_the_same_actions(make_env):
    """Sanity check for the comparison above: the filter is not a no-op on this rollout."""
    filtered = SafetyFilter(CartesianImpedanceAction(make_env(scenario="multi")))
    plain = CartesianImpedanceAction(make_env(scenario="multi"))
    a, _ = rollout(filtered, 4, 60, mixed_policy)
    b, _ = rollout(plain, 4, 60, mixed_policy)
    assert not np.array_equal(a, b)


def test_same_seed_same_filtered_trajectory(make_env):
    """An episode repeats (to the solver's precision, see SAME) whatever ran before it on the
    same env. Full torque from the first step makes the joint-speed rows bind at once, so the QP
    solver (not its fast path) decides the torques from the start."""
    env = SafetyFilter(make_env(scenario="crossing"))
    policy = lambda e, rng: np.sign(rng.uniform(-1, 1, 6)).astype(np.float32)  # noqa: E731
    a, info_a = rollout(env, 11, 40, policy)
    rollout(env, 12, 40, policy)  # another episode in between leaves another solver state
    b, info_b = rollout(env, 11, 40, policy)
    np.testing.assert_allclose(a, b, **SAME)
    for (_, ia), (_, ib) in zip(info_a, info_b):
        assert_same_safety(ia, ib)
    assert info_a[0][1]["safety"]["intervened"]


@pytest.mark.parametrize("how", ["deepcopy", "pickle"])
def test_a_copied_filtered_env_is_filtered_like_the_original(make_env, how):
    """Gymnasium's MuJoCo envs pickle as their constructor arguments, so a copy is a new env: the
    wrappers must put their hooks on it, or the copy would step unfiltered without a word."""
    import copy
    import pickle

    original = SafetyFilter(CartesianImpedanceAction(make_env(scenario="multi")))
    rollout(original, 3, 5, mixed_policy)  # a used env, hooks bound
    clone = copy.deepcopy(original) if how == "deepcopy" else pickle.loads(pickle.dumps(original))
    base = clone.unwrapped
    assert base is not original.unwrapped
    assert base.torque_hook("filter") is clone.hook and base.torque_hook("nominal") is clone.env.hook
    assert clone.hook.env is base and clone.env.hook.env is base
    a, info_a = rollout(original, 4, 60, mixed_policy)
    b, info_b = rollout(clone, 4, 60, mixed_policy)
    np.testing.assert_allclose(a, b, **SAME)
    for (reward_a, ia), (reward_b, ib) in zip(info_a, info_b):
        assert reward_a == pytest.approx(reward_b, abs=SAME["atol"])  # two solver instances: see SAME
        assert_same_safety(ia, ib)
    assert sum(ia["safety"]["intervened"] for _, ia in info_a) > 0


# ----------------------------------------------------------------------------- info


def test_info_safety_keys_and_types(make_env):
    env = SafetyFilter(make_env(scenario="multi"))
    env.reset(seed=1)
    rng = np.random.default_rng(1)
    interventions = infeasible = 0
    for step in range(30):
        _, _, _, _, info = env.step(rng.uniform(-1, 1, 6).astype(np.float32))
        safety = info["safety"]
        for key, kind in SAFETY_TYPES.items():
            assert type(safety[key]) is kind, (key, type(safety[key]))
        for key, value in safety.items():  # anything else added later: plain scalars only
            assert type(value) in (bool, int, float), (key, type(value))
        assert safety["slack"] >= 0.0 and safety["correction"] >= 0.0
        # timings stay off info; inside the env's compiled policy step the filter takes none
        assert "solve_time" not in safety and np.isnan(env.hook.report.solve_time)
        assert safety["feasible"] == (safety["infeasible_steps"] == 0)
        held = safety["infeasible_steps"] == safety["gain_raised_steps"] == 0
        assert held == (safety["slack"] == 0.0)  # a barrier row held with a raised gain used slack
        if held:  # every row held as written at the applied torque (A τ − b in the rows' units)
            assert safety["min_constraint"] >= -1e-2  # (tolerance 1e-6 normalised; row norms < 1e4)
        # flat keys for SB3's Monitor(info_keywords=...)
        assert type(info["safety_intervened"]) is float and info["safety_intervened"] in (0.0, 1.0)
        assert type(info["safety_infeasible"]) is float and info["safety_infeasible"] in (0.0, 1.0)
        assert info["safety_intervened"] == float(safety["intervened"])
        assert info["safety_infeasible"] == float(not safety["feasible"])
        interventions += safety["intervened"]
        infeasible += not safety["feasible"]
        assert type(info["episode_interventions"]) is int and info["episode_interventions"] == interventions
        assert type(info["episode_infeasible"]) is int and info["episode_infeasible"] == infeasible
    assert interventions > 0
    env.reset(seed=2)
    _, _, _, _, info = env.step(np.zeros(6, np.float32))
    assert info["episode_interventions"] == int(info["safety"]["intervened"])  # counters restart
    assert info["episode_infeasible"] == int(not info["safety"]["feasible"])


def test_sb3_monitor_logs_the_flat_keys(make_env):
    monitor_module = pytest.importorskip("stable_baselines3.common.monitor")
    keys = ("safety_intervened", "safety_infeasible", "episode_interventions", "episode_infeasible")
    env = monitor_module.Monitor(SafetyFilter(make_env(scenario="multi", max_episode_steps=15)), info_keywords=keys)
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    total = 0
    for _ in range(15):
        _, _, terminated, truncated, info = env.step(rng.uniform(-1, 1, 6).astype(np.float32))
        total += info["safety_intervened"]
    assert truncated
    episode = info["episode"]
    assert episode["l"] == 15
    assert episode["episode_interventions"] == total
    for key in keys:
        assert isinstance(episode[key], (int, float))


# ----------------------------------------------------------------------------- gym.make shortcut


def test_gym_make_safety_filter_shortcut():
    env = gym.make(ENV_ID, safety_filter="c3bf", scenario="static")
    try:
        u = env.unwrapped
        assert u.has_torque_hook("filter")
        env.reset(seed=0)
        _, _, _, _, info = env.step(np.zeros(6, np.float32))
        assert set(SAFETY_TYPES) <= set(info["safety"])
        assert "safety_intervened" in info and "episode_interventions" in info
    finally:
        env.close()
    assert not u.has_torque_hook("filter")


def test_gym_make_shortcut_barrier_choice_and_default():
    env = gym.make(ENV_ID, safety_filter="hocbf")
    try:
        wrapper = env
        while not isinstance(wrapper, SafetyFilter):
            wrapper = wrapper.env
        assert isinstance(wrapper.hook.barrier, DistanceHOCBF)
    finally:
        env.close()
    env = gym.make(ENV_ID)
    try:
        assert not env.unwrapped.has_torque_hook("filter")  # no filter unless asked for
    finally:
        env.close()
    with pytest.raises(ValueError, match=r"(?s)safety_filter.*'c3bf'.*'hocbf'"):
        gym.make(ENV_ID, safety_filter="cbf")


# ----------------------------------------------------------------------------- bad input

BAD_FILTER_ARGS = [
    (dict(barrier="cbf"), r"(?s)barrier.*'c3bf'.*'hocbf'"),
    (dict(barrier=None), r"(?s)barrier.*'c3bf'.*'hocbf'"),
    (dict(points="links"), r"(?s)points.*'whole_arm'.*'ee'"),
    (dict(weight="diag"), r"(?s)weight.*'limits'.*'identity'.*'tool'"),
    (dict(tool_acceleration=3.0), r"tool_acceleration=3.0 was given with weight='limits'.*weight='tool'"),
    (dict(weight="tool", tool_acceleration=0.05), r"tool_acceleration must be a finite number >= 0.1"),
    (dict(weight="tool", tool_acceleration=float("nan")), r"tool_acceleration must be a finite number >= 0.1"),
    (dict(on_infeasible="ignore"), r"(?s)on_infeasible.*'relax'.*'raise'"),
    (dict(gamma=-1.0), "gamma"),
    (dict(gamma=0.0), "gamma"),
    (dict(gamma=float("nan")), "gamma"),
    (dict(barrier="hocbf", gamma=-2.0), "gamma"),
    (dict(margin=-0.01), "margin"),
    (dict(margin=float("inf")), "margin"),
    (dict(sensing_radius=0.0), "sensing_radius"),
    (dict(sensing_radius=-1.0), "sensing_radius"),
    (dict(sensing_radius=float("nan")), "sensing_radius"),
    (dict(ee_radius=-0.05), "ee_radius"),
    (dict(joint_speed_fraction=0.0), "joint_speed_fraction"),
    (dict(joint_speed_fraction=-0.5), "joint_speed_fraction"),
    (dict(joint_speed_fraction=1.5), "joint_speed_fraction"),
    (dict(joint_speed_fraction=float("nan")), "joint_speed_fraction"),
    (dict(joint_range_reserve=-0.1), r"joint_range_reserve must be a finite number >= 0"),
    (dict(joint_range_reserve=float("inf")), r"joint_range_reserve must be a finite number >= 0"),
    (dict(joint_limits=False, joint_range_reserve=0.3), r"joint_range_reserve=0.3 needs joint_limits=True"),
    (dict(nominal_speed_fraction=0.0), r"nominal_speed_fraction must be a finite number > 0 and <= 1"),
    (dict(nominal_speed_fraction=float("nan")), r"nominal_speed_fraction must be a finite number"),
    (dict(joint_limits=False, nominal_speed_fraction=0.4), r"nominal_speed_fraction=0.4 needs joint_limits=True"),
    (dict(nominal_speed_fraction=0.6), r"nominal_speed_fraction=0.6 is above joint_speed_fraction=0.5"),
    (dict(guard=None, allowance_level=True), r"allowance_level=True needs a guard beside the barrier"),
    (dict(barrier="hocbf", allowance_level=True), r"allowance_level=True needs a guard beside the barrier"),
    (dict(allowance_level=1), r"allowance_level must be True or False"),
    (dict(self_collision="yes"), r"self_collision must be True or False"),
    (dict(guard="distance"), r"(?s)guard.*'auto'.*None.*'c3bf'.*'hocbf'.*Barrier"),
    (dict(guard=True), r"(?s)guard.*'auto'.*None"),
    (dict(guard_gamma=0.0), r"guard_gamma must be a finite number > 0"),
    (dict(guard_gamma=float("nan")), r"guard_gamma must be a finite number > 0"),
    (dict(guard=None, guard_gamma=5.0), r"guard_gamma was given, but guard=None puts no named guard"),
    (dict(guard=DistanceHOCBF(), guard_gamma=5.0), r"guard_gamma was given, but guard=DistanceHOCBF"),
    (dict(barrier="hocbf", guard_gamma=5.0), r"guard='auto' puts no named guard beside barrier 'hocbf'"),
    (dict(barrier=C3BF(), gamma=2.0), r"gamma was given beside a Barrier instance"),
    (dict(margin=True), r"margin must be a finite number >= 0"),
    (dict(margin="0.02"), r"margin must be a finite number >= 0"),
    (dict(joint_limits="false"), r"joint_limits must be True or False"),
    (dict(solver="daqp"), r"(?s)unknown filter setting\(s\) 'solver'"),
    (dict(bogus=1.0), r"(?s)unknown filter setting\(s\) 'bogus'; valid settings: barrier, gamma"),
]


@pytest.mark.parametrize("kwargs, message", BAD_FILTER_ARGS, ids=[str(k) for k, _ in BAD_FILTER_ARGS])
def test_bad_filter_arguments_rejected_and_nothing_installed(make_env, kwargs, message):
    env = make_env(scenario="none")
    with pytest.raises(ValueError, match=message):
        SafetyFilter(env, **kwargs)
    assert not env.unwrapped.has_torque_hook("filter")
    SafetyFilter(env)  # the env is still usable


def test_edge_values_accepted(make_env):
    env = make_env(scenario="none")
    for kwargs in (dict(joint_speed_fraction=1.0), dict(margin=0.0), dict(points="ee", ee_radius=0.0),
                   dict(barrier=C3BF(gamma=2.0)), dict(weight="identity", on_infeasible="raise"),
                   dict(guard=None), dict(guard=DistanceHOCBF(gamma1=2.0, gamma2=3.0))):  # fmt: skip
        SafetyFilter(env, **kwargs).close()


@pytest.mark.parametrize(
    "barrier, guard, expected",
    [("c3bf", "auto", DistanceHOCBF), (C3BF(gamma=2.0), "auto", DistanceHOCBF), ("hocbf", "auto", type(None)),
     ("c3bf", None, type(None)), ("c3bf", "none", type(None)), ("hocbf", "c3bf", C3BF)],
)
def test_guard_choices(make_env, barrier, guard, expected):
    """``guard="auto"`` puts the distance HOCBF (gains GUARD_GAMMA) beside a C3BF and nothing
    beside the distance HOCBF, whose rows would only repeat; a named guard is that barrier."""
    env = SafetyFilter(make_env(scenario="none"), barrier=barrier, guard=guard)
    assert type(env.hook.guard) is expected
    if expected is DistanceHOCBF:
        assert (env.hook.guard.gamma1, env.hook.guard.gamma2) == (GUARD_GAMMA, GUARD_GAMMA)
        assert env.hook._params.guard == (True, GUARD_GAMMA, GUARD_GAMMA)  # the fused kernel's


def test_guard_gamma_sets_a_named_guards_gains(make_env):
    env = SafetyFilter(make_env(scenario="none"), guard_gamma=7.0)
    assert (env.hook.guard.gamma1, env.hook.guard.gamma2) == (7.0, 7.0)
    assert env.hook._params.guard == (True, 7.0, 7.0)
    env = SafetyFilter(make_env(scenario="none"), barrier="hocbf", guard="c3bf", guard_gamma=3.0)
    assert env.hook.guard.gamma == 3.0 and env.hook.barrier.gamma1 == 5.0  # the barrier keeps its own


@pytest.mark.parametrize("wrapper", [SafetyFilter, CartesianImpedanceAction])
def test_non_c3bf_env_rejected(wrapper):
    env = gym.make("Pendulum-v1")
    try:
        with pytest.raises(TypeError, match="C3BFReach"):
            wrapper(env)
    finally:
        env.close()


def test_double_filter_rejected(make_env):
    env = SafetyFilter(make_env(scenario="none"))
    with pytest.raises(ValueError, match="already"):
        SafetyFilter(env)
    with pytest.raises(ValueError, match="already"):
        SafetyFilter(CartesianImpedanceAction(env))


def test_double_impedance_rejected(make_env):
    env = CartesianImpedanceAction(make_env(scenario="none"))
    with pytest.raises(ValueError, match="already"):
        CartesianImpedanceAction(SafetyFilter(env))
    with pytest.raises(ValueError, match="already"):
        CartesianImpedanceAction(env)


@pytest.mark.parametrize("max_offset", [0.0, -0.1, float("nan"), float("inf")])
def test_bad_max_offset_rejected(make_env, max_offset):
    env = make_env(scenario="none")
    with pytest.raises(ValueError, match="max_offset"):
        CartesianImpedanceAction(env, max_offset=max_offset)
    assert not env.unwrapped.has_torque_hook("nominal")


def test_residual_action_heads_for_the_goal(make_env):
    """residual=True: a = 0 targets a straight step for the goal (clipped per axis to max_offset)
    and a adds max_offset * a on top; residual=False keeps the offset from the tool."""
    env = CartesianImpedanceAction(make_env(scenario="none"), max_offset=0.1, residual=True)
    env.reset(seed=3)
    base = env.unwrapped
    tool = base.data.site_xpos[base.ee_site_id].copy()
    straight = np.clip(base.goal - tool, -0.1, 0.1)
    assert np.abs(straight).max() == pytest.approx(0.1)  # goals start >= 0.3 m away
    env.action(np.zeros(3, np.float32))
    np.testing.assert_allclose(env.hook.target_pos, tool + straight)
    env.action(np.array([1.0, -1.0, 0.5], np.float32))
    np.testing.assert_allclose(env.hook.target_pos, tool + straight + [0.1, -0.1, 0.05], atol=1e-7)
    plain = CartesianImpedanceAction(make_env(scenario="none"), max_offset=0.1)
    plain.reset(seed=3)
    plain.action(np.zeros(3, np.float32))
    np.testing.assert_allclose(plain.hook.target_pos, tool)


def test_residual_zero_action_reaches_the_goal(make_env):
    """With no obstacle, the zero residual brings the tool within the success tolerance."""
    env = CartesianImpedanceAction(make_env(scenario="none"), residual=True)
    env.reset(seed=5)
    for _ in range(150):
        _, _, _, _, info = env.step(np.zeros(3, np.float32))
    assert info["is_success"], info["distance"]


def test_residual_fade_shrinks_the_correction_near_the_goal(make_env):
    """fade: within fade of the goal the correction is scaled by d / fade (the target is
    goal + (d / fade) max_offset a there); beyond it the action is as without fade."""
    env = CartesianImpedanceAction(make_env(scenario="none"), max_offset=0.1, residual=True, fade=0.1)
    env.reset(seed=3)
    base = env.unwrapped
    tool = base.data.site_xpos[base.ee_site_id]
    a = np.array([1.0, -1.0, 0.5], np.float32)
    env.action(a)  # goals start >= 0.3 m away: no fade
    np.testing.assert_allclose(env.hook.target_pos, tool + np.clip(base.goal - tool, -0.1, 0.1) + 0.1 * a, atol=1e-7)
    base.goal[:] = tool + [0.02, 0.0, -0.03]  # d = 0.036 m
    d = float(np.linalg.norm(base.goal - tool))
    env.action(a)
    np.testing.assert_allclose(env.hook.target_pos, base.goal + (d / 0.1) * 0.1 * a, atol=1e-7)


def test_residual_fade_lets_no_small_bias_hold_the_tool_off_the_goal(make_env):
    """A constant action of norm < 1 rests the tool that far off the goal without fade, and on
    it with fade = max_offset (what TrainConfig.residual_fade is for)."""
    bias = np.array([0.3, -0.3, 0.2], np.float32)  # 0.047 m of target offset, inside the 0.05 m tolerance's rim
    final = {}
    for fade in (None, 0.1):
        env = CartesianImpedanceAction(make_env(scenario="none", frame_skip=50), residual=True, fade=fade)
        env.reset(seed=5)
        for _ in range(50):  # 5 s at 10 Hz, an episode of the training recipe
            _, _, _, _, info = env.step(bias)
        final[fade] = info["distance"]
    assert final[None] == pytest.approx(0.1 * np.linalg.norm(bias), abs=0.004)
    assert final[0.1] < 0.002


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"fade": 0.1}, "fade shrinks the residual correction near the goal: it needs residual=True"),
    ({"residual": True, "fade": 0.0}, "fade must be None or a finite number > 0"),
    ({"residual": True, "fade": float("nan")}, "fade must be None or a finite number > 0"),
    ({"residual": True, "fade": True}, "fade must be None or a finite number > 0"),
])  # fmt: skip
def test_bad_fade_rejected(make_env, kwargs, message):
    env = make_env(scenario="none")
    with pytest.raises(ValueError, match=re.escape(message)):
        CartesianImpedanceAction(env, **kwargs)
    assert not env.unwrapped.has_torque_hook("nominal")


def test_modulate_turns_a_step_round_a_sphere():
    """The modulation of Khansari-Zadeh and Billard for a sphere: at its surface a step straight
    in loses its normal part, a step along it doubles, a step leaving it keeps its normal part;
    in between it is E diag(λ_n, λ_t, λ_t) Eᵀ; beyond REACH radii, and for a step that moves with
    the sphere, nothing changes."""
    c, radius = np.zeros(3), 0.1
    surface = np.array([0.0, 0.0, 0.1])  # Γ = 1, n = +z
    np.testing.assert_allclose(modulate(surface, [0.3, 0.0, -1.0], [c], [np.zeros(3)], [radius]), [0.6, 0.0, 0.0])
    np.testing.assert_allclose(modulate(surface, [0.3, 0.0, 1.0], [c], [np.zeros(3)], [radius]), [0.6, 0.0, 1.0])
    x = np.array([0.12, -0.05, 0.15])
    step = np.array([-0.4, 0.2, -0.3])  # heading in: n · step < 0
    r = np.linalg.norm(x)
    n, gamma = x / r, r / radius
    e1 = np.cross(n, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    E = np.stack([n, e1, np.cross(n, e1)], axis=1)
    expected = E @ np.diag([1 - 1 / gamma, 1 + 1 / gamma, 1 + 1 / gamma]) @ E.T @ step
    np.testing.assert_allclose(modulate(x, step, [c], [np.zeros(3)], [radius]), expected, atol=1e-12)
    far = np.array([0.0, 0.0, REACH * radius + 1e-6])
    np.testing.assert_array_equal(modulate(far, step, [c], [np.zeros(3)], [radius]), step)
    w = np.array([0.0, 0.0, 0.5])
    np.testing.assert_allclose(modulate(surface, w, [c], [w], [radius]), w)
    np.testing.assert_array_equal(modulate(x, step, np.zeros((0, 3)), np.zeros((0, 3)), []), step)


@pytest.mark.parametrize(("args", "message"), [
    ((np.zeros(2), np.ones(3), [np.ones(3)], [np.zeros(3)], [0.1]), "position and step must have shape (3,)"),
    ((np.zeros(3), np.ones(3), [np.ones(3)], np.zeros((2, 3)), [0.1]), "must describe the same spheres"),
    ((np.zeros(3), np.ones(3), np.ones(6), np.zeros((2, 3)), [0.1, 0.1]), "must describe the same spheres"),
    ((np.zeros(3), np.ones(3), [np.ones(3)], [np.zeros(3)], [0.0]), "radii must be > 0 (m)"),
    ((np.zeros(3), [np.nan, 0, 0], [np.ones(3)], [np.zeros(3)], [0.1]), "step must be finite"),
])  # fmt: skip
def test_modulate_rejects_bad_spheres(args, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        modulate(*args)


def test_modulated_straight_step_bends_round_a_sensed_sphere(make_env):
    """modulate=True: with no sphere near the tool the target is the plain residual's; with one
    at rest on the way to the goal the straight step turns aside, goes less far into it and stays
    inside the max_offset box; the correction is added after, unchanged."""
    plain = CartesianImpedanceAction(make_env(scenario="none"), residual=True, fade=0.1)
    env = CartesianImpedanceAction(make_env(scenario="none"), residual=True, fade=0.1, modulate=True)
    for wrapper in (plain, env):
        wrapper.reset(seed=3)
    a = np.array([0.4, -1.0, 0.2], np.float32)
    env.action(a)
    plain.action(a)
    np.testing.assert_array_equal(env.hook.target_pos, plain.hook.target_pos)
    base = env.unwrapped
    tool = base.data.site_xpos[base.ee_site_id].copy()
    way = (base.goal - tool) / np.linalg.norm(base.goal - tool)
    sphere = tool + 0.15 * way + 0.02 * np.cross(way, [0.0, 0.0, 1.0])  # on the way, a little to one side
    base.place_obstacle(0, sphere, radius=0.06)
    assert base.sensed_mask()[0]
    zero = np.zeros(3, np.float32)
    env.action(zero)
    step = env.hook.target_pos - tool
    straight = np.clip(base.goal - tool, -0.1, 0.1)
    n = (tool - sphere) / np.linalg.norm(tool - sphere)
    assert np.abs(step).max() <= 0.1 + 1e-12
    assert -(n @ step) < -(n @ straight)  # less far into the sphere
    assert np.linalg.norm(step - (step @ n) * n) > np.linalg.norm(straight - (straight @ n) * n)  # more along it
    env.action(a)
    np.testing.assert_allclose(env.hook.target_pos - tool, step + 0.1 * a, atol=1e-7)


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"modulate": True}, "modulate bends the residual action's straight step for the goal: it needs residual=True"),
    ({"residual": True, "modulate": 1}, "modulate must be True or False"),
])  # fmt: skip
def test_bad_modulate_rejected(make_env, kwargs, message):
    env = make_env(scenario="none")
    with pytest.raises(ValueError, match=re.escape(message)):
        CartesianImpedanceAction(env, **kwargs)
    assert not env.unwrapped.has_torque_hook("nominal")


def test_posture_reach_moves_the_posture_target_and_not_the_tool_target(make_env):
    """posture_reach: the action's last n entries set the posture task's target home + reach * a,
    the first three the tool target exactly as without the option; zero entries are the
    controller alone, and the controller's own posture is left as it was."""
    plain = CartesianImpedanceAction(make_env(scenario="none"), residual=True, fade=0.1)
    env = CartesianImpedanceAction(make_env(scenario="none"), residual=True, fade=0.1, posture_reach=0.5)
    home = env.hook.controller.posture.copy()
    assert env.action_space.shape == (3 + home.size,) and plain.action_space.shape == (3,)
    for wrapper in (plain, env):
        wrapper.reset(seed=3)
    a = np.array([0.4, -1.0, 0.2], np.float32)
    q = np.linspace(-1.0, 1.0, home.size).astype(np.float32)
    env.action(np.concatenate([a, q]))
    plain.action(a)
    np.testing.assert_array_equal(env.hook.target_pos, plain.hook.target_pos)
    np.testing.assert_allclose(env.hook.gains.posture, home + 0.5 * q, atol=1e-7)
    np.testing.assert_array_equal(env.hook.controller.posture, home)
    env.action(np.concatenate([a, np.zeros_like(q)]))
    np.testing.assert_array_equal(env.hook.gains.posture, home)


def test_posture_reach_moves_the_arm_and_holds_the_tool(make_env):
    """With the tool target held, a posture offset turns the redundant joints (the tool task's null
    space) and leaves the tool where the zero offset leaves it, to a few mm."""
    finals = []
    for entries in (0.0, 1.0):
        env = CartesianImpedanceAction(make_env(scenario="none", frame_skip=50), residual=True, fade=0.1,
                                       posture_reach=0.5)  # fmt: skip
        env.reset(seed=5)
        action = np.zeros(env.action_space.shape, np.float32)
        action[3:] = entries
        for _ in range(50):
            _, _, _, _, info = env.step(action)
        finals.append((env.unwrapped.data.qpos.copy(), info["distance"]))
    (q_zero, d_zero), (q_moved, d_moved) = finals
    assert np.abs(q_moved - q_zero).max() > 0.1
    assert d_zero < 0.01 and d_moved < 0.01


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"posture_reach": 0.0}, "posture_reach must be None or a finite number > 0"),
    ({"posture_reach": float("inf")}, "posture_reach must be None or a finite number > 0"),
    ({"posture_reach": True}, "posture_reach must be None or a finite number > 0"),
    ({"posture_reach": 0.5, "controller": CartesianImpedance()}, "this controller has none: build it with posture="),
])  # fmt: skip
def test_bad_posture_reach_rejected(make_env, kwargs, message):
    env = make_env(scenario="none")
    with pytest.raises(ValueError, match=re.escape(message)):
        CartesianImpedanceAction(env, residual=True, **kwargs)
    assert not env.unwrapped.has_torque_hook("nominal")


def test_posture_entries_checked_like_the_rest(make_env):
    env = CartesianImpedanceAction(make_env(scenario="none"), residual=True, posture_reach=0.5)
    env.reset(seed=1)
    n = env.action_space.shape[0]
    for bad, message in ((np.zeros(3, np.float32), f"action must have shape ({n},)"),
                         (np.r_[np.zeros(3), 1.5 * np.ones(n - 3)].astype(np.float32), "then of posture_reach"),
                         (np.r_[np.zeros(n - 1), np.nan].astype(np.float32), "NaN or inf")):  # fmt: skip
        posture = env.hook.gains.posture.copy()
        with pytest.raises(ValueError, match=re.escape(message)):
            env.step(bad)
        np.testing.assert_array_equal(env.hook.gains.posture, posture)


@pytest.mark.parametrize("residual", [1, "yes", None])
def test_bad_residual_rejected(make_env, residual):
    with pytest.raises(ValueError, match="residual must be True or False"):
        CartesianImpedanceAction(make_env(scenario="none"), residual=residual)


NAN_CASES = {
    "filter": (lambda e: SafetyFilter(e), np.array([0, np.nan, 0, 0, 0, 0], np.float32)),
    "impedance": (lambda e: CartesianImpedanceAction(e), np.array([np.nan, 0, 0], np.float32)),
    "filter(impedance)": (lambda e: SafetyFilter(CartesianImpedanceAction(e)), np.array([0, 0, np.nan], np.float32)),
    "impedance(filter)": (lambda e: CartesianImpedanceAction(SafetyFilter(e)), np.array([0, np.inf, 0], np.float32)),
    "impedance out of range": (lambda e: CartesianImpedanceAction(e), np.array([0, 1.5, 0], np.float32)),
    "impedance wrong shape": (lambda e: CartesianImpedanceAction(e), np.zeros(6, np.float32)),
}


@pytest.mark.parametrize("case", list(NAN_CASES))
def test_bad_action_raises_and_leaves_the_env_untouched(make_env, case):
    build, bad = NAN_CASES[case]
    env = build(make_env(scenario="crossing"))
    env.reset(seed=0)
    good = np.zeros(env.action_space.shape, np.float32)
    for _ in range(3):
        env.step(good)
    before = snapshot(env)
    wrappers = []
    w = env
    while isinstance(w, gym.Wrapper):
        wrappers.append(w)
        w = w.env
    filters = [w for w in wrappers if isinstance(w, SafetyFilter)]
    impedances = [w for w in wrappers if isinstance(w, CartesianImpedanceAction)]
    counters = [(f._episode_interventions, f._episode_infeasible) for f in filters]
    targets = [i.hook.target_pos.copy() for i in impedances]
    with pytest.raises(ValueError):
        env.step(bad)
    after = snapshot(env)
    for key in before:
        np.testing.assert_array_equal(after[key], before[key], err_msg=key)
    assert counters == [(f._episode_interventions, f._episode_infeasible) for f in filters]
    for i, target in zip(impedances, targets):
        np.testing.assert_array_equal(i.hook.target_pos, target)
    obs, *_ = env.step(good)  # and it keeps working
    assert np.isfinite(obs).all()


# ----------------------------------------------------------------------------- lifetime


@pytest.mark.parametrize("order", ["filter outside", "filter inside", "filter only", "impedance only"])
def test_close_removes_the_hooks(make_env, order):
    base = make_env(scenario="none")
    build = {
        "filter outside": lambda e: SafetyFilter(CartesianImpedanceAction(e)),
        "filter inside": lambda e: CartesianImpedanceAction(SafetyFilter(e)),
        "filter only": SafetyFilter,
        "impedance only": CartesianImpedanceAction,
    }[order]
    env = build(base)
    u = base.unwrapped
    assert u.has_torque_hook("filter") or u.has_torque_hook("nominal")
    env.close()
    assert not u.has_torque_hook("filter") and not u.has_torque_hook("nominal")
    assert u.torque_hook("filter") is None and u.torque_hook("nominal") is None
    env.close()  # closing twice is harmless


def test_hooks_removed_by_close_no_longer_act(make_env):
    """After close, the same env (reset) steps like an unfiltered one."""
    raw = make_env(scenario="crossing")
    filtered = SafetyFilter(make_env(scenario="crossing"))
    filtered.close()
    rng_actions = np.random.default_rng(0).uniform(-1, 1, (20, 6)).astype(np.float32)
    a, _ = raw.reset(seed=3)
    b, _ = filtered.unwrapped.reset(seed=3)
    for action in rng_actions:
        a, *_ = raw.step(action)
        b, *_ = filtered.unwrapped.step(action)
    np.testing.assert_array_equal(a, b)


def test_action_penalty_adds_its_term_and_nothing_else(make_env):
    plain = CartesianImpedanceAction(make_env(scenario="static"), residual=True)
    penalised = ActionPenalty(CartesianImpedanceAction(make_env(scenario="static"), residual=True), weight=2.0)
    for env in (plain, penalised):
        env.reset(seed=3)
    action = np.array([0.5, -1.0, 0.0], np.float32)
    obs_a, reward_a, *_, info_a = plain.step(action)
    obs_b, reward_b, *_, info_b = penalised.step(action)
    assert info_b["reward_action"] == pytest.approx(-2.0 * (0.25 + 1.0) / 3)
    assert reward_b == pytest.approx(reward_a + info_b["reward_action"])
    np.testing.assert_array_equal(obs_a, obs_b)  # the task is the same: only the reward changes
    _, _, *_, info_zero = penalised.step(np.zeros(3, np.float32))
    assert info_zero["reward_action"] == 0.0  # the prior costs nothing


@pytest.mark.parametrize("weight", [-1.0, float("nan"), float("inf"), True, "1"])
def test_action_penalty_bad_weight_rejected(make_env, weight):
    with pytest.raises(ValueError, match="weight must be a finite number >= 0"):
        ActionPenalty(make_env(), weight)


def test_action_penalty_passes_bad_actions_to_the_env_check(make_env):
    env = ActionPenalty(CartesianImpedanceAction(make_env(), residual=True), weight=1.0)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="NaN or inf"):
        env.step(np.array([np.nan, 0.0, 0.0], np.float32))


def test_applied_action_reads_a_task_force_back_as_its_target_shift(make_env):
    """A correction ``Jᵀ K Δx`` (a pure task force at the tool) is read back as the target shift
    ``Δx``: the applied action is ``clip(a + Δx / reach, −1, 1)``; where the filter left the
    torque alone it is the action itself."""
    impedance = CartesianImpedanceAction(make_env(scenario="none"), residual=True)
    env = AppliedAction(SafetyFilter(impedance))
    base = env.unwrapped
    limit = base.robot.torque_limit
    env.reset(seed=1)
    action = np.array([0.2, -0.1, 0.0], np.float32)
    for _ in range(3):
        *_, info = env.step(action)
    report = base.torque_hook("filter").report
    np.testing.assert_array_equal(report.tau, np.clip(report.tau_nominal, -limit, limit))  # free space: no correction
    np.testing.assert_array_equal(info["applied_action"], action)
    assert info["applied_action"].dtype == np.float32
    base.arm.update(base.data)
    jac = base.arm.site_dynamics(base.data).jac[0]
    stiffness = impedance.hook.controller.K
    for shift, expected in ((np.array([0.004, -0.006, 0.002]), [0.24, -0.16, 0.02]),   # reach 0.1 m
                            (np.array([0.5, 0.0, -0.5]), [1.0, -0.1, -1.0])):  # fmt: skip
        report.tau = np.clip(report.tau_nominal, -limit, limit) + jac.T @ (stiffness @ shift)
        np.testing.assert_allclose(env.applied(action, report), expected, rtol=0, atol=1e-5)


def test_applied_action_follows_the_filter_and_leaves_the_rollout_alone(make_env):
    """In a multi episode the filter pulls the arm, and the applied action says where: it differs
    from the zero action, stays in the action space, keeps the posture entries as chosen, and the
    rollout (observations, rewards) is the same as without the wrapper."""
    plain = SafetyFilter(CartesianImpedanceAction(make_env(scenario="multi"), residual=True, posture_reach=0.3))
    told = AppliedAction(SafetyFilter(CartesianImpedanceAction(make_env(scenario="multi"), residual=True,
                                                               posture_reach=0.3)))  # fmt: skip
    plain.reset(seed=1)
    told.reset(seed=1)
    action = np.zeros(9, np.float32)
    action[3:] = 0.5
    moved = 0
    for _ in range(20):
        obs_a, reward_a, *_ = plain.step(action)
        obs_b, reward_b, *_, info = told.step(action)
        np.testing.assert_array_equal(obs_a, obs_b)
        assert reward_a == reward_b
        applied = info["applied_action"]
        assert told.action_space.contains(applied)
        np.testing.assert_array_equal(applied[3:], action[3:])
        moved += np.abs(applied[:3]).max() > 0.1
    assert moved > 10, "the filter corrects the zero action from the start of this multi episode"


def test_applied_action_needs_a_filter_and_a_cartesian_action(make_env):
    with pytest.raises(ValueError, match="AppliedAction maps back the safety filter's correction: wrap a SafetyFilter"):
        AppliedAction(CartesianImpedanceAction(make_env(), residual=True))
    with pytest.raises(ValueError, match="wrap a CartesianImpedanceAction under it; this environment's actions are torques"):
        AppliedAction(SafetyFilter(make_env()))


def test_action_penalty_charges_the_applied_action_when_asked(make_env):
    env = ActionPenalty(AppliedAction(SafetyFilter(CartesianImpedanceAction(make_env(scenario="multi"), residual=True))),
                        weight=2.0, charge="applied")  # fmt: skip
    env.reset(seed=1)
    *_, info = env.step(np.zeros(3, np.float32))
    assert info["reward_action"] == pytest.approx(-2.0 * float(np.mean(np.square(info["applied_action"]))))
    assert info["reward_action"] < 0.0  # the filter moved the zero action: the move is charged
    with pytest.raises(ValueError, match=re.escape("ActionPenalty(charge='applied') charges info['applied_action']")):
        ActionPenalty(SafetyFilter(CartesianImpedanceAction(make_env(), residual=True)), 1.0, charge="applied")
    with pytest.raises(ValueError, match="unknown charge 'filtered'; valid choices: 'policy', 'applied'"):
        ActionPenalty(make_env(), 1.0, charge="filtered")


def test_correction_penalty_charges_the_filters_correction_and_nothing_else(make_env):
    """-weight * correction / ‖τ_max‖ on the reward, the filter's report unchanged; the rollout
    (observations) is the same as without the wrapper."""
    plain = SafetyFilter(CartesianImpedanceAction(make_env(scenario="static"), residual=True))
    charged = CorrectionPenalty(SafetyFilter(CartesianImpedanceAction(make_env(scenario="static"), residual=True)), 4.0)
    scale = float(np.linalg.norm(charged.unwrapped.robot.torque_limit))
    for env in (plain, charged):
        env.reset(seed=3)
    seen = []
    for _ in range(30):  # the zero action runs the tool into the sphere at rest on its path
        obs_a, reward_a, *_, info_a = plain.step(np.zeros(3, np.float32))
        obs_b, reward_b, *_, info_b = charged.step(np.zeros(3, np.float32))
        np.testing.assert_array_equal(obs_a, obs_b)
        assert info_b["reward_correction"] == pytest.approx(-4.0 * info_b["safety"]["correction"] / scale)
        assert reward_b == pytest.approx(reward_a + info_b["reward_correction"])
        seen.append(info_b["reward_correction"])
    assert min(seen) < -1e-3 and max(seen) <= 0.0  # the filter did act, and was charged


def test_correction_penalty_needs_a_filter_and_a_weight(make_env):
    env = CartesianImpedanceAction(make_env(), residual=True)
    with pytest.raises(ValueError, match="CorrectionPenalty charges the safety filter's correction"):
        CorrectionPenalty(env, 1.0)
    for weight in (-1.0, float("nan"), True):
        with pytest.raises(ValueError, match="weight must be a finite number >= 0"):
            CorrectionPenalty(SafetyFilter(make_env()), weight)


def test_arm_clearance_appends_each_geoms_clearance_to_the_nearest_obstacle(make_env):
    """One entry per arm geom: clip(d, −cap, cap) / cap for its smallest distance to an active
    obstacle (MuJoCo's sensors), 1 with none; the rollout and the env's own observation are
    unchanged."""
    plain = CartesianImpedanceAction(make_env(scenario="multi"), residual=True)
    seen = ArmClearance(CartesianImpedanceAction(make_env(scenario="multi"), residual=True), cap=0.5)
    base = seen.unwrapped
    n = len(base.arm_geom_ids)
    assert seen.observation_space.shape == (plain.observation_space.shape[0] + n,)
    obs_a, _ = plain.reset(seed=4)
    obs_b, _ = seen.reset(seed=4)
    for step in range(25):
        np.testing.assert_array_equal(obs_a, obs_b[:-n])
        expected = np.clip(base.distances[base.obstacle_active].min(axis=0), -0.5, 0.5) / 0.5
        np.testing.assert_allclose(obs_b[-n:], expected, atol=1e-6)
        obs_a, *_ = plain.step(np.zeros(3, np.float32))
        obs_b, *_ = seen.step(np.zeros(3, np.float32))
    assert obs_b[-n:].min() < 0.5  # the arm came within a quarter metre of a sphere
    free = ArmClearance(make_env(scenario="none"))
    obs, _ = free.reset(seed=1)
    np.testing.assert_array_equal(obs[-len(free.unwrapped.arm_geom_ids):], 1.0)


def test_elapsed_time_appends_the_share_of_the_time_limit_used_and_survives_a_refused_step(make_env):
    """The last entry is t / T (T the time limit's ``max_episode_steps``), 0 after reset and 1 at the
    limit; the environment's own observation and the rollout are unchanged; a step that raises
    leaves the count as it was; an environment with no time limit is refused."""
    plain = SafetyFilter(make_env(scenario="crossing", max_episode_steps=20))
    timed = ElapsedTime(SafetyFilter(make_env(scenario="crossing", max_episode_steps=20)))
    assert timed.observation_space.shape == (plain.observation_space.shape[0] + 1,)
    assert timed.observation_space.dtype == np.float32
    obs_a, _ = plain.reset(seed=3)
    obs_b, _ = timed.reset(seed=3)
    action = np.full(6, 0.2, np.float32)
    for step in range(1, 21):
        np.testing.assert_array_equal(obs_a, obs_b[:-1])
        assert obs_b[-1] == pytest.approx((step - 1) / 20)
        if step == 5:
            with pytest.raises(ValueError, match="NaN"):
                timed.step(np.full(6, np.nan, np.float32))
        obs_a, _, _, truncated_a, _ = plain.step(action)
        obs_b, _, _, truncated_b, _ = timed.step(action)
        assert truncated_a == truncated_b == (step == 20)
    assert obs_b[-1] == 1.0
    obs, _ = timed.reset(seed=4)
    assert obs[-1] == 0.0
    with pytest.raises(ValueError, match="TimeLimit"):
        ElapsedTime(make_env().unwrapped)
    with pytest.raises(ValueError, match="flatten and normalize_time must be True"):
        ElapsedTime(make_env(), normalize_time=False)


def test_arm_contact_time_appends_how_soon_each_geom_would_be_touched(make_env):
    """One entry per arm geom: min over the active obstacles of d / r (r the gap's closing speed
    over the last step, d / r counted only where r > 0), over the horizon, capped at 1; 1 after
    reset, 0 in contact; the rollout and the env's own observation are unchanged."""
    plain = CartesianImpedanceAction(make_env(scenario="multi"), residual=True)
    seen = ArmContactTime(CartesianImpedanceAction(make_env(scenario="multi"), residual=True), horizon=2.0)
    base = seen.unwrapped
    n = len(base.arm_geom_ids)
    assert seen.observation_space.shape == (plain.observation_space.shape[0] + n,)
    obs_a, _ = plain.reset(seed=4)
    obs_b, _ = seen.reset(seed=4)
    np.testing.assert_array_equal(obs_b[-n:], 1.0)  # nothing has closed yet
    lowest = 1.0
    for _ in range(25):
        before = base.distances.copy()
        obs_a, *_ = plain.step(np.zeros(3, np.float32))
        obs_b, *_ = seen.step(np.zeros(3, np.float32))
        np.testing.assert_array_equal(obs_a, obs_b[:-n])
        active = base.obstacle_active
        gap = base.distances[active]
        closing = (before[active] - gap) / base.dt
        time = np.where(closing > 0, gap / np.where(closing > 0, closing, 1.0), np.inf)
        time[gap <= 0] = 0.0  # in contact (no filter here: the tool does reach a sphere)
        expected = np.minimum(time.min(axis=0) / 2.0, 1.0)
        np.testing.assert_allclose(obs_b[-n:], expected, rtol=1e-5, atol=1e-6)
        lowest = min(lowest, obs_b[-n:].min())
    assert lowest == 0.0  # the unfiltered arm met a sphere
    with pytest.raises(ValueError, match=re.escape("horizon must be a finite number > 0 [s]")):
        ArmContactTime(make_env(), horizon=0.0)


def test_arm_forecast_appends_the_moved_obstacles_clearance_to_the_arm_and_the_goal(make_env):
    """Per horizon: the arm entry, then the goal entry. At a vanishing horizon the arm entry is the
    present clearance MuJoCo's distance sensors give (ArmClearance's least entry); at 1 s it is
    the clearance of each obstacle moved 1 s along its motion to the arm's capsules (the sampler's
    own routine), and the goal entry is the moved obstacle's surface distance to the goal. The
    rollout and the env's own observation are unchanged."""
    plain = CartesianImpedanceAction(make_env(scenario="multi"), residual=True)
    seen = ArmForecast(ArmClearance(CartesianImpedanceAction(make_env(scenario="multi"), residual=True)),
                       horizons=(1e-9, 1.0), cap=0.5)  # fmt: skip
    base = seen.unwrapped
    n = len(base.arm_geom_ids)
    assert seen.observation_space.shape == (plain.observation_space.shape[0] + n + 4,)
    plain.reset(seed=4)
    seen.reset(seed=4)
    lowest = 1.0
    for _ in range(25):
        obs_a, *_ = plain.step(np.zeros(3, np.float32))
        obs_b, *_ = seen.step(np.zeros(3, np.float32))
        np.testing.assert_array_equal(obs_a, obs_b[: -n - 4])
        now, ahead = obs_b[-4:-2], obs_b[-2:]
        np.testing.assert_allclose(now[0], obs_b[-n - 4 : -4].min(), atol=1e-5)  # MuJoCo's distances, now
        active = base.obstacle_active
        moved = base.obstacle_pos[active] + base.obstacle_vel[active] + 0.5 * base.obstacle_acc[active]
        radius = base.obstacle_radius[active]
        arm = base.arm_capsules()
        to_arm = min(arm.clearance(p, r) for p, r in zip(moved, radius))
        to_goal = (np.linalg.norm(moved - base.goal, axis=1) - radius).min()
        np.testing.assert_allclose(ahead, np.clip([to_arm, to_goal], -0.5, 0.5) / 0.5, atol=1e-5)
        lowest = min(lowest, ahead[0])
    assert lowest < 0.0  # a sphere's path crossed the arm where it stood


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"horizons": ()}, "ArmForecast needs at least one horizon [s], got none"),
    ({"horizons": (1.0, 0.0)}, "horizon must be a finite number > 0 [s]"),
    ({"cap": float("inf")}, "cap must be a finite number > 0 [m]"),
])  # fmt: skip
def test_arm_forecast_bad_horizons_or_cap_rejected(make_env, kwargs, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        ArmForecast(make_env(), **kwargs)


@pytest.mark.parametrize("cap", [0.0, -1.0, float("inf"), True])
def test_arm_clearance_bad_cap_rejected(make_env, cap):
    with pytest.raises(ValueError, match=re.escape("cap must be a finite number > 0 [m]")):
        ArmClearance(make_env(), cap=cap)


def test_filter_feedback_observes_the_filters_last_correction(make_env):
    """The appended entries are (τ − clip(τ_nom)) / τ_max of the last physics step, 0 after reset;
    the environment's own observation and the rollout are unchanged."""
    plain = SafetyFilter(CartesianImpedanceAction(make_env(scenario="multi"), residual=True))
    observed = FilterFeedback(SafetyFilter(CartesianImpedanceAction(make_env(scenario="multi"), residual=True)))
    base = observed.unwrapped
    n, limit = base.robot.n, base.robot.torque_limit
    assert observed.observation_space.shape == (plain.observation_space.shape[0] + n,)
    obs_a, _ = plain.reset(seed=1)
    obs_b, _ = observed.reset(seed=1)
    np.testing.assert_array_equal(obs_b[:-n], obs_a)
    assert (obs_b[-n:] == 0).all()
    corrected = 0
    for _ in range(30):
        obs_a, *_ = plain.step(np.zeros(3, np.float32))
        obs_b, *_, info = observed.step(np.zeros(3, np.float32))
        np.testing.assert_array_equal(obs_b[:-n], obs_a)  # the same rollout
        report = base.torque_hook("filter").report
        expected = (report.tau - np.clip(report.tau_nominal, -limit, limit)) / limit
        np.testing.assert_allclose(obs_b[-n:], expected, rtol=1e-6, atol=1e-7)
        assert observed.observation_space.contains(obs_b)
        corrected += info["safety"]["correction"] > 1.0
    assert corrected > 0, "the filter corrected the torque in this multi episode"
    obs_b, _ = observed.reset(seed=2)
    assert (obs_b[-n:] == 0).all()  # nothing carried over from the last episode


def test_filter_feedback_needs_a_filter(make_env):
    with pytest.raises(ValueError, match="wrap a SafetyFilter"):
        FilterFeedback(CartesianImpedanceAction(make_env(), residual=True))
    with pytest.raises(TypeError, match="C3BFReach environment"):
        FilterFeedback(gym.make("Pendulum-v1"))


_ROLLOUT_HASH = """
import hashlib, gymnasium as gym, numpy as np, c3bf_gym
env = c3bf_gym.SafetyFilter(gym.make("C3BFReach-v0", scenario="multi"), barrier="c3bf")
env.reset(seed=5)
rng, digest = np.random.default_rng(5), hashlib.sha256()
for _ in range(60):
    obs, reward, *_ = env.step(np.sign(rng.uniform(-1, 1, 6)).astype(np.float32))
    digest.update(obs.tobytes() + np.float64(reward).tobytes())
print(digest.hexdigest())
"""


def test_filtered_rollout_repeats_bit_for_bit_across_processes(tmp_path):
    """The compiled path (rows, DAQP) depends on nothing but its inputs, so a seeded
    filtered rollout is the same in a new process, to the last bit (training runs can be
    replayed). Full torques make the QP decide from the first step."""
    import os
    import subprocess
    import sys

    import c3bf_gym

    # the package this process tested (installed or not), not whatever the working directory holds
    env = {**os.environ, "PYTHONPATH": os.path.dirname(os.path.dirname(c3bf_gym.__file__))}
    runs = [subprocess.run([sys.executable, "-c", _ROLLOUT_HASH], capture_output=True, text=True, cwd=tmp_path, env=env)
            for _ in range(2)]  # fmt: skip
    assert all(r.returncode == 0 for r in runs), runs[0].stderr[-2000:]
    first, second = (r.stdout.split() for r in runs)
    assert first == second


# ----------------------------------------------------------------------------- Gymnasium conventions


@pytest.mark.parametrize("stack", ["filter", "impedance", "both"])
def test_spec_round_trip_rebuilds_the_wrappers(make_env, stack):
    """``gym.make(env.spec)`` rebuilds the same wrappers with the same settings: the same seed and
    actions then give the same observations."""
    env = make_env(scenario="multi")
    if stack in ("impedance", "both"):
        env = CartesianImpedanceAction(env, max_offset=0.05)
    if stack in ("filter", "both"):
        env = SafetyFilter(env, "c3bf", margin=0.03)
    copy = gym.make(env.spec)
    try:
        assert [w.name for w in copy.spec.additional_wrappers] == [w.name for w in env.spec.additional_wrappers]
        if stack != "impedance":
            assert copy.config == env.config and copy.config.name == "c3bf" and copy.config.margin == 0.03
        actions = np.random.default_rng(0).uniform(-1, 1, (5,) + env.action_space.shape).astype(np.float32)
        for e in (env, copy):
            e.reset(seed=4)
        for a in actions:
            np.testing.assert_array_equal(env.step(a)[0], copy.step(a)[0])
    finally:
        copy.close()


@pytest.mark.parametrize("stack", ["filter", "impedance"])
def test_check_env_passes_on_the_wrappers(stack):
    from gymnasium.utils.env_checker import check_env

    env = c3bf_gym.C3BFReachEnv(scenario="multi")
    env = SafetyFilter(env) if stack == "filter" else CartesianImpedanceAction(env)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*(different from the unwrapped|infinity).*")
            check_env(env, skip_render_check=True)
    finally:
        env.close()


def test_closed_filter_refuses_to_step(make_env):
    """After close() the hook is gone: stepping would apply unfiltered torques, so it raises."""
    env = SafetyFilter(make_env(scenario="multi"))
    env.reset(seed=0)
    env.close()
    with pytest.raises(RuntimeError, match="closed"):
        env.step(env.action_space.sample())
    with pytest.raises(RuntimeError, match="closed"):
        env.reset(seed=1)
    env.close()  # closing twice is harmless


def test_config_object_name_and_settings(make_env):
    config = FilterConfig(margin=0.03, guard_gamma=20.0)
    env = SafetyFilter(make_env(scenario="none"), config, on_infeasible="raise")
    assert env.config == config.replace(on_infeasible="raise") and env.config.name == "c3bf+hocbf20"
    assert env.hook.margin == 0.03 and env.hook.guard.gamma == 20.0
    assert SafetyFilter(make_env(scenario="none"), "hocbf").config == FilterConfig(barrier="hocbf", guard=None)
    assert SafetyFilter(make_env(scenario="none")).config.name == DEFAULT_FILTER == "c3bf+hocbf"
    for name in FILTERS:  # one name, one filter: gym.make and SafetyFilter agree
        made = gym.make(ENV_ID, scenario="none", safety_filter=name)
        try:
            assert made.unwrapped.has_torque_hook("filter")
            assert _filter_of(made).config == FilterConfig.named(name)
        finally:
            made.close()
    with pytest.raises(TypeError, match="config must be a FilterConfig"):
        SafetyFilter(make_env(scenario="none"), 3)


def _filter_of(env) -> SafetyFilter:
    while not isinstance(env, SafetyFilter):
        env = env.env
    return env


def test_numpy_scalars_are_numbers(make_env):
    env = SafetyFilter(make_env(scenario="none"), margin=np.float32(0.03), gamma=np.int64(4))
    assert env.config.margin == pytest.approx(0.03) and type(env.config.margin) is float
    assert env.hook.barrier.gamma == 4.0


def test_raise_on_infeasible_leaves_the_env_as_before_the_step(make_env):
    """``on_infeasible="raise"``: the step with no safe torque raises SafetyInfeasibleError with
    the environment restored to its state before that step (no substep integrated, no cost
    counted); what to do next is the caller's choice."""
    env = SafetyFilter(make_env(scenario="multi"), on_infeasible="raise", margin=0.1)
    env.reset(seed=2)
    u = env.unwrapped
    rng = np.random.default_rng(2)
    for _ in range(250):
        before = (u.data.time, u.data.qpos.copy(), u.data.qvel.copy(), u.obstacle_pos.copy(), u._episode_cost)
        try:
            env.step(rng.choice([-1.0, 1.0], size=6).astype(np.float32))
        except c3bf_gym.SafetyInfeasibleError:
            break
    else:
        pytest.fail("chattering torques in multi with a 10 cm margin found no infeasible step (seed 2 did at step 121)")
    after = (u.data.time, u.data.qpos, u.data.qvel, u.obstacle_pos, u._episode_cost)
    assert after[0] == before[0] and after[4] == before[4]
    for a, b in zip(after[1:4], before[1:4]):
        np.testing.assert_array_equal(a, b)
