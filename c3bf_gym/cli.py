"""The ``c3bf-gym`` command line.

    c3bf-gym experiments [options]      the paper's four scenarios, C3BF vs HOCBF vs no filter
    c3bf-gym train [options]            one training run: Stable-Baselines3 (SAC, PPO) or RLlib PPO
    c3bf-gym evaluate MODEL [options]   roll out a saved model
    c3bf-gym plot-training RUNS...      learning curves of several runs, grouped by filter

Run ``c3bf-gym COMMAND --help`` for each command's options; ``c3bf-gym --version`` prints the
installed version.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Sequence

__all__ = ["main"]


def _number(kind: type, low: float, strict: bool):
    """An argparse type: a finite ``kind`` (int or float) above ``low`` (strictly, if asked)."""
    words = "a whole number" if kind is int else "a finite number"
    bound = f"{words} {'>' if strict else '>='} {low:g}"

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {words}, got {text!r}") from None
        if not (value > low if strict else value >= low) or value == float("inf"):
            raise argparse.ArgumentTypeError(f"expected {bound}, got {text}")
        return value

    parse.__name__ = bound  # argparse names the type in its messages
    return parse


_positive_int = _number(int, 1, strict=False)
_nonnegative_int = _number(int, 0, strict=False)
_positive_float = _number(float, 0.0, strict=True)
_nonnegative_float = _number(float, 0.0, strict=False)


def filter_setting(text: str) -> tuple[str, object]:
    """An argparse type: ``"NAME=VALUE"``, a change to a
    :class:`~c3bf_gym.safety.FilterConfig` field, as ``(name, value)``. The value is read as
    true/false, none, a whole number, a number, or else as text; the filter checks the name and
    the value when it is built."""
    name, sep, value = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"expected SETTING=VALUE (a FilterConfig field), got {text!r}")
    words = {"true": True, "false": False, "none": None}
    if value.lower() in words:
        return name, words[value.lower()]
    for kind in (int, float):
        try:
            return name, kind(value)
        except ValueError:
            pass
    return name, value


filter_setting.__name__ = "SETTING=VALUE"  # argparse names the type in its messages


def add_filter_settings(parser: argparse.ArgumentParser, flag: str = "--filter-set", default: object = (),
                        note: str = "") -> None:
    """The option that changes the filter's settings: ``flag NAME=VALUE ...``
    (:func:`filter_setting`), collected as a list of ``(name, value)`` pairs; ``note`` ends its help."""
    parser.add_argument(flag, nargs="+", type=filter_setting, default=default, metavar="SETTING=VALUE",
                        help="change the filter's settings (FilterConfig fields: numbers, true/false, none or "
                             f"names), e.g. allowance_level=true joint_range_reserve=0.3{note}")  # fmt: skip


def subcommand(sub: argparse._SubParsersAction, name: str, summary: str, description: str, *,
               defaults: type | None = None) -> argparse.ArgumentParser:
    """Add the subcommand ``name`` (``summary`` in ``c3bf-gym --help``, ``description`` in its own).

    ``defaults``: the dataclass whose fields are the options' defaults, the one place they are kept
    (e.g. :class:`~c3bf_gym.training.TrainConfig`); the description ends by naming it, and each
    option's help shows its default.
    """
    formatter = argparse.HelpFormatter
    if defaults is not None:
        description = f"{description} Defaults: {defaults.__module__}.{defaults.__qualname__}."
        formatter = argparse.ArgumentDefaultsHelpFormatter
    return sub.add_parser(name, help=summary, description=description, formatter_class=formatter)


def add_robot(parser: argparse.ArgumentParser, default: str) -> None:
    """The ``--robot`` option: the arm, one of :data:`~c3bf_gym.envs.reach.ROBOTS`."""
    from c3bf_gym.envs.reach import ROBOTS

    parser.add_argument("--robot", choices=list(ROBOTS), default=default,
                        help="the arm: ur5e (C3BFReach-v0's) or panda (C3BFReachPanda-v0's)")  # fmt: skip


def _add_train(sub: argparse._SubParsersAction) -> None:
    from c3bf_gym.scenarios import SCENARIOS
    from c3bf_gym.safety import GUARD_GAMMA
    from c3bf_gym.training import (ACTION_REACH, ACTION_WEIGHTS, ACTIONS, ALGORITHMS, DEFAULT_TIMESTEPS, ENGINE_DEFAULTS, ENGINES, OBSTACLE_ENCODERS,
                                   POLICY_RATES, RESIDUAL_FADE, TRAIN_FILTERS, TrainConfig)  # fmt: skip

    d = TrainConfig()  # the defaults live there

    def by_engine(name: str) -> str:
        return ", ".join(f"{e}: {ENGINE_DEFAULTS[e][name]}" for e in ENGINES)

    p = subcommand(
        sub, "train", "train one agent (Stable-Baselines3, or Ray RLlib with --engine rllib)",
        "Train PPO or SAC on C3BFReach-v0, with no filter or a named safety filter "
        "(c3bf_gym.FILTERS). Writes a run directory (config, model, per-episode metrics with the cumulative "
        "training cost, evaluations, tensorboard logs). --engine rllib trains RLlib PPO with --n-envs env "
        "runners on a local Ray instance, or on the cluster at --address (the rllib extra). With its "
        "defaults it trains the recipe of the README's RL table.", defaults=TrainConfig,
    )
    p.add_argument("--engine", choices=ENGINES, default=d.engine, help="training engine")
    p.add_argument("--address", default=None,
                   help="with --engine rllib: the Ray cluster to join (e.g. auto); default: a local Ray instance")  # fmt: skip
    p.add_argument("--algo", choices=ALGORITHMS, default=None, help=f"algorithm (default by engine: {by_engine('algo')})")
    add_robot(p, d.robot)
    p.add_argument("--action", choices=ACTIONS, default=d.action,
                   help="impedance: Cartesian tool targets through the impedance controller; residual: corrections "
                   "to a straight step for the goal, through the same controller; torque: raw joint torques")  # fmt: skip
    p.add_argument("--filter", choices=TRAIN_FILTERS, default=d.filter,
                   help="safety filter during training: 'c3bf+hocbf' (SafetyFilter's default: the C3BF with its "
                        "distance-HOCBF guard), 'c3bf' (the paper's C3BF alone), 'hocbf' or 'none'")  # fmt: skip
    p.add_argument("--guard-gamma", type=_positive_float, default=d.guard_gamma,
                   help=f"the guard's gains, gamma1 = gamma2 [1/s], with filter c3bf+hocbf (None: {GUARD_GAMMA:g})")
    add_filter_settings(p)
    p.add_argument("--scenario", choices=list(SCENARIOS), default=d.scenario, help="obstacle scenario")
    p.add_argument("--eval-scenario", choices=list(SCENARIOS), default=d.eval_scenario,
                   help="scenario of the periodic and final evaluations (default: the training scenario)")
    p.add_argument("--timesteps", type=_positive_int, default=None,
                   help=f"policy steps to train (default by algorithm: {', '.join(f'{a}: {n:,}' for a, n in DEFAULT_TIMESTEPS.items())})")
    p.add_argument("--seed", type=_nonnegative_int, default=d.seed, help="seed of the agent and the training envs")
    p.add_argument("--n-envs", type=_positive_int, default=d.n_envs,
                   help="parallel environments (SB3: SubprocVecEnv when > 1; RLlib: env runners)")  # fmt: skip
    p.add_argument("--eval-freq", type=_positive_int, default=d.eval_freq, help="evaluate every N timesteps")
    p.add_argument("--eval-episodes", type=_positive_int, default=d.eval_episodes, help="episodes per periodic evaluation")
    p.add_argument("--final-eval-episodes", type=_nonnegative_int, default=d.final_eval_episodes,
                   help="episodes of the final model's evaluation (final_eval.json; 0: none)")  # fmt: skip
    p.add_argument("--checkpoint-freq", type=_positive_int, default=d.checkpoint_freq, help="save a checkpoint every N timesteps")
    p.add_argument("--out", default=d.out, help="parent directory of the run directory")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--policy-hz", type=int, default=d.policy_hz, choices=POLICY_RATES,
                   help="actions per second (the physics and the filter stay at 500 Hz; episodes stay 5 s)")  # fmt: skip
    p.add_argument("--distance-weight", type=_nonnegative_float, default=d.distance_weight,
                   help="weight of the reward's dense -distance term (C3BFReachEnv's distance_weight; 0: off)")  # fmt: skip
    p.add_argument("--action-weight", type=_nonnegative_float, default=None,
                   help="weight of a -mean(action^2) reward term (ActionPenalty; keeps a residual policy near its prior; "
                        f"0: off; default by robot: {', '.join(f'{r}: {w:g}' for r, w in ACTION_WEIGHTS.items())})")  # fmt: skip
    p.add_argument("--obstacle-encoder", choices=OBSTACLE_ENCODERS, default=None,
                   help="how the policy reads the obstacle slots: flat (an MLP on the whole observation) or set "
                        "(one shared encoder per slot, pooled: c3bf_gym.policies.ObstacleSetExtractor; SB3 only) "
                        f"(default by engine: {by_engine('obstacle_encoder')})")  # fmt: skip
    p.add_argument("--normalize-obs", action="store_true",
                   help="normalise observations with running statistics (SB3 VecNormalize, saved with the model)")  # fmt: skip
    p.add_argument("--posture-stiffness", type=_nonnegative_float, default=d.posture_stiffness,
                   help="the impedance controller's null-space pull to home [N m/rad] (default: the arm's own, "
                        "20 on the UR5e, 2 on the Panda)")  # fmt: skip
    p.add_argument("--correction-weight", type=_nonnegative_float, default=0.0,
                   help="charge the safety filter's correction in the reward: -W * ||tau - tau_nom|| / ||tau_max|| "
                        "per step (c3bf_gym.wrappers.CorrectionPenalty; a filter only; default: 0, none)")  # fmt: skip
    p.add_argument("--posture-reach", type=_positive_float, default=None, metavar="RAD",
                   help="give the policy the controller's posture target too: one more action entry per joint, the "
                        "posture home + RAD * a (Cartesian actions only; default: the tool target only)")  # fmt: skip
    p.add_argument("--residual-fade", type=_nonnegative_float, default=None, metavar="M",
                   help="shrink the residual correction within M metres of the goal, in proportion to the distance "
                        f"(residual actions only; 0: never; default: {RESIDUAL_FADE:g})")  # fmt: skip
    p.add_argument("--action-reach", type=_positive_float, default=None, metavar="M",
                   help="how far one unit of a Cartesian action entry moves the tool target, and the most the "
                        f"residual's straight step for the goal moves it, per axis [m] (default: {ACTION_REACH:g})")  # fmt: skip
    p.add_argument("--modulate", action="store_true",
                   help="bend the residual action's straight step for the goal round the sensed obstacles "
                        "(c3bf_gym.controllers.modulate; residual actions only)")  # fmt: skip
    p.add_argument("--observe-correction", action="store_true",
                   help="append the filter's last correction to the observation (c3bf_gym.wrappers.FilterFeedback; "
                        "SB3 and a filter only)")  # fmt: skip
    p.add_argument("--observe-clearance", action="store_true",
                   help="append each arm geom's clearance to the obstacles to the observation "
                        "(c3bf_gym.wrappers.ArmClearance)")  # fmt: skip
    p.add_argument("--observe-contact-time", action="store_true",
                   help="append, per arm geom, how soon an obstacle would touch it at the present closing speed "
                        "(c3bf_gym.wrappers.ArmContactTime)")  # fmt: skip
    p.add_argument("--observe-forecast", action="store_true",
                   help="append the obstacles' clearance, moved ahead along their motion by 0.5-3 s, to the arm held "
                        "still and to the goal (c3bf_gym.wrappers.ArmForecast)")  # fmt: skip
    p.add_argument("--observe-time", action="store_true",
                   help="append the share of the episode's time used to the observation, and end each episode at "
                        "its time limit in SAC's replay buffer (c3bf_gym.wrappers.ElapsedTime; SB3 SAC only)")  # fmt: skip
    p.add_argument("--applied-action", action="store_true",
                   help="store the action the filter applied in the replay buffer, in place of the policy's (Cheng "
                        "et al. 2019; c3bf_gym.wrappers.AppliedAction; SAC, a filter and Cartesian actions only)")  # fmt: skip
    p.add_argument("--hyperparams", type=json.loads, default={},
                   help='JSON overriding the defaults, e.g. \'{"learning_rate": 1e-3}\'')  # fmt: skip
    p.set_defaults(func=_run_train)


def _run_train(args: argparse.Namespace) -> int:
    from c3bf_gym.training import ENGINE_DEFAULTS, TrainConfig, train

    defaults = ENGINE_DEFAULTS[args.engine]
    config = TrainConfig(
        engine=args.engine, algo=args.algo or defaults["algo"], robot=args.robot, action=args.action, filter=args.filter, guard_gamma=args.guard_gamma, filter_settings=dict(args.filter_set), scenario=args.scenario,
        eval_scenario=args.eval_scenario, timesteps=args.timesteps, seed=args.seed, n_envs=args.n_envs, eval_freq=args.eval_freq,
        eval_episodes=args.eval_episodes, final_eval_episodes=args.final_eval_episodes, checkpoint_freq=args.checkpoint_freq, out=args.out,
        progress_bar=not args.no_progress, normalize_obs=args.normalize_obs, policy_hz=args.policy_hz, distance_weight=args.distance_weight, action_weight=args.action_weight, obstacle_encoder=args.obstacle_encoder or defaults["obstacle_encoder"], hyperparams=args.hyperparams,
        observe_correction=args.observe_correction, posture_stiffness=args.posture_stiffness,
        posture_reach=args.posture_reach, correction_weight=args.correction_weight, residual_fade=args.residual_fade,
        action_reach=args.action_reach, observe_clearance=args.observe_clearance, residual_modulation=args.modulate, applied_action=args.applied_action,
        observe_time=args.observe_time, observe_contact_time=args.observe_contact_time,
        observe_forecast=args.observe_forecast,
    )  # fmt: skip
    run_dir = train(config, address=args.address)
    print(f"run written to {run_dir}")
    print((run_dir / "summary.json").read_text())
    return 0


def _add_evaluate(sub: argparse._SubParsersAction) -> None:
    from c3bf_gym.scenarios import SCENARIOS
    from c3bf_gym.training import FINAL_EVAL_SEED, TRAIN_FILTERS

    p = subcommand(
        sub, "evaluate", "evaluate a saved model",
        "Roll out a saved model for N seeded episodes: success rate, return, collisions "
        "(from the environment's geometric cost) and filter interventions. --filter evaluates a "
        "model under another filter than it was trained with (e.g. an unfiltered agent with the default filter on).",
    )
    p.add_argument("model", help="path to model.zip inside a run directory, or an RLlib run's checkpoint directory")
    p.add_argument("--episodes", type=_positive_int, default=50)
    p.add_argument("--filter", choices=TRAIN_FILTERS, default=None, help="default: the run's own")
    p.add_argument("--guard-gamma", type=_positive_float, default=None,
                   help="the guard's gains with filter c3bf+hocbf (default: the run's own, or the default gains with "
                        "--filter)")  # fmt: skip
    add_filter_settings(p, default=None, note=" (default: the run's own, or none with --filter)")
    p.add_argument("--scenario", choices=list(SCENARIOS), default=None, help="default: the run's own")
    p.add_argument("--residual-fade", type=_nonnegative_float, default=None, metavar="M",
                   help="the residual action's fade [m] (default: the run's own; 0: none)")
    p.add_argument("--seed", type=_nonnegative_int, default=FINAL_EVAL_SEED, help="seed of the first episode")
    p.add_argument("--per-episode", action="store_true",
                   help="add one record per episode: scenario, success, the tool's closest and final distance to the "
                        "goal, the nearest obstacle's clearance to the goal at the end")  # fmt: skip
    p.add_argument("--json", dest="json_out", default=None, help="also write the result to this JSON file")
    p.set_defaults(func=_run_evaluate)


def _run_evaluate(args: argparse.Namespace) -> int:
    from c3bf_gym.training import evaluate

    result = evaluate(args.model, args.episodes, args.filter, args.scenario, args.seed, guard_gamma=args.guard_gamma,
                      residual_fade=args.residual_fade, per_episode=args.per_episode,
                      filter_settings=None if args.filter_set is None else dict(args.filter_set))  # fmt: skip
    text = json.dumps(result, indent=2)
    print(text)
    if args.json_out:
        Path(args.json_out).write_text(text)
    return 0


def _add_plot_training(sub: argparse._SubParsersAction) -> None:
    from c3bf_gym.training import FINAL_EVAL_FILE

    p = subcommand(
        sub, "plot-training", "learning curves of several runs",
        "Plot return, success rate and cumulative training collisions against timesteps "
        "for run directories, grouped by filter (mean and min-max band over seeds).",
    )
    p.add_argument("runs", nargs="+", help="run directories (each with config.json and episodes.csv)")
    p.add_argument("--out", default="docs/results/training/training_curves.png")
    p.add_argument("--table", default=None, help="also write a summary table (markdown) here")
    p.add_argument("--evaluation", default=FINAL_EVAL_FILE,
                   help="the final models' numbers come from this file in each run directory: the run's own "
                   f"{FINAL_EVAL_FILE} (default) or a longer evaluation written there by "
                   "`c3bf-gym evaluate RUN/model.zip --episodes N --json RUN/FILE`")  # fmt: skip
    p.set_defaults(func=_run_plot_training)


def _run_plot_training(args: argparse.Namespace) -> int:
    from c3bf_gym.plots import plot_training

    table = plot_training([Path(r) for r in args.runs], Path(args.out), evaluation=args.evaluation)
    print(table)
    if args.table:
        Path(args.table).write_text(table + "\n")
    print(f"figure written to {args.out}")
    return 0


def _version() -> str:
    """The version of the installed ``c3bf-gym`` distribution (its package metadata), or the
    package's own ``c3bf_gym.__version__`` where no distribution is installed (a checkout on
    ``PYTHONPATH``)."""
    from importlib import metadata

    try:
        return metadata.version("c3bf-gym")
    except metadata.PackageNotFoundError:
        from c3bf_gym import __version__

        return __version__


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="c3bf-gym",
        description="Safe robot-arm RL with Collision Cone Control Barrier Functions: the paper's "
        "experiments, and Stable-Baselines3 baselines with and without the safety filter.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    from c3bf_gym.experiments import add_parser as add_experiments

    add_experiments(sub)
    _add_train(sub)
    _add_evaluate(sub)
    _add_plot_training(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except (ValueError, FileNotFoundError, ImportError) as error:  # ImportError: an extra not installed
        parser.exit(2, f"c3bf-gym {args.command}: error: {error}\n")


if __name__ == "__main__":
    sys.exit(main())
