"""Does an escape exist? A search over the arm's motions that knows every sphere's future (issue 32).

The filter's rows look one physics step ahead. When an episode of ``benchmarks/third_party.py``
collides under the filter, this asks whether any motion of the arm would have kept it clear:
if none does, no filter could have, and the spheres were outside what any controller can
guarantee; if one does, the filter missed it, and a look-ahead has something to find.

The episode is the benchmark's own (:func:`third_party.episode_start`: the same arm, scenario,
seed and filter settings draw the same spheres, starting where the benchmark starts them), and
the arm is the same model with two changes that make a motion easy to search
(:func:`escape_spec`):

* every arm joint is driven by a velocity servo, its target within ``joint_speed_fraction`` of
  the manufacturer's speed (the filter's bound), its force within the motor's torque limit;
* gravity is compensated through the same actuators (MuJoCo's ``gravcomp`` with
  ``actuatorgravcomp``), so servo and compensation together stay within that limit.

The servos are a torque law the arm's motors could apply, τ = clip(K (q̇* − q̇) + g(q)),
integrated with the scene's own explicit Euler step; their gains are scaled down together until
that step is stable for the arm's mass matrix (:data:`STABLE_GAIN`), which leaves them soft: the
searched arm accelerates more slowly than the real one could, so an escape it finds is one the
real arm has with torque to spare.

A motion is a sequence of joint-velocity targets held for :data:`SEGMENT` s each, searched by the
cross-entropy method (:func:`search`): :data:`SAMPLES` motions per iteration (``--samples``)
rolled out in MuJoCo's C rollout (``mujoco.rollout``), the best eighth (:data:`ELITES`)
re-centring the next draw, up to ``--iterations``, stopping once a motion keeps :data:`TARGET`
clear. Clearance is MuJoCo's distance sensors (``mj_geomDistance`` on the real geoms, the
benchmark's measure) between every protected geom and every sphere at every physics step. An **escape** keeps every clearance above 0
and every joint within 1 % of its bound over the horizon: until the last moving sphere has left,
plus 0.5 s, within the episode's length. Contacts with the floor and between links are simulated,
as in the benchmark, and allowed. A search that finds none does not prove that none exists; one
that finds one shows it does, on the benchmark's model and physics step.

``--hold T`` keeps the arm still for the first T seconds before it may move: how late an escape
can still start, and so how far ahead a look-ahead would have to see. ``--replay`` applies each
motion found to the benchmark's own torque-driven model (:func:`replay`): as it is, as the
filter's nominal torque, and as the fallback where the filter's rows give way.

``--online`` drops the oracle's knowledge: it runs the benchmark's filtered episode under each of
``--policies`` and, where the filter's rows give way, searches from the state reached with only
what the filter knows there (each sphere's position and velocity, held), over ``--lookahead`` s,
and engages an escape found for ``--engage`` s as the filter's nominal torque and its fallback
(:class:`OnlineEscape`). Each episode runs without and with it on the same seed. ``--trigger``
says what starts a search: the rows giving way (``rows``), a hard row giving way (``hard``), or a
forecast of one: the filtered arm rolled ahead from the state reached, left to the filter, every
``--forecast-every`` s (0.1) over ``--forecast-horizon`` s (``--lookahead``'s) (``forecast``,
:class:`Forecast`). ``--forecast-gate D`` runs that forecast only while some sphere, moved along its
velocity, comes within ``D`` m of the arm's capsules held still within the horizon
(:func:`near_path`).

Usage::

    python benchmarks/escape.py --arm sawyer --scenario multi --seeds 20 23 67 \\
        --set joint_range_reserve=0.3 allowance_level=true joint_speed_fraction=1.0 nominal_speed_fraction=0.4
    python benchmarks/escape.py --arm sawyer --scenario multi --seeds 20 --hold 1.0 --set joint_speed_fraction=1.0
    python benchmarks/escape.py --online --arm sawyer --scenario multi --seeds 2 12 20 40 89
    python benchmarks/escape.py --online --trigger forecast --arm sawyer --scenario multi --seeds 2 12 20 40 89
    python benchmarks/escape.py --online --trigger forecast --forecast-every 0.3 --arm sawyer --seeds 2 12 20 40 89
    python benchmarks/escape.py --online --trigger forecast --forecast-every 0.3 --forecast-gate 0.1 --arm sawyer \
        --seeds 2 12 20 40 89
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
import time
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

import mujoco
import mujoco.rollout
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import third_party as tp  # the benchmark beside this file

from c3bf_gym.cli import add_filter_settings
from c3bf_gym.safety import (
    EnvelopeWarning,
    FilterConfig,
    FilterEnvelope,
    MocapSpheres,
    Obstacles,
    RobotDescription,
    SafetyController,
    UnprotectedGeometryWarning,
    capsule_distances,
)

SEGMENT = 0.1  # [s] a velocity target is held this long
SAMPLES = 96  # motions per iteration (--samples)
ELITES = 1 / 8  # the best fraction of them, which re-centres the next draw
SMOOTHING = 0.7  # weight of the elites' mean and spread against the last ones
SPREAD = 0.3  # the first draw's spread, as a fraction of each joint's speed bound
SPREAD_FLOOR = 0.005  # the spread never falls below this fraction of the bound
TARGET = 0.015  # [m] the search pushes clearances up to this and stops there (--target); an escape needs > 0
SPEED_TOLERANCE = 1.01  # an escape keeps every joint within this multiple of its bound
TAIL = 0.5  # [s] the horizon runs this long past the last moving sphere's exit
SERVO_RESPONSE = 0.2  # a servo saturates at this fraction of the bound in velocity error
STABLE_GAIN = 0.5  # the largest eigenvalue of dt M⁻¹ K the servo gains K may reach (explicit Euler needs < 2)


@dataclass
class Escape:
    """What the search found for one episode (lengths in m, times in s)."""

    arm: str
    scenario: str
    seed: int
    hold: float
    horizon: float
    found: bool
    lowest_clearance: float  # the best motion's lowest clearance over the horizon
    max_speed_ratio: float  # its largest |q̇_i| / bound_i
    still_clearance: float  # the lowest clearance if the arm holds still throughout
    still_contact: float  # when a sphere first touches the arm held still (inf: never)
    iterations: int
    seconds: float  # wall time
    targets: list[list[float]]  # the best motion: joint-velocity targets [rad/s], one row per SEGMENT s
    start: float = 0.0  # [s] into the episode, where the search started (a Start's time)


@dataclass
class Start:
    """A search's start other than the episode's beginning: a state the filtered episode reached,
    with the spheres as the filter knew them there."""

    time: float  # [s] into the episode
    qpos: np.ndarray  # (model.nq,) the scene's joint positions
    qvel: np.ndarray  # (model.nv,) [rad/s] and velocities
    spheres: tp.Spheres  # their positions then, velocities held from then on; times count from ``time``
    horizon: float  # [s] into the episode: the search's end


def servo_gains(model: mujoco.MjModel, robot: RobotDescription, qpos: np.ndarray, bound: np.ndarray) -> np.ndarray:
    """(n,) the servos' velocity gains K [N m s/rad]: each joint's torque limit over
    :data:`SERVO_RESPONSE` of its ``bound`` [rad/s], scaled down together until the largest
    eigenvalue of dt M⁻¹ K, with the mass matrix at ``qpos``, is :data:`STABLE_GAIN` (explicit
    Euler, the scene's integrator, is stable below 2)."""
    data = mujoco.MjData(model)
    data.qpos[model.jnt_qposadr[model.dof_jntid[robot.dof_ids]]] = qpos
    mujoco.mj_forward(model, data)
    dense = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, dense)
    gains = np.asarray(robot.torque_limit, dtype=float) / (SERVO_RESPONSE * bound)
    coupling = model.opt.timestep * np.linalg.inv(dense)[np.ix_(robot.dof_ids, robot.dof_ids)] * gains
    return gains * min(1.0, STABLE_GAIN / np.max(np.abs(np.linalg.eigvals(coupling))))


