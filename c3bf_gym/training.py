"""Training on ``C3BFReach-v0``, with and without the safety filter: Stable-Baselines3 runs here,
Ray RLlib runs in :mod:`c3bf_gym.rllib` (``TrainConfig.engine``), with the same run directory.

One run = one (algorithm, action mode, filter, scenario, seed). Its directory holds:

* ``config.json``: everything needed to reproduce it, including the command line;
* ``model.zip`` (final), ``checkpoints/``, ``best/`` (best evaluation), ``tb/`` (tensorboard);
* ``episodes.csv``: one row per finished training episode: ``timesteps, return, length, success,
  cost, interventions, infeasible, cumulative_cost`` (the headline: collisions summed over all
  training; ``infeasible``: the episode's steps whose QP had no solution, where the filter's
  guarantee does not hold);
* ``evaluations.npz``: SB3's periodic evaluation (returns and successes).

The wrapping order is explicit, not ``make_vec_env(wrapper_class=...)``: SB3 puts ``Monitor``
inside ``wrapper_class``, where it would not see the filter's info. Here ``Monitor`` is outermost.
"""

from __future__ import annotations

import csv
import importlib
import inspect
import json
import math
import os
import sys
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Callable, Literal

import gymnasium as gym
import numpy as np

from c3bf_gym import validation
from c3bf_gym.envs.reach import ROBOTS, observation_layout
from c3bf_gym.safety import DEFAULT_FILTER, FILTERS, FilterConfig
from c3bf_gym.safety.config import TOOL_ACCELERATION
from c3bf_gym.wrappers import (ActionPenalty, AppliedAction, ArmClearance, ArmContactTime, CartesianImpedanceAction,
                               ArmForecast, CorrectionPenalty, ElapsedTime, FilterFeedback, SafetyFilter, default_impedance)  # fmt: skip

__all__ = [
    "ACTIONS",
    "ACTION_WEIGHTS",
    "ALGORITHMS",
    "FILTERS",
    "FINAL_EVAL_FILE",
    "FINAL_EVAL_SEED",
    "HYPERPARAMS",
    "OBSTACLE_ENCODERS",
    "ENGINES",
    "RLLIB_PPO_HYPERPARAMS",
    "TrainConfig",
    "build_env",
    "by_scenario",
    "evaluate",
    "make_env",
    "train",
]

#: Seed of the first evaluation episode (``c3bf-gym evaluate`` and the final evaluation of a run);
#: training envs use ``1000 * seed + i`` and the periodic evaluation ``10_000 + seed``.
FINAL_EVAL_SEED = 100_000

#: The final model's evaluation in a run directory (``final_eval_episodes`` episodes from
#: ``FINAL_EVAL_SEED``; ``c3bf-gym evaluate --json``'s format).
FINAL_EVAL_FILE = "final_eval.json"

#: With ``normalize_obs``, the observation statistics saved beside ``model.zip`` (SB3's
#: ``VecNormalize``), and the clip applied to normalised observations.
NORMALIZATION_FILE = "vecnormalize.pkl"
OBS_CLIP = 10.0

#: The environment's physics rate, its registered policy rate and episode length.
PHYSICS_HZ, DEFAULT_POLICY_HZ, EPISODE_SECONDS = 500, 50, 5
#: Policy rates a run may use: each a whole number of physics steps per action.
POLICY_RATES = (10, 20, 25, 50, 100)
#: The training default: 10 actions per second (the controller and the filter still run at
#: 500 Hz): each decision moves the tool visibly, and an episode is 50 decisions instead of 250.
#: Why (measured): the docs' design decisions, "Training defaults".
DEFAULT_TRAIN_HZ = 10

ALGORITHMS = ("sac", "ppo")
#: Each algorithm's training budget in env (policy) steps, when a run names none: SAC learns
#: from every sample through its replay buffer, PPO's samples are cheap and it needs more of
#: them. Why these (measured): the docs' RL results page, "PPO: its own budget".
DEFAULT_TIMESTEPS = {"sac": 25_000, "ppo": 100_000}
#: The residual action's fade [m] when a run names none: the correction shrinks in proportion
#: within this distance of the goal (:class:`~c3bf_gym.wrappers.CartesianImpedanceAction`'s
#: ``fade``, here its ``max_offset``), so a policy's small bias cannot hold the tool off the goal.
#: Why (measured): the docs' RL results page, "Holding the goal".
RESIDUAL_FADE = 0.1
#: The Cartesian action's reach [m] when a run names none: one unit of an action entry moves the
#: impedance controller's target this far (:class:`~c3bf_gym.wrappers.CartesianImpedanceAction`'s
#: ``max_offset``), and the residual action's straight step for the goal is clipped to it.
ACTION_REACH = 0.1
#: The reward's action penalty (:class:`~c3bf_gym.wrappers.ActionPenalty`'s weight) per arm when a
#: run names none; an arm not listed gets the UR5e's. It makes a residual correction pay for
#: itself. The Panda's is dearer: with it its filtered SAC agents came within 0.03 of its unfiltered
#: ones in every scenario (``multi`` 0.92 against 0.88 at 3), while on the UR5e it lowered
#: ``multi``. Why (measured): the docs' RL results page, "A dearer correction on the Panda".
ACTION_WEIGHTS = {"ur5e": 3.0, "panda": 10.0}
#: Training engines: Stable-Baselines3 on one machine, or Ray RLlib (PPO on its new API stack,
#: env runners on a local Ray instance or a cluster; :mod:`c3bf_gym.rllib`, the ``rllib`` extra).
ENGINES = ("sb3", "rllib")
#: What each engine trains unless told otherwise: RLlib runs PPO with its default MLP encoder
#: (the set encoder is an SB3 feature extractor).
ENGINE_DEFAULTS = {"sb3": {"algo": "sac", "obstacle_encoder": "set"}, "rllib": {"algo": "ppo", "obstacle_encoder": "flat"}}
ACTIONS = ("impedance", "residual", "torque")
#: A run's ``filter``: "none" or a name of :data:`~c3bf_gym.safety.FILTERS` (the default
#: :data:`~c3bf_gym.safety.DEFAULT_FILTER`, the C3BF with its distance-HOCBF guard).
TRAIN_FILTERS = ("none", *FILTERS)


#: How to install what Stable-Baselines3 runs need (the README's Install section): a CPU torch
#: first, or pip may pull a multi-GB CUDA build.
_TRAIN_EXTRA = ('install a CPU torch first, pip install torch --index-url https://download.pytorch.org/whl/cpu, '
               'then pip install "c3bf-gym[train]"')


def _require_train_extra(*modules: str, purpose: str = "training with Stable-Baselines3") -> None:
    """Import the top-level ``modules`` (of the ``train`` extra and what it depends on).

    Raises:
        ImportError: one or more of them is not installed; the message names them and how to
            install the extra (:data:`_TRAIN_EXTRA`). A module that fails to import for another
            reason raises its own error.
    """
    missing = []
    for module in modules:
        try:
            importlib.import_module(module)
        except ModuleNotFoundError as error:  # this module, or another of them that it imports
            name = (error.name or "").partition(".")[0]
            if name not in modules:
                raise
            if name not in missing:
                missing.append(name)
    if missing:
        raise ImportError(f"{purpose} needs {', '.join(missing)}, not installed here: {_TRAIN_EXTRA}")


