"""The envelope the filter states: the obstacle speed and sensing range within which the arm can
still get out of the way, computed from its torque limits, inertia and joint speed bounds.

A control barrier function keeps its guarantee only while some torque satisfies its rows. Against
a moving obstacle that is not only a matter of the next instant: the threatened point must be able
to leave the obstacle's path before the obstacle arrives, with the torques and joint speeds it
has. :func:`filter_envelope` checks that for every protected point the obstacles can reach, in
every direction they can come from, over a sample of the arm's configurations, and states the
result as a :class:`FilterEnvelope`: the largest obstacle speed the filter's sensing radius allows,
and (:meth:`FilterEnvelope.min_sensing_range`) the sensing radius a given speed needs.

**The escape argument.** An obstacle sphere (radius ``R_o``) is sensed when its surface is ``D``
(the sensing radius) from the arm, and comes at a protected point ``x`` on a capsule of radius
``R`` along a straight line ``w`` at speed ``V``, the arm at rest. Let
``r = R_o + R + margin`` be the clearance the filter keeps. The point escapes when, before the
obstacle arrives, it either

* **sidesteps**: moves ``r`` along some direction ``u ⊥ w``, so that the obstacle passes beside
  it. Moving along ``u``, its speed is at most the support of the joint-speed box,
  ``σ(u) = Σ_j |u·J_j| q̇_max,j``, and its acceleration at most the support of the torque box
  net of gravity and of the forces the filter cannot predict,
  ``α(u) = Σ_j |u·G_j| τ_max,j − Σ_k |u·G_k| f_k + u·c`` (``G = J M⁻¹``, ``c`` the acceleration at
  zero torque, ``f`` :attr:`~c3bf_gym.safety.RobotDescription.unmodelled_force`). Accelerating
  at ``α`` up to ``σ``, covering ``r`` takes ``t(u) = √(2r/α)`` when ``r ≤ σ²/2α``, else
  ``r/σ + σ/2α``; the sidestep time is ``t⊥ = min over u ⊥ w of t(u)``;
* **or outruns** it: moves away along ``w`` at ``V`` (possible when ``σ(w) ≥ V``), reaching that
  speed after the obstacle has closed ``V²/2α(w)``.

The distance HOCBF beside the C3BF (the guard, gains ``γ₁``) caps the closing speed by the gap
``g`` left, ``V ≤ γ₁ g (g + 2r) / 2(g + r)``: below the gap ``g_s(V)`` where that holds with
equality the point must already have stepped aside, or outrun. So the sensing radius a speed ``V``
needs at one (configuration, point, approach) is

    D(V) = g_s(V) + min( V t⊥,  V² / 2α(w)  if σ(w) ≥ V )

and :meth:`FilterEnvelope.min_sensing_range` is the largest ``D(V)`` over the sample;
``max_speed`` is the largest ``V`` with ``D(V)`` within the sensing radius (``D`` grows with ``V``
at every sample, so it is found by bisection).

**What it covers and what it does not.** It is a per-obstacle argument: several obstacles can
close in from opposite sides, where no sidestep serves both. It assumes the arm at rest when the
obstacle is sensed (a policy driving the arm at the obstacle adds its own speed to ``V``). It
samples: configurations (uniform in the joint ranges, with every capsule above the floor, and the
one given), five points along each capsule axis (ends and quarters), :data:`APPROACHES`
approach directions and twice :data:`SIDESTEPS` sidestep directions around each. And it says a safe
escape *exists*; that the filter's rows find it is measured, by the guarantee sweeps
(``docs/results/guarantee.md``). Points no obstacle can touch, because the scenario keeps
obstacles out of a cylinder about the base's vertical axis (``keep_out_radius``,
``keep_out_height``, as :class:`~c3bf_gym.scenarios.Envelope`'s), are left out: a base and a
shoulder cannot sidestep, and only a keep-out region protects them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import mujoco
import numpy as np

from c3bf_gym.safety.barriers import DistanceHOCBF
from c3bf_gym.safety.config import FilterConfig
from c3bf_gym.safety.dynamics import ArmModel
from c3bf_gym.safety.robot import RobotDescription, floor_height

__all__ = ["APPROACHES", "SIDESTEPS", "EnvelopeWarning", "FilterEnvelope", "filter_envelope"]

#: Approach directions sampled (a Fibonacci sphere).
APPROACHES = 64
#: Sidestep directions sampled around each approach: evenly over half the circle ``⊥ w``, each with
#: its opposite (``2 SIDESTEPS`` in all; their speed supports agree, their accelerations do not).
SIDESTEPS = 12
_LAMBDAS = np.array([0.0, 0.25, 0.5, 0.75, 1.0])  # points along each capsule axis


class EnvelopeWarning(UserWarning):
    """Obstacles outside what the filter states it can guarantee (:class:`FilterEnvelope`): too
    fast for the sensing radius, or larger than the envelope was computed for."""


@dataclass(frozen=True)
class FilterEnvelope:
    """What the filter states it can guarantee for one arm, filter configuration and obstacle size
    (:func:`filter_envelope`; the argument is in :mod:`c3bf_gym.safety.envelope`).

    Attributes:
        obstacle_radius: the largest obstacle radius it holds for [m].
        sensing_radius: the sensing radius it was computed for [m].
        max_speed: the largest obstacle speed a safe escape exists for at that sensing radius
            [m/s]; 0.0 when some reachable point cannot escape at all.
        keep_out_radius, keep_out_height: the cylinder about the base's vertical axis the
            obstacles stay out of [m] (0: none).
        configurations: how many configurations the sample held.
        limiting_geom: the protected geom whose point limits ``max_speed``.
        limiting_point: (3,) that point, in world coordinates at ``limiting_configuration`` [m].
        limiting_approach: (3,) the unit direction the limiting obstacle moves in.
        limiting_configuration: (n,) the arm's joint positions there [rad or m].
    """

    obstacle_radius: float
    sensing_radius: float
    max_speed: float
    keep_out_radius: float
    keep_out_height: float
    configurations: int
    limiting_geom: str
    limiting_point: np.ndarray
    limiting_approach: np.ndarray
    limiting_configuration: np.ndarray
    _standoff_gain: float = field(repr=False)
    _radius: np.ndarray = field(repr=False)  # (N,) clearance r of each sample [m]
    _sidestep: np.ndarray = field(repr=False)  # (N,) t⊥ [s]
    _outrun_speed: np.ndarray = field(repr=False)  # (N,) σ(w) [m/s]
    _outrun_accel: np.ndarray = field(repr=False)  # (N,) α(w) [m/s²]

    def min_sensing_range(self, speed: float) -> float:
        """The sensing radius [m] a safe escape needs from obstacles of up to ``speed`` [m/s]
        (and of up to :attr:`obstacle_radius`); inf when some point cannot escape at that speed.

        Raises:
            ValueError: ``speed`` not finite or negative.
        """
        speed = float(speed)
        if not (math.isfinite(speed) and speed >= 0.0):
            raise ValueError(f"speed must be a finite number >= 0 [m/s], got {speed!r}")
        return float(self._needed(speed).max()) if self._radius.size else 0.0

    def problems(self, speed: float, radius: float, sensing_radius: float | None = None) -> list[str]:
        """Why obstacles of up to ``speed`` [m/s] and ``radius`` [m], sensed at ``sensing_radius``
        [m] (None: :attr:`sensing_radius`), are outside this envelope: one sentence each, none
        when inside."""
        sensing = self.sensing_radius if sensing_radius is None else float(sensing_radius)
        out = []
        if radius > self.obstacle_radius * (1.0 + 1e-9):
            out.append(f"obstacles of radius {radius:.3g} m are larger than the {self.obstacle_radius:.3g} m the "
                       "envelope was computed for")  # fmt: skip
        needed = self.min_sensing_range(speed)
        if needed > sensing:
            where = (f"{self.limiting_geom} at {np.round(self.limiting_point, 3).tolist()} m cannot get out of the "
                     f"way of an obstacle moving along {np.round(self.limiting_approach, 2).tolist()}")
            out.append(f"obstacles at {speed:.3g} m/s need a sensing radius of {needed:.3g} m and the filter senses "
                       f"at {sensing:.3g} m: it guarantees up to {self.max_speed:.3g} m/s ({where})")
        return out

    def _needed(self, speed: float) -> np.ndarray:
        """``D(V)`` of every sample (:mod:`c3bf_gym.safety.envelope`)."""
        r = self._radius
        if self._standoff_gain > 0.0:
            k = speed / self._standoff_gain
            standoff = k - r + np.sqrt(r * r + k * k)  # the gap where γ₁ g (g + 2r) / 2(g + r) = V
        else:
            standoff = np.zeros_like(r)
        with np.errstate(divide="ignore", invalid="ignore"):
            sidestep = speed * self._sidestep
            outrun = np.where((self._outrun_speed >= speed) & (self._outrun_accel > 0.0),
                              speed * speed / (2.0 * self._outrun_accel), np.inf)  # fmt: skip
        return standoff + np.minimum(np.nan_to_num(sidestep, nan=0.0), outrun)


def _directions(count: int) -> np.ndarray:
    """(count, 3) unit vectors spread evenly over the sphere (a Fibonacci lattice)."""
    i = np.arange(count) + 0.5
    polar = np.arccos(1.0 - 2.0 * i / count)
    azimuth = np.pi * (1.0 + math.sqrt(5.0)) * i
    return np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], axis=1)


def _sidesteps(approach: np.ndarray, count: int) -> np.ndarray:
    """(A, count, 3) unit vectors evenly around the circle perpendicular to each approach (A, 3)."""
    helper = np.where(np.abs(approach[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = np.cross(approach, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(approach, e1)
    angle = np.linspace(0.0, np.pi, count, endpoint=False)  # u and −u have the same supports but α's c
    angle = np.concatenate([angle, angle + np.pi])
    return np.cos(angle)[None, :, None] * e1[:, None] + np.sin(angle)[None, :, None] * e2[:, None]


def _escape_time(distance: np.ndarray, speed: np.ndarray, accel: np.ndarray) -> np.ndarray:
    """Time [s] to cover ``distance`` from rest accelerating at ``accel`` up to ``speed``; inf
    where the acceleration is not positive."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ramp = speed * speed / (2.0 * accel)
        t = np.where(distance <= ramp, np.sqrt(2.0 * distance / accel), distance / speed + speed / (2.0 * accel))
    return np.where(accel > 0.0, np.nan_to_num(t, nan=np.inf), np.inf)


