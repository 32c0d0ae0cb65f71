"""A real, non-editable install: ``pip install .`` into a fresh plain venv (no system site
packages), then make and reset the environment from an unrelated directory. This proves the MJCF
assets ship in the wheel (the editable install used for development would find them in the
checkout either way).

Takes ~25-30 s here: pip resolves gymnasium, mujoco, numpy and proxsuite from the configured
package index/wheel cache into the new venv.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import venv
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

CHECK = r"""
import sys
from importlib import metadata, resources
import gymnasium as gym, c3bf_gym
env = gym.make('C3BFReach-v0')
obs, info = env.reset(seed=0)
assert obs.shape == (85,), obs.shape
obs, *_ = env.step(env.action_space.sample())
# the safety filter's compiled kernels (numba) compile, or load from their cache, in the installed package
from c3bf_gym import SafetyFilter
filtered = SafetyFilter(gym.make('C3BFReach-v0', scenario='multi'), barrier='c3bf')
filtered.reset(seed=0)
for _ in range(3):
    obs, reward, terminated, truncated, info = filtered.step(filtered.action_space.sample())
assert info['safety']['sensed'] > 0, info  # the multi scenario's obstacles reach the filter's rows
behind = SafetyFilter(c3bf_gym.CartesianImpedanceAction(gym.make('C3BFReach-v0', scenario='multi')))
behind.reset(seed=0)  # the filter behind the impedance controller: both in the compiled policy step
behind.step(behind.action_space.sample())
timed = SafetyFilter(gym.make('C3BFReach-v0', scenario='multi'))
timed.hook.record_times()  # timing its calls: every call of the filter comes from Python
timed.reset(seed=0)
timed.step(timed.action_space.sample())
from c3bf_gym.safety import _step  # the fused step came from the machine code the build compiled
print('KERNEL_CACHE_HITS', sum(_step.filter_substep_at.stats.cache_hits.values()))
from c3bf_gym import scenarios  # and the environment's own: its obstacle sampler, physics steps (plain, under the
from c3bf_gym.envs import _kernels as env_kernels  # filter, and under the impedance controller and the filter) and observation
print('ENV_CACHE_HITS', *(sum(f.stats.cache_hits.values()) for f in (scenarios._sample, env_kernels.observe)))
print('STACKS_LOADED', sum(hits >= 1 for hits in env_kernels.policy_steps.stats.cache_hits.values()))
scene = resources.files('c3bf_gym.assets').joinpath('scene.xml')
import mujoco  # the Panda scene compiles from the installed files too (its <include> resolves there)
panda = mujoco.MjModel.from_xml_path(str(resources.files('c3bf_gym.assets').joinpath('panda_scene.xml')))
assert panda.nu == 7, panda.nu
shipped = sorted(str(f) for f in metadata.files('c3bf-gym') if str(f).endswith('.xml'))
print('PACKAGE', c3bf_gym.__file__)
print('SCENE', scene)
print('SHIPPED', ' '.join(shipped))
"""



def _clean_env() -> dict[str, str]:
    env = dict(os.environ)
    # NUMBA_CACHE_DIR too: the installed package must load the kernels its build compiled into it
    for key in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "PYTHONSTARTUP", "NUMBA_CACHE_DIR"):
        env.pop(key, None)
    return env


def _run(args, cwd: Path, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run(
        [str(a) for a in args], cwd=cwd, env=_clean_env(), capture_output=True, text=True, timeout=timeout
    )


@pytest.mark.slow
def test_pip_install_dot_into_fresh_venv_ships_assets(tmp_path):
    # Install from a copy of the checkout: pip builds in the source tree (build/, *.egg-info),
    # which must not touch the shared working tree.
    src = tmp_path / "src"
    shutil.copytree(
        REPO,
        src,
        ignore=shutil.ignore_patterns(
            ".git", "build", "dist", "*.egg-info", "__pycache__", "_numba_cache", ".pytest_cache", ".hypothesis",
            ".venv", "runs", "results",
        ),
    )
    prefix = tmp_path / "venv"
    venv.EnvBuilder(with_pip=True, system_site_packages=False, clear=True).create(prefix)
    python = prefix / "bin" / "python"
    assert "include-system-site-packages = false" in (prefix / "pyvenv.cfg").read_text()

    install = _run([python, "-m", "pip", "install", "-v", "--no-input", "--disable-pip-version-check", "."], cwd=src)
    assert install.returncode == 0, install.stdout[-3000:] + install.stderr[-3000:]
    built = [line for line in (install.stdout + install.stderr).splitlines() if "c3bf_gym: " in line]
    assert any("compiled the filter's kernels" in line for line in built), built or install.stderr[-3000:]

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    check = _run([python, "-c", CHECK], cwd=elsewhere, timeout=300)

    assert check.returncode == 0, check.stdout[-3000:] + check.stderr[-3000:]
    lines = dict(line.split(" ", 1) for line in check.stdout.splitlines() if " " in line)
    site = str(prefix.resolve())
    assert Path(lines["PACKAGE"]).resolve().as_posix().startswith(site), lines["PACKAGE"]  # not the checkout
    assert Path(lines["SCENE"]).resolve().as_posix().startswith(site), lines["SCENE"]
    assert int(lines["KERNEL_CACHE_HITS"]) >= 1, (built, check.stdout[-2000:])  # the build's compiled kernels
    assert all(int(hits) >= 1 for hits in lines["ENV_CACHE_HITS"].split()), (built, check.stdout[-2000:])
    assert int(lines["STACKS_LOADED"]) == 3, (built, check.stdout[-2000:])  # each stack's policy step, from the cache
    assert lines["SHIPPED"].split() == [
        "c3bf_gym/assets/panda.xml", "c3bf_gym/assets/panda_scene.xml", "c3bf_gym/assets/scene.xml",
        "c3bf_gym/assets/ur5e.xml",
    ]


