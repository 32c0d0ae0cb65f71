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
given, so a seed fixes the episode. The attempts run in compiled code (numba, which draws from the
same ``numpy.random.Generator`` with numpy's own algorithms), so a reset costs microseconds per
attempt rather than a Python loop's tens. Every field is checked when its object is built (numbers are
Python or numpy numbers, ranges exactly two of them; see :mod:`c3bf_gym.validation`), and
:func:`max_spawn_distance` bounds where a spec can spawn, so that a spec the envelope can never
place is refused before any sampling.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np
from numba import njit

from c3bf_gym import _compile_cache  # noqa: F401  (before any @njit(cache=True): the cache keys)
from c3bf_gym.validation import choice, number, number_range, sequence

__all__ = [
    "MAX_OBSTACLES",
    "SCENARIOS",
    "ArmCapsules",
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
        """Whether the straight path from ``start`` over ``horizon`` s respects keep-out and floor.

        The floor: both ends stay ``radius`` above ``min_height``. The keep-out cylinder: when
        either end is below ``keep_out_height`` (plus ``radius``), the horizontal projection of
        the path stays ``keep_out_radius + radius`` from the base's vertical axis (conservative:
        the whole segment is checked). The sampler's own check (compiled).
        """
        return bool(_path_ok(self._compiled, np.asarray(start, dtype=np.float64),
                             np.asarray(velocity, dtype=np.float64), float(radius)))

    def contains(self, position: np.ndarray) -> bool:
        low, high = self.workspace
        return bool(np.all(position >= low) and np.all(position <= high))

    @functools.cached_property
    def _compiled(self) -> _EnvelopeArrays:
        """The envelope as the compiled sampler reads it."""
        return _EnvelopeArrays(self.speed_range, self.radius_range, self.spawn_clearance, self.keep_out_radius,
                               self.keep_out_height, self.min_height, self.horizon,
                               *(np.array(corner, dtype=np.float64) for corner in self.workspace))


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
SCENARIOS["random_multi"] = Scenario(
    "random_multi", mixture=("static", "head_on", "crossing", "multi", "multi", "multi"),
    description="the four, multi in half the episodes (a training mixture; evaluate on random)",
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


@dataclass(frozen=True)
class ArmCapsules:
    """The arm as the sampler keeps obstacles clear of it: capsules about the segments ``a[g]`` to
    ``b[g]`` (``G`` of them; a sphere is a segment of length 0) with radii ``radius[g]``.

    Attributes:
        a, b: (G, 3) the segments' end points [m].
        radius: (G,) [m], >= 0.

    Stored as float64 arrays; ``ValueError`` names the field for other shapes, NaN or inf, or a
    negative radius.
    """

    a: np.ndarray
    b: np.ndarray
    radius: np.ndarray

    def __post_init__(self) -> None:
        count = np.shape(self.radius)[0] if np.ndim(self.radius) == 1 else -1
        for name, shape in (("a", (count, 3)), ("b", (count, 3)), ("radius", (count,))):
            value = np.ascontiguousarray(getattr(self, name), dtype=np.float64)
            if count < 0 or value.shape != shape or not np.isfinite(value).all():
                raise ValueError(f"ArmCapsules needs a and b of shape (G, 3) and radius of shape (G,), all finite; "
                                 f"got shapes {np.shape(self.a)}, {np.shape(self.b)}, {np.shape(self.radius)}")
            object.__setattr__(self, name, value)
        if (self.radius < 0.0).any():
            raise ValueError(f"ArmCapsules radius must be >= 0 [m], got {self.radius.tolist()}")

    @classmethod
    def none(cls) -> ArmCapsules:
        """No arm: every candidate is clear of it."""
        return cls(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))

    def clearance(self, centre: np.ndarray, radius: float) -> float:
        """The smallest surface distance [m] from the sphere (``centre`` (3,) [m], ``radius`` [m])
        to the capsules, negative when it overlaps one; ``inf`` without capsules."""
        return float(_clearance(self._compiled, np.asarray(centre, dtype=np.float64), float(radius)))

    @functools.cached_property
    def _compiled(self) -> _ArmArrays:
        """The capsules as the compiled sampler reads them."""
        return _ArmArrays(self.a, self.b, self.radius)


#: the kinds' codes in the compiled sampler
_KIND_CODES = {kind: code for code, kind in enumerate(_KINDS)}


class _SpecArrays(NamedTuple):
    """An :class:`ObstacleSpec` as the compiled sampler reads it."""

    kind: int
    path_fraction: tuple[float, float]
    meet_time: tuple[float, float]
    crossing_angle: tuple[float, float]
    lateral_jitter: float


class _EnvelopeArrays(NamedTuple):
    """An :class:`Envelope` as the compiled sampler reads it."""

    speed_range: tuple[float, float]
    radius_range: tuple[float, float]
    spawn_clearance: float
    keep_out_radius: float
    keep_out_height: float
    min_height: float
    horizon: float
    low: np.ndarray
    high: np.ndarray


class _ArmArrays(NamedTuple):
    """:class:`ArmCapsules` as the compiled sampler reads it."""

    a: np.ndarray
    b: np.ndarray
    radius: np.ndarray


@dataclass
class ObstacleSampler:
    """Draws obstacle trajectories inside an :class:`Envelope`, clear of an arm.

    ``max_attempts`` bounds the draws per call of :meth:`sample`.
    """

    envelope: Envelope
    max_attempts: int = 200

    def __post_init__(self) -> None:
        self._specs: dict[ObstacleSpec, _SpecArrays] = {}
        self._out = np.zeros(7)

    def sample(
        self, spec: ObstacleSpec, start: np.ndarray, goal: np.ndarray, rng: np.random.Generator, arm: ArmCapsules
    ) -> ObstacleSample | None:
        """One trajectory for ``spec`` around the path ``start`` -> ``goal`` (3,) [m]; None if none
        of ``max_attempts`` draws fits.

        Each attempt draws, from ``rng`` and in this order: the radius (uniform in the envelope's
        range), the path point's fraction of the way from start to goal (uniform), a lateral
        offset (normal, ``lateral_jitter`` per axis), and for a moving obstacle its speed
        (uniform), for a crossing one the roll of its heading about the path and its angle to it
        (uniform), and the time until it meets the path point (uniform); the spawn point is the
        path point moved back along the heading by speed times that time. It is accepted when
        the spawn point lies in the envelope's workspace, its straight path over ``horizon``
        respects the keep-out cylinder and the floor (:meth:`Envelope.path_ok`), and its surface
        is at least ``spawn_clearance`` from every capsule of ``arm``.
        """
        if not isinstance(spec, ObstacleSpec) or not isinstance(arm, ArmCapsules):
            raise TypeError(f"sample needs an ObstacleSpec and ArmCapsules, got {type(spec).__name__} and "
                            f"{type(arm).__name__}")
        params = self._specs.get(spec)
        if params is None:
            params = self._specs[spec] = _SpecArrays(_KIND_CODES[spec.kind], spec.path_fraction, spec.meet_time,
                                                     spec.crossing_angle, spec.lateral_jitter)
        out = self._out
        start, goal = (np.ascontiguousarray(x, dtype=np.float64) for x in (start, goal))
        if start.shape != (3,) or goal.shape != (3,) or not (np.isfinite(start).all() and np.isfinite(goal).all()):
            raise ValueError(f"start and goal must be finite points of shape (3,) [m], got {start!r} and {goal!r}")
        if not _sample(params, self.envelope._compiled, arm._compiled, start, goal, rng, self.max_attempts, out):
            return None
        return ObstacleSample(out[:3].copy(), out[3:6].copy(), float(out[6]))


_opts = {"cache": True, "nogil": True, "error_model": "numpy", "boundscheck": False}


@njit(**_opts)
def _path_ok(envelope, start, velocity, radius):
    """:meth:`Envelope.path_ok` on the envelope's :class:`_EnvelopeArrays`."""
    end0 = start[0] + velocity[0] * envelope.horizon
    end1 = start[1] + velocity[1] * envelope.horizon
    end2 = start[2] + velocity[2] * envelope.horizon
    low_z = min(start[2], end2) - radius
    if low_z < envelope.min_height:
        return False
    if low_z > envelope.keep_out_height:
        return True
    ab0, ab1 = end0 - start[0], end1 - start[1]
    denom = ab0 * ab0 + ab1 * ab1
    t = 0.0 if denom == 0.0 else min(max(-(start[0] * ab0 + start[1] * ab1) / denom, 0.0), 1.0)
    x, y = start[0] + t * ab0, start[1] + t * ab1
    return math.sqrt(x * x + y * y) >= envelope.keep_out_radius + radius


@njit(**_opts)
def _clearance(arm, centre, radius):
    """The smallest surface distance [m] from the sphere (``centre``, ``radius``) to the capsules
    of ``arm`` (:class:`_ArmArrays`; ``inf`` without one)."""
    a, b, capsule_radius = arm.a, arm.b, arm.radius
    gap = np.inf
    for g in range(a.shape[0]):
        ab0, ab1, ab2 = b[g, 0] - a[g, 0], b[g, 1] - a[g, 1], b[g, 2] - a[g, 2]
        length2 = ab0 * ab0 + ab1 * ab1 + ab2 * ab2
        t = 0.0
        if length2 > 0.0:
            t = ((centre[0] - a[g, 0]) * ab0 + (centre[1] - a[g, 1]) * ab1 + (centre[2] - a[g, 2]) * ab2) / length2
            t = min(max(t, 0.0), 1.0)
        d0 = centre[0] - (a[g, 0] + t * ab0)
        d1 = centre[1] - (a[g, 1] + t * ab1)
        d2 = centre[2] - (a[g, 2] + t * ab2)
        gap = min(gap, math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) - capsule_radius[g] - radius)
    return gap


