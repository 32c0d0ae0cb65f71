"""The envelope the filter states (c3bf_gym.safety.envelope): the obstacle speed and sensing range
within which a safe escape exists, the warnings that name obstacles outside it, and the filter
holding at the envelope's own worst case."""

from __future__ import annotations

import warnings

import gymnasium as gym
import mujoco
import numpy as np
import pytest

import c3bf_gym
from c3bf_gym.filter import scenario_envelope
from c3bf_gym.safety import (
    EnvelopeWarning,
    FilterConfig,
    MocapSpheres,
    RobotDescription,
    SafetyController,
    filter_envelope,
)

from test_safety_api import ARM

pytestmark = pytest.mark.filterwarnings("ignore::c3bf_gym.safety.UnprotectedGeometryWarning")

CONFIG = FilterConfig(sensing_radius=1.0)


def _arm(timestep: float = 0.002):
    model = mujoco.MjModel.from_xml_string(ARM)
    model.opt.timestep = timestep
    return model, RobotDescription.from_model(model, site="tool", joint_speed_limit=2.0)


@pytest.fixture(scope="module", params=["C3BFReach-v0", "C3BFReachPanda-v0"])
def reach(request):
    env = gym.make(request.param).unwrapped
    yield env, scenario_envelope(env, FilterConfig())
    env.close()


def _env_id(env) -> str:
    return "C3BFReachPanda-v0" if env.task_robot.name == "panda" else "C3BFReach-v0"


def test_the_envelope_covers_the_projects_own_scenarios(reach):
    """Both arms' scenarios' speeds and sizes (spheres up to 0.4 m/s and 8 cm, sensed at 1 m, out
    of the keep-out cylinder) lie inside the envelope the default filter states, and a filter on
    them says nothing. (Where the scenarios spawn their obstacles is not checked here: they may
    appear inside the sensing range a speed needs, which the envelope does not cover.)"""
    env, envelope = reach
    assert envelope.obstacle_radius == env.envelope.radius_range[1] == 0.08
    assert envelope.max_speed >= 0.4
    assert envelope.problems(0.4, 0.08) == []
    with warnings.catch_warnings():
        warnings.simplefilter("error", EnvelopeWarning)
        c3bf_gym.SafetyFilter(gym.make(_env_id(env))).close()


def test_max_speed_and_min_sensing_range_are_inverse(reach):
    _, envelope = reach
    v = envelope.max_speed
    assert envelope.min_sensing_range(v) <= envelope.sensing_radius * (1 + 1e-6)
    assert envelope.min_sensing_range(1.01 * v) > envelope.sensing_radius
    ranges = [envelope.min_sensing_range(s) for s in (0.0, 0.1, 0.2, 0.4, 0.8)]
    assert ranges[0] == 0.0 and np.all(np.diff(ranges) > 0.0)


def test_what_the_arm_cannot_do_shrinks_the_envelope(reach):
    """Slower joints, a larger margin, larger obstacles and no keep-out region each lower the speed
    the filter can promise; the base axis' links limit it without a keep-out."""
    env, envelope = reach
    kwargs = dict(obstacle_radius=0.08, keep_out_radius=env.envelope.keep_out_radius,
                  keep_out_height=env.envelope.keep_out_height, configurations=32)  # fmt: skip
    base = filter_envelope(env.model, env.robot, CONFIG, **kwargs)
    for config, change in ((CONFIG.replace(joint_speed_fraction=0.25), {}), (CONFIG.replace(margin=0.06), {}),
                           (CONFIG, {"obstacle_radius": 0.2}), (CONFIG, {"keep_out_height": 0.0})):  # fmt: skip
        assert filter_envelope(env.model, env.robot, config, **{**kwargs, **change}).max_speed < base.max_speed
    bare = filter_envelope(env.model, env.robot, CONFIG, **{**kwargs, "keep_out_height": 0.0})
    assert np.hypot(*bare.limiting_point[:2]) < 0.1  # a point on the base's axis, which only the pan turns


