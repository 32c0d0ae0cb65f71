"""Public wrappers: the safety filter and the Cartesian impedance action space.

Both act at the physics rate through the environment's torque hooks, so they compose in either
wrapping order: the impedance controller is always the ``nominal`` stage and the filter the
``filter`` stage, which runs after it at every physics step (see ``C3BFReachEnv``)::

    env = gym.make("C3BFReach-v0")
    env = CartesianImpedanceAction(env)          # policy outputs tool targets
    env = SafetyFilter(env)                      # every torque passes the QP
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from c3bf_gym import validation
from c3bf_gym.controllers._kernels import ImpedanceWork, task_inertia
from c3bf_gym.controllers.impedance import CartesianImpedance, ImpedanceHook
from c3bf_gym.controllers.modulation import modulated
from c3bf_gym.envs.reach import _ACTION_BOUND, C3BFReachEnv
from c3bf_gym.filter import SafetyHook
from c3bf_gym.safety import FILTERS, FilterConfig, StepSafety, capsule_distances

__all__ = [
    "ActionPenalty",
    "AppliedAction",
    "ArmClearance",
    "ArmContactTime",
    "ArmForecast",
    "CartesianImpedanceAction",
    "CorrectionPenalty",
    "ElapsedTime",
    "FilterFeedback",
    "ImpedanceHook",
    "SafetyFilter",
    "make_reach",
    "reach_env",
    "MODULATION_LOOKAHEAD",
]

#: [s] ``CartesianImpedanceAction(modulate=True)`` bends the straight step relative to each
#: sphere's displacement over this time (the step and the displacement then share a unit, m).
MODULATION_LOOKAHEAD = 1.0


def reach_env(env: gym.Env, wrapper: str) -> C3BFReachEnv:
    """The unwrapped :class:`C3BFReachEnv` under ``env``, or a clear error."""
    base = getattr(env, "unwrapped", None)
    if not isinstance(base, C3BFReachEnv):
        raise TypeError(
            f"{wrapper} wraps a C3BFReach environment (gym.make('C3BFReach-v0') or C3BFReachEnv), "
            f"got {type(base if base is not None else env).__name__}"
        )
    return base


def _filtered_env(env: gym.Env, wrapper: str, use: str) -> C3BFReachEnv:
    """:func:`reach_env`, refused (ValueError) when it has no safety filter, for a ``wrapper`` that
    reads the filter's correction (FilterFeedback, CorrectionPenalty; ``use``: what it does with it)."""
    base = reach_env(env, wrapper)
    if not base.has_torque_hook("filter"):
        raise ValueError(f"{wrapper} {use} the safety filter's correction: wrap a SafetyFilter "
                         f"(SafetyFilter(env), then {wrapper}(...)); this environment has none")  # fmt: skip
    return base


def _appended_space(space: gym.Space, bound: np.ndarray, wrapper: str) -> gym.spaces.Box:
    """The flat ``Box`` ``space`` with entries in ``[-bound, bound]`` appended (TypeError for any
    other space): the observation of a wrapper that appends to it (FilterFeedback, ArmClearance)."""
    if not isinstance(space, gym.spaces.Box) or len(space.shape) != 1:
        raise TypeError(f"{wrapper} needs a flat Box observation space, got {space}")
    bound = bound.astype(space.dtype)
    return gym.spaces.Box(np.concatenate([space.low, -bound]), np.concatenate([space.high, bound]), dtype=space.dtype)