def filter_envelope(
    model: mujoco.MjModel,
    robot: RobotDescription,
    config: FilterConfig | None = None,
    *,
    obstacle_radius: float,
    sensing_radius: float | None = None,
    keep_out_radius: float = 0.0,
    keep_out_height: float = 0.0,
    configurations: int = 128,
    qpos: np.ndarray | None = None,
    seed: int = 0,
) -> FilterEnvelope:
    """The obstacle speed and sensing range within which the filter ``config`` can keep ``robot``
    safe: the escape argument of :mod:`c3bf_gym.safety.envelope`, over a sample of configurations.

    Args:
        model: the compiled model ``robot`` was described from.
        robot: the arm.
        config: the filter (None: the default). Its ``margin``, ``joint_speed_fraction`` (the
            speed bound ``σ`` uses: the fraction times :attr:`~c3bf_gym.safety.RobotDescription.joint_speed_limit`,
            or none without ``joint_limits``) and guard gains (the standoff) enter the envelope.
        obstacle_radius: the largest obstacle radius [m], >= 0.
        sensing_radius: [m], > 0; None: ``config.sensing_radius``, which must then be set.
        keep_out_radius, keep_out_height: a cylinder about the world's vertical axis through the
            arm's base that obstacles never enter [m], >= 0 (0: none).
        configurations: the number of configurations drawn uniformly within the joint ranges
            (a joint without a range: ``[−π, π]``), >= 0; those with a capsule below the floor
            (the model's upright world plane, if any) are dropped.
        qpos: (n,) a configuration always included (None: the model's ``qpos0``).
        seed: the draw's seed.

    Returns:
        The :class:`FilterEnvelope`.

    Raises:
        ValueError: a radius, range or count out of its range, a ``qpos`` of the wrong shape, or
            no sensing radius given.
    """
    config = FilterConfig() if config is None else config
    sensing = config.sensing_radius if sensing_radius is None else sensing_radius
    if sensing is None or not (math.isfinite(float(sensing)) and float(sensing) > 0.0):
        raise ValueError(f"sensing_radius must be a finite number > 0 [m] (here or in the config), got {sensing!r}")
    for name, value in (("obstacle_radius", obstacle_radius), ("keep_out_radius", keep_out_radius),
                        ("keep_out_height", keep_out_height)):  # fmt: skip
        if not (math.isfinite(float(value)) and float(value) >= 0.0):
            raise ValueError(f"{name} must be a finite number >= 0 [m], got {value!r}")
    if int(configurations) != configurations or configurations < 0:
        raise ValueError(f"configurations must be an integer >= 0, got {configurations!r}")
    qpos_ids = model.jnt_qposadr[model.dof_jntid[robot.dof_ids]]
    first = model.qpos0[qpos_ids] if qpos is None else np.asarray(qpos, dtype=np.float64)
    if first.shape != (robot.n,) or not np.isfinite(first).all():
        raise ValueError(f"qpos must be {robot.n} finite joint positions, got {qpos!r}")
    samples = [first] + _random_configurations(robot, int(configurations), seed)
    escapes = _Escapes(model, robot, config, float(obstacle_radius), float(keep_out_radius), float(keep_out_height))
    found = [escapes.at(q, qpos_ids, drop_below_floor=index > 0) for index, q in enumerate(samples)]
    parts = [part for part, _ in filter(None, found)]
    kept = [where for _, where in filter(None, found)]
    if parts:
        radius_all, t_all, speed_all, accel_all = (np.concatenate([p[i].reshape(-1) for p in parts]) for i in range(4))
    else:
        radius_all = t_all = speed_all = accel_all = np.zeros(0)
    envelope = FilterEnvelope(float(obstacle_radius), float(sensing), 0.0, float(keep_out_radius),
                              float(keep_out_height), len(kept), "", np.zeros(3), np.zeros(3), first.copy(),
                              escapes.standoff, radius_all, t_all, speed_all, accel_all)  # fmt: skip
    if not parts:
        return envelope
    max_speed, just_above = _largest_speed(envelope, float(sensing))
    worst = int(np.argmax(envelope._needed(just_above)))  # the sample that sets the limit
    sizes = [p[1].size for p in parts]
    which = int(np.searchsorted(np.cumsum(sizes), worst, side="right"))
    point, direction = divmod(worst - sum(sizes[:which]), APPROACHES)
    q, pos, geoms = kept[which]
    return FilterEnvelope(float(obstacle_radius), float(sensing), max_speed,
                          float(keep_out_radius), float(keep_out_height), len(kept),
                          mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, int(geoms[point])) or
                          f"geom {int(geoms[point])}", pos[point].copy(), escapes.approach[direction].copy(),
                          np.array(q), escapes.standoff, radius_all, t_all, speed_all, accel_all)  # fmt: skip


