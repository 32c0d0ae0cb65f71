"""``C3BFReach-v0``: a torque-controlled UR5e-class arm reaching goals among moving spheres."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Callable, Literal

import mujoco
import numpy as np
from gymnasium import error, spaces, utils
from gymnasium.envs.mujoco.mujoco_env import MujocoEnv

from c3bf_gym.controllers._kernels import BoundImpedance
from c3bf_gym.controllers.impedance import ImpedanceHook
from c3bf_gym.envs._kernels import Drive, Observed, Physics, departed, entry, observe, policy_steps
from c3bf_gym.safety.controller import SafetyController
from c3bf_gym.safety.dynamics import ArmModel
from c3bf_gym.safety.obstacles import Obstacles
from c3bf_gym.safety.robot import RobotDescription, UnprotectedGeometryWarning
from c3bf_gym.safety.substep import FilterCall
from c3bf_gym.scenarios import (
    MAX_OBSTACLES,
    ArmCapsules,
    Envelope,
    ObstacleSample,
    ObstacleSampler,
    ObstacleSpec,
    Scenario,
    get_scenario,
    max_spawn_distance,
)
from c3bf_gym.validation import boolean, choice, integer, number, number_range

__all__ = [
    "C3BFReachEnv", "DISTANCE_CUTOFF", "HOOK_STAGES", "OBSERVATION_LAYOUT", "OBSERVATION_SLICES", "ROBOTS", "ReachRobot",
    "TorqueHook", "UR5E_JOINT_SPEED", "observation_layout", "observation_slices",
]

#: A per-physics-step torque transformation: total joint torque in (N m, gravity compensation
#: included), total joint torque out. It may read ``env.data`` (kinematics and dynamics are
#: current for the state about to be integrated) and must not write to it.
TorqueHook = Callable[[np.ndarray], np.ndarray]

#: Hook stages in the order they run at every physics step: a ``nominal`` controller first (it may
#: replace the commanded torque), then a ``filter`` (the last word before the physics).
HOOK_STAGES = ("nominal", "filter")


def observation_layout(n_joints: int) -> tuple[tuple[str, int, str], ...]:
    """The observation of an arm with ``n_joints`` joints: (name, size, unit) in order. Obstacle
    entries repeat for each of the 8 slots. Its length is ``2 n + 73``."""
    return (
        ("joint_pos", n_joints, "rad"),
        ("joint_vel", n_joints, "rad/s"),
        ("tool_pos", 3, "m (world frame)"),
        ("tool_vel", 3, "m/s"),
        ("goal_rel", 3, "m (goal - tool)"),
        ("obstacle_rel_pos", 3 * MAX_OBSTACLES, "m (obstacle centre - tool), slot-major"),
        ("obstacle_vel", 3 * MAX_OBSTACLES, "m/s"),
        ("obstacle_radius", MAX_OBSTACLES, "m"),
        ("obstacle_sensed", MAX_OBSTACLES, "1 if sensed, else 0 (and the slot's other entries are 0)"),
    )


def observation_slices(n_joints: int) -> dict[str, slice]:
    """Where each part of :func:`observation_layout` lies in the observation vector."""
    layout = observation_layout(n_joints)
    ends = np.cumsum([size for _, size, _ in layout]).tolist()
    return {name: slice(end - size, end) for (name, size, _), end in zip(layout, ends)}


#: The UR5e's (``C3BFReach-v0``'s) observation layout and slices; other arms: the functions above.
OBSERVATION_LAYOUT = observation_layout(6)
OBSERVATION_SLICES = observation_slices(6)

_ARM_CONTYPE = 2  # arm geoms: contype 2, conaffinity 1 (see assets/ur5e.xml)
_PARK_DEPTH = -50.0  # unused obstacles wait here, far beyond the distance cutoff
_ACTION_BOUND = 1.0 + 1e-6  # |action| allowed, with a little rounding room above 1
#: Signed distances between every obstacle and every arm geom come from MuJoCo distance sensors
#: (``mjSENS_GEOMDIST``), computed in C at every physics step; beyond this cutoff (m) they read
#: the cutoff itself.
DISTANCE_CUTOFF = 3.0
#: UR5e joint speed limit, 180 deg/s on every joint (UR5e technical specifications): the filter's
#: joint-speed rows bound each joint at ``FilterConfig.joint_speed_fraction`` of it.
UR5E_JOINT_SPEED = np.pi
_GOAL_MIN_TRAVEL = 0.3  # m, minimum start-to-goal distance


@dataclass(frozen=True)
class ReachRobot:
    """One arm's numbers for the reaching task, in one place.

    Attributes:
        name: the ``robot`` argument that selects it.
        scene: the MJCF scene in ``c3bf_gym.assets`` (the arm, a floor, ``goal`` and the mocap
            spheres ``obstacle_0..7``).
        n_joints: the arm's joints (the observation's first two parts).
        joint_speed_limit: the joint speed limits [rad/s], one per joint.
        goal_low, goal_high: the goal region, an axis-aligned box in front of the robot [m].
        home_noise: the uniform joint noise around the ``home`` keyframe at reset [rad].
        keep_out_radius, keep_out_height: the radius and height of the
            :class:`~c3bf_gym.scenarios.Envelope`'s keep-out cylinder around the base's vertical
            axis [m]: the base and the links about that axis, which cannot sidestep an obstacle
            (the pan joint turns them in place), lie inside it. The filter's envelope
            (:func:`c3bf_gym.filter.scenario_envelope`) covers the task's obstacles only with
            them out of reach.
        posture_stiffness: the default impedance controller's null-space pull towards the
            ``home`` keyframe, ``K_q`` [N m/rad] on every joint
            (:func:`c3bf_gym.wrappers.default_impedance`). The pull works against the filter
            whenever the filter moves a link out of an obstacle's way, so it is kept small where
            the wrist's torque limits are small (``train/scripted_reference.py --robot ...
            --posture-stiffness ...``; the docs' RL results page).
    """

    name: str
    scene: str
    n_joints: int
    joint_speed_limit: tuple[float, ...]
    goal_low: tuple[float, float, float] = (0.3, -0.4, 0.15)
    goal_high: tuple[float, float, float] = (0.65, 0.4, 0.6)
    home_noise: float = 0.05
    keep_out_radius: float = 0.3
    keep_out_height: float = 0.5
    posture_stiffness: float = 20.0

    def goal_corners(self) -> np.ndarray:
        """(8, 3) the goal box's corners (the farthest goal from any start is one of them)."""
        return np.array([[hi if bit else lo for lo, hi, bit in zip(self.goal_low, self.goal_high, bits)]
                         for bits in np.ndindex(2, 2, 2)])  # fmt: skip