class SafetyFilter(gym.Wrapper, gym.utils.RecordConstructorArgs, gym.utils.EzPickle):
    """Project every torque through the safety filter's quadratic program.

    The filter runs at every physics step (500 Hz) on whatever total torque arrives (the policy's
    torque plus gravity compensation, or the impedance controller's), so the policy's rate does
    not weaken it. Its settings are one :class:`~c3bf_gym.safety.FilterConfig`; by default the
    C3BF with its distance-HOCBF guard (``"c3bf+hocbf"``, :data:`~c3bf_gym.safety.DEFAULT_FILTER`).

    Adds ``info["safety"]`` (a dict, see :class:`~c3bf_gym.safety.StepSafety`; deterministic:
    wall-clock timings are kept on ``filter.hook`` for benchmarks, not in ``info``) and flat
    scalars for SB3's ``Monitor(info_keywords=...)``: ``safety_intervened`` (0/1 this step),
    ``safety_infeasible`` (0/1), ``episode_interventions`` and ``episode_infeasible`` (counts of
    such steps so far in the episode: the value at the episode's last step is its total).

    Args:
        env: a ``C3BFReach-v0`` environment (possibly wrapped).
        config: a :class:`~c3bf_gym.safety.FilterConfig`, or the name of one in
            :data:`~c3bf_gym.safety.FILTERS` (``"c3bf+hocbf"``, ``"c3bf"``: the paper's C3BF
            alone, ``"hocbf"``); None for the default configuration.
        **settings: changes to fields of ``config`` (e.g. ``margin=0.03``, ``barrier="hocbf"``,
            ``on_infeasible="raise"``); see :class:`~c3bf_gym.safety.FilterConfig` for each
            field, its unit and its default.

    Raises:
        ValueError: on an unknown filter name or setting (the message lists the valid ones), an
            invalid value, or an environment that already has a filter.
        TypeError: when ``env`` is not a ``C3BFReach`` environment.

    Failure paths: with ``on_infeasible="raise"`` a step with no safe torque raises
    :class:`~c3bf_gym.safety.SafetyInfeasibleError` and leaves the environment as it was before
    the step. After :meth:`close`, ``step`` and ``reset`` raise: a closed filter never steps the
    environment unfiltered.

    ``gym.make(filtered.spec)`` rebuilds the same stack (the wrapper records its arguments).
    Pickling (and ``copy.deepcopy``) rebuilds the filter with the same arguments around the
    unpickled environment, which Gymnasium's MuJoCo environments rebuild from their own
    arguments: the copy is filtered like the original and, like any copied MuJoCo env, starts
    from a fresh state (reset it).
    """

    def __init__(self, env: gym.Env, config: FilterConfig | str | None = None, **settings: Any) -> None:
        gym.utils.RecordConstructorArgs.__init__(self, config=config, **settings)
        gym.utils.EzPickle.__init__(self, env, config, **settings)
        super().__init__(env)
        if config is None:
            config = FilterConfig()
        elif isinstance(config, str):
            config = FilterConfig.named(config)
        elif not isinstance(config, FilterConfig):
            raise TypeError(f"config must be a FilterConfig, a filter name ({', '.join(map(repr, FILTERS))}) or None, "
                            f"got {type(config).__name__}")  # fmt: skip
        config = config.replace(**settings)
        base = reach_env(env, "SafetyFilter")
        if base.has_torque_hook("filter"):
            raise ValueError("this environment already has a safety filter installed")
        self.config: FilterConfig = config
        self.hook = SafetyHook(base, config)
        base.add_torque_hook(self.hook, stage="filter")
        self._base = base
        self._closed = False
        self._episode_interventions = 0
        self._episode_infeasible = 0

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("this SafetyFilter is closed: its hook was removed, so stepping would apply unfiltered "
                               "torques; build a new SafetyFilter around a fresh environment")  # fmt: skip

    def reset(self, **kwargs: Any):
        self._check_open()
        self._episode_interventions = 0
        self._episode_infeasible = 0
        self.hook.reset()  # a seeded episode repeats bit for bit, whatever ran before it
        return self.env.reset(**kwargs)

    def step(self, action):
        self._check_open()
        self.hook.begin_step()
        obs, reward, terminated, truncated, info = self.env.step(action)
        report: StepSafety = self.hook.report
        self._episode_interventions += int(report.intervened)
        self._episode_infeasible += int(not report.feasible)
        info["safety"] = report.as_info()
        info["safety_intervened"] = float(report.intervened)
        info["safety_infeasible"] = float(not report.feasible)
        info["episode_interventions"] = self._episode_interventions
        info["episode_infeasible"] = self._episode_infeasible
        return obs, reward, terminated, truncated, info

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._base.remove_torque_hook("filter")
        super().close()


def default_impedance(env: C3BFReachEnv, posture_stiffness: float | None = None) -> CartesianImpedance:
    """The impedance law used by default: 300 N/m, critically damped, a null-space pull to the
    ``home`` keyframe of ``posture_stiffness`` [N m/rad] (None: the arm's own,
    :attr:`~c3bf_gym.envs.reach.ReachRobot.posture_stiffness`: 20 on the UR5e, 2 on the Panda)."""
    stiffness = env.task_robot.posture_stiffness if posture_stiffness is None else posture_stiffness
    return CartesianImpedance(stiffness=300.0, posture=env.model.key_qpos[0].copy(), posture_stiffness=stiffness,
                              max_force=150.0)


