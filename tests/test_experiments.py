"""`c3bf-gym experiments` end to end on a tiny configuration, and its option errors."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from c3bf_gym.cli import main
from c3bf_gym.experiments import ExperimentConfig, MinimumJerk, run_episode

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    out = tmp_path_factory.mktemp("experiments")
    code = main(
        ["experiments", "--out", str(out), "--seeds", "0", "--duration", "3", "--sensing-radius", "0.05", "1.0",
         "--sensing-speeds", "0.4", "--sensing-seeds", "0", "--no-progress"]
    )  # fmt: skip
    assert code == 0
    return out


def _table(results):
    with open(results / "table.csv") as fh:
        return {(r["scenario"], r["filter"]): r for r in csv.DictReader(fh)}


def test_table_covers_every_scenario_and_filter(results):
    table = _table(results)
    assert set(table) == {(s, f) for s in ("static", "head_on", "crossing", "multi") for f in ("none", "hocbf", "c3bf")}
    assert json.loads((results / "table.json").read_text())[0].keys() >= {"scenario", "filter", "collision_episodes"}
    assert (results / "table.md").read_text().startswith("| scenario | filter |")


def test_c3bf_never_collides_and_unfiltered_head_on_does(results):
    table = _table(results)
    for scenario in ("static", "head_on", "crossing", "multi"):
        row = table[(scenario, "c3bf")]
        assert int(row["collision_episodes"]) == 0 and int(row["collision_steps"]) == 0
        assert float(row["min_clearance_m"]) >= 0.0
    assert int(table[("head_on", "none")]["collision_episodes"]) == 1  # the nominal path runs into it


def test_table_numbers_are_consistent(results):
    for row in _table(results).values():
        episodes = int(row["episodes"])
        assert episodes == 1
        assert 0 <= int(row["collision_episodes"]) <= episodes
        assert (int(row["collision_steps"]) > 0) == (int(row["collision_episodes"]) > 0)
        assert (float(row["min_clearance_m"]) <= 0.0) == (int(row["collision_episodes"]) > 0)
        assert 0.0 <= float(row["reached"]) <= 1.0
        if row["filter"] == "none":
            assert row["intervention_share"] == "nan"
        else:
            assert 0.0 <= float(row["intervention_share"]) <= 1.0
            assert float(row["solve_us_median"]) > 0.0
            assert float(row["tracking_deviation_m"]) >= 0.0


def test_figures_are_nonempty_pngs(results):
    names = {p.name for p in (results / "figures").iterdir()}
    for scenario in ("static", "head_on", "crossing", "multi"):
        for kind in ("trajectories", "clearance", "barrier", "torques"):
            assert f"{scenario}_{kind}.png" in names
    assert {"summary_c3bf_vs_hocbf.png", "sensing_boundary.png"} <= names
    for path in (results / "figures").iterdir():
        data = path.read_bytes()
        assert data.startswith(PNG_MAGIC) and len(data) > 5_000, path


def test_sensing_table(results):
    with open(results / "sensing.csv") as fh:
        rows = list(csv.DictReader(fh))
    filtered = {(r["filter"], float(r["sensing_radius"])) for r in rows if r["filter"] != "none"}
    assert filtered == {(f, r) for f in ("hocbf", "c3bf") for r in (0.05, 1.0)}
    assert [r["filter"] for r in rows].count("none") == 1  # the radius-independent reference
    assert all(0.0 <= float(r["collision_rate"]) <= 1.0 for r in rows)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["experiments", "--scenarios", "sideways"], "invalid choice: 'sideways'"),
        (["experiments", "--filters", "cbf"], "invalid choice: 'cbf'"),
        (["experiments", "--points", "elbow"], "invalid choice: 'elbow'"),
        (["experiments", "--num-seeds", "0"], "expected a whole number >= 1"),
        (["experiments", "--seeds", "-1"], "expected a whole number >= 0"),
        (["experiments", "--seeds", "0", "1", "--num-seeds", "2"], "argument --num-seeds: not allowed with argument --seeds"),
        (["experiments", "--first-seed", "3"], "--first-seed only applies with --num-seeds"),
        (["experiments", "--seeds", "1", "1"], "seeds repeats a seed id"),
        (["experiments", "--no-sensing", "--sensing-only"], "not allowed with argument --no-sensing"),
        (["experiments", "--sensing-only", "--scenarios", "static"], "--scenarios selects neither"),
        (["experiments", "--sensing-radius"], "expected at least one argument"),
        (["experiments", "--gamma", "-1"], "expected a finite number > 0"),
        (["experiments", "--margin", "nan"], "expected a finite number >= 0"),
        (["experiments", "--sensing-radius", "0"], "expected a finite number > 0"),
        (["experiments", "--robot", "ur10"], "invalid choice: 'ur10' (choose from 'ur5e', 'panda')"),
        (["train", "--filter", "cbf"], "invalid choice: 'cbf'"),
        (["train", "--timesteps", "-5"], "expected a whole number >= 1"),
        (["evaluate", "/nonexistent/model.zip"], "no model at /nonexistent/model.zip"),
    ],
)
def test_bad_options_exit_with_a_clear_message(argv, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


def test_the_guarded_filter_is_an_experiment_filter(tmp_path):
    """"c3bf" in the experiments is the paper's C3BF alone; "c3bf+hocbf" is SafetyFilter's default
    (with the distance guard): the two differ on the same episode."""
    code = main(["experiments", "--out", str(tmp_path), "--seeds", "0", "--duration", "2", "--scenarios", "head_on",
                 "--filters", "c3bf", "c3bf+hocbf", "--no-sensing", "--no-progress"])  # fmt: skip
    assert code == 0
    table = _table(tmp_path)
    assert set(table) == {("head_on", "c3bf"), ("head_on", "c3bf+hocbf")}
    alone, guarded = table[("head_on", "c3bf")], table[("head_on", "c3bf+hocbf")]
    assert int(guarded["collision_steps"]) == 0
    assert alone["mean_correction_Nm"] != guarded["mean_correction_Nm"]


def test_experiments_run_on_the_panda(tmp_path):
    """``--robot panda`` runs the same experiment on the 7-joint Panda: its torques have 7
    components, the filter keeps it collision-free where the unfiltered arm is hit, and
    config.json names the robot."""
    code = main(["experiments", "--robot", "panda", "--out", str(tmp_path), "--seeds", "0", "--duration", "2",
                 "--scenarios", "head_on", "--filters", "none", "c3bf+hocbf", "--no-sensing", "--no-progress"])  # fmt: skip
    assert code == 0
    table = _table(tmp_path)
    assert int(table[("head_on", "c3bf+hocbf")]["collision_steps"]) == 0
    assert json.loads((tmp_path / "config.json").read_text())["robot"] == "panda"
    record, _ = run_episode("head_on", "c3bf+hocbf", 0, ExperimentConfig(robot="panda", duration=0.1))
    assert np.asarray(record.tau).shape[1] == 7


def test_experiment_config_rejects_an_unknown_robot():
    with pytest.raises(ValueError, match="unknown robot 'ur10'; valid choices: 'ur5e', 'panda'"):
        ExperimentConfig(robot="ur10").validate()
    with pytest.raises(ValueError, match="ExperimentConfig.robot"):
        ExperimentConfig(env_kwargs={"robot": "panda"}).validate()


def test_no_command_prints_help(capsys):
    assert main([]) == 2
    assert "experiments" in capsys.readouterr().out


def test_minimum_jerk_starts_and_ends_at_rest():
    import numpy as np

    path = MinimumJerk(np.zeros(3), np.array([0.3, 0.0, -0.1]), 2.0)
    for t in (0.0, 2.0, 3.0):
        _, vel, acc = path(t)
        assert np.allclose(vel, 0.0) and np.allclose(acc, 0.0)
    assert np.allclose(path(2.0)[0], [0.3, 0.0, -0.1]) and np.allclose(path(1.0)[0], [0.15, 0.0, -0.05])
    # velocity is the derivative of position
    h = 1e-6
    assert np.allclose((path(0.7 + h)[0] - path(0.7 - h)[0]) / (2 * h), path(0.7)[1], atol=1e-6)


# ----------------------------------------------------------------------------- options


def _experiments_parser():
    from c3bf_gym.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    return parser, sub.choices["experiments"]


def _config(argv):
    from c3bf_gym.experiments import config_from_args

    parser, _ = _experiments_parser()
    return config_from_args(parser.parse_args(["experiments", *argv]))


def test_seed_ids_and_seed_counts_are_separate_options():
    from c3bf_gym.experiments import ExperimentConfig

    assert _config([]).seeds == ExperimentConfig().seeds == (0, 1, 2)  # the main job's seeds
    assert _config(["--seeds", "4", "2"]).seeds == (4, 2)
    assert _config(["--seeds", "3"]).seeds == (3,)  # an id, not a count
    assert _config(["--num-seeds", "3"]).seeds == (0, 1, 2)
    assert _config(["--num-seeds", "2", "--first-seed", "5"]).seeds == (5, 6)
    assert _config(["--sensing-seeds", "7"]).sensing_seeds == (7,)


def test_quick_presets_what_is_left_at_its_default():
    from c3bf_gym.experiments import QUICK, ExperimentConfig

    quick = _config(["--quick"])
    for key, value in QUICK.items():
        assert getattr(quick, key) == value != getattr(ExperimentConfig(), key)
    mixed = _config(["--quick", "--duration", "4", "--num-seeds", "2"])
    assert (mixed.duration, mixed.seeds, mixed.sensing_speeds) == (4.0, (0, 1), QUICK["sensing_speeds"])


def test_help_shows_every_default_from_the_config(capsys):
    from c3bf_gym.experiments import ExperimentConfig

    _, parser = _experiments_parser()
    text = " ".join(parser.format_help().split())
    defaults = ExperimentConfig()
    for action in parser._actions:
        if action.dest == "help":
            continue
        assert f"(default: {action.default})" in text, action.dest
        field = {"sensing_radii": "sensing_radii"}.get(action.dest, action.dest)
        if hasattr(defaults, field):
            value = getattr(defaults, field)
            assert action.default == (list(value) if isinstance(value, tuple) else value), action.dest
    assert "(head_on, crossing)" in text  # where the sensing sweep runs


def test_sensing_sweep_runs_on_the_selected_scenarios_only(tmp_path, monkeypatch):
    from c3bf_gym import experiments

    calls = []
    real = experiments.run_episode

    def spy(scenario, filter_name, seed, config, **kwargs):
        calls.append((scenario, filter_name, seed))
        return real(scenario, filter_name, seed, config, **kwargs)

    monkeypatch.setattr(experiments, "run_episode", spy)
    code = main(["experiments", "--out", str(tmp_path / "a"), "--sensing-only", "--scenarios", "crossing", "static",
                 "--filters", "c3bf", "--duration", "0.5", "--sensing-radius", "1.0", "--sensing-speeds", "0.4",
                 "--sensing-seeds", "3", "--no-progress"])  # fmt: skip
    assert code == 0
    assert calls == [("crossing", "none", 3), ("crossing", "c3bf", 3)]
    assert not (tmp_path / "a" / "table.csv").exists()
    with open(tmp_path / "a" / "sensing.csv") as fh:
        assert {int(r["episodes"]) for r in csv.DictReader(fh)} == {1}

    calls.clear()  # no supported scenario selected: the table runs, the sweep is skipped and says so
    code = main(["experiments", "--out", str(tmp_path / "b"), "--scenarios", "static", "--filters", "none",
                 "--seeds", "0", "--duration", "0.5", "--no-progress"])  # fmt: skip
    assert code == 0
    assert calls == [("static", "none", 0)]
    assert (tmp_path / "b" / "table.csv").exists() and not (tmp_path / "b" / "sensing.csv").exists()


def test_markdown_tables_are_written_from_their_json(results):
    from c3bf_gym.experiments import COLUMNS, SENSING_COLUMNS, markdown_table

    for stem, columns in (("table", COLUMNS), ("sensing", SENSING_COLUMNS)):
        rows = json.loads((results / f"{stem}.json").read_text())
        assert markdown_table(rows, columns) + "\n" == (results / f"{stem}.md").read_text()


# ----------------------------------------------------------------------------- figures and video


def _record(name_cost, steps=20):
    """A synthetic EpisodeRecord: the tool moves along x, contact on the steps ``name_cost`` lists."""
    import numpy as np

    from c3bf_gym.metrics import EpisodeRecord

    record = EpisodeRecord(dt=0.02, obstacle_radius=np.array([0.05]), goal=np.array([0.5, 0.0, 0.3]))
    record.time = list(np.arange(steps + 1) * 0.02)
    record.tool = [np.array([0.01 * i, 0.0, 0.3]) for i in range(steps + 1)]
    record.obstacles = [np.array([[0.2, 0.0, 0.3]]) for _ in range(steps + 1)]
    record.cost = [1.0 if i in name_cost else 0.0 for i in range(steps)]
    record.min_distance = [0.1] * steps
    record.min_h = [0.5 - 0.01 * i for i in range(steps)]
    record.min_constraint = [0.0] * steps
    return record


def test_trajectory_plot_marks_every_contact_step():
    import numpy as np

    from c3bf_gym.plots import CONTACT_GID, _pyplot, trajectory_figure

    records = {"none": _record({3, 4, 5}), "c3bf": _record(set())}
    fig = trajectory_figure(records, "test")
    markers = [line for ax in fig.axes for line in ax.lines if line.get_gid() == CONTACT_GID]
    assert sum(len(line.get_xdata()) for line in markers) == 2 * 3  # three contact steps, two views
    # each marker sits on the tool's position after its contact step
    assert np.allclose(markers[0].get_xdata(), [0.04, 0.05, 0.06])
    _pyplot().close(fig)


def test_barrier_panels_name_the_quantity_they_show():
    from c3bf_gym.plots import _pyplot, barrier_figure

    fig = barrier_figure({"hocbf": _record(set()), "c3bf": _record(set())}, "test")
    hocbf, c3bf = fig.axes[0], fig.axes[1]
    assert "ψ₁ = ḣ + γ₁h" in hocbf.get_title() and hocbf.get_ylabel() == "min ψ₁ [m²/s]"
    assert "C3BF h =" in c3bf.get_title() and c3bf.get_ylabel() == "min h [m²/s]"
    _pyplot().close(fig)


def test_overlay_names_the_time_and_rings_the_goal():
    import numpy as np

    from c3bf_gym.experiments import OVERLAY_HEIGHT, annotate_frame

    blank = np.full((300, 400, 3), 128, dtype=np.uint8)
    early, late = annotate_frame(blank, "C3BF   t = 0.00 s", (200.0, 150.0)), annotate_frame(blank, "C3BF   t = 1.00 s")
    box = (slice(0, OVERLAY_HEIGHT), slice(0, 150))
    assert np.any(early[box] != late[box])  # the time is drawn
    assert np.array_equal(early[:OVERLAY_HEIGHT, 200:], blank[:OVERLAY_HEIGHT, 200:])  # the box fits the text
    ring = early[150, 200 - 12 : 200 - 6]  # left of the goal: the ring's bright green
    assert np.any((ring[:, 1] > 200) & (ring[:, 0] < 100))
    assert np.array_equal(late[140:160, 190:210], blank[140:160, 190:210])  # no goal given, no ring


@pytest.fixture(scope="module")
def gl():
    from test_env import gl_unavailable_reason

    reason = gl_unavailable_reason()
    if reason is not None:
        pytest.skip(reason)


def test_video_frames_carry_the_overlay_and_the_goal_projects_onto_it(gl):
    import numpy as np

    from c3bf_gym.envs.reach import C3BFReachEnv
    from c3bf_gym.experiments import OVERLAY_HEIGHT, ExperimentConfig, project, run_episode

    _, frames = run_episode("head_on", "c3bf", 0, ExperimentConfig(duration=0.1), render=True)
    assert len(frames) == 3 and frames[0].shape == (300, 400, 3)  # t = 0, 0.04, 0.08 s
    assert np.any(frames[0][:OVERLAY_HEIGHT, :150] != frames[-1][:OVERLAY_HEIGHT, :150])  # the time differs
    # the camera's own axis projects to the frame's centre, a point behind it nowhere
    env = C3BFReachEnv(render_mode="rgb_array", width=400, height=300)
    env.reset(seed=0)
    cam = env.model.camera("overview").id
    position, axis = env.data.cam_xpos[cam], -env.data.cam_xmat[cam].reshape(3, 3)[:, 2]
    assert np.allclose(project(env, position + axis, "overview"), (200.0, 150.0))
    assert project(env, position - axis, "overview") is None
    env.close()
