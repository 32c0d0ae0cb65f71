"""assets/panda.xml: the Franka Emika Panda, checked against the published numbers it was built from.

Every number is checked on the COMPILED model (what MuJoCo made of the XML), against the sources
assets/panda.xml cites: Franka's FCI documentation (DH table in Craig's convention, joint limits)
and Gaz et al., IEEE RA-L 2019 (identified link masses, centres of mass and inertia tensors).
"""

from __future__ import annotations

import importlib.util
import re
from importlib import resources
from pathlib import Path

import mujoco
import numpy as np
import pytest

from c3bf_gym.safety import RobotDescription, UnprotectedGeometryWarning

ROOT = Path(__file__).resolve().parents[1]
ASSETS = resources.files("c3bf_gym.assets")  # as installed

# FCI, "Robot and interface specifications": Craig's DH rows (a_{i-1}, d_i, alpha_{i-1}), joints 1-7 + flange.
DH = [(0.0, 0.333, 0.0), (0.0, 0.0, -np.pi / 2), (0.0, 0.316, np.pi / 2), (0.0825, 0.0, np.pi / 2),
      (-0.0825, 0.384, -np.pi / 2), (0.0, 0.0, np.pi / 2), (0.088, 0.0, np.pi / 2), (0.0, 0.107, 0.0)]  # fmt: skip
# FCI, "Limits for Panda".
Q_MIN = [-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973]
Q_MAX = [2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973]
SPEED = [2.1750] * 4 + [2.6100] * 3
TORQUE = [87.0] * 4 + [12.0] * 3
HOME = [0.0, -np.pi / 4, 0.0, -3 * np.pi / 4, 0.0, np.pi / 2, np.pi / 4]
# Gaz et al. 2019, supplementary tables VIII-IX: mass, CoM in DH frame i, barycentric inertia
# (Ixx, Ixy, Ixz, Iyy, Iyz, Izz).
GAZ = [
    (4.970684, (3.875e-3, 2.081e-3, 0.0), (7.0337e-1, -1.3900e-4, 6.7720e-3, 7.0661e-1, 1.9169e-2, 9.1170e-3)),
    (0.646926, (-3.141e-3, -2.872e-2, 3.495e-3), (7.9620e-3, -3.9250e-3, 1.0254e-2, 2.8110e-2, 7.0400e-4, 2.5995e-2)),
    (3.228604, (2.7518e-2, 3.9252e-2, -6.6502e-2), (3.7242e-2, -4.7610e-3, -1.1396e-2, 3.6155e-2, -1.2805e-2, 1.0830e-2)),
    (3.587895, (-5.317e-2, 1.04419e-1, 2.7454e-2), (2.5853e-2, 7.7960e-3, -1.3320e-3, 1.9552e-2, 8.6410e-3, 2.8323e-2)),
    (1.225946, (-1.1953e-2, 4.1065e-2, -3.8437e-2), (3.5549e-2, -2.1170e-3, -4.0370e-3, 2.9474e-2, 2.2900e-4, 8.6270e-3)),
    (1.666555, (6.0149e-2, -1.4117e-2, -1.0517e-2), (1.9640e-3, 1.0900e-4, -1.1580e-3, 4.3540e-3, 3.4100e-4, 5.4330e-3)),
    (0.735522, (1.0517e-2, -4.252e-3, 6.1597e-2), (1.2516e-2, -4.2800e-4, -1.1960e-3, 1.0027e-2, -7.4100e-4, 4.8150e-3)),
]
LINKS = [f"link{i}" for i in range(1, 8)]
CAPSULES = LINKS + ["hand"]


def _load(name: str = "panda.xml") -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(ASSETS / name))


def _speed_limit(model: mujoco.MjModel) -> np.ndarray:
    numeric = model.numeric("joint_speed_limit")
    return model.numeric_data[numeric.adr[0]:numeric.adr[0] + numeric.size[0]].copy()


def _dh_frames(q) -> list[np.ndarray]:
    """World poses of DH frames 1-7 and the flange (Craig: Rx(alpha) Tx(a) Rz(q) Tz(d))."""

    def rx(t):
        c, s = np.cos(t), np.sin(t)
        return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])

    def rz(t):
        c, s = np.cos(t), np.sin(t)
        return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])

    def trans(x, z):
        out = np.eye(4)
        out[0, 3], out[2, 3] = x, z
        return out

    pose, frames = np.eye(4), []
    for (a, d, alpha), qi in zip(DH, list(q) + [0.0]):
        pose = pose @ rx(alpha) @ trans(a, 0.0) @ rz(qi) @ trans(0.0, d)
        frames.append(pose)
    return frames


