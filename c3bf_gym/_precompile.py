"""Compile the package's kernels (the filter's and the obstacle sampler's) into numba's on-disk
cache: ``python -m c3bf_gym._precompile``.

Building the package (``pip install .``) runs this on the built copy of the package (``setup.py``),
so the installed package carries machine code for the fused filter step of the environment's arms
(the UR5e and the Panda) in its ``_numba_cache`` folders, and a fresh process's first filtered step loads it
instead of compiling for about half a minute. numba checks every cached entry against the numba
version, the CPU and the kernels' sources (:mod:`c3bf_gym._compile_cache`); any mismatch, or a
read-only install, only means the kernels compile on first use as without this step.
"""

from __future__ import annotations

import time


def main() -> None:
    start = time.perf_counter()
    import gymnasium as gym
    import numpy as np

    import c3bf_gym

    for env_id in ("C3BFReach-v0", "C3BFReachPanda-v0"):
        # the filter alone (called from the environment's compiled policy step), then behind the
        # impedance controller (called from Python, between the controller's calls)
        for env in (c3bf_gym.SafetyFilter(gym.make(env_id, scenario="multi")),
                    c3bf_gym.SafetyFilter(c3bf_gym.CartesianImpedanceAction(gym.make(env_id, scenario="multi")))):
            env.reset(seed=0)
            env.step(np.zeros(env.action_space.shape, np.float32))
            env.close()
    print(f"c3bf_gym: compiled the filter's kernels in {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