def _random_configurations(robot: RobotDescription, count: int, seed: int) -> list[np.ndarray]:
    """``count`` joint positions drawn uniformly within the joint ranges (``[−π, π]`` for a joint
    without one)."""
    low, high = robot.joint_range.T.copy()
    low[~np.isfinite(low)], high[~np.isfinite(high)] = -np.pi, np.pi
    rng = np.random.default_rng(seed)
    return [rng.uniform(low, high) for _ in range(count)]


def _largest_speed(envelope: FilterEnvelope, sensing: float) -> tuple[float, float]:
    """The bracket ``(low, high)`` of the largest obstacle speed whose needed range is within
    ``sensing`` at every sample, by bisection (the needed range grows with the speed everywhere)."""
    low_v, high_v = 0.0, 1.0
    while envelope._needed(high_v).max() <= sensing and high_v < 1e3:
        low_v, high_v = high_v, 2.0 * high_v
    for _ in range(50):
        mid = 0.5 * (low_v + high_v)
        low_v, high_v = (mid, high_v) if envelope._needed(mid).max() <= sensing else (low_v, mid)
    return low_v, high_v


class _Escapes:
    """The escape argument at one configuration after another, for one robot, filter and obstacle
    size: per protected point an obstacle can reach, the sidestep time per approach direction and
    the outrun speed and acceleration along it."""

    def __init__(self, model: mujoco.MjModel, robot: RobotDescription, config: FilterConfig, obstacle_radius: float,
                 keep_out_radius: float, keep_out_height: float) -> None:  # fmt: skip
        self.model, self.robot, self.config = model, robot, config
        self.keep_out = (keep_out_radius, keep_out_height)
        self.speed_bound = None
        if config.joint_limits and robot.joint_speed_limit is not None:
            self.speed_bound = config.joint_speed_fraction * robot.joint_speed_limit
        self.standoff = 0.0
        for barrier in (config.guard_object(), config.barrier_object()):
            if isinstance(barrier, DistanceHOCBF):
                self.standoff = barrier.gamma1
                break
        self.arm = ArmModel(model, robot.geom_ids, robot.site_id, robot.capsules)
        self.data = mujoco.MjData(model)
        self.floor = floor_height(model)
        self.approach = _directions(APPROACHES)
        self.sidestep = _sidesteps(self.approach, SIDESTEPS).reshape(-1, 3)
        self.clearance = np.repeat(obstacle_radius + self.arm.capsule_radius + config.margin, len(_LAMBDAS))
        self.dense = np.zeros((model.nv, model.nv))

    def at(self, q: np.ndarray, qpos_ids: np.ndarray, drop_below_floor: bool):
        """``((clearance, sidestep time, outrun speed, outrun acceleration), (q, points, geoms))``
        at the joint positions ``q`` (at rest), or None when ``drop_below_floor`` and a capsule
        is below the floor, or when no protected point is outside the keep-out cylinder."""
        model, data, arm, robot, margin = self.model, self.data, self.arm, self.robot, self.config.margin
        data.qpos[:] = model.qpos0
        data.qpos[qpos_ids] = q
        data.qvel[:] = 0.0
        mujoco.mj_forward(model, data)
        radius = arm.capsule_radius
        a, b = arm.capsule_segments(data)
        if drop_below_floor and self.floor is not None and min(a[:, 2].min(), b[:, 2].min()) - radius.max() < self.floor:
            return None
        arm.update(data)
        ends = arm.end_dynamics()
        s = len(radius)
        # every quantity is affine along a capsule's axis (one rigid body): points at _LAMBDAS
        lam = _LAMBDAS[None, :, None]
        pos = (ends.pos[:s, None] * (1 - lam) + ends.pos[s:, None] * lam).reshape(-1, 3)
        G = (ends.G[:s, None] * (1 - lam[..., None]) + ends.G[s:, None] * lam[..., None]).reshape(-1, 3, model.nv)
        c = (ends.c[:s, None] * (1 - lam) + ends.c[s:, None] * lam).reshape(-1, 3)
        mujoco.mj_fullM(model, data, self.dense)
        J = G @ (self.dense + np.diag(arm.implicit_damping))  # G = J (M + h D)⁻¹
        # points an obstacle can touch: not deep inside the keep-out cylinder
        rp = np.repeat(radius, len(_LAMBDAS)) + margin
        hidden = (np.hypot(pos[:, 0], pos[:, 1]) + rp < self.keep_out[0]) & (pos[:, 2] + rp < self.keep_out[1])
        reach = ~hidden
        if not reach.any():
            return None
        G, c, J = G[reach], c[reach], J[reach]

        def supports(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            uG = np.einsum("dk,pkj->pdj", u, G)  # (P, D, nv)
            accel = np.abs(uG[:, :, robot.dof_ids]) @ robot.torque_limit
            accel -= np.abs(uG) @ robot.unmodelled_force
            accel += c @ u.T
            if self.speed_bound is None:
                return np.full(accel.shape, np.inf), accel
            return np.abs(np.einsum("dk,pkj->pdj", u, J[:, :, robot.dof_ids])) @ self.speed_bound, accel

        side_speed, side_accel = supports(self.sidestep)
        r = self.clearance[reach][:, None]
        t_side = _escape_time(r, side_speed, side_accel).reshape(len(r), APPROACHES, -1).min(axis=2)
        out_speed, out_accel = supports(self.approach)
        geoms = np.repeat(robot.geom_ids, len(_LAMBDAS))[reach]
        return (np.broadcast_to(r, t_side.shape), t_side, out_speed, out_accel), (q, pos[reach], geoms)