def test_the_filter_holds_at_the_envelopes_worst_case(reach):
    """An obstacle at the envelope's top speed, sensed at the sensing radius, coming along the
    limiting direction at the limiting point of the limiting configuration: the filter (gravity
    compensation as the nominal torque) keeps it off, by MuJoCo's distances, with every QP feasible."""
    env, envelope = reach
    model, robot = env.model, env.robot
    data = mujoco.MjData(model)
    data.qpos[model.jnt_qposadr[model.dof_jntid[robot.dof_ids]]] = envelope.limiting_configuration
    balls = [model.body(b).name for b in range(model.nbody) if model.body_mocapid[b] >= 0]
    for k, name in enumerate(balls):
        data.mocap_pos[model.body(name).mocapid[0]] = (5.0 + k, 5.0, 1.0)
    spheres = MocapSpheres(model, balls[:1])
    ball, mocap = int(spheres.geom_ids[0]), model.body(balls[0]).mocapid[0]
    size = model.geom_size[ball, 0]
    model.geom_size[ball, 0] = envelope.obstacle_radius
    try:
        velocity = envelope.max_speed * envelope.limiting_approach
        back = 1.0 + 0.08 + 0.1  # along the approach, until the sphere's surface is 1 m from the whole arm
        while True:
            data.mocap_pos[mocap] = envelope.limiting_point - envelope.limiting_approach * back
            mujoco.mj_forward(model, data)
            if min(mujoco.mj_geomDistance(model, data, ball, int(g), 2.0, None) for g in robot.geom_ids) >= 1.0:
                break
            back += 0.05
        controller = SafetyController(model, data, robot, spheres, FilterConfig(), sensing_radius=1.0,
                                      envelope=envelope)  # fmt: skip
        lowest, infeasible = np.inf, 0
        for _ in range(1500):
            mujoco.mj_step1(model, data)
            lowest = min(lowest, *(mujoco.mj_geomDistance(model, data, ball, int(g), 1.0, None) for g in robot.geom_ids))
            spheres.velocity[0] = velocity
            tau, report = controller.filter(np.clip(data.qfrc_bias[robot.dof_ids], -robot.torque_limit,
                                                    robot.torque_limit))  # fmt: skip
            infeasible += report.infeasible_steps
            robot.write_ctrl(model, data, tau)
            mujoco.mj_step2(model, data)
            data.mocap_pos[mocap] += velocity * model.opt.timestep
    finally:
        model.geom_size[ball, 0] = size
    assert lowest > 0.0 and infeasible == 0


def test_an_environment_with_faster_obstacles_warns_with_the_numbers():
    env = gym.make("C3BFReach-v0", obstacle_speed_range=(0.1, 0.9))
    with pytest.warns(EnvelopeWarning, match=r"up to 0\.9 m/s.*guarantees up to 0\.\d+ m/s \(link"):
        c3bf_gym.SafetyFilter(env)
    env.close()


def test_the_standalone_controller_warns_once_about_fast_obstacles():
    model, robot = _arm()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    spheres = MocapSpheres(model, ["ball"])
    controller = SafetyController(model, data, robot, spheres, CONFIG)
    assert controller.envelope is None
    tau = np.zeros(3)
    with warnings.catch_warnings():
        warnings.simplefilter("error", EnvelopeWarning)
        controller.filter(tau)  # at rest: inside any envelope, computed now
    assert controller.envelope is not None and controller.envelope.obstacle_radius == pytest.approx(0.06)
    spheres.velocity[0] = (0.0, 0.0, -5.0 * controller.envelope.max_speed - 0.5)
    with pytest.warns(EnvelopeWarning, match="outside the filter's envelope"):
        controller.filter(tau)
    with warnings.catch_warnings():
        warnings.simplefilter("error", EnvelopeWarning)
        controller.filter(tau)  # once per controller


