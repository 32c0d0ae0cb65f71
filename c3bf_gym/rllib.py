"""Ray RLlib training on ``C3BFReach-v0``: PPO on RLlib's new API stack, with the safety filter.

The ``rllib`` extra installs it (``pip install "c3bf-gym[rllib]"``). RLlib steps the same
environment stack as the Stable-Baselines3 runs (:func:`c3bf_gym.training.build_env`: the
action mode, the filter, the reward's terms), in ``n_envs`` env runners, each a Ray actor with one
env. A run is a :class:`~c3bf_gym.training.TrainConfig` with ``engine="rllib"``, and its
directory has the SB3 runs' layout, so ``c3bf-gym evaluate`` and ``c3bf-gym plot-training`` read
both:

* ``config.json``, ``summary.json`` and ``final_eval.json`` (:func:`c3bf_gym.training.finish_run`);
* ``checkpoint/``: the final algorithm state (``Algorithm.save_to_path``); its RL module is what
  :func:`load_policy` and ``c3bf-gym evaluate RUN/checkpoint`` roll out; ``checkpoints/N/`` every
  ``checkpoint_freq`` env steps;
* ``episodes.csv``: one row per finished training episode, as in SB3 runs, except that
  ``timesteps`` is the env-step count at the end of the training iteration that collected the
  episode;
* ``progress.csv``: one row per training iteration: env steps, episodes, mean return, success
  rate, collision steps (``cost``, summed over the iteration's finished episodes), cumulative
  cost, interventions and infeasible steps per episode, wall time.

The per-episode safety numbers are read from the environment's own ``info`` at each episode's end
(``episode_cost``, ``is_success``, ``episode_interventions``, ``episode_infeasible``) by
:func:`safety_metrics` and reach the driver through RLlib's metrics, under ``env_runners/c3bf``.

By default ``ray.init`` starts a local Ray instance sized for the run (``n_envs`` env runners and
the learner in the driver); ``address`` joins an existing cluster instead (``"auto"``, or
``"ray://host:10001"``).
"""

from __future__ import annotations

import csv
import functools
import math
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from c3bf_gym.training import TrainConfig, build_env, finish_run, start_run

__all__ = ["ENV_NAME", "load_policy", "safety_metrics", "train_rllib"]

#: The name the environment stack is registered under with Ray (``ray.tune.register_env``).
ENV_NAME = "c3bf_gym/train_env"
#: The per-episode record of :func:`safety_metrics`, in ``episodes.csv``'s column order.
EPISODE_FIELDS = ("return", "length", "success", "cost", "interventions", "infeasible")


def _make_env(env_config: dict[str, Any]):
    """RLlib's env creator: :func:`~c3bf_gym.training.build_env` on the run's keywords (importing
    this module registered the environments, in an env-runner process too)."""
    return build_env(**env_config)


@functools.cache
def safety_metrics() -> type:
    """The RLlib callback class that logs each finished episode's safety record (below); pass it
    to ``AlgorithmConfig.callbacks`` to use it in your own RLlib setup. Built on the first call
    (then the same class), so that importing this module does not import Ray."""
    from ray.rllib.callbacks.callbacks import RLlibCallback

    class SafetyMetrics(RLlibCallback):
        """Logs each finished episode's safety record from the environment's last ``info``:
        ``env_runners/c3bf/episodes`` (a list of :data:`EPISODE_FIELDS` tuples per iteration),
        and the iteration's means of success, cost, interventions and infeasible steps."""

        def on_episode_end(self, *, episode, metrics_logger=None, **kwargs) -> None:
            info = episode.get_infos(-1)
            record = (
                float(episode.get_return()),
                float(len(episode)),
                float(info.get("is_success", False)),
                float(info.get("episode_cost", 0.0)),
                float(info.get("episode_interventions", 0)),
                float(info.get("episode_infeasible", 0)),
            )
            metrics_logger.log_value(("c3bf", "episodes"), record, reduce="item_series")
            for name, value in zip(EPISODE_FIELDS[2:], record[2:]):
                metrics_logger.log_value(("c3bf", name), value, reduce="mean", window=100)

    return SafetyMetrics


