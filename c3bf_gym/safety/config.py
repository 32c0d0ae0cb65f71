"""The safety filter's settings: one frozen, validated :class:`FilterConfig`, and the named filters.

Every default of the filter lives here once; the wrappers, training, the experiments, the
benchmarks and the command-line help read them from :class:`FilterConfig`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Literal

from c3bf_gym import validation
from c3bf_gym.safety.barriers import BARRIERS, C3BF, Barrier, make_barrier

__all__ = [
    "DEFAULT_FILTER", "FILTERS", "FilterConfig", "GUARD_GAMMA", "GUARDS", "ON_INFEASIBLE", "POINTS",
    "MIN_TOOL_ACCELERATION", "TOOL_ACCELERATION", "WEIGHTS",
]

POINTS = ("whole_arm", "ee")
ON_INFEASIBLE = ("relax", "raise")
WEIGHTS = ("limits", "identity", "tool")
#: The tool metric's ``a`` [m/s²] (``FilterConfig.tool_acceleration``) when none is given: chosen by
#: the metric's probe (docs/design-decisions.md, "The QP metric: what the tool feels").
TOOL_ACCELERATION = 10.0
#: The smallest ``tool_acceleration`` [m/s²]. The UR5e's and the Panda's tools move at up to 90 and
#: 150 m/s² per unit of the scaled torque (``‖G‖₂``), so at 0.1 ``H = I + GᵀG / a²`` already has a
#: condition number of about 10⁶: below it the QP grows ill-conditioned, for nothing the metric's
#: measurements ask for (a = 1 did worse than 3 and 10).
MIN_TOOL_ACCELERATION = 0.1
#: ``FilterConfig.guard``'s named choices besides a Barrier instance and the barrier names.
GUARDS = ("auto", None, "none")

#: The gains γ₁ = γ₂ [1/s] of the guard ``guard="auto"`` puts beside the C3BF (a distance
#: HOCBF) when ``guard_gamma`` is None. Chosen by the guarantee sweep (docs/design-decisions.md).
GUARD_GAMMA = 10.0


@dataclass(frozen=True)
class FilterConfig:
    """Every setting of the safety filter, validated when built; the one place its defaults live.

    ``SafetyFilter``, ``gym.make(..., safety_filter=...)``, the experiments, training and the
    benchmarks all take or build one. Named configurations (:data:`FILTERS`) come from
    :meth:`named`; ``dataclasses.replace`` (or :meth:`replace`) derives variants, validated again.

    Attributes:
        barrier: the obstacle barrier, ``"c3bf"`` (:class:`~c3bf_gym.safety.barriers.C3BF`) or
            ``"hocbf"`` (:class:`~c3bf_gym.safety.barriers.DistanceHOCBF`), or a
            :class:`~c3bf_gym.safety.barriers.Barrier` instance.
        gamma: the named barrier's class-K gain [1/s] (C3BF: γ; HOCBF: γ₁ = γ₂); None for the
            barrier's own default (5). Must be None with a Barrier instance (it carries its own).
        guard: a second barrier whose row, for every (sensed obstacle, protected point), holds
            beside the barrier's. ``"auto"``: a distance HOCBF beside the C3BF and nothing beside
            any other barrier; None (or ``"none"``, read as None): no guard; a barrier name or a
            Barrier instance. The C3BF bounds only the direction of approach; the distance HOCBF
            bounds the approach speed by the distance left.
        guard_gamma: the named guard's gains [1/s] (HOCBF: γ₁ = γ₂); None for
            :data:`GUARD_GAMMA` with ``"auto"``, else the named barrier's default. Must be None
            without a named guard.
        points: ``"whole_arm"`` (the closest point of every link capsule) or ``"ee"`` (a sphere
            of ``ee_radius`` at the tool site, as in the paper).
        margin: extra clearance added to every combined radius [m], >= 0.
        sensing_radius: obstacles whose surface is farther than this from the arm add no row
            [m], > 0; None for the environment's own (the paper's perception boundary).
        ee_radius: radius of the protected tool sphere with ``points="ee"`` [m], >= 0.
        joint_limits: add the ``4 n`` joint position and speed rows.
        joint_speed_fraction: the joint speed bound as a fraction of the robot's own
            (:attr:`~c3bf_gym.safety.RobotDescription.joint_speed_limit`), in (0, 1].
        joint_range_reserve: [rad or m] keep every joint this far inside its range (at most a
            quarter of the range), >= 0; 0 (the default): no reserve, the joints may run to their
            limits. The reserve is a level of priority of its own, below the guard, the floor
            and the joint limits at the range itself, above the barrier's rows: in a pinch the
            guard (and the other rows of that level) can take a joint into the last of its
            range, which an escape may need; the barrier's rows and the nominal torque cannot.
            Needs ``joint_limits``.
        nominal_speed_fraction: the joint speed bound the nominal torque is held to, as a fraction
            of the robot's own, in (0, ``joint_speed_fraction``]; None (the default): the same as
            ``joint_speed_fraction``, one bound for every row. Below ``joint_speed_fraction`` the
            joints keep a speed reserve for escapes: the speed rows at this bound form a level of
            priority of their own below the barrier's rows, their copies at
            ``joint_speed_fraction`` stay in level 1. So the nominal torque drives no joint past
            this bound, while the barrier's rows (turning the arm's velocity out of a collision
            cone can need a joint to speed up) and the guard may take it up to
            ``joint_speed_fraction``, never past it. Needs ``joint_limits``.
        allowance_level: when the rows conflict, hold the barrier's rows first loosened by their
            allowance (the barrier condition ``ḣ ≥ −γ' h`` with the gain raised up to
            ``γ_max`` = 0.5/Δt where ``h > 0``; as written where ``h ≤ 0``), in a level of priority
            below the guard's and the joint range's reserve, and as written only last. The
            QP then lets a barrier row give way beyond its allowance (an infeasible step) only
            where no torque the levels above allow holds it within, instead of spreading a conflict
            over all of the barrier's rows by least squares. False (the default): one level for
            the barrier's rows. Needs a guard (without one the barrier's rows share level 1).
        floor_gamma: gain [1/s] of the floor rows' second-order barrier, > 0: every capsule end
            that can move vertically keeps ``margin`` above an upright world plane. The arm's own
            pairs (``self_collision``) use it too.
        self_collision: keep the pairs of the arm's protected capsules that the model lets collide
            ``margin`` apart, each with a second-order barrier row of gain ``floor_gamma``
            (:class:`~c3bf_gym.safety.barriers.SelfCollision`): contact forces between links are
            not in the filter's model, so a link pressed against another could be pushed past
            the rows. True (the default) adds those rows; a model whose links cannot collide with
            each other (the UR5e's and the Panda's here) has none either way.
        weight: the QP metric, what a change of the nominal torque costs: ``"limits"``
            (``‖u − u_nom‖²`` in the scaled torque ``u = τ / τ_max``: relative changes weigh the
            same on every joint), ``"identity"`` (the paper's plain ``‖τ − τ_nom‖²``) or
            ``"tool"`` (``(u − u_nom)ᵀ (I + GᵀG / a²) (u − u_nom)``, ``G = J (M + hD)⁻¹
            diag(τ_max)`` the tool site's acceleration per unit of ``u`` and ``a`` =
            ``tool_acceleration``: the ``"limits"`` metric, plus a cost on what the correction
            does to the tool's acceleration. Of the safe torques it prefers those that move the
            links the obstacles press on and leave the tool where the nominal torque takes it:
            a redundant arm has joint motions the tool does not feel. The rows and their
            priorities are the same in every metric: where every row can hold, only which safe
            torque is taken changes; where the rows of a level conflict, DAQP measures their
            violations in the metric, so the conflict spreads differently over that level's
            rows (:mod:`c3bf_gym.safety._qp`). Needs a tool site).
        tool_acceleration: ``a`` of the ``"tool"`` metric [m/s²], >= :data:`MIN_TOOL_ACCELERATION`:
            a change of the tool's acceleration by ``a`` costs as much as a change of one
            joint's torque by its limit. Smaller: the tool held more firmly, the other joints
            spent more freely. None: :data:`TOOL_ACCELERATION` with ``weight="tool"``; must be
            None with any other weight.
        on_infeasible: what happens when no torque within the limits satisfies every row:
            ``"relax"`` (the rows give way by priority, the barrier's first, and the step is
            reported: :mod:`c3bf_gym.safety.priority_qp`) or
            ``"raise"`` (raise :class:`~c3bf_gym.safety.SafetyInfeasibleError`; the environment is restored to its
            state before the step).
        intervention_tol: ‖τ − τ_nom‖ above which a physics step counts as an intervention
            [N m], >= 0.

    Raises:
        ValueError: on an unknown name or choice (the message lists the valid ones), a value
            out of its range, or inconsistent settings (a gain beside a Barrier instance, a
            ``guard_gamma`` without a named guard, a ``joint_range_reserve`` or
            ``nominal_speed_fraction`` without ``joint_limits``, a ``nominal_speed_fraction``
            above ``joint_speed_fraction``, an ``allowance_level`` without a guard, a
            ``tool_acceleration`` without ``weight="tool"``).
    """

    barrier: str | Barrier = "c3bf"
    gamma: float | None = None
    guard: str | Barrier | None = "auto"
    guard_gamma: float | None = None
    points: Literal["whole_arm", "ee"] = "whole_arm"
    margin: float = 0.02
    sensing_radius: float | None = None
    ee_radius: float = 0.05
    joint_limits: bool = True
    joint_speed_fraction: float = 0.5
    joint_range_reserve: float = 0.0
    nominal_speed_fraction: float | None = None
    allowance_level: bool = False
    floor_gamma: float = 10.0
    self_collision: bool = True
    weight: Literal["limits", "identity", "tool"] = "limits"
    tool_acceleration: float | None = None
    on_infeasible: Literal["relax", "raise"] = "relax"
    intervention_tol: float = 1e-3

    def __post_init__(self) -> None:
        check = validation
        set_ = object.__setattr__
        if not isinstance(self.barrier, Barrier):
            _choice_or_barrier("barrier", self.barrier, BARRIERS)
        if self.gamma is not None:
            if isinstance(self.barrier, Barrier):
                raise ValueError("gamma was given beside a Barrier instance: pass the gain to the instance, or name "
                                 "the barrier")  # fmt: skip
            set_(self, "gamma", check.number("gamma", self.gamma, low=0.0, low_open=True, unit="1/s"))
        guard = self.guard
        if not isinstance(guard, Barrier):
            guard = _choice_or_barrier("guard", guard, (*GUARDS, *BARRIERS))
            set_(self, "guard", None if guard == "none" else guard)
        if self.guard_gamma is not None:
            if not isinstance(self.guard, str) or (self.guard == "auto" and self.resolved_guard() is None):
                raise ValueError(
                    f"guard_gamma was given, but guard={self.guard!r} puts no named guard beside barrier "
                    f"{self.barrier!r} (guard_gamma sets the gains of 'auto' beside the C3BF, or of a guard named "
                    f"by {', '.join(map(repr, BARRIERS))})"
                )
            set_(self, "guard_gamma", check.number("guard_gamma", self.guard_gamma, low=0.0, low_open=True,
                                                   unit="1/s"))  # fmt: skip
        check.choice("points", self.points, POINTS)
        set_(self, "margin", check.number("margin", self.margin, low=0.0, unit="m"))
        if self.sensing_radius is not None:
            set_(self, "sensing_radius", check.number("sensing_radius", self.sensing_radius, low=0.0, low_open=True,
                                                      unit="m"))  # fmt: skip
        set_(self, "ee_radius", check.number("ee_radius", self.ee_radius, low=0.0, unit="m"))
        set_(self, "joint_limits", check.boolean("joint_limits", self.joint_limits))
        set_(self, "joint_speed_fraction", check.number("joint_speed_fraction", self.joint_speed_fraction, low=0.0,
                                                        low_open=True, high=1.0))  # fmt: skip
        set_(self, "joint_range_reserve", check.number("joint_range_reserve", self.joint_range_reserve, low=0.0))
        if self.joint_range_reserve > 0.0 and not self.joint_limits:
            raise ValueError(f"joint_range_reserve={self.joint_range_reserve!r} needs joint_limits=True: the "
                             "reserve is kept by the joint limits' rows")
        if self.nominal_speed_fraction is not None:
            set_(self, "nominal_speed_fraction", check.number("nominal_speed_fraction", self.nominal_speed_fraction,
                                                              low=0.0, low_open=True, high=1.0))  # fmt: skip
            if not self.joint_limits:
                raise ValueError(f"nominal_speed_fraction={self.nominal_speed_fraction!r} needs joint_limits=True: "
                                 "the speed bound is kept by the joint limits' rows")
            if self.nominal_speed_fraction > self.joint_speed_fraction:
                raise ValueError(f"nominal_speed_fraction={self.nominal_speed_fraction!r} is above "
                                 f"joint_speed_fraction={self.joint_speed_fraction!r}: the nominal torque's bound must "
                                 "be at most the filter's")
        set_(self, "allowance_level", check.boolean("allowance_level", self.allowance_level))
        if self.allowance_level and self.resolved_guard() is None:
            raise ValueError(f"allowance_level=True needs a guard beside the barrier (guard={self.guard!r}): "
                             "without one the barrier's rows share level 1 with the joint limits and the floor")
        set_(self, "floor_gamma", check.number("floor_gamma", self.floor_gamma, low=0.0, low_open=True, unit="1/s"))
        set_(self, "self_collision", check.boolean("self_collision", self.self_collision))
        check.choice("weight", self.weight, WEIGHTS)
        if self.tool_acceleration is not None:
            if self.weight != "tool":
                raise ValueError(f"tool_acceleration={self.tool_acceleration!r} was given with weight={self.weight!r}: "
                                 "it sets the 'tool' metric's a (weight='tool')")  # fmt: skip
            set_(self, "tool_acceleration", check.number("tool_acceleration", self.tool_acceleration,
                                                         low=MIN_TOOL_ACCELERATION, unit="m/s^2"))  # fmt: skip
        check.choice("on_infeasible", self.on_infeasible, ON_INFEASIBLE)
        set_(self, "intervention_tol", check.number("intervention_tol", self.intervention_tol, low=0.0, unit="N m"))

    @classmethod
    def named(cls, name: str, **changes: Any) -> FilterConfig:
        """The configuration :data:`FILTERS` names ``name``, with ``changes`` to its fields."""
        settings = FILTERS.get(name) if isinstance(name, str) else None
        if settings is None:
            raise ValueError(f"unknown filter {name!r}; valid choices: {', '.join(map(repr, FILTERS))}")
        return cls(**settings).replace(**changes)

    def replace(self, **changes: Any) -> FilterConfig:
        """A copy with ``changes`` to its fields (validated); unknown names are a ValueError."""
        unknown = sorted(set(changes) - {f.name for f in dataclasses.fields(self)})
        if unknown:
            raise ValueError(f"unknown filter setting(s) {', '.join(map(repr, unknown))}; valid settings: "
                             f"{', '.join(f.name for f in dataclasses.fields(self))}")  # fmt: skip
        return dataclasses.replace(self, **changes) if changes else self

    @property
    def name(self) -> str | None:
        """The :data:`FILTERS` name of this configuration's rows (barrier and guard, whatever the
        other settings), with the guard's gains appended when they are not the default
        (``"c3bf+hocbf20"``); None for Barrier instances."""
        if isinstance(self.barrier, Barrier) or isinstance(self.guard, Barrier):
            return None
        guard = self.resolved_guard()
        if guard is None:
            return self.barrier
        gains = self.guard_object().gamma
        return f"{self.barrier}+{guard}" + ("" if gains == GUARD_GAMMA else f"{gains:g}")

    def resolved_tool_acceleration(self) -> float | None:
        """The ``"tool"`` metric's ``a`` [m/s²]: ``tool_acceleration``, or
        :data:`TOOL_ACCELERATION` when that is None; None with another weight."""
        if self.weight != "tool":
            return None
        return TOOL_ACCELERATION if self.tool_acceleration is None else self.tool_acceleration

    def resolved_guard(self) -> str | Barrier | None:
        """The guard itself: ``"auto"`` resolved against the barrier (``"hocbf"`` beside the C3BF)."""
        if self.guard != "auto":
            return self.guard
        is_c3bf = self.barrier == "c3bf" or isinstance(self.barrier, C3BF)
        return "hocbf" if is_c3bf else None

    def resolved_guard_gamma(self) -> float | None:
        """The named guard's gains (None: the named barrier's default, or no named guard)."""
        if self.guard_gamma is not None or self.guard != "auto":
            return self.guard_gamma
        return GUARD_GAMMA if self.resolved_guard() is not None else None

    def barrier_object(self) -> Barrier:
        """The barrier as a :class:`~c3bf_gym.safety.barriers.Barrier`."""
        return self.barrier if isinstance(self.barrier, Barrier) else _named_barrier(self.barrier, self.gamma)

    def guard_object(self) -> Barrier | None:
        """The guard as a :class:`~c3bf_gym.safety.barriers.Barrier`, or None."""
        guard = self.resolved_guard()
        if guard is None or isinstance(guard, Barrier):
            return guard
        return _named_barrier(guard, self.resolved_guard_gamma())


def _choice_or_barrier(name: str, value: Any, choices: tuple) -> Any:
    """:func:`~c3bf_gym.validation.choice`, whose error also offers a Barrier instance."""
    try:
        return validation.choice(name, value, choices)
    except ValueError as error:
        raise ValueError(f"{error}, or a Barrier instance") from None


def _named_barrier(name: str, gamma: float | None) -> Barrier:
    """The barrier of :data:`~c3bf_gym.safety.barriers.BARRIERS` named ``name``, with ``gamma`` as all its
    gains (None: its defaults)."""
    if gamma is None:
        return make_barrier(name)
    return make_barrier(name, **({"gamma1": gamma, "gamma2": gamma} if name == "hocbf" else {"gamma": gamma}))


#: The named filters: each a :class:`FilterConfig`'s barrier and guard (the other settings at
#: their defaults). One name means one filter everywhere: the API, ``gym.make``, the command
#: line, the experiments, training runs, tables and plots.
FILTERS: dict[str, dict[str, Any]] = {
    "c3bf+hocbf": {"barrier": "c3bf", "guard": "auto"},
    "c3bf": {"barrier": "c3bf", "guard": None},
    "hocbf": {"barrier": "hocbf", "guard": None},
}
#: The filter :class:`~c3bf_gym.SafetyFilter` applies by default: the C3BF with its distance-HOCBF guard.
DEFAULT_FILTER = "c3bf+hocbf"
