"""The speed benchmarks the README names run: their exit status and the JSON they write (its keys and
structure, and the relations between its numbers), not the wording of their printed tables. The long
ones (a training loop, edited copies of the package compiled afresh) are slow tests."""

from __future__ import annotations

import json
import platform
import subprocess
import sys
from pathlib import Path

import pytest

from c3bf_gym import SCENARIOS

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
#: filter_speed.py replays the filter's calls timed with the x86 time-stamp counter, only there
REPLAYED = platform.machine() in ("x86_64", "AMD64", "i686", "i386")


def test_env_speed_times_every_configuration_against_the_bare_physics(tmp_path):
    out = tmp_path / "env_speed.json"
    done = subprocess.run([sys.executable, str(BENCHMARKS / "env_speed.py"), "--rounds", "2", "--steps", "5",
                           "--reset-samples", "2", "--json", str(out)], capture_output=True, text=True, timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(out.read_text())
    assert set(result["breakdown"]) == {"physics_us", "env_us", "filter_random_us", "filter_adversarial_us"}
    assert result["breakdown"]["physics_us"] > 0
    assert {"bare", "unfiltered", "filtered random", "filtered adversarial", "impedance", "recipe",
            "Pusher-v5"} <= set(result["us_per_step"])
    assert result["recipe_to_filtered"] > 0 and result["impedance_to_unfiltered"] > 0
    assert result["ratio_to_bare"]["bare"] == 1.0 and all(len(v) == 2 for v in result["us_per_step"].values())
    assert set(result["reset_ms"]) == set(SCENARIOS) - {"none"}  # every registered scenario with obstacles
    refused = subprocess.run([sys.executable, str(BENCHMARKS / "env_speed.py"), "--rounds", "0"],
                             capture_output=True, text=True, timeout=300)  # fmt: skip
    assert refused.returncode == 2 and "--rounds and --steps must be >= 1" in refused.stderr


def test_env_speed_compares_a_filter_option_side_by_side(tmp_path):
    out = tmp_path / "env_speed.json"
    done = subprocess.run([sys.executable, str(BENCHMARKS / "env_speed.py"), "--rounds", "2", "--steps", "5",
                           "--reset-samples", "0", "--compare", "allowance_level=true", "--json", str(out)],
                          capture_output=True, text=True, timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(out.read_text())
    assert result["compared"]["settings"] == {"allowance_level": True}
    assert set(result["compared"]["to_default"]) == {"filtered random", "filtered adversarial", "recipe"}
    assert all(len(result["us_per_step"][f"{name} *"]) == 2 for name in result["compared"]["to_default"])
    assert "with allowance_level=True (*) ÷ the default filter" in done.stdout
    refused = subprocess.run([sys.executable, str(BENCHMARKS / "env_speed.py"), "--compare", "allowance_level=maybe"],
                             capture_output=True, text=True, timeout=300)  # fmt: skip
    assert refused.returncode == 2 and "--compare: allowance_level must be True or False" in refused.stderr


def test_filter_speed_times_the_hook_latency(tmp_path):
    out = tmp_path / "filter_speed.json"
    done = subprocess.run([sys.executable, str(BENCHMARKS / "filter_speed.py"), "--calls", "40", "--obstacles", "1", "4",
                           "--json", str(out)], capture_output=True, text=True, timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(out.read_text())
    for count in ("1", "4"):
        row = result["hook"][count]
        assert row["total_median_us"] > 0 and row["total_mean_us"] > 0 and sum(row["status"].values()) >= 40
        if REPLAYED:  # the compiled replay times the same calls: it must give their torques, bit for bit
            assert row["compiled_same_torques"] is True
            assert 0 < row["compiled_median_us"] <= row["compiled_p99_us"] and row["compiled_mean_us"] > 0
    skipped = subprocess.run([sys.executable, str(BENCHMARKS / "filter_speed.py"), "--calls", "10", "--obstacles", "1",
                              "--no-replay", "--json", str(out)], capture_output=True, text=True, timeout=600)  # fmt: skip
    assert skipped.returncode == 0, skipped.stderr[-2000:]
    assert json.loads(out.read_text())["hook"]["1"]["compiled_same_torques"] is None  # not "equal": not checked


@pytest.mark.slow
def test_train_speed_times_filtered_and_unfiltered_throughput_side_by_side(tmp_path):
    out = tmp_path / "train_speed.json"
    done = subprocess.run([sys.executable, str(BENCHMARKS / "train_speed.py"), "--actions", "torque", "--rounds", "2",
                           "--steps", "64", "--json", str(out)], capture_output=True, text=True, timeout=900)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(out.read_text())
    rows = {(r["algo"], r["action"], r["filter"]): r for r in result["results"]}
    assert set(rows) == {(algo, "torque", name) for algo in ("sac", "ppo") for name in ("none", "c3bf+hocbf")}
    assert all(len(r["steps_per_s"]) == 2 and r["median"] > 0 for r in rows.values())
    for algo in ("sac", "ppo"):  # the share of the unfiltered throughput kept, from the same run's medians
        filtered, unfiltered = rows[algo, "torque", "c3bf+hocbf"], rows[algo, "torque", "none"]
        assert filtered["filtered_over_unfiltered"] == pytest.approx(filtered["median"] / unfiltered["median"])
    refused = subprocess.run([sys.executable, str(BENCHMARKS / "train_speed.py"), "--rounds", "0"],
                             capture_output=True, text=True, timeout=300)  # fmt: skip
    assert refused.returncode == 2 and "--rounds must be >= 1" in refused.stderr


@pytest.mark.slow
def test_filter_parts_times_the_filtered_step_without_its_qp_and_without_its_rows(tmp_path):
    out = tmp_path / "filter_parts.json"
    done = subprocess.run([sys.executable, str(BENCHMARKS / "filter_parts.py"), "--runs", "1", "--rounds", "1",
                           "--steps", "5", "--json", str(out)], capture_output=True, text=True, timeout=900)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(out.read_text())
    assert set(result["runs"]) == {"filter", "no QP", "no rows, no QP"}
    assert all(len(runs) == 1 and runs[0]["breakdown"]["physics_us"] > 0 for runs in result["runs"].values())
    assert result["budget_us_for_2x"] == (2.0 - result["unfiltered_ratio"]) * result["physics_us"]
    # The edited copies passed the check that they step as the unfiltered env does; the filter itself
    # (which changes random torques) fails it, with its own exit status, so the check can tell.
    unedited = subprocess.run([sys.executable, str(BENCHMARKS / "filter_parts.py"), "--same-steps", "30"],
                              capture_output=True, text=True, timeout=600)  # fmt: skip
    assert unedited.returncode == 3, unedited.stderr[-2000:]
