"""The filter as a library (c3bf_gym.safety): a robot description read from any MuJoCo model, the
obstacle interface, and SafetyController on an inline 3-joint arm that is not the UR5e.

Collisions are judged independently of the filter, by MuJoCo's own ``mj_geomDistance``."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from c3bf_gym.safety import (
    FilterConfig,
    MocapSpheres,
    Obstacles,
    RobotDescription,
    SafetyController,
    SafetyInfeasibleError,
    UnprotectedGeometryWarning,
    UnsupportedModelError,
)

import reference

#: The inline arm's post lies on its yaw axis: the default selection leaves it out with a warning
#: (test_description_reads_the_model checks it), which the other tests need not repeat.
pytestmark = pytest.mark.filterwarnings("ignore::c3bf_gym.safety.UnprotectedGeometryWarning")

#: A planar-ish 3-joint arm: a yaw joint and two pitch joints, capsule links, a sphere at the
#: wrist, a tool site, torque motors, a floor, and one mocap ball.
ARM = """
<mujoco model="three_link">
  <compiler angle="radian"/>
  <option timestep="0.002"/>
  <worldbody>
    <geom name="floor" type="plane" size="2 2 0.1"/>
    <body name="base" pos="0 0 0.1">
      <joint name="yaw" axis="0 0 1" range="-3 3" damping="1"/>
      <geom name="post" type="capsule" fromto="0 0 0 0 0 0.3" size="0.05" mass="2"/>
      <body name="upper" pos="0 0 0.3">
        <joint name="shoulder" axis="0 1 0" range="-2 2" damping="1"/>
        <geom name="upper" type="capsule" fromto="0 0 0 0.4 0 0" size="0.04" mass="1.5"/>
        <body name="fore" pos="0.4 0 0">
          <joint name="elbow" axis="0 1 0" range="-2.5 2.5" damping="0.5"/>
          <geom name="fore" type="capsule" fromto="0 0 0 0.35 0 0" size="0.035" mass="1"/>
          <geom name="wrist" type="sphere" pos="0.35 0 0" size="0.05" mass="0.2"/>
          <site name="tool" pos="0.4 0 0"/>
        </body>
      </body>
    </body>
    <body name="ball" mocap="true" pos="0.6 0 1.2">
      <geom name="ball" type="sphere" size="0.06" contype="0" conaffinity="0"/>
    </body>
  </worldbody>
  <actuator>
    <motor name="yaw" joint="yaw" ctrlrange="-40 40"/>
    <motor name="shoulder" joint="shoulder" ctrlrange="-40 40"/>
    <motor name="elbow" joint="elbow" ctrlrange="-20 20"/>
  </actuator>
