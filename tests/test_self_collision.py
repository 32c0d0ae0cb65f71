"""The arm against itself: pairs of its capsules that the model lets collide get barrier rows
(``FilterConfig.self_collision``, :class:`~c3bf_gym.safety.barriers.SelfCollision`).

Distances are judged by MuJoCo's own ``mj_geomDistance`` and accelerations by its Jacobians, not
by the filter's kernels."""

from __future__ import annotations

import warnings

import mujoco
import numpy as np
import pytest

from c3bf_gym.safety import (FilterConfig, MocapSpheres, RobotDescription, SafetyController,
                              UnprotectedGeometryWarning)
from c3bf_gym.safety.barriers import SelfCollision
from c3bf_gym.safety.dynamics import ArmModel

#: A planar three-link arm, no gravity: folded at the elbow and the wrist, the hand meets the
#: upper arm (not its parent, so MuJoCo lets them collide). One mocap ball, far away.
FOLDING = """
<mujoco model="folding_arm">
  <compiler angle="radian"/>
  <option timestep="0.002" gravity="0 0 0"/>
  <worldbody>
    <body name="upper" pos="0 0 0.5">
      <joint name="shoulder" axis="0 1 0" range="-1 1" damping="0.5"/>
      <geom name="upper" type="capsule" fromto="0 0 0 0.4 0 0" size="0.04" mass="1.5"/>
      <body name="fore" pos="0.4 0 0">
        <joint name="elbow" axis="0 1 0" range="-3 3" damping="0.2"/>
        <geom name="fore" type="capsule" fromto="0 0 0 0.3 0 0" size="0.035" mass="1"/>
        <body name="hand" pos="0.3 0 0">
          <joint name="wrist" axis="0 1 0" range="-3 3" damping="0.1"/>
          <geom name="hand" type="capsule" fromto="0 0 0 0.25 0 0" size="0.03" mass="0.5"/>
          <site name="tool" pos="0.25 0 0"/>
        </body>
      </body>
    </body>
    <body name="ball" mocap="true" pos="3 0 3">
      <geom name="ball" type="sphere" size="0.05" contype="0" conaffinity="0"/>
    </body>
  </worldbody>
  <actuator>
    <motor name="shoulder" joint="shoulder" ctrlrange="-30 30"/>
    <motor name="elbow" joint="elbow" ctrlrange="-30 30"/>
    <motor name="wrist" joint="wrist" ctrlrange="-15 15"/>
  </actuator>
</mujoco>
"""
FOLDED = np.array([0.0, -2.9, -2.0])  # a PD target whose links would intersect


def _arm(xml: str = FOLDING):
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return model, data, RobotDescription.from_model(model, site="tool", joint_speed_limit=4.0)


def _pair_names(model, robot, pairs):
    names = [model.geom(int(g)).name for g in robot.geom_ids]
    return sorted(tuple(sorted((names[i], names[j]))) for i, j in pairs)


def test_pairs_follow_mujocos_collision_rules():
    """A pair gets a row when MuJoCo would let its geoms collide and the arm's joints can move
    them relative to each other: not parent and child, not excluded, not filtered by
    contype/conaffinity, unless named in a <pair>; never two geoms the same joints move."""
    def xml(extra_geom="", contact=""):
        return FOLDING.replace('<site name="tool"', extra_geom + '<site name="tool"').replace(
            "</worldbody>", "</worldbody>" + contact)

    model, _, robot = _arm(xml())
    arm = ArmModel(model, robot.geom_ids, robot.site_id, robot.capsules)
    rows = SelfCollision.of_model(model, arm, 0.02, 10.0)
    assert _pair_names(model, robot, rows.pairs) == [("hand", "upper")]  # fore-upper, hand-fore: parent and child
    radius = arm.capsule_radius
    np.testing.assert_allclose(rows.min_distance, [radius[0] + radius[2] + 0.02])

    knuckle = '<geom name="knuckle" type="sphere" size="0.03" pos="0.1 0 0"/>'  # on the hand's body: moved as it
    cases = {
        "excluded": (xml(contact='<contact><exclude body1="upper" body2="hand"/></contact>'), []),
        "contype": (xml().replace('name="hand" type="capsule"',
                                  'name="hand" type="capsule" contype="2" conaffinity="2"'), []),
        "pair": (xml(contact='<contact><pair geom1="fore" geom2="upper"/></contact>'),
                 [("fore", "upper"), ("hand", "upper")]),
        "same joints": (xml(knuckle), [("hand", "upper"), ("knuckle", "upper")]),
    }
    for name, (text, want) in cases.items():
        model, _, robot = _arm(text)
        arm = ArmModel(model, robot.geom_ids, robot.site_id, robot.capsules)
        assert _pair_names(model, robot, SelfCollision.of_model(model, arm, 0.02, 10.0).pairs) == want, name