class CartesianImpedanceAction(gym.ActionWrapper, gym.utils.RecordConstructorArgs, gym.utils.EzPickle):
    """Actions are tool position targets; an impedance controller turns them into torque.

    The action ``a`` in ``Box(-1, 1, (3,))`` sets the target ``x_tool + max_offset * a`` (world
    frame, m) when the step begins; at every physics step the controller
    (:class:`~c3bf_gym.controllers.CartesianImpedance`, default 300 N/m, critically damped, with a
    null-space pull to the ``home`` posture) computes the torque towards it, inside the
    environment's compiled policy step, with the :class:`SafetyFilter` behind it if there is one
    (:class:`ImpedanceHook`). Out-of-range, wrongly shaped or non-finite actions raise ``ValueError``.

    With ``residual=True`` the action is a correction to a step straight for the goal: the target
    is ``x_tool + clip(goal - x_tool, ±max_offset) + max_offset * a`` (per axis, so up to
    ``2 max_offset`` from the tool), and ``a = 0`` heads for the goal. This is residual RL
    (Johannink et al., ICRA 2019): the policy only has to learn what the straight line gets
    wrong, such as going around an obstacle at rest on it. The task itself does not change.

    With ``fade`` (residual only) the correction's reach shrinks near the goal: it is scaled by
    ``min(1, d / fade)``, ``d`` [m] being the tool's distance to the goal when the step begins.
    Within ``min(fade, max_offset)`` of the goal the target is ``goal + (d / fade) max_offset a``,
    so for an action of Euclidean norm below ``fade / max_offset`` the only target the tool can
    rest at is the goal itself: a policy's small bias near the goal, where the reward hardly tells
    actions apart, cannot hold the tool off it. Measured in the docs' RL results page ("Holding
    the goal").

    With ``posture_reach`` the action has ``n`` more entries, one per joint: the posture task's
    target is ``q_home + posture_reach * a[3:]`` [rad] (``q_home`` the controller's posture),
    set when the step begins. The posture task acts in the tool task's null space, so these
    entries choose how the redundant arm holds the tool (where the elbow and the wrist are, how
    the tool points) without pulling the tool itself; ``a[3:] = 0`` is the controller alone.
    The action space is then ``Box(-1, 1, (3 + n,))``.

    With ``modulate`` (residual only) the step straight for the goal bends round the obstacles
    the filter senses (:meth:`~c3bf_gym.envs.C3BFReachEnv.sensed_mask`) before the correction is
    added: :func:`~c3bf_gym.controllers.modulation.modulate` reshapes it at the tool, relative to
    each sphere's displacement over the next :data:`MODULATION_LOOKAHEAD` seconds, and it is then
    scaled down, direction kept, until every axis is within ``max_offset``. The zero action then
    flows round a sphere in its way instead of pressing against the filter. It steers the nominal
    motion only: the filter still keeps every link off the spheres. Measured in the docs' RL
    results page ("An attempt on the UR5e: the straight step bent round the spheres").

    Args:
        env: a ``C3BFReach-v0`` environment (possibly wrapped, e.g. by :class:`SafetyFilter`).
        max_offset: the target's largest distance from the tool per axis (per part with
            ``residual``) [m].
        controller: a custom :class:`CartesianImpedance`.
        residual: actions correct a straight step for the goal instead of being the whole offset.
        fade: with ``residual``, the goal distance [m] below which the correction shrinks in
            proportion (None: never).
        posture_reach: the largest posture offset per joint [rad] the action sets (None: the
            action sets the tool target only). Needs a controller with a posture task.
        modulate: with ``residual``, bend the straight step round the sensed obstacles.

    ``gym.make(wrapped.spec)`` rebuilds the same stack (the wrapper records its arguments).
    Pickling rebuilds the wrapper, and so its controller hook, around the unpickled environment
    (as :class:`SafetyFilter`).
    """

    def __init__(
        self,
        env: gym.Env,
        max_offset: float = 0.1,
        controller: CartesianImpedance | None = None,
        residual: bool = False,
        fade: float | None = None,
        posture_reach: float | None = None,
        modulate: bool = False,
    ) -> None:
        gym.utils.RecordConstructorArgs.__init__(self, max_offset=max_offset, controller=controller, residual=residual,
                                                 fade=fade, posture_reach=posture_reach, modulate=modulate)  # fmt: skip
        gym.utils.EzPickle.__init__(self, env, max_offset, controller, residual, fade, posture_reach, modulate)
        super().__init__(env)
        base = reach_env(env, "CartesianImpedanceAction")
        if base.has_torque_hook("nominal"):
            raise ValueError("this environment already has a nominal controller installed")
        if not (isinstance(max_offset, (int, float)) and np.isfinite(max_offset) and max_offset > 0):
            raise ValueError(f"max_offset must be a finite number > 0 (m), got {max_offset!r}")
        if not isinstance(residual, (bool, np.bool_)):
            raise ValueError(f"residual must be True or False, got {residual!r}")
        if fade is not None:
            if not residual:
                raise ValueError("fade shrinks the residual correction near the goal: it needs residual=True")
            if isinstance(fade, bool) or not (isinstance(fade, (int, float)) and np.isfinite(fade) and fade > 0):
                raise ValueError(f"fade must be None or a finite number > 0 (m), got {fade!r}")
        if not isinstance(modulate, (bool, np.bool_)):
            raise ValueError(f"modulate must be True or False, got {modulate!r}")
        if modulate and not residual:
            raise ValueError("modulate bends the residual action's straight step for the goal: it needs residual=True")
        controller = controller or default_impedance(base)
        if posture_reach is not None:
            if isinstance(posture_reach, bool) or not (
                    isinstance(posture_reach, (int, float)) and np.isfinite(posture_reach) and posture_reach > 0):
                raise ValueError(f"posture_reach must be None or a finite number > 0 (rad), got {posture_reach!r}")
            if controller.posture is None:
                raise ValueError("posture_reach moves the controller's posture task, and this controller has none: "
                                 "build it with posture=")  # fmt: skip
        self.fade = None if fade is None else float(fade)
        self.max_offset = float(max_offset)
        self.residual = bool(residual)
        self.posture_reach = None if posture_reach is None else float(posture_reach)
        self.modulate = bool(modulate)
        self.hook = ImpedanceHook(base, controller)
        base.add_torque_hook(self.hook, stage="nominal")
        self._base = base
        self._home = None if controller.posture is None else controller.posture.copy()
        self._n_action = 3 if posture_reach is None else 3 + self._home.size
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(self._n_action,), dtype=np.float32)
        self._scales = "fractions of max_offset per axis" + ("" if posture_reach is None else ", then of posture_reach")
        self._zero = np.zeros(base.action_space.shape, dtype=np.float32)
        self._tool = base.data.site_xpos[base.ee_site_id]  # views, made once
        self._goal = base.goal
        self._straight = np.zeros(3)
        #: [m] how far one unit of the action's tool entries moved the target at the last step:
        #: ``max_offset``, times the fade's ``d / fade`` near the goal.
        self.reach = self.max_offset

    def action(self, action: np.ndarray) -> np.ndarray:
        a = np.asarray(action)
        if a.shape != (self._n_action,):
            raise ValueError(f"action must have shape ({self._n_action},), got {a.shape}")
        if a.dtype.kind not in "fiu":
            raise ValueError(f"action must be a real (float) array, got dtype {a.dtype}")
        # on the entries as Python numbers: for three of them, cheaper than numpy's abs and all (the
        # wrapper's Python is a sizeable part of a policy step once the controller is compiled)
        if not all(-_ACTION_BOUND <= v <= _ACTION_BOUND for v in a.tolist()):  # also False for NaN
            if not np.isfinite(a).all():
                raise ValueError(f"action contains NaN or inf: {a}")
            raise ValueError(f"action must lie in [-1, 1] ({self._scales}), got {a}")
        tool = self._tool
        if self.posture_reach is not None:
            self.hook.set_posture(self._home + self.posture_reach * a[3:])
            a = a[:3]
        offset = self.max_offset * a
        self.reach = self.max_offset
        if self.residual:  # + clip(goal − tool, ±max_offset), per axis
            m, straight, squared = self.max_offset, self._straight, 0.0
            for i, (g, x) in enumerate(zip(self._goal.tolist(), tool.tolist())):
                straight[i] = min(max(g - x, -m), m)
                squared += (g - x) * (g - x)
            if self.fade is not None and squared < self.fade * self.fade:
                shrink = math.sqrt(squared) / self.fade
                offset = offset * shrink
                self.reach = self.max_offset * shrink
            if self.modulate:
                straight = self._bent(tool, straight)
            offset = offset + straight
        self.hook.set_target(tool + offset)
        return self._zero  # the torque action underneath is replaced by the controller's

    def _bent(self, tool: np.ndarray, straight: np.ndarray) -> np.ndarray:
        """The straight step bent round the sensed obstacles, back inside the ``max_offset`` box."""
        base = self._base
        near = base.sensed_mask()
        if not near.any():
            return straight
        bent = modulated(tool, straight, base.obstacle_pos[near], MODULATION_LOOKAHEAD * base.obstacle_vel[near],
                         base.obstacle_radius[near])  # fmt: skip
        largest = float(np.abs(bent).max())
        return bent / largest * self.max_offset if largest > self.max_offset else bent

    def close(self) -> None:
        self._base.remove_torque_hook("nominal")
        super().close()


