"""The capsules the filter protects in place of a model's geoms (c3bf_gym.safety.geometry), and
the filter on an arm whose links are a box, a cylinder and a mesh.

Containment is judged by MuJoCo's own ``mj_geomDistance`` between the geom and probe spheres,
independently of the fitting code."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from c3bf_gym.safety import (
    Capsule,
    FilterConfig,
    MocapSpheres,
    RobotDescription,
    SafetyController,
    UnprotectedGeometryWarning,
    UnsupportedGeomError,
    capsule_distances,
    enclosing_capsule,
    fit_capsule,
)
from c3bf_gym.safety.dynamics import ArmModel

#: An irregular convex mesh, longer along a tilted axis (vertices in the mesh file's own frame:
#: MuJoCo re-centres and aligns them, the geom frame moves with them).
_MESH = " ".join(f"{x:.4f}" for x in (np.random.default_rng(3).normal(size=(40, 3)) * (0.15, 0.04, 0.03)
                                      @ np.linalg.qr(np.random.default_rng(4).normal(size=(3, 3)))[0]).ravel())

#: A 3-joint arm whose protected links are a box, a cylinder and a mesh, with a fixed base box,
#: a mocap probe (no contacts: distances are measured) and a floor.
ARM = f"""
<mujoco model="shapes">
  <compiler angle="radian"/>
  <option timestep="0.002"/>
  <asset><mesh name="blob" vertex="{_MESH}"/></asset>
  <worldbody>
    <geom name="floor" type="plane" size="2 2 0.1"/>
    <geom name="plinth" type="box" size="0.1 0.1 0.04" pos="0 0 0.04"/>  <!-- clear of the post: no contact -->
    <body name="base" pos="0 0 0.1">
      <joint name="yaw" axis="0 0 1" range="-3 3" damping="1" frictionloss="0.5"/>
      <geom name="post" type="box" size="0.05 0.05 0.15" pos="0.1 0 0.15" mass="2"/>
      <body name="upper" pos="0.1 0 0.3">
        <joint name="shoulder" axis="0 1 0" range="-2 2" damping="1" armature="0.05"/>
        <geom name="upper" type="cylinder" fromto="0 0 0 0.4 0 0" size="0.04" mass="1.5"/>
        <body name="fore" pos="0.4 0 0">
          <joint name="elbow" axis="0 1 0" range="-2.5 2.5" damping="0.5" frictionloss="0.3"/>
          <geom name="fore" type="mesh" mesh="blob" pos="0.18 0 0" euler="0.3 0.2 0.1" mass="1"/>
          <geom name="cosmetic" type="sphere" size="0.02" pos="0.3 0 0" contype="0" conaffinity="0"/>
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
    <motor name="shoulder" joint="shoulder" gear="2" ctrlrange="-20 20"/>
    <motor name="elbow" joint="elbow" ctrlrange="-20 20"/>
  </actuator>
</mujoco>
"""


def _model() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_string(ARM)


def _probe_gaps(model, data, geom, probes) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo's distances from tiny spheres at ``probes`` (P, 3) (world) to ``geom``, and the
    distances from the same points to the geom's enclosing capsule as ArmModel places it."""
    spec = mujoco.MjSpec.from_string(ARM)
    body = spec.worldbody.add_body(name="probe", mocap=True)
    body.add_geom(name="probe", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[1e-4, 0, 0], contype=0, conaffinity=0)
    probe_model = spec.compile()
    probe_data = mujoco.MjData(probe_model)
    probe_data.qpos[:] = data.qpos
    arm = ArmModel(model, np.array([geom]), -1)
    exact, capsule = [], []
    for point in probes:
        probe_data.mocap_pos[probe_model.body("probe").mocapid[0]] = point
        mujoco.mj_forward(probe_model, probe_data)
        exact.append(mujoco.mj_geomDistance(probe_model, probe_data, probe_model.geom("probe").id, geom, 2.0, None))
        a, b = arm.capsule_segments(probe_data)
        ab = b[0] - a[0]
        t = np.clip((point - a[0]) @ ab / (ab @ ab), 0.0, 1.0) if ab @ ab > 0 else 0.0
        capsule.append(np.linalg.norm(point - (a[0] + t * ab)) - arm.capsule_radius[0])
    return np.array(exact) + 1e-4, np.array(capsule)