#: The arms the task runs on. Both reach the same goal box: its farthest corner from the
#: shoulder is 0.79 m for the Panda (reach 0.855 m, Franka's datasheet) and less for the UR5e.
ROBOTS: dict[str, ReachRobot] = {
    # Keep-out 0.5 m high: the upper arm stands on the base axis when the shoulder is upright, and
    # its points up to about 0.45 m can only move along one horizontal line (the envelope, 8 cm
    # spheres, 1 m sensing: 0.33 m/s with 0.45 m, 0.50 m/s with 0.5 m; docs/design-decisions.md).
    "ur5e": ReachRobot("ur5e", "scene.xml", 6, (UR5E_JOINT_SPEED,) * 6),
    # Franka FCI limits: 2.175 rad/s on joints 1-4, 2.61 rad/s on joints 5-7 (assets/panda.xml).
    # Keep-out 0.2 m: the base and links 1-2 (capsules of radius 0.06 m on the base axis) lie
    # within it; with the UR5e's 0.3 m, head-on and multi obstacles aimed at the Panda's tool
    # (0.31 m from the axis at home) found no path outside it for some seeds. 0.7 m high: links
    # 2-3 stand on the base axis up to 0.65 m with the shoulder upright (the envelope: 0.10 m/s
    # with 0.45 m, 0.27 m/s with 0.65 m, 0.50 m/s with 0.7 m). Posture stiffness 2 N m/rad, not
    # the UR5e's 20: at 20 the pull to home (20 N m at 1 rad, beyond the wrist's 12 N m) fought the
    # filter's evasions, and the zero-action policy under the default filter reached the goal in
    # 0.26 of the evaluation's `multi` episodes (0.89 unfiltered); at 2 in 0.91 (docs/results/rl.md).
    "panda": ReachRobot("panda", "panda_scene.xml", 7, (2.175,) * 4 + (2.61,) * 3, keep_out_radius=0.2,
                        keep_out_height=0.7, posture_stiffness=2.0),
}
#: What ``step`` saves to undo itself: every part of MuJoCo's state that integration reads
#: (time, qpos, qvel, act, history, warmstart, ctrl, applied forces, eq_active, mocap poses,
#: userdata, plugin and plastic state), so that restoring it continues bit-identically.
_STEP_STATE = mujoco.mjtState.mjSTATE_INTEGRATION


def _asset(name: str) -> str:
    """The path of an MJCF file of the package's ``c3bf_gym.assets``: installed package data, or,
    when ``c3bf_gym`` is imported from a source checkout (the checkout on ``sys.path``, as in Ray
    workers started in it), the checkout's top-level ``assets/`` folder that the install maps
    there."""
    try:
        return str(resources.files("c3bf_gym.assets").joinpath(name))
    except ModuleNotFoundError:
        checkout = Path(__file__).resolve().parents[2] / "assets"
        if not (checkout / name).is_file():
            raise
        return str(checkout / name)