def _wrapper_under(env: gym.Env, kind: type[gym.Wrapper]) -> gym.Wrapper | None:
    """The outermost wrapper of type ``kind`` in ``env``'s stack (``env`` itself included), or None."""
    while isinstance(env, gym.Wrapper):
        if isinstance(env, kind):
            return env
        env = env.env
    return None


class ActionPenalty(gym.Wrapper):
    """Adds ``-weight * mean(a²)`` to the reward, ``a`` being the policy's action as it arrives
    (``charge="policy"``) or the action the safety filter let through (``charge="applied"``,
    ``info["applied_action"]`` of an :class:`AppliedAction` under this wrapper).

    A training aid for residual policies (``CartesianImpedanceAction(residual=True)``): ``a = 0``
    is the prior (straight for the goal), and the penalty makes a correction pay for itself, so
    the agent keeps the prior where it already works instead of drifting from it wherever the
    other reward terms are flat. The term is in ``info["reward_action"]`` (negative or zero);
    the task, its success and its cost do not change. Put it outside wrappers that change the
    action's meaning, so that it sees the policy's own action. ``charge="applied"`` is for a
    learner that stores the applied action in place of its own (:class:`AppliedAction`): the
    reward it stores then belongs to the action it stores.

    Args:
        env: any environment with a ``Box`` action space (with ``charge="applied"``, with an
            :class:`AppliedAction` under this wrapper).
        weight: the penalty's weight (finite, >= 0; 0 adds nothing but the info key).
        charge: ``"policy"`` or ``"applied"``: whose action is charged.

    Raises:
        ValueError: a bad ``weight`` or ``charge``, or ``charge="applied"`` without an
            :class:`AppliedAction` under this wrapper.
    """

    def __init__(self, env: gym.Env, weight: float, charge: str = "policy") -> None:
        super().__init__(env)
        if not isinstance(env.action_space, gym.spaces.Box):
            raise TypeError(f"ActionPenalty needs a Box action space, got {env.action_space}")
        self.weight = validation.number("weight", weight, low=0.0)
        self.charge = validation.choice("charge", charge, ("policy", "applied"))
        if self.charge == "applied" and _wrapper_under(env, AppliedAction) is None:
            raise ValueError("ActionPenalty(charge='applied') charges info['applied_action']: wrap an AppliedAction "
                             "under it (AppliedAction(env), then ActionPenalty(...)); this environment has none")  # fmt: skip

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)  # validates the action
        charged = info["applied_action"] if self.charge == "applied" else action
        penalty = -self.weight * float(np.mean(np.square(charged, dtype=np.float64)))
        info["reward_action"] = penalty
        return obs, float(reward) + penalty, terminated, truncated, info


