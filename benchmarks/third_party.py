"""The safety filter on arms nobody here modelled: robosuite's MJCF arms (issue 32).

The arms are the MJCF files robosuite 1.5.2 ships (``robosuite/models/assets/robots/<arm>/robot.xml``
and their meshes), fetched from PyPI by :func:`robosuite_assets`; robosuite's runtime is not used
and nothing of it is copied into this repository. Each arm is loaded as its file describes it; the
benchmark adds only the scene, in code (:func:`build_scene`): a floor, the obstacle spheres (mocap,
no contacts: clearance is measured, not felt), a tool site on the last link when the arm has none,
and a torque motor on any joint without one. The arm is described by
``RobotDescription.from_model``'s default selection (every colliding geom on a moving body, meshes
enclosed by capsules; with a gripper, its fingers swept over their stroke) and filtered by the
default filter with the project's environment's sensing radius (``FilterConfig(sensing_radius=``
:data:`SENSING_RADIUS` ``)``: a sphere adds rows once its surface is within 1 m of the arm). The
arm's geoms keep the file's ``contype`` and ``conaffinity``, so the arms can touch the floor and robosuite's Sawyer its own links and base (its
file excludes no pair; its first link touches the base at the start): contact forces are outside
the filter's model, as in the project's own environment. ``--exclude BODY1 BODY2`` switches off the
contacts of one pair of bodies, as the filter's warning advises (off by default).

Episodes of ``--seconds`` (:data:`SECONDS`, 8 s) at a 0.002 s physics step start from robosuite's initial joint
configuration of the arm. Obstacle spheres (radius 5-8 cm, speed 0.1-0.4 m/s capped by the filter's
envelope on the arm, :func:`speed_range`; ``--max-speed`` lowers the 0.4) are aimed at a random point of a random protected capsule
or at the tool, as in the project's scenarios:

* ``static``: one sphere at rest, its surface 0.1-0.3 m from the point it is aimed at;
* ``head_on``: one sphere coming horizontally straight at the point, along the line from the
  base's axis through it turned by up to 60 deg about the vertical (so that the path can stay
  out of the keep-out cylinder), reaching it 0.8-2 s after it crosses into the sensing range
  the filter's envelope needs at its speed (below), and leaving the scene (deactivated) 0.3 m
  past it (so does every moving sphere);
* ``crossing``: one sphere crossing that line at 50-90 deg, timed as ``head_on``'s;
* ``multi``: four at once (static, head_on and two crossing), each aimed independently.

A sphere moving at ``V`` starts ``FilterEnvelope.min_sensing_range(V)`` back along its path from
where it would be 0.8-2 s before its aim (so ``min_sensing_range(V) / V`` seconds more before it
arrives) and at least that far from every protected capsule: the envelope's escape argument
assumes an obstacle is sensed that far out, and one that appeared closer would be outside it
(``--ignore-envelope`` drops this too). Every sphere spawns at least 0.1 m (surface to surface)
from every protected capsule and keeps its path (over the episode, or until it leaves) above the floor and outside the arm's keep-out cylinder around the
base's vertical axis (:attr:`Arm.keep_out`: the base and the links the pan joint only turns in place
cannot sidestep, so no controller could protect them). The speeds and the keep-out are those of
the envelope the filter states (``c3bf_gym.safety.filter_envelope``), printed per arm;
``--ignore-envelope`` sends every arm spheres at 0.1-0.4 m/s, from 0.8-2 s before their aim. Policies (:data:`POLICIES`):

* ``random``: gravity and Coriolis compensation (``data.qfrc_bias``) plus torques drawn uniformly
  within ``robot.torque_limit``, the draw held for 10 physics steps (a 50 Hz policy at 500 Hz
  physics), clipped to the limits;
* ``adversarial``: ``data.qfrc_bias`` plus ``Jᵀ F`` for a 400 N force pulling the arm point
  nearest to the nearest sphere (on its capsule's axis) towards the sphere's centre, clipped to
  the limits: ``benchmarks/guarantee.py``'s adversary on a torque-driven arm.

Every episode runs twice on the same seed: filtered and unfiltered. Collisions are judged by
MuJoCo alone: ``mj_geomDistance`` between every sphere and every protected geom (the geom itself,
e.g. the mesh, not its capsule) at the start and after every physics step; negative is
penetration. A pair is skipped where the geom's enclosing capsule is no closer than the lowest
clearance so far: the capsule contains the geom, so the geom could not be closer either. Per
arm x scenario x policy the table prints: episodes, filtered episodes with a collision, the
lowest clearance [m], infeasible physics steps per 1,000 (rows gave way beyond
their allowance, ``StepSafety.infeasible_steps``), ``raised/1k`` the steps where only the barrier's
rows gave way, within it (held with a raised gain, ``StepSafety.gain_raised_steps``), ``hard/1k``
those where rows of the last priority (the guard's, the floor's or the joint limits') gave way,
the largest ``|q̇_i| / q̇_max,i`` (the manufacturer's speed, :data:`ARMS`; the default filter holds
``joint_speed_fraction`` = 0.5 of it), and the same three without the filter (left out, and None
in the rows, with ``--no-unfiltered``). A line on stderr at every tenth of the episodes says how
far the run is. An arm the library refuses (``UnsupportedModelError``) is listed with the
library's message instead.

Usage::

    python benchmarks/third_party.py --quick
    python benchmarks/third_party.py --episodes 10 --arms iiwa sawyer jaco --json third_party.json
    python benchmarks/third_party.py --episodes 8 --arms iiwa sawyer --scenarios multi head_on --no-unfiltered \\
        --set joint_speed_fraction=1.0 guard_gamma=20       # another filter setting, on the same seeds
    python benchmarks/third_party.py --episodes 20 --arms sawyer --no-unfiltered \\
        --exclude right_l0 right_arm_base_link              # the Sawyer without its link 0's contact on its base
"""

from __future__ import annotations

import argparse
import contextlib
import json
import multiprocessing as mp
import os
import shutil
import subprocess
import sys
import tempfile
import time
import warnings
import zipfile
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Protocol

import mujoco
import numpy as np

from c3bf_gym.cli import add_filter_settings
from c3bf_gym.safety import (
    FilterConfig,
    FilterEnvelope,
    MocapSpheres,
    RobotDescription,
    SafetyController,
    UnsupportedModelError,
    filter_envelope,
)
from c3bf_gym.safety.dynamics import ArmModel, segment_closest_points