def _ppo_config(config: TrainConfig, hyper: dict[str, Any]):
    """The ``PPOConfig`` of a run: the env stack, ``n_envs`` env runners, the hyperparameters
    (:data:`~c3bf_gym.training.RLLIB_PPO_HYPERPARAMS` with the run's overrides)."""
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.default_model_config import DefaultModelConfig

    hyper = dict(hyper)
    hidden = hyper.pop("fcnet_hiddens")
    per_env = hyper.pop("train_batch_size_per_env")
    env_config = dict(scenario=config.scenario, **config.env_options())
    ppo = PPOConfig()
    try:
        ppo = ppo.training(train_batch_size_per_learner=per_env * config.n_envs, **hyper)
    except TypeError as error:  # an unknown keyword
        raise ValueError(f"bad RLlib PPO hyperparameters {sorted(hyper)}: {error} (valid: PPOConfig.training's "
                         "keywords, plus fcnet_hiddens and train_batch_size_per_env)") from None  # fmt: skip
    return (
        ppo.environment(ENV_NAME, env_config=env_config, clip_actions=True, normalize_actions=False)
        # sample_timeout_s=None: wait for every env runner's samples. RLlib's default (60 s) discards
        # the samples of a runner that takes longer (a busy machine, a cold first step) and reports
        # an empty iteration: steps paid for and thrown away.
        .env_runners(num_env_runners=config.n_envs, num_envs_per_env_runner=1, num_cpus_per_env_runner=1,
                     sample_timeout_s=None)
        .learners(num_learners=0)
        .rl_module(model_config=DefaultModelConfig(fcnet_hiddens=hidden, fcnet_activation="tanh",
                                                   vf_share_layers=False, free_log_std=True))  # fmt: skip
        .callbacks(safety_metrics())
        .debugging(seed=config.seed)
        .reporting(metrics_num_episodes_for_smoothing=100)
    )


def train_rllib(config: TrainConfig, address: str | None = None) -> Path:
    """Train one RLlib PPO run (``config.engine == "rllib"``) until ``config.timesteps`` env
    steps are sampled; returns the run directory (module docstring for its files).

    ``address``: None starts a local Ray instance with ``n_envs + 1`` CPUs (the env runners and
    the learner; the machine's cores may be fewer), anything else is passed to ``ray.init`` to
    join a cluster. A Ray instance this call started is shut down at the end.

    Raises:
        ValueError: the config is invalid, is not an RLlib run, or has a hyperparameter that
            ``PPOConfig.training`` does not take.
        ImportError: Ray RLlib is not installed (the ``rllib`` extra).
    """
    config.validate()
    if config.engine != "rllib":
        raise ValueError(f"train_rllib trains engine='rllib' runs; this config's engine is {config.engine!r}")
    try:
        import ray
        from ray.tune.registry import register_env
    except ImportError as error:
        raise ImportError('the rllib engine needs Ray RLlib: pip install "c3bf-gym[rllib]"') from error

    ppo = _ppo_config(config, config.resolved_hyperparams())  # bad hyperparameters fail here, before any file
    run_dir, _ = start_run(config)
    started = not ray.is_initialized()
    if started:
        local = {"num_cpus": config.n_envs + 1} if address is None else {}
        ray.init(address=address, include_dashboard=False, log_to_driver=False, **local)
    try:
        register_env(ENV_NAME, _make_env)
        algo = ppo.build_algo()
        summary = _train_loop(algo, config, run_dir)
        algo.save_to_path(str((run_dir / "checkpoint").resolve()))
        algo.stop()
    finally:
        if started:
            ray.shutdown()
    return finish_run(config, run_dir, run_dir / "checkpoint", summary)