class CorrectionPenalty(gym.Wrapper):
    """Adds ``-weight * c / ‖τ_max‖`` to the reward, ``c`` [N m] being the safety filter's largest
    correction ``‖τ − clip(τ_nom)‖`` over the step's physics steps (``info["safety"]["correction"]``)
    and ``‖τ_max‖`` the norm of the arm's torque limits (``env.unwrapped.robot.torque_limit``).

    A training aid: the agent pays for what the filter had to change, so it can learn to stay out
    of the situations where the filter acts. ``c / ‖τ_max‖`` lies in [0, 2]. The term is in
    ``info["reward_correction"]`` (negative or zero); the task, its success and its cost do not
    change.

    Args:
        env: a ``C3BFReach`` environment with a :class:`SafetyFilter` under this wrapper.
        weight: the penalty's weight (finite, >= 0; 0 adds nothing but the info key).

    Raises:
        ValueError: ``env`` has no safety filter, or a bad ``weight``.
    """

    def __init__(self, env: gym.Env, weight: float) -> None:
        super().__init__(env)
        base = _filtered_env(env, "CorrectionPenalty", "charges")
        self.weight = validation.number("weight", weight, low=0.0)
        self._scale = float(np.linalg.norm(base.robot.torque_limit))

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        penalty = -self.weight * float(info["safety"]["correction"]) / self._scale
        info["reward_correction"] = penalty
        return obs, float(reward) + penalty, terminated, truncated, info


class AppliedAction(gym.Wrapper):
    """Puts the action the safety filter let through in ``info["applied_action"]``: the Cartesian
    action that, given to the impedance controller with no filter, would have produced the
    filtered torque's pull on the tool.

    For learners trained on the action the barrier applied rather than the one the policy chose
    (Cheng, Orosz, Murray and Burdick, AAAI 2019): an off-policy learner that stores this action
    (:class:`~c3bf_gym.replay.AppliedActionReplayBuffer`) learns the value of what was done.

    The filter changes torque, and the action sets the impedance controller's tool target, so the
    correction is mapped back to a target shift. At the last physics step of the policy step, with
    ``Δτ = τ − clip(τ_nom)`` the filter's correction [N m] (the nominal clipped to the torque
    limits, as :class:`FilterFeedback`), ``G = J M_h⁻¹`` the tool's acceleration per unit torque
    (:meth:`~c3bf_gym.safety.dynamics.ArmModel.site_dynamics`) and ``Λ = (G Jᵀ)⁻¹`` the task
    inertia the controller uses (:func:`~c3bf_gym.controllers._kernels.task_inertia`: eigenvalues
    of ``G Jᵀ`` clamped from below),
    the task force with the same tool acceleration is ``ΔF = Λ G Δτ`` [N], the target shift that
    the controller's stiffness ``K`` turns into that force is ``Δx = K⁻¹ ΔF`` [m], and::

        applied[:3] = clip(a[:3] + Δx / r, −1, 1)

    with ``r`` [m] the target's reach per unit action at that step
    (:attr:`CartesianImpedanceAction.reach`: ``max_offset``, shrunk by the residual action's
    fade). The correction's null-space part, which does not move the tool, is dropped, and the
    action's posture entries (``posture_reach``) are passed on as chosen. Where the filter left the
    torque alone, or where ``r`` is 0 (the fade at the goal itself: every action sets the same
    target there), ``applied`` is ``a``. Approximations: one physics step stands for the policy
    step's fifty, ``G`` and ``Λ`` are taken at the state the step reached (one physics step after
    that correction), and the controller's ``max_force`` bound is not inverted. The environment's
    step, its reward and its observation are unchanged.

    Args:
        env: a ``C3BFReach`` environment with a :class:`CartesianImpedanceAction` and a
            :class:`SafetyFilter` under this wrapper.

    Raises:
        ValueError: ``env`` has no safety filter or no Cartesian impedance action.
    """

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        base = _filtered_env(env, "AppliedAction", "maps back")
        impedance = _wrapper_under(env, CartesianImpedanceAction)
        if impedance is None:
            raise ValueError("AppliedAction maps the filter's correction back to a tool target: wrap a "
                             "CartesianImpedanceAction under it; this environment's actions are torques")  # fmt: skip
        self._base = base
        self._impedance = impedance
        self._limit = np.asarray(base.robot.torque_limit, dtype=np.float64)
        self._stiffness = np.asarray(impedance.hook.controller.K, dtype=np.float64)
        self._work = ImpedanceWork.of(base.robot.n)

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)  # validates the action
        info["applied_action"] = self.applied(action, self._base.torque_hook("filter").report)
        return obs, reward, terminated, truncated, info

    def applied(self, action: np.ndarray, report: StepSafety) -> np.ndarray:
        """The applied action (float32, the action's shape) for ``action``, the one the last
        :meth:`step` received, given the filter's ``report`` of that step (its last physics step's
        ``tau`` and ``tau_nominal``), at the state that step reached."""
        out = np.array(action, dtype=np.float32)
        reach = self._impedance.reach
        if report.tau is None or report.tau_nominal is None or reach <= 0.0:
            return out
        delta = report.tau - np.clip(report.tau_nominal, -self._limit, self._limit)
        if not delta.any():
            return out
        arm, data = self._base.arm, self._base.data
        arm.update(data)  # M_h⁻¹ at the state the step reached (data holds its mj_step1 results)
        tool = arm.site_dynamics(data)
        gain = np.ascontiguousarray(tool.G[0])
        task_inertia(gain, np.ascontiguousarray(tool.jac[0]), self._work)  # Λ, as the controller's
        force = self._work.mats[2] @ (gain @ delta)
        shift = np.linalg.solve(self._stiffness, force)
        out[:3] = np.clip(out[:3] + shift / reach, -1.0, 1.0)
        return out