ROBOSUITE_VERSION = "1.5.2"
#: Environment variable naming the folder :func:`robosuite_assets` downloads and extracts into.
CACHE_VARIABLE = "C3BF_ROBOSUITE_CACHE"
_ASSETS = "robosuite/models/assets"
_EXTRACTED = (f"{_ASSETS}/robots/", f"{_ASSETS}/grippers/")


def robosuite_assets(cache: str | os.PathLike | None = None) -> Path:
    """The ``robosuite/models/assets`` folder of robosuite 1.5.2, holding ``robots/`` and
    ``grippers/`` (MJCF files and meshes), downloaded and extracted on first use.

    The wheel comes from PyPI through pip (``pip download --no-deps robosuite==1.5.2``) into
    ``cache``; only the members under ``robosuite/models/assets/robots/`` and ``.../grippers/`` are
    extracted (into a temporary folder, then moved into place, so an interrupted or concurrent
    extraction never leaves a partial tree). Later calls only check that the folder is there.

    Args:
        cache: the folder for the wheel and the extracted files; None: ``$C3BF_ROBOSUITE_CACHE``,
            else ``~/.cache/c3bf-gym/robosuite-1.5.2``.

    Raises:
        RuntimeError: pip failed (its output is in the message; PyPI must be reachable), or the
            wheel has no ``robosuite/models/assets/robots/``.
    """
    default = Path.home() / ".cache" / "c3bf-gym" / f"robosuite-{ROBOSUITE_VERSION}"
    cache = Path(cache if cache is not None else os.environ.get(CACHE_VARIABLE) or default).expanduser()
    assets = cache / _ASSETS
    if (assets / "robots").is_dir() and (assets / "grippers").is_dir():
        return assets
    cache.mkdir(parents=True, exist_ok=True)
    wheels = sorted(cache.glob(f"robosuite-{ROBOSUITE_VERSION}-*.whl"))
    if not wheels:
        done = subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:",
                               f"robosuite=={ROBOSUITE_VERSION}", "-d", str(cache)],
                              capture_output=True, text=True)  # fmt: skip
        wheels = sorted(cache.glob(f"robosuite-{ROBOSUITE_VERSION}-*.whl"))
        if done.returncode != 0 or not wheels:
            raise RuntimeError(f"pip download robosuite=={ROBOSUITE_VERSION} failed:\n{done.stdout}{done.stderr}")
    with zipfile.ZipFile(wheels[-1]) as wheel, tempfile.TemporaryDirectory(dir=cache) as scratch:
        members = [name for name in wheel.namelist() if name.startswith(_EXTRACTED)]
        if not any(name.startswith(_EXTRACTED[0]) for name in members):
            raise RuntimeError(f"{wheels[-1]} has no {_EXTRACTED[0]}")
        wheel.extractall(scratch, members)
        if not assets.is_dir():
            assets.parent.mkdir(parents=True, exist_ok=True)
            try:
                os.replace(Path(scratch) / _ASSETS, assets)
            except OSError:  # another process moved its copy in first
                if not assets.is_dir():
                    raise
        else:  # a partial earlier tree (one of robots/, grippers/ missing): complete it
            for part in ("robots", "grippers"):
                if not (assets / part).is_dir():
                    shutil.move(str(Path(scratch) / _ASSETS / part), assets / part)
    return assets


@dataclass(frozen=True)
class Arm:
    """How the benchmark runs one robosuite arm.

    Attributes:
        folder: the arm's folder under ``robots/``.
        init_qpos: (n,) the starting joint configuration [rad]: robosuite's own ``init_qpos`` for
            the arm (``robosuite/models/robots/manipulators/<arm>_robot.py``).
        joint_speed_limit: (n,) the manufacturer's joint speed limits [rad/s] (sources in
            :data:`ARMS`).
        keep_out: (radius, height) of the cylinder about the base's vertical axis no sphere's
            path enters [m]: the base and the links standing on that axis, which the pan joint
            only turns in place, inside it (chosen with the filter's envelope, :data:`ARMS`).
        gripper: a gripper file of robosuite's ``grippers/`` to attach at the last link, as
            robosuite attaches its grippers (None: the bare arm).
    """

    folder: str
    init_qpos: tuple[float, ...]
    joint_speed_limit: tuple[float, ...]
    keep_out: tuple[float, float]
    gripper: str | None = None


def _deg(*values: float) -> tuple[float, ...]:
    return tuple(float(np.deg2rad(v)) for v in values)


#: The arms, by name. Joint speed limits are not in the MJCF files; each comes with its source.
#: The keep-out cylinders: the smallest of (0.2, 0.25, 0.3) m x (0.45 ... 1.1) m tried (ours
#: after the project's 0.3 m x 0.5 m) beyond which the envelope
#: (``filter_envelope``, 8 cm spheres, the default filter at 1 m sensing) stops growing or
#: passes 0.4 m/s; the envelope with robosuite's own 0.2 m x 0.45 m is 0.03-0.09 m/s on every
#: arm, limited by a shoulder point on the base's axis (docs/results/guarantee.md).
ARMS = {
    # KUKA LBR iiwa 7 R800 (robosuite's "iiwa7"; its torque limits 176/176/110/110/110/40/40 N m
    # are this variant's): KUKA's LBR iiwa specification sheet, axis speeds A1-A7.
    "iiwa": Arm("iiwa", (0.0, 0.65, 0.0, -1.89, 0.0, 0.6, 0.0), _deg(98, 98, 100, 130, 140, 180, 180), (0.2, 0.9)),
    # Rethink Robotics Sawyer: the velocity limits of Rethink's own model (sawyer_description's
    # URDF, right_j0-right_j6, as quoted in public code); Rethink's public datasheet gives no
    # per-joint speeds, so these are the manufacturer's model values, not a datasheet's (unsure).
    "sawyer": Arm("sawyer", (0.0, -1.18, 0.0, 2.18, 0.0, 0.57, -1.57),
                  (1.74, 1.328, 1.957, 1.957, 3.485, 3.485, 4.545), (0.3, 0.6)),
    # Kinova Gen3 (7 dof): 80 deg/s (1.3963 rad/s) for the large actuators (joints 1-4) and
    # 70 deg/s (1.2218 rad/s) for the small ones (5-7), the velocity limits of Kinova's ros_kortex
    # model of the Gen3; the Gen3 user guide's own table was not checked here (unsure).
    "kinova3": Arm("kinova3", (0.0, 0.65, 0.0, 1.89, 0.0, 0.6, -np.pi / 2), (1.3963,) * 4 + (1.2218,) * 3,
                   (0.2, 0.8)),
    # Kinova Jaco 2 (j2s7s300): 36 deg/s (0.628 rad/s) for joints 1-4, the velocity limit of
    # Kinova's kinova-ros model (seen for joints 1 and 2); 48 deg/s for the KA-58 wrist actuators
    # (5-7) is the Jaco 2 specification as remembered, not checked against the actuator datasheet
    # robosuite cites for the torques (unsure).
    "jaco": Arm("jaco", (3.192, 3.68, 0.0, 1.17, 0.05, 3.76, 3.142), _deg(36, 36, 36, 36, 48, 48, 48), (0.25, 0.8)),
    # the Sawyer with robosuite's default gripper for it (RethinkGripper: two slide fingers on
    # force-limited position servos), attached at "right_hand" as robosuite's add_gripper does
    "sawyer+gripper": Arm("sawyer", (0.0, -1.18, 0.0, 2.18, 0.0, 0.57, -1.57),
                          (1.74, 1.328, 1.957, 1.957, 3.485, 3.485, 4.545), (0.3, 0.6), "rethink_gripper.xml"),
}