def _arm_actuators(model: mujoco.MjModel, robot: RobotDescription) -> list[tuple[int, int]]:
    """(actuator id, index among ``robot``'s joints) of every actuator on one of the arm's joints
    (a gripper's are left out)."""
    joint_of = {int(dof): i for i, dof in enumerate(robot.dof_ids)}
    dofs = model.jnt_dofadr[model.actuator_trnid[:, 0]]
    return [(i, joint_of[int(dof)]) for i, dof in enumerate(dofs) if int(dof) in joint_of]


@functools.cache
def _scene(arm: str, scenario: str, config: FilterConfig,
           assets: Path) -> tuple[mujoco.MjModel, RobotDescription, FilterEnvelope, np.ndarray]:
    """``third_party``'s scene for ``scenario`` on ``arm`` (ValueError on an unknown arm), the
    envelope of ``config`` there, and the joints' speed bound [rad/s] under ``config``: built once
    per process (the envelope takes seconds), so callers share them and must not change them
    except through ``third_party.episode_start``, which sets the spheres' radii for its episode."""
    model, robot, _ = tp.build_scene(assets, arm, len(tp.SCENARIOS[scenario]))
    envelope = tp.arm_envelope(model, robot, arm, config)
    return model, robot, envelope, config.joint_speed_fraction * np.asarray(robot.joint_speed_limit, dtype=float)


def escape_spec(spec: mujoco.MjSpec, robot: RobotDescription, model: mujoco.MjModel, qpos: np.ndarray,
                bound: np.ndarray, spheres: int) -> int:
    """Turn the scene ``spec`` (of :func:`third_party.scene_spec`, whose compiled ``model`` the
    arm ``robot`` describes) into the search's model, in place: velocity servos on the arm's
    joints (targets within ``bound`` (n,) [rad/s], forces within ``robot.torque_limit``),
    gravity compensated through them, and a
    distance sensor between every protected geom and each of the ``spheres`` spheres. The servo
    gains are :func:`servo_gains` at ``qpos`` (the arm's joint positions). Returns the index of
    the first distance sensor (the file's own sensors come before them)."""
    limit = np.asarray(robot.torque_limit, dtype=float)
    gains = servo_gains(model, robot, qpos, bound)
    for a, i in _arm_actuators(model, robot):  # a gripper's fingers keep their own servos
        actuator = spec.actuator(model.actuator(a).name)
        gain = gains[i]
        actuator.gear[0] = 1.0
        actuator.gaintype, actuator.biastype = mujoco.mjtGain.mjGAIN_FIXED, mujoco.mjtBias.mjBIAS_AFFINE
        actuator.gainprm[0] = gain
        actuator.biasprm[:3] = [0.0, 0.0, -gain]
        actuator.ctrllimited = actuator.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        actuator.ctrlrange, actuator.forcerange = [-bound[i], bound[i]], [-limit[i], limit[i]]
        joint = spec.joint(model.joint(model.actuator_trnid[a, 0]).name)
        joint.actgravcomp = True  # the compensation is the actuators' torque, within their limit
        joint.actfrclimited = mujoco.mjtLimited.mjLIMITED_TRUE
        joint.actfrcrange = [-limit[i], limit[i]]
    for body in spec.bodies[1:]:
        if not body.mocap:
            body.gravcomp = 1.0
    first = len(spec.sensors)
    for geom in robot.geom_ids:
        for k in range(spheres):
            spec.add_sensor(type=mujoco.mjtSensor.mjSENS_GEOMDIST, objtype=mujoco.mjtObj.mjOBJ_GEOM,
                            objname=model.geom(int(geom)).name, reftype=mujoco.mjtObj.mjOBJ_GEOM,
                            refname=tp._BALL.format(k), cutoff=tp.CUTOFF)  # fmt: skip
    return first


