"""The escape search (benchmarks/escape.py): on an episode of robosuite's Sawyer that the filter
loses, a motion within the arm's torque limits and the filter's speed bound keeps it clear (on the
search's model and, replayed, on the benchmark's own), and a search that cannot find one says so;
run by the episode itself where the filter's rows give way, with only what the filter knows, it
keeps that episode clear, and so it does when started only where a forecast of the filtered arm
sees a hard row give way."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest

from c3bf_gym.safety import FilterConfig

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(f"{name}_benchmark", BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is built
    spec.loader.exec_module(module)
    return module


escape = _load("escape")
tp = escape.tp

#: the candidate settings of the guarantee page, under which the Sawyer's multi seed 20 collides
CANDIDATE = FilterConfig(sensing_radius=tp.SENSING_RADIUS, joint_range_reserve=0.3, allowance_level=True,
                         joint_speed_fraction=1.0, nominal_speed_fraction=0.4)  # fmt: skip


@pytest.fixture(scope="module")
def assets() -> Path:
    return tp.robosuite_assets()


def test_an_episode_the_filter_loses_has_an_escape_and_holding_still_has_none(assets):
    model, robot, _ = tp.build_scene(assets, "sawyer", 4)
    speed = tp.speed_range(tp.arm_envelope(model, robot, "sawyer", CANDIDATE))
    assert tp.run_episode((str(assets), "sawyer", "multi", "random", CANDIDATE, 20, tp.SECONDS, speed,
                           CANDIDATE, ())).collided  # the filter loses it

    found = escape.search("sawyer", "multi", 20, CANDIDATE, assets=assets, iterations=15)
    assert found.found
    assert found.lowest_clearance > 0.0
    assert found.max_speed_ratio <= escape.SPEED_TOLERANCE
    assert found.still_clearance < -0.05  # standing still, a sphere passes through the arm
    assert found.horizon > 3.0  # until the last moving sphere has left

    # the motion is an escape of the benchmark's own torque-driven arm, not only of the search's model
    again = escape.replay("sawyer", "multi", 20, CANDIDATE, np.array(found.targets), found.horizon, assets=assets)
    assert again.unfiltered_clearance > 0.0
    assert abs(again.unfiltered_clearance - found.lowest_clearance) < 0.002
    assert again.filtered_infeasible_steps > 0 and again.fallback_steps > 0  # the rows give way here


def test_a_search_that_finds_no_escape_says_so(assets):
    """Held still until after the spheres have closed, no motion is left that clears them."""
    found = escape.search("sawyer", "multi", 20, CANDIDATE, assets=assets, hold=4.0, iterations=2)
    assert not found.found
    assert found.lowest_clearance < 0.0
    assert found.iterations == 2


def test_the_search_model_keeps_the_arms_torque_limits_and_speed_bound(assets):
    model, robot, _ = tp.build_scene(assets, "sawyer+gripper", 4)
    bound = 0.5 * np.asarray(robot.joint_speed_limit)
    spec, _, _, _ = tp.scene_spec(assets, "sawyer+gripper", 4)
    first = escape.escape_spec(spec, robot, model, np.array(tp.ARMS["sawyer+gripper"].init_qpos), bound, 4)
    servo = spec.compile()
    limit = np.asarray(robot.torque_limit)
    arm = [i for i in range(servo.nu) if servo.jnt_dofadr[servo.actuator_trnid[i, 0]] in robot.dof_ids]
    dofs = servo.jnt_dofadr[servo.actuator_trnid[arm, 0]]
    order = [int(np.flatnonzero(robot.dof_ids == d)[0]) for d in dofs]
    np.testing.assert_allclose(servo.actuator_forcerange[arm, 1], limit[order])
    np.testing.assert_allclose(servo.actuator_ctrlrange[arm, 1], bound[order])
    joints = servo.dof_jntid[robot.dof_ids]
    assert servo.jnt_actgravcomp[joints].all()  # gravity is compensated within the same limit
    np.testing.assert_allclose(servo.jnt_actfrcrange[joints, 1], limit)
    assert len(arm) == robot.n < servo.nu  # the gripper's fingers keep their own actuators
    distance = servo.sensor_type[first:] == mujoco.mjtSensor.mjSENS_GEOMDIST
    assert distance.all() and len(distance) == len(robot.geom_ids) * 4
    # zero targets hold the arm where it is: the servos are stable on the scene's Euler step
    data = mujoco.MjData(servo)
    qpos = servo.jnt_qposadr[servo.dof_jntid[robot.dof_ids]]
    data.qpos[qpos] = tp.ARMS["sawyer+gripper"].init_qpos
    start = data.qpos[qpos].copy()
    for _ in range(1000):
        mujoco.mj_step(servo, data)
    assert np.abs(data.qvel[robot.dof_ids]).max() < 1e-3
    np.testing.assert_allclose(data.qpos[qpos], start, atol=1e-3)


def test_the_search_names_the_valid_choices(assets):
    with pytest.raises(ValueError, match="static, head_on, crossing, multi"):
        escape.search("sawyer", "swarm", 20, CANDIDATE, assets=assets)
    with pytest.raises(ValueError, match="unknown arm"):
        escape.search("ur10", "multi", 20, CANDIDATE, assets=assets)
    with pytest.raises(ValueError, match="target > 0 m"):
        escape.search("sawyer", "multi", 20, CANDIDATE, assets=assets, target=0.0)
    with pytest.raises(ValueError, match="samples >= 2"):
        escape.search("sawyer", "multi", 20, CANDIDATE, assets=assets, samples=1)
    with pytest.raises(ValueError, match=r"hold must be in \[0, "):
        escape.search("sawyer", "multi", 20, CANDIDATE, assets=assets, hold=30.0)
    with pytest.raises(ValueError, match=r"engage must be in \(0, lookahead = 1\] s"):
        escape.OnlineEscape("sawyer", "multi", 20, CANDIDATE, assets=assets, max_speed=0.4, lookahead=1.0,
                            engage=2.0, iterations=1, threads=1, target=escape.TARGET)  # fmt: skip
    with pytest.raises(ValueError, match="unknown trigger 'soon'; choose from rows, hard, forecast"):
        escape.OnlineEscape("sawyer", "multi", 20, CANDIDATE, assets=assets, max_speed=0.4, lookahead=2.0,
                            engage=1.0, iterations=1, threads=1, target=escape.TARGET, trigger="soon")  # fmt: skip
    with pytest.raises(SystemExit):
        escape.main(["--seeds", "20", "--online", "--policies", "lazy"])
    with pytest.raises(ValueError, match="unknown forecast_torque 'policy'; choose from bias, held"):
        escape.OnlineEscape("sawyer", "multi", 20, CANDIDATE, assets=assets, max_speed=0.4, lookahead=2.0,
                            engage=1.0, iterations=1, threads=1, target=escape.TARGET, trigger="forecast",
                            forecast_torque="policy")  # fmt: skip
    with pytest.raises(SystemExit):
        escape.main(["--seeds", "20", "--online", "--trigger", "soon"])
    for every, horizon in ((0.0, None), (0.1, -1.0)):
        with pytest.raises(ValueError, match="forecast_every and forecast_horizon must be > 0 s"):
            escape.OnlineEscape("sawyer", "multi", 20, CANDIDATE, assets=assets, max_speed=0.4, lookahead=2.0,
                                engage=1.0, iterations=1, threads=1, target=escape.TARGET, trigger="forecast",
                                forecast_every=every, forecast_horizon=horizon)  # fmt: skip
    with pytest.raises(ValueError, match=r"forecast_gate must be > 0 m \(or None: no gate\), got 0.0"):
        escape.OnlineEscape("sawyer", "multi", 20, CANDIDATE, assets=assets, max_speed=0.4, lookahead=2.0,
                            engage=1.0, iterations=1, threads=1, target=escape.TARGET, trigger="forecast",
                            forecast_gate=0.0)  # fmt: skip


def test_the_forecast_gate_opens_for_a_sphere_headed_at_the_arm_within_the_horizon(assets):
    """near_path: a sphere 1 m above a link's middle, coming down at 0.5 m/s, is on the arm's path
    within 2 s, not within 0.5 s; going up, or inactive, it never is."""
    from c3bf_gym.safety import Obstacles

    model, robot, _ = tp.build_scene(assets, "sawyer", 4)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    a, b, radius = robot.capsule_segments(data)
    spheres = Obstacles(1)
    spheres.position[0] = 0.5 * (a[2] + b[2]) + (0.0, 0.0, 1.0)
    spheres.radius[0] = 0.05
    spheres.active[0] = True
    assert escape.capsule_distances(spheres.position[0], a, b, radius).min() - 0.05 > 0.5  # far at the start
    spheres.velocity[0] = (0.0, 0.0, -0.5)
    assert escape.near_path(robot, data, spheres, 2.0, 0.1)
    assert not escape.near_path(robot, data, spheres, 0.5, 0.1)
    spheres.velocity[0] = (0.0, 0.0, 0.5)
    assert not escape.near_path(robot, data, spheres, 2.0, 0.1)
    spheres.velocity[0] = (0.0, 0.0, -0.5)
    spheres.active[0] = False
    assert not escape.near_path(robot, data, spheres, 2.0, 0.1)


class _PassThrough:
    """A takeover that changes nothing: the policy's nominal, the filter's torque."""

    def __init__(self) -> None:
        self.gave_way_steps = 0

    def nominal(self, step, data, obstacles, tau):
        return tau

    def gave_way(self, step, data, obstacles, safe, hard):
        self.gave_way_steps += 1
        return safe


def test_a_takeover_that_changes_nothing_leaves_the_episode_as_it_was(assets):
    model, robot, _ = tp.build_scene(assets, "sawyer", 4)
    speed = tp.speed_range(tp.arm_envelope(model, robot, "sawyer", CANDIDATE))
    task = (str(assets), "sawyer", "multi", "random", CANDIDATE, 20, 2.0, speed, CANDIDATE, ())
    watching, alone = _PassThrough(), tp.run_episode(task)
    assert tp.run_episode(task, watching) == alone
    assert watching.gave_way_steps == alone.infeasible_steps > 0  # asked at every step they gave way


class _Forecasting(_PassThrough):
    """A takeover that changes nothing and forecasts every ``FORECAST_EVERY`` s of the first second."""

    def __init__(self, robot, envelope) -> None:
        super().__init__()
        self.robot, self.envelope, self.forecast, self.pinched = robot, envelope, None, []

    def nominal(self, step, data, obstacles, tau):
        if step % round(escape.FORECAST_EVERY / tp.TIMESTEP) == 0 and step * tp.TIMESTEP < 1.0:
            if self.forecast is None:
                self.forecast = escape.Forecast(data.model, self.robot, 4, tp.CONFIG, self.envelope)
            self.pinched.append(self.forecast.pinched(data, obstacles, escape.LOOKAHEAD))
        return tau


def test_the_forecast_sees_a_pinch_ahead_on_its_own_data_and_none_without_spheres(assets):
    """The Sawyer's multi seed 2, which the default filter loses: a hard row gives way within
    2 s of its first second's states, and forecasting leaves the episode as it was."""
    model, robot, _ = tp.build_scene(assets, "sawyer", 4)
    envelope = tp.arm_envelope(model, robot, "sawyer", tp.CONFIG)
    task = (str(assets), "sawyer", "multi", "random", tp.CONFIG, 2, tp.SECONDS, tp.speed_range(envelope), tp.CONFIG,
            ())
    alone, watching = tp.run_episode(task), _Forecasting(robot, envelope)
    assert tp.run_episode(task, watching) == alone
    assert len(watching.pinched) == 10 and any(watching.pinched)
    forecast = watching.forecast
    data = mujoco.MjData(forecast.model)
    mujoco.mj_forward(forecast.model, data)
    nothing = escape.MocapSpheres(forecast.model, [tp._BALL.format(k) for k in range(4)])
    nothing.clear()
    assert not forecast.pinched(data, nothing, escape.LOOKAHEAD)
    assert forecast.runs == 11 and forecast.seconds > 0.0


