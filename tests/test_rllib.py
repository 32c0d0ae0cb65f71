"""Ray: RLlib PPO training under the filter, and the guarantee sweep as Ray tasks.

These run where the ``rllib`` extra is installed (CI's second environment, with the gymnasium
that RLlib pins); elsewhere they are skipped.
"""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("ray.rllib")

from c3bf_gym.cli import main  # noqa: E402
from c3bf_gym.rllib import load_policy  # noqa: E402
from c3bf_gym.training import TrainConfig, evaluate, train  # noqa: E402

#: a few small PPO iterations: 2 env runners x 100 steps each
SMOKE = {"train_batch_size_per_env": 100, "minibatch_size": 50, "num_epochs": 1}


def test_rllib_ppo_trains_under_the_filter_on_two_env_runners_and_evaluates(tmp_path):
    config = TrainConfig(engine="rllib", algo="ppo", obstacle_encoder="flat", n_envs=2, timesteps=400,
                         checkpoint_freq=200, final_eval_episodes=2, out=str(tmp_path), progress_bar=False,
                         hyperparams=SMOKE)  # fmt: skip
    run = train(config)
    assert run.name == "rllib_ppo_residual_10hz_dw10_aw3_fade0.1_c3bf+hocbf_random_s0"
    assert (run / "checkpoint").is_dir() and (run / "checkpoints" / "200").is_dir()
    saved = json.loads((run / "config.json").read_text())
    assert saved["engine"] == "rllib" and saved["resolved_hyperparams"]["minibatch_size"] == 50
    with open(run / "progress.csv") as fh:
        progress = list(csv.DictReader(fh))
    assert [int(r["timesteps"]) for r in progress] == [200, 400], "2 env runners x 100 steps per iteration"
    with open(run / "episodes.csv") as fh:
        episodes = list(csv.DictReader(fh))
    assert len(episodes) == sum(int(r["episodes"]) for r in progress) >= 4  # 50-step episodes
    assert all(float(r["length"]) == 50 and float(r["interventions"]) > 0 for r in episodes)
    summary = json.loads((run / "summary.json").read_text())
    assert summary["timesteps"] == 400 and summary["training_episodes"] == len(episodes)
    assert summary["training_cost"] == 0.0, "the default filter kept every obstacle off the arm"
    final = json.loads((run / "final_eval.json").read_text())
    assert final["filter"] == "c3bf+hocbf" and final["episodes"] == 2 and final["collision_episodes"] == 0
    # the same episodes, rolled out again through `c3bf-gym evaluate`: the same numbers
    assert evaluate(run / "checkpoint", episodes=2) == final
    assert main(["evaluate", str(run / "checkpoints" / "200"), "--episodes", "1", "--filter", "none"]) == 0
    policy = load_policy(run / "checkpoint")
    action = policy(np.zeros(saved_obs_size(run), np.float32))
    assert action.shape == (3,) and np.all(np.abs(action) <= 1.0)
    with pytest.raises(FileNotFoundError, match="no RLlib checkpoint"):
        load_policy(tmp_path)


def test_an_unknown_hyperparameter_is_refused_before_anything_is_written(tmp_path):
    config = TrainConfig(engine="rllib", algo="ppo", obstacle_encoder="flat", out=str(tmp_path), hyperparams={"learning_rate": 1e-3})
    with pytest.raises(ValueError, match="bad RLlib PPO hyperparameters .*learning_rate"):
        train(config)
    assert not any(tmp_path.iterdir())


def saved_obs_size(run: Path) -> int:
    """The observation size of a run's env (from a fresh env of its config)."""
    from c3bf_gym.training import build_env, env_kwargs

    config = json.loads((run / "config.json").read_text())
    env = build_env(config["scenario"], "none", config["action"], **env_kwargs(config["policy_hz"], config["distance_weight"]))
    size = env.observation_space.shape[0]
    env.close()
    return size


def test_guarantee_sweep_gives_the_same_table_on_ray_and_on_one_local_worker(tmp_path):
    script = Path(__file__).resolve().parents[1] / "benchmarks" / "guarantee.py"
    tables = {}
    for mode, argv in (("pool", ["--workers", "1"]), ("ray", ["--ray", "--workers", "2"])):
        out = tmp_path / mode
        done = subprocess.run([sys.executable, str(script), "--quick", "--scenarios", "static", "head_on", "--filters",
                               "c3bf+hocbf/whole_arm", "none", "--out", str(out), *argv],
                              capture_output=True, text=True, timeout=600)  # fmt: skip
        assert done.returncode == 0, done.stderr[-2000:]
        rows = json.loads((out / "summary.json").read_text())["configurations"]
        tables[mode] = [{k: v for k, v in r.items() if k != "max_filter_ms"} for r in rows]  # wall clock
        assert (out / "episodes.csv").read_text().count("\n") == 1 + 2 * 2 * 2 * 2
    assert tables["ray"] == tables["pool"]
    assert any(r["collision_episodes"] for r in tables["ray"] if r["filter"] == "none"), "the sweep can fail"
