"""examples/own_arm.py: the standalone filter on a user's MJCF arm, as its docstring runs it."""

from __future__ import annotations

import importlib.util
import re
from importlib import resources
from pathlib import Path

import pytest

import c3bf_gym

from test_safety_api import ARM

ROOT = Path(__file__).resolve().parents[1]


def _example():
    spec = importlib.util.spec_from_file_location("own_arm", ROOT / "examples" / "own_arm.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _clearances(text: str) -> dict[str, float]:
    return {name: float(mm) for name, mm in re.findall(r"(unfiltered|filtered)\s*: lowest clearance ([-+\d.]+) mm", text)}


@pytest.mark.parametrize("arm", ["inline", "ur5e"])
def test_example_keeps_the_ball_off_the_arm(arm, tmp_path, capsys):
    """Without the filter the ball hits the arm; with it, it does not (clearance from MuJoCo's
    mj_geomDistance)."""
    if arm == "inline":
        path = tmp_path / "arm.xml"
        path.write_text(ARM.split('<body name="ball"')[0] + "</worldbody>" + ARM.split("</worldbody>")[1])
        argv = [str(path), "--site", "tool", "--bodies", "upper", "fore"]
    else:
        path = resources.files("c3bf_gym.assets") / "ur5e.xml"  # as installed
        argv = [str(path), "--site", "ee_site", "--joint-speed-limit", "3.14159"]
    assert _example().main(argv) == 0
    out = capsys.readouterr().out
    clearance = _clearances(out)
    assert clearance["unfiltered"] < 0.0, out
    assert clearance["filtered"] > 0.0, out
    assert re.search(r"filtered\s*: .* \d+ interventions", out)


def test_example_names_what_the_model_lacks(tmp_path):
    path = tmp_path / "arm.xml"
    path.write_text(ARM.replace('<motor name="elbow" joint="elbow" ctrlrange="-20 20"/>', ""))
    with pytest.raises(c3bf_gym.UnsupportedModelError, match="joint 'elbow' has no torque motor"):
        _example().main([str(path), "--site", "tool"])



def test_example_draws_the_protected_capsules(tmp_path, capsys):
    """--picture writes the arm with its protected capsules drawn over it in translucent blue: the
    arm's own geoms and the floor are grey, so blue pixels are the capsules'."""
    import imageio.v3 as iio

    from test_geometry import ARM as SHAPES  # links that are a box, a cylinder and a mesh

    path = tmp_path / "arm.xml"
    path.write_text(SHAPES.split('<body name="ball"')[0] + "</worldbody>" + SHAPES.split("</worldbody>")[1])
    picture = tmp_path / "capsules.png"
    assert _example().main([str(path), "--site", "tool", "--seconds", "0.1", "--picture", str(picture)]) == 0
    assert f"wrote {picture}" in capsys.readouterr().out
    image = iio.imread(picture).astype(int)
    assert image.shape == (480, 640, 3)
    assert ((image[..., 2] - image[..., 0]) > 60).sum() > 500