@pytest.mark.parametrize("name", ["panda.xml", "panda_scene.xml"])
def test_loads(name):
    model = _load(name)
    assert (model.nq, model.nv, model.nu) == (7, 7, 7)
    assert model.key("home").id == 0


def test_home_is_held_by_gravity_compensation():
    """1 s from home with zero ctrl: MuJoCo's gravity compensation holds the arm, without warnings."""
    model = _load("panda_scene.xml")
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("home").id)
    np.testing.assert_allclose(data.qpos, HOME, atol=1e-8)
    data.ctrl[:] = 0.0
    for _ in range(int(round(1.0 / model.opt.timestep))):
        mujoco.mj_step(model, data)
    assert all(w.number == 0 for w in data.warning), [(i, w.number) for i, w in enumerate(data.warning) if w.number]
    assert np.abs(data.qpos - HOME).max() < 1e-3
    assert np.abs(data.qvel).max() < 1e-3
    assert data.ncon == 0


def test_masses_centres_and_inertias_are_gaz_et_al():
    model = _load()
    link1 = model.body("link1").id
    assert model.body_subtreemass[link1] == pytest.approx(16.062132, abs=1e-9)
    for name, (mass, com, (ixx, ixy, ixz, iyy, iyz, izz)) in zip(LINKS, GAZ):
        body = model.body(name)
        assert body.mass[0] == pytest.approx(mass, abs=1e-9), name
        np.testing.assert_allclose(body.ipos, com, atol=1e-9, err_msg=name)
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, body.iquat)
        rot = rot.reshape(3, 3)
        tensor = rot @ np.diag(body.inertia) @ rot.T  # the compiled tensor in the body (= DH) frame
        expected = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
        np.testing.assert_allclose(tensor, expected, atol=1e-9, err_msg=name)
    assert model.body("hand").mass[0] == 0.0  # the hand adds no mass (assets/panda.xml says why)


def test_limits_are_franka_fci():
    model = _load()
    for j, name in enumerate(f"joint{i}" for i in range(1, 8)):
        joint = model.joint(name)
        assert joint.limited[0], name
        np.testing.assert_allclose(joint.range, [Q_MIN[j], Q_MAX[j]], atol=0, err_msg=name)
        np.testing.assert_allclose(model.jnt_actfrcrange[joint.id], [-TORQUE[j], TORQUE[j]], atol=0, err_msg=name)
        assert model.jnt_actfrclimited[joint.id] and model.jnt_actgravcomp[joint.id], name
    np.testing.assert_allclose(_speed_limit(model), SPEED, atol=0)
    assert np.all(model.actuator_gear[:, 0] == 1.0)
    assert np.all(model.body_gravcomp[[model.body(n).id for n in LINKS]] == 1.0)


@pytest.mark.parametrize("q", [np.zeros(7), HOME, [0.5, -0.7, 1.1, -1.9, -0.8, 2.2, -1.3]])
def test_frames_follow_the_dh_table(q):
    """Every link body is its DH frame (position and orientation), so the joint axes match too."""
    model = _load()
    data = mujoco.MjData(model)
    data.qpos[:] = q
    mujoco.mj_kinematics(model, data)
    for name, pose in zip(LINKS + ["flange"], _dh_frames(q)):
        body = model.body("hand" if name == "flange" else name).id
        np.testing.assert_allclose(data.xpos[body], pose[:3, 3], atol=1e-9, err_msg=name)
        if name != "flange":  # the hand is mounted turned by -pi/4 about the flange's z axis
            np.testing.assert_allclose(data.xmat[body].reshape(3, 3), pose[:3, :3], atol=1e-8, err_msg=name)
        else:
            np.testing.assert_allclose(data.xmat[body].reshape(3, 3)[:, 2], pose[:3, 2], atol=1e-8)
    for j in range(7):
        np.testing.assert_allclose(data.xaxis[j], _dh_frames(q)[j][:3, 2], atol=1e-8)