def test_rows_match_mujocos_distance_and_jacobians():
    """At rest, without gravity, a pair's row is ``nᵀ (J₁ − J₂) (M + h D)⁻¹ τ ≥ −γ² (d − margin)``
    with ``d``, ``n`` and the closest points from ``mj_geomDistance`` and the Jacobians from
    ``mj_jac``."""
    model, data, robot = _arm()
    data.qpos[:] = [0.2, -2.6, -0.4]  # the hand 85 mm from the upper arm
    mujoco.mj_forward(model, data)
    spheres = MocapSpheres(model, ["ball"])
    controller = SafetyController(model, data, robot, spheres, FilterConfig(sensing_radius=0.5))
    A, b, *_ = controller.rows()
    kinds = controller.row_kinds(len(b))
    k = kinds.index("self_collision")
    assert kinds.count("self_collision") == 1
    gamma = controller.config.floor_gamma
    hand, upper = model.geom("hand").id, model.geom("upper").id
    fromto = np.zeros(6)
    gap = mujoco.mj_geomDistance(model, data, hand, upper, 1.0, fromto)
    assert 0.0 < gap < 0.2
    np.testing.assert_allclose(b[k], -gamma**2 * (gap - controller.config.margin), rtol=1e-9)
    normal = (fromto[:3] - fromto[3:]) / np.linalg.norm(fromto[:3] - fromto[3:])  # from upper to hand
    jac_hand, jac_upper = np.zeros((3, model.nv)), np.zeros((3, model.nv))
    mujoco.mj_jac(model, data, jac_hand, None, fromto[:3], model.body("hand").id)
    mujoco.mj_jac(model, data, jac_upper, None, fromto[3:], model.body("upper").id)
    mass = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, mass)
    mass += np.diag(model.opt.timestep * model.dof_damping)  # the Euler integrator's implicit damping
    want = normal @ (jac_hand - jac_upper) @ np.linalg.inv(mass)
    np.testing.assert_allclose(A[k], want, rtol=1e-7, atol=1e-9)


def _fold(config: FilterConfig | None) -> tuple[float, float]:
    """Drive the folding arm at ``FOLDED`` for 3 s: the lowest hand-to-upper-arm distance by
    ``mj_geomDistance`` [m] and the largest reported self-collision violation."""
    model, data, robot = _arm()
    controller = None
    if config is not None:
        controller = SafetyController(model, data, robot, MocapSpheres(model, ["ball"]), config)
    hand, upper = model.geom("hand").id, model.geom("upper").id
    lowest, violation = np.inf, 0.0
    for _ in range(1500):
        mujoco.mj_step1(model, data)
        tau = np.clip(60.0 * (FOLDED - data.qpos) - 5.0 * data.qvel, -robot.torque_limit, robot.torque_limit)
        if controller is not None:
            tau, report = controller.filter(tau)
            violation = max(violation, report.violation["self_collision"])
        robot.write_ctrl(model, data, tau)
        mujoco.mj_step2(model, data)
        lowest = min(lowest, mujoco.mj_geomDistance(model, data, hand, upper, 1.0, None))
    return lowest, violation


@pytest.mark.parametrize("path", ["fused", "per-class"])
def test_the_filter_keeps_a_folding_arm_off_itself(path):
    """Unfiltered, or with ``self_collision=False``, the hand hits the upper arm; with the rows it
    stays clear, every row held. The per-class path (a user's own barrier instance) adds the same
    rows."""
    from c3bf_gym.safety.barriers import C3BF

    lowest, _ = _fold(None)
    assert lowest < 0.0
    barrier = "c3bf" if path == "fused" else C3BF()
    lowest, _ = _fold(FilterConfig(barrier=barrier, sensing_radius=1.0, self_collision=False))
    assert lowest < 0.0
    lowest, violation = _fold(FilterConfig(barrier=barrier, sensing_radius=1.0))
    # the margin is 20 mm; the closest points' turning, left out of the rows, costs a few mm at speed
    assert lowest > 0.01
    assert violation == 0.0