def test_the_search_run_where_the_rows_give_way_keeps_an_episode_the_filter_loses_clear(assets):
    """Knowing only what the filter knows there (the spheres' positions and velocities)."""
    run = escape.online("sawyer", "multi", "random", 20, tp.CONFIG, assets=assets, iterations=10)
    assert run["filtered"]["collided"] and run["filtered"]["lowest_clearance"] < -0.02
    assert not run["online"]["collided"] and run["online"]["lowest_clearance"] > 0.01
    assert run["searches"] and run["fallback_steps"] > 0
    first = run["searches"][0]
    assert first["start"] < tp.SECONDS and first["horizon"] == pytest.approx(first["start"] + escape.LOOKAHEAD)


def test_the_search_run_where_a_forecast_sees_a_pinch_keeps_an_episode_the_filter_loses_clear(assets):
    """The Sawyer's multi seed 12: the rows give way from the first step, the forecast sees a hard
    row give way only later, and the searches it starts keep the episode clear."""
    run = escape.online("sawyer", "multi", "random", 12, tp.CONFIG, assets=assets, iterations=10, trigger="forecast")
    assert run["filtered"]["collided"] and run["filtered"]["infeasible_steps"] > 0
    assert not run["online"]["collided"] and run["online"]["lowest_clearance"] > 0.01
    assert run["forecasts"] > 0 and run["forecast_seconds"] > 0.0
    assert run["searches"] and run["searches"][0]["start"] >= 1.0 and run["fallback_steps"] > 0