def test_flange_at_zero_is_franka_convention():
    """q = 0: flange at x = a4 + a5 + a7 = 0.088, z = d1 + d3 + d5 - d_flange = 0.926 m, pointing down."""
    model = _load()
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    hand = model.body("hand").id
    np.testing.assert_allclose(data.xpos[hand], [0.088, 0.0, 0.926], atol=1e-12)
    np.testing.assert_allclose(data.xmat[hand].reshape(3, 3)[:, 2], [0.0, 0.0, -1.0], atol=1e-12)
    # the segment lengths the DH table gives, between joint origins
    joint = [data.xanchor[model.joint(f"joint{i}").id] for i in range(1, 8)]
    assert joint[0][2] == pytest.approx(0.333)
    assert np.linalg.norm(joint[2] - joint[1]) == pytest.approx(0.316)
    assert np.linalg.norm(joint[4] - joint[3]) == pytest.approx(np.hypot(0.0825, 0.384))


def test_home_is_in_front_above_the_table_without_contacts():
    model = _load("panda_scene.xml")
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("home").id)
    mujoco.mj_forward(model, data)
    assert data.ncon == 0
    tool = data.site_xpos[model.site("ee_site").id]
    assert tool[0] > 0.25 and abs(tool[1]) < 1e-9 and 0.3 < tool[2] < 0.7, tool
    for name in CAPSULES:  # every moving capsule clears the floor
        geom = model.geom(name).id
        assert mujoco.mj_geomDistance(model, data, geom, model.geom("floor").id, 1.0, None) > 0.0, name


def test_scene_keeps_the_ur5e_scene_obstacles():
    """panda_scene.xml has scene.xml's goal and obstacles, identical, so the env can take either arm."""
    panda, ur5e = _load("panda_scene.xml"), _load("scene.xml")
    assert panda.opt.timestep == ur5e.opt.timestep and panda.opt.integrator == ur5e.opt.integrator
    for name in ["goal", "floor"] + [f"obstacle_{i}" for i in range(8)]:
        a, b = panda.geom(name), ur5e.geom(name)
        for field in ("type", "size", "contype", "conaffinity", "rgba"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=f"{name}.{field}")
        if name != "floor":
            assert panda.body(name).mocapid[0] >= 0
            np.testing.assert_array_equal(panda.body(name).pos, ur5e.body(name).pos)
    assert panda.camera("overview").id >= 0


def test_robot_description_accepts_the_panda():
    model = _load("panda_scene.xml")
    with pytest.warns(UnprotectedGeometryWarning, match=r"geom 'link1' lies on the axis of the joints that move it"):
        robot = RobotDescription.from_model(model, site="ee_site", joint_speed_limit=_speed_limit(model))
    assert robot.n == 7
    np.testing.assert_array_equal(robot.torque_limit, TORQUE)
    # every capsule but link1's, which lies on joint 1's axis (it only turns about itself)
    assert sorted(model.geom(g).name for g in robot.geom_ids) == sorted(CAPSULES[1:])
    assert robot.site_id == model.site("ee_site").id
    np.testing.assert_allclose(robot.joint_range, np.column_stack([Q_MIN, Q_MAX]))
    np.testing.assert_allclose(robot.joint_speed_limit, SPEED)


def test_example_keeps_the_ball_off_the_panda(capsys):
    """examples/own_arm.py on the Panda, as tests/test_examples.py runs it on the UR5e: without the
    filter the ball hits the arm; with it, it does not (mj_geomDistance). The default --move (0.3 m
    sideways, 0.1 m down from home) is reachable and collision-free for the Panda."""
    spec = importlib.util.spec_from_file_location("own_arm", ROOT / "examples" / "own_arm.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    argv = [str(ASSETS / "panda.xml"), "--site", "ee_site", "--joint-speed-limit", "2.175"]
    assert module.main(argv) == 0
    out = capsys.readouterr().out
    assert "7 joints, protecting link2, link3, link4, link5, link6, link7, hand" in out
    clearance = {k: float(v) for k, v in re.findall(r"(unfiltered|filtered)\s*: lowest clearance ([-+\d.]+) mm", out)}
    assert clearance["unfiltered"] < 0.0, out
    assert clearance["filtered"] > 0.0, out
    assert re.search(r"filtered\s*: .* \d+ interventions, 0 infeasible", out)