SCENARIOS = {"static": ("static",), "head_on": ("head_on",), "crossing": ("crossing",),
             "multi": ("static", "head_on", "crossing", "crossing")}  # fmt: skip
POLICIES = ("random", "adversarial")

TIMESTEP = 0.002  # [s] physics step, set on every model (robosuite's files say 0.002 too)
HOLD_STEPS = 10  # the random policy's draw is held 10 physics steps: 50 Hz at 500 Hz physics
PULL_FORCE = 400.0  # [N] the adversary's pull
RADIUS = (0.05, 0.08)  # [m] sphere radii
SPEED = (0.1, 0.4)  # [m/s] sphere speeds, capped by the arm's envelope (speed_range)
MEET_TIME = (0.8, 2.0)  # [s] when a moving sphere reaches its aim point
PASS_DISTANCE = 0.3  # [m] a moving sphere leaves the scene this far past its aim point
HEAD_ON_BEARING = 60.0  # [deg] a head-on line's largest turn from the line from the base's axis
STATIC_GAP = (0.1, 0.3)  # [m] a static sphere's surface from its aim point
CROSSING_ANGLE = (50.0, 90.0)  # [deg] a crossing sphere's heading from the head-on line
SPAWN_CLEARANCE = 0.1  # [m] from every protected capsule at the start
MIN_HEIGHT = 0.05  # [m] every sphere's surface stays this far above the floor
EXTRA_MOTOR_TORQUE = 10.0  # [N m] bound of a motor added to a joint the file leaves without one
SECONDS = 8.0  # [s] episode length: the slowest-escaping arm's fastest sphere meets its aim by 6.3 s
CUTOFF = 1.0  # [m] distances beyond this are not resolved (the lowest clearance is capped here)
SENSING_RADIUS = 1.0  # [m] the filter's, as C3BFReach-v0's default
#: The kinds of rows that give way last (priority 1): the ``hard/1k`` column counts steps where any did.
HARD_ROWS = ("guard", "floor", "joint_limits", "self_collision")
CONFIG = FilterConfig(sensing_radius=SENSING_RADIUS)  # the default filter at the env's sensing radius
_BALL = "c3bf_ball{}"


# ----------------------------------------------------------------------------- the scene


def build_scene(assets: Path, arm: str, spheres: int,
                exclude: Sequence[tuple[str, str]] = ()) -> tuple[mujoco.MjModel, RobotDescription, list[str]]:
    """The arm's robosuite MJCF with the benchmark's scene added (:func:`scene_spec`, ``exclude``
    passed on), compiled, and its description.

    Returns:
        (model, robot, notes): the compiled model, ``RobotDescription.from_model`` with the
        default geom selection, the first site as the tool and the arm's speed limits, and the
        warnings and additions to report (strings).

    Raises:
        ValueError: an unknown arm (names the valid ones), a file that reads angles in degrees, or
            an ``exclude`` body the arm lacks.
        UnsupportedModelError: the library refuses the model (its message says why).
    """
    spec, arm_joints, tool, notes = scene_spec(assets, arm, spheres, exclude)
    model = spec.compile()
    with _warnings_into(notes):
        robot = RobotDescription.from_model(model, joints=arm_joints, site=tool,
                                            joint_speed_limit=ARMS[arm].joint_speed_limit)  # fmt: skip
    return model, robot, notes