</mujoco>
"""


def _model(xml: str = ARM) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_string(xml)


def test_description_reads_the_model():
    model = _model()
    with pytest.warns(UnprotectedGeometryWarning, match=r"geom 'post' lies on the axis of the joints that move it"):
        robot = RobotDescription.from_model(model, site="tool", joint_speed_limit=2.0)
    names = [model.geom(g).name for g in robot.geom_ids]
    assert names == ["upper", "fore", "wrist"]  # colliding geoms that the joints can move away
    assert [c.source for c in robot.capsules] == ["capsule", "capsule", "sphere"]
    assert robot.describe(model).splitlines()[1].split() == ["upper", "upper", "capsule", "0.0400", "0.4000"]
    np.testing.assert_array_equal(robot.torque_limit, [40.0, 40.0, 20.0])
    np.testing.assert_array_equal(robot.joint_range, [[-3, 3], [-2, 2], [-2.5, 2.5]])
    np.testing.assert_array_equal(robot.joint_speed_limit, [2.0, 2.0, 2.0])
    assert robot.n == 3 and model.site(robot.site_id).name == "tool"
    by_body = RobotDescription.from_model(model, bodies=["fore"])
    assert [model.geom(g).name for g in by_body.geom_ids] == ["fore", "wrist"]
    assert by_body.joint_speed_limit is None and by_body.site_id == -1


BAD_MODELS = [
    (ARM.replace('<motor name="elbow" joint="elbow" ctrlrange="-20 20"/>', ""), {}, r"joint 'elbow' has no torque motor"),
    (ARM.replace('<motor name="elbow" joint="elbow" ctrlrange="-20 20"/>', '<position name="elbow" joint="elbow" kp="10" ctrlrange="-1 1"/>'),
     {}, r"actuator 'elbow' is not a torque motor"),
    (ARM.replace('<motor name="elbow" joint="elbow" ctrlrange="-20 20"/>', '<motor name="elbow" joint="elbow"/>'),
     {}, r"actuator 'elbow' has no torque limit"),
    (ARM.split("<actuator>")[0] + "</mujoco>", {}, r"no actuators"),
    (ARM, {"geoms": ["floor"]}, r"geom 'floor' is on a body the arm's joints do not move"),
    (ARM, {"geoms": ["post", "upper"]}, r"geom 'post' lies on the axis of the joints that move it.*leave it out"),
    (ARM.replace('<body name="ball"', '<site name="corner" pos="1 1 0"/><body name="ball"'), {"site": "corner"},
     r"site 'corner' is on body 'world', which the arm's joints do not move"),
    (ARM, {"geoms": ["upper", "nope"]}, r"unknown geom 'nope'.*post.*upper"),
    (ARM.replace('<body name="ball" mocap="true" pos="0.6 0 1.2">', '<body name="ball" pos="0.6 0 1.2"><freejoint/>'),
     {}, r"is a free joint"),
    (ARM, {"site": "hand"}, r"unknown site 'hand'; the model's named sites: tool"),
    (ARM, {"joint_speed_limit": [1.0, 2.0]}, r"joint_speed_limit must be one finite number > 0 or 3"),
]  # fmt: skip


@pytest.mark.parametrize("xml, kwargs, message", BAD_MODELS, ids=[m for *_, m in BAD_MODELS])
def test_models_the_filter_cannot_protect_are_refused_by_name(xml, kwargs, message):
    with pytest.raises(UnsupportedModelError, match=message):
        RobotDescription.from_model(_model(xml), **kwargs)


def test_joint_limits_need_speed_limits_and_a_continuous_joint_gets_speed_rows_only():
    """A joint without position limits (a continuous one) keeps its speed rows; its position rows
    are ``0 τ ≥ −1``, which hold, so the filter still runs and holds the other joints' limits."""
    model = _model(ARM.replace(' range="-2.5 2.5"', ""))
    robot = RobotDescription.from_model(model, joint_speed_limit=2.0)
    data = mujoco.MjData(model)
    data.qpos[:] = (0.3, -0.6, 4.0)  # the elbow far beyond any range: nothing to hold
    mujoco.mj_forward(model, data)
    controller = SafetyController(model, data, robot, Obstacles(1))
    A, b, *_ = controller.rows()
    n = 3
    A, b = A[-4 * n :], b[-4 * n :]  # the joint-limit rows come last
    np.testing.assert_array_equal(A[[2, n + 2]], 0.0)  # the elbow's position rows, upper and lower
    np.testing.assert_array_equal(b[[2, n + 2]], -1.0)
    assert np.all(np.abs(A[[0, 1, n, n + 1, 2 * n + 2, 3 * n + 2]]).sum(axis=1) > 0)  # the others, and its speed rows
    _, report = controller.filter(np.zeros(3))
    assert report.feasible
    robot = RobotDescription.from_model(_model(), site="tool")
    with pytest.raises(UnsupportedModelError, match="joint speed limits"):
        SafetyController(_model(), mujoco.MjData(_model()), robot, Obstacles(1))


def _ball_clearance(model, data) -> float:
    """MuJoCo's own smallest signed distance between the ball and any arm geom [m]."""
    ball = model.geom("ball").id
    arm = [model.geom(n).id for n in ("post", "upper", "fore", "wrist")]
    return min(mujoco.mj_geomDistance(model, data, ball, g, 1.0, None) for g in arm)