class FilterFeedback(gym.ObservationWrapper):
    """Appends the safety filter's last correction to the observation, so a policy can see the filter act.

    The entries added, one per arm joint, are ``(τ − clip(τ_nom)) / τ_max`` at the last physics
    step of the policy step that produced the observation: the filtered torque minus the nominal
    one (clipped to the torque limits, so that saturation alone is not a correction), divided by
    each joint's torque limit ``τ_max`` [N m] (``env.unwrapped.robot.torque_limit``). Each lies
    in [−2, 2]; 0 where the filter left the torque alone, and 0 after ``reset``. The observation
    grows from ``(2 n + 73,)`` to ``(3 n + 73,)`` (the appended part last); everything else is
    unchanged.

    With it an agent can see the filter act and learn to anticipate it; the training option
    ``TrainConfig.observe_correction`` (off by default) puts it in a run's environments.

    Args:
        env: a ``C3BFReach`` environment with a :class:`SafetyFilter` under this wrapper.

    Raises:
        TypeError: ``env`` is not a ``C3BFReach`` environment, or its observation space is not a
            ``Box``.
        ValueError: ``env`` has no safety filter (there would be no correction to observe).
    """

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        base = _filtered_env(env, "FilterFeedback", "observes")
        self._limit = np.asarray(base.robot.torque_limit, dtype=np.float64)
        n = self._limit.shape[0]
        self.observation_space = _appended_space(env.observation_space, np.full(n, 2.0), "FilterFeedback")
        self._base = base
        self._correction = np.zeros(n)

    def reset(self, **kwargs: Any):
        obs, info = self.env.reset(**kwargs)
        self._correction[:] = 0.0
        return self.observation(obs), info

    def step(self, action: Any):
        obs, reward, terminated, truncated, info = self.env.step(action)
        report = self._base.torque_hook("filter").report
        if report.tau is not None and report.tau_nominal is not None:
            nominal = np.clip(report.tau_nominal, -self._limit, self._limit)
            np.divide(report.tau - nominal, self._limit, out=self._correction)
        return self.observation(obs), reward, terminated, truncated, info

    def observation(self, observation: np.ndarray) -> np.ndarray:
        return np.concatenate([observation, self._correction.astype(observation.dtype)])