@contextlib.contextmanager
def _warnings_into(notes: list[str]) -> Iterator[None]:
    """Record every warning the library gives inside the block, repeats included, and append its
    message to ``notes`` (the benchmark reports them with the arm instead of letting them reach
    stderr)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield
    notes += [str(w.message) for w in caught]


def scene_spec(assets: Path, arm: str, spheres: int,
               exclude: Sequence[tuple[str, str]] = ()) -> tuple[mujoco.MjSpec, list[str], str, list[str]]:
    """The arm's robosuite MJCF with the benchmark's scene added, not yet compiled.

    Added: ``model.opt.timestep`` = :data:`TIMESTEP`; a floor plane at z = 0 (the arm's base
    stands on it); ``spheres`` mocap spheres ``c3bf_ball0``... (contype = conaffinity = 0, radius
    set per episode); a site ``c3bf_tool`` on the last body when the file has no site; and a
    ``<motor>`` (±:data:`EXTRA_MOTOR_TORQUE` N m) on every joint without an actuator. With
    ``exclude``, pairs of the model's body names (``--exclude``), an ``<exclude>`` for each: the
    contacts between those two bodies are switched off, as the filter's
    ``UnprotectedGeometryWarning`` advises for a contact no row can part (the Sawyer's link 0 on
    its base: ``("right_l0", "right_arm_base_link")``). Nothing is excluded by default: the arms
    are robosuite's as shipped.

    Returns:
        (spec, joints, tool, notes): the scene's ``MjSpec``, the names of the arm's joints (a
        gripper's are not among them), the tool site's name, and the additions to report.

    Raises:
        ValueError: an unknown arm (names the valid ones), a file that reads angles in degrees, or
            an ``exclude`` body the arm lacks (names the arm's bodies).
    """
    if arm not in ARMS:
        raise ValueError(f"unknown arm {arm!r}; choose from {', '.join(ARMS)}")
    path = Path(assets) / "robots" / ARMS[arm].folder / "robot.xml"
    spec = mujoco.MjSpec.from_file(str(path))
    if spec.compiler.degree:  # MuJoCo reads angles in degrees unless <compiler angle="radian"/>
        raise ValueError(f"{path} reads angles in degrees; the joint limits and init_qpos here are radians")
    notes = []
    spec.option.timestep = TIMESTEP
    # the tool: a site on the last link (the body deepest in the tree; robosuite's "right_hand",
    # where its grippers attach). robosuite's only site, "right_center", is on the fixed base.
    parents = spec.compile().body_parentid
    depth = [0] * len(parents)
    for body in range(1, len(parents)):
        depth[body] = depth[parents[body]] + 1
    last = spec.bodies[len(depth) - 1 - int(np.argmax(depth[::-1]))]  # spec.bodies[i] is model body i
    arm_joints = [joint.name for joint in spec.joints]
    if ARMS[arm].gripper is not None:
        # robosuite's add_gripper merges the gripper's bodies into the arm's last link; its
        # actuators (the fingers' servos) come with them; the tool is its grip site
        gripper = mujoco.MjSpec.from_file(str(Path(assets) / "grippers" / ARMS[arm].gripper))
        last.add_frame().attach_body(gripper.worldbody.first_body(), "gripper0_", "")
        tool = "gripper0_grip_site"
        notes.append(f"attached {ARMS[arm].gripper} at body {last.name!r}; the tool is its grip site")
    elif last.sites:
        tool = last.sites[0].name
    else:
        tool = "c3bf_tool"
        last.add_site(name=tool)
        notes.append(f"added a tool site on the last link, body {last.name!r}")
    spec.worldbody.add_geom(name="c3bf_floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[3.0, 3.0, 0.1])
    for k in range(spheres):
        body = spec.worldbody.add_body(name=_BALL.format(k), mocap=True, pos=[5.0 + k, 0.0, 1.0])
        body.add_geom(name=_BALL.format(k), type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[RADIUS[0], 0, 0],
                      contype=0, conaffinity=0, rgba=[0.9, 0.2, 0.15, 0.6])  # fmt: skip
    for pair in exclude:
        missing = [name for name in pair if spec.body(name) is None]
        if missing:
            raise ValueError(f"--exclude: {arm} has no body {', '.join(map(repr, missing))}; its bodies are "
                             f"{', '.join(body.name for body in spec.bodies[1:])}")  # fmt: skip
        spec.add_exclude(bodyname1=pair[0], bodyname2=pair[1])
        notes.append(f"excluded the contacts between bodies {pair[0]!r} and {pair[1]!r}")
    driven = {actuator.target for actuator in spec.actuators}
    for joint in (j for j in spec.joints if j.name in arm_joints):
        # e.g. a Sawyer head joint: the filter needs a torque motor on every dof (robosuite 1.5.2's
        # sawyer comments its head_pan joint out, so none of ARMS needs this today)
        if joint.name not in driven:
            spec.add_actuator(name=f"c3bf_motor_{joint.name}", target=joint.name,
                              trntype=mujoco.mjtTrn.mjTRN_JOINT, ctrllimited=mujoco.mjtLimited.mjLIMITED_TRUE,
                              ctrlrange=[-EXTRA_MOTOR_TORQUE, EXTRA_MOTOR_TORQUE])  # fmt: skip
            notes.append(f"added a ±{EXTRA_MOTOR_TORQUE:g} N m motor on joint {joint.name!r}")
    return spec, arm_joints, tool, notes


# ----------------------------------------------------------------------------- spheres


def _spawn(rng: np.random.Generator, kinds: tuple[str, ...], a: np.ndarray, b: np.ndarray, capsule_radius: np.ndarray,
           tool: np.ndarray, horizon: float, *, speed: tuple[float, float], keep_out: tuple[float, float],
           sensing: Callable[[float], float] | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Positions (K, 3), velocities (K, 3), radii (K,) and leaving times (K,) of one sphere per
    kind, aimed at the capsules ``a``-``b`` (S, 3) of ``capsule_radius`` (S,) or the ``tool`` (3,)
    [m] (module docstring), moving at a speed drawn from ``speed`` [m/s] on paths out of the
    ``keep_out`` cylinder (radius, height) [m] until they leave the scene, :data:`PASS_DISTANCE`
    past their aim point (inf for a static sphere) [s]; RuntimeError when 1,000 attempts place none.

    ``sensing``: the sensing range [m] the filter's envelope needs at a speed [m/s]
    (``FilterEnvelope.min_sensing_range``), or None. A moving sphere then starts that much further
    back on its path, ``sensing(V) / V`` seconds more before it meets its aim, and at least that
    far (surface to surface) from every protected capsule: no sphere appears inside the range the
    envelope's escape argument assumes it was sensed at."""
    out = np.zeros((len(kinds), 3)), np.zeros((len(kinds), 3)), np.zeros(len(kinds)), np.full(len(kinds), np.inf)
    for k, kind in enumerate(kinds):
        for _ in range(1000):
            s = int(rng.integers(len(a) + 1))
            aim = tool if s == len(a) else a[s] + rng.uniform() * (b[s] - a[s])
            radius, pace = rng.uniform(*RADIUS), rng.uniform(*speed)
            outward = np.array([aim[0], aim[1], 0.0])
            outward = outward / np.linalg.norm(outward) if np.linalg.norm(outward) > 1e-6 else np.array([1.0, 0, 0])
            if kind == "static":
                direction = rng.normal(size=3)
                direction /= np.linalg.norm(direction)
                reach = (0.0 if s == len(a) else capsule_radius[s]) + radius + rng.uniform(*STATIC_GAP)
                position, velocity, leave = aim + reach * direction, np.zeros(3), np.inf
            else:
                turn = np.deg2rad(rng.uniform(-HEAD_ON_BEARING, HEAD_ON_BEARING))  # about the vertical
                heading = -np.array([np.cos(turn) * outward[0] - np.sin(turn) * outward[1],
                                     np.sin(turn) * outward[0] + np.cos(turn) * outward[1], 0.0])  # fmt: skip
                if kind == "crossing":  # turned away from the head-on line, rolled about it
                    side = np.cross(heading, [0.0, 0.0, 1.0])
                    side /= np.linalg.norm(side)
                    roll = rng.uniform(0.0, 2 * np.pi)
                    normal = np.cos(roll) * side + np.sin(roll) * np.cross(heading, side)
                    angle = np.deg2rad(rng.uniform(*CROSSING_ANGLE))
                    heading = np.cos(angle) * heading + np.sin(angle) * normal
                velocity = pace * heading
                lead = 0.0 if sensing is None else sensing(pace)
                meet = rng.uniform(*MEET_TIME) + lead / pace
                position, leave = aim - velocity * meet, meet + PASS_DISTANCE / pace
            if _placeable(position, velocity, radius, a, b, capsule_radius, min(horizon, leave), keep_out,
                          clearance=SPAWN_CLEARANCE if kind == "static" else max(SPAWN_CLEARANCE, lead)):
                out[0][k], out[1][k], out[2][k], out[3][k] = position, velocity, radius, leave
                break
        else:
            raise RuntimeError(f"no {kind} sphere could be placed in 1,000 attempts")
    return out


def _placeable(position: np.ndarray, velocity: np.ndarray, radius: float, a: np.ndarray, b: np.ndarray,
               capsule_radius: np.ndarray, horizon: float, keep_out: tuple[float, float], *, clearance: float) -> bool:
    """Clear of every capsule by ``clearance`` [m], and a path over ``horizon`` s that stays
    :data:`MIN_HEIGHT` above the floor and out of the ``keep_out`` cylinder (radius, height)."""
    closest = segment_closest_points(a, b, position[None])[0]
    if np.min(np.linalg.norm(closest - position, axis=1) - capsule_radius) - radius < clearance:
        return False
    path = position + np.linspace(0.0, horizon, 51)[:, None] * velocity
    if np.min(path[:, 2]) - radius < MIN_HEIGHT:
        return False
    low = path[:, 2] < keep_out[1] + radius
    return not np.any(np.linalg.norm(path[low, :2], axis=1) < keep_out[0] + radius)


# ----------------------------------------------------------------------------- one episode


@dataclass
class Episode:
    """One episode's outcome (lengths in m)."""

    arm: str
    scenario: str
    policy: str
    filtered: bool
    seed: int
    steps: int = 0
    collided: bool = False
    lowest_clearance: float = CUTOFF
    infeasible_steps: int = 0
    hard_relaxed_steps: int = 0
    gain_raised_steps: int = 0
    max_speed_ratio: float = 0.0


_SCENES: dict = {}  # (assets, arm, spheres, exclude) -> build_scene(...), per process
_ENVELOPES: dict = {}  # (assets, arm, config) -> arm_envelope(...), per process


def arm_envelope(model: mujoco.MjModel, robot: RobotDescription, arm: str, config: FilterConfig) -> FilterEnvelope:
    """The envelope the filter ``config`` states on ``arm`` (``filter_envelope``: spheres up to
    :data:`RADIUS`, the arm's keep-out cylinder, robosuite's initial configuration among the
    sample)."""
    radius, height = ARMS[arm].keep_out
    return filter_envelope(model, robot, config, obstacle_radius=RADIUS[1], keep_out_radius=radius,
                           keep_out_height=height, qpos=ARMS[arm].init_qpos)  # fmt: skip


def speed_range(envelope: FilterEnvelope, top: float = SPEED[1]) -> tuple[float, float]:
    """:data:`SPEED`, its top replaced by ``top``, capped by the envelope's speed ``v``:
    ``(min(low, v/2, top), min(top, v))`` [m/s]."""
    return min(SPEED[0], envelope.max_speed / 2, top), min(top, envelope.max_speed)


def _envelope(assets: str, arm: str, config: FilterConfig, model: mujoco.MjModel,
              robot: RobotDescription) -> FilterEnvelope:
    """:func:`arm_envelope` of ``config`` on ``arm`` (``model`` and ``robot``: any of its scenes,
    the spheres do not enter it), computed once per process."""
    if (assets, arm, config) not in _ENVELOPES:
        _ENVELOPES[assets, arm, config] = arm_envelope(model, robot, arm, config)
    return _ENVELOPES[assets, arm, config]


@dataclass(frozen=True)
class Spheres:
    """One episode's spheres (:func:`_spawn`): positions at the start (K, 3) [m], velocities (K, 3)
    [m/s], radii (K,) [m] and the times they leave the scene (K,) [s] (inf: never)."""

    position: np.ndarray
    velocity: np.ndarray
    radius: np.ndarray
    leave: np.ndarray

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(positions (K, 3) [m], active (K,)) at time ``t`` [s]: a sphere that has left is parked
        at (10 + k, 0, 1), far from every arm, as the episodes park it."""
        active = self.leave > t
        parked = np.array([_parked(k) for k in range(len(self.radius))])
        return np.where(active[:, None], self.position + self.velocity * t, parked), active


def _parked(k: int) -> tuple[float, float, float]:
    """Where sphere ``k`` waits once it has left the scene [m]: far from every arm, apart from the others."""
    return (10.0 + k, 0.0, 1.0)


def episode_start(model: mujoco.MjModel, robot: RobotDescription, arm: str, scenario: str, seed: int,
                  seconds: float, speed: tuple[float, float],
                  sensing: Callable[[float], float] | None) -> tuple[mujoco.MjData, Spheres]:
    """The state an episode starts from: a new ``MjData`` of ``model`` (a scene of
    :func:`scene_spec` for ``scenario``'s spheres) at robosuite's initial configuration of
    ``arm``, with seed ``seed``'s spheres (:func:`_spawn`: ``speed`` [m/s], ``sensing`` the range
    the moving ones start outside of, or None) placed (``model.geom_size`` set to their radii),
    after ``mj_forward``; and those spheres. RuntimeError (naming arm, scenario and seed) when
    they cannot be placed."""
    kinds = SCENARIOS[scenario]
    data = mujoco.MjData(model)
    data.qpos[model.jnt_qposadr[model.dof_jntid[robot.dof_ids]]] = ARMS[arm].init_qpos
    mujoco.mj_forward(model, data)
    arm_model = ArmModel(model, robot.geom_ids, robot.site_id, robot.capsules)
    a, b = arm_model.capsule_segments(data)
    try:
        drawn = Spheres(*_spawn(np.random.default_rng(seed), kinds, a, b, arm_model.capsule_radius,
                                data.site_xpos[robot.site_id], seconds, speed=speed, keep_out=ARMS[arm].keep_out,
                                sensing=sensing))  # fmt: skip
    except RuntimeError as error:
        raise RuntimeError(f"{arm}, {scenario}, seed {seed}: {error}") from None
    model.geom_size[[model.geom(_BALL.format(k)).id for k in range(len(kinds))], 0] = drawn.radius
    data.mocap_pos[[model.body(_BALL.format(k)).mocapid[0] for k in range(len(kinds))]] = drawn.position
    mujoco.mj_forward(model, data)
    return data, drawn


class Takeover(Protocol):
    """A controller that may take the arm over from the episode's policy (``escape.py --online``).

    At each physics step :func:`run_episode` asks :meth:`nominal` for the torque to filter, and,
    when the filter's rows gave way beyond their allowance, :meth:`gave_way` for the torque to
    apply instead of the filter's. Both see the step, ``data`` after ``mj_step1`` (the state the
    last physics step reached, its kinematics current) and the filter's obstacles as the filter
    sees them (positions, velocities, which are active); torques are the arm's (n,) [N m]."""

    def nominal(self, step: int, data: mujoco.MjData, obstacles: MocapSpheres, tau: np.ndarray) -> np.ndarray:
        """The nominal torque of this step: ``tau``, the policy's, or the takeover's own."""

    def gave_way(self, step: int, data: mujoco.MjData, obstacles: MocapSpheres, safe: np.ndarray,
                 hard: bool) -> np.ndarray:
        """The torque to apply where the rows gave way: ``safe``, the filter's, or the takeover's own;
        ``hard``: whether a guard, floor, joint-limit or self-collision row (:data:`HARD_ROWS`) was
        among them, not only the C3BF's."""


def run_episode(task: tuple[str, str, str, str, FilterConfig | None, int, float, tuple[float, float],
                            FilterConfig | None, tuple[tuple[str, str], ...]],
                takeover: Takeover | None = None) -> Episode:
    """One episode: ``task`` = (assets folder, arm, scenario, policy, the filter's configuration or
    None for none, seed, seconds, the spheres' speed range [m/s], the configuration whose envelope's
    sensing range the moving spheres start outside of (:func:`_spawn`), or None for none, the body
    pairs whose contacts :func:`scene_spec` excludes, () for none); with a filter, ``takeover`` (or
    None) may replace the policy's nominal torque and the torque applied where the rows give way."""
    assets, arm, scenario, policy, config, seed, seconds, speed, spawn_config, exclude = task
    filtered = config is not None
    kinds = SCENARIOS[scenario]
    key = (assets, arm, len(kinds), exclude)
    if key not in _SCENES:
        _SCENES[key] = build_scene(Path(assets), arm, len(kinds), exclude)
    model, robot, _ = _SCENES[key]
    sensing = None if spawn_config is None else _envelope(assets, arm, spawn_config, model, robot).min_sensing_range
    data, drawn = episode_start(model, robot, arm, scenario, seed, seconds, speed, sensing)
    velocity, radius, leave = drawn.velocity.copy(), drawn.radius, drawn.leave.copy()
    dofs = robot.dof_ids  # the arm's; a gripper's fingers are the model's other dofs
    balls = [model.geom(_BALL.format(k)).id for k in range(len(kinds))]
    mocap = [model.body(_BALL.format(k)).mocapid[0] for k in range(len(kinds))]
    spheres = MocapSpheres(model, [_BALL.format(k) for k in range(len(kinds))])
    arm_model = ArmModel(model, robot.geom_ids, robot.site_id, robot.capsules)
    controller = None
    if filtered:
        controller = SafetyController(model, data, robot, spheres, config,
                                      envelope=_envelope(assets, arm, config, model, robot))
    if controller is not None:
        arm_model = controller.arm
    out = Episode(arm, scenario, policy, filtered, seed)
    limit, speed_limit = robot.torque_limit, robot.joint_speed_limit
    jac = np.zeros((3, model.nv))
    draw = np.zeros(robot.n)
    policy_rng = np.random.default_rng([seed, 1])
    steps = int(round(seconds / TIMESTEP))

    def capsule_gaps() -> tuple[np.ndarray, np.ndarray]:
        """The closest point of every capsule axis to every sphere centre (K, S, 3) and the
        surfaces' gap (K, S) [m], at the current kinematics."""
        a, b = arm_model.capsule_segments(data)
        centres = data.mocap_pos[mocap]
        closest = segment_closest_points(a, b, centres)
        gaps = np.linalg.norm(closest - centres[:, None], axis=2) - arm_model.capsule_radius - radius[:, None]
        return closest, gaps

    def measure() -> tuple[np.ndarray, np.ndarray]:  # MuJoCo's own distances, sphere to geom, now
        # A geom lies inside its capsule, so the capsule's gap bounds the geom's from below: a pair
        # whose capsule gap is no lower than the lowest clearance so far cannot lower it.
        closest, bound = capsule_gaps()
        for k, s in zip(*np.nonzero(bound < min(out.lowest_clearance, CUTOFF)), strict=True):
            gap = mujoco.mj_geomDistance(model, data, balls[k], int(robot.geom_ids[s]),
                                         min(out.lowest_clearance, CUTOFF), None)  # fmt: skip
            out.lowest_clearance = min(out.lowest_clearance, gap)
        out.collided |= out.lowest_clearance < 0.0
        out.max_speed_ratio = max(out.max_speed_ratio, float(np.max(np.abs(data.qvel[dofs]) / speed_limit)))
        return closest, bound

    for step in range(steps):
        mujoco.mj_step1(model, data)  # kinematics of the state the last physics step reached
        closest, gaps = measure()
        if policy == "random":
            if step % HOLD_STEPS == 0:
                draw = policy_rng.uniform(-limit, limit)
            tau = data.qfrc_bias[dofs] + draw
        else:
            k, s = np.unravel_index(int(np.argmin(gaps)), gaps.shape)
            pull = data.mocap_pos[mocap[k]] - closest[k, s]
            mujoco.mj_jac(model, data, jac, None, closest[k, s], int(model.geom_bodyid[robot.geom_ids[s]]))
            tau = (data.qfrc_bias + jac.T @ (PULL_FORCE * pull / max(np.linalg.norm(pull), 1e-9)))[dofs]
        tau = np.clip(tau, -limit, limit)
        if controller is not None:
            spheres.velocity[:] = velocity
            if takeover is not None:
                tau = takeover.nominal(step, data, spheres, tau)
            tau, report = controller.filter(tau)
            hard = any(report.violation[kind] > 0.0 for kind in HARD_ROWS)
            if takeover is not None and report.infeasible_steps:
                tau = takeover.gave_way(step, data, spheres, tau, hard)
            out.infeasible_steps += report.infeasible_steps
            out.hard_relaxed_steps += hard
            out.gain_raised_steps += report.gain_raised_steps
        robot.write_ctrl(model, data, tau)
        mujoco.mj_step2(model, data)
        data.mocap_pos[mocap] += velocity * TIMESTEP
        out.steps += 1
        for k in np.flatnonzero(leave <= out.steps * TIMESTEP):  # past its aim: out of the scene
            leave[k], velocity[k] = np.inf, 0.0
            spheres.clear(k)
            data.mocap_pos[mocap[k]] = _parked(k)
    mujoco.mj_kinematics(model, data)
    measure()
    return out


# ----------------------------------------------------------------------------- the table


def summarise(episodes: list[Episode]) -> list[dict]:
    """One row per (arm, scenario, policy), filtered and unfiltered episodes side by side (the
    unfiltered fields None where no unfiltered episode ran: ``--no-unfiltered``)."""
    rows = {}
    for e in sorted(episodes, key=lambda e: (list(ARMS).index(e.arm), list(SCENARIOS).index(e.scenario),
                                             POLICIES.index(e.policy), e.seed)):  # fmt: skip
        row = rows.setdefault((e.arm, e.scenario, e.policy), {
            "arm": e.arm, "scenario": e.scenario, "policy": e.policy, "episodes": 0, "collision_episodes": 0,
            "lowest_clearance_m": CUTOFF, "infeasible_per_1000_steps": 0.0, "gain_raised_per_1000_steps": 0.0,
            "hard_relaxed_per_1000_steps": 0.0,
            "max_speed_ratio": 0.0, "unfiltered_episodes": 0, "unfiltered_collision_episodes": 0,
            "unfiltered_lowest_clearance_m": CUTOFF,
            "unfiltered_max_speed_ratio": 0.0, "_steps": 0, "_infeasible": 0, "_raised": 0, "_hard": 0})  # fmt: skip
        prefix = "" if e.filtered else "unfiltered_"
        row[prefix + "episodes"] += 1
        row[prefix + "collision_episodes"] += int(e.collided)
        row[prefix + "lowest_clearance_m"] = min(row[prefix + "lowest_clearance_m"], e.lowest_clearance)
        row[prefix + "max_speed_ratio"] = max(row[prefix + "max_speed_ratio"], e.max_speed_ratio)
        if e.filtered:
            row["_steps"] += e.steps
            row["_infeasible"] += e.infeasible_steps
            row["_hard"] += e.hard_relaxed_steps
            row["_raised"] += e.gain_raised_steps
    for row in rows.values():
        steps = max(row.pop("_steps"), 1)
        row["infeasible_per_1000_steps"] = 1e3 * row.pop("_infeasible") / steps
        row["gain_raised_per_1000_steps"] = 1e3 * row.pop("_raised") / steps
        row["hard_relaxed_per_1000_steps"] = 1e3 * row.pop("_hard") / steps
        if not row["unfiltered_episodes"]:
            for name in ("unfiltered_collision_episodes", "unfiltered_lowest_clearance_m", "unfiltered_max_speed_ratio"):
                row[name] = None
    return list(rows.values())


def print_table(rows: list[dict], unsupported: dict[str, str]) -> None:
    """The table (module docstring; the unfiltered columns when unfiltered episodes ran), then the
    arms the library refused with its message."""
    twins = any(r["unfiltered_episodes"] for r in rows)
    print(f"{'':<37}{' filtered ':-^70}" + (f"   {' unfiltered ':-^32}" if twins else ""))
    print(f"{'arm':<14} {'scenario':<9} {'policy':<11} {'episodes':>8} {'collisions':>10} {'lowest [m]':>10} "
          f"{'infeas/1k':>9} {'raised/1k':>9} {'hard/1k':>7} {'max|qd|/lim':>11}"
          + (f"   {'collisions':>10} {'lowest [m]':>10} {'max|qd|/lim':>11}" if twins else ""))  # fmt: skip
    for r in rows:
        filtered = (f"{r['episodes']:>8} {r['collision_episodes']:>10} {r['lowest_clearance_m']:>+10.4f} "
                    f"{r['infeasible_per_1000_steps']:>9.2f} {r['gain_raised_per_1000_steps']:>9.2f} "
                    f"{r['hard_relaxed_per_1000_steps']:>7.2f} "
                    f"{r['max_speed_ratio']:>11.2f}")  # fmt: skip
        unfiltered = ("" if not r["unfiltered_episodes"] else
                      f"   {r['unfiltered_collision_episodes']:>10} {r['unfiltered_lowest_clearance_m']:>+10.4f} "
                      f"{r['unfiltered_max_speed_ratio']:>11.2f}")  # fmt: skip
        print(f"{r['arm']:<14} {r['scenario']:<9} {r['policy']:<11} {filtered}{unfiltered}")
    for arm, why in unsupported.items():
        print(f"{arm}: not run, the library refuses it: {why}")


# ----------------------------------------------------------------------------- main


def _check_arm(assets: Path, arm: str, config: FilterConfig,
               exclude: Sequence[tuple[str, str]] = ()) -> tuple[str | None, list[str], FilterEnvelope | None]:
    """(None, notes, the filter's envelope on the arm) when the filter ``config`` runs on ``arm``
    (its scene with ``exclude``'s pairs excluded), else (the library's refusal, notes, None). The
    notes are :func:`build_scene`'s and the warnings the filter gives when it is built."""
    try:
        model, robot, notes = build_scene(assets, arm, 1, exclude)
        with _warnings_into(notes):  # the filter's own, e.g. a contact no row can part
            SafetyController(model, mujoco.MjData(model), robot, MocapSpheres(model, [_BALL.format(0)]), config)
    except UnsupportedModelError as error:
        return str(error), [], None
    return None, notes, _envelope(str(assets), arm, config, model, robot)  # run_episode's too


def _choices(values: list[str], valid, what: str, parser: argparse.ArgumentParser) -> list[str]:
    unknown = [v for v in values if v not in valid]
    if unknown:
        parser.error(f"unknown {what} {', '.join(unknown)}; choose from {', '.join(valid)}")
    return list(dict.fromkeys(values))


def _progress(episodes, total: int, start: float) -> list[Episode]:
    """The ``total`` episodes of the iterable ``episodes``, in order, with a line on stderr at
    every tenth of them: how many are done, the wall time so far and the time left at that rate."""
    done = []
    for episode in episodes:
        done.append(episode)
        if total >= 20 and len(done) % (total // 10) == 0 and len(done) < total:
            elapsed = time.perf_counter() - start
            print(f"{len(done)} of {total} episodes, {elapsed:.0f} s, about {elapsed * (total / len(done) - 1):.0f} s "
                  "left", file=sys.stderr, flush=True)  # fmt: skip
    return done


def main(argv: list[str] | None = None) -> dict:
    """Run the benchmark (``argv``: the command line without the program name) and return what it
    writes to ``--json``: ``settings``, ``unsupported`` (arm -> the library's message), ``notes``
    (arm -> added scene parts and the library's warnings) and ``configurations`` (the rows)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=10, help="episodes per configuration (each run filtered "
                        "and unfiltered)")  # fmt: skip
    parser.add_argument("--arms", nargs="+", help=f"from {', '.join(ARMS)} (default: all)")
    parser.add_argument("--scenarios", nargs="+", help=f"from {', '.join(SCENARIOS)} (default: all)")
    parser.add_argument("--policies", nargs="+", default=list(POLICIES), help=f"from {', '.join(POLICIES)}")
    parser.add_argument("--seconds", type=float, default=SECONDS, help="episode length [s]")
    parser.add_argument("--seed", type=int, default=0, help="episode i uses seed + i in every configuration")
    parser.add_argument("--workers", type=int, default=1, help="processes")
    parser.add_argument("--json", type=Path, help="write the settings and the table here")
    parser.add_argument("--cache", help=f"robosuite download folder (default ${CACHE_VARIABLE} or "
                        f"~/.cache/c3bf-gym/robosuite-{ROBOSUITE_VERSION})")  # fmt: skip
    parser.add_argument("--quick", action="store_true", help="smoke run: 1 episode of 1 s, by default on iiwa "
                        "in static and head_on")  # fmt: skip
    add_filter_settings(parser, "--set")
    parser.add_argument("--no-unfiltered", action="store_true", help="skip the unfiltered twin of each episode")
    parser.add_argument("--ignore-envelope", action="store_true", help=f"spheres at {SPEED[0]}-{SPEED[1]} m/s on "
                        "every arm, not capped by the filter's envelope")  # fmt: skip
    parser.add_argument("--max-speed", type=float, default=SPEED[1], metavar="V",
                        help=f"the spheres' top speed [m/s] before the envelope's cap (default {SPEED[1]}); a "
                             "lower one asks whether slower spheres are safer")  # fmt: skip
    parser.add_argument("--exclude", nargs=2, action="append", default=[], metavar=("BODY1", "BODY2"),
                        help="switch off the contacts between two of the model's bodies (repeatable), as the "
                             "filter's warning advises for a contact no row can part, e.g. the Sawyer's "
                             "right_l0 right_arm_base_link (default: none, the files as shipped)")  # fmt: skip
    args = parser.parse_args(argv)
    try:
        config = CONFIG.replace(**dict(args.set))
    except (TypeError, ValueError) as error:
        parser.error(f"--set: {error}")
    if args.quick:
        args.episodes, args.seconds = 1, 1.0
    arms = _choices(args.arms or (["iiwa"] if args.quick else list(ARMS)), ARMS, "arm", parser)
    scenarios = _choices(args.scenarios or (["static", "head_on"] if args.quick else list(SCENARIOS)), SCENARIOS,
                         "scenario", parser)  # fmt: skip
    policies = _choices(args.policies, POLICIES, "policy", parser)
    if args.episodes < 1 or args.workers < 1 or not args.seconds > 0:
        parser.error("--episodes and --workers must be >= 1 and --seconds > 0")
    if not 0 < args.max_speed < float("inf"):
        parser.error(f"--max-speed must be a finite speed > 0 (m/s), got {args.max_speed}")
    assets = robosuite_assets(args.cache)

    unsupported, notes, envelopes, speeds = {}, {}, {}, {}
    exclude = tuple(map(tuple, args.exclude))
    for arm in arms:
        try:
            why, notes[arm], envelope = _check_arm(assets, arm, config, exclude)
        except ValueError as error:
            parser.error(str(error))
        if why is not None:
            unsupported[arm] = why
            continue
        envelopes[arm] = {"max_speed_m_s": envelope.max_speed, "keep_out_m": list(ARMS[arm].keep_out),
                          "limiting_geom": envelope.limiting_geom,
                          "limiting_point_m": envelope.limiting_point.tolist()}  # fmt: skip
        speeds[arm] = ((min(SPEED[0], args.max_speed), args.max_speed) if args.ignore_envelope
                       else speed_range(envelope, args.max_speed))  # fmt: skip
        notes[arm].append(f"the filter's envelope: {envelope.max_speed:.3f} m/s for spheres up to {RADIUS[1]} m, "
                          f"keep-out {ARMS[arm].keep_out[0]} m x {ARMS[arm].keep_out[1]} m (limited by "
                          f"{envelope.limiting_geom}); spheres at {speeds[arm][0]:.3g}-{speeds[arm][1]:.3g} m/s")
    runnable = [arm for arm in arms if arm not in unsupported]
    twins = (config,) if args.no_unfiltered else (config, None)
    spawn_config = None if args.ignore_envelope else config
    tasks = [(str(assets), arm, scenario, policy, twin, args.seed + i, args.seconds, speeds[arm], spawn_config,
              exclude)
             for arm in runnable for scenario in scenarios for policy in policies
             for i in range(args.episodes) for twin in twins]  # fmt: skip
    print(f"robosuite {ROBOSUITE_VERSION} arms from {assets}: {len(tasks)} episodes of {args.seconds:g} s "
          f"(dt {TIMESTEP} s) on {args.workers} worker(s)")  # fmt: skip
    for arm, lines in notes.items():
        for line in lines:
            print(f"{arm}: {line}")
    start = time.perf_counter()
    if args.workers == 1:
        episodes = _progress(map(run_episode, tasks), len(tasks), start)
    else:
        with mp.get_context("spawn").Pool(args.workers) as pool:
            episodes = _progress(pool.imap(run_episode, tasks, chunksize=1), len(tasks), start)
    rows = summarise(episodes)
    print_table(rows, unsupported)
    print(f"wall time {time.perf_counter() - start:.1f} s")
    result = {"settings": {"robosuite": ROBOSUITE_VERSION, "episodes_per_configuration": args.episodes,
                           "seconds": args.seconds, "timestep": TIMESTEP, "seed": args.seed, "arms": arms,
                           "scenarios": scenarios, "policies": policies, "filter": repr(config),
                           "exclude": [list(pair) for pair in exclude],
                           "joint_speed_limit_rad_s": {arm: list(ARMS[arm].joint_speed_limit) for arm in arms},
                           "sphere_speed_m_s": {arm: list(speed) for arm, speed in speeds.items()},
                           "envelopes": envelopes},
              "unsupported": unsupported, "notes": notes, "configurations": rows,
              "episodes": [asdict(e) for e in episodes]}  # fmt: skip
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2))
        print(f"wrote {args.json}")
    return result


if __name__ == "__main__":
    main()