def _run(filtered: bool, config: FilterConfig | None = None, seconds: float = 1.5):
    """The arm pulled up towards a ball that falls onto it at 1 m/s; returns (lowest clearance,
    interventions, the controller)."""
    model = _model()
    data = mujoco.MjData(model)
    data.qpos[:] = (0.0, -0.3, 0.4)
    mujoco.mj_forward(model, data)
    robot = RobotDescription.from_model(model, site="tool", joint_speed_limit=3.0)
    balls = MocapSpheres(model, ["ball"])
    controller = SafetyController(model, data, robot, balls, config) if filtered else None
    ball_velocity = np.array([0.0, 0.0, -1.0])
    lowest, interventions = np.inf, 0
    for _ in range(int(seconds / model.opt.timestep)):
        mujoco.mj_step1(model, data)
        lowest = min(lowest, _ball_clearance(model, data))
        # nominal: a PD pull towards an upright pose, plus gravity compensation
        tau_nom = 60.0 * (np.array([0.0, -1.2, 0.0]) - data.qpos) - 8.0 * data.qvel + data.qfrc_bias
        tau_nom = np.clip(tau_nom, -robot.torque_limit, robot.torque_limit)
        if controller is not None:
            balls.velocity[0] = ball_velocity
            tau, report = controller.filter(tau_nom)
            interventions += report.intervened
        else:
            tau = tau_nom
        data.ctrl[:] = tau
        mujoco.mj_step2(model, data)
        data.mocap_pos[0] += ball_velocity * model.opt.timestep
    return lowest, interventions, controller


def test_standalone_controller_keeps_a_falling_ball_off_an_inline_arm():
    unfiltered, _, _ = _run(filtered=False)
    assert unfiltered < 0.0, "the scenario must collide without the filter, or the test proves nothing"
    lowest, interventions, controller = _run(filtered=True)
    assert lowest > 0.0 and interventions > 0
    assert controller.report.substeps == 1  # filter(): one call's own report


@pytest.mark.parametrize(("points", "barrier", "guard", "obstacle_rows"),
                         [("whole_arm", "c3bf", None, 3), ("ee", "c3bf", None, 1), ("ee", "c3bf", "auto", 2),
                          ("ee", "hocbf", None, 1), ("ee", "hocbf", "hocbf", 2)])  # fmt: skip
def test_standalone_fused_and_per_class_paths_agree(points, barrier, guard, obstacle_rows):
    """The fused kernel (which measures sensing distances to the protected geoms itself when the
    obstacles keep none, treats the wrist sphere as a capsule of length 0, and writes the tool
    site's rows for ``points="ee"``) gives the rows of the per-class path, which uses numpy
    geometry and the barrier classes' ``terms``, the guard's included. (The site's dynamics, the
    same kernel on both paths, are checked against MuJoCo's ``mj_jacSite`` and ``mj_jacDot`` in
    tests/test_robot.py.)"""
    model = _model()
    data = mujoco.MjData(model)
    data.qpos[:] = (0.3, -0.6, 0.9)
    data.qvel[:] = (0.5, -1.0, 0.7)
    data.mocap_pos[0] = (0.45, 0.1, 0.75)
    mujoco.mj_forward(model, data)
    robot = RobotDescription.from_model(model, site="tool", joint_speed_limit=3.0)
    balls = MocapSpheres(model, ["ball"])
    balls.velocity[0] = (-0.2, 0.0, -0.4)
    config = FilterConfig(sensing_radius=0.5, barrier=barrier, guard=guard, points=points)
    fused = SafetyController(model, data, robot, balls, config)
    generic = SafetyController(model, data, robot, balls, config)
    generic._fused = False  # the per-class path, as a barrier the kernel cannot fuse takes
    assert fused._fused
    A1, b1, h1, in1, n1 = (x.copy() if isinstance(x, np.ndarray) else x for x in fused.rows())
    A2, b2, h2, in2, n2 = generic.rows()
    assert n1 == n2 == 1 and in1 == in2 and h1 == pytest.approx(h2, rel=1e-12)
    np.testing.assert_allclose(A1, A2, rtol=0, atol=1e-10)
    np.testing.assert_allclose(b1, b2, rtol=0, atol=1e-10)
    # whole arm: 3 protected geoms (ee: the tool site; with a guard, its row too); floor: both ends
    # of 2 capsules, 1 of the sphere; the post on the yaw axis, a fixed part, against the forearm
    # and the wrist (the upper arm is its body's child); 4n
    assert len(b1) == obstacle_rows + 5 + 2 + 12
    assert np.abs(A1[:obstacle_rows]).max() > 0.0  # the obstacle rows are there, not zeros on both paths