def test_a_protected_geom_resting_on_the_arms_base_is_named():
    """A protected geom that touches a geom of its own arm no row keeps it from (the base, welded
    to the world, so MuJoCo collides it with its child) is warned about by name, with the
    exclusion that would remove the contact; an excluded pair is not."""
    base = ('<body name="base" pos="0 0 0.5"><geom name="plinth" type="sphere" size="0.05" pos="0.1 0 -0.09"/>'
            '<body name="upper" pos="0 0 0">')
    xml = FOLDING.replace('<body name="upper" pos="0 0 0.5">', base)
    xml = xml.replace('<body name="ball"', '</body><body name="ball"')  # the base's own end
    model, data, robot = _arm(xml)
    spheres = MocapSpheres(model, ["ball"])
    with pytest.warns(UnprotectedGeometryWarning, match=r"geom 'upper' touches geom 'plinth' of the same arm"
                      r".*<exclude body1=\"upper\" body2=\"base\"/>"):
        SafetyController(model, data, robot, spheres, FilterConfig(sensing_radius=1.0))
    excluded = xml.replace("</worldbody>", '</worldbody><contact><exclude body1="base" body2="upper"/></contact>')
    model, data, robot = _arm(excluded)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UnprotectedGeometryWarning)
        SafetyController(model, data, robot, MocapSpheres(model, ["ball"]), FilterConfig(sensing_radius=1.0))


@pytest.mark.parametrize("pairs, min_distance, gamma, message", [
    ([[0, 1, 2]], [0.1], 10.0, r"pairs must have shape \(P, 2\)"),
    ([[0, 0]], [0.1], 10.0, r"two different capsule indices"),
    ([[-1, 1]], [0.1], 10.0, r"two different capsule indices"),
    ([[0, 1]], [[0.1]], 10.0, r"min_distance must have shape \(P,\)"),
    ([[0, 1]], [0.1, 0.2], 10.0, r"min_distance must have shape \(P,\)"),
    ([[0, 1]], [float("nan")], 10.0, r"min_distance must be finite and >= 0"),
    ([[0, 1]], [0.1], 0.0, r"gamma"),
])
def test_bad_pairs_are_refused_by_name(pairs, min_distance, gamma, message):
    with pytest.raises(ValueError, match=message):
        SelfCollision(pairs, min_distance, gamma)


def test_a_pair_beyond_the_arms_capsules_is_refused():
    rows = SelfCollision([[0, 3]], [0.1], 10.0)
    with pytest.raises(ValueError, match=r"pairs name capsule 3, but packed_ends holds 3 capsules"):
        rows.rows(np.zeros((6, 3, 3 + 3)))
    assert SelfCollision((), (), 10.0).rows(np.zeros((6, 3, 6))).A.shape == (0, 3)


def test_the_filter_keeps_the_links_off_a_fixed_part_of_the_arm():
    """A geom on the arm's base (no joint moves it, so it is not protected against obstacles) is
    a partner of every capsule MuJoCo collides it with: the folding arm, which sweeps its forearm
    through it unfiltered, keeps clear of it."""
    base = ('<body name="base" pos="0 0 0.5"><geom name="knob" type="sphere" size="0.03" pos="0.25 0 0.15"/>'
            '<body name="upper" pos="0 0 0">')
    xml = FOLDING.replace('<body name="upper" pos="0 0 0.5">', base)
    xml = xml.replace('<body name="ball"', '</body><body name="ball"')  # the base's own end

    def lowest(config):
        model, data, robot = _arm(xml)
        controller = None
        if config is not None:
            controller = SafetyController(model, data, robot, MocapSpheres(model, ["ball"]), config)
        knob = model.geom("knob").id
        low = np.inf
        for _ in range(1500):
            mujoco.mj_step1(model, data)
            tau = np.clip(60.0 * (FOLDED - data.qpos) - 5.0 * data.qvel, -robot.torque_limit, robot.torque_limit)
            if controller is not None:
                tau, report = controller.filter(tau)
                assert report.violation["self_collision"] == 0.0
            robot.write_ctrl(model, data, tau)
            mujoco.mj_step2(model, data)
            low = min(low, *(mujoco.mj_geomDistance(model, data, knob, int(g), 1.0, None) for g in robot.geom_ids))
        return low, controller

    assert lowest(None)[0] < 0.0
    assert lowest(FilterConfig(sensing_radius=1.0, self_collision=False))[0] < 0.0
    low, controller = lowest(FilterConfig(sensing_radius=1.0))
    assert low > 0.01
    model = controller.model
    partners = [(model.geom(int(controller.arm.capsule_ids[i])).name, model.geom(int(g)).name)
                for i, g in zip(controller.self_collision.fixed_capsules, controller.self_collision.fixed_geoms)]
    assert partners == [("upper", "knob"), ("fore", "knob"), ("hand", "knob")]
