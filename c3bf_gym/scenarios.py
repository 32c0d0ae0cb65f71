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
given, so a seed fixes the episode.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Literal

import numpy as np

__all__ = [
    "MAX_OBSTACLES",
    "SCENARIOS",
    "Envelope",
    "ObstacleSpec",
    "Scenario",
    "ObstacleSample",
    "ObstacleSampler",
    "get_scenario",
]

#: Obstacle slots in the scene (``obstacle_0`` ... ``obstacle_7``) and in the observation.
MAX_OBSTACLES = 8

ObstacleKind = Literal["static", "head_on", "crossing"]
_KINDS = ("static", "head_on", "crossing")


def _check_range(name: str, value: tuple[float, float], lower: float, allow_equal_lower: bool) -> tuple[float, float]:
    lo, hi = (float(v) for v in value)
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise ValueError(f"{name} must be finite, got {value!r}")
    if lo > hi:
        raise ValueError(f"{name} must be (low, high) with low <= high, got {value!r}")
    if lo < lower or (lo == lower and not allow_equal_lower):
        bound = ">=" if allow_equal_lower else ">"
        raise ValueError(f"{name} must be {bound} {lower}, got {value!r}")
    return lo, hi


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
        object.__setattr__(self, "speed_range", _check_range("speed_range", self.speed_range, 0.0, True))
        object.__setattr__(self, "radius_range", _check_range("radius_range", self.radius_range, 0.0, False))
        for name in ("spawn_clearance", "keep_out_radius", "keep_out_height", "min_height", "horizon"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        low, high = (np.asarray(c, dtype=float) for c in self.workspace)
        if low.shape != (3,) or high.shape != (3,) or not np.all(low < high):
            raise ValueError(f"workspace must be ((xlo, ylo, zlo), (xhi, yhi, zhi)) with lo < hi, got {self.workspace!r}")

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

    Moving obstacles reach the path point ``meet_time`` seconds after spawning.
    """

    kind: ObstacleKind
    path_fraction: tuple[float, float] = (0.35, 0.65)
    meet_time: tuple[float, float] = (0.8, 2.0)
    crossing_angle: tuple[float, float] = (50.0, 90.0)
    lateral_jitter: float = 0.02

    def __post_init__(self) -> None:
        if self.kind not in _KINDS:
            raise ValueError(f"unknown obstacle kind {self.kind!r}; valid choices: {', '.join(map(repr, _KINDS))}")
        _check_range("path_fraction", self.path_fraction, 0.0, True)
        _check_range("meet_time", self.meet_time, 0.0, False)
        _check_range("crossing_angle", self.crossing_angle, 0.0, False)


@dataclass(frozen=True)
class ObstacleSample:
    position: np.ndarray  # (3,) m
    velocity: np.ndarray  # (3,) m/s
    radius: float  # m


@dataclass(frozen=True)
class Scenario:
    """A named set of obstacles, or (``mixture``) a uniform choice among other scenarios."""

    name: str
    obstacles: tuple[ObstacleSpec, ...] = ()
    mixture: tuple[str, ...] = ()
    description: str = ""

    def resolve(self, rng: np.random.Generator) -> Scenario:
        """The concrete scenario for one episode (itself, or one mixture component)."""
        if not self.mixture:
            return self
        return get_scenario(self.mixture[int(rng.integers(len(self.mixture)))])


SCENARIOS: dict[str, Scenario] = {
    s.name: s
    for s in (
        Scenario("static", (ObstacleSpec("static"),), description="one obstacle at rest on the tool's path"),
        Scenario("head_on", (ObstacleSpec("head_on"),), description="one obstacle coming down the path at the tool"),
        Scenario("crossing", (ObstacleSpec("crossing"),), description="one obstacle crossing the path at an angle"),
        Scenario(
            "multi",
            (ObstacleSpec("static"), ObstacleSpec("head_on"), ObstacleSpec("crossing"), ObstacleSpec("crossing")),
            description="four obstacles at once: static, head-on and two crossing",
        ),
        Scenario("random", mixture=("static", "head_on", "crossing", "multi"), description="a uniform mixture of the four"),
        Scenario("none", description="no obstacles (free reaching)"),
    )
}


def get_scenario(name: str) -> Scenario:
    try:
        return SCENARIOS[name]
    except (KeyError, TypeError):
        raise ValueError(
            f"unknown scenario {name!r}; valid choices: {', '.join(map(repr, SCENARIOS))}"
        ) from None


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