class C3BFReachEnv(MujocoEnv, utils.EzPickle):
    r"""Reach a goal with a torque-controlled arm while spheres move through the workspace.

    The arm is a UR5e-class manipulator written in MJCF from Universal Robots' published DH
    parameters, masses, centres of mass and torque limits (``assets/ur5e.xml`` cites each number);
    with ``robot="panda"`` (``C3BFReachPanda-v0``) the 7-joint Franka Emika Panda
    (``assets/panda.xml``), in the same task. The spaces below are the UR5e's; see Arguments.
    Physics runs at 500 Hz; the policy acts every ``frame_skip`` physics steps (default 10: 50 Hz).

    ## Action Space
    ``Box(-1, 1, (6,), float32)``: joint torque as a fraction of each joint's limit
    (150, 150, 150, 28, 28, 28 N m), applied on top of gravity compensation (when
    ``gravity_compensation=True``); MuJoCo clamps the total to the limits. Actions outside
    ``[-1, 1]``, of the wrong shape or non-finite raise ``ValueError``: nothing is clipped silently.

    At every physics step the commanded total torque passes through the installed *torque hooks*
    (``add_torque_hook``): a ``nominal`` controller (e.g. Cartesian impedance), then a ``filter``
    (the C3BF safety filter). This is how wrappers act at 500 Hz rather than at the policy rate.

    ## Observation Space
    ``Box(-inf, inf, (85,), float32)``, in order (see ``OBSERVATION_LAYOUT``):

    | index | name | unit |
    |-------|------|------|
    | 0-5   | joint positions | rad |
    | 6-11  | joint velocities | rad/s |
    | 12-14 | tool position (``ee_site``) | m, world |
    | 15-17 | tool linear velocity | m/s |
    | 18-20 | goal minus tool position | m |
    | 21-44 | obstacle centre minus tool, 8 slots x 3 | m |
    | 45-68 | obstacle velocity, 8 slots x 3 | m/s |
    | 69-76 | obstacle radius, 8 slots | m |
    | 77-84 | obstacle sensed flag, 8 slots | 1 or 0 |

    An obstacle is *sensed* (the paper's perception boundary) when its surface is within
    ``sensing_radius`` of some arm geom; unsensed and unused slots are all zeros.

    ## Rewards
    ``reward = progress + success - distance - effort`` with, per step,
    ``progress = progress_weight * (d_prev - d)`` (d: tool-to-goal distance in m),
    ``success = success_bonus`` if ``d < success_tolerance`` else 0,
    ``distance = distance_weight * d`` (0 by default; Reacher's dense term) and
    ``effort = effort_weight * mean_j (u_j / limit_j)^2`` averaged over the physics steps, where
    ``u`` is the torque applied on top of gravity compensation. The progress term only rewards
    net approach and the success term is flat inside the tolerance, so neither prefers the
    goal's centre to its rim: ``distance_weight > 0`` does (a learned policy that hovers near the
    rim drifts out of it). ``info`` carries the four terms as ``reward_progress``,
    ``reward_success``, ``reward_distance`` and ``reward_effort`` (the last two negative or zero);
    they sum to the reward. ``info["is_success"]`` is ``d < success_tolerance``.

    ## Cost and safety signals
    Computed from MuJoCo's geometry at every physics step, independent of any filter:
    ``info["cost"]`` is 1.0 if any obstacle touched any arm geom (base, links, tool) during the step
    (signed distance <= 0), else 0.0 (the Safety-Gymnasium convention); ``info["min_distance"]`` is
    the smallest signed surface distance (m) between any obstacle and any arm geom during the step
    (capped at ``DISTANCE_CUTOFF`` = 3 m); ``info["episode_cost"]`` is the sum of ``cost`` so far in
    the episode (at the last step, the episode's number of collision steps: what SB3's
    ``Monitor(info_keywords=("episode_cost",))`` logs). Distances are MuJoCo's exact signed geom distances
    (distance sensors, one per obstacle/arm-geom pair).

    ## Starting State
    The ``home`` keyframe (tool in front of the robot, pointing down) plus uniform joint noise of
    +/-0.05 rad, at rest. The goal is drawn uniformly in the box x in [0.3, 0.65], y in
    [-0.4, 0.4], z in [0.15, 0.6] m, at least 0.3 m from the tool. Obstacles follow the scenario.

    ## Episode End
    Truncation after ``max_episode_steps`` (250 steps, 5 s, set at registration). Termination only
    on collision and only with ``terminate_on_collision=True``. ``step`` before the first
    ``reset`` (or after a ``reset`` that raised) raises ``gymnasium.error.ResetNeeded``, also on
    the bare class (``gym.make`` adds Gymnasium's ``OrderEnforcing`` on top).

    ## Errors during a step
    A ``step`` that raises (a torque hook mid-step, e.g. the safety filter's
    ``SafetyInfeasibleError`` with ``on_infeasible="raise"``, an interrupt, a renderer error)
    leaves the environment as it was before the call, then re-raises the same exception
    unchanged: MuJoCo's integration state (``mjSTATE_INTEGRATION``: time, joints, obstacle
    positions, warm start, ...) with its derived quantities recomputed, the obstacles' velocity,
    radius, activity and spec, their geom sizes in the model, the episode's reward and cost
    bookkeeping, and ``np_random`` (respawns draw from it). Stepping on then continues exactly as
    if the failed call had never been made. ``state_version`` is the exception: it moves on to a
    number never used before, so no cache keyed on a version seen before or during the failed
    call takes itself for current. Hooks' own state (a filter's counters and warm start) is
    theirs to manage.

    ## Scenarios
    ``static``, ``head_on``, ``crossing``, ``multi`` (the paper's four), ``random`` (uniform mixture
    of the four, the default), ``random_multi`` (the four, ``multi`` in half the episodes: a
    training mixture) and ``none``; or any :class:`~c3bf_gym.scenarios.Scenario` instance.
    Obstacles move at constant velocity and respawn (redrawn by their spec) when they leave the
    workspace box. The :class:`~c3bf_gym.scenarios.Envelope` bounds the speed of moving obstacles
    (``obstacle_speed_range``, default 0.1-0.4 m/s; static ones are at rest) and radius (``obstacle_radius_range``, default
    0.04-0.08 m), spawns every obstacle at least 0.2 m from the arm, and keeps every path out of a
    0.3 m-radius, 0.45 m-high keep-out cylinder around the base.

    ## Arguments
    ``scenario``, ``frame_skip``, ``gravity_compensation``, ``sensing_radius`` (m),
    ``terminate_on_collision``, ``success_tolerance`` (m), ``obstacle_speed_range`` (m/s),
    ``obstacle_radius_range`` (m), ``progress_weight``, ``success_bonus``, ``effort_weight``,
    ``distance_weight``, ``render_mode`` (``human``, ``rgb_array``, ``depth_array``), ``width``, ``height``,
    ``camera_name``, ``robot`` (``"ur5e"``, the default, or ``"panda"``: the Franka Emika Panda,
    7 joints, ``assets/panda_scene.xml``; :data:`ROBOTS` holds each arm's numbers, and
    ``C3BFReachPanda-v0`` registers it). With n joints the observation has ``2 n + 73`` entries
    (:func:`observation_layout`; the table above is the UR5e's), the action n, and the torque
    limits are the arm's. Numbers may be Python or numpy numbers (not bools or strings), the two flags
    must be bools, ranges exactly ``(low, high)``; anything else raises ``ValueError`` naming the
    argument, the value and the valid form. A scenario with an obstacle the envelope can never
    place (every point it could spawn at lies within ``spawn_clearance`` plus its radius of the
    tool's start) is refused here too, naming the obstacle and the ``path_fraction`` it needs.
    """

    metadata = {"render_modes": ["human", "rgb_array", "depth_array"], "render_fps": 50}

    def __init__(
        self,
        *,
        scenario: str | Scenario = "random",
        frame_skip: int = 10,
        gravity_compensation: bool = True,
        sensing_radius: float = 1.0,
        terminate_on_collision: bool = False,
        success_tolerance: float = 0.05,
        obstacle_speed_range: tuple[float, float] = (0.1, 0.4),
        obstacle_radius_range: tuple[float, float] = (0.04, 0.08),
        progress_weight: float = 50.0,
        success_bonus: float = 1.0,
        effort_weight: float = 0.05,
        distance_weight: float = 0.0,
        render_mode: str | None = None,
        width: int = 480,
        height: int = 480,
        camera_name: str = "overview",
        robot: str = "ur5e",
    ) -> None:
        utils.EzPickle.__init__(  # by keyword: a copy is built as this one was
            self, scenario=scenario, frame_skip=frame_skip, gravity_compensation=gravity_compensation,
            sensing_radius=sensing_radius, terminate_on_collision=terminate_on_collision,
            success_tolerance=success_tolerance, obstacle_speed_range=obstacle_speed_range,
            obstacle_radius_range=obstacle_radius_range, progress_weight=progress_weight, success_bonus=success_bonus,
            effort_weight=effort_weight, distance_weight=distance_weight, render_mode=render_mode, width=width,
            height=height, camera_name=camera_name, robot=robot,
        )  # fmt: skip
        #: The arm's task numbers (:data:`ROBOTS`).
        self.task_robot: ReachRobot = ROBOTS[choice("robot", robot, ROBOTS)]
        self.scenario = scenario if isinstance(scenario, Scenario) else get_scenario(scenario)
        #: The concrete scenario of the current episode: ``scenario`` itself, or the mixture
        #: component ``reset`` drew (``random`` draws one of the paper's four per episode).
        self.episode_scenario: Scenario = self.scenario
        frame_skip = integer("frame_skip", frame_skip, low=1)
        self.gravity_compensation = boolean("gravity_compensation", gravity_compensation)
        self.sensing_radius = number("sensing_radius", sensing_radius, low=0.0, low_open=True, unit="m")
        self.terminate_on_collision = boolean("terminate_on_collision", terminate_on_collision)
        self.success_tolerance = number("success_tolerance", success_tolerance, low=0.0, low_open=True, unit="m")
        self.envelope = Envelope(
            keep_out_radius=self.task_robot.keep_out_radius,
            keep_out_height=self.task_robot.keep_out_height,
            speed_range=number_range("obstacle_speed_range", obstacle_speed_range, low=0.0, unit="m/s"),
            radius_range=number_range("obstacle_radius_range", obstacle_radius_range, low=0.0, low_open=True, unit="m"),
        )
        self._weights = tuple(number(name, value, low=0.0) for name, value in (
            ("progress_weight", progress_weight), ("success_bonus", success_bonus), ("effort_weight", effort_weight),
            ("distance_weight", distance_weight)))  # fmt: skip
        render_mode = choice("render_mode", render_mode, (None, *self.metadata["render_modes"]))
        width, height = integer("width", width, low=1), integer("height", height, low=1)

        self.metadata = {**self.metadata, "render_fps": int(round(1.0 / (0.002 * frame_skip)))}
        #: Where each part of the observation lies (:func:`observation_slices`).
        self.observation_slices = observation_slices(self.task_robot.n_joints)
        size = max(part.stop for part in self.observation_slices.values())
        observation_space = spaces.Box(-np.inf, np.inf, shape=(size,), dtype=np.float32)
        MujocoEnv.__init__(
            self,
            _asset(self.task_robot.scene),
            frame_skip,
            observation_space=observation_space,
            render_mode=render_mode,
            width=width,
            height=height,
            camera_name=camera_name,
        )
        self._setup_model()
        self._check_scenario(self.scenario)
        self._init_bookkeeping()

    def _init_bookkeeping(self) -> None:
        """The state :meth:`step` and :meth:`reset` keep besides MuJoCo's: the torque hooks and the
        compiled paths they select, the state version, the drive's buffers, the obstacle sampler,
        the episode's tallies and the step's undo record."""
        self._hooks: dict[str, TorqueHook] = {}
        #: Incremented whenever ``data`` moves to a new state (each physics step, reset,
        #: respawn, a failed step's roll-back): consumers key their per-state caches on it. It
        #: only grows, so a number once seen never stands for another state.
        self.state_version = 0
        self._arm = None
        self._hook_chain: tuple[TorqueHook, ...] = ()
        self._compiled_filter: SafetyController | None = None
        self._compiled_nominal: ImpedanceHook | None = None
        self._entry_cache: tuple | None = None  # (nominal, filter buffers, policy_steps' entry point): _steps_entry
        n = self.model.nv
        self._filter_scratch = (np.zeros(n), np.zeros(n), np.zeros((self.frame_skip, n)))  # tau_nom, tau, effort rows
        self._drive = Drive(self._gravcomp, self._ctrl, self._inv_limit, *self._filter_scratch)
        self._sampler = ObstacleSampler(self.envelope)
        self._workspace = tuple(np.asarray(c, dtype=float) for c in self.envelope.workspace)
        self._departed = entry(departed, self.obstacle_pos, self.obstacle_active, *self._workspace)
        self._goal_distance = 0.0
        self._episode_cost = 0.0
        self._needs_reset = True
        # step's undo record: MuJoCo's state, saved at every step, and the obstacles' bookkeeping,
        # saved only when a step is about to respawn (see _save_obstacles)
        self._saved_state = np.empty(mujoco.mj_stateSize(self.model, _STEP_STATE))
        self._saved_obstacles = (
            np.empty_like(self.obstacle_vel),
            np.empty_like(self.obstacle_acc),
            np.empty_like(self.obstacle_radius),
            np.empty_like(self.obstacle_active),
            self.model.geom_size[self.obstacle_geom_ids].copy(),
            self.model.geom_rbound[self.obstacle_geom_ids].copy(),
        )
        self._saved_specs: list = []
        self._saved_rng: dict | None = None
        self._obstacles_saved = False

    # ------------------------------------------------------------------ model and spaces
    def _setup_model(self) -> None:
        m = self.model
        obj = mujoco.mjtObj
        self.arm_geom_ids = np.flatnonzero(m.geom_contype == _ARM_CONTYPE)
        self.obstacle_geom_ids = np.array(
            [mujoco.mj_name2id(m, obj.mjOBJ_GEOM, f"obstacle_{i}") for i in range(MAX_OBSTACLES)]
        )
        obstacle_bodies = m.geom_bodyid[self.obstacle_geom_ids]
        mocap = m.body_mocapid[obstacle_bodies]
        if not np.array_equal(mocap, np.arange(mocap[0], mocap[0] + MAX_OBSTACLES)):
            raise RuntimeError("scene.xml must declare obstacle_0..7 as consecutive mocap bodies")
        self._goal_mocap = int(m.body_mocapid[mujoco.mj_name2id(m, obj.mjOBJ_BODY, "goal")])
        self.ee_site_id = mujoco.mj_name2id(m, obj.mjOBJ_SITE, "ee_site")
        self.torque_limit = m.jnt_actfrcrange[:, 1].copy()
        self.joint_range = m.jnt_range.copy()
        n_arm = len(self.arm_geom_ids)
        #: (obstacle slot, arm geom) signed surface distances: a view into MuJoCo's sensordata.
        self.distances = self.data.sensordata[: MAX_OBSTACLES * n_arm].reshape(MAX_OBSTACLES, n_arm)
        if not self.gravity_compensation:
            m.body_gravcomp[:] = 0.0
        self._inv_limit = 1.0 / self.torque_limit
        # Obstacle state. Positions are a view into MuJoCo's mocap array: one source of truth.
        self.obstacle_pos = self.data.mocap_pos[mocap[0] : mocap[0] + MAX_OBSTACLES]
        self.obstacle_vel = np.zeros((MAX_OBSTACLES, 3))
        #: Obstacle accelerations: zero, the scenarios move obstacles at constant velocity (the
        #: C3BF theorem's assumption); filters read it rather than assume it.
        self.obstacle_acc = np.zeros((MAX_OBSTACLES, 3))
        self.obstacle_radius = np.zeros(MAX_OBSTACLES)
        self.obstacle_active = np.zeros(MAX_OBSTACLES, dtype=bool)
        self._obstacle_specs: list = [None] * MAX_OBSTACLES
        self._step_displacement = np.zeros((MAX_OBSTACLES, 3))
        if m.nv != self.task_robot.n_joints:
            raise RuntimeError(f"{self.task_robot.scene} has {m.nv} dofs, robot {self.task_robot.name!r} {self.task_robot.n_joints}")
        parts = self.observation_slices
        self._obs = np.zeros(max(part.stop for part in parts.values()))
        self._tool_vel = np.zeros(6)
        #: the compiled physics steps' views of the model, data and obstacles (_simulate)
        self._physics = Physics.of(m, self.data, self.obstacle_pos, self._step_displacement, self.distances,
                                   DISTANCE_CUTOFF)
        self._seen = Observed(self.data.qpos, self.data.qvel, self.data.site_xpos[self.ee_site_id], self._tool_vel,
                              self.data.mocap_pos[self._goal_mocap], self.obstacle_pos, self.obstacle_vel,
                              self.obstacle_radius, self.obstacle_active, self.distances)
        self._observe = entry(observe, self._seen, 1.0, self._obs)
        # the MjData arrays the hooks' loop reads and writes, as views made once
        self._gravcomp, self._ctrl = self.data.qfrc_gravcomp, self.data.ctrl
        #: The obstacles as the safety filter reads them: views of the arrays above and of the
        #: distance sensors, so they are current at every physics step.
        self.obstacles = Obstacles(
            MAX_OBSTACLES, position=self.obstacle_pos, velocity=self.obstacle_vel, acceleration=self.obstacle_acc,
            radius=self.obstacle_radius, active=self.obstacle_active, distances=self.distances,
        )  # fmt: skip
        #: The arm as the safety filter sees it: its protected capsules, torque and joint limits.
        #: Link 1 lies on the base's pan axis, which no joint can move it away from: it is left
        #: out (the from_model warning says so), like the base, and the scenarios' keep-out zone
        #: keeps spheres off both.
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UnprotectedGeometryWarning)
            self.robot = RobotDescription.from_model(self.model, site="ee_site",
                                                     joint_speed_limit=self.task_robot.joint_speed_limit)  # fmt: skip
        self._setup_reach_bounds()

    def _initialize_simulation(self) -> tuple[mujoco.MjModel, mujoco.MjData]:
        """Compile scene.xml plus one distance sensor per (obstacle, arm geom) pair."""
        spec = mujoco.MjSpec.from_file(self.fullpath)
        arm = [g.name for g in spec.geoms if g.contype == _ARM_CONTYPE]
        for i in range(MAX_OBSTACLES):
            for name in arm:
                spec.add_sensor(
                    name=f"distance_obstacle_{i}_{name}",
                    type=mujoco.mjtSensor.mjSENS_GEOMDIST,
                    objtype=mujoco.mjtObj.mjOBJ_GEOM,
                    objname=f"obstacle_{i}",
                    reftype=mujoco.mjtObj.mjOBJ_GEOM,
                    refname=name,
                    cutoff=DISTANCE_CUTOFF,
                )
        model = spec.compile()
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, self.width)
        model.vis.global_.offheight = max(model.vis.global_.offheight, self.height)
        return model, mujoco.MjData(model)

    def _set_action_space(self) -> spaces.Box:
        self.action_space = spaces.Box(-1.0, 1.0, shape=(self.model.nu,), dtype=np.float32)
        return self.action_space

    def _check_scenario(self, scenario: Scenario) -> None:
        """Refuse a scenario the scene cannot hold or the envelope can never place (``ValueError``)."""
        if len(scenario.obstacles) > MAX_OBSTACLES:
            raise ValueError(
                f"scenario {scenario.name!r} has {len(scenario.obstacles)} obstacles; "
                f"the scene and the observation hold at most {MAX_OBSTACLES}"
            )
        for component in [get_scenario(name) for name in scenario.mixture] or [scenario]:
            for index, spec in enumerate(component.obstacles):
                reason = self._unplaceable(spec, self._longest_path)
                if reason is not None:
                    raise ValueError(f"scenario {component.name!r}, obstacle {index} ({spec!r}) can never be placed: {reason}")

    def _setup_reach_bounds(self) -> None:
        """What ``_unplaceable`` needs: how deep ``ee_site`` lies in the arm geoms of its own body
        (signed, m), and the longest start-to-goal path any reset can draw (m).

        The start is the tool at the home keyframe moved by the reset noise: turning each joint by
        at most ``theta`` moves the tool by at most ``theta (R + n delta)`` for lever arms ``R``
        summed over the ``n`` joints (anchor to tool, at home), so ``delta <= theta R / (1 - n theta)``.
        """
        m = self.model
        home = mujoco.MjData(m)
        mujoco.mj_resetDataKeyframe(m, home, 0)
        mujoco.mj_forward(m, home)
        tool = home.site_xpos[self.ee_site_id].copy()
        rigid = self.arm_geom_ids[m.geom_bodyid[self.arm_geom_ids] == m.site_bodyid[self.ee_site_id]]
        self._tool_depth = -self._arm_capsules(home, rigid).clearance(tool, 0.0)
        levers = np.linalg.norm(home.xanchor[: m.njnt] - tool, axis=1).sum()
        home_noise = self.task_robot.home_noise
        noise = home_noise * levers / (1.0 - m.njnt * home_noise)
        self._longest_path = float(np.linalg.norm(self.task_robot.goal_corners() - tool, axis=1).max()) + noise

    def _unplaceable(self, spec: ObstacleSpec, path_length: float) -> str | None:
        """Why no obstacle of ``spec`` fits for paths up to ``path_length`` m, or None if one may.

        ``ee_site`` (the path's start) lies ``_tool_depth`` deep in the arm, so a centre closer
        than ``spawn_clearance + radius + _tool_depth`` to it is too close to the arm; the sampler
        never spawns farther than :func:`~c3bf_gym.scenarios.max_spawn_distance`.
        """
        envelope = self.envelope
        needed = envelope.spawn_clearance + envelope.radius_range[0] + self._tool_depth
        reach = max_spawn_distance(spec, envelope, path_length)
        if reach >= needed:
            return None
        fraction = spec.path_fraction[1] + (needed - reach) / path_length
        return (
            f"it spawns at most {reach:.3g} m from the tool's start (paths up to {path_length:.3g} m), but every "
            f"obstacle spawns at least spawn_clearance {envelope.spawn_clearance:g} m + its radius "
            f"(>= {envelope.radius_range[0]:g} m) from the arm, and the start lies {self._tool_depth:.3g} m inside "
            f"the tool: {needed:.3g} m from the start; path_fraction's high end must be >= {fraction:.3g}"
            + (" (or meet_time's, or the speed range's, larger)" if spec.kind != "static" else "")
        )

    @property
    def goal(self) -> np.ndarray:
        """The goal position (3,) [m] (a view into MuJoCo's mocap array)."""
        return self.data.mocap_pos[self._goal_mocap]

    @property
    def arm(self) -> ArmModel:
        """The arm's :class:`~c3bf_gym.safety.dynamics.ArmModel`, shared by every hook on this env."""
        if self._arm is None:
            self._arm = ArmModel(self.model, self.robot.geom_ids, self.ee_site_id)
        return self._arm

    # ------------------------------------------------------------------ hooks
    def add_torque_hook(self, hook: TorqueHook, stage: Literal["nominal", "filter"]) -> None:
        """Install ``hook`` to run at every physics step at ``stage`` (one hook per stage).

        The built-in hooks run inside the compiled policy step
        (:func:`~c3bf_gym.envs._kernels.policy_steps`): a ``nominal``
        :class:`~c3bf_gym.controllers.ImpedanceHook` and a ``filter``
        :class:`~c3bf_gym.safety.SafetyController` (``SafetyFilter``'s
        :class:`~c3bf_gym.filter.SafetyHook`), alone or together, whenever they offer a compiled
        call (:meth:`~c3bf_gym.controllers.ImpedanceHook.compiled_call`,
        :meth:`~c3bf_gym.safety.SafetyController.compiled_call`), with the same torques as through
        ``__call__`` (to rounding, with the impedance controller). Any other hook, a Python
        function, runs in Python at every physics step, and so do the hooks beside it: it is the
        extension point for a controller of one's own."""
        if stage not in HOOK_STAGES:
            raise ValueError(f"unknown hook stage {stage!r}; valid choices: {', '.join(map(repr, HOOK_STAGES))}")
        if not callable(hook):
            raise TypeError(f"hook must be callable, got {type(hook).__name__}")
        if stage in self._hooks:
            raise ValueError(f"a {stage!r} torque hook is already installed on this environment")
        self._hooks[stage] = hook
        self._chain_changed()

    def remove_torque_hook(self, stage: Literal["nominal", "filter"]) -> None:
        self._hooks.pop(stage, None)
        self._chain_changed()

    def _chain_changed(self) -> None:
        self._hook_chain = tuple(self._hooks[s] for s in HOOK_STAGES if s in self._hooks)
        # the built-in hooks, alone or together, can run inside the compiled policy step (_compiled_calls)
        nominal, behind = self._hooks.get("nominal"), self._hooks.get("filter")
        compiled = ((nominal is None or isinstance(nominal, ImpedanceHook))
                    and (behind is None or isinstance(behind, SafetyController)))  # fmt: skip
        self._compiled_nominal = nominal if compiled else None
        self._compiled_filter = behind if compiled else None

    def has_torque_hook(self, stage: str) -> bool:
        return stage in self._hooks

    def torque_hook(self, stage: Literal["nominal", "filter"]) -> TorqueHook | None:
        """The hook installed at ``stage`` (:data:`HOOK_STAGES`), or None."""
        if stage not in HOOK_STAGES:
            raise ValueError(f"unknown hook stage {stage!r}; valid choices: {', '.join(map(repr, HOOK_STAGES))}")
        return self._hooks.get(stage)

    # ------------------------------------------------------------------ gym API
    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Apply ``action`` (6,) for ``frame_skip`` physics steps; Gymnasium's 5-tuple.

        Raises ``gymnasium.error.ResetNeeded`` before the first ``reset`` and ``ValueError`` for
        an invalid action (both before anything changes). Whatever raises during the step (a
        torque hook, a respawn, rendering) leaves the environment as it was before the call,
        except for a fresh ``state_version``, and propagates unchanged (the class docstring's
        "Errors during a step" lists what is restored).
        """
        if self._needs_reset:
            raise error.ResetNeeded(
                "C3BFReachEnv.step() was called before reset(): call reset() first (after a reset that "
                "raised, too)"
            )
        torque = self._validate_action(action) * self.torque_limit
        mujoco.mj_getState(self.model, self.data, self._saved_state, _STEP_STATE)
        self._obstacles_saved = False
        goal_distance, episode_cost = self._goal_distance, self._episode_cost
        try:
            min_distance, effort = self._simulate(torque)
            return self._outcome(min_distance, effort)
        except BaseException:
            self._goal_distance, self._episode_cost = goal_distance, episode_cost
            self._restore()
            raise

    def _outcome(self, min_distance: float, effort: float) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """The step's 5-tuple after its physics steps: obstacles that left the workspace respawn,
        then the reward, its terms and the measurements (``min_distance`` [m] and ``effort``, from
        :meth:`_simulate`) into ``info``."""
        self._respawn_departed()

        to_goal = self._seen.goal - self._seen.tool  # the goal's mocap and the tool site, views made once
        distance = math.sqrt(to_goal.dot(to_goal))  # ndarray.dot: numpy's dot, as @, with less dispatch
        w_progress, w_success, w_effort, w_distance = self._weights
        progress = w_progress * (self._goal_distance - distance)
        self._goal_distance = distance
        success = distance < self.success_tolerance
        info = {  # the reward's terms first, then the step's measurements
            "reward_progress": progress,
            "reward_success": w_success if success else 0.0,
            "reward_distance": -w_distance * distance,
            "reward_effort": -w_effort * effort,
        }
        reward = sum(info.values())
        cost = 1.0 if min_distance <= 0.0 else 0.0
        self._episode_cost += cost
        info.update(distance=distance, is_success=success, cost=cost, episode_cost=self._episode_cost,
                    min_distance=min_distance)
        if self.render_mode == "human":
            self.render()
        terminated = self.terminate_on_collision and cost > 0.0
        return self._get_obs(), reward, terminated, False, info

    def _save_obstacles(self) -> None:
        """Save what a respawn changes besides MuJoCo's state (once per step, before the first)."""
        if self._obstacles_saved:
            return
        vel, acc, radius, active, size, rbound = self._saved_obstacles
        geoms = self.obstacle_geom_ids
        np.copyto(vel, self.obstacle_vel)
        np.copyto(acc, self.obstacle_acc)
        np.copyto(radius, self.obstacle_radius)
        np.copyto(active, self.obstacle_active)
        size[:] = self.model.geom_size[geoms]
        rbound[:] = self.model.geom_rbound[geoms]
        self._saved_specs = list(self._obstacle_specs)
        self._saved_rng = self.np_random.bit_generator.state
        self._obstacles_saved = True

    def _restore(self) -> None:
        """Undo the current step: the state saved at its start, and the obstacles' bookkeeping if
        a respawn saved it; then recompute what ``_simulate``'s invariant promises
        (``mj_step1``: kinematics, dynamics, sensors) and move ``state_version`` past every
        number used so far."""
        m, d = self.model, self.data
        if self._obstacles_saved:
            vel, acc, radius, active, size, rbound = self._saved_obstacles
            geoms = self.obstacle_geom_ids
            np.copyto(self.obstacle_vel, vel)
            np.copyto(self.obstacle_acc, acc)
            np.copyto(self.obstacle_radius, radius)
            np.copyto(self.obstacle_active, active)
            m.geom_size[geoms] = size
            m.geom_rbound[geoms] = rbound
            self._obstacle_specs = list(self._saved_specs)
            self.np_random.bit_generator.state = self._saved_rng
            self._obstacles_saved = False
        mujoco.mj_setState(m, d, self._saved_state, _STEP_STATE)
        mujoco.mj_step1(m, d)
        self.state_version += 1

    def _validate_action(self, action: Any) -> np.ndarray:
        a = np.asarray(action)
        if a.shape != self.action_space.shape:
            raise ValueError(f"action must have shape {self.action_space.shape}, got {a.shape}")
        if a.dtype.kind not in "fiu":
            raise ValueError(f"action must be a real (float) array, got dtype {a.dtype}")
        # on the entries as Python numbers: for six of them, cheaper than numpy's abs and all
        if not all(-_ACTION_BOUND <= v <= _ACTION_BOUND for v in a.tolist()):  # also False for NaN
            if not np.isfinite(a).all():
                raise ValueError(f"action contains NaN or inf: {a}; it must be finite and lie in [-1, 1]")
            raise ValueError(f"action must lie in [-1, 1] (fraction of each joint's torque limit), got {a}")
        return a.astype(np.float64)

    def _simulate(self, torque: np.ndarray) -> tuple[float, float]:
        """Advance ``frame_skip`` physics steps; return (min signed distance, mean effort).

        Invariant: between calls ``data`` holds ``mj_step1`` results for the current state, so a
        hook reads current kinematics, mass matrix and bias forces. The steps run in one compiled
        call (:func:`~c3bf_gym.envs._kernels.policy_steps`) under ``torque``, or under the
        built-in hooks when they offer compiled calls (:meth:`_compiled_calls`): the impedance
        controller, the safety filter, or both. Any other hook runs in Python between compiled
        single steps (:meth:`_simulate_hooks`). Both loops call the same kernels and give the same
        steps: bit for bit without the impedance controller; with it the tests hold them to
        rounding. A filter call that stops the step raises the filter's exception
        (:meth:`~c3bf_gym.safety.SafetyController.failure`).
        """
        np.multiply(self.obstacle_vel, self.model.opt.timestep, out=self._step_displacement)
        nominal, call = self._compiled_calls()
        if self._hook_chain and nominal is None and call is None:
            return self._simulate_hooks(torque)
        steps = self._steps_entry(nominal, call)
        done, min_distance, status = steps(self._physics, self.frame_skip, torque, self._drive, nominal, call)
        self.state_version += done
        if status:
            error = self._compiled_filter.failure(status)
            if error is not None:
                raise error
        if not self._hook_chain:
            u = torque * self._inv_limit
            return float(min_distance), float(u.dot(u)) / len(u)  # ndarray.dot: numpy's dot, as @
        return float(min_distance), self._effort()

    def _compiled_calls(self) -> tuple[BoundImpedance | None, FilterCall | None]:
        """What :func:`~c3bf_gym.envs._kernels.policy_steps` runs this step: the impedance
        controller's and the filter's compiled calls, each None where that hook is absent;
        (None, None) too when a hook must run in Python (a Python function; a trajectory target;
        a filter on its per-class path or timing its calls)."""
        nominal_hook, filter_hook = self._compiled_nominal, self._compiled_filter
        nominal = call = None
        if nominal_hook is not None:
            nominal = nominal_hook.compiled_call()
            if nominal is None:
                return None, None
        if filter_hook is not None:  # (after the nominal's check: it claims the arm for the loop)
            call = filter_hook.compiled_call(self.state_version)
            if call is None:
                return None, None
        elif nominal is not None:
            self.arm.forget()  # the controller overwrites the arm's dynamics arrays
        return nominal, call

    def _steps_entry(self, nominal: BoundImpedance | None, call: FilterCall | None) -> Callable:
        """:func:`~c3bf_gym.envs._kernels.policy_steps`' entry point for this stack (``nominal``,
        ``call``), its torque a float64 (n,) array: compiled once per stack, kept while the
        controller's and the filter's buffers stay the same objects."""
        buffers = None if call is None else call.buffers
        cached = self._entry_cache
        if cached is None or cached[0] is not nominal or cached[1] is not buffers:
            types = (self._physics, self.frame_skip, self._drive.tau, self._drive, nominal, call)
            cached = self._entry_cache = (nominal, buffers, entry(policy_steps, *types))
        return cached[2]

    def _simulate_hooks(self, torque: np.ndarray) -> tuple[float, float]:
        """:meth:`_simulate` with the hooks called from Python at every physics step, in stage
        order, on the nominal total torque ``torque + data.qfrc_gravcomp``."""
        gravity, inv_limit = self._gravcomp, self._inv_limit
        physics, drive = self._physics, self._drive
        steps = self._steps_entry(None, None)
        min_distance = DISTANCE_CUTOFF
        effort = 0.0
        for _ in range(self.frame_skip):
            tau = torque + gravity
            for hook in self._hook_chain:
                tau = hook(tau)
            ctrl = tau - gravity
            u = ctrl * inv_limit
            effort += float(u @ u) / (len(u) * self.frame_skip)
            _, distance, _ = steps(physics, 1, ctrl, drive, None, None)  # data.ctrl = ctrl, one physics step
            self.state_version += 1
            if distance < min_distance:
                min_distance = distance
        return float(min_distance), effort

    def _effort(self) -> float:
        """The mean effort over the last policy step's physics steps, from the compiled steps' rows."""
        rows = self._filter_scratch[2]
        effort, count = 0.0, rows.shape[1] * self.frame_skip
        # np.vecdot takes each row's u @ u with numpy's own dot (the same bits), without a view per row
        for square in np.vecdot(rows, rows).tolist():
            effort += square / count
        return effort

    def obstacle_distances(self) -> np.ndarray:
        """Per obstacle slot, the smallest signed surface distance (m) to any arm geom, now
        (``DISTANCE_CUTOFF`` when farther, and for unused slots)."""
        return self.distances.min(axis=1)

    def _get_obs(self) -> np.ndarray:
        mujoco.mj_objectVelocity(self.model, self.data, mujoco.mjtObj.mjOBJ_SITE, self.ee_site_id, self._tool_vel, 0)
        return self._observe(self._seen, self.sensing_radius, self._obs)

    def sensed_mask(self) -> np.ndarray:
        """Which obstacle slots are active and within ``sensing_radius`` of the arm, now."""
        return self.obstacle_active & (self.obstacle_distances() <= self.sensing_radius)

    # ------------------------------------------------------------------ reset and scenarios
    def reset_model(self) -> np.ndarray:
        self._needs_reset = True  # until this reset has placed everything
        m, d, rng = self.model, self.data, self.np_random
        mujoco.mj_resetDataKeyframe(m, d, 0)
        noise = self.task_robot.home_noise
        d.qpos[:] += rng.uniform(-noise, noise, size=m.nq)
        self._park_all()
        mujoco.mj_forward(m, d)
        start = d.site_xpos[self.ee_site_id].copy()
        scenario = self.episode_scenario = self.scenario.resolve(rng)
        longest = float(np.linalg.norm(self.task_robot.goal_corners() - start, axis=1).max())
        for index, spec in enumerate(scenario.obstacles):  # draws nothing: a placeable scenario is unaffected
            reason = self._unplaceable(spec, longest)
            if reason is not None:
                raise RuntimeError(
                    f"could not place scenario {scenario.name!r} from this start: obstacle {index} ({spec!r}) does not "
                    f"fit: {reason}"
                )
        failures = np.zeros(len(scenario.obstacles), dtype=int)
        arm = self._arm_capsules(d, self.arm_geom_ids)
        for _ in range(100):
            goal = self._sample_goal(start, rng)
            samples = [self._sampler.sample(spec, start, goal, rng, arm) for spec in scenario.obstacles]
            if all(s is not None for s in samples):
                break
            failures += [s is None for s in samples]
        else:
            worst = int(failures.argmax())
            raise RuntimeError(
                f"could not place scenario {scenario.name!r} inside the envelope in 100 attempts (goal draws); "
                f"obstacle {worst} ({scenario.obstacles[worst]!r}) did not fit in {failures[worst]} of them"
            )
        d.mocap_pos[self._goal_mocap] = goal
        for slot, (spec, sample) in enumerate(zip(scenario.obstacles, samples)):
            self._place(slot, sample)
            self._obstacle_specs[slot] = spec
        mujoco.mj_forward(m, d)
        self._goal_distance = float(np.linalg.norm(goal - start))
        self._episode_cost = 0.0
        self.state_version += 1
        self._needs_reset = False
        return self._get_obs()

    def _sample_goal(self, start: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        for _ in range(1000):
            goal = rng.uniform(np.array(self.task_robot.goal_low), np.array(self.task_robot.goal_high))
            if np.linalg.norm(goal - start) >= _GOAL_MIN_TRAVEL:
                return goal
        raise RuntimeError("could not draw a goal far enough from the tool")

    def _park_all(self) -> None:
        self.obstacle_active[:] = False
        self.obstacle_vel[:] = 0.0
        self.obstacle_radius[:] = 0.0
        self._obstacle_specs = [None] * MAX_OBSTACLES
        self.obstacle_pos[:] = 0.0
        self.obstacle_pos[:, 0] = np.arange(MAX_OBSTACLES) * 2.0 * DISTANCE_CUTOFF
        self.obstacle_pos[:, 2] = _PARK_DEPTH

    def place_obstacle(self, slot: int, position: np.ndarray, velocity: np.ndarray = (0.0, 0.0, 0.0),
                       radius: float = 0.05, respawn: ObstacleSpec | None = None) -> None:
        """Put obstacle ``slot`` (``0 <= slot < MAX_OBSTACLES``, active or not) at ``position`` (3,)
        [m], moving at the constant ``velocity`` (3,) [m/s], with ``radius`` [m]: for hand-made
        scenes in tests, demos and benchmarks, after :meth:`reset` and between steps. The
        kinematics and distance sensors are recomputed (``mj_forward``) and ``state_version``
        moves on, so the next observation, step and safety filter call see it. When it leaves the
        workspace it respawns as ``respawn`` draws it (default ``ObstacleSpec("static")``: at rest
        on the tool's path). Nothing checks that it is clear of the arm or outside the keep-out
        cylinder: a hand-made obstacle may start in contact.

        Raises:
            ValueError: an unknown slot, a position or velocity that is not three finite numbers,
                a radius that is not a finite number > 0, or a ``respawn`` that is not an
                ``ObstacleSpec`` (nothing changes).
        """
        slot = integer("slot", slot, low=0)
        if slot >= MAX_OBSTACLES:
            raise ValueError(f"slot must be an integer in [0, {MAX_OBSTACLES - 1}], got {slot}")
        position, velocity = (np.array(v, dtype=np.float64) for v in (position, velocity))
        for name, v in (("position", position), ("velocity", velocity)):
            if v.shape != (3,) or not np.isfinite(v).all():
                raise ValueError(f"{name} must be three finite numbers [m, m/s], got {v!r}")
        radius = number("radius", radius, low=0.0, low_open=True, unit="m")
        if respawn is not None and not isinstance(respawn, ObstacleSpec):
            raise ValueError(f"respawn must be an ObstacleSpec or None, got {respawn!r}")
        self._place(slot, ObstacleSample(position, velocity, radius))
        self._obstacle_specs[slot] = ObstacleSpec("static") if respawn is None else respawn
        mujoco.mj_forward(self.model, self.data)
        self.state_version += 1

    def _place(self, slot: int, sample) -> None:
        geom = self.obstacle_geom_ids[slot]
        self.model.geom_size[geom, 0] = sample.radius
        self.model.geom_rbound[geom] = sample.radius
        self.obstacle_pos[slot] = sample.position
        self.obstacle_vel[slot] = sample.velocity
        self.obstacle_radius[slot] = sample.radius
        self.obstacle_active[slot] = True

    def _respawn_departed(self) -> None:
        low, high = self._workspace
        if not self._departed(self.obstacle_pos, self.obstacle_active, low, high):
            return
        outside = ((self.obstacle_pos < low) | (self.obstacle_pos > high)).any(axis=1) & self.obstacle_active
        if not outside.any():
            return
        self._save_obstacles()
        for slot in np.flatnonzero(outside):
            tool = self.data.site_xpos[self.ee_site_id].copy()
            goal = self.data.mocap_pos[self._goal_mocap].copy()
            sample = self._sampler.sample(self._obstacle_specs[slot], tool, goal, self.np_random,
                                          self._arm_capsules(self.data, self.arm_geom_ids))
            if sample is None:  # nothing fits right now: retire the obstacle for this episode
                self.obstacle_active[slot] = False
                self.obstacle_vel[slot] = 0.0
                self.obstacle_pos[slot] = (slot * 2.0 * DISTANCE_CUTOFF, 0.0, _PARK_DEPTH)
            else:
                self._place(slot, sample)
            mujoco.mj_forward(self.model, self.data)  # sensors and contacts see the new position
        self.state_version += 1

    def arm_capsules(self) -> ArmCapsules:
        """The arm geoms (:attr:`arm_geom_ids`, in that order) as capsules in the present state,
        each about its axis (exact for capsules and spheres) [m]."""
        return self._arm_capsules(self.data, self.arm_geom_ids)

    def _arm_capsules(self, d: mujoco.MjData, ids: np.ndarray) -> ArmCapsules:
        """Geoms ``ids`` in state ``d``, each taken as a capsule about its axis (exact for
        capsules and spheres): what obstacles spawn clear of."""
        m = self.model
        axis = d.geom_xmat[ids][:, 2::3] * m.geom_size[ids, 1][:, None]  # z column, half length
        return ArmCapsules(d.geom_xpos[ids] - axis, d.geom_xpos[ids] + axis, m.geom_size[ids, 0].copy())
