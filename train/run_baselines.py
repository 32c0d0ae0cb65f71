"""Run the baseline set: one algorithm and action mode, three filters, several seeds.

Runs go two at a time (one core each; set --jobs) as `c3bf-gym train` subprocesses, so every
run's exact command is in its config.json and its log in OUT/logs/. `--n-envs N` gives each run N
environments in SB3's SubprocVecEnv (e.g. PPO: `--algo ppo --n-envs 2 --jobs 1`). Finished runs are skipped,
so the script can be re-run after an interruption. The defaults are `TrainConfig`'s (the
README's RL recipe); for example, the main set of the README's table:

    python train/run_baselines.py --seeds 0 1 2 3 4
"""

from __future__ import annotations

import argparse
import itertools
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from c3bf_gym.cli import filter_setting
from c3bf_gym.envs.reach import ROBOTS
from c3bf_gym.training import ACTIONS, ALGORITHMS, OBSTACLE_ENCODERS, POLICY_RATES, TRAIN_FILTERS, TrainConfig


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    d = TrainConfig()  # the defaults live there
    parser.add_argument("--algo", choices=ALGORITHMS, default=d.algo)
    parser.add_argument("--robot", choices=list(ROBOTS), default=d.robot, help="the arm (default %(default)s)")
    parser.add_argument("--action", choices=ACTIONS, default=d.action)
    parser.add_argument("--filters", nargs="+", choices=TRAIN_FILTERS, default=["none", d.filter, "hocbf"])
    parser.add_argument("--guard-gamma", type=float, default=d.guard_gamma,
                        help="the gains of c3bf+hocbf's guard (default: the filter's)")
    parser.add_argument("--filter-set", nargs="+", default=[], metavar="SETTING=VALUE",
                        help="change the filter's settings in every filtered run (c3bf-gym train --filter-set), "
                             "e.g. allowance_level=true")  # fmt: skip
    parser.add_argument("--scenario", default=d.scenario)
    parser.add_argument("--eval-scenario", default=d.eval_scenario,
                        help="scenario of the evaluations (default: the training scenario)")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--timesteps", type=int, default=None, help="policy steps per run (default: the algorithm's, TrainConfig)")
    parser.add_argument("--policy-hz", type=int, choices=POLICY_RATES, default=d.policy_hz)
    parser.add_argument("--normalize-obs", action="store_true")
    parser.add_argument("--distance-weight", type=float, default=d.distance_weight,
                        help="the reward's dense -distance term (default %(default)s)")
    parser.add_argument("--action-weight", type=float, default=None,
                        help="the reward's -mean(action^2) term (default: the robot's, TrainConfig)")
    parser.add_argument("--residual-fade", type=float, default=None, metavar="M",
                        help="shrink the residual correction within M metres of the goal (0: never; default: TrainConfig's)")
    parser.add_argument("--obstacle-encoder", choices=OBSTACLE_ENCODERS, default=d.obstacle_encoder,
                        help="flat MLP or a shared per-obstacle encoder (set)")
    parser.add_argument("--hyperparams", default=None, help="JSON overriding the defaults (passed to every run)")
    parser.add_argument("--n-envs", type=int, default=d.n_envs,
                        help="environments per run (more than 1: SB3's SubprocVecEnv; default %(default)s)")
    parser.add_argument("--final-eval-episodes", type=int, default=d.final_eval_episodes,
                        help="episodes of each final model's evaluation (default %(default)s; the README's tables: 200)")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--out", default="runs")
    args = parser.parse_args()
    try:
        settings = dict(filter_setting(item) for item in args.filter_set)
    except argparse.ArgumentTypeError as error:
        parser.error(f"--filter-set: {error}")

    def changes(filter_name: str) -> dict:
        """--filter-set for the filtered runs, nothing for the unfiltered ones."""
        return {} if filter_name == "none" else settings

    def gains(filter_name: str) -> float | None:
        """--guard-gamma for the filters with a guard (c3bf+hocbf), None for the others."""
        return args.guard_gamma if filter_name == "c3bf+hocbf" else None

    out = Path(args.out)
    (out / "logs").mkdir(parents=True, exist_ok=True)
    jobs = []
    for seed, filter_name in itertools.product(args.seeds, args.filters):
        try:  # the name builds the run's filter: a setting it refuses is an error here, before any run starts
            name = TrainConfig(
                algo=args.algo, robot=args.robot, action=args.action, filter=filter_name, guard_gamma=gains(filter_name), filter_settings=changes(filter_name), scenario=args.scenario, seed=seed,
                policy_hz=args.policy_hz, normalize_obs=args.normalize_obs, distance_weight=args.distance_weight,
                action_weight=args.action_weight, obstacle_encoder=args.obstacle_encoder, residual_fade=args.residual_fade,
            ).name  # fmt: skip
        except ValueError as error:
            parser.error(f"{filter_name}: {error}")
        if (out / name / "summary.json").exists():
            print(f"skip {name}: finished")
            continue
        command = [
            sys.executable, "-m", "c3bf_gym.cli", "train", "--algo", args.algo, "--robot", args.robot, "--action", args.action,
            "--filter", filter_name, *(["--guard-gamma", str(gains(filter_name))] if gains(filter_name) else []),
            *(["--filter-set", *args.filter_set] if changes(filter_name) else []),
            "--scenario", args.scenario, "--seed", str(seed),
            *(["--eval-scenario", args.eval_scenario] if args.eval_scenario else []),
            *(["--timesteps", str(args.timesteps)] if args.timesteps is not None else []), "--out", str(out), "--no-progress", "--policy-hz", str(args.policy_hz),
            "--distance-weight", str(args.distance_weight),
            *(["--action-weight", str(args.action_weight)] if args.action_weight is not None else []),
            "--obstacle-encoder", args.obstacle_encoder, "--n-envs", str(args.n_envs),
            "--final-eval-episodes", str(args.final_eval_episodes),
            *(["--residual-fade", str(args.residual_fade)] if args.residual_fade is not None else []),
        ] + (["--normalize-obs"] if args.normalize_obs else []) + (["--hyperparams", args.hyperparams] if args.hyperparams else [])  # fmt: skip
        jobs.append((name, command))

    def run(job: tuple[str, list[str]]) -> tuple[str, int, float]:
        name, command = job
        start = time.perf_counter()
        with open(out / "logs" / f"{name}.log", "w") as log:
            code = subprocess.call(command, stdout=log, stderr=subprocess.STDOUT)
        return name, code, time.perf_counter() - start

    failed = 0
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        for name, code, seconds in pool.map(run, jobs):
            print(f"{'done' if code == 0 else 'FAILED'} {name} in {seconds / 60:.1f} min", flush=True)
            failed += code != 0
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
