"""Training smoke runs (slow): SAC and PPO, with and without the filter; save, reload, evaluate."""

from __future__ import annotations

import csv
import json

import pytest

from c3bf_gym.cli import main
from c3bf_gym.training import TrainConfig, evaluate, make_env, train


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["sac", "ppo"])
@pytest.mark.parametrize("filter_name", ["none", "c3bf"])
def test_train_save_reload_evaluate(algo, filter_name, tmp_path):
    config = TrainConfig(
        algo=algo, filter=filter_name, scenario="head_on", timesteps=300, eval_freq=250, eval_episodes=1,
        checkpoint_freq=250, out=str(tmp_path), progress_bar=False,
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
    if filter_name == "c3bf":
        assert summary["training_cost"] == 0.0
        assert all(float(r["interventions"]) >= 0 for r in rows)
    result = evaluate(run / "model.zip", episodes=1)
    assert result["filter"] == filter_name and result["episodes"] == 1
    assert 0.0 <= result["success_rate"] <= 1.0
    if filter_name == "c3bf":
        assert result["collision_episodes"] == 0


@pytest.mark.slow
def test_evaluate_command_with_another_filter(tmp_path, capsys):
    run = train(TrainConfig(timesteps=260, filter="none", scenario="head_on", eval_freq=10_000, out=str(tmp_path),
                            progress_bar=False, hyperparams={"learning_starts": 100}))  # fmt: skip
    out_json = tmp_path / "eval.json"
    assert main(["evaluate", str(run / "model.zip"), "--episodes", "2", "--filter", "c3bf", "--json", str(out_json)]) == 0
    result = json.loads(out_json.read_text())
    assert result["filter"] == "c3bf" and result["collision_episodes"] == 0 and result["episodes"] == 2


def test_make_env_puts_monitor_outside_the_filter():
    env = make_env("static", "c3bf", "impedance", seed=0)()
    assert type(env).__name__ == "Monitor"
    assert "episode_interventions" in env.info_keywords
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
    ],
)
def test_bad_training_options(kwargs, message):
    with pytest.raises(ValueError, match=message):
        TrainConfig(**kwargs).validate()


def test_evaluate_missing_model(tmp_path):
    with pytest.raises(FileNotFoundError, match="no model at"):
        evaluate(tmp_path / "model.zip")
