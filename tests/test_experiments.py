"""`c3bf-gym experiments` end to end on a tiny configuration, and its option errors."""

from __future__ import annotations

import csv
import json

import pytest

from c3bf_gym.cli import main
from c3bf_gym.experiments import MinimumJerk

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    out = tmp_path_factory.mktemp("experiments")
    code = main(
        ["experiments", "--out", str(out), "--seeds", "1", "--duration", "3", "--sensing-radius", "0.05", "1.0",
         "--sensing-speeds", "0.4", "--sensing-seeds", "1", "--no-progress"]
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
        (["experiments", "--seeds", "0"], "expected a whole number >= 1"),
        (["experiments", "--gamma", "-1"], "expected a finite number > 0"),
        (["experiments", "--margin", "nan"], "expected a finite number >= 0"),
        (["experiments", "--sensing-radius", "0"], "expected a finite number > 0"),
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
    code = main(["experiments", "--out", str(tmp_path), "--seeds", "1", "--duration", "2", "--scenarios", "head_on",
                 "--filters", "c3bf", "c3bf+hocbf", "--sensing-radius", "--no-progress"])  # fmt: skip
    assert code == 0
    table = _table(tmp_path)
    assert set(table) == {("head_on", "c3bf"), ("head_on", "c3bf+hocbf")}
    alone, guarded = table[("head_on", "c3bf")], table[("head_on", "c3bf+hocbf")]
    assert int(guarded["collision_steps"]) == 0
    assert alone["mean_correction_Nm"] != guarded["mean_correction_Nm"]


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