def _train_loop(algo, config: TrainConfig, run_dir: Path) -> dict[str, Any]:
    """``algo.train()`` until ``config.timesteps`` env steps; writes ``episodes.csv``,
    ``progress.csv`` and the periodic checkpoints; returns the summary's training numbers."""
    start = time.perf_counter()
    steps, episodes, cumulative_cost, next_checkpoint = 0, 0, 0.0, config.checkpoint_freq
    with open(run_dir / "episodes.csv", "w", newline="") as ef, open(run_dir / "progress.csv", "w", newline="") as pf:
        episode_rows, progress_rows = csv.writer(ef), csv.writer(pf)
        episode_rows.writerow(["timesteps", *EPISODE_FIELDS, "cumulative_cost"])
        progress_rows.writerow(["iteration", "timesteps", "episodes", "return_mean", "success_rate", "cost",
                                "cumulative_cost", "interventions_per_episode", "infeasible_per_episode", "wall_time_s"])  # fmt: skip
        iteration = 0
        while steps < config.timesteps:
            result = algo.train()
            iteration += 1
            steps = int(result["num_env_steps_sampled_lifetime"])
            # an iteration whose env runners returned nothing in time has no env_runners results
            records = list(result.get("env_runners", {}).get("c3bf", {}).get("episodes", []))
            iteration_cost = 0.0
            for record in records:
                cumulative_cost += record[3]
                iteration_cost += record[3]
                episode_rows.writerow([steps, *record, cumulative_cost])
            episodes += len(records)
            columns = np.array(records, dtype=float).reshape(-1, len(EPISODE_FIELDS))
            mean = columns.mean(axis=0) if len(records) else np.full(len(EPISODE_FIELDS), math.nan)
            progress_rows.writerow([iteration, steps, len(records), mean[0], mean[2], iteration_cost, cumulative_cost,
                                    mean[4], mean[5], round(time.perf_counter() - start, 3)])  # fmt: skip
            ef.flush()
            pf.flush()
            if steps >= next_checkpoint and steps < config.timesteps:
                algo.save_to_path(str((run_dir / "checkpoints" / str(steps)).resolve()))
                next_checkpoint += config.checkpoint_freq
    wall = time.perf_counter() - start
    return {"timesteps": steps, "wall_time_s": wall, "training_cost": cumulative_cost, "training_episodes": episodes,
            "env_steps_per_s": steps / wall}  # fmt: skip


def load_policy(checkpoint: str | Path, deterministic: bool = True) -> Callable[[np.ndarray], np.ndarray]:
    """The RL module of an RLlib checkpoint (``RUN/checkpoint`` or ``RUN/checkpoints/N``) as
    ``observation -> action``, on the CPU: the action distribution's mode when ``deterministic``,
    else a sample, clipped to the action box [-1, 1] as in training (``clip_actions``).

    Raises:
        FileNotFoundError: the directory holds no RLlib checkpoint of a single-agent module.
    """
    import torch
    from ray.rllib.core import COMPONENT_LEARNER, COMPONENT_LEARNER_GROUP, COMPONENT_RL_MODULE, DEFAULT_MODULE_ID
    from ray.rllib.core.rl_module.rl_module import RLModule

    path = Path(checkpoint) / COMPONENT_LEARNER_GROUP / COMPONENT_LEARNER / COMPONENT_RL_MODULE / DEFAULT_MODULE_ID
    if not path.is_dir():
        raise FileNotFoundError(f"no RLlib checkpoint of a single-agent module in {checkpoint} (expected {path})")
    module = RLModule.from_checkpoint(str(path.resolve()))
    dist_cls = module.get_inference_action_dist_cls()

    def policy(obs: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            out = module.forward_inference({"obs": torch.as_tensor(np.asarray(obs, np.float32)[None])})
            dist = dist_cls.from_logits(out["action_dist_inputs"])
            action = (dist.to_deterministic() if deterministic else dist).sample()[0].numpy()
        return np.clip(action, -1.0, 1.0)

    return policy