def _moving_arm() -> tuple[mujoco.MjModel, mujoco.MjData, RobotDescription]:
    """The 3-joint arm in motion (its kinematics and dynamics current), and its description with
    the tool site."""
    model = _model()
    data = mujoco.MjData(model)
    data.qpos[:] = (0.3, -0.6, 0.9)
    data.qvel[:] = (0.5, -1.0, 0.7)
    mujoco.mj_forward(model, data)
    return model, data, RobotDescription.from_model(model, site="tool", joint_speed_limit=3.0)


def test_the_tool_metric_on_a_users_arm_is_the_qp_in_that_metric():
    """``weight="tool"`` through the standalone API, on a 3-joint arm of the user's: the torque is
    proxsuite's optimum of ``½ (u − u_nom)ᵀ (I + GᵀG / a²) (u − u_nom)`` over the filter's own
    rows and the box (``u = τ / τ_max``, ``G`` from MuJoCo's site Jacobian and mass matrix), and
    not the ``"limits"`` metric's."""
    proxqp = pytest.importorskip("proxsuite").proxqp
    model, data, robot = _moving_arm()
    obstacles = Obstacles(1, position=np.array([[0.45, 0.1, 0.75]]), velocity=np.array([[-0.2, 0.0, -0.4]]),
                          radius=np.array([0.05]), active=np.ones(1, bool))
    tau_nom = np.array([20.0, -30.0, 10.0])
    config = FilterConfig(sensing_radius=None, weight="tool", tool_acceleration=2.0, on_infeasible="raise")
    controller = SafetyController(model, data, robot, obstacles, config)
    A, b, *_ = (x.copy() for x in controller.rows()[:2])
    tau, report = controller.filter(tau_nom)
    assert report.feasible and report.correction > 0.0
    limit = robot.torque_limit
    G = reference.tool_acceleration_gain(model, data, robot.site_id, limit)
    H = np.eye(3) + G.T @ G / 2.0**2
    u_nom = tau_nom / limit
    result = proxqp.dense.solve(H, -H @ u_nom, None, None, np.vstack([A * limit, np.eye(3)]),
                                np.concatenate([b, -np.ones(3)]), np.concatenate([np.full(len(b), 1e20), np.ones(3)]),
                                eps_abs=1e-10, eps_rel=0.0)  # fmt: skip
    np.testing.assert_allclose(tau / limit, result.x, atol=1e-6)
    limits, _ = SafetyController(model, data, robot, obstacles, config.replace(weight="limits",
                                                                               tool_acceleration=None)).filter(tau_nom)
    assert np.linalg.norm((limits - tau) / limit) > 1e-3


def test_obstacle_arrays_given_as_strided_views_filter_as_their_copies():
    """Obstacles may keep their arrays as views of a simulator's state, which need not be contiguous.
    The controller's call from Python hands contiguous buffers to compiled code by address and takes
    the others as they are: the torques are the same, bit for bit."""
    model, data, robot = _moving_arm()
    state = np.zeros((2, 6))  # a simulator's (position, velocity) rows
    state[0] = (0.45, 0.1, 0.75, -0.2, 0.0, -0.4)
    state[1] = (-0.3, 0.2, 0.6, 0.3, 0.1, 0.0)
    strided = Obstacles(2, position=state[:, :3], velocity=state[:, 3:], radius=np.array([0.05, 0.08]),
                        active=np.ones(2, bool))
    assert not strided.position.flags.c_contiguous
    contiguous = Obstacles(2, position=state[:, :3].copy(), velocity=state[:, 3:].copy(),
                           radius=np.array([0.05, 0.08]), active=np.ones(2, bool))
    config = FilterConfig(sensing_radius=None)
    tau_nom = np.array([20.0, -30.0, 10.0])
    taus = []
    for obstacles in (strided, contiguous):
        controller = SafetyController(model, data, robot, obstacles, config)
        tau, report = controller.filter(tau_nom)
        assert report.sensed == 2 and report.correction > 0.0  # the rows are there and bind
        taus.append(tau)
    np.testing.assert_array_equal(taus[0], taus[1])


