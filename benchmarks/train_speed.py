"""SB3 training throughput, filtered and unfiltered, side by side.

For each learner (``--algo``, by default SAC and PPO), each action mode (``--actions``) and each
filter (none, and ``--filter``, by default the default filter), a model of the training recipe
(``c3bf_gym.training.TrainConfig``'s defaults: policy rate, reward terms, obstacle encoder, the
learner's hyperparameters) learns on ``--n-envs`` environments (``SubprocVecEnv``;
:func:`c3bf_gym.training.training_envs`). Every configuration is built once (subprocesses
started, compiled code loaded) and warmed up with one round; then rounds alternate the
configurations, the order rotating from round to round, and each round times ``model.learn`` over
``--steps`` environment steps: the environments' steps and the learner's updates together, as a
training run spends them. Printed per configuration: the median over rounds of environment steps
per second, and for each learner and action mode the ratio filtered ÷ unfiltered (the share of
the unfiltered throughput that training under the filter keeps).

The action modes differ in what runs at every physics step: with ``torque`` actions the filter
alone; with ``residual`` (the recipe) or ``impedance`` actions the compiled impedance controller in
front of it. Both run inside the environment's compiled policy step.

Usage::

    python benchmarks/train_speed.py                        # SAC and PPO, 2 envs, torque and residual, 5 rounds
    python benchmarks/train_speed.py --rounds 3 --steps 2048 --json results/train_speed.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

from c3bf_gym.safety import DEFAULT_FILTER, FILTERS
from c3bf_gym.training import ACTIONS, ALGORITHMS, TrainConfig, sb3_model, training_envs


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--algo", nargs="+", choices=ALGORITHMS, default=list(ALGORITHMS),
                        help=f"the learners (default: {' '.join(ALGORITHMS)})")
    parser.add_argument("--actions", nargs="+", choices=ACTIONS, default=["torque", "residual"],
                        help="action modes (default: torque residual)")
    parser.add_argument("--filter", choices=list(FILTERS), default=DEFAULT_FILTER, help="the filtered runs' filter")
    parser.add_argument("--n-envs", type=int, default=2, help="subprocess environments (default 2)")
    parser.add_argument("--steps", type=int, default=4096, help="environment steps per round (default 4096)")
    parser.add_argument("--rounds", type=int, default=5, help="timed rounds (default 5)")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args(argv)
    if args.n_envs < 1 or args.steps < args.n_envs or args.rounds < 1:
        parser.error("--n-envs and --rounds must be >= 1 and --steps >= --n-envs")

    import torch

    torch.set_num_threads(1)  # as training runs do
    algos = list(dict.fromkeys(args.algo))  # each learner once, in the order given
    configs = [(algo, action, name) for algo in algos for action in args.actions for name in ("none", args.filter)]
    models = {}
    for algo, action, name in configs:
        config = TrainConfig(algo=algo, action=action, filter=name, n_envs=args.n_envs, progress_bar=False)
        config.validate()
        hyper = config.resolved_hyperparams()
        if algo == "ppo":  # one rollout of all the envs per round (the update's share does not change)
            hyper["n_steps"] = max(args.steps // args.n_envs, 2)
            hyper["batch_size"] = min(hyper["batch_size"], hyper["n_steps"] * args.n_envs)
        model = sb3_model(config, training_envs(config), hyper)
        model.learn(args.steps)  # warm-up: first-call costs out of the timed rounds
        models[algo, action, name] = model
    rates: dict[tuple[str, str, str], list[float]] = {key: [] for key in configs}
    for r in range(args.rounds):
        order = configs[r % len(configs):] + configs[:r % len(configs)]
        for key in order:
            model = models[key]
            start = time.perf_counter()
            model.learn(args.steps, reset_num_timesteps=False)
            rates[key].append(args.steps / (time.perf_counter() - start))
    for model in models.values():
        model.get_env().close()

    print(f"SB3, {args.n_envs} SubprocVecEnv envs, recipe's env (policy at {TrainConfig().policy_hz} Hz), "
          f"{args.rounds} rounds x {args.steps} env steps per configuration, interleaved")
    print(f"{'algo':5s} {'action':10s} {'filter':12s} | {'env steps/s median':>18s} {'min':>7s} {'max':>7s} | filtered ÷ unfiltered")
    out = {"algo": algos, "n_envs": args.n_envs, "steps": args.steps, "rounds": args.rounds, "results": []}
    for algo, action, name in configs:
        values = rates[algo, action, name]
        median = statistics.median(values)
        row = {"algo": algo, "action": action, "filter": name, "steps_per_s": values, "median": median}
        ratio = ""
        if name != "none":
            row["filtered_over_unfiltered"] = median / statistics.median(rates[algo, action, "none"])
            ratio = f"{row['filtered_over_unfiltered']:.2f}"
        print(f"{algo:5s} {action:10s} {name:12s} | {median:18.0f} {min(values):7.0f} {max(values):7.0f} | {ratio}")
        out["results"].append(row)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
