"""Time to the first filtered step of a fresh process, import included.

Runs, each in a new interpreter and ``--rounds`` times alternately: import ``c3bf_gym``, build
``SafetyFilter(gym.make("C3BFReach-v0", scenario="multi"))``, reset, one step. Two cases:

* ``package cache``: numba's cache as the package has it. After ``pip install .`` that is the
  machine code the build compiled into the package (``setup.py``, ``c3bf_gym/_precompile.py``); in
  an editable checkout, whatever earlier runs left in ``c3bf_gym/_numba_cache``.
* ``empty cache``: ``NUMBA_CACHE_DIR`` set to a new empty folder, so every kernel compiles.

Usage: ``python benchmarks/first_step.py [--rounds 2]``. Prints each run's seconds, the medians and
which ``c3bf_gym`` ran.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile

PROBE = """
import time
start = time.perf_counter()
import gymnasium as gym
import numpy as np
import c3bf_gym
env = c3bf_gym.SafetyFilter(gym.make("C3BFReach-v0", scenario="multi"))
env.reset(seed=0)
env.step(np.zeros(6, np.float32))
print(time.perf_counter() - start, c3bf_gym.__file__)
"""


def run(empty_cache: bool) -> tuple[float, str]:
    env = dict(os.environ)
    env.pop("NUMBA_CACHE_DIR", None)
    with tempfile.TemporaryDirectory() as folder:
        if empty_cache:
            env["NUMBA_CACHE_DIR"] = folder
        done = subprocess.run([sys.executable, "-c", PROBE], env=env, cwd=folder, capture_output=True, text=True,
                              check=True)  # fmt: skip
    seconds, package = done.stdout.split()
    return float(seconds), package


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=2, help="runs of each case, alternating (default 2)")
    args = parser.parse_args()
    times: dict[str, list[float]] = {"package cache": [], "empty cache": []}
    for r in range(args.rounds):
        for name in (list(times) if r % 2 == 0 else list(times)[::-1]):
            seconds, package = run(name == "empty cache")
            times[name].append(seconds)
            print(f"round {r + 1}: {name:<13} {seconds:6.1f} s   ({package})", flush=True)
    for name, values in times.items():
        print(f"median {name:<13} {statistics.median(values):6.1f} s over {len(values)} runs")


if __name__ == "__main__":
    main()