def test_controller_input_errors():
    model = _model()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    robot = RobotDescription.from_model(model, site="tool", joint_speed_limit=3.0)
    controller = SafetyController(model, data, robot, MocapSpheres(model, ["ball"]))
    with pytest.raises(ValueError, match=r"tau_nom must have shape \(3,\)"):
        controller.filter(np.zeros(6))
    with pytest.raises(ValueError, match="NaN or inf"):
        controller.filter(np.array([0.0, np.nan, 0.0]))
    with pytest.raises(ValueError, match="not a mocap body; the model's mocap bodies: ball"):
        MocapSpheres(model, ["upper"])
    with pytest.raises(UnsupportedModelError, match="points='ee'.*site"):
        SafetyController(model, data, RobotDescription.from_model(model, joint_speed_limit=3.0), Obstacles(1),
                         FilterConfig(points="ee"))
    with pytest.raises(UnsupportedModelError, match="weight='tool'.*site=.*weight='limits'"):
        SafetyController(model, data, RobotDescription.from_model(model, joint_speed_limit=3.0), Obstacles(1),
                         FilterConfig(weight="tool"))
    obstacles = Obstacles(2)
    with pytest.raises(ValueError, match="radius must be a finite number > 0"):
        obstacles.set(0, (0, 0, 1), radius=0.0)
    with pytest.raises(ValueError, match="position must be 3 finite numbers"):
        obstacles.set(0, (0, 0, np.inf), radius=0.1)
    with pytest.raises(ValueError, match=r"position must be a \(2, 3\) float64 array"):
        Obstacles(2, position=np.zeros((3, 3)))


def test_raise_policy_on_the_standalone_controller():
    """``on_infeasible="raise"`` raises from filter(); the data is untouched (the controller never
    writes to it), so the caller decides what to apply instead."""
    model = _model()
    data = mujoco.MjData(model)
    data.qpos[:] = (0.0, -0.3, 0.4)
    data.qvel[:] = (0.0, -60.0, 60.0)  # far beyond the speed bound: no torque can hold it this step
    mujoco.mj_forward(model, data)
    robot = RobotDescription.from_model(model, site="tool", joint_speed_limit=1.0)
    controller = SafetyController(model, data, robot, Obstacles(1), FilterConfig(on_infeasible="raise"))
    qpos = data.qpos.copy()
    with pytest.raises(SafetyInfeasibleError):
        controller.filter(data.qfrc_bias.copy())
    np.testing.assert_array_equal(data.qpos, qpos)


#: The inline arm with a two-finger gripper on position servos (force-limited) at the wrist, and a
#: free box lying on the floor: dofs the filter does not drive.
GRIPPER_ARM = ARM.replace(
    '<site name="tool" pos="0.4 0 0"/>',
    '''<site name="tool" pos="0.4 0 0"/>
          <body name="finger_l" pos="0.4 0 0.02">
            <joint name="finger_l" type="slide" axis="0 0 1" range="0 0.03" damping="5" frictionloss="0.5"/>
            <geom name="finger_l" type="box" size="0.03 0.01 0.005" mass="0.05"/>
          </body>
          <body name="finger_r" pos="0.4 0 -0.02">
            <joint name="finger_r" type="slide" axis="0 0 -1" range="0 0.03" damping="5"/>
            <geom name="finger_r" type="box" size="0.03 0.01 0.005" mass="0.05"/>
          </body>''',
).replace(
    '<body name="ball" mocap="true" pos="0.6 0 1.2">',
    '<body name="crate" pos="1.2 0.8 0.05"><freejoint name="crate"/><geom type="box" size="0.05 0.05 0.05" mass="0.3"/></body>'
    '<body name="ball" mocap="true" pos="0.6 0 1.2">',
).replace(
    "</actuator>",
    '<position name="finger_l" joint="finger_l" kp="200" ctrlrange="0 0.03" forcerange="-15 15"/>'
    '<position name="finger_r" joint="finger_r" kp="200" ctrlrange="0 0.03" forcerange="-15 15"/></actuator>',
)
ARM_JOINTS = ["yaw", "shoulder", "elbow"]


