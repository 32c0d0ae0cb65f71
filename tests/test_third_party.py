"""The safety filter on robosuite's arms (benchmarks/third_party.py): the arms load as their MJCF
files describe them (a gripper attached as robosuite attaches it), every link's collision mesh is
protected, and the benchmark's scene is a real threat (the unfiltered adversary collides).

robosuite 1.5.2's wheel is fetched from PyPI on first use (``robosuite_assets``: into
``$C3BF_ROBOSUITE_CACHE`` or ``~/.cache/c3bf-gym/robosuite-1.5.2``)."""

from __future__ import annotations

import importlib.util
import sys
import warnings
from pathlib import Path

import mujoco
import numpy as np
import pytest

from c3bf_gym.safety import UnprotectedGeometryWarning


def _load_benchmark():
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "third_party.py"
    spec = importlib.util.spec_from_file_location("third_party_benchmark", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is built
    spec.loader.exec_module(module)
    return module


tp = _load_benchmark()


@pytest.fixture(scope="module")
def assets() -> Path:
    return tp.robosuite_assets()


def test_only_the_robot_and_gripper_assets_are_extracted(assets):
    assert {p.name for p in assets.iterdir()} == {"robots", "grippers"}
    assert {p.name for p in assets.parent.iterdir()} == {"assets"}
    assert (assets / "robots" / "iiwa" / "robot.xml").is_file()
    assert tp.robosuite_assets(assets.parents[2]) == assets  # already there: found, not fetched again


@pytest.mark.parametrize("arm", list(tp.ARMS))
def test_each_arm_loads_and_every_link_collision_geom_is_protected(assets, arm):
    """Every colliding geom on a moving body is protected (meshes as the capsules that contain
    them), except those the library names as lying on their joints' axes; the tool is on the
    last link; the arm starts inside its joint limits."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", UnprotectedGeometryWarning)  # build_scene records, never leaks, them
        model, robot, notes = tp.build_scene(assets, arm, 2)
    assert model.opt.timestep == tp.TIMESTEP
    skipped = {line.split("'")[1] for line in notes if "lies on the axis" in line}
    moving = {b for b in range(1, model.nbody) if any(model.body_dofnum[a] for a in _ancestors(model, b))}
    colliding = {g for g in range(model.ngeom) if model.geom_bodyid[g] in moving
                 and (model.geom_contype[g] or model.geom_conaffinity[g])}  # fmt: skip
    protected = {int(g) for g in robot.geom_ids}
    assert protected == {g for g in colliding if model.geom(g).name not in skipped}
    assert len(protected) >= 6
    for g, capsule in zip(robot.geom_ids, robot.capsules, strict=True):
        kind = mujoco.mjtGeom(model.geom_type[g]).name.removeprefix("mjGEOM_").lower()
        assert capsule.source == kind and capsule.radius > 0.0
    if not arm.startswith("sawyer"):  # robosuite's sawyer collides as spheres and cylinders, the others as meshes
        assert all(c.source == "mesh" for c in robot.capsules)
    fingers = [g for g, c in zip(robot.geom_ids, robot.capsules, strict=True) if c.body >= 0]
    if tp.ARMS[arm].gripper is None:
        assert not fingers and model.body(model.site_bodyid[robot.site_id]).name == "right_hand"
    else:  # the gripper's fingers are swept over their stroke, on the hand the arm moves
        assert robot.nv == robot.n + 2 and {model.body(c.body).name for c in robot.capsules if c.body >= 0} == {
            "gripper0_gripper_base"}  # fmt: skip
        assert len(fingers) >= 4 and model.site(robot.site_id).name == "gripper0_grip_site"
    q = np.array(tp.ARMS[arm].init_qpos)
    assert np.all((robot.joint_range[:, 0] <= q) & (q <= robot.joint_range[:, 1]))
    assert robot.joint_speed_limit.shape == (7,)


def _ancestors(model, body):
    while body > 0:
        yield body
        body = model.body_parentid[body]


def test_kinova3_runs_with_its_continuous_joints(assets):
    """Kinova Gen3's joints 1, 3, 5 and 7 turn without limit: the default filter keeps their speed
    rows and runs, and states an envelope covering the benchmark's spheres with its keep-out."""
    why, _, envelope = tp._check_arm(assets, "kinova3", tp.CONFIG)
    assert why is None and envelope.max_speed >= tp.SPEED[1]
    model, robot, _ = tp.build_scene(assets, "kinova3", 1)
    assert (~robot.joint_limited()).sum() == 4


@pytest.mark.parametrize("policy, seed", [("random", 4), ("adversarial", 15)])
def test_the_jacos_friction_loss_does_not_carry_its_joints_past_their_speed_bound(assets, policy, seed):
    """robosuite's Jaco declares friction loss on every joint, a force the filter cannot predict;
    through the coupling of ``M⁻¹`` it reaches the other joints' speed rows. The joint rows take
    the last physics step's constraint force (``qfrc_constraint``, the friction included), so the
    joints stay within 5 % of the filter's speed bound (left out, these two episodes exceed it by
    15–17 %)."""
    result = tp.main(["--arms", "jaco", "--scenarios", "static", "--policies", policy, "--episodes", "1",
                      "--seed", str(seed), "--no-unfiltered", "--cache", str(assets.parents[2])])  # fmt: skip
    row = result["configurations"][0]
    assert row["collision_episodes"] == 0
    assert row["max_speed_ratio"] <= 1.05 * tp.CONFIG.joint_speed_fraction


def test_excluding_the_contact_the_filter_warns_of_holds_the_sawyers_speed_bound(assets, capsys):
    """robosuite's Sawyer rests its link 0 on its base; the filter warns of that contact and names
    the ``<exclude>`` that removes it. Its friction impulses, which no row predicts, throw the
    joints past the filter's speed bound (this episode: 1.55 times it); with ``--exclude``
    the pair no longer touches and the bound holds. A body the arm lacks is refused by name."""
    common = ["--arms", "sawyer", "--scenarios", "static", "--policies", "random", "--episodes", "1", "--seed",
              "1", "--no-unfiltered", "--cache", str(assets.parents[2])]  # fmt: skip
    shipped = tp.main(common)
    assert any("touches geom 'base_col'" in line for line in shipped["notes"]["sawyer"])
    assert shipped["settings"]["exclude"] == []
    excluded = tp.main(common + ["--exclude", "right_l0", "right_arm_base_link"])
    assert excluded["settings"]["exclude"] == [["right_l0", "right_arm_base_link"]]
    assert not any("touches geom 'base_col'" in line for line in excluded["notes"]["sawyer"])
    bound = tp.CONFIG.joint_speed_fraction
    assert shipped["configurations"][0]["max_speed_ratio"] > 1.05 * bound
    assert excluded["configurations"][0]["max_speed_ratio"] <= 1.05 * bound
    assert excluded["configurations"][0]["collision_episodes"] == 0
    with pytest.raises(SystemExit):
        tp.main(common + ["--exclude", "right_l0", "pedestal"])
    assert "sawyer has no body 'pedestal'; its bodies are base, right_arm_base_link, right_l0" in capsys.readouterr().err


def test_the_benchmark_runs_writes_its_json_and_the_unfiltered_adversary_collides(assets, tmp_path):
    out = tmp_path / "third_party.json"
    result = tp.main(["--arms", "iiwa", "kinova3", "--scenarios", "static", "head_on", "--episodes", "1",
                      "--seconds", "1", "--json", str(out), "--cache", str(assets.parents[2])])  # fmt: skip
    written = tp.json.loads(out.read_text())
    assert set(written) == {"settings", "unsupported", "notes", "configurations", "episodes"}
    assert list(written["unsupported"]) == []
    rows = written["configurations"]
    assert [(r["arm"], r["scenario"], r["policy"]) for r in rows] == [
        (a, s, p) for a in ("iiwa", "kinova3") for s in ("static", "head_on") for p in ("random", "adversarial")]
    keys = {"arm", "scenario", "policy", "episodes", "collision_episodes", "lowest_clearance_m",
            "infeasible_per_1000_steps", "gain_raised_per_1000_steps", "hard_relaxed_per_1000_steps", "max_speed_ratio",
            "unfiltered_episodes", "unfiltered_collision_episodes",
            "unfiltered_lowest_clearance_m", "unfiltered_max_speed_ratio"}  # fmt: skip
    assert all(set(r) == keys and r["episodes"] == r["unfiltered_episodes"] == 1 for r in rows)
    assert all(e["steps"] == 500 for e in written["episodes"])
    # the scene is a real threat: without the filter the adversary drives the arm into a sphere
    assert any(r["unfiltered_collision_episodes"] for r in rows if r["policy"] == "adversarial")
    assert result["configurations"] == rows


def test_a_table_without_unfiltered_episodes_claims_nothing_about_them(capsys):
    filtered = [tp.Episode("iiwa", "static", "random", True, seed, steps=100, lowest_clearance=0.05 - seed / 100)
                for seed in range(2)]  # fmt: skip
    (row,) = tp.summarise(filtered)
    assert row["episodes"] == 2 and row["unfiltered_episodes"] == 0 and row["lowest_clearance_m"] == 0.04
    assert row["unfiltered_collision_episodes"] is row["unfiltered_lowest_clearance_m"] is None
    tp.print_table([row], {})
    assert "unfiltered" not in capsys.readouterr().out
    (row,) = tp.summarise([*filtered, tp.Episode("iiwa", "static", "random", False, 0, collided=True,
                                                 lowest_clearance=-0.1)])  # fmt: skip
    assert row["unfiltered_episodes"] == row["unfiltered_collision_episodes"] == 1
    tp.print_table([row], {})
    assert "unfiltered" in capsys.readouterr().out


def test_moving_spheres_start_outside_the_sensing_range_the_envelope_needs(assets):
    """A moving sphere is first seen where the envelope's escape argument assumes it is sensed:
    its surface at least ``min_sensing_range(V)`` from every protected capsule, 0.8-2 s (plus the
    time to cross that range) before it meets its aim. Without that rule (``sensing=None``, as
    ``--ignore-envelope``) the same draws put spheres inside it."""
    model, robot, _ = tp.build_scene(assets, "sawyer", 4)
    data = mujoco.MjData(model)
    data.qpos[model.jnt_qposadr[model.dof_jntid[robot.dof_ids]]] = tp.ARMS["sawyer"].init_qpos
    mujoco.mj_forward(model, data)
    arm = tp.ArmModel(model, robot.geom_ids, robot.site_id, robot.capsules)
    a, b = arm.capsule_segments(data)
    envelope = tp._envelope(str(assets), "sawyer", tp.CONFIG, model, robot)
    needed, inside_without = envelope.min_sensing_range, 0
    for seed in range(8):
        for sensing in (needed, None):
            position, velocity, radius, leave = tp._spawn(
                np.random.default_rng(seed), tp.SCENARIOS["multi"], a, b, arm.capsule_radius,
                data.site_xpos[robot.site_id], tp.SECONDS, speed=tp.speed_range(envelope),
                keep_out=tp.ARMS["sawyer"].keep_out, sensing=sensing)  # fmt: skip
            closest = tp.segment_closest_points(a, b, position)  # (K, S, 3)
            gaps = (np.linalg.norm(closest - position[:, None], axis=2) - arm.capsule_radius).min(axis=1) - radius
            for k in np.flatnonzero(np.linalg.norm(velocity, axis=1) > 0):  # the moving ones
                pace = np.linalg.norm(velocity[k])
                lead = needed(pace) / pace if sensing is not None else 0.0
                meet = leave[k] - tp.PASS_DISTANCE / pace - lead  # [s] from where the old rule started it
                assert tp.MEET_TIME[0] - 1e-9 <= meet <= tp.MEET_TIME[1] + 1e-9
                if sensing is not None:
                    assert gaps[k] >= max(tp.SPAWN_CLEARANCE, needed(pace)) - 1e-9
                else:
                    inside_without += gaps[k] < needed(pace)
    assert inside_without > 0


def test_the_command_line_names_the_valid_choices(capsys):
    with pytest.raises(SystemExit) as exit_info:
        tp.main(["--arms", "ur10"])
    assert exit_info.value.code == 2
    assert "unknown arm ur10; choose from iiwa, sawyer, kinova3, jaco" in capsys.readouterr().err


def test_max_speed_lowers_the_spheres_top_speed_below_the_envelopes(assets, capsys):
    """``--max-speed``: the spheres' speeds are drawn up to it, never above the envelope's,
    recorded in the settings; a speed that is not a finite one > 0 is refused by name."""
    common = ["--arms", "iiwa", "--scenarios", "head_on", "--policies", "random", "--episodes", "1", "--seconds",
              "0.2", "--no-unfiltered", "--cache", str(assets.parents[2])]  # fmt: skip
    assert tp.main(common)["settings"]["sphere_speed_m_s"]["iiwa"] == list(tp.SPEED)  # the iiwa's envelope: 0.85 m/s
    assert tp.main(common + ["--max-speed", "0.25"])["settings"]["sphere_speed_m_s"]["iiwa"] == [0.1, 0.25]
    assert tp.main(common + ["--max-speed", "2"])["settings"]["sphere_speed_m_s"]["iiwa"][1] < 2  # the envelope caps it
    for bad in ("0", "-0.1", "inf"):
        with pytest.raises(SystemExit):
            tp.main(common + ["--max-speed", bad])
        assert "--max-speed must be a finite speed > 0" in capsys.readouterr().err


def _guide_snippet() -> str:
    """The own-robot guide's robosuite example, as the guide shows it."""
    guide = (Path(__file__).resolve().parents[1] / "docs" / "guides" / "own-robot.md").read_text()
    section = guide.split("## A robosuite arm, from its MJCF file", 1)[1]
    return section.split("```python\n", 1)[1].split("```", 1)[0]


def test_the_guides_robosuite_example_runs_in_under_30_lines_and_keeps_the_ball_off(assets, capsys):
    snippet = _guide_snippet()
    assert len(snippet.strip().splitlines()) < 30
    filter_line = "    tau, report = controller.filter(np.clip(tau, -robot.torque_limit, robot.torque_limit))\n"
    assert filter_line in snippet
    lowest = {}
    for filtered in (True, False):
        code = snippet if filtered else snippet.replace(filter_line, "    tau = np.clip(tau, -robot.torque_limit, robot.torque_limit)\n")
        exec(compile(code, "own-robot.md", "exec"), {"assets": str(assets)})
        lowest[filtered] = float(capsys.readouterr().out.rsplit("lowest clearance", 1)[1].split("mm")[0])
    assert lowest[False] < 0.0 < lowest[True], lowest


def test_filter_settings_are_set_by_name_and_a_wrong_one_is_refused(assets, capsys):
    result = tp.main(["--arms", "iiwa", "--scenarios", "static", "--policies", "random", "--episodes", "1",
                      "--seconds", "0.2", "--no-unfiltered", "--set", "joint_speed_fraction=1.0", "guard=none",
                      "--cache", str(assets.parents[2])])  # fmt: skip
    assert "joint_speed_fraction=1.0" in result["settings"]["filter"] and "guard=None" in result["settings"]["filter"]
    assert [e["filtered"] for e in result["episodes"]] == [True]
    for bad, message in (("jsf=1", "unknown filter setting"), ("margin", "expected SETTING=VALUE")):
        with pytest.raises(SystemExit):
            tp.main(["--arms", "iiwa", "--set", bad, "--cache", str(assets.parents[2])])
        assert message in capsys.readouterr().err