def search(arm: str, scenario: str, seed: int, config: FilterConfig, *, assets: Path, hold: float = 0.0,
           iterations: int = 40, max_speed: float = tp.SPEED[1], threads: int = 2, target: float = TARGET,
           start: Start | None = None, initial: np.ndarray | None = None, samples: int = SAMPLES) -> Escape:
    """Search for an escape in ``third_party``'s episode (``arm``, ``scenario``, ``seed``, the
    spheres the filter ``config``'s envelope allows at up to ``max_speed`` m/s), the arm held
    still for the first ``hold`` seconds; ``iterations`` of the cross-entropy method at most, each
    ``samples`` motions rolled out on ``threads`` threads, until a motion keeps ``target`` [m] clear.

    From the episode's beginning, with the spheres' whole paths, until the last moving one has left
    plus :data:`TAIL`; or from ``start``, with the spheres it gives, until its horizon. The first
    draw is centred on ``initial`` (segments, n) [rad/s] (a motion to start from; zeros past its
    end), or on holding still. ValueError on an unknown arm or scenario, a hold outside
    [0, horizon), iterations < 1, samples < 2 or a target <= 0."""
    if scenario not in tp.SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}; choose from {', '.join(tp.SCENARIOS)}")
    if iterations < 1 or samples < 2 or not target > 0.0:
        raise ValueError(f"iterations must be >= 1, samples >= 2 and target > 0 m, got {iterations}, {samples} "
                         f"and {target}")  # fmt: skip
    clock = time.perf_counter()
    kinds = len(tp.SCENARIOS[scenario])
    model, robot, envelope, bound = _scene(arm, scenario, config, assets)
    joints = model.jnt_qposadr[model.dof_jntid[robot.dof_ids]]  # the arm's entries of qpos
    spec, _, _, _ = tp.scene_spec(assets, arm, kinds)
    qpos = np.array(tp.ARMS[arm].init_qpos) if start is None else start.qpos[joints]
    first = escape_spec(spec, robot, model, qpos, bound, kinds)
    servo = spec.compile()
    sensed = slice(int(servo.sensor_adr[first]), None)  # the distance sensors' entries of sensordata
    data, spheres = tp.episode_start(servo, robot, arm, scenario, seed, tp.SECONDS,
                                     tp.speed_range(envelope, max_speed), envelope.min_sensing_range)  # fmt: skip
    mocap = [servo.body(tp._BALL.format(k)).mocapid[0] for k in range(kinds)]
    if start is None:
        begin, leaving = 0.0, spheres.leave[np.isfinite(spheres.leave)]
        horizon = min(tp.SECONDS, (leaving.max() if leaving.size else 0.0) + TAIL)
    else:
        begin, horizon, spheres = start.time, start.horizon, start.spheres
        data.qpos[:], data.qvel[:], data.time = start.qpos, start.qvel, start.time
        data.mocap_pos[mocap] = spheres.at(0.0)[0]
        mujoco.mj_forward(servo, data)
    if not 0.0 <= hold < horizon - begin:
        raise ValueError(f"hold must be in [0, {horizon - begin:g}) s, the horizon of this search, got {hold}")
    dt = servo.opt.timestep
    steps = round((horizon - begin) / dt)
    segment = round(SEGMENT / dt)
    segments = -(-steps // segment)
    held = round(hold / SEGMENT)
    # the spheres' positions at every step, as the control's mocap part
    spheres_path = np.zeros((steps, servo.nmocap, 3))
    spheres_path[:] = data.mocap_pos
    for t in range(steps):
        spheres_path[t, mocap] = spheres.at((t + 1) * dt)[0]
    arm_actuators = _arm_actuators(servo, robot)
    spec_bits = mujoco.mjtState.mjSTATE_CTRL | mujoco.mjtState.mjSTATE_MOCAP_POS
    full = mujoco.mjtState.mjSTATE_FULLPHYSICS
    state0 = np.zeros(mujoco.mj_stateSize(servo, full))
    mujoco.mj_getState(servo, data, state0, full)
    qvel = 1 + servo.nq + robot.dof_ids  # the arm's velocities in a FULLPHYSICS state (time, qpos, qvel, ...)
    datas = [mujoco.MjData(servo) for _ in range(threads)]

    def roll(plans: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(cost, lowest clearance, largest speed ratio, each step's lowest clearance (B, steps))
        of each plan (B, segments, n) [rad/s]."""
        control = np.zeros((len(plans), steps, servo.nu + 3 * servo.nmocap))
        targets = np.repeat(plans, segment, axis=1)[:, :steps]
        for actuator, joint in arm_actuators:
            control[:, :, actuator] = targets[:, :, joint]
        control[:, :, servo.nu:] = spheres_path.reshape(steps, -1)
        states, sensors = mujoco.rollout.rollout(servo, datas, np.tile(state0, (len(plans), 1)), control,
                                                 control_spec=spec_bits)  # fmt: skip
        distances = sensors[:, :, sensed]
        lowest_per_step = distances.min(axis=2)
        lowest = lowest_per_step.min(axis=1)
        ratio = (np.abs(states[:, :, qvel]) / bound).max(axis=(1, 2))
        cost = (1e3 * (np.maximum(target - distances, 0.0) ** 2).sum(axis=(1, 2))
                + 100.0 * np.maximum(ratio - 1.0, 0.0) + 1e-4 * ((plans / bound) ** 2).sum(axis=(1, 2)))  # fmt: skip
        return cost, lowest, ratio, lowest_per_step

    _, still_lowest, _, still_path = roll(np.zeros((1, segments, robot.n)))
    touching = np.flatnonzero(still_path[0] < 0.0)
    still_contact = begin + (touching[0] + 1) * dt if touching.size else np.inf
    mean, spread = np.zeros((segments, robot.n)), np.tile(SPREAD * bound, (segments, 1))
    if initial is not None:
        mean[: len(initial)] = np.clip(initial[:segments], -bound, bound)
    best = (np.inf, float(still_lowest[0]), 0.0, mean)
    done = 0
    for done in range(1, iterations + 1):
        rng = np.random.default_rng([seed, done] if start is None else [seed, done, round(begin / dt)])
        plans = np.clip(mean + spread * rng.standard_normal((samples, segments, robot.n)), -bound, bound)
        plans[0] = mean
        plans[:, :held] = 0.0
        cost, lowest, ratio, _ = roll(plans)
        order = np.argsort(cost)
        if cost[order[0]] < best[0]:
            best = (float(cost[order[0]]), float(lowest[order[0]]), float(ratio[order[0]]), plans[order[0]])
        if best[1] >= target and best[2] <= SPEED_TOLERANCE or held >= segments:
            break  # clear by the target: no need to search on
        elites = plans[order[: max(2, round(ELITES * samples))]]
        mean = SMOOTHING * elites.mean(axis=0) + (1 - SMOOTHING) * mean
        spread = SMOOTHING * elites.std(axis=0) + (1 - SMOOTHING) * spread + SPREAD_FLOOR * bound
    found = best[1] > 0.0 and best[2] <= SPEED_TOLERANCE
    return Escape(arm, scenario, seed, hold, horizon, found, best[1], best[2], float(still_lowest[0]),
                  float(still_contact), done, time.perf_counter() - clock, best[3].round(6).tolist(), begin)


def servo_torque(model: mujoco.MjModel, rest: mujoco.MjData, data: mujoco.MjData, robot: RobotDescription,
                 gains: np.ndarray, targets: np.ndarray, elapsed: float) -> np.ndarray:
    """(n,) [N m] the search's torque law on the benchmark's torque-driven ``model`` at ``data``'s
    state, ``elapsed`` s into the motion ``targets`` (segments, n) [rad/s] (its last target held
    past its end): τ = clip(g(q) + K (q̇* − q̇)) within the torque limits, with the servo
    ``gains`` K and g(q) the gravity torque of the arm at rest at q (``rest``, a scratch
    ``MjData`` of ``model``)."""
    rest.qpos[:] = data.qpos
    mujoco.mj_forward(model, rest)
    target = targets[min(int(elapsed / SEGMENT + 1e-9), len(targets) - 1)]
    limit = np.asarray(robot.torque_limit)
    return np.clip(rest.qfrc_bias[robot.dof_ids] + gains * (target - data.qvel[robot.dof_ids]), -limit, limit)


@dataclass
class Replay:
    """A motion of :func:`search` replayed on the benchmark's own torque-driven model (lengths in m)."""

    unfiltered_clearance: float  # the lowest clearance with the motion's torques applied as they are
    filtered_clearance: float  # ... with them as the nominal torque of the filter
    filtered_infeasible_steps: int  # physics steps where the filter's rows gave way beyond their allowance
    fallback_clearance: float  # ... beneath the filter, but the motion's own torque where its rows gave way
    fallback_steps: int  # physics steps where the motion's torque replaced the filter's


def replay(arm: str, scenario: str, seed: int, config: FilterConfig, targets: np.ndarray, horizon: float, *,
           assets: Path, max_speed: float = tp.SPEED[1]) -> Replay:
    """Apply ``targets`` (segments, n) [rad/s] (:attr:`Escape.targets`) to ``third_party``'s own
    model of the episode (torque motors, no servos, no sensors) for ``horizon`` s: the torque
    τ = clip(K (q̇* − q̇) + g(q)) at every physics step, with the search's gains
    (:func:`servo_gains`) and the gravity torque g(q) of the arm at rest, three times: as it is;
    as the nominal torque of the filter ``config``; and beneath the filter, but applied as it is at
    every physics step where the filter's rows gave way beyond their allowance (the motion as a
    certified fallback in place of the QP's compromise). Clearance as ``third_party.py`` measures
    it (``mj_geomDistance``, every protected geom to every sphere, before every physics step)."""
    model, robot, envelope, bound = _scene(arm, scenario, config, assets)
    gains = servo_gains(model, robot, np.array(tp.ARMS[arm].init_qpos), bound)
    targets = np.asarray(targets, dtype=float)
    dt = model.opt.timestep
    names = [tp._BALL.format(k) for k in range(len(tp.SCENARIOS[scenario]))]
    balls = [model.geom(name).id for name in names]
    mocap = [model.body(name).mocapid[0] for name in names]
    rest = mujoco.MjData(model)  # the arm at rest in the same configuration: its qfrc_bias is g(q)
    outcome = []
    for mode in ("as it is", "filtered", "fallback"):
        filtered = mode != "as it is"
        data, drawn = tp.episode_start(model, robot, arm, scenario, seed, tp.SECONDS,
                                       tp.speed_range(envelope, max_speed), envelope.min_sensing_range)  # fmt: skip
        spheres = MocapSpheres(model, names)
        controller = SafetyController(model, data, robot, spheres, config, envelope=envelope) if filtered else None
        lowest, infeasible = tp.CUTOFF, 0
        for step in range(round(horizon / dt)):
            mujoco.mj_step1(model, data)
            for ball in balls:
                for geom in robot.geom_ids:
                    lowest = min(lowest, mujoco.mj_geomDistance(model, data, ball, int(geom), lowest, None))
            tau = servo_torque(model, rest, data, robot, gains, targets, step * dt)
            if controller is not None:
                spheres.active[:] = drawn.leave > step * dt
                spheres.velocity[:] = drawn.velocity
                safe, report = controller.filter(tau)
                infeasible += report.infeasible_steps
                if not (mode == "fallback" and report.infeasible_steps):
                    tau = safe
            robot.write_ctrl(model, data, tau)
            mujoco.mj_step2(model, data)
            data.mocap_pos[mocap] = drawn.at((step + 1) * dt)[0]
        outcome.append((lowest, infeasible))
    return Replay(outcome[0][0], outcome[1][0], outcome[1][1], outcome[2][0], outcome[2][1])


LOOKAHEAD = 2.0  # [s] an online search's horizon (--lookahead)
ENGAGE = 1.0  # [s] how long an escape it finds stays engaged before the next search (--engage)
#: What starts a search (--trigger): any row given way beyond its allowance; only a hard one (a
#: guard, floor, joint-limit or self-collision row, :data:`third_party.HARD_ROWS`), which also
#: narrows where an escape's torque replaces the filter's; or a forecast of a hard row giving way
#: (:class:`Forecast`).
TRIGGERS = ("rows", "hard", "forecast")
FORECAST_EVERY = 0.1  # [s] how often the forecast runs while no escape is engaged (--trigger forecast)
#: The forecast's nominal torque (--forecast-torque): the bias force alone (the arm left to the
#: filter), or with the policy's excess over it at the forecast's start held throughout.
FORECAST_TORQUES = ("bias", "held")
GATE_STEP = 0.05  # [s] the times at which near_path checks the spheres' paths


def near_path(robot: RobotDescription, data: mujoco.MjData, obstacles: Obstacles, horizon: float,
              distance: float) -> bool:
    """Whether some active obstacle, moved along its velocity (``p + v t``), comes within
    ``distance`` [m] (surface to surface) of the robot's protected capsules held in ``data``'s pose,
    at some ``t`` of 0, :data:`GATE_STEP`, ... up to ``horizon`` s. The arm does not stay still, so
    this only says where a forecast has something to look at: a pinch needs a sphere on its way to
    the arm."""
    active = obstacles.active
    if not active.any():
        return False
    a, b, radius = robot.capsule_segments(data)
    times = np.arange(0.0, horizon + 0.5 * GATE_STEP, GATE_STEP)[:, None, None]
    moved = obstacles.position[active] + obstacles.velocity[active] * times  # (T, N, 3)
    gap = capsule_distances(moved, a, b, radius) - obstacles.radius[active][:, None]
    return bool(gap.min() < distance)


class Forecast:
    """The benchmark's filtered arm rolled ahead from a state, left to the filter: its nominal
    torque is the arm's bias force (gravity and Coriolis compensation, the zero policy), plus a
    held excess if :meth:`pinched` is given one; the spheres keep the velocities the filter knows. It answers one question: does a hard row
    (:data:`third_party.HARD_ROWS`) give way within the horizon? That is the pinch's signature in
    every ``multi`` episode the filter lost. The roll-out is the benchmark's own model, physics
    step and filter, on a second ``MjData`` and :class:`SafetyController`."""

    def __init__(self, model: mujoco.MjModel, robot: RobotDescription, spheres: int, config: FilterConfig,
                 envelope: FilterEnvelope) -> None:
        self.model, self.robot = model, robot
        self.data = mujoco.MjData(model)
        names = [tp._BALL.format(k) for k in range(spheres)]
        self.spheres = MocapSpheres(model, names)
        self.mocap = [model.body(name).mocapid[0] for name in names]
        with warnings.catch_warnings():  # the episode's filter has said it of the same model
            warnings.simplefilter("ignore", UnprotectedGeometryWarning)
            self.controller = SafetyController(model, self.data, robot, self.spheres, config, envelope=envelope)
        self.runs, self.seconds = 0, 0.0

    def pinched(self, data: mujoco.MjData, obstacles: MocapSpheres, horizon: float,
                excess: np.ndarray | None = None) -> bool:
        """Whether a hard row gives way within ``horizon`` s of ``data``'s state, with ``obstacles``'
        velocities and active slots held, and ``excess`` (n,) [N m] (None: zero) added to the bias
        force at every step of the roll-out before the torque limits clip it."""
        clock = time.perf_counter()
        model, rolled, robot = self.model, self.data, self.robot
        mujoco.mj_copyData(rolled, model, data)
        self.spheres.velocity[:] = np.where(obstacles.active[:, None], obstacles.velocity, 0.0)
        self.spheres.active[:] = obstacles.active
        self.controller.reset()
        limit, dofs, dt = np.asarray(robot.torque_limit), robot.dof_ids, model.opt.timestep
        excess = 0.0 if excess is None else excess
        pinch = False
        with warnings.catch_warnings():  # the episode's own spheres: its filter warns of them, if any
            warnings.simplefilter("ignore", EnvelopeWarning)
            for _ in range(round(horizon / dt)):
                mujoco.mj_step1(model, rolled)
                tau, report = self.controller.filter(np.clip(rolled.qfrc_bias[dofs] + excess, -limit, limit))
                if any(report.violation[kind] > 0.0 for kind in tp.HARD_ROWS):
                    pinch = True
                    break
                robot.write_ctrl(model, rolled, tau)
                mujoco.mj_step2(model, rolled)
                rolled.mocap_pos[self.mocap] += self.spheres.velocity * dt
        self.runs += 1
        self.seconds += time.perf_counter() - clock
        return pinch


class OnlineEscape:
    """The search run by the filtered episode itself (a :class:`third_party.Takeover`), knowing
    only what the filter knows, as a receding horizon that runs while the filter's rows give way.

    Where the rows give way beyond their allowance and no escape is engaged, :func:`search` runs
    from that state (:class:`Start`) over the next ``lookahead`` s, with the spheres then active
    held at their velocities (none leaves, none appears), its first draw centred on what is left of
    the last motion found. An escape it finds (a motion certified clear over the horizon) is
    engaged for ``engage`` s: it is the filter's nominal torque (:func:`servo_torque`), and is
    applied as it is wherever the rows give way. So each engaged stretch ends with ``lookahead −
    engage`` s of certified motion still ahead, for the next search to start from: at its end the
    search runs again, and an escape found is engaged again while a sphere would still reach the
    arm held still within the horizon; else the policy has the arm back. When that search finds
    none, the engaged escape goes on to the end of its certified horizon, and the search runs again
    there. When a search from an unengaged arm finds none, nothing is engaged: the filter's own
    torque stands and the next search waits ``engage`` s. The policy's torque is the nominal
    whenever nothing is engaged. Each search's
    record is kept in :attr:`searches`, the physics steps on an escape's own torque counted in
    :attr:`fallback_steps`.

    ``trigger="hard"`` narrows both uses of the rows' giving way to the hard rows: a search starts
    only where a guard, floor, joint-limit or self-collision row gives way, and an engaged
    escape's torque replaces the filter's only there. Where only the C3BF's rows give way, the
    filter's own torque (the relaxed QP's, with the escape as its nominal) is applied.

    ``trigger="forecast"`` starts a search, while nothing is engaged, only where the
    :class:`Forecast` run every ``forecast_every`` s (None: :data:`FORECAST_EVERY`) over
    ``forecast_horizon`` s (None: ``lookahead``) sees a hard row give way; the rest is as with
    ``"rows"``. With ``forecast_torque="held"`` the forecast's nominal
    adds the policy's torque in excess of the bias force at its start, held. With ``forecast_gate``
    [m] the forecast runs only where :func:`near_path` sees a sphere come within that of the arm
    held still within its horizon (None: wherever it is due). Its runs and their wall time are
    kept in :attr:`forecast`."""

    def __init__(self, arm: str, scenario: str, seed: int, config: FilterConfig, *, assets: Path,
                 max_speed: float, lookahead: float, engage: float, iterations: int, threads: int,
                 target: float, samples: int = SAMPLES, trigger: str = "rows", forecast_torque: str = "bias",
                 forecast_every: float | None = None, forecast_horizon: float | None = None,
                 forecast_gate: float | None = None) -> None:
        if not 0.0 < engage <= lookahead:
            raise ValueError(f"engage must be in (0, lookahead = {lookahead:g}] s, got {engage}")
        if trigger not in TRIGGERS:
            raise ValueError(f"unknown trigger {trigger!r}; choose from {', '.join(TRIGGERS)}")
        if forecast_torque not in FORECAST_TORQUES:
            raise ValueError(f"unknown forecast_torque {forecast_torque!r}; choose from {', '.join(FORECAST_TORQUES)}")
        self.trigger, self.forecast_torque = trigger, forecast_torque
        self.forecast: Forecast | None = None  # built at the first step (trigger "forecast"), on the episode's model
        self.episode = (arm, scenario, seed, config)
        self.options = {"assets": assets, "max_speed": max_speed, "iterations": iterations, "threads": threads,
                        "target": target, "samples": samples}  # fmt: skip
        self.model, self.robot, self.envelope, self.bound = _scene(arm, scenario, config, assets)
        self.rest = mujoco.MjData(self.model)
        self.lookahead, self.engage = lookahead, engage
        every = FORECAST_EVERY if forecast_every is None else forecast_every
        self.forecast_horizon = lookahead if forecast_horizon is None else forecast_horizon
        if not (every > 0.0 and self.forecast_horizon > 0.0):
            raise ValueError(f"forecast_every and forecast_horizon must be > 0 s, got {every}, {self.forecast_horizon}")
        self._every = max(1, round(every / self.model.opt.timestep))
        if forecast_gate is not None and not forecast_gate > 0.0:
            raise ValueError(f"forecast_gate must be > 0 m (or None: no gate), got {forecast_gate}")
        self.forecast_gate = forecast_gate
        self.searches: list[Escape] = []
        self.fallback_steps = 0
        # the motion's first step, its engaged end, the end of its certified horizon, the next search's
        self._first = self._until = self._certified = self._next = 0
        self._targets = self._gains = None

    def _torque(self, step: int, data: mujoco.MjData) -> np.ndarray:
        dt = self.model.opt.timestep
        return servo_torque(self.model, self.rest, data, self.robot, self._gains, self._targets,
                            (step - self._first) * dt)  # fmt: skip

    def nominal(self, step: int, data: mujoco.MjData, obstacles: MocapSpheres, tau: np.ndarray) -> np.ndarray:
        if step == self._until and self._targets is not None:  # an engaged stretch ends here
            obstacles.refresh(data)
            found = self._search(step, data, obstacles)
            if found.found and found.still_contact < found.horizon:
                self._engage(step, data, found)  # a sphere would still reach the arm: go on
            elif found.found:
                self._next = step  # none would: the policy's again, searched again where the rows give way
            elif step < self._certified:  # none found: the engaged escape is certified until its horizon
                self._until = self._certified
        if self.trigger == "forecast" and step >= max(self._until, self._next) and step % self._every == 0:
            obstacles.refresh(data)  # the filter last read them a physics step ago, or never (step 0)
            if self.forecast_gate is not None and not near_path(self.robot, data, obstacles, self.forecast_horizon,
                                                                self.forecast_gate):  # fmt: skip
                return tau
            if self.forecast is None:
                _, scenario, _, config = self.episode
                self.forecast = Forecast(data.model, self.robot, len(tp.SCENARIOS[scenario]), config, self.envelope)
            held = tau - data.qfrc_bias[self.robot.dof_ids] if self.forecast_torque == "held" else None
            if self.forecast.pinched(data, obstacles, self.forecast_horizon, held):
                found = self._search(step, data, obstacles)
                if found.found:
                    self._engage(step, data, found)
        return self._torque(step, data) if step < self._until else tau

    def gave_way(self, step: int, data: mujoco.MjData, obstacles: MocapSpheres, safe: np.ndarray,
                 hard: bool) -> np.ndarray:
        if self.trigger == "hard" and not hard:
            return safe
        if self.trigger != "forecast" and step >= max(self._until, self._next):
            found = self._search(step, data, obstacles)
            if found.found:
                self._engage(step, data, found)
        if step >= self._until:
            return safe
        self.fallback_steps += 1
        return self._torque(step, data)

    def _search(self, step: int, data: mujoco.MjData, obstacles: MocapSpheres) -> Escape:
        """Search from ``data``'s state with what the filter knows (``obstacles``, current at it);
        no search again for ``engage`` s unless the caller says otherwise."""
        dt = self.model.opt.timestep
        active = obstacles.active.copy()
        known = tp.Spheres(obstacles.position.copy(), np.where(active[:, None], obstacles.velocity, 0.0),
                           obstacles.radius.copy(), np.where(active, np.inf, 0.0))  # fmt: skip
        begin = step * dt
        start = Start(begin, data.qpos.copy(), data.qvel.copy(), known, min(tp.SECONDS, begin + self.lookahead))
        left = None
        if self._targets is not None:  # warm start: the last motion, from where it has got to
            left = self._targets[min(int((step - self._first) * dt / SEGMENT + 1e-9), len(self._targets)):]
        found = search(*self.episode, start=start, initial=left, **self.options)
        self.searches.append(found)
        self._next = step + round(self.engage / dt)
        return found

    def _engage(self, step: int, data: mujoco.MjData, found: Escape) -> None:
        """Engage ``found`` (searched from ``data``'s state at ``step``) for ``engage`` s."""
        joints = self.model.jnt_qposadr[self.model.dof_jntid[self.robot.dof_ids]]
        self._gains = servo_gains(self.model, self.robot, data.qpos[joints], self.bound)
        self._targets, self._first = np.array(found.targets), step
        self._until = step + round(self.engage / self.model.opt.timestep)
        self._certified = round(found.horizon / self.model.opt.timestep)


def online(arm: str, scenario: str, policy: str, seed: int, config: FilterConfig, *, assets: Path,
           max_speed: float = tp.SPEED[1], lookahead: float = LOOKAHEAD, engage: float = ENGAGE,
           iterations: int = 40, threads: int = 2, target: float = TARGET, samples: int = SAMPLES,
           trigger: str = "rows", forecast_torque: str = "bias", forecast_every: float | None = None,
           forecast_horizon: float | None = None, forecast_gate: float | None = None) -> dict:
    """``third_party``'s filtered episode (``arm``, ``scenario``, ``policy``, ``seed``), without and
    with :class:`OnlineEscape` (its ``trigger``, ``forecast_torque``, ``forecast_every``,
    ``forecast_horizon`` and ``forecast_gate``): each one's outcome (:class:`third_party.Episode`)
    and wall time [s], and the online searches' records."""
    envelope = _scene(arm, scenario, config, assets)[2]  # third_party.main's: the arm's, the same on every scene
    task = (str(assets), arm, scenario, policy, config, seed, tp.SECONDS,
            tp.speed_range(envelope, max_speed), config, ())  # fmt: skip
    clock = time.perf_counter()
    alone = tp.run_episode(task)
    alone_seconds = time.perf_counter() - clock
    takeover = OnlineEscape(arm, scenario, seed, config, assets=assets, max_speed=max_speed, lookahead=lookahead,
                            engage=engage, iterations=iterations, threads=threads, target=target,
                            samples=samples, trigger=trigger, forecast_torque=forecast_torque,
                            forecast_every=forecast_every, forecast_horizon=forecast_horizon,
                            forecast_gate=forecast_gate)  # fmt: skip
    clock = time.perf_counter()
    helped = tp.run_episode(task, takeover)
    return {"filtered": asdict(alone), "filtered_seconds": alone_seconds, "online": asdict(helped),
            "online_seconds": time.perf_counter() - clock, "fallback_steps": takeover.fallback_steps,
            "forecasts": takeover.forecast.runs if takeover.forecast else 0,
            "forecast_seconds": takeover.forecast.seconds if takeover.forecast else 0.0,
            "searches": [asdict(found) for found in takeover.searches]}  # fmt: skip


def _online_records(args: argparse.Namespace, config: FilterConfig, assets: Path) -> list[dict]:
    """``--online``: :func:`online` for each seed and policy, one line each."""
    records = []
    for seed in args.seeds:
        for policy in args.policies:
            run = online(args.arm, args.scenario, policy, seed, config, assets=assets, max_speed=args.max_speed,
                         lookahead=args.lookahead, engage=args.engage, iterations=args.iterations,
                         threads=args.threads, target=args.target, samples=args.samples,
                         trigger=args.trigger, forecast_torque=args.forecast_torque,
                         forecast_every=args.forecast_every, forecast_horizon=args.forecast_horizon,
                         forecast_gate=args.forecast_gate)  # fmt: skip
            records.append({"seed": seed, "policy": policy, **run})
            alone, helped = run["filtered"], run["online"]
            print(f"seed {seed}, {policy}: filtered {1e3 * alone['lowest_clearance']:+.1f} mm "
                  f"({alone['infeasible_steps']} infeasible physics steps, {run['filtered_seconds']:.1f} s); "
                  f"with the online search {1e3 * helped['lowest_clearance']:+.1f} mm "
                  f"({run['forecasts']} forecasts, {run['forecast_seconds']:.1f} s; "
                  f"{len(run['searches'])} searches, {sum(f['found'] for f in run['searches'])} found an escape, "
                  f"{run['fallback_steps']} physics steps on its torque, {run['online_seconds']:.1f} s)", flush=True)  # fmt: skip
    return records


def _search_records(args: argparse.Namespace, config: FilterConfig, assets: Path) -> list[dict]:
    """The search for each seed's whole episode (and ``--replay``), one line each."""
    records = []
    for seed in args.seeds:
        found = search(args.arm, args.scenario, seed, config, assets=assets, hold=args.hold,
                       iterations=args.iterations, max_speed=args.max_speed, threads=args.threads,
                       target=args.target, samples=args.samples)  # fmt: skip
        records.append(asdict(found))
        print(f"seed {seed}: {'escape' if found.found else 'none found'}, lowest clearance "
              f"{1e3 * found.lowest_clearance:+.1f} mm, joint speed {found.max_speed_ratio:.2f} of the bound "
              f"(holding still: {1e3 * found.still_clearance:+.1f} mm, touching at {found.still_contact:.2f} s), "
              f"{found.iterations} iterations, "
              f"horizon {found.horizon:.2f} s, {found.seconds:.0f} s", flush=True)  # fmt: skip
        if args.replay:
            again = replay(args.arm, args.scenario, seed, config, np.array(found.targets), found.horizon,
                           assets=assets, max_speed=args.max_speed)  # fmt: skip
            records[-1]["replay"] = asdict(again)
            print(f"  replayed on the benchmark's model: {1e3 * again.unfiltered_clearance:+.1f} mm as it is, "
                  f"{1e3 * again.filtered_clearance:+.1f} mm beneath the filter "
                  f"({again.filtered_infeasible_steps} infeasible physics steps), "
                  f"{1e3 * again.fallback_clearance:+.1f} mm with it as the fallback where the rows give way "
                  f"({again.fallback_steps} physics steps)", flush=True)  # fmt: skip
    return records


def main(argv: list[str] | None = None) -> list[dict]:
    """Run the search for each seed, or with ``--online`` the episode of each seed and policy with
    :class:`OnlineEscape` (``argv``: the command line without the program name); print one line each
    and return (and write to ``--json``) the records."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--arm", default="sawyer", help=f"from {', '.join(tp.ARMS)}")
    parser.add_argument("--scenario", default="multi", help=f"from {', '.join(tp.SCENARIOS)}")
    parser.add_argument("--seeds", type=int, nargs="+", required=True, help="the benchmark's episode seeds")
    parser.add_argument("--hold", type=float, default=0.0, help="the arm holds still this long first [s]")
    parser.add_argument("--iterations", type=int, default=40, help="cross-entropy iterations at most")
    parser.add_argument("--samples", type=int, default=SAMPLES, help="motions rolled out per iteration")
    parser.add_argument("--max-speed", type=float, default=tp.SPEED[1], metavar="V",
                        help="the spheres' top speed before the envelope's cap, as third_party.py's [m/s]")  # fmt: skip
    parser.add_argument("--threads", type=int, default=2, help="rollout threads")
    parser.add_argument("--target", type=float, default=TARGET, help="search until a motion keeps this clear [m]")
    parser.add_argument("--replay", action="store_true", help="replay each motion found on the benchmark's own "
                        "model: as it is, as the filter's nominal torque, as its fallback")  # fmt: skip
    parser.add_argument("--online", action="store_true", help="instead of searching each episode whole, run "
                        "it filtered with the search started where the rows give way (OnlineEscape)")  # fmt: skip
    parser.add_argument("--policies", nargs="+", default=list(tp.POLICIES),
                        help=f"--online: from {', '.join(tp.POLICIES)}")
    parser.add_argument("--lookahead", type=float, default=LOOKAHEAD, help="--online: each search's horizon [s]")
    parser.add_argument("--engage", type=float, default=ENGAGE, help="--online: how long an escape found is engaged [s]")
    parser.add_argument("--trigger", choices=TRIGGERS, default="rows", help="--online: what starts a search: any "
                        "row giving way beyond its allowance (rows); a hard row giving way, where alone an escape's "
                        "torque then replaces the filter's (hard); a forecast of one over --lookahead s (forecast)")  # fmt: skip
    parser.add_argument("--forecast-torque", choices=FORECAST_TORQUES, default="bias", help="--trigger forecast: "
                        "its nominal torque, the bias force alone or with the policy's excess over it held")  # fmt: skip
    parser.add_argument("--forecast-every", type=float, default=FORECAST_EVERY, metavar="S",
                        help="--trigger forecast: how often the forecast runs while nothing is engaged [s]")
    parser.add_argument("--forecast-horizon", type=float, default=None, metavar="S",
                        help="--trigger forecast: how far ahead it rolls the arm [s] (default: --lookahead)")
    parser.add_argument("--forecast-gate", type=float, default=None, metavar="D",
                        help="--trigger forecast: run it only while a sphere's path comes within D m of the arm held "
                             "still within the horizon [m] (default: no gate)")  # fmt: skip
    parser.add_argument("--cache", help="robosuite download folder (third_party.py's)")
    parser.add_argument("--json", type=Path, help="write the records here")
    add_filter_settings(parser, "--set")
    args = parser.parse_args(argv)
    try:
        config = tp.CONFIG.replace(**dict(args.set))
    except (TypeError, ValueError) as error:
        parser.error(f"--set: {error}")
    if args.arm not in tp.ARMS or args.scenario not in tp.SCENARIOS:
        parser.error(f"--arm from {', '.join(tp.ARMS)}; --scenario from {', '.join(tp.SCENARIOS)}")
    if args.iterations < 1 or args.threads < 1 or args.samples < 2 or args.hold < 0 or not args.target > 0:
        parser.error("--iterations and --threads must be >= 1, --samples >= 2, --hold >= 0 and --target > 0")
    if not 0 < args.engage <= args.lookahead:
        parser.error(f"--engage must be in (0, --lookahead], got {args.engage} and {args.lookahead}")
    unknown = [policy for policy in args.policies if policy not in tp.POLICIES]
    if unknown:
        parser.error(f"unknown --policies {', '.join(unknown)}; choose from {', '.join(tp.POLICIES)}")
    assets = tp.robosuite_assets(args.cache)
    print(f"{args.arm}, {args.scenario}, joint speeds within {config.joint_speed_fraction:g} of the manufacturer's; "
          f"filter {config!r}")  # fmt: skip
    run = _online_records if args.online else _search_records
    records = run(args, config, assets)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        settings = {"filter": repr(config), "hold": args.hold, "iterations": args.iterations,
                    "samples": args.samples, "max_speed": args.max_speed}
        if args.online:
            settings.update(online=True, lookahead=args.lookahead, engage=args.engage, target=args.target,
                            trigger=args.trigger, forecast_torque=args.forecast_torque,
                            forecast_every=args.forecast_every,
                            forecast_horizon=args.forecast_horizon or args.lookahead,
                            forecast_gate=args.forecast_gate)
        args.json.write_text(json.dumps({"settings": settings,
                                         "episodes": records}, indent=2))  # fmt: skip
        print(f"wrote {args.json}")
    return records


if __name__ == "__main__":
    main()
