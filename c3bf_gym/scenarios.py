"""Obstacle scenarios: the paper's four experiments and a mixture for RL, as data.

A scenario is a frozen :class:`Scenario` naming a tuple of :class:`ObstacleSpec` (what kind of
motion each obstacle makes) or a mixture of other scenarios. :class:`Envelope` is the generator's
promise, checked at every spawn and respawn:

* obstacles move in straight lines at constant velocity (the C3BF theorem's assumption), with
  speed in ``speed_range`` and radius in ``radius_range``;
* an obstacle spawns at least ``spawn_clearance`` (surface to surface) from every arm geom;
* an obstacle's whole straight path over ``horizon`` seconds stays out of the base keep-out
  cylinder (radius ``keep_out_radius`` around the base's vertical axis, up to ``keep_out_height``),
  inflated by its own radius: the base and shoulder cannot dodge, so no controller could;
* the path stays above ``min_height`` (no obstacle is sent through the floor).

Sampling is rejection-based with a bounded number of attempts, driven only by the generator it is
given, so a seed fixes the episode. Every field is checked when its object is built (numbers are
Python or numpy numbers, ranges exactly two of them; see :mod:`c3bf_gym.validation`), and
:func:`max_spawn_distance` bounds where a spec can spawn, so that a spec the envelope can never
place is refused before any sampling.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Literal

import numpy as np

from c3bf_gym.validation import choice, number, number_range, sequence

__all__ = [
    "MAX_OBSTACLES",
    "SCENARIOS",
    "Envelope",
    "ObstacleSpec",
    "Scenario",
    "ObstacleSample",
    "ObstacleSampler",
    "get_scenario",
    "max_spawn_distance",
]

#: Obstacle slots in the scene (``obstacle_0`` ... ``obstacle_7``) and in the observation.
MAX_OBSTACLES = 8

ObstacleKind = Literal["static", "head_on", "crossing"]
_KINDS = ("static", "head_on", "crossing")


#: :func:`max_spawn_distance` takes a lateral jitter draw (a 3-D normal vector) to be at most this
#: many standard deviations long: a longer one has probability below 1e-13.
JITTER_SIGMAS = 8.0


@dataclass(frozen=True)
class Envelope:
    """What every generated obstacle satisfies. Lengths in m, speeds in m/s, times in s."""

    speed_range: tuple[float, float] = (0.1, 0.4)
    radius_range: tuple[float, float] = (0.04, 0.08)
    spawn_clearance: float = 0.2
    keep_out_radius: float = 0.3
    keep_out_height: float = 0.45
    min_height: float = 0.05
    horizon: float = 5.0
    #: Axis-aligned box (low, high corners) the obstacles live in; leaving it means a respawn.
    workspace: tuple[tuple[float, float, float], tuple[float, float, float]] = (
        (-1.2, -1.2, -0.2),
        (1.4, 1.2, 1.4),
    )

    def __post_init__(self) -> None:
        set_field = object.__setattr__  # frozen: fields are stored in their canonical types
        set_field(self, "speed_range", number_range("speed_range", self.speed_range, low=0.0, unit="m/s"))
        set_field(self, "radius_range", number_range("radius_range", self.radius_range, low=0.0, low_open=True, unit="m"))
        for name in ("spawn_clearance", "keep_out_radius", "keep_out_height", "min_height", "horizon"):
            set_field(self, name, number(name, getattr(self, name), low=0.0, unit="s" if name == "horizon" else "m"))
        form = "((xlo, ylo, zlo), (xhi, yhi, zhi)): two corners of three finite numbers with lo < hi [m]"
        try:
            corners = sequence("workspace", self.workspace, object, form)
            low, high = (tuple(number("workspace", x) for x in sequence("workspace", c, object, form)) for c in corners)
        except ValueError:
            raise ValueError(f"workspace must be {form}, got {self.workspace!r}") from None
        if len(low) != 3 or len(high) != 3 or not all(lo < hi for lo, hi in zip(low, high)):
            raise ValueError(f"workspace must be {form}, got {self.workspace!r}")
        set_field(self, "workspace", (low, high))

    def path_ok(self, start: np.ndarray, velocity: np.ndarray, radius: float) -> bool:
        """Whether the straight path from ``start`` over ``horizon`` s respects keep-out and floor."""
        end = start + velocity * self.horizon
        if min(start[2], end[2]) - radius < self.min_height:
            return False
        # Closest approach of the horizontal projection of the segment to the base axis, checked
        # only where the segment is below the keep-out height (conservatively: if either end is).
        if min(start[2], end[2]) - radius > self.keep_out_height:
            return True
        a, b = start[:2], end[:2]
        ab = b - a
        denom = float(ab @ ab)
        t = 0.0 if denom == 0.0 else float(np.clip(-(a @ ab) / denom, 0.0, 1.0))
        return float(np.linalg.norm(a + t * ab)) >= self.keep_out_radius + radius

    def contains(self, position: np.ndarray) -> bool:
        low, high = self.workspace
        return bool(np.all(position >= low) and np.all(position <= high))


@dataclass(frozen=True)
class ObstacleSpec:
    """One obstacle's motion relative to the tool's start-to-goal path.

    * ``static``: at rest on the path (``path_fraction`` of the way from start to goal).
    * ``head_on``: moves along the path, from beyond the goal towards the tool's start.
    * ``crossing``: crosses the path at ``crossing_angle`` (deg, from the path direction).

    Moving obstacles reach the path point ``meet_time`` seconds after spawning. Ranges are
    ``(low, high)``: ``path_fraction`` >= 0 (and for a static obstacle reaching above 0: at 0 it
    would sit on the tool's start, inside the arm), ``meet_time`` > 0 [s], ``crossing_angle`` > 0
    [deg]; ``lateral_jitter`` >= 0 [m] is the standard deviation of a normal offset per axis.
    """

    kind: ObstacleKind
    path_fraction: tuple[float, float] = (0.35, 0.65)
    meet_time: tuple[float, float] = (0.8, 2.0)
    crossing_angle: tuple[float, float] = (50.0, 90.0)
    lateral_jitter: float = 0.02

    def __post_init__(self) -> None:
        set_field = object.__setattr__  # frozen: fields are stored in their canonical types
        set_field(self, "kind", choice("obstacle kind", self.kind, _KINDS))
        path_fraction = number_range("path_fraction", self.path_fraction, low=0.0)
        if self.kind == "static" and path_fraction[1] == 0.0:
            raise ValueError(
                "path_fraction must be (low, high) with high > 0 for a static obstacle (at 0 it sits on the "
                f"tool's start, inside the arm, and can never spawn clear of it), got {self.path_fraction!r}"
            )
        set_field(self, "path_fraction", path_fraction)
        set_field(self, "meet_time", number_range("meet_time", self.meet_time, low=0.0, low_open=True, unit="s"))
        set_field(
            self, "crossing_angle", number_range("crossing_angle", self.crossing_angle, low=0.0, low_open=True, unit="deg")
        )
        set_field(self, "lateral_jitter", number("lateral_jitter", self.lateral_jitter, low=0.0, unit="m"))


@dataclass(frozen=True)
class ObstacleSample:
    position: np.ndarray  # (3,) m
    velocity: np.ndarray  # (3,) m/s
    radius: float  # m


@dataclass(frozen=True)
class Scenario:
    """A named set of obstacles, or (``mixture``) a uniform choice among other scenarios.

    ``obstacles`` is a sequence of :class:`ObstacleSpec` and ``mixture`` of names of registered
    (:data:`SCENARIOS`) scenarios that are not mixtures themselves; both are stored as tuples and a
    scenario has one or the other, not both. Checked when built: ``ValueError`` names the field.
    """

    name: str
    obstacles: tuple[ObstacleSpec, ...] = ()
    mixture: tuple[str, ...] = ()
    description: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.name, str):
            raise ValueError(f"Scenario name must be a string, got {self.name!r}")
        if not isinstance(self.description, str):
            raise ValueError(f"Scenario description must be a string, got {self.description!r}")
        obstacles = sequence("obstacles", self.obstacles, ObstacleSpec, "ObstacleSpec instances (a tuple of them)")
        mixture = sequence("mixture", self.mixture, str, "a tuple of scenario names")
        if obstacles and mixture:
            raise ValueError(
                f"scenario {self.name!r} has both obstacles and a mixture; give one: a mixture draws one of its "
                "scenarios per episode and would ignore the obstacles"
            )
        for name in mixture:
            if get_scenario(name).mixture:
                raise ValueError(f"scenario {self.name!r}: mixture component {name!r} is itself a mixture; "
                                 "components must be scenarios with obstacles (or none)")
        object.__setattr__(self, "obstacles", obstacles)
        object.__setattr__(self, "mixture", mixture)

    def resolve(self, rng: np.random.Generator) -> Scenario:
        """The concrete scenario for one episode (itself, or one mixture component)."""
        if not self.mixture:
            return self
        return get_scenario(self.mixture[int(rng.integers(len(self.mixture)))])


#: The registered scenarios by name (what ``get_scenario`` and mixtures look up), in this order.
SCENARIOS: dict[str, Scenario] = {}


def get_scenario(name: str) -> Scenario:
    """The registered scenario ``name``; ``ValueError`` listing the valid names otherwise."""
    return SCENARIOS[choice("scenario", name, SCENARIOS)]


for _scenario in (
    Scenario("static", (ObstacleSpec("static"),), description="one obstacle at rest on the tool's path"),
    Scenario("head_on", (ObstacleSpec("head_on"),), description="one obstacle coming down the path at the tool"),
    Scenario("crossing", (ObstacleSpec("crossing"),), description="one obstacle crossing the path at an angle"),
    Scenario(
        "multi",
        (ObstacleSpec("static"), ObstacleSpec("head_on"), ObstacleSpec("crossing"), ObstacleSpec("crossing")),
        description="four obstacles at once: static, head-on and two crossing",
    ),
):
    SCENARIOS[_scenario.name] = _scenario
# registered after its components, which building it looks up
SCENARIOS["random"] = Scenario(
    "random", mixture=("static", "head_on", "crossing", "multi"), description="a uniform mixture of the four"
)
SCENARIOS["none"] = Scenario("none", description="no obstacles (free reaching)")
del _scenario


def max_spawn_distance(spec: ObstacleSpec, envelope: Envelope, path_length: float) -> float:
    """How far (m) from the path's start an obstacle of ``spec`` can spawn, for paths of length at
    most ``path_length`` (m): its path point (``path_fraction``), plus the lateral jitter (taken as
    :data:`JITTER_SIGMAS` standard deviations), plus, when it moves, the distance it covers at the
    envelope's top speed in the longest ``meet_time``. :class:`ObstacleSampler` never draws a
    position farther away, so a spec needing more room than this can never be placed.
    """
    reach = spec.path_fraction[1] * path_length + JITTER_SIGMAS * spec.lateral_jitter
    if spec.kind != "static":
        reach += envelope.speed_range[1] * spec.meet_time[1]
    return reach


@dataclass
class ObstacleSampler:
    """Draws obstacle trajectories inside an :class:`Envelope`.

    ``clearance`` is a callable returning, for a candidate centre and radius, the smallest surface
    distance to the arm's geoms in its current configuration (the environment supplies it).
    """

    envelope: Envelope
    clearance: Callable[[np.ndarray, float], float]
    max_attempts: int = 200

    def sample(
        self, spec: ObstacleSpec, start: np.ndarray, goal: np.ndarray, rng: np.random.Generator
    ) -> ObstacleSample | None:
        """One trajectory for ``spec`` around the path ``start`` -> ``goal``; None if none fits."""
        env = self.envelope
        path = goal - start
        length = float(np.linalg.norm(path))
        direction = path / length if length > 0 else np.array([1.0, 0.0, 0.0])
        for _ in range(self.max_attempts):
            radius = float(rng.uniform(*env.radius_range))
            target = start + rng.uniform(*spec.path_fraction) * path
            target = target + rng.normal(size=3) * spec.lateral_jitter
            if spec.kind == "static":
                velocity = np.zeros(3)
                position = target
            else:
                speed = float(rng.uniform(*env.speed_range))
                if spec.kind == "head_on":
                    heading = -direction
                else:
                    heading = self._crossing_heading(direction, spec, rng)
                velocity = speed * heading
                position = target - velocity * rng.uniform(*spec.meet_time)
            if (
                env.contains(position)
                and env.path_ok(position, velocity, radius)
                and self.clearance(position, radius) >= env.spawn_clearance
            ):
                return ObstacleSample(position, velocity, radius)
        return None

    @staticmethod
    def _crossing_heading(direction: np.ndarray, spec: ObstacleSpec, rng: np.random.Generator) -> np.ndarray:
        # A unit vector at the drawn angle from the path direction, rotated about the path by a
        # random roll, so crossings come from any side.
        helper = np.array([0.0, 0.0, 1.0]) if abs(direction[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        normal = np.cross(direction, helper)
        normal /= np.linalg.norm(normal)
        binormal = np.cross(direction, normal)
        roll = rng.uniform(0.0, 2.0 * np.pi)
        side = np.cos(roll) * normal + np.sin(roll) * binormal
        angle = np.deg2rad(rng.uniform(*spec.crossing_angle))
        return np.cos(angle) * direction + np.sin(angle) * side