@pytest.mark.parametrize("start, velocity, warns", [
    ((0.6, 0.0, 0.62), (0.0, 0.0, -1.0), True),  # 0.1 m above the arm, coming down at the envelope's speed
    ((0.6, 0.0, 0.62), (0.0, 0.0, 0.0), False),  # at rest there: nothing to escape from
    ((0.6, 0.0, 1.62), (0.0, 0.0, -1.0), False),  # beyond the sensing radius: sensed as the envelope assumes
])
def test_an_obstacle_appearing_inside_the_sensing_range_its_speed_needs_is_named(start, velocity, warns):
    """The envelope's escape argument assumes an obstacle is first sensed ``min_sensing_range(V)``
    out; one that becomes active closer (placed there, not come from afar) is outside it."""
    model, robot = _arm()
    data = mujoco.MjData(model)
    data.mocap_pos[0] = start
    mujoco.mj_forward(model, data)
    spheres = MocapSpheres(model, ["ball"])
    spheres.clear()
    controller = SafetyController(model, data, robot, spheres, CONFIG)
    controller.filter(np.zeros(3))  # no obstacle yet
    controller.compute_envelope(0.06, keep_out_radius=0.15, keep_out_height=0.5, configurations=0)  # at rest here
    assert controller.envelope.max_speed > 0.0
    spheres.active[0] = True
    spheres.velocity[0] = 0.9 * controller.envelope.max_speed * np.array(velocity)
    gap = mujoco.mj_geomDistance(model, data, int(spheres.geom_ids[0]), model.geom("upper").id, 2.0, None)
    if warns:
        assert gap < controller.envelope.min_sensing_range(0.9 * controller.envelope.max_speed)
        with pytest.warns(EnvelopeWarning, match=r"obstacle 0 appeared 0\.\d+ m from the arm, moving at .* needs it "
                                                 r"sensed 0\.\d+ m out or farther"):  # fmt: skip
            controller.filter(np.zeros(3))
    else:
        with warnings.catch_warnings():
            warnings.simplefilter("error", EnvelopeWarning)
            controller.filter(np.zeros(3))


def test_a_coarse_timestep_is_named():
    model, robot = _arm(timestep=0.01)
    data = mujoco.MjData(model)
    with pytest.warns(EnvelopeWarning, match=r"timestep 0\.01 s is too coarse.*gamma_v = 20"):
        SafetyController(model, data, robot, MocapSpheres(model, ["ball"]), CONFIG)
    with warnings.catch_warnings():
        warnings.simplefilter("error", EnvelopeWarning)
        model.opt.timestep = 0.002
        SafetyController(model, data, robot, MocapSpheres(model, ["ball"]), CONFIG)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"obstacle_radius": -0.1}, "obstacle_radius must be a finite number >= 0"),
        ({"obstacle_radius": 0.1, "keep_out_height": np.nan}, "keep_out_height must be"),
        ({"obstacle_radius": 0.1, "configurations": -1}, "configurations must be an integer >= 0"),
        ({"obstacle_radius": 0.1, "qpos": np.zeros(2)}, "qpos must be 3 finite joint positions"),
        ({"obstacle_radius": 0.1, "sensing_radius": 0.0}, "sensing_radius must be a finite number > 0"),
    ],
)
def test_envelope_input_errors(kwargs, message):
    model, robot = _arm()
    with pytest.raises(ValueError, match=message):
        filter_envelope(model, robot, CONFIG, **kwargs)


def test_an_envelope_needs_a_sensing_radius():
    model, robot = _arm()
    with pytest.raises(ValueError, match="sensing_radius must be"):
        filter_envelope(model, robot, FilterConfig(), obstacle_radius=0.1)
    with pytest.raises(ValueError, match="speed must be a finite number >= 0"):
        filter_envelope(model, robot, CONFIG, obstacle_radius=0.1, configurations=2).min_sensing_range(-1.0)


def test_the_envelope_benchmark_counts_obstacles_spawned_inside_the_range_their_speed_needs():
    """``benchmarks/envelope.py --spawns``: the Panda's scenarios place some moving obstacles closer
    than ``D(V)`` (its envelope needs 0.53 m at 0.4 m/s, they spawn 0.2 m clear), which the
    envelope's argument does not cover; the count is of real obstacles, not of every one."""
    import importlib.util
    import sys
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "envelope.py"
    spec = importlib.util.spec_from_file_location("envelope_benchmark", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    (row,) = module.main(["--arms", "panda", "--configurations", "4", "--spawns", "20"])
    inside, moving = row["spawned_inside"]
    assert 20 <= moving and 0 < inside < moving