def test_an_arm_with_a_gripper_and_other_bodies_is_filtered_on_its_own_joints():
    """joints= names the arm: the filter drives those; the gripper's servos and a free body are left
    to the model, their forces bounded by the servos' forcerange (and the joints' friction loss), and
    the fingers are protected like the links. A servo whose force has no bound is refused."""
    model = _model(GRIPPER_ARM)
    with pytest.raises(UnsupportedModelError, match=r"joint 'crate' is a free joint.*name the arm's joints with joints="):
        RobotDescription.from_model(model)  # the gripper and the crate are not the arm's
    with pytest.raises(UnsupportedModelError, match=r"joints= names no joint"):
        RobotDescription.from_model(model, joints=[])
    robot = RobotDescription.from_model(model, joints=ARM_JOINTS + ["yaw"], site="tool", joint_speed_limit=3.0)
    assert (robot.n, robot.nv) == (3, 11) and robot.dof_ids.tolist() == [0, 1, 2]  # a joint named twice counts once
    assert {"finger_l", "finger_r", "upper", "fore", "wrist"} <= {model.geom(g).name for g in robot.geom_ids}
    finger_l, finger_r = model.joint("finger_l").dofadr[0], model.joint("finger_r").dofadr[0]
    bound = robot.unmodelled_force
    assert bound[finger_l] == 15.5 and bound[finger_r] == 15.0 and bound[robot.dof_ids].tolist() == [0.0] * 3
    unbounded = GRIPPER_ARM.replace('ctrlrange="0 0.03" forcerange="-15 15"/></actuator>', 'ctrlrange="0 0.03"/></actuator>')
    with pytest.raises(UnsupportedModelError, match=r"actuator 'finger_r' drives joint 'finger_r'.*no force bound"):
        RobotDescription.from_model(_model(unbounded), joints=ARM_JOINTS)

    # the arm pulled up into a falling ball while the gripper opens and closes: kept off every protected geom
    lowest = {}
    for filtered in (False, True):
        data = mujoco.MjData(model)
        data.qpos[robot.dof_ids] = (0.0, -0.3, 0.4)
        mujoco.mj_forward(model, data)
        balls = MocapSpheres(model, ["ball"])
        controller = SafetyController(model, data, robot, balls)
        ball, lowest[filtered] = model.geom("ball").id, np.inf
        for step in range(750):
            mujoco.mj_step1(model, data)
            lowest[filtered] = min(lowest[filtered], *(mujoco.mj_geomDistance(model, data, ball, g, 1.0, None)
                                                       for g in robot.geom_ids))  # fmt: skip
            q, qd = data.qpos[robot.dof_ids], data.qvel[robot.dof_ids]
            tau = 60.0 * (np.array([0.0, -1.2, 0.0]) - q) - 8.0 * qd + data.qfrc_bias[robot.dof_ids]
            tau = np.clip(tau, -robot.torque_limit, robot.torque_limit)
            if filtered:
                balls.velocity[0] = (0.0, 0.0, -1.0)
                tau, report = controller.filter(tau)
            robot.write_ctrl(model, data, tau)
            data.ctrl[model.actuator("finger_l").id :] = 0.03 * ((step // 100) % 2)  # the gripper opens and closes
            mujoco.mj_step2(model, data)
            data.mocap_pos[0] += model.opt.timestep * np.array([0.0, 0.0, -1.0])
    assert lowest[False] < 0.0 < lowest[True], lowest


def test_a_finger_is_protected_over_its_whole_stroke():
    """A geom that joints the filter does not drive move (a finger) is protected by a capsule on the
    last body the arm moves that holds it at every finger position: its corners at both ends of the
    stroke and halfway lie inside that capsule."""
    model = _model(GRIPPER_ARM)
    robot = RobotDescription.from_model(model, joints=ARM_JOINTS, site="tool", joint_speed_limit=3.0)
    data = mujoco.MjData(model)
    for name in ("finger_l", "finger_r"):
        geom = model.geom(name).id
        capsule = robot.capsules[list(robot.geom_ids).index(geom)]
        assert capsule.body == model.body("fore").id and capsule.source == "box"
        joint = model.joint(name)
        half = model.geom_size[geom]
        corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * half
        for finger in np.linspace(*model.jnt_range[joint.id], 3):
            data.qpos[joint.qposadr[0]] = finger
            mujoco.mj_kinematics(model, data)
            world = data.geom_xpos[geom] + corners @ data.geom_xmat[geom].reshape(3, 3).T
            local = (world - data.xpos[capsule.body]) @ data.xmat[capsule.body].reshape(3, 3)
            assert capsule.distance(local).max() <= 1e-9


def test_a_geom_on_hinged_fingers_is_held_at_every_angle():
    """Two nested hinges the filter does not drive, the outer one off its body's origin: the swept
    capsule holds the tip at every angle of a dense grid, not only at the sampled ones."""
    xml = """<mujoco><compiler angle="radian"/><worldbody>
      <body name="l1" pos="0 0 .3"><joint name="j1" axis="0 1 0" range="-3 3"/>
        <geom type="capsule" fromto="0 0 0 .3 0 0" size=".04"/>
        <body name="fbase" pos=".3 0 0"><joint name="f1" axis="0 1 0" range="0 0.6" pos="-0.3 0 0"/>
          <inertial pos="0 0 0" mass=".01" diaginertia="1e-5 1e-5 1e-5"/>
          <body name="mid" pos=".4 0 0"><joint name="f2" axis="0 1 0" range="0 0.6"/>
            <inertial pos="0 0 0" mass=".01" diaginertia="1e-5 1e-5 1e-5"/>
            <body name="tip" pos=".4 0 0"><geom name="tip" type="box" size=".01 .01 .01"/></body>
          </body></body></body></worldbody>
      <actuator><motor joint="j1" ctrlrange="-1 1"/><motor joint="f1" ctrlrange="-1 1"/>
        <motor joint="f2" ctrlrange="-1 1"/></actuator></mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    robot = RobotDescription.from_model(model, joints=["j1"], geoms=["tip"])
    capsule, geom = robot.capsules[0], model.geom("tip").id
    assert capsule.body == model.body("l1").id
    data = mujoco.MjData(model)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * 0.01
    f1, f2 = model.joint("f1").qposadr[0], model.joint("f2").qposadr[0]
    for a in np.linspace(0.0, 0.6, 61):
        for b in np.linspace(0.0, 0.6, 61):
            data.qpos[[f1, f2]] = a, b
            mujoco.mj_kinematics(model, data)
            world = data.geom_xpos[geom] + corners @ data.geom_xmat[geom].reshape(3, 3).T
            local = (world - data.xpos[capsule.body]) @ data.xmat[capsule.body].reshape(3, 3)
            assert capsule.distance(local).max() <= 0.0


def test_gear_and_gain_scale_the_torque_limits_and_the_other_dofs_bounds():
    """A motor's joint torque is gear × gain × ctrl, and a force range bounds the actuator's force
    before its gear: the torque limit, write_ctrl and the other dofs' force bounds all say so."""
    xml = ARM.replace('<motor name="elbow" joint="elbow" ctrlrange="-20 20"/>',
                      '<general name="elbow" joint="elbow" gear="5" gainprm="3" ctrlrange="-1 1"/>').replace(
                      '<motor name="yaw" joint="yaw" ctrlrange="-40 40"/>',
                      '<motor name="yaw" joint="yaw" gear="10" forcerange="-2 2"/>')  # fmt: skip
    model = _model(xml)
    robot = RobotDescription.from_model(model, site="tool", joint_speed_limit=3.0)
    np.testing.assert_array_equal(robot.torque_limit, [20.0, 40.0, 15.0])
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    robot.write_ctrl(model, data, np.array([12.0, -30.0, 9.0]))
    mujoco.mj_step2(model, data)
    np.testing.assert_allclose(data.qfrc_actuator, [12.0, -30.0, 9.0])
    geared = GRIPPER_ARM.replace('<position name="finger_r" joint="finger_r" kp="200" ctrlrange="0 0.03" '
                                 'forcerange="-15 15"/>', '<motor name="finger_r" joint="finger_r" gear="10" '
                                 'forcerange="-2 2"/>')  # fmt: skip
    model = _model(geared)
    others = RobotDescription.from_model(model, joints=ARM_JOINTS, site="tool", joint_speed_limit=3.0)
    assert others.unmodelled_force[model.joint("finger_r").dofadr[0]] == 20.0  # gear 10 × force 2, no friction


def test_a_compiled_loop_of_ones_own_calls_the_filter_through_the_seam():
    """The seam of :mod:`c3bf_gym.safety.substep`, used as a simulator of one's own would: a numba
    function calling ``filter_substep`` with a ``compiled_call`` gets the torque and the report
    ``__call__`` gives from Python, bit for bit; ``failure`` names the exception of a status that
    stops the loop (a non-finite torque; no safe torque under ``on_infeasible="raise"``)."""
    from numba import njit

    from c3bf_gym.safety import FilterCall
    from c3bf_gym.safety.substep import filter_substep

    @njit
    def one_step(call, tau_nom, tau):
        return filter_substep(call.stage, tau_nom, tau, call.buffers)

    def controller(qvel=(0.5, -1.0, 0.7), **settings):
        model = _model()
        data = mujoco.MjData(model)
        data.qpos[:] = (0.3, -0.6, 0.9)
        data.qvel[:] = qvel
        mujoco.mj_forward(model, data)
        robot = RobotDescription.from_model(model, site="tool", joint_speed_limit=3.0)
        ball = Obstacles(1)  # kept by the caller (MocapSpheres refresh from the model: Python calls only)
        ball.position[0], ball.velocity[0], ball.radius[0], ball.active[0] = (0.45, 0.1, 0.75), (-0.2, 0.0, -0.4), 0.06, True
        return SafetyController(model, data, robot, ball, FilterConfig(sensing_radius=0.5, **settings))

    python, compiled = controller(), controller()
    tau_nom = python.data.qfrc_bias + np.array([0.0, 30.0, -15.0])  # the fore-arm pushed up into the ball
    expected = python(tau_nom)
    call = compiled.compiled_call(version=0)
    assert isinstance(call, FilterCall) and call.stage == 2 and not call.halt
    tau = np.empty(3)
    status = one_step(call, tau_nom.copy(), tau)
    assert status == 0 and compiled.failure(status) is None
    assert tau.tobytes() == expected.tobytes() and not np.allclose(tau, tau_nom)  # the filter changed it
    assert python.report.as_info() == compiled.report.as_info()
    assert python.report.solve_time > 0.0 and np.isnan(compiled.report.solve_time)  # compiled calls are not timed

    assert isinstance(compiled.failure(one_step(call, np.full(3, np.nan), tau)), ValueError)
    strict = controller(qvel=(0.0, -60.0, 60.0), on_infeasible="raise")  # far beyond the speed bound
    call = strict.compiled_call(version=0)
    assert call.halt
    status = one_step(call, strict.data.qfrc_bias.copy(), tau)
    assert status > 0 and isinstance(strict.failure(status), SafetyInfeasibleError)