@pytest.mark.parametrize("name", ["post", "upper", "fore"])
def test_enclosing_capsules_contain_the_geom_as_mujoco_measures_it(name):
    """Every probe point is at least as close to the capsule as to the geom itself (so the capsule
    contains the geom), and the capsule is not loose: at most 2.5 times the volume of the geom's
    bounding box."""
    model = _model()
    data = mujoco.MjData(model)
    data.qpos[:] = (0.4, -0.7, 1.1)
    mujoco.mj_forward(model, data)
    geom = model.geom(name).id
    rng = np.random.default_rng(0)
    centre = data.geom_xpos[geom]
    directions = rng.normal(size=(60, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    probes = centre + directions * rng.uniform(0.05, 0.4, size=(60, 1))
    exact, capsule = _probe_gaps(model, data, geom, probes)
    outside = exact > 1e-6
    assert outside.sum() > 30
    # the capsule holds the geom: no probe outside the geom is farther from the capsule than from the geom
    assert np.all(capsule[outside] <= exact[outside] + 1e-6)
    capsule_volume = enclosing_capsule(model, geom).volume()
    assert capsule_volume <= 2.5 * np.prod(2 * model.geom_aabb[geom, 3:])


def test_primitives_are_enclosed_as_documented():
    model = _model()
    box = enclosing_capsule(model, model.geom("post").id)
    corners = np.array([[x, y, z] for x in (-0.05, 0.05) for y in (-0.05, 0.05) for z in (-0.15, 0.15)])
    assert box.source == "box" and box.distance(corners).max() <= 1e-9
    assert np.hypot(0.05, 0.05) <= box.radius < 0.08 and abs(box.b - box.a)[:2].max() < 1e-9  # along the long axis
    cylinder = enclosing_capsule(model, model.geom("upper").id)
    assert cylinder.source == "cylinder" and cylinder.radius == 0.04 and cylinder.half_length == pytest.approx(0.2)
    sphere = enclosing_capsule(model, model.geom("cosmetic").id)
    assert sphere.source == "sphere" and sphere.half_length == 0.0 and sphere.radius == 0.02
    mesh = model.geom("fore").id
    vertices = model.mesh_vert[model.mesh_vertadr[0] : model.mesh_vertadr[0] + model.mesh_vertnum[0]]
    fitted = enclosing_capsule(model, mesh)
    assert fitted.source == "mesh" and fitted.distance(vertices).max() <= 1e-9
    # a link-shaped point set: the capsule runs along it, a few times thinner than long
    assert fitted.half_length > 2 * fitted.radius
    with pytest.raises(UnsupportedGeomError, match=r"geom 'floor' is a plane: it has no enclosing capsule"):
        enclosing_capsule(model, model.geom("floor").id)


def test_capsule_distances_are_mujocos_for_capsules_and_spheres():
    """Signed distances from points to capsule surfaces (a sphere being a segment of length 0),
    for any leading shape of the points, against MuJoCo's ``mj_geomDistance`` from tiny spheres."""
    spec = mujoco.MjSpec.from_string("""
    <mujoco><worldbody>
      <geom name="a" type="capsule" fromto="0 0 0 0.3 0.1 0.2" size="0.05"/>
      <geom name="b" type="sphere" pos="-0.2 0.1 0.4" size="0.07"/>
      <body name="probe" mocap="true"><geom name="probe" type="sphere" size="1e-4" contype="0" conaffinity="0"/></body>
    </worldbody></mujoco>""")
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    a = np.array([[0.0, 0.0, 0.0], [-0.2, 0.1, 0.4]])
    b = np.array([[0.3, 0.1, 0.2], [-0.2, 0.1, 0.4]])
    points = np.random.default_rng(0).uniform(-0.4, 0.6, size=(4, 5, 3))
    points[0, 0] = (0.15, 0.05, 0.1)  # on the first axis: inside
    ours = capsule_distances(points, a, b, np.array([0.05, 0.07]))
    assert ours.shape == (4, 5, 2) and ours[0, 0, 0] == pytest.approx(-0.05)
    for index in np.ndindex(4, 5):
        data.mocap_pos[0] = points[index]
        mujoco.mj_forward(model, data)
        for g, name in enumerate("ab"):
            exact = mujoco.mj_geomDistance(model, data, model.geom("probe").id, model.geom(name).id, 2.0, None)
            if exact > 0.0:  # MuJoCo's penetration depth is not the distance to the axis's capsule
                assert ours[index][g] == pytest.approx(exact + 1e-4, abs=1e-9)
            else:
                assert ours[index][g] <= 1e-4


def test_fit_capsule_holds_every_point_and_refuses_bad_input():
    rng = np.random.default_rng(1)
    for scale in ((1.0, 0.1, 0.1), (0.2, 0.2, 0.2), (0.5, 0.3, 0.01)):
        points = rng.normal(size=(200, 3)) * scale
        capsule = fit_capsule(points)
        assert isinstance(capsule, Capsule) and capsule.distance(points).max() <= 1e-9
    single = fit_capsule(np.array([[1.0, 2.0, 3.0]]))
    assert single.distance(np.array([[1.0, 2.0, 3.0]]))[0] <= 1e-9
    for bad in (np.zeros((0, 3)), np.zeros((4, 2)), np.array([[0.0, np.nan, 0.0]])):
        with pytest.raises(ValueError, match=r"finite points of shape \(P, 3\)"):
            fit_capsule(bad)


def test_default_selection_protects_every_colliding_shape_and_names_what_it_leaves():
    model = _model()
    robot = RobotDescription.from_model(model, site="tool", joint_speed_limit=3.0)
    assert [model.geom(g).name for g in robot.geom_ids] == ["post", "upper", "fore"]  # not the fixed plinth
    assert [c.source for c in robot.capsules] == ["box", "cylinder", "mesh"]
    table = robot.describe(model)
    assert "fore" in table and "mesh" in table and len(table.splitlines()) == 4
    data = mujoco.MjData(model)
    data.qpos[:] = (0.4, -0.7, 1.1)
    mujoco.mj_kinematics(model, data)
    a, b, radius = robot.capsule_segments(data)  # in world coordinates, as the filter places them
    a2, b2 = ArmModel(model, robot.geom_ids, -1).capsule_segments(data)
    np.testing.assert_array_equal(a, a2)
    np.testing.assert_array_equal(b, b2)
    np.testing.assert_array_equal(radius, [c.radius for c in robot.capsules])
    # a moving body whose geoms all have collisions off is named, with the reason
    xml = ARM.replace('<geom name="post" type="box" size="0.05 0.05 0.15" pos="0.1 0 0.15" mass="2"/>',
                      '<geom name="post" type="box" size="0.05 0.05 0.15" pos="0.1 0 0.15" mass="2" contype="0" '
                      'conaffinity="0"/>')  # fmt: skip
    with pytest.warns(UnprotectedGeometryWarning, match=r"bodies 'base' move with the arm but none of their geoms"):
        robot = RobotDescription.from_model(mujoco.MjModel.from_xml_string(xml))
    assert "post" not in [mujoco.MjModel.from_xml_string(xml).geom(g).name for g in robot.geom_ids]


def test_write_ctrl_applies_the_joint_torque():
    """write_ctrl divides by the gear and leaves other actuators alone; MuJoCo then applies exactly
    the requested joint torque. Out-of-range controls and bad torques are refused by name."""
    model = _model()
    data = mujoco.MjData(model)
    robot = RobotDescription.from_model(model, site="tool", joint_speed_limit=3.0)
    mujoco.mj_forward(model, data)
    tau = np.array([10.0, -30.0, 5.0])
    robot.write_ctrl(model, data, tau)
    np.testing.assert_allclose(data.ctrl, [10.0, -15.0, 5.0])  # the shoulder's gear is 2
    mujoco.mj_step2(model, data)
    np.testing.assert_allclose(data.qfrc_actuator, tau)
    with pytest.raises(ValueError, match=r"actuator 'shoulder' would need ctrl -25.*ctrlrange"):
        robot.write_ctrl(model, data, np.array([0.0, -50.0, 0.0]))
    with pytest.raises(ValueError, match=r"tau must be 3 finite joint torques"):
        robot.write_ctrl(model, data, np.array([0.0, np.nan, 0.0]))


def test_filter_before_the_dynamics_are_computed_is_refused():
    model = _model()
    data = mujoco.MjData(model)
    robot = RobotDescription.from_model(model, site="tool", joint_speed_limit=3.0)
    controller = SafetyController(model, data, robot, MocapSpheres(model, ["ball"]))
    with pytest.raises(RuntimeError, match=r"call mujoco.mj_forward\(model, data\)"):
        controller.filter(np.zeros(3))
    mujoco.mj_forward(model, data)
    tau, report = controller.filter(np.zeros(3))
    assert report.feasible and tau.shape == (3,)


def test_friction_loss_tightens_every_row_by_its_worst_case():
    """Dry friction is a force of at most ``frictionloss`` per dof that the rows cannot predict: each
    obstacle and floor row's bound rises by ``Σ_j |A_kj| f_j``, the same in the compiled and the
    per-class rows; the joint-limit rows are left as they are."""
    model = _model()
    data = mujoco.MjData(model)
    data.qpos[:] = (0.3, -0.6, 0.9)
    data.qvel[:] = (0.5, -1.0, 0.7)
    data.mocap_pos[0] = (0.45, 0.1, 0.75)
    mujoco.mj_forward(model, data)
    robot = RobotDescription.from_model(model, site="tool", joint_speed_limit=3.0)
    balls = MocapSpheres(model, ["ball"])
    balls.velocity[0] = (-0.2, 0.0, -0.4)
    config = FilterConfig(sensing_radius=0.5)
    A, b, *_ = (x.copy() for x in SafetyController(model, data, robot, balls, config).rows()[:2])
    frictionless = _model()
    frictionless.dof_frictionloss[:] = 0.0
    robot0 = RobotDescription.from_model(frictionless, site="tool", joint_speed_limit=3.0)
    np.testing.assert_array_equal(robot.unmodelled_force, model.dof_frictionloss)
    np.testing.assert_array_equal(robot0.unmodelled_force, 0.0)
    A0, b0, *_ = SafetyController(frictionless, data, robot0, balls, config).rows()
    np.testing.assert_array_equal(A, A0)
    joint_rows = 4 * robot.n  # the last rows: a joint's own friction never drives it towards a limit
    np.testing.assert_allclose(b[:-joint_rows], b0[:-joint_rows] + np.abs(A0[:-joint_rows]) @ model.dof_frictionloss,
                               rtol=0, atol=1e-12)  # fmt: skip
    np.testing.assert_array_equal(b[-joint_rows:], b0[-joint_rows:])
    generic = SafetyController(model, data, robot, balls, config)
    generic._fused = False
    A2, b2, *_ = generic.rows()
    np.testing.assert_allclose(b2, b, rtol=0, atol=1e-9 * np.abs(b).max())


def test_filter_keeps_a_falling_ball_off_links_of_every_shape():
    """The arm is pulled up towards a ball that falls onto it at 1 m/s: unfiltered they collide, the
    filter keeps the ball off the box, the cylinder and the mesh (MuJoCo's distances)."""
    lowest = {}
    for filtered in (False, True):
        model = _model()
        data = mujoco.MjData(model)
        data.qpos[:] = (0.0, -0.3, 0.4)
        data.mocap_pos[0] = (0.6, 0.0, 1.2)
        mujoco.mj_forward(model, data)
        robot = RobotDescription.from_model(model, site="tool", joint_speed_limit=3.0)
        balls = MocapSpheres(model, ["ball"])
        controller = SafetyController(model, data, robot, balls)
        ball = model.geom("ball").id
        lowest[filtered] = np.inf
        for _ in range(750):
            mujoco.mj_step1(model, data)
            lowest[filtered] = min(lowest[filtered], *(mujoco.mj_geomDistance(model, data, ball, g, 1.0, None)
                                                       for g in robot.geom_ids))  # fmt: skip
            tau = np.clip(60.0 * (np.array([0.0, -1.2, 0.0]) - data.qpos) - 8.0 * data.qvel + data.qfrc_bias,
                          -robot.torque_limit, robot.torque_limit)  # fmt: skip
            if filtered:
                balls.velocity[0] = (0.0, 0.0, -1.0)
                tau, _ = controller.filter(tau)
            robot.write_ctrl(model, data, tau)
            mujoco.mj_step2(model, data)
            data.mocap_pos[0] += model.opt.timestep * np.array([0.0, 0.0, -1.0])
    assert lowest[False] < 0.0, lowest  # the scene is a real threat
    assert lowest[True] > 0.0, lowest