class _PerArmGeom(gym.ObservationWrapper):
    """An observation wrapper that appends one entry in [-1, 1] per arm geom
    (``env.unwrapped.arm_geom_ids``, in that order), kept in ``self._entries``."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        name = type(self).__name__
        self._base = reach_env(env, name)
        n = len(self._base.arm_geom_ids)
        self.observation_space = _appended_space(env.observation_space, np.ones(n), name)
        self._entries = np.zeros(n)


class ArmClearance(_PerArmGeom):
    """Appends each arm geom's clearance to the obstacles, so a policy can see which link is close.

    The entries added, one per arm geom (``env.unwrapped.arm_geom_ids``, in that order), are
    ``clip(d, −cap, cap) / cap``, ``d`` [m] being the geom's smallest signed surface distance to
    any active obstacle (MuJoCo's distance sensors, ``env.unwrapped.distances``; negative inside):
    1 for a geom ``cap`` or farther from every obstacle, 0 in contact. The environment's own
    observation (which places the obstacles relative to the tool only) is unchanged; the appended
    part comes last. The training option ``TrainConfig.observe_clearance`` (off by default) puts it
    in a run's environments.

    Args:
        env: a ``C3BFReach`` environment (any wrappers, with or without a filter).
        cap: the distance [m] at which the entries saturate (finite, > 0).
    """

    def __init__(self, env: gym.Env, cap: float = 0.5) -> None:
        self.cap = validation.number("cap", cap, low=0.0, low_open=True, unit="m")
        super().__init__(env)

    def observation(self, observation: np.ndarray) -> np.ndarray:
        base, out = self._base, self._entries
        out[:] = self.cap
        if base.obstacle_active.any():
            np.minimum(out, base.distances[base.obstacle_active].min(axis=0), out=out)
        np.clip(out, -self.cap, self.cap, out=out)
        out /= self.cap
        return np.concatenate([observation, out.astype(observation.dtype)])


class ArmContactTime(_PerArmGeom):
    """Appends, per arm geom, how soon an obstacle would touch it at the present closing speed.

    For each arm geom (``env.unwrapped.arm_geom_ids``, in that order) and each active obstacle,
    ``d`` [m] is their signed surface distance now (MuJoCo's distance sensors,
    ``env.unwrapped.distances``) and ``r = (d_prev − d) / dt`` [m/s] the rate at which the gap
    closed over the last policy step (``dt``: the environment's step; 0 after reset and for an
    obstacle that was not active at the last step). The time to contact ``t`` is ``d / r`` where
    ``r > 0`` (whatever moved, the sphere or the arm), none where the gap opens or holds, and 0 in
    contact (``d <= 0``). The entry is ``min(t, horizon) / horizon`` for the least ``t`` over the
    obstacles: 1 for nothing closing within ``horizon``, 0 in contact. Where :class:`ArmClearance`
    tells the policy how close each link is, this tells it how soon, which is what decides whether
    a link has to leave a passing sphere's way. The environment's own observation is unchanged;
    the appended part comes last. The training option ``TrainConfig.observe_contact_time`` (off
    by default) puts it in a run's environments.

    Args:
        env: a ``C3BFReach`` environment (any wrappers, with or without a filter).
        horizon: the time [s] at which the entries saturate (finite, > 0).
    """

    def __init__(self, env: gym.Env, horizon: float = 2.0) -> None:
        self.horizon = validation.number("horizon", horizon, low=0.0, low_open=True, unit="s")
        super().__init__(env)
        self._previous = self._base.distances.copy()
        self._was_active = np.zeros_like(self._base.obstacle_active)

    def reset(self, **kwargs: Any):
        obs, info = self.env.reset(**kwargs)
        self._was_active[:] = False  # no closing speed yet
        return self.observation(obs), info

    def observation(self, observation: np.ndarray) -> np.ndarray:
        base, out = self._base, self._entries
        now, active = base.distances, base.obstacle_active
        out[:] = 1.0
        if active.any():
            gap = now[active]
            before = np.where(self._was_active[active, None], self._previous[active], gap)
            closing = (before - gap) / base.dt
            with np.errstate(divide="ignore", invalid="ignore"):
                time = np.where(closing > 0.0, gap / closing, np.inf)
            time[gap <= 0.0] = 0.0
            np.minimum(out, time.min(axis=0) / self.horizon, out=out)
        self._previous[:] = now
        self._was_active[:] = active
        return np.concatenate([observation, out.astype(observation.dtype)])


class ArmForecast(gym.ObservationWrapper):
    """Appends where the obstacles will be relative to the arm held still and to the goal, at
    several horizons: what decides whether to stay at the goal or wait for a sphere to pass.

    Each active obstacle is moved ahead along its present motion, ``p + v τ + ½ a τ²``
    (``env.unwrapped.obstacle_pos``, ``obstacle_vel``, ``obstacle_acc``; the scenarios' spheres
    move at constant velocity), for each horizon ``τ`` of ``horizons`` [s]. Two entries per
    horizon, in the order of ``horizons``: the least surface distance [m] from a moved obstacle to
    the arm's geoms in their present pose (:meth:`~c3bf_gym.envs.C3BFReachEnv.arm_capsules`), then
    to the goal point; each ``clip(d, −cap, cap) / cap``, 1 for nothing within ``cap``, 0 in
    contact, negative inside. :class:`ArmClearance` and :class:`ArmContactTime` describe the
    present; this says whether the arm, or the goal it is headed for, lies on a sphere's path
    within the horizons. The environment's own observation is unchanged; the appended part comes
    last. The training option ``TrainConfig.observe_forecast`` (off by default) puts it in a
    run's environments.

    Args:
        env: a ``C3BFReach`` environment (any wrappers, with or without a filter).
        horizons: the look-ahead times [s], each finite and > 0, at least one.
        cap: the distance [m] at which the entries saturate (finite, > 0).

    Raises:
        ValueError: an empty ``horizons``, or a horizon or ``cap`` that is not a finite number > 0.
    """

    def __init__(self, env: gym.Env, horizons: Sequence[float] = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0),
                 cap: float = 0.5) -> None:  # fmt: skip
        super().__init__(env)
        if len(horizons) == 0:
            raise ValueError("ArmForecast needs at least one horizon [s], got none")
        self.horizons = np.array([validation.number("horizon", h, low=0.0, low_open=True, unit="s") for h in horizons])
        self.cap = validation.number("cap", cap, low=0.0, low_open=True, unit="m")
        self._base = reach_env(env, "ArmForecast")
        self.observation_space = _appended_space(env.observation_space, np.ones(2 * len(self.horizons)), "ArmForecast")

    def observation(self, observation: np.ndarray) -> np.ndarray:
        base, tau = self._base, self.horizons[:, None, None]
        out = np.full((len(self.horizons), 2), self.cap)
        active = base.obstacle_active
        if active.any():
            ahead = base.obstacle_pos[active] + base.obstacle_vel[active] * tau + 0.5 * base.obstacle_acc[active] * tau**2
            radius = base.obstacle_radius[active]
            arm = base.arm_capsules()
            gap = capsule_distances(ahead, arm.a, arm.b, arm.radius) - radius[:, None]  # (K, N, G)
            out[:, 0] = np.minimum(out[:, 0], gap.min(axis=(1, 2)))
            to_goal = np.linalg.norm(ahead - base.goal, axis=-1) - radius
            out[:, 1] = np.minimum(out[:, 1], to_goal.min(axis=1))
        np.clip(out, -self.cap, self.cap, out=out)
        return np.concatenate([observation, (out.ravel() / self.cap).astype(observation.dtype)])


class ElapsedTime(gym.wrappers.TimeAwareObservation):
    """Appends the share of the episode's time limit already used, ``t / T`` in [0, 1], to the
    observation: Gymnasium's ``gymnasium.wrappers.TimeAwareObservation``, flattened and
    normalised by the environment's ``max_episode_steps``.

    An episode judged at its last step (``is_success`` there) is not Markov in the environment's
    own observation: the same state calls for waiting out a passing sphere early in the episode
    and for holding the goal near its end. With the time observed it is (Pardo et al., "Time
    Limits in Reinforcement Learning", ICML 2018), provided the learner treats the time limit as
    the end of the episode rather than bootstrapping past it (the training option
    ``TrainConfig.observe_time`` does both). The appended entry comes last.

    Unlike Gymnasium's wrapper, a step that raises (a bad action, a filter's
    :class:`~c3bf_gym.safety.SafetyInfeasibleError`) leaves the count as it was.

    Args:
        env: an environment with a flat ``Box`` observation (TypeError otherwise) and a time
            limit (``gym.make`` with ``max_episode_steps``; ValueError otherwise).
        flatten, normalize_time, dict_time_key: Gymnasium's arguments, which it records to rebuild
            the wrapper; only ``True``, ``True`` (the form described above) is accepted.
    """

    def __init__(self, env: gym.Env, flatten: bool = True, normalize_time: bool = True, *,
                 dict_time_key: str = "time") -> None:  # fmt: skip
        space = env.observation_space
        if not isinstance(space, gym.spaces.Box) or len(space.shape) != 1:
            raise TypeError(f"ElapsedTime needs a flat Box observation space, got {space}")
        if flatten is not True or normalize_time is not True:
            raise ValueError("ElapsedTime appends t / T to the flat observation: flatten and normalize_time must be "
                             f"True, got flatten={flatten!r}, normalize_time={normalize_time!r}")  # fmt: skip
        super().__init__(env, flatten=True, normalize_time=True, dict_time_key=dict_time_key)  # finds T or raises

    def step(self, action: Any):
        try:
            return super().step(action)
        except BaseException:
            self.timesteps -= 1  # Gymnasium's wrapper counted the step before it was taken
            raise


def make_reach(safety_filter: FilterConfig | str | None = None, **kwargs: Any) -> gym.Env:
    """Entry point of ``C3BFReach-v0``: the environment, optionally inside a :class:`SafetyFilter`.

    ``gym.make("C3BFReach-v0", safety_filter=NAME)`` is the shortcut for
    ``SafetyFilter(gym.make("C3BFReach-v0"), NAME)``: ``safety_filter`` is None (no filter), a
    name of :data:`~c3bf_gym.safety.FILTERS` or a :class:`~c3bf_gym.safety.FilterConfig`. Every
    other keyword goes to :class:`~c3bf_gym.envs.C3BFReachEnv`.
    """
    if not (safety_filter is None or isinstance(safety_filter, FilterConfig)
            or (isinstance(safety_filter, str) and safety_filter in FILTERS)):
        raise ValueError(f"unknown safety_filter {safety_filter!r}; valid choices: None, "
                         f"{', '.join(map(repr, FILTERS))} or a FilterConfig")  # fmt: skip
    env = C3BFReachEnv(**kwargs)
    return env if safety_filter is None else SafetyFilter(env, safety_filter)
