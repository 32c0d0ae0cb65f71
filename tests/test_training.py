"""Training smoke runs (slow): SAC and PPO, with and without the filter; save, reload, evaluate."""

from __future__ import annotations

import argparse
import csv
import importlib.util
import inspect
import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from c3bf_gym.cli import filter_setting, main
from c3bf_gym.safety import GUARD_GAMMA, FilterConfig
from c3bf_gym.plots import plot_training
from c3bf_gym.training import (
    ACTION_REACH,
    ACTION_WEIGHTS,
    NORMALIZATION_FILE,
    RESIDUAL_FADE,
    TrainConfig,
    _load_normalizer,
    build_env,
    by_scenario,
    evaluate,
    filter_label,
    make_env,
    policy_rate_kwargs,
    sb3_model,
    train,
)


@pytest.mark.slow
def test_a_run_on_a_weighted_mixture_is_evaluated_on_its_eval_scenario(tmp_path):
    """``eval_scenario``: the periodic and final evaluations, and ``evaluate`` by default, run the
    evaluation scenario, not the training mixture."""
    config = TrainConfig(scenario="random_multi", eval_scenario="static", timesteps=200, eval_freq=150, eval_episodes=1,
                         final_eval_episodes=2, checkpoint_freq=150, out=str(tmp_path), progress_bar=False,
                         hyperparams={"learning_starts": 100})  # fmt: skip
    run = train(config)
    assert run.name.endswith("_random_multi_s0")
    assert json.loads((run / "config.json").read_text())["eval_scenario"] == "static"
    final = json.loads((run / "final_eval.json").read_text())
    assert final["scenario"] == "static" and list(final["by_scenario"]) == ["static"]
    assert evaluate(run / "model.zip", episodes=1)["scenario"] == "static"
    assert evaluate(run / "model.zip", episodes=2, scenario="multi")["by_scenario"].keys() == {"multi"}


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["sac", "ppo"])
@pytest.mark.parametrize("filter_name", ["none", "c3bf+hocbf"])
def test_train_save_reload_evaluate(algo, filter_name, tmp_path):
    config = TrainConfig(
        algo=algo, filter=filter_name, scenario="head_on", timesteps=300, eval_freq=250, eval_episodes=1,
        final_eval_episodes=2, checkpoint_freq=250, out=str(tmp_path), progress_bar=False,
        hyperparams={"learning_starts": 100} if algo == "sac" else {"n_steps": 128, "batch_size": 64},
    )  # fmt: skip
    run = train(config)
    assert (run / "model.zip").exists() and (run / "checkpoints").is_dir() and (run / "evaluations.npz").exists()
    saved = json.loads((run / "config.json").read_text())
    assert saved["algo"] == algo and saved["filter"] == filter_name and saved["resolved_hyperparams"]
    with open(run / "episodes.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert rows, "at least one training episode finished"
    cumulative = [float(r["cumulative_cost"]) for r in rows]
    assert cumulative == sorted(cumulative)
    summary = json.loads((run / "summary.json").read_text())
    assert summary["training_cost"] >= cumulative[-1]
    if filter_name != "none":
        assert summary["training_cost"] == 0.0
        # the filter acted in training (the head-on obstacle comes at the arm), at most once per step
        assert sum(float(r["interventions"]) for r in rows) > 0
        assert all(max(float(r["interventions"]), float(r["infeasible"])) <= float(r["length"]) for r in rows)
    final = json.loads((run / "final_eval.json").read_text())
    assert final["episodes"] == 2 and final["filter"] == filter_name and summary["final_eval"] == final
    result = evaluate(run / "model.zip", episodes=1)
    assert result["filter"] == filter_name and result["episodes"] == 1
    assert list(final["by_scenario"]) == ["head_on"] and final["by_scenario"]["head_on"]["episodes"] == 2
    best = evaluate(run / "best" / "best_model.zip", episodes=1)  # the run's config from one level up
    assert best["filter"] == filter_name and best["scenario"] == "head_on"
    assert 0.0 <= result["collision_free_success_rate"] <= result["success_rate"] <= 1.0
    if filter_name != "none":
        assert result["collision_episodes"] == 0
        assert result["collision_free_success_rate"] == result["success_rate"]


@pytest.mark.slow
def test_evaluate_command_with_another_filter(tmp_path, capsys):
    run = train(TrainConfig(timesteps=260, filter="none", scenario="head_on", eval_freq=10_000, final_eval_episodes=0, out=str(tmp_path),
                            progress_bar=False, hyperparams={"learning_starts": 100}))  # fmt: skip
    out_json = tmp_path / "eval.json"
    assert main(["evaluate", str(run / "model.zip"), "--episodes", "2", "--filter", "c3bf+hocbf", "--json", str(out_json)]) == 0
    result = json.loads(out_json.read_text())
    assert result["filter"] == "c3bf+hocbf" and result["collision_episodes"] == 0 and result["episodes"] == 2
    assert result["guard_gamma"] == GUARD_GAMMA  # another filter than the run's: its default gains
    assert evaluate(run / "model.zip", episodes=1, filter="c3bf")["guard_gamma"] is None  # the C3BF alone
    result = evaluate(run / "model.zip", episodes=1, filter="c3bf+hocbf", guard_gamma=8.0)
    assert (result["filter"], result["guard_gamma"]) == ("c3bf+hocbf8", 8.0)
    with pytest.raises(ValueError, match="guard_gamma was given"):
        evaluate(run / "model.zip", episodes=1, filter="hocbf", guard_gamma=8.0)
    # a run trained with other gains is evaluated with its own
    config = json.loads((run / "config.json").read_text())
    config.update(filter="c3bf+hocbf", guard_gamma=20.0)
    (run / "config.json").write_text(json.dumps(config))
    assert evaluate(run / "model.zip", episodes=1)["filter"] == "c3bf+hocbf20"
    # ... and with its own filter settings, unless it is given others
    config.update(filter_settings={"allowance_level": True})
    (run / "config.json").write_text(json.dumps(config))
    result = evaluate(run / "model.zip", episodes=1)
    assert (result["filter"], result["filter_settings"]) == ("c3bf+hocbf20[allowance_level=true]", {"allowance_level": True})
    assert main(["evaluate", str(run / "model.zip"), "--episodes", "1", "--filter-set", "joint_range_reserve=0.2",
                 "--json", str(out_json)]) == 0  # fmt: skip
    assert json.loads(out_json.read_text())["filter"] == "c3bf+hocbf20[joint_range_reserve=0.2]"
    assert evaluate(run / "model.zip", episodes=1, filter="c3bf+hocbf")["filter"] == "c3bf+hocbf"


@pytest.mark.slow
def test_normalized_run_saves_and_applies_its_statistics(tmp_path, monkeypatch):
    from stable_baselines3 import SAC

    run = train(TrainConfig(timesteps=300, action="impedance", filter="none", scenario="head_on", normalize_obs=True, policy_hz=10,
                            eval_freq=10_000, final_eval_episodes=1, out=str(tmp_path), progress_bar=False, distance_weight=2.0,
                            action_weight=0.0, obstacle_encoder="flat", hyperparams={"learning_starts": 100}))  # fmt: skip
    assert run.name == "sac_impedance_norm_10hz_dw2_none_head_on_s0"
    stats = _load_normalizer(run / NORMALIZATION_FILE)
    assert stats is not None and stats.obs_rms.count >= 300 and not stats.training
    obs = np.ones(stats.obs_rms.mean.shape, np.float32)
    assert not np.allclose(stats.normalize_obs(obs), obs)
    import c3bf_gym.training as training

    built = []
    build_env = training.build_env
    monkeypatch.setattr(training, "build_env", lambda *a, **kw: (built.append(kw), build_env(*a, **kw))[1])
    seen = []
    original = SAC.predict
    monkeypatch.setattr(SAC, "predict", lambda self, o, **kw: (seen.append(o.copy()), original(self, o, **kw))[1])
    assert evaluate(run / "model.zip", episodes=1, seed=7)["episodes"] == 1
    assert built[-1]["distance_weight"] == 2.0  # the run's reward, read from its config
    raw, _ = make_env("head_on", "none", "impedance", seed=7, **policy_rate_kwargs(10))().reset(seed=7)
    np.testing.assert_allclose(seen[0], stats.normalize_obs(raw), rtol=1e-6)  # the policy saw normalised obs
    assert len(seen) == 50  # one 5-s episode at the run's 10 Hz


@pytest.mark.slow
def test_set_encoder_run_names_itself_reloads_and_evaluates(tmp_path):
    from stable_baselines3 import SAC

    from c3bf_gym.policies import ObstacleSetExtractor

    run = train(TrainConfig(timesteps=250, action="residual", scenario="multi", policy_hz=10, obstacle_encoder="set",
                            eval_freq=10_000, final_eval_episodes=0, out=str(tmp_path), progress_bar=False,
                            hyperparams={"learning_starts": 100}))  # fmt: skip
    assert run.name == "sac_residual_10hz_dw10_aw3_set_fade0.1_c3bf+hocbf_multi_s0"
    assert json.loads((run / "config.json").read_text())["obstacle_encoder"] == "set"
    model = SAC.load(run / "model.zip", device="cpu")
    assert isinstance(model.actor.features_extractor, ObstacleSetExtractor)
    assert isinstance(model.critic.features_extractor, ObstacleSetExtractor)
    result = evaluate(run / "model.zip", episodes=1)
    assert result["episodes"] == 1 and result["collision_episodes"] == 0


def test_posture_stiffness_sets_the_nominal_controllers_pull_and_names_the_run():
    """``posture_stiffness`` reaches the impedance controller the run's envs step (None: the arm's
    own), and the run's name carries it."""
    assert TrainConfig(posture_stiffness=2.0).name == "sac_residual_10hz_dw10_aw3_set_ps2_fade0.1_c3bf+hocbf_random_s0"
    for stiffness, expected in ((None, 20.0), (2.0, 2.0), (0.0, 0.0)):
        env = build_env("static", "c3bf+hocbf", "residual", posture_stiffness=stiffness, **policy_rate_kwargs(10))
        try:
            assert float(env.unwrapped.torque_hook("nominal").controller.Kq) == expected
        finally:
            env.close()
    with pytest.raises(ValueError, match="posture_stiffness sets the impedance controller"):
        build_env("static", "none", "torque", posture_stiffness=2.0)


def _evaluated_with(tmp_path, monkeypatch, saved: dict, actions: int = 3) -> dict:
    """The keywords ``evaluate`` builds its env with, for a residual run whose ``config.json`` has
    ``saved`` (a policy of ``actions`` zeros, one episode)."""
    import c3bf_gym.training as training

    built = []
    monkeypatch.setattr(training, "build_env", lambda *args, **kwargs: built.append(kwargs) or build_env(*args, **kwargs))
    monkeypatch.setattr(training, "_load_policy", lambda *args: lambda obs: np.zeros(actions, np.float32))
    (tmp_path / "model.zip").touch()
    (tmp_path / "config.json").write_text(json.dumps({"algo": "sac", "action": "residual", "filter": "none",
                                                      "policy_hz": 10, **saved}))  # fmt: skip
    assert evaluate(tmp_path / "model.zip", episodes=1)["episodes"] == 1
    return built.pop()


def test_posture_reach_reaches_the_action_names_the_run_and_is_evaluated_with(tmp_path, monkeypatch):
    """``posture_reach`` reaches the Cartesian action of the run's envs (one more entry per joint)
    and its name; ``evaluate`` rebuilds a run's envs with the run's own; torque actions refuse it."""
    assert TrainConfig(posture_reach=0.5).name == "sac_residual_10hz_dw10_aw3_set_pr0.5_fade0.1_c3bf+hocbf_random_s0"
    for reach, shape in ((None, (3,)), (0.5, (9,))):
        env = build_env("static", "c3bf+hocbf", "residual", posture_reach=reach, **policy_rate_kwargs(10))
        try:
            assert env.get_wrapper_attr("posture_reach") == reach and env.action_space.shape == shape
        finally:
            env.close()
    with pytest.raises(ValueError, match="posture_reach sets the impedance controller"):
        build_env("static", "none", "torque", posture_reach=0.5)
    for bad, message in (({"posture_reach": 0.0}, "posture_reach must be a finite number > 0"),
                         ({"posture_reach": 0.5, "action": "torque"}, "this run's action is 'torque'")):  # fmt: skip
        with pytest.raises(ValueError, match=re.escape(message)):
            TrainConfig(**bad).validate()
    assert _evaluated_with(tmp_path, monkeypatch, {"posture_reach": 0.5}, actions=9)["posture_reach"] == 0.5


def test_residual_modulation_reaches_the_action_names_the_run_and_is_evaluated_with(tmp_path, monkeypatch):
    """``residual_modulation`` reaches the residual action of the run's envs and its name;
    ``evaluate`` rebuilds a run's envs with the run's own; other action modes refuse it."""
    assert TrainConfig(residual_modulation=True).name == "sac_residual_10hz_dw10_aw3_set_fade0.1_mod_c3bf+hocbf_random_s0"
    assert "_mod" not in TrainConfig().name
    for modulate in (False, True):
        env = build_env("static", "c3bf+hocbf", "residual", residual_modulation=modulate, **policy_rate_kwargs(10))
        try:
            assert env.get_wrapper_attr("modulate") is modulate
        finally:
            env.close()
    with pytest.raises(ValueError, match="residual_modulation bends the residual action's straight step"):
        build_env("static", "none", "impedance", residual_modulation=True)
    for bad, message in (({"residual_modulation": True, "action": "torque"}, "it needs action='residual'"),
                         ({"residual_modulation": 1}, "residual_modulation must be True or False")):  # fmt: skip
        with pytest.raises(ValueError, match=re.escape(message)):
            TrainConfig(**bad).validate()
    assert _evaluated_with(tmp_path, monkeypatch, {"residual_modulation": True})["residual_modulation"] is True


def test_applied_action_reaches_the_run_its_buffer_and_its_name_and_is_evaluated_with(tmp_path, monkeypatch):
    """``applied_action``: the run's envs put the applied action in ``info`` and charge it, the
    SAC model stores it (its replay buffer class), the run's name says so, and ``evaluate``
    rebuilds the run's reward; PPO, RLlib, torque actions and no filter refuse it."""
    from stable_baselines3 import SAC

    from c3bf_gym.replay import AppliedActionReplayBuffer

    assert TrainConfig(applied_action=True).name == "sac_residual_10hz_dw10_aw3_set_fade0.1_applied_c3bf+hocbf_random_s0"
    assert "_applied" not in TrainConfig().name
    env = build_env("static", "c3bf+hocbf", "residual", action_weight=3.0, applied_action=True, **policy_rate_kwargs(10))
    try:
        env.reset(seed=0)
        assert env.get_wrapper_attr("charge") == "applied"
        assert env.step(np.zeros(3, np.float32))[-1]["applied_action"].shape == (3,)
    finally:
        env.close()
    for bad, message in (({"applied_action": True, "algo": "ppo"}, "it needs engine='sb3' and algo='sac', got engine='sb3', algo='ppo'"),
                         ({"applied_action": True, "filter": "none"}, "applied_action maps back the safety filter's correction"),
                         ({"applied_action": True, "action": "torque"}, "it needs a Cartesian action ('impedance', 'residual'), got 'torque'"),
                         ({"applied_action": 1}, "applied_action must be True or False")):  # fmt: skip
        with pytest.raises(ValueError, match=re.escape(message)):
            TrainConfig(**bad).validate()
    with pytest.raises(ValueError, match="applied_action maps the filter's correction back to a tool target"):
        build_env("static", "c3bf+hocbf", "torque", applied_action=True)
    run = train(TrainConfig(timesteps=150, scenario="multi", applied_action=True, eval_freq=10_000, final_eval_episodes=0,
                            out=str(tmp_path / "run"), progress_bar=False, hyperparams={"learning_starts": 100}))  # fmt: skip
    assert json.loads((run / "config.json").read_text())["applied_action"] is True
    assert SAC.load(run / "model.zip", device="cpu").replay_buffer_class is AppliedActionReplayBuffer
    saved = {"applied_action": True, "filter": "c3bf+hocbf", "action_weight": 3.0}
    assert _evaluated_with(tmp_path, monkeypatch, saved)["applied_action"] is True


def test_correction_weight_charges_the_run_names_it_and_needs_a_filter():
    assert TrainConfig(correction_weight=5.0).name == "sac_residual_10hz_dw10_aw3_set_cw5_fade0.1_c3bf+hocbf_random_s0"
    assert TrainConfig().correction_weight == 0.0 and "_cw" not in TrainConfig().name
    env = build_env("static", "c3bf+hocbf", "residual", correction_weight=5.0, **policy_rate_kwargs(10))
    try:
        assert env.get_wrapper_attr("weight") == 5.0
        env.reset(seed=0)
        assert "reward_correction" in env.step(np.zeros(3, np.float32))[-1]
    finally:
        env.close()
    with pytest.raises(ValueError, match="CorrectionPenalty charges the safety filter's correction"):
        build_env("static", "none", "residual", correction_weight=5.0)
    for bad, message in (({"correction_weight": 5.0, "filter": "none"}, "correction_weight charges the safety filter's"),
                         ({"correction_weight": -1.0}, "correction_weight must be a finite number >= 0")):  # fmt: skip
        with pytest.raises(ValueError, match=re.escape(message)):
            TrainConfig(**bad).validate()


def test_action_reach_reaches_the_action_names_the_run_and_is_evaluated_with(tmp_path, monkeypatch):
    """``action_reach`` is the Cartesian action's ``max_offset`` in the run's envs: the residual's
    zero action steps at most that far per axis, and one unit of an entry moves the target that
    far. The default keeps the run's name as before the option; ``evaluate`` rebuilds a run's
    envs with its own (the default for runs from before the option)."""
    from c3bf_gym import training

    assert TrainConfig(action_reach=0.15).name == "sac_residual_10hz_dw10_aw3_set_fade0.1_reach0.15_c3bf+hocbf_random_s0"
    assert TrainConfig().name == TrainConfig(action_reach=ACTION_REACH).name == (
        "sac_residual_10hz_dw10_aw3_set_fade0.1_c3bf+hocbf_random_s0")
    assert TrainConfig().action_reach == ACTION_REACH and TrainConfig(action="torque").action_reach is None
    for reach in (None, 0.15):
        env = build_env("none", "none", "residual", action_reach=reach, **policy_rate_kwargs(10))
        try:
            env.reset(seed=0)
            base = env.unwrapped
            tool = base.data.site_xpos[base.ee_site_id].copy()
            assert np.linalg.norm(base.goal - tool) > RESIDUAL_FADE  # the fade leaves this step alone
            env.step(np.array([1.0, 0.0, 0.0], np.float32))
            step = env.get_wrapper_attr("hook").target_pos - tool  # straight (clipped per axis) + one unit along x
            expected = reach or ACTION_REACH
            straight = np.clip(base.goal - tool, -expected, expected)
            np.testing.assert_allclose(step, straight + [expected, 0.0, 0.0], atol=1e-12)
        finally:
            env.close()
    built = []
    monkeypatch.setattr(training, "build_env", lambda *args, **kwargs: built.append(kwargs) or build_env(*args, **kwargs))
    monkeypatch.setattr(training, "_load_policy", lambda *args: lambda obs: np.zeros(3, np.float32))
    (tmp_path / "model.zip").touch()
    for saved, expected in (({"action_reach": 0.15}, 0.15), ({}, None)):
        (tmp_path / "config.json").write_text(json.dumps({"algo": "sac", "action": "residual", "filter": "none",
                                                          "policy_hz": 10, **saved}))  # fmt: skip
        evaluate(tmp_path / "model.zip", episodes=1, scenario="none")
        assert built.pop()["action_reach"] == expected


def test_residual_fade_reaches_the_action_names_the_run_and_is_evaluated_with(tmp_path, monkeypatch):
    """``residual_fade`` reaches the residual action of the run's envs and its name; ``evaluate``
    rebuilds a run's envs with the run's own (None for runs from before the option)."""
    import c3bf_gym.training as training

    assert TrainConfig(residual_fade=0.2).name == "sac_residual_10hz_dw10_aw3_set_fade0.2_c3bf+hocbf_random_s0"
    assert TrainConfig(residual_fade=0.0).name == "sac_residual_10hz_dw10_aw3_set_c3bf+hocbf_random_s0"  # as before it
    assert TrainConfig().residual_fade == RESIDUAL_FADE and TrainConfig(action="torque").residual_fade is None
    for fade in (None, 0.1):
        env = build_env("static", "c3bf+hocbf", "residual", residual_fade=fade, **policy_rate_kwargs(10))
        try:
            assert env.get_wrapper_attr("fade") == fade
        finally:
            env.close()
    for action in ("impedance", "torque"):
        with pytest.raises(ValueError, match=f"residual_fade shrinks the residual correction near the goal; action='{action}'"):
            build_env("static", "none", action, residual_fade=0.1)
    built = []
    monkeypatch.setattr(training, "build_env", lambda *args, **kwargs: built.append(kwargs) or build_env(*args, **kwargs))
    monkeypatch.setattr(training, "_load_policy", lambda *args: lambda obs: np.zeros(3, np.float32))
    (tmp_path / "model.zip").touch()
    for saved, given, expected in (({"residual_fade": 0.1}, None, 0.1), ({}, None, None), ({"residual_fade": 0.1}, 0.0, None),
                                   ({}, 0.2, 0.2)):  # fmt: skip
        config = {"algo": "sac", "action": "residual", "filter": "none", "policy_hz": 10, **saved}
        (tmp_path / "config.json").write_text(json.dumps(config))
        result = evaluate(tmp_path / "model.zip", episodes=1, residual_fade=given)
        assert built.pop()["residual_fade"] == expected
        assert 0 <= result["reached_not_held_episodes"] <= 1 - result["success_rate"]
    with pytest.raises(ValueError, match="residual_fade must be a finite number >= 0"):
        evaluate(tmp_path / "model.zip", episodes=1, residual_fade=-0.1)

    # a policy that reaches the goal (zero residual) and then leaves it (full correction away): not held
    steps = iter(range(10**6))
    monkeypatch.setattr(training, "_load_policy",
                        lambda *args: lambda obs: np.zeros(3, np.float32) if next(steps) % 50 < 35 else np.ones(3, np.float32))
    (tmp_path / "config.json").write_text(json.dumps({"algo": "sac", "action": "residual", "filter": "none", "policy_hz": 10}))
    result = evaluate(tmp_path / "model.zip", episodes=2, scenario="none", per_episode=True)
    assert (result["success_rate"], result["reached_not_held_episodes"]) == (0.0, 2)
    for record in result["per_episode"]:
        assert record["scenario"] == "none" and not record["success"] and not record["collided"]
        assert record["closest_distance"] < 0.05 < record["final_distance"] and record["goal_clearance"] is None
    record = evaluate(tmp_path / "model.zip", episodes=1, scenario="static", per_episode=True)["per_episode"][0]
    assert record["goal_clearance"] is not None and record["goal_clearance"] > 0.0  # the sphere at rest, off the goal


@pytest.mark.slow
def test_correction_observing_run_names_itself_reloads_and_evaluates(tmp_path):
    """``observe_correction``: the run's envs append the filter's correction (FilterFeedback), the
    set encoder passes it through, and the saved model evaluates on the same observation."""
    from stable_baselines3 import SAC

    run = train(TrainConfig(timesteps=250, scenario="multi", observe_correction=True, eval_freq=10_000,
                            final_eval_episodes=0, out=str(tmp_path), progress_bar=False,
                            hyperparams={"learning_starts": 100}))  # fmt: skip
    assert run.name == "sac_residual_10hz_dw10_aw3_set_oc_fade0.1_c3bf+hocbf_multi_s0"
    assert json.loads((run / "config.json").read_text())["observe_correction"] is True
    model = SAC.load(run / "model.zip", device="cpu")
    assert model.observation_space.shape == (2 * 6 + 73 + 6,)
    assert model.actor.features_extractor.features_dim == 21 + 6 + 2 * 64
    result = evaluate(run / "model.zip", episodes=1)
    assert result["episodes"] == 1 and result["collision_episodes"] == 0
    with pytest.raises(ValueError, match="evaluate it with a filter"):
        evaluate(run / "model.zip", episodes=1, filter="none")


@pytest.mark.slow
def test_posture_reach_correction_weight_and_clearance_run_trains_reloads_and_evaluates(tmp_path):
    """A run with the posture entries, the correction's cost and the arm's clearances: the model
    acts in 3 + 6 dimensions and sees 8 more entries, which the set encoder passes through, and
    evaluate rebuilds the run's action, observation and reward from its config."""
    from stable_baselines3 import SAC

    run = train(TrainConfig(timesteps=250, scenario="multi", posture_reach=0.5, correction_weight=5.0,
                            observe_clearance=True, eval_freq=10_000, final_eval_episodes=0, out=str(tmp_path),
                            progress_bar=False, hyperparams={"learning_starts": 100}))  # fmt: skip
    assert run.name == "sac_residual_10hz_dw10_aw3_set_cl_pr0.5_cw5_fade0.1_c3bf+hocbf_multi_s0"
    saved = json.loads((run / "config.json").read_text())
    assert (saved["posture_reach"], saved["correction_weight"], saved["observe_clearance"]) == (0.5, 5.0, True)
    model = SAC.load(run / "model.zip", device="cpu")
    assert model.action_space.shape == (9,) and model.observation_space.shape == (2 * 6 + 73 + 8,)
    assert model.actor.features_extractor.features_dim == 21 + 8 + 2 * 64  # the clearances beside the arm's own
    result = evaluate(run / "model.zip", episodes=1)
    assert result["episodes"] == 1 and result["collision_episodes"] == 0
    assert evaluate(run / "model.zip", episodes=1, filter="none")["episodes"] == 1  # no filter, no correction to charge


def test_observe_time_run_sees_the_clock_and_ends_its_episodes_at_the_limit(tmp_path):
    """``observe_time``: the model sees one more entry (the set encoder passes it through), SAC's
    replay buffer stores the time limit as the episode's end, and evaluate rebuilds the
    observation from the run's config. PPO and RLlib are refused by name."""
    from stable_baselines3 import SAC
    from stable_baselines3.common.vec_env import DummyVecEnv

    run = train(TrainConfig(timesteps=150, scenario="crossing", observe_time=True, eval_freq=10_000,
                            final_eval_episodes=0, out=str(tmp_path), progress_bar=False,
                            hyperparams={"learning_starts": 100}))  # fmt: skip
    assert run.name == "sac_residual_10hz_dw10_aw3_set_time_fade0.1_c3bf+hocbf_crossing_s0"
    assert json.loads((run / "config.json").read_text())["observe_time"] is True
    model = SAC.load(run / "model.zip", device="cpu")
    assert model.observation_space.shape == (2 * 6 + 73 + 1,)
    assert model.actor.features_extractor.features_dim == 21 + 1 + 2 * 64
    config = TrainConfig(observe_time=True)
    venv = DummyVecEnv([make_env(config.scenario, seed=0, **config.env_options())])
    try:
        buffer = sb3_model(config, venv, config.resolved_hyperparams()).replay_buffer
        assert buffer.handle_timeout_termination is False
    finally:
        venv.close()
    assert evaluate(run / "model.zip", episodes=1)["episodes"] == 1
    for bad in ({"algo": "ppo"}, {"engine": "rllib", "algo": "ppo", "obstacle_encoder": "flat"}):
        with pytest.raises(ValueError, match="observe_time ends each episode at its time limit .* needs engine='sb3' and algo='sac'"):
            TrainConfig(observe_time=True, **bad).validate()


@pytest.mark.parametrize(("option", "suffix", "attribute", "value", "entries"), [
    ("observe_contact_time", "ct", "horizon", 2.0, lambda n: n),
    ("observe_forecast", "fc", "cap", 0.5, lambda n: 12),
])  # fmt: skip
def test_an_observation_option_reaches_the_envs_names_the_run_and_is_evaluated_with(tmp_path, monkeypatch, option,
                                                                                   suffix, attribute, value, entries):
    """``observe_contact_time`` (ArmContactTime: one entry per arm geom) and ``observe_forecast``
    (ArmForecast: two per horizon, six horizons) append their entries to the run's observation,
    name the run, and ``evaluate`` rebuilds them from the run's config."""
    from c3bf_gym import training

    assert TrainConfig(**{option: True}).name == f"sac_residual_10hz_dw10_aw3_set_{suffix}_fade0.1_c3bf+hocbf_random_s0"
    plain = build_env("multi", **TrainConfig().env_options())
    seen = build_env("multi", **TrainConfig(**{option: True}).env_options())
    try:
        n = len(seen.unwrapped.arm_geom_ids)
        assert seen.observation_space.shape == (plain.observation_space.shape[0] + entries(n),)
        assert seen.get_wrapper_attr(attribute) == value
    finally:
        plain.close()
        seen.close()
    built = []
    monkeypatch.setattr(training, "build_env", lambda *args, **kwargs: built.append(kwargs) or build_env(*args, **kwargs))
    monkeypatch.setattr(training, "_load_policy", lambda *args: lambda obs: np.zeros(3, np.float32))
    (tmp_path / "model.zip").touch()
    for saved, expected in (({option: True}, True), ({}, False)):
        (tmp_path / "config.json").write_text(json.dumps({"algo": "sac", "action": "residual", "filter": "none",
                                                          "policy_hz": 10, **saved}))  # fmt: skip
        evaluate(tmp_path / "model.zip", episodes=1, scenario="none")
        assert built.pop()[option] is expected


def test_the_open_loop_oracle_wins_an_episode_the_zero_action_loses(monkeypatch, capsys):
    """train/oracle.py: on evaluation episode 12 (`static`) the zero action stops behind the
    resting sphere, 26 cm from the goal; a small search under the filter finds a sequence that
    ends within the tolerance with no collision, and the summary counts it for the scenario."""
    spec = importlib.util.spec_from_file_location("oracle", Path(__file__).parents[1] / "train" / "oracle.py")
    oracle = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(oracle)
    argv = ["oracle.py", "--episodes", "12", "--segments", "5", "--samples", "16", "--iterations", "2"]
    monkeypatch.setattr(sys, "argv", argv)
    oracle.main()
    searched, summary = (json.loads(line) for line in capsys.readouterr().out.splitlines())
    assert searched["episode"] == 12 and searched["scenario"] == "static"
    assert searched["zero_action_final"] > 0.2 and searched["zero_action_collisions"] == 0
    assert searched["searched_success"] and searched["searched_final"] < 0.05
    assert summary["by_scenario"] == {"static": {"episodes": 1, "zero_action": 0.0, "zero_action_or_searched": 1.0}}


@pytest.mark.parametrize("in_filter", [False, True])
def test_the_tool_metric_probe_holds_the_goal_where_the_default_filter_pushes_the_tool_off(capsys, in_filter):
    """train/tool_metric.py: on evaluation episode 192 (`multi`) the zero action under the default
    filter ends 6.6 cm from the goal; with the probe's metric (corrections the tool feels cost
    more), or the filter's own (``--in-filter``: ``weight="tool"``), it ends within the tolerance,
    with no collision by the environment's own distances."""
    spec = importlib.util.spec_from_file_location("tool_metric", Path(__file__).parents[1] / "train" / "tool_metric.py")
    probe = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(probe)
    default, tool = probe.main(["--episodes", "192", "--tool-acceleration", "10"] + ["--in-filter"] * in_filter)
    (lost,), (won,) = default["episodes"], tool["episodes"]
    assert lost["scenario"] == won["scenario"] == "multi"
    assert not lost["success"] and lost["final"] > 0.05 and lost["collisions"] == 0
    assert won["success"] and won["final"] < 0.05 and won["collisions"] == 0
    if in_filter:
        assert tool["calls"] is None and tool["in_filter"]
    else:
        assert tool["calls"] == 2_500 and tool["fallbacks"] < tool["calls"] // 10
    out = capsys.readouterr().out
    assert "default filter: multi 0/1 (0 collided)" in out
    assert ("a = 10 (in the filter): multi 1/1" in out) == in_filter
    with pytest.raises(SystemExit):
        probe.main(["--tool-acceleration", "0"])


@pytest.mark.slow
def test_panda_run_trains_under_the_filter_names_itself_and_evaluates_on_the_panda(tmp_path):
    """``robot="panda"``: the run's envs are the 7-joint Panda's (its 87-entry observation,
    7-joint torques under the filter), the run name says so, and evaluation rebuilds the Panda from
    the run's config."""
    run = train(TrainConfig(robot="panda", timesteps=250, scenario="multi", eval_freq=10_000, final_eval_episodes=0,
                            out=str(tmp_path), progress_bar=False, hyperparams={"learning_starts": 100}))  # fmt: skip
    assert run.name == "panda_sac_residual_10hz_dw10_aw10_set_fade0.1_c3bf+hocbf_multi_s0"
    assert json.loads((run / "config.json").read_text())["robot"] == "panda"
    summary = json.loads((run / "summary.json").read_text())
    assert summary["training_cost"] == 0.0
    result = evaluate(run / "model.zip", episodes=1)
    assert result["episodes"] == 1 and result["collision_episodes"] == 0


def test_robot_reaches_the_env_and_is_validated():
    env = make_env("none", "c3bf+hocbf", "residual", seed=0, **TrainConfig(robot="panda").env_kwargs())()
    assert env.unwrapped.robot.n == 7 and env.observation_space.shape == (87,)
    env.step(env.action_space.sample())
    env.close()
    assert "robot" not in TrainConfig().env_kwargs()  # UR5e runs keep their earlier configs and names
    with pytest.raises(ValueError, match="unknown robot 'ur10'; valid choices: 'ur5e', 'panda'"):
        TrainConfig(robot="ur10").validate()


@pytest.mark.parametrize("hz", [10, 50])
def test_policy_rate_keeps_five_second_episodes(hz):
    env = make_env("none", "none", "impedance", seed=0, **policy_rate_kwargs(hz))()
    assert env.unwrapped.dt == pytest.approx(1.0 / hz)
    steps, done = 0, False
    while not done:
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        steps, done = steps + 1, terminated or truncated
    assert steps == 5 * hz and env.unwrapped.data.time == pytest.approx(5.0)
    env.close()


def test_distance_weight_reaches_the_env_and_names_the_run():
    config = TrainConfig(action="residual", distance_weight=5.0, action_weight=0.0, obstacle_encoder="flat", policy_hz=10)
    assert config.name == "sac_residual_10hz_dw5_fade0.1_c3bf+hocbf_random_s0"
    assert TrainConfig(action="residual", policy_hz=10, distance_weight=0.0).env_kwargs() == policy_rate_kwargs(10)
    env = make_env("none", "none", "residual", seed=0, **config.env_kwargs())()
    _, reward, *_, info = env.step(np.zeros(3, np.float32))
    assert info["reward_distance"] == pytest.approx(-5.0 * info["distance"])
    env.close()


def test_filter_names_reach_the_filter_and_name_the_run():
    """A run's filter is a FILTERS name, the same filter as SafetyFilter's of that name: "c3bf" is
    the C3BF's rows alone, the default "c3bf+hocbf" has the distance HOCBF beside them; the run
    name says which, and the guard's gains when they are not the default."""
    from c3bf_gym.safety.barriers import DistanceHOCBF

    assert TrainConfig(filter="c3bf").name == "sac_residual_10hz_dw10_aw3_set_fade0.1_c3bf_random_s0"
    assert TrainConfig(filter="hocbf").name == "sac_residual_10hz_dw10_aw3_set_fade0.1_hocbf_random_s0"
    assert TrainConfig().name == "sac_residual_10hz_dw10_aw3_set_fade0.1_c3bf+hocbf_random_s0"
    assert TrainConfig(guard_gamma=5.0).name == "sac_residual_10hz_dw10_aw3_set_fade0.1_c3bf+hocbf5_random_s0"
    for name, expected in (("c3bf+hocbf", DistanceHOCBF), ("c3bf", type(None))):
        env = make_env("none", name, "residual", seed=0)()
        assert type(env.get_wrapper_attr("hook").guard) is expected
        assert env.get_wrapper_attr("config") == FilterConfig.named(name)
        env.close()
    env = make_env("none", "c3bf+hocbf", "residual", seed=0, guard_gamma=7.0)()
    assert env.get_wrapper_attr("hook").guard.gamma1 == 7.0
    env.close()
    for bad in (0.0, -1.0, float("inf"), True):
        with pytest.raises(ValueError, match="guard_gamma must be a finite number > 0"):
            TrainConfig(guard_gamma=bad).validate()
    for name in ("hocbf", "c3bf", "none"):  # gains without a guard are an inconsistency, not ignored
        with pytest.raises(ValueError, match="guard_gamma was given"):
            TrainConfig(filter=name, guard_gamma=7.0).validate()
    with pytest.raises(ValueError, match=r"unknown filter 'cbf'; valid choices: 'none', 'c3bf\+hocbf', 'c3bf', 'hocbf'"):
        make_env("none", "cbf", "residual")


def test_filter_settings_build_the_run_filter_and_name_it():
    """A run's filter_settings change the named filter's other fields: the env is built with them,
    the run's name and the tables' label list the ones that differ from the named filter, and
    anything the filter cannot take, or that a name already says, is refused by name."""
    config = TrainConfig(filter_settings={"allowance_level": True, "joint_range_reserve": 0.3})
    config.validate()
    assert config.filter_config() == FilterConfig.named("c3bf+hocbf", allowance_level=True, joint_range_reserve=0.3)
    assert config.name == ("sac_residual_10hz_dw10_aw3_set_fade0.1_c3bf+hocbf[joint_range_reserve=0.3,"
                           "allowance_level=true]_random_s0")  # fmt: skip
    assert filter_label("c3bf+hocbf", 20.0, {"margin": 0.02}) == "c3bf+hocbf20"  # a default is no change
    assert filter_label("c3bf", None, {"gamma": 2, "weight": "identity"}) == "c3bf[gamma=2,weight=identity]"
    tool = filter_label("c3bf+hocbf", None, {"weight": "tool"})  # a = 10 is what None reads as: one filter, one name
    assert tool == filter_label("c3bf+hocbf", None, {"weight": "tool", "tool_acceleration": 10.0}) == "c3bf+hocbf[weight=tool]"
    assert filter_label("c3bf+hocbf", None, {"weight": "tool", "tool_acceleration": 3}) == "c3bf+hocbf[weight=tool,tool_acceleration=3]"
    assert filter_label("c3bf", None, {"margin": 0.0123456789}) == "c3bf[margin=0.0123456789]"  # exact
    env = make_env("none", config.filter_config(), "residual", seed=0)()
    assert env.get_wrapper_attr("config").allowance_level
    env.close()
    for settings, match in (
        ({"allowance_level": 1}, "allowance_level must be True or False"),
        ({"foo": 1}, "unknown filter setting.*'foo'.*valid settings: barrier, gamma"),
        ({"guard": None}, "'guard' are chosen by the filter's name"),
        ({"guard_gamma": 5.0}, "'guard_gamma' are chosen by the filter's name"),
        ({"margin": [0.1]}, "filter settings must map FilterConfig field names to numbers"),
    ):
        with pytest.raises(ValueError, match=match):
            TrainConfig(filter_settings=settings).validate()
    with pytest.raises(ValueError, match="allowance_level=True needs a guard"):
        TrainConfig(filter="c3bf", filter_settings={"allowance_level": True}).validate()
    with pytest.raises(ValueError, match=r"filter settings were given without a filter \(filter='none'\)"):
        TrainConfig(filter="none", filter_settings={"margin": 0.05}).validate()


def test_filter_setting_reads_values_as_the_command_line_spells_them():
    assert [filter_setting(text) for text in ("allowance_level=true", "sensing_radius=none", "margin=0.05",
                                              "joint_range_reserve=1", "weight=identity")] == [  # fmt: skip
        ("allowance_level", True), ("sensing_radius", None), ("margin", 0.05), ("joint_range_reserve", 1),
        ("weight", "identity")]  # fmt: skip
    for bad in ("allowance_level", "=true"):
        with pytest.raises(argparse.ArgumentTypeError, match="expected SETTING=VALUE"):
            filter_setting(bad)


def test_action_weight_penalises_the_policy_action_and_names_the_run():
    config = TrainConfig(action="residual", distance_weight=10.0, action_weight=0.5, obstacle_encoder="flat", policy_hz=10)
    assert config.name == "sac_residual_10hz_dw10_aw0.5_fade0.1_c3bf+hocbf_random_s0"
    env = make_env("none", "c3bf+hocbf", "residual", seed=0, action_weight=0.5, **config.env_kwargs())()
    assert [type(w).__name__ for w in (env, env.env)] == ["Monitor", "ActionPenalty"]
    _, reward, *_, info = env.step(np.ones(3, np.float32))
    assert info["reward_action"] == pytest.approx(-0.5)
    assert reward == pytest.approx(sum(v for k, v in info.items() if k.startswith("reward_")))
    env.close()


@pytest.mark.parametrize(("flag", "field"), [
    ("--observe-clearance", "observe_clearance"), ("--observe-contact-time", "observe_contact_time"),
    ("--observe-forecast", "observe_forecast"), ("--observe-time", "observe_time"),
])  # fmt: skip
def test_train_observation_flags_reach_their_config_field(monkeypatch, tmp_path, flag, field):
    import c3bf_gym.training

    seen = []
    (tmp_path / "summary.json").write_text("{}")
    monkeypatch.setattr(c3bf_gym.training, "train", lambda config, address=None: seen.append(config) or tmp_path)
    assert main(["train", flag]) == 0 and seen == [TrainConfig(**{field: True})]


def test_defaults_are_the_readme_recipe_on_every_entry_point(monkeypatch, tmp_path):
    """`c3bf-gym train` and train/run_baselines.py take their defaults from TrainConfig, whose
    defaults are the recipe of the README's RL table (its run names say so)."""
    import c3bf_gym.training

    assert TrainConfig().name == "sac_residual_10hz_dw10_aw3_set_fade0.1_c3bf+hocbf_random_s0"
    assert TrainConfig().timesteps == 25_000 and TrainConfig(algo="ppo").timesteps == 100_000  # each its budget
    assert TrainConfig(algo="ppo", timesteps=7).timesteps == 7
    seen = []
    (tmp_path / "summary.json").write_text("{}")
    monkeypatch.setattr(c3bf_gym.training, "train", lambda config, address=None: seen.append(config) or tmp_path)
    assert main(["train"]) == 0 and seen == [TrainConfig()]
    # run_baselines.py passes every option on, so its runs are the same recipe
    spec = importlib.util.spec_from_file_location("run_baselines", Path(__file__).parents[1] / "train" / "run_baselines.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    commands = []
    monkeypatch.setattr(module.subprocess, "call", lambda command, **_: commands.append(command) or 0)
    monkeypatch.setattr(sys, "argv", ["run_baselines.py", "--filters", "c3bf+hocbf", "--seeds", "0", "--out", str(tmp_path)])
    assert module.main() == 0 and len(commands) == 1 and commands[0][1:4] == ["-m", "c3bf_gym.cli", "train"]
    assert main(commands[0][3:]) == 0
    assert seen[1] == TrainConfig(out=str(tmp_path), progress_bar=False)
    # the Panda's own action weight, through both entry points
    panda = TrainConfig(robot="panda")
    assert panda.action_weight == ACTION_WEIGHTS["panda"] == 10.0 and TrainConfig().action_weight == 3.0
    assert panda.name == "panda_sac_residual_10hz_dw10_aw10_set_fade0.1_c3bf+hocbf_random_s0"
    assert TrainConfig(robot="panda", action_weight=3.0).action_weight == 3.0  # a given weight is kept
    assert main(["train", "--robot", "panda"]) == 0 and seen[2] == panda
    monkeypatch.setattr(sys, "argv", ["run_baselines.py", "--robot", "panda", "--filters", "none", "--seeds", "0",
                                      "--out", str(tmp_path)])  # fmt: skip
    assert module.main() == 0 and main(commands[1][3:]) == 0
    assert seen[3] == TrainConfig(robot="panda", filter="none", out=str(tmp_path), progress_bar=False)
    # --filter-set reaches the filtered runs only, and a setting the filter refuses stops the set before it starts
    monkeypatch.setattr(sys, "argv", ["run_baselines.py", "--filters", "none", "c3bf+hocbf", "--filter-set",
                                      "allowance_level=true", "--seeds", "0", "--out", str(tmp_path)])  # fmt: skip
    assert module.main() == 0
    by_filter = {command[command.index("--filter") + 1]: command for command in commands[2:]}
    assert "--filter-set" not in by_filter["none"]
    assert by_filter["c3bf+hocbf"][by_filter["c3bf+hocbf"].index("--filter-set") + 1] == "allowance_level=true"
    assert main(by_filter["c3bf+hocbf"][3:]) == 0 and seen[-1].filter_settings == {"allowance_level": True}
    monkeypatch.setattr(sys, "argv", ["run_baselines.py", "--filters", "c3bf", "--filter-set", "allowance_level=true",
                                      "--seeds", "0", "--out", str(tmp_path)])  # fmt: skip
    with pytest.raises(SystemExit):
        module.main()
    assert len(commands) == 4  # nothing ran


def test_the_rllib_engine_has_its_own_defaults_and_refuses_what_it_cannot_train(monkeypatch, tmp_path):
    """`c3bf-gym train --engine rllib` trains RLlib PPO with the flat encoder unless told
    otherwise, names its runs apart, passes --address on; what RLlib cannot train is an error."""
    import c3bf_gym.training

    seen = []
    (tmp_path / "summary.json").write_text("{}")
    monkeypatch.setattr(c3bf_gym.training, "train", lambda config, address=None: seen.append((config, address)) or tmp_path)
    assert main(["train", "--engine", "rllib", "--n-envs", "2", "--address", "auto"]) == 0
    config, address = seen[0]
    assert config == TrainConfig(engine="rllib", algo="ppo", obstacle_encoder="flat", n_envs=2) and address == "auto"
    assert config.name == "rllib_ppo_residual_10hz_dw10_aw3_fade0.1_c3bf+hocbf_random_s0" and config.timesteps == 100_000
    assert config.resolved_hyperparams()["train_batch_size_per_env"] == 1024
    assert main(["train", "--engine", "rllib", "--algo", "sac"]) == 0  # the CLI passes it on; validate() refuses
    with pytest.raises(ValueError, match="the rllib engine supports algo='ppo' only, got 'sac'"):
        seen[1][0].validate()
    monkeypatch.undo()  # the real train: an SB3 run has no Ray cluster to join
    with pytest.raises(ValueError, match="address is the Ray cluster of the rllib engine"):
        train(TrainConfig(out=str(tmp_path / "runs")), address="auto")
    assert not (tmp_path / "runs").exists()


def test_by_scenario_splits_an_evaluation_by_its_concrete_scenarios():
    table = by_scenario(["multi", "static", "multi", "multi", "static"], [1.0, 0.0, 0.0, 1.0, 1.0],
                        [0.0, 1.0, 0.0, 0.0, 1.0])  # fmt: skip
    assert list(table) == ["multi", "static"]
    assert table["multi"] == {"episodes": 3, "success_rate": pytest.approx(2 / 3), "collision_episodes": 0,
                              "collision_free_success_rate": pytest.approx(2 / 3)}  # fmt: skip
    # a success through an obstacle is a success, but not a collision-free one
    assert table["static"] == {"episodes": 2, "success_rate": 0.5, "collision_episodes": 2,
                               "collision_free_success_rate": 0.0}  # fmt: skip


def test_make_env_puts_monitor_outside_the_filter():
    env = make_env("static", "c3bf+hocbf", "impedance", seed=0)()
    assert type(env).__name__ == "Monitor"
    assert "episode_interventions" in env.info_keywords and "episode_infeasible" in env.info_keywords
    env.close()


def test_every_engine_builds_the_run_environment_from_env_options():
    # every build_env option but the scenario (and guard_gamma, which filter_config has applied)
    # is a run's: an option added to build_env and not to env_options fails here
    options = set(inspect.signature(build_env).parameters) - {"scenario", "guard_gamma", "env_kwargs"}
    assert options <= set(TrainConfig().env_options())
    config = TrainConfig(correction_weight=0.5, observe_clearance=True, applied_action=True, policy_hz=20)
    env = make_env(config.scenario, seed=0, **config.env_options())()
    chain, layer = [], env
    while hasattr(layer, "env"):
        chain.append(type(layer).__name__)
        layer = layer.env
    assert chain[:7] == ["Monitor", "ActionPenalty", "AppliedAction", "CorrectionPenalty", "ArmClearance",
                         "SafetyFilter", "CartesianImpedanceAction"]  # fmt: skip
    assert env.unwrapped.frame_skip == 25 and env.get_wrapper_attr("fade") == config.residual_fade  # 20 Hz at 500 Hz
    env.close()


@pytest.mark.parametrize("action, shape", [("impedance", (3,)), ("residual", (3,)), ("torque", (6,))])
def test_make_env_action_modes(action, shape):
    env = make_env("static", "c3bf", action, seed=0)()
    assert env.action_space.shape == shape
    impedance = env.get_wrapper_attr("residual") if action != "torque" else None
    assert impedance == {"impedance": False, "residual": True, "torque": None}[action]
    env.step(env.action_space.sample())
    env.close()


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"algo": "dqn"}, "unknown algo 'dqn'; valid choices: 'sac', 'ppo'"),
        ({"action": "joint"}, "unknown action 'joint'"),
        ({"filter": "cbf"}, "unknown filter 'cbf'"),
        ({"scenario": "sideways"}, "unknown scenario 'sideways'"),
        ({"timesteps": 0}, "timesteps must be an integer >= 1"),
        ({"seed": -1}, "seed must be an integer >= 0"),
        ({"final_eval_episodes": -1}, "final_eval_episodes must be an integer >= 0"),
        ({"eval_scenario": "radnom"}, "scenario 'radnom'.*'random', 'random_multi'"),
        ({"normalize_obs": 1}, "normalize_obs must be True or False"),
        ({"policy_hz": 30}, "policy_hz must be one of 10, 20, 25, 50, 100"),
        ({"policy_hz": 10.0}, "policy_hz must be one of"),
        ({"distance_weight": -1.0}, "distance_weight must be a finite number >= 0"),
        ({"distance_weight": float("nan")}, "distance_weight must be a finite number >= 0"),
        ({"action_weight": -0.1}, "action_weight must be a finite number >= 0"),
        ({"obstacle_encoder": "gnn"}, "unknown obstacle_encoder 'gnn'; valid choices: 'flat', 'set'"),
        ({"engine": "jax"}, "unknown engine 'jax'; valid choices: 'sb3', 'rllib'"),
        ({"engine": "rllib"}, "the rllib engine supports algo='ppo' only, got 'sac'"),
        ({"engine": "rllib", "algo": "ppo"}, "the rllib engine supports obstacle_encoder='flat' only, got 'set'"),
        ({"engine": "rllib", "algo": "ppo", "obstacle_encoder": "flat", "normalize_obs": True},
         "the rllib engine supports normalize_obs=False only, got True"),
        ({"engine": "rllib", "algo": "ppo", "obstacle_encoder": "flat", "observe_correction": True},
         "the rllib engine supports observe_correction=False only, got True"),
        ({"observe_correction": 1}, "observe_correction must be True or False"),
        ({"observe_correction": True, "filter": "none"}, "observe_correction .* needs a filter .* got filter='none'"),
        ({"posture_stiffness": -1.0}, "posture_stiffness must be a finite number >= 0"),
        ({"posture_stiffness": float("nan")}, "posture_stiffness must be a finite number >= 0"),
        ({"posture_stiffness": 2.0, "action": "torque"}, "posture_stiffness sets the impedance controller .* 'torque'"),
        ({"residual_fade": -0.1}, re.escape("residual_fade must be a finite number >= 0 [m], got -0.1")),
        ({"residual_fade": float("inf")}, "residual_fade must be a finite number >= 0"),
        ({"residual_fade": 0.1, "action": "impedance"}, "residual_fade shrinks .* action='impedance' .*'residual' only"),
        ({"action_reach": 0.0}, re.escape("action_reach must be a finite number > 0 [m], got 0.0")),
        ({"action_reach": float("nan")}, "action_reach must be a finite number > 0"),
        ({"action_reach": 0.2, "action": "torque"}, "action_reach scales .* action='torque' .*'impedance' and 'residual' only"),
    ],
)
def test_bad_training_options(kwargs, message):
    with pytest.raises(ValueError, match=message):
        TrainConfig(**kwargs).validate()


