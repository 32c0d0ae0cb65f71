"""The command line's own behaviour (c3bf_gym/cli.py): its version, and the errors a new user meets.
Each command's options are tested with the module it runs (test_experiments.py, test_training.py)."""

from __future__ import annotations

import sys
from importlib import metadata

import pytest

import c3bf_gym
from c3bf_gym.cli import main


def _exit(argv: list[str]) -> int:
    with pytest.raises(SystemExit) as stop:
        main(argv)
    return stop.value.code


def test_version_is_the_installed_distributions(capsys):
    assert _exit(["--version"]) == 0
    assert capsys.readouterr().out == f"c3bf-gym {metadata.version('c3bf-gym')}\n"


def test_version_without_an_installed_distribution_is_the_packages_own(monkeypatch, capsys):
    def not_installed(name: str) -> str:
        raise metadata.PackageNotFoundError(name)

    monkeypatch.setattr(metadata, "version", not_installed)
    assert _exit(["--version"]) == 0
    assert capsys.readouterr().out == f"c3bf-gym {c3bf_gym.__version__}\n"


@pytest.mark.parametrize("module", ["torch", "stable_baselines3"])
def test_train_and_evaluate_without_the_train_extra_say_how_to_install_it(module, monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, module, None)  # import fails as if it were not installed
    model = tmp_path / "model.zip"
    model.write_bytes(b"")
    for argv in (["train", "--out", str(tmp_path / "runs")], ["evaluate", str(model)]):
        assert _exit(argv) == 2
        error = capsys.readouterr().err
        assert error.startswith(f"c3bf-gym {argv[0]}: error: ") and f"needs {module}, not installed here" in error
        assert "pip install torch --index-url https://download.pytorch.org/whl/cpu" in error
        assert 'then pip install "c3bf-gym[train]"' in error
    assert not (tmp_path / "runs").exists()  # nothing written before the check


@pytest.mark.parametrize(("argv", "wrong", "valid"), [
    (["--hyperparams", '{"learning_rat": 0.001}'], "unknown SAC hyperparameters 'learning_rat'", "learning_rate"),
    (["--algo", "ppo", "--hyperparams", '{"n_step": 64, "seed": 1}'], "unknown PPO hyperparameters 'n_step', 'seed'", "n_steps"),
    (["--hyperparams", "[1]"], "hyperparams must be a dict of keyword arguments, got [1]", None),
])  # fmt: skip
def test_train_refuses_bad_hyperparameters_before_writing_anything(argv, wrong, valid, tmp_path, capsys):
    assert _exit(["train", "--out", str(tmp_path / "runs"), *argv]) == 2
    error = capsys.readouterr().err
    assert f"c3bf-gym train: error: {wrong}" in error and "Traceback" not in error
    if valid:
        assert "valid keys: " in error and f" {valid}," in error
    assert not (tmp_path / "runs").exists()