@njit(**_opts)
def _sample(spec, envelope, arm, start, goal, rng, max_attempts, out):
    """:meth:`ObstacleSampler.sample`'s attempts, for ``spec`` (:class:`_SpecArrays`) in ``envelope``
    (:class:`_EnvelopeArrays`) clear of ``arm`` (:class:`_ArmArrays`): on success ``out`` (7,) holds
    position (3,), velocity (3,) and radius, and the result is True. The arithmetic is element by element in the
    order of the numpy expressions it replaced, so the draws and samples are theirs bit for bit."""
    path = np.empty(3)
    direction = np.empty(3)
    target = np.empty(3)
    velocity = np.empty(3)
    position = np.empty(3)
    for i in range(3):
        path[i] = goal[i] - start[i]
    length = math.sqrt(path[0] * path[0] + path[1] * path[1] + path[2] * path[2])
    for i in range(3):
        direction[i] = path[i] / length if length > 0 else (1.0 if i == 0 else 0.0)
    # the crossing headings' frame: a normal and a binormal of the path
    normal = np.empty(3)
    binormal = np.empty(3)
    if spec.kind == 2:
        h0, h1, h2 = (0.0, 0.0, 1.0) if abs(direction[2]) < 0.9 else (1.0, 0.0, 0.0)
        normal[0] = direction[1] * h2 - direction[2] * h1
        normal[1] = direction[2] * h0 - direction[0] * h2
        normal[2] = direction[0] * h1 - direction[1] * h0
        size = math.sqrt(normal[0] * normal[0] + normal[1] * normal[1] + normal[2] * normal[2])
        for i in range(3):
            normal[i] /= size
        binormal[0] = direction[1] * normal[2] - direction[2] * normal[1]
        binormal[1] = direction[2] * normal[0] - direction[0] * normal[2]
        binormal[2] = direction[0] * normal[1] - direction[1] * normal[0]
    low, high = envelope.low, envelope.high
    for _ in range(max_attempts):
        radius = rng.uniform(envelope.radius_range[0], envelope.radius_range[1])
        fraction = rng.uniform(spec.path_fraction[0], spec.path_fraction[1])
        jitter = rng.normal(size=3)
        for i in range(3):
            target[i] = start[i] + fraction * path[i]
            target[i] = target[i] + jitter[i] * spec.lateral_jitter
        if spec.kind == 0:
            for i in range(3):
                velocity[i] = 0.0
                position[i] = target[i]
        else:
            speed = rng.uniform(envelope.speed_range[0], envelope.speed_range[1])
            if spec.kind == 1:
                for i in range(3):
                    velocity[i] = speed * -direction[i]
            else:
                roll = rng.uniform(0.0, 2.0 * np.pi)
                angle = rng.uniform(spec.crossing_angle[0], spec.crossing_angle[1]) * (np.pi / 180.0)
                cos_roll, sin_roll, cos_angle, sin_angle = math.cos(roll), math.sin(roll), math.cos(angle), math.sin(angle)
                for i in range(3):
                    side = cos_roll * normal[i] + sin_roll * binormal[i]
                    velocity[i] = speed * (cos_angle * direction[i] + sin_angle * side)
            meet = rng.uniform(spec.meet_time[0], spec.meet_time[1])
            for i in range(3):
                position[i] = target[i] - velocity[i] * meet
        inside = True
        for i in range(3):
            inside = inside and low[i] <= position[i] <= high[i]
        if (inside and _path_ok(envelope, position, velocity, radius)
                and _clearance(arm, position, radius) >= envelope.spawn_clearance):
            for i in range(3):
                out[i] = position[i]
                out[3 + i] = velocity[i]
            out[6] = radius
            return True
    return False