#: The FilterConfig fields a run's ``filter_settings`` may not change: the filter's name says them,
#: and ``guard_gamma`` has its own option.
_NAMED_SETTINGS = ("barrier", "guard", "guard_gamma")


def filter_config(filter: str | FilterConfig | None, guard_gamma: float | None = None,
                  settings: dict[str, Any] | None = None) -> FilterConfig | None:
    """The :class:`~c3bf_gym.safety.FilterConfig` a run's filter names (None for ``"none"`` or
    None), with ``guard_gamma`` the guard's gains (None: the default; only with a guard) and
    ``settings`` changes to its other fields (e.g. ``{"allowance_level": True}``; None or empty:
    none).

    Raises:
        ValueError: an unknown filter name; ``guard_gamma`` or ``settings`` without a filter;
            a setting that is not a FilterConfig field, names the filter's rows (``barrier``,
            ``guard``: choose the filter; ``guard_gamma``: its own argument), is not a JSON
            scalar (a run records its settings in ``config.json``), or that the filter refuses.
    """
    settings = dict(settings or {})
    if not (all(isinstance(key, str) for key in settings)
            and all(value is None or isinstance(value, (bool, int, float, str)) for value in settings.values())):
        raise ValueError(f"filter settings must map FilterConfig field names to numbers, booleans, text or None, "
                         f"got {settings!r}")  # fmt: skip
    named = sorted(set(settings) & set(_NAMED_SETTINGS))
    if named:
        raise ValueError(f"filter setting(s) {', '.join(map(repr, named))} are chosen by the filter's name "
                         f"({', '.join(map(repr, FILTERS))}) and guard_gamma, not by the filter's settings")  # fmt: skip
    if isinstance(filter, FilterConfig):
        changes = settings | ({} if guard_gamma is None else {"guard_gamma": guard_gamma})
        return filter.replace(**changes)
    if filter in (None, "none"):
        for what, given in (("guard_gamma was", guard_gamma is not None), ("filter settings were", bool(settings))):
            if given:
                raise ValueError(f"{what} given without a filter (filter={filter!r})")
        return None
    if not (isinstance(filter, str) and filter in FILTERS):
        raise ValueError(f"unknown filter {filter!r}; valid choices: {', '.join(map(repr, TRAIN_FILTERS))}")
    return FilterConfig.named(filter, guard_gamma=guard_gamma, **settings)


def filter_label(filter: str | FilterConfig | None, guard_gamma: float | None = None,
                 settings: dict[str, Any] | None = None) -> str:
    """A run's filter as its name and the training tables spell it: ``"none"``, or the
    configuration's :attr:`~c3bf_gym.safety.FilterConfig.name` (``"c3bf+hocbf20"`` for the guard
    with gains 20) followed by the settings that differ from that named filter's, in brackets, in
    the fields' order (``"c3bf+hocbf[joint_range_reserve=0.3,allowance_level=true]"``).

    Raises:
        ValueError: as :func:`filter_config`, or for a filter built on Barrier instances (it has
            no name)."""
    config = filter_config(filter, guard_gamma, settings)
    if config is None:
        return "none"
    if config.name is None:
        raise ValueError("a filter built on Barrier instances has no name to label a run with")
    if config.tool_acceleration == TOOL_ACCELERATION:  # what None reads as: one filter, one label
        config = config.replace(tool_acceleration=None)
    rows = FilterConfig(barrier=config.barrier, guard=config.guard, guard_gamma=config.guard_gamma)
    changed = [f"{field.name}={_setting_text(getattr(config, field.name))}" for field in fields(config)
               if getattr(config, field.name) != getattr(rows, field.name)]  # fmt: skip
    return config.name + (f"[{','.join(changed)}]" if changed else "")


def _setting_text(value: Any) -> str:
    """A filter setting's value as a label spells it (and ``--filter-set`` reads it back)."""
    if isinstance(value, bool) or value is None:
        return str(value).lower()
    if isinstance(value, float):
        short = f"{value:g}"
        return short if float(short) == value else repr(value)  # exact, where 6 digits are not
    return str(value)


#: How the policy network reads the obstacle slots: ``flat`` (SB3's MLP on the whole
#: observation) or ``set`` (:class:`~c3bf_gym.policies.ObstacleSetExtractor`: one shared encoder
#: per obstacle slot, pooled, so what is learnt about one slot holds for every slot).
OBSTACLE_ENCODERS = ("flat", "set")

#: Default hyperparameters per (algorithm, action mode): SB3 / RL-Zoo defaults for continuous
#: control, with one env per SAC run, a 256x256 MLP with batch 128, a discount of 0.98, SAC's
#: entropy coefficient starting at 0.1, 1000 random steps before learning for the Cartesian
#: modes, and PPO with RL-Zoo's MuJoCo settings; raw observations. Why each (measured): the docs'
#: design decisions, "Training defaults".
HYPERPARAMS: dict[tuple[str, str], dict[str, Any]] = {
    ("sac", "impedance"): dict(
        learning_rate=3e-4, buffer_size=300_000, batch_size=128, gamma=0.98, tau=0.005, ent_coef="auto_0.1",
        learning_starts=1_000, train_freq=1, gradient_steps=1, policy_kwargs=dict(net_arch=[256, 256]),
    ),
    ("sac", "residual"): dict(
        learning_rate=3e-4, buffer_size=300_000, batch_size=128, gamma=0.98, tau=0.005, ent_coef="auto_0.1",
        learning_starts=1_000, train_freq=1, gradient_steps=1, policy_kwargs=dict(net_arch=[256, 256]),
    ),
    ("sac", "torque"): dict(
        learning_rate=3e-4, buffer_size=300_000, batch_size=128, gamma=0.98, tau=0.005, ent_coef="auto_0.1",
        learning_starts=5_000, train_freq=1, gradient_steps=1, policy_kwargs=dict(net_arch=[256, 256]),
    ),
    ("ppo", "impedance"): dict(
        learning_rate=3e-4, n_steps=1024, batch_size=64, n_epochs=10, gamma=0.98, gae_lambda=0.95,
        clip_range=0.2, ent_coef=0.0, policy_kwargs=dict(net_arch=dict(pi=[256, 256], vf=[256, 256])),
    ),
    ("ppo", "residual"): dict(
        learning_rate=3e-4, n_steps=1024, batch_size=64, n_epochs=10, gamma=0.98, gae_lambda=0.95,
        clip_range=0.2, ent_coef=0.0, policy_kwargs=dict(net_arch=dict(pi=[256, 256], vf=[256, 256])),
    ),
    ("ppo", "torque"): dict(
        learning_rate=3e-4, n_steps=1024, batch_size=64, n_epochs=10, gamma=0.98, gae_lambda=0.95,
        clip_range=0.2, ent_coef=0.0, policy_kwargs=dict(net_arch=dict(pi=[256, 256], vf=[256, 256])),
    ),
}  # fmt: skip

