"""Compile the package's kernels (the filter's, the impedance controller's and the obstacle
sampler's) into numba's on-disk cache: ``python -m c3bf_gym._precompile``.

Building the package (``pip install .``) runs this on the built copy of the package (``setup.py``),
so the installed package carries machine code for the fused filter step of the environment's arms
(the UR5e and the Panda), alone and behind the Cartesian impedance controller, and for the
controller alone, in its ``_numba_cache`` folders, and a fresh process's first filtered step loads it
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
    from c3bf_gym.controllers import ImpedanceHook
    from c3bf_gym.wrappers import default_impedance

    for env_id in ("C3BFReach-v0", "C3BFReachPanda-v0"):
        # the torque alone, the filter alone, behind the impedance controller, and the controller alone,
        # each in the environment's compiled policy step
        for env in (gym.make(env_id, scenario="multi"), c3bf_gym.SafetyFilter(gym.make(env_id, scenario="multi")),
                    c3bf_gym.SafetyFilter(c3bf_gym.CartesianImpedanceAction(gym.make(env_id, scenario="multi"))),
                    c3bf_gym.CartesianImpedanceAction(gym.make(env_id, scenario="multi"))):
            env.reset(seed=0)
            env.step(np.zeros(env.action_space.shape, np.float32))
            env.close()
        # the controller called from Python (a trajectory target), and the filter behind it
        env = c3bf_gym.SafetyFilter(gym.make(env_id, scenario="multi"))
        base = env.unwrapped
        env.reset(seed=0)
        target = base.data.site_xpos[base.ee_site_id].copy()
        base.add_torque_hook(ImpedanceHook(base, default_impedance(base), lambda t: (target, 0.0, 0.0)), "nominal")
        env.step(np.zeros(env.action_space.shape, np.float32))
        env.close()
    # the law on its own (CartesianImpedance.torque, damping_for)
    law = c3bf_gym.CartesianImpedance(stiffness=[100.0, 200.0, 300.0])
    law.torque(np.zeros(6), np.zeros(6), np.zeros(3), np.zeros(3), np.eye(3, 6), np.zeros(3), np.eye(6), np.zeros(6),
               np.ones(3))  # fmt: skip
    law.damping_for(np.eye(3))
    print(f"c3bf_gym: compiled the filter's kernels and the impedance controller's in {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