def _has_rllib() -> bool:
    try:
        import ray.rllib  # noqa: F401
    except ImportError:
        return False
    return True


@pytest.mark.skipif(_has_rllib(), reason="Ray RLlib is installed here")
def test_the_rllib_engine_without_ray_names_the_extra(tmp_path):
    config = TrainConfig(engine="rllib", algo="ppo", obstacle_encoder="flat", out=str(tmp_path))
    with pytest.raises(ImportError, match=r'pip install "c3bf-gym\[rllib\]"'):
        train(config)
    assert not any(tmp_path.iterdir()), "nothing is written before Ray is found"
    with pytest.raises(SystemExit) as stop:  # the command line says the same, without a traceback
        main(["train", "--engine", "rllib", "--out", str(tmp_path)])
    assert stop.value.code == 2


def test_evaluate_missing_model(tmp_path):
    with pytest.raises(FileNotFoundError, match="no model at"):
        evaluate(tmp_path / "model.zip")


def _fake_run(root, name, filter_name, action, costs, final=None, by_scenario=None, infeasible=True, **options):
    """A run directory as `train` writes it, with made-up numbers (tests the table, not RL); an
    infeasible step in episode 2 if it had no collision, and no such column with ``infeasible=False``
    (runs from before it was recorded)."""
    run = root / name
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"algo": "sac", "action": action, "filter": filter_name, **options}))
    with open(run / "episodes.csv", "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["timesteps", "return", "length", "success", "cost", "interventions"] + ["infeasible"] * infeasible + ["cumulative_cost"])
        for i, cost in enumerate(costs):
            row = [250 * (i + 1), 10.0 * i, 250, float(i % 2), cost, 0] + [float(i == 1 and cost == 0)] * infeasible
            writer.writerow(row + [sum(costs[: i + 1])])
    (run / "summary.json").write_text(json.dumps({"training_cost": float(sum(costs))}))
    if final is not None:
        record = {"success_rate": final, "return_mean": 5.0, "episodes": 50}
        if by_scenario is not None:
            record["by_scenario"] = by_scenario
        (run / "final_eval.json").write_text(json.dumps(record))
    return run


def test_plot_training_table_groups_by_mode_and_filter(tmp_path):
    runs = [
        _fake_run(tmp_path, "a", "none", "impedance", [3, 0, 2], final=0.5),
        _fake_run(tmp_path, "b", "none", "impedance", [1, 1, 0], final=0.25),
        _fake_run(tmp_path, "c", "c3bf", "residual", [0, 0, 0], final=1.0),
        _fake_run(tmp_path, "d", "c3bf", "impedance", [0, 0, 0], infeasible=False),  # no evaluation at all, an old run
    ]
    out = tmp_path / "curves.png"
    assert main(["plot-training", *map(str, runs), "--out", str(out), "--table", str(tmp_path / "t.md")]) == 0
    rows = (tmp_path / "t.md").read_text().splitlines()
    assert out.stat().st_size > 0
    assert "| sac | impedance | none | 2 | 750 | 7 (5, 2) | 1 (1, 0) | 0.38 (0.50, 0.25) | 5.0 | 50 |" in rows
    assert "| sac | impedance | c3bf | 1 | 750 | 0 (0) | n/a | n/a | n/a | n/a |" in rows
    assert "| sac | residual | c3bf | 1 | 750 | 0 (0) | 1 (1) | 1.00 (1.00) | 5.0 | 50 |" in rows
    assert not any("multi" in row for row in rows)  # no run recorded the split by scenario


def test_plot_training_splits_final_success_by_scenario(tmp_path):
    split = [{"multi": {"episodes": 3, "success_rate": s, "collision_episodes": 0},
              "static": {"episodes": 2, "success_rate": 1.0, "collision_episodes": 0}} for s in (1 / 3, 2 / 3)]  # fmt: skip
    runs = [_fake_run(tmp_path, name, "c3bf", "residual", [0, 0, 0], final=0.8, by_scenario=b) for name, b in zip("ab", split)]
    table = plot_training(runs, tmp_path / "curves.png").splitlines()
    assert "| algo | action | filter | static | multi |" in table  # the paper's order
    assert "| sac | residual | c3bf | 1.00 (1.00, 1.00; 2 ep.) | 0.50 (0.33, 0.67; 3 ep.) |" in table


def test_plot_training_reads_a_longer_evaluation_when_asked(tmp_path):
    runs = [_fake_run(tmp_path, name, "c3bf", "residual", [0, 0], final=0.8) for name in "ab"]
    for run, rate in zip(runs, (0.9, 0.95)):
        split = {"multi": {"episodes": 50, "success_rate": rate, "collision_episodes": 0}}
        (run / "eval_200.json").write_text(json.dumps({"success_rate": rate, "return_mean": 7.0, "episodes": 200, "by_scenario": split}))
    table = (tmp_path / "t.md")
    assert main(["plot-training", *map(str, runs), "--out", str(tmp_path / "c.png"), "--table", str(table), "--evaluation", "eval_200.json"]) == 0
    rows = table.read_text().splitlines()
    assert "| sac | residual | c3bf | 2 | 500 | 0 (0, 0) | 2 (1, 1) | 0.93 (0.90, 0.95) | 7.0 | 200 |" in rows
    assert "| sac | residual | c3bf | 0.93 (0.90, 0.95; 50 ep.) |" in rows
    (runs[1] / "eval_200.json").unlink()
    with pytest.raises(FileNotFoundError, match=r"b has no eval_200.json \(write it with: c3bf-gym evaluate"):
        plot_training(runs, tmp_path / "c.png", evaluation="eval_200.json")


def test_plot_training_keeps_the_guarded_c3bf_apart(tmp_path):
    """Runs of the C3BF with its guard are their own row per guard gain ("c3bf+hocbf" with the
    default, "c3bf+hocbf5" with gains 5), apart from the C3BF alone and the HOCBF."""
    runs = [
        _fake_run(tmp_path, "old", "c3bf", "residual", [0, 0], final=0.8),
        _fake_run(tmp_path, "alone", "c3bf", "residual", [0, 0], final=0.9, guard_gamma=None),
        _fake_run(tmp_path, "guarded5", "c3bf+hocbf", "residual", [0, 0], final=0.6, guard_gamma=5.0),
        _fake_run(tmp_path, "guarded", "c3bf+hocbf", "residual", [0, 0], final=1.0, guard_gamma=None),
        _fake_run(tmp_path, "h_old", "hocbf", "residual", [0, 0], final=0.7),
        _fake_run(tmp_path, "h_new", "hocbf", "residual", [0, 0], final=0.9, guard_gamma=None),
    ]
    rows = plot_training(runs, tmp_path / "c.png").splitlines()
    assert "| sac | residual | c3bf | 2 | 500 | 0 (0, 0) | 2 (1, 1) | 0.85 (0.80, 0.90) | 5.0 | 50 |" in rows
    assert "| sac | residual | c3bf+hocbf5 | 1 | 500 | 0 (0) | 1 (1) | 0.60 (0.60) | 5.0 | 50 |" in rows
    assert "| sac | residual | c3bf+hocbf | 1 | 500 | 0 (0) | 1 (1) | 1.00 (1.00) | 5.0 | 50 |" in rows
    assert "| sac | residual | hocbf | 2 | 500 | 0 (0, 0) | 2 (1, 1) | 0.80 (0.70, 0.90) | 5.0 | 50 |" in rows
    # and a run with other filter settings is its own row, labelled with them
    runs.append(_fake_run(tmp_path, "allow", "c3bf+hocbf", "residual", [0, 0], final=0.7, guard_gamma=None,
                          filter_settings={"allowance_level": True}))  # fmt: skip
    rows = plot_training(runs, tmp_path / "c.png").splitlines()
    assert "| sac | residual | c3bf+hocbf[allowance_level=true] | 1 | 500 | 0 (0) | 1 (1) | 0.70 (0.70) | 5.0 | 50 |" in rows
    assert "| sac | residual | c3bf+hocbf | 1 | 500 | 0 (0) | 1 (1) | 1.00 (1.00) | 5.0 | 50 |" in rows


def test_plot_training_refuses_to_average_different_recipes(tmp_path):
    runs = [
        _fake_run(tmp_path, "a", "c3bf", "residual", [0, 0], final=0.8, seed=0),  # predates obstacle_encoder
        _fake_run(tmp_path, "b", "c3bf", "residual", [0, 0], final=0.9, seed=1, obstacle_encoder="flat"),
    ]
    plot_training(runs, tmp_path / "same.png")  # an old config means the default: one recipe
    runs.append(_fake_run(tmp_path, "c", "c3bf", "residual", [0, 0], final=1.0, seed=2, obstacle_encoder="set"))
    with pytest.raises(ValueError, match="runs grouped as sac residual c3bf differ in obstacle_encoder"):
        plot_training(runs, tmp_path / "mixed.png")


def test_plot_training_refuses_to_average_two_arms(tmp_path):
    runs = [_fake_run(tmp_path, "u", "c3bf", "residual", [0, 0], final=0.8),  # predates robot: the UR5e
            _fake_run(tmp_path, "p", "c3bf", "residual", [0, 0], final=0.9, robot="panda")]  # fmt: skip
    with pytest.raises(ValueError, match="runs grouped as sac residual c3bf differ in robot"):
        plot_training(runs, tmp_path / "mixed.png")


def test_plot_training_reports_the_steps_to_competence(tmp_path):
    """The first training step at which the success over the last 50 episodes reached 0.9 (a full
    window), and the minutes the run's wall time gives it pro rata; "-" for a seed that never did."""
    runs = [_fake_run(tmp_path, name, "c3bf", "residual", [0] * 120, final=0.9) for name in "ab"]
    wins = np.r_[np.zeros(20), np.ones(100)]  # from episode 20 on every episode succeeds
    for run, success in zip(runs, (wins, np.tile([0.0, 1.0], 60))):  # the second: 0.5 throughout
        with open(run / "episodes.csv", newline="") as fh:
            rows = list(csv.DictReader(fh))
        for row, value in zip(rows, success):
            row["success"] = value
        with open(run / "episodes.csv", "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
        (run / "summary.json").write_text(json.dumps({"training_cost": 0.0, "wall_time_s": 600.0}))
    table = plot_training(runs, tmp_path / "c.png").splitlines()
    # 45 successes of 50 first at episode 65 (index 64): step 250 * 65, 16,250 of 30,000 steps
    assert "| sac | residual | c3bf | 16250, - | 5.4, - | 1 of 2 |" in table


def test_plot_training_rejects_a_non_run(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["plot-training", str(tmp_path), "--out", str(tmp_path / "x.png")])
    assert "not a run directory" in capsys.readouterr().err