#: RLlib PPO's defaults, as ``PPOConfig.training`` keywords (plus ``fcnet_hiddens``, the policy and
#: value networks): SB3 PPO's settings above, spelt for RLlib. SB3 has no KL penalty and no value
#: clipping, so neither has this; its batch of ``n_steps`` per env is
#: ``train_batch_size_per_env · n_envs`` here.
RLLIB_PPO_HYPERPARAMS: dict[str, Any] = dict(
    lr=3e-4, train_batch_size_per_env=1024, minibatch_size=64, num_epochs=10, gamma=0.98, lambda_=0.95,
    clip_param=0.2, entropy_coeff=0.0, use_kl_loss=False, vf_clip_param=float("inf"), fcnet_hiddens=[256, 256],
)  # fmt: skip


@dataclass
class TrainConfig:
    """One training run. ``filter`` is one of :data:`TRAIN_FILTERS`, ``guard_gamma`` the
    guard's gains where the filter has one (None: :data:`~c3bf_gym.safety.GUARD_GAMMA`) and
    ``filter_settings`` changes to the filter's other :class:`~c3bf_gym.safety.FilterConfig`
    fields (e.g. ``{"allowance_level": True}``; recorded in ``config.json``, named in the run's
    name and rebuilt by :func:`evaluate`).

    The defaults are the recipe of the README's RL table (the one place they are kept; the
    command line takes them from here): SAC, residual Cartesian actions at 10 Hz that fade within
    0.1 m of the goal (``residual_fade``), the reward's distance term (``distance_weight=10``) and
    action penalty (``action_weight``: the arm's, :data:`ACTION_WEIGHTS`), the set encoder for the
    obstacle slots, 25k steps. Each was chosen by measured runs (the docs' RL results page,
    ``docs/results/rl.md``). PPO shares the actions, reward and encoder, with RL-Zoo's MuJoCo
    settings (:data:`HYPERPARAMS`) and its own budget (of the README's RLlib PPO rows, the Panda's
    and the UR5e's unfiltered one were trained before the fade and the Panda's weight).

    ``timesteps`` None (the default) is the algorithm's budget, :data:`DEFAULT_TIMESTEPS`
    (SAC 25k, PPO 100k); it is resolved when the config is made, so ``config.timesteps`` and the
    run's ``config.json`` hold the number.

    ``eval_scenario`` is the scenario of the periodic and the final evaluations (None: the training
    scenario): a run trained on a weighted mixture such as ``random_multi`` is evaluated on the
    same episodes as every other run (``random``).

    ``posture_stiffness`` is the nominal impedance controller's null-space pull to home [N m/rad]
    for the Cartesian action modes (None: the arm's own,
    :attr:`~c3bf_gym.envs.reach.ReachRobot.posture_stiffness`).

    ``observe_correction`` appends the filter's last correction to the observation
    (:class:`~c3bf_gym.wrappers.FilterFeedback`; SB3 and a filter only).

    ``observe_clearance`` appends each arm geom's clearance to the obstacles to the observation
    (:class:`~c3bf_gym.wrappers.ArmClearance`, saturating at 0.5 m).

    ``observe_contact_time`` appends, per arm geom, how soon an obstacle would touch it at the
    present closing speed (:class:`~c3bf_gym.wrappers.ArmContactTime`, saturating at 2 s).

    ``observe_forecast`` appends the obstacles' clearance, moved ahead along their present
    motion by 0.5 to 3 s, to the arm held in its present pose and to the goal
    (:class:`~c3bf_gym.wrappers.ArmForecast`).

    ``observe_time`` appends the share of the episode's time already used
    (:class:`~c3bf_gym.wrappers.ElapsedTime`) and makes SAC's replay buffer end each episode at its
    time limit instead of bootstrapping past it (``handle_timeout_termination=False``): an episode
    judged at its last step is then a finite-horizon task the critic sees whole (SB3 SAC only; off
    by default).

    ``applied_action`` stores the action the filter applied in the replay buffer in place of
    the policy's (:class:`~c3bf_gym.wrappers.AppliedAction`,
    :class:`~c3bf_gym.replay.AppliedActionReplayBuffer`; the action penalty then charges it too;
    SAC, a filter and Cartesian actions only; off by default).

    ``correction_weight`` charges the safety filter's correction in the reward
    (:class:`~c3bf_gym.wrappers.CorrectionPenalty`; a filter only; 0, the default: none).

    ``posture_reach`` [rad] gives the policy the impedance controller's posture target too: the
    action gets one entry per joint, the posture ``q_home + posture_reach * a[3:]``
    (:class:`~c3bf_gym.wrappers.CartesianImpedanceAction`'s ``posture_reach``; Cartesian action
    modes only; None, the default: the tool target only).

    ``action_reach`` [m] is the Cartesian action's reach: one unit of an action entry moves the
    impedance controller's target that far along its axis, and the residual action's straight
    step for the goal is clipped to it (:class:`~c3bf_gym.wrappers.CartesianImpedanceAction`'s
    ``max_offset``; Cartesian action modes only). None (the default) is :data:`ACTION_REACH`,
    resolved when the config is made like ``timesteps``.

    ``residual_modulation`` bends the residual action's straight step for the goal round the
    sensed obstacles (:class:`~c3bf_gym.wrappers.CartesianImpedanceAction`'s ``modulate``;
    residual actions only; off by default).

    ``action_weight`` None (the default) is the arm's, :data:`ACTION_WEIGHTS` (UR5e 3, Panda 10),
    resolved when the config is made like ``timesteps``.

    ``residual_fade`` [m] shrinks the residual correction within that distance of the goal
    (:class:`~c3bf_gym.wrappers.CartesianImpedanceAction`'s ``fade``; residual actions only, 0:
    never). None (the default) is :data:`RESIDUAL_FADE` for residual actions, resolved when the
    config is made like ``timesteps``; runs from before the option had none (0).

    ``engine="rllib"`` trains with Ray RLlib instead (:func:`c3bf_gym.rllib.train_rllib`): PPO
    only, the flat encoder only, no ``normalize_obs``; ``n_envs`` env runners, one env each.
    """

    engine: Literal["sb3", "rllib"] = "sb3"
    algo: Literal["sac", "ppo"] = "sac"
    robot: str = "ur5e"
    action: Literal["impedance", "residual", "torque"] = "residual"
    filter: str = DEFAULT_FILTER
    guard_gamma: float | None = None
    filter_settings: dict[str, Any] = field(default_factory=dict)
    scenario: str = "random"
    eval_scenario: str | None = None
    timesteps: int | None = None
    seed: int = 0
    n_envs: int = 1
    eval_freq: int = 10_000
    eval_episodes: int = 10
    final_eval_episodes: int = 50
    checkpoint_freq: int = 20_000
    out: str = "runs"
    progress_bar: bool = True
    normalize_obs: bool = False
    policy_hz: int = DEFAULT_TRAIN_HZ
    distance_weight: float = 10.0
    action_weight: float | None = None
    obstacle_encoder: Literal["flat", "set"] = "set"
    observe_correction: bool = False
    observe_clearance: bool = False
    observe_contact_time: bool = False
    observe_forecast: bool = False
    observe_time: bool = False
    posture_stiffness: float | None = None
    posture_reach: float | None = None
    correction_weight: float = 0.0
    residual_fade: float | None = None
    action_reach: float | None = None
    residual_modulation: bool = False
    applied_action: bool = False
    hyperparams: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.timesteps is None and self.algo in DEFAULT_TIMESTEPS:  # an unknown algo: validate() names it
            self.timesteps = DEFAULT_TIMESTEPS[self.algo]
        if self.residual_fade is None and self.action == "residual":
            self.residual_fade = RESIDUAL_FADE
        if self.action_reach is None and self.action in ("impedance", "residual"):
            self.action_reach = ACTION_REACH
        if self.action_weight is None:
            self.action_weight = ACTION_WEIGHTS.get(self.robot, ACTION_WEIGHTS["ur5e"])

    def validate(self) -> None:
        from c3bf_gym.scenarios import get_scenario

        for name, value, choices in (
            ("engine", self.engine, ENGINES),
            ("algo", self.algo, ALGORITHMS),
            ("action", self.action, ACTIONS),
            ("filter", self.filter, TRAIN_FILTERS),
            ("obstacle_encoder", self.obstacle_encoder, OBSTACLE_ENCODERS),
            ("robot", self.robot, tuple(ROBOTS)),
        ):
            if value not in choices:
                raise ValueError(f"unknown {name} {value!r}; valid choices: {', '.join(map(repr, choices))}")
        if self.engine == "rllib":
            for name, value, supported in (("algo", self.algo, "ppo"), ("obstacle_encoder", self.obstacle_encoder, "flat"),
                                           ("normalize_obs", self.normalize_obs, False),
                                           ("observe_correction", self.observe_correction, False)):  # fmt: skip
                if value != supported:
                    raise ValueError(f"the rllib engine supports {name}={supported!r} only, got {value!r}")
        get_scenario(self.scenario)
        if self.eval_scenario is not None:
            get_scenario(self.eval_scenario)
        policy_rate_kwargs(self.policy_hz)
        filter_ = self.filter_config()  # the filter's own checks, guard_gamma's and the settings' included
        for name in ("distance_weight", "action_weight", "correction_weight"):
            validation.number(name, getattr(self, name), low=0.0)
        if self.posture_stiffness is not None:
            validation.number("posture_stiffness", self.posture_stiffness, low=0.0)
            if self.action == "torque":
                raise ValueError("posture_stiffness sets the impedance controller of the Cartesian action modes "
                                 "('impedance', 'residual'); this run's action is 'torque'")  # fmt: skip
        if self.posture_reach is not None:
            validation.number("posture_reach", self.posture_reach, low=0.0, low_open=True)
            if self.action == "torque":
                raise ValueError("posture_reach moves the impedance controller's posture target, in the Cartesian "
                                 "action modes ('impedance', 'residual'); this run's action is 'torque'")  # fmt: skip
        _residual_fade_or_none(self.residual_fade, self.action)
        _action_reach(self.action_reach, self.action)
        if not (isinstance(self.hyperparams, dict) and all(isinstance(key, str) for key in self.hyperparams)):
            raise ValueError(f"hyperparams must be a dict of keyword arguments, got {self.hyperparams!r}")
        for name in ("normalize_obs", "observe_correction", "observe_clearance", "observe_contact_time",
                     "observe_forecast", "observe_time", "residual_modulation", "applied_action"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be True or False, got {getattr(self, name)!r}")
        _check_residual_modulation(self.residual_modulation, self.action)
        _check_applied_action(self.applied_action, self.action)
        for name, use in (("applied_action", "relabels the actions of an off-policy replay buffer"),
                          ("observe_time", "ends each episode at its time limit in an off-policy replay buffer")):
            if getattr(self, name) and (self.engine, self.algo) != ("sb3", "sac"):
                raise ValueError(f"{name} {use}: it needs engine='sb3' and algo='sac', got engine={self.engine!r}, "
                                 f"algo={self.algo!r}")  # fmt: skip
        for name, use in (("correction_weight", "charges"), ("observe_correction", "observes"),
                          ("applied_action", "maps back")):
            if getattr(self, name) and filter_ is None:
                raise ValueError(f"{name} {use} the safety filter's correction: it needs a filter "
                                 f"(one of {', '.join(map(repr, FILTERS))}), got filter={self.filter!r}")  # fmt: skip
        for name in ("timesteps", "n_envs", "eval_freq", "eval_episodes", "checkpoint_freq"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        for name in ("seed", "final_eval_episodes"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"{name} must be an integer >= 0, got {value!r}")

    @property
    def name(self) -> str:
        norm = "_norm" if self.normalize_obs else ""
        rate = "" if self.policy_hz == DEFAULT_POLICY_HZ else f"_{self.policy_hz}hz"
        dense = f"_dw{self.distance_weight:g}" if self.distance_weight else ""
        penalty = f"_aw{self.action_weight:g}" if self.action_weight else ""
        encoder = "" if self.obstacle_encoder == "flat" else f"_{self.obstacle_encoder}"
        encoder += "_oc" if self.observe_correction else ""
        encoder += "_cl" if self.observe_clearance else ""
        encoder += "_ct" if self.observe_contact_time else ""
        encoder += "_fc" if self.observe_forecast else ""
        encoder += "_time" if self.observe_time else ""
        encoder += "" if self.posture_stiffness is None else f"_ps{self.posture_stiffness:g}"
        encoder += "" if self.posture_reach is None else f"_pr{self.posture_reach:g}"
        encoder += f"_cw{self.correction_weight:g}" if self.correction_weight else ""
        encoder += f"_fade{self.residual_fade:g}" if self.residual_fade else ""
        encoder += "" if self.action_reach in (None, ACTION_REACH) else f"_reach{self.action_reach:g}"
        encoder += "_mod" if self.residual_modulation else ""
        encoder += "_applied" if self.applied_action else ""
        robot = "" if self.robot == "ur5e" else f"{self.robot}_"  # UR5e runs keep their earlier names
        engine = "" if self.engine == "sb3" else f"{self.engine}_"
        return (
            f"{engine}{robot}{self.algo}_{self.action}{norm}{rate}{dense}{penalty}{encoder}_{filter_label(self.filter, self.guard_gamma, self.filter_settings)}"
            f"_{self.scenario}_s{self.seed}"
        )

    def filter_config(self) -> FilterConfig | None:
        """The run's safety filter: ``filter`` with ``guard_gamma`` and ``filter_settings``
        (:func:`filter_config`); None for ``"none"``."""
        return filter_config(self.filter, self.guard_gamma, self.filter_settings)

    @property
    def evaluated_scenario(self) -> str:
        """The scenario of the periodic and the final evaluations: ``eval_scenario``, or the
        training scenario when that is None."""
        return self.scenario if self.eval_scenario is None else self.eval_scenario

    def env_kwargs(self) -> dict[str, Any]:
        """``gym.make`` keywords: the policy rate (the episode stays ``EPISODE_SECONDS`` long), the
        reward's dense distance term and the robot."""
        return env_kwargs(self.policy_hz, self.distance_weight, self.robot)

    def env_options(self) -> dict[str, Any]:
        """:func:`build_env`'s keywords for this run's environments, all but the scenario: the
        filter (:meth:`filter_config`), the action mode, the wrappers' options and
        :meth:`env_kwargs`. Every engine builds its environments from these, so an option added
        to the run reaches them all by being added here."""
        return dict(filter=self.filter_config(), action=self.action, action_weight=self.action_weight,
                    observe_correction=self.observe_correction, posture_stiffness=self.posture_stiffness,
                    residual_fade=self.residual_fade, posture_reach=self.posture_reach,
                    action_reach=self.action_reach, correction_weight=self.correction_weight, observe_clearance=self.observe_clearance,
                    observe_contact_time=self.observe_contact_time, observe_forecast=self.observe_forecast,
                    observe_time=self.observe_time, residual_modulation=self.residual_modulation,
                    applied_action=self.applied_action,
                    **self.env_kwargs())  # fmt: skip

    def resolved_hyperparams(self) -> dict[str, Any]:
        """The engine's defaults for this algorithm and action mode, with ``hyperparams`` over them."""
        defaults = RLLIB_PPO_HYPERPARAMS if self.engine == "rllib" else HYPERPARAMS[(self.algo, self.action)]
        return {**defaults, **self.hyperparams}


def env_kwargs(policy_hz: int, distance_weight: float = 0.0, robot: str = "ur5e") -> dict[str, Any]:
    """``gym.make`` keywords of a run: :func:`policy_rate_kwargs`, plus ``distance_weight`` when set
    and ``robot`` (:data:`~c3bf_gym.envs.ROBOTS`) when not the UR5e."""
    return {**policy_rate_kwargs(policy_hz), **({"distance_weight": distance_weight} if distance_weight else {}),
            **({"robot": robot} if robot != "ur5e" else {})}


def policy_rate_kwargs(hz: int) -> dict[str, int]:
    """``frame_skip`` and ``max_episode_steps`` for a policy acting ``hz`` times per second on
    the 500 Hz physics, with episodes of ``EPISODE_SECONDS``; ValueError names the valid rates."""
    if isinstance(hz, bool) or not isinstance(hz, int) or hz not in POLICY_RATES:
        raise ValueError(f"policy_hz must be one of {', '.join(map(str, POLICY_RATES))} (divisors of the "
                         f"{PHYSICS_HZ} Hz physics), got {hz!r}")  # fmt: skip
    return {"frame_skip": PHYSICS_HZ // hz, "max_episode_steps": EPISODE_SECONDS * hz}


def info_keywords(filter: str | FilterConfig | None) -> tuple[str, ...]:
    """The per-episode keys ``Monitor`` records for a run with this filter."""
    keys = ("is_success", "episode_cost")
    return keys + ("episode_interventions", "episode_infeasible") if filter_config(filter) else keys


def _residual_fade_or_none(value: float | None, action: str) -> float | None:
    """``value`` as the residual action's fade [m], None for none (None or 0).

    Raises:
        ValueError: not a finite number >= 0, or a fade with another action mode than residual.
    """
    if value is None:
        return None
    fade = validation.number("residual_fade", value, low=0.0, unit="m")
    if fade and action != "residual":
        raise ValueError(f"residual_fade shrinks the residual correction near the goal; action={action!r} "
                         "(valid with 'residual' only)")  # fmt: skip
    return fade or None


def _action_reach(value: float | None, action: str) -> float:
    """``value`` as the Cartesian action's reach [m] (None: :data:`ACTION_REACH`).

    Raises:
        ValueError: not a finite number > 0, or given with torque actions (which have no reach).
    """
    if value is None:
        return ACTION_REACH
    reach = validation.number("action_reach", value, low=0.0, low_open=True, unit="m")
    if action not in ("impedance", "residual"):
        raise ValueError(f"action_reach scales the Cartesian actions' tool target; action={action!r} "
                         "(valid with 'impedance' and 'residual' only)")  # fmt: skip
    return reach


def _check_applied_action(applied: bool, action: str) -> None:
    """ValueError for ``applied_action`` with torque actions (it maps the correction back to a tool target)."""
    if applied and action not in ("impedance", "residual"):
        raise ValueError("applied_action maps the filter's correction back to a tool target: it needs a Cartesian "
                         f"action ('impedance', 'residual'), got {action!r}")  # fmt: skip


def _check_residual_modulation(modulate: bool, action: str) -> None:
    """ValueError for ``residual_modulation`` with another action mode than residual."""
    if modulate and action != "residual":
        raise ValueError("residual_modulation bends the residual action's straight step for the goal: it needs "
                         f"action='residual', got {action!r}")  # fmt: skip


def build_env(
    scenario: str = "random",
    filter: str | FilterConfig | None = DEFAULT_FILTER,
    action: str = "impedance",
    action_weight: float = 0.0,
    guard_gamma: float | None = None,
    observe_correction: bool = False,
    posture_stiffness: float | None = None,
    residual_fade: float | None = None,
    posture_reach: float | None = None,
    action_reach: float | None = None,
    correction_weight: float = 0.0,
    observe_clearance: bool = False,
    observe_contact_time: bool = False,
    observe_forecast: bool = False,
    observe_time: bool = False,
    residual_modulation: bool = False,
    applied_action: bool = False,
    **env_kwargs: Any,
) -> gym.Env:
    """``ActionPenalty(AppliedAction(CorrectionPenalty(ElapsedTime(ArmForecast(ArmContactTime(
    ArmClearance(FilterFeedback(SafetyFilter(CartesianImpedanceAction(C3BFReach-v0))))))))))``, the
    parts the options ask for (``ActionPenalty`` when ``action_weight > 0``, charging the applied
    action with ``applied_action``, ``AppliedAction`` with ``applied_action``, ``CorrectionPenalty``
    when ``correction_weight > 0``, ``ElapsedTime`` with ``observe_time``, ``ArmForecast`` with
    ``observe_forecast``, ``ArmContactTime`` with ``observe_contact_time``, ``ArmClearance`` with
    ``observe_clearance``, ``FilterFeedback`` with ``observe_correction``): the environment every
    training engine steps. ``filter``: "none"/None, a name of :data:`~c3bf_gym.safety.FILTERS` or a
    :class:`~c3bf_gym.safety.FilterConfig`; ``guard_gamma``: the guard's gains where it has one
    (None: the default); ``posture_stiffness``: the impedance controller's null-space pull [N m/rad]
    (None: the arm's own, :func:`~c3bf_gym.wrappers.default_impedance`); ``residual_fade``: the
    residual action's ``fade`` [m] (None or 0: none); ``posture_reach``: the action's posture
    entries [rad] (None: none); ``action_reach``: the Cartesian action's ``max_offset`` [m] (None:
    :data:`ACTION_REACH`); ``correction_weight``: the weight of the filter's correction in the
    reward (0: none); ``residual_modulation``: the residual action's ``modulate``;
    ``applied_action``: put the action the filter applied in ``info``; ``env_kwargs`` go to
    ``gym.make`` (:func:`env_kwargs`).

    Raises:
        ValueError: an unknown filter or action mode, ``observe_correction`` or
            ``correction_weight`` without a filter, ``posture_stiffness`` or ``posture_reach``
            with torque actions, an ``action_reach`` that is not a finite number > 0 or is given
            with torque actions, a ``residual_fade`` that is not a finite number >= 0 or is given
            with other than residual actions, ``residual_modulation`` with other than residual
            actions, ``applied_action`` without a filter or with torque actions, or bad environment
            keywords.
    """
    config = filter_config(filter, guard_gamma)
    validation.choice("action", action, ACTIONS)
    fade = _residual_fade_or_none(residual_fade, action)
    _check_residual_modulation(residual_modulation, action)
    _check_applied_action(applied_action, action)
    reach = _action_reach(action_reach, action)
    env = gym.make("C3BFReach-v0", scenario=scenario, **env_kwargs)
    if action in ("impedance", "residual"):
        controller = None if posture_stiffness is None else default_impedance(env.unwrapped, posture_stiffness)
        env = CartesianImpedanceAction(env, reach, controller=controller, residual=action == "residual", fade=fade,
                                       posture_reach=posture_reach, modulate=residual_modulation)  # fmt: skip
    else:
        for name, value in (("posture_stiffness", posture_stiffness), ("posture_reach", posture_reach)):
            if value is not None:
                raise ValueError(f"{name} sets the impedance controller of the Cartesian action modes; "
                                 f"action={action!r}")  # fmt: skip
    if config is not None:
        env = SafetyFilter(env, config)
    if observe_correction:
        env = FilterFeedback(env)  # refuses an environment without a filter
    if observe_clearance:
        env = ArmClearance(env)
    if observe_contact_time:
        env = ArmContactTime(env)
    if observe_forecast:
        env = ArmForecast(env)
    if observe_time:
        env = ElapsedTime(env)
    if correction_weight:
        env = CorrectionPenalty(env, correction_weight)  # refuses an environment without a filter too
    if applied_action:
        env = AppliedAction(env)  # refuses an environment without a filter too
    if action_weight:
        env = ActionPenalty(env, action_weight, charge="applied" if applied_action else "policy")
    return env


def make_env(scenario: str = "random", filter: str | FilterConfig | None = DEFAULT_FILTER, action: str = "impedance",
             seed: int = 0, monitor_file: str | None = None, guard_gamma: float | None = None,
             **options: Any) -> Callable[[], gym.Env]:
    """A thunk building ``Monitor(build_env(scenario, filter, action, **options))`` for SB3 vector
    envs, seeded ``seed`` on its first reset; ``options`` are :func:`build_env`'s other keywords.
    A run's environments are ``make_env(config.scenario, seed=..., **config.env_options())``
    (:meth:`TrainConfig.env_options`). The filter (with ``guard_gamma``) and the action mode are
    checked here, before any env is built."""
    from stable_baselines3.common.monitor import Monitor

    config = filter_config(filter, guard_gamma)
    validation.choice("action", action, ACTIONS)

    def thunk() -> gym.Env:
        env = Monitor(build_env(scenario, config, action, **options), monitor_file, info_keywords=info_keywords(config))
        env.reset(seed=seed)
        env.action_space.seed(seed)
        return env

    return thunk


def _episode_logger():
    from stable_baselines3.common.callbacks import BaseCallback

    class EpisodeLogger(BaseCallback):
        """Writes ``episodes.csv`` and logs cumulative training cost (collision steps)."""

        def __init__(self, path: Path) -> None:
            super().__init__()
            self.path = path
            self.cumulative_cost = 0.0
            self.episodes = 0
            self._file = None
            self._writer = None

        def _on_training_start(self) -> None:
            self._file = open(self.path, "w", newline="")
            self._writer = csv.writer(self._file)
            self._writer.writerow(
                ["timesteps", "return", "length", "success", "cost", "interventions", "infeasible", "cumulative_cost"]
            )

        def _on_step(self) -> bool:
            for info in self.locals["infos"]:
                self.cumulative_cost += float(info.get("cost", 0.0))
                episode = info.get("episode")
                if episode is None:
                    continue
                self.episodes += 1
                self._writer.writerow(
                    [
                        self.num_timesteps,
                        episode["r"],
                        episode["l"],
                        float(info.get("is_success", False)),
                        float(info.get("episode_cost", 0.0)),
                        float(info.get("episode_interventions", 0)),
                        float(info.get("episode_infeasible", 0)),
                        self.cumulative_cost,
                    ]
                )
                self._file.flush()
            self.logger.record("safety/cumulative_cost", self.cumulative_cost)
            return True

        def _on_training_end(self) -> None:
            if self._file is not None:
                self._file.close()

    return EpisodeLogger


def _code_version() -> str:
    """The package version and, when run from a git checkout, its commit."""
    import subprocess

    from c3bf_gym import __version__

    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=Path(__file__).parent, capture_output=True, text=True, timeout=5
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        commit = ""
    return f"{__version__}+{commit}" if commit else __version__


def train(config: TrainConfig, address: str | None = None) -> Path:
    """Run one training run; returns its directory. ``address``: with ``engine="rllib"``, the Ray
    cluster to join (None: a local Ray instance; see :func:`c3bf_gym.rllib.train_rllib`)."""
    config.validate()
    if config.engine == "rllib":
        from c3bf_gym.rllib import train_rllib

        return train_rllib(config, address)
    if address is not None:
        raise ValueError("address is the Ray cluster of the rllib engine; this run's engine is 'sb3'")
    _require_train_extra("torch", "stable_baselines3", "tensorboard", *(("tqdm", "rich") if config.progress_bar else ()))
    import torch
    from stable_baselines3.common.callbacks import CallbackList, CheckpointCallback, EvalCallback
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    _check_sb3_hyperparams(config)
    torch.set_num_threads(1)  # one core per run: the machine runs several runs side by side
    run_dir, hyper = start_run(config)
    venv = training_envs(config)
    eval_env = DummyVecEnv([make_env(config.evaluated_scenario, seed=10_000 + config.seed, **config.env_options())])
    if config.normalize_obs:
        # Running mean/std of the observations (not of the rewards); EvalCallback copies the
        # statistics into the evaluation env, and they are saved beside the model.
        venv = VecNormalize(venv, norm_obs=True, norm_reward=False, clip_obs=OBS_CLIP, gamma=hyper.get("gamma", 0.99))
        eval_env = VecNormalize(eval_env, training=False, norm_obs=True, norm_reward=False, clip_obs=OBS_CLIP)
    model = sb3_model(config, venv, hyper, tensorboard_log=str(run_dir / "tb"))
    callbacks = CallbackList(
        [
            _episode_logger()(run_dir / "episodes.csv"),
            CheckpointCallback(max(config.checkpoint_freq // config.n_envs, 1), str(run_dir / "checkpoints")),
            EvalCallback(
                eval_env,
                n_eval_episodes=config.eval_episodes,
                eval_freq=max(config.eval_freq // config.n_envs, 1),
                log_path=str(run_dir),
                best_model_save_path=str(run_dir / "best"),
                deterministic=True,
            ),
        ]
    )
    start = time.perf_counter()
    model.learn(config.timesteps, callback=callbacks, progress_bar=config.progress_bar, tb_log_name="run")
    model.save(run_dir / "model.zip")
    if config.normalize_obs:
        venv.save(str(run_dir / NORMALIZATION_FILE))
    summary = {
        "timesteps": config.timesteps,
        "wall_time_s": time.perf_counter() - start,
        "training_cost": callbacks.callbacks[0].cumulative_cost,
        "training_episodes": callbacks.callbacks[0].episodes,
    }
    venv.close()
    eval_env.close()
    return finish_run(config, run_dir, run_dir / "model.zip", summary)


def training_envs(config: TrainConfig):
    """The SB3 vector env a run of ``config`` trains on: ``config.n_envs`` environments
    (:func:`make_env`, seeds ``1000 * seed + i``), in subprocesses when more than one."""
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    thunks = [make_env(config.scenario, seed=config.seed * 1000 + i, **config.env_options())
              for i in range(config.n_envs)]  # fmt: skip
    return SubprocVecEnv(thunks) if config.n_envs > 1 else DummyVecEnv(thunks)


def _sb3_algorithm(algo: str):
    """The Stable-Baselines3 class of an algorithm of :data:`ALGORITHMS`."""
    from stable_baselines3 import PPO, SAC

    return {"sac": SAC, "ppo": PPO}[algo]


#: The SB3 constructor's arguments that a run sets itself, not through ``hyperparams``.
_RUN_ARGUMENTS = ("policy", "env", "seed", "verbose", "tensorboard_log", "_init_setup_model")


def _check_sb3_hyperparams(config: TrainConfig) -> None:
    """Check ``config.hyperparams`` against the keyword arguments of its SB3 algorithm's
    constructor, before a run writes anything.

    Raises:
        ValueError: a key the constructor does not take (or that the run sets itself:
            :data:`_RUN_ARGUMENTS`); the message names the valid keys.
    """
    valid = [name for name in inspect.signature(_sb3_algorithm(config.algo)).parameters if name not in _RUN_ARGUMENTS]
    unknown = [key for key in config.hyperparams if key not in valid]
    if unknown:
        raise ValueError(f"unknown {config.algo.upper()} hyperparameters {', '.join(map(repr, unknown))}; "
                         f"valid keys: {', '.join(valid)}")  # fmt: skip


def sb3_model(config: TrainConfig, venv, hyper: dict[str, Any], **kwargs: Any):
    """The SB3 model of ``config`` (its algorithm and obstacle encoder, hyperparameters ``hyper``)
    on ``venv``; ``kwargs`` go to the algorithm's constructor."""
    algo = _sb3_algorithm(config.algo)
    if config.obstacle_encoder == "set":
        from c3bf_gym.policies import ObstacleSetExtractor

        # the entries the wrappers appended to the environment's own (FilterFeedback, ArmClearance)
        own = sum(size for _, size, _ in observation_layout(ROBOTS[config.robot].n_joints))
        appended = venv.observation_space.shape[0] - own
        extra = {"features_extractor_kwargs": {"extra_features": appended}} if appended else {}
        hyper = {**hyper, "policy_kwargs": {**hyper.get("policy_kwargs", {}), "features_extractor_class": ObstacleSetExtractor,
                                            **extra}}  # fmt: skip
    if config.applied_action:
        from c3bf_gym.replay import AppliedActionReplayBuffer

        hyper = {**hyper, "replay_buffer_class": AppliedActionReplayBuffer}
    if config.observe_time:  # the time limit is the task's end, seen in the observation: no bootstrap past it
        buffer = {**hyper.get("replay_buffer_kwargs", {}), "handle_timeout_termination": False}
        hyper = {**hyper, "replay_buffer_kwargs": buffer}
    return algo("MlpPolicy", venv, seed=config.seed, verbose=0, **hyper, **kwargs)


def start_run(config: TrainConfig) -> tuple[Path, dict[str, Any]]:
    """Create the run directory and write its ``config.json`` (the config, the resolved
    hyperparameters, the command line and the code version); returns the directory and the
    hyperparameters."""
    run_dir = Path(config.out) / config.name
    run_dir.mkdir(parents=True, exist_ok=True)
    hyper = config.resolved_hyperparams()
    record = {**asdict(config), "resolved_hyperparams": hyper, "command": " ".join(sys.argv), "code": _code_version()}
    (run_dir / "config.json").write_text(json.dumps(record, indent=2))
    return run_dir, hyper


def finish_run(config: TrainConfig, run_dir: Path, model_path: Path, summary: dict[str, Any]) -> Path:
    """The final model's evaluation (``final_eval_episodes`` episodes from
    :data:`FINAL_EVAL_SEED`, the same episodes for every run; :data:`FINAL_EVAL_FILE`) and
    ``summary.json``; returns ``run_dir``."""
    if config.final_eval_episodes:
        final = evaluate(model_path, episodes=config.final_eval_episodes, seed=FINAL_EVAL_SEED)
        (run_dir / FINAL_EVAL_FILE).write_text(json.dumps(final, indent=2))
        summary["final_eval"] = final
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    return run_dir


def _run_dir(model_path: Path) -> Path | None:
    """The run directory of a saved model: ``model.zip``'s own, or the parent of ``best/`` and
    ``checkpoints/`` (the first with a ``config.json``); None for a model outside a run."""
    for directory in (model_path.parent, model_path.parent.parent):
        if (directory / "config.json").exists():
            return directory
    return None


def _load_normalizer(path: Path):
    """The run's saved ``VecNormalize`` statistics (frozen), or None when the run has none."""
    import pickle

    if not path.exists():
        return None
    with open(path, "rb") as fh:
        normalizer = pickle.load(fh)
    normalizer.training = False
    return normalizer


def _load_policy(model_path: Path, config: dict, run_dir: Path | None, deterministic: bool) -> Callable[[np.ndarray], np.ndarray]:
    """The saved policy as ``observation -> action``: an RLlib checkpoint directory
    (:func:`c3bf_gym.rllib.load_policy`) or an SB3 ``.zip`` (with the run's observation
    statistics when it was trained with ``normalize_obs``)."""
    if model_path.is_dir():
        from c3bf_gym.rllib import load_policy

        return load_policy(model_path, deterministic)
    _require_train_extra("torch", "stable_baselines3", purpose="evaluating a Stable-Baselines3 model")
    model = _sb3_algorithm(config.get("algo", "sac")).load(model_path, device="cpu")
    normalizer = _load_normalizer(run_dir / NORMALIZATION_FILE) if run_dir else None

    def policy(obs: np.ndarray) -> np.ndarray:
        action, _ = model.predict(obs if normalizer is None else normalizer.normalize_obs(obs), deterministic=deterministic)
        return action

    return policy


def evaluate(
    model_path: str | os.PathLike,
    episodes: int = 50,
    filter: str | None = None,
    scenario: str | None = None,
    seed: int = FINAL_EVAL_SEED,
    deterministic: bool = True,
    guard_gamma: float | None = None,
    residual_fade: float | None = None,
    per_episode: bool = False,
    filter_settings: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Roll out a saved model for ``episodes`` seeded episodes (``seed``, ``seed + 1``, ...).

    ``model_path`` is an SB3 ``model.zip`` (or one in ``best/`` or ``checkpoints/``) or an RLlib
    checkpoint directory (``checkpoint/`` of a run trained with ``engine="rllib"``).
    ``filter`` (one of :data:`TRAIN_FILTERS`), ``guard_gamma`` and ``filter_settings`` (changes
    to the filter's other settings, as :func:`filter_config` takes them) default to the run's own
    (from its ``config.json``; runs from before the settings had none), ``scenario`` to the run's
    evaluation scenario (its ``eval_scenario``, else its training scenario); pass a filter to
    evaluate, e.g., an unfiltered agent with the default filter on (its guard then has the
    default gains and its other settings their defaults, unless given). The action mode,
    policy rate and reward (``distance_weight``, ``action_weight``) are the run's too (also for
    ``best/`` and ``checkpoints/`` models), so returns compare only between runs with the same
    reward (and ``correction_weight`` and ``applied_action``'s charge, when evaluated with a
    filter); success and collisions do not
    depend on it. So are the nominal controller's ``posture_stiffness`` and ``posture_reach``,
    the residual action's ``residual_fade`` (unless ``residual_fade`` is given: 0 for none) and
    ``observe_correction`` (such a run needs a filter: ValueError otherwise),
    ``observe_clearance`` and ``residual_modulation``. A run
    trained with ``normalize_obs`` has its final observation statistics in the run directory;
    they are applied (to a ``best/`` or checkpoint model too, an approximation).

    Besides the success rate (the tool within the tolerance at the episode's last step) the result
    has ``collision_free_success_rate`` (the share of episodes that succeeded with no collision at
    any step: an unfiltered agent may reach the goal through an obstacle; also per scenario in
    ``by_scenario``) and counts ``reached_not_held_episodes``: episodes whose tool was within the
    tolerance at some earlier policy step but not at the last. ``per_episode`` adds
    ``per_episode``, one record per episode: ``scenario``, ``success``, ``collided``,
    ``closest_distance`` and ``final_distance`` (the tool's distance to the goal, its least over
    the policy steps and at the last one, m) and ``goal_clearance`` (the nearest obstacle's
    surface distance to the goal at the last step, m; None with no obstacle).
    """
    model_path = Path(model_path)
    if not model_path.exists():
        raise FileNotFoundError(f"no model at {model_path}")
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"episodes must be an integer >= 1, got {episodes!r}")
    run_dir = _run_dir(model_path)
    config = json.loads((run_dir / "config.json").read_text()) if run_dir else {}
    action = config.get("action", "impedance")
    if filter is None:
        filter = config.get("filter", "none")
        guard_gamma = config.get("guard_gamma") if guard_gamma is None else guard_gamma
        filter_settings = config.get("filter_settings") if filter_settings is None else filter_settings
    filter_ = filter_config(filter, guard_gamma, filter_settings)  # checked before the model loads
    observe = config.get("observe_correction", False)
    if observe and filter_ is None:
        raise ValueError("this run observes the filter's correction (observe_correction): evaluate it with a filter")
    if scenario is None:
        scenario = config.get("eval_scenario") or config.get("scenario", "random")
    if residual_fade is None:
        residual_fade = config.get("residual_fade")  # absent from runs before the option: none
    residual_fade = _residual_fade_or_none(residual_fade, action)
    policy = _load_policy(model_path, config, run_dir, deterministic)
    returns, successes, costs, collided, interventions, infeasible, kinds = [], [], [], [], [], [], []
    not_held, records = 0, []
    run_env = env_kwargs(config.get("policy_hz", DEFAULT_POLICY_HZ), config.get("distance_weight", 0.0),
                         config.get("robot", "ur5e"))
    env = build_env(scenario, filter_, action, action_weight=config.get("action_weight", 0.0),
                    observe_correction=observe, posture_stiffness=config.get("posture_stiffness"),
                    residual_fade=residual_fade, posture_reach=config.get("posture_reach"),
                    action_reach=config.get("action_reach"),
                    correction_weight=config.get("correction_weight", 0.0) if filter_ is not None else 0.0,
                    observe_clearance=config.get("observe_clearance", False),
                    observe_contact_time=config.get("observe_contact_time", False),
                    observe_forecast=config.get("observe_forecast", False),
                    observe_time=config.get("observe_time", False),
                    residual_modulation=config.get("residual_modulation", False),
                    applied_action=config.get("applied_action", False) if filter_ is not None else False,
                    **run_env)  # fmt: skip
    env.reset(seed=seed)  # as a training env starts (make_env); each episode below is reseeded
    for episode in range(episodes):
        obs, _ = env.reset(seed=seed + episode)
        kinds.append(env.unwrapped.episode_scenario.name)
        total, done, info, reached, closest = 0.0, False, {}, False, math.inf
        while not done:
            obs, reward, terminated, truncated, info = env.step(policy(obs))
            total += float(reward)
            done = terminated or truncated
            reached = reached or bool(info.get("is_success", False))
            closest = min(closest, float(info["distance"]))
        success = bool(info.get("is_success", False))
        not_held += reached and not success
        if per_episode:
            records.append({"scenario": kinds[-1], "success": success,
                            "collided": info.get("episode_cost", 0.0) > 0, "closest_distance": closest,
                            "final_distance": float(info["distance"]), "goal_clearance": _goal_clearance(env.unwrapped)})  # fmt: skip
        returns.append(total)
        successes.append(float(success))
        costs.append(float(info.get("episode_cost", 0.0)))
        collided.append(float(info.get("episode_cost", 0.0) > 0))
        interventions.append(float(info.get("episode_interventions", 0)))
        infeasible.append(float(info.get("episode_infeasible", 0)))
    env.close()
    return {
        "model": str(model_path),
        "filter": filter_label(filter_),
        "guard_gamma": None if filter_ is None else filter_.resolved_guard_gamma(),
        "filter_settings": dict(filter_settings or {}),
        "scenario": scenario,
        "episodes": episodes,
        "success_rate": float(np.mean(successes)),
        "collision_free_success_rate": float(np.mean(np.multiply(successes, np.logical_not(collided)))),
        "return_mean": float(np.mean(returns)),
        "return_std": float(np.std(returns)),
        "collision_episodes": int(np.sum(collided)),
        "collision_steps": float(np.sum(costs)),
        "interventions_per_episode": float(np.mean(interventions)),
        "infeasible_steps": float(np.sum(infeasible)),
        "reached_not_held_episodes": int(not_held),
        "by_scenario": by_scenario(kinds, successes, collided),
        **({"per_episode": records} if per_episode else {}),
    }


def _goal_clearance(env) -> float | None:
    """The nearest active obstacle's surface distance to the goal [m] (negative: the goal inside
    it), or None with no obstacle active."""
    active = env.obstacle_active
    if not active.any():
        return None
    gaps = np.linalg.norm(env.obstacle_pos[active] - env.goal, axis=1) - env.obstacle_radius[active]
    return float(gaps.min())


def by_scenario(kinds: list[str], successes: list[float], collided: list[float]) -> dict[str, dict[str, float]]:
    """Episodes, success rate, collision episodes and collision-free success rate (the share of
    episodes that succeeded without any collision) per concrete scenario (the components of a
    ``random`` evaluation), in order of first appearance."""
    table: dict[str, dict[str, float]] = {}
    for kind, success, collision in zip(kinds, successes, collided):
        row = table.setdefault(kind, {"episodes": 0, "success_rate": 0.0, "collision_episodes": 0,
                                      "collision_free_success_rate": 0.0})  # fmt: skip
        row["episodes"] += 1
        row["success_rate"] += success
        row["collision_episodes"] += int(collision)
        row["collision_free_success_rate"] += success * (not collision)
    for row in table.values():
        row["success_rate"] /= row["episodes"]
        row["collision_free_success_rate"] /= row["episodes"]
    return table
