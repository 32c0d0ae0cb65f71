"""A fingerprint of seeded rollouts, filtered and not, to check that a change leaves the filter's
torques and the environment's steps bit for bit as they were.

For each named filter of the table below (spelled with ``barrier``/``guard`` settings, which every
version of ``SafetyFilter`` since the guard takes) and for no filter, and each of the paper's four
scenarios, it runs ``EPISODES`` seeded episodes of ``STEPS`` policy steps, alternating uniformly
random and chattering ±1 torques, and hashes the observations, joint positions and velocities,
rewards, goal and obstacle distances, effort and the safety report's numbers; a second hash
leaves the report's numbers out (a change to the report alone moves only the first). A second
table does the same for the training recipe's stack (the residual Cartesian impedance action,
filtered by the default filter and not) on both arms, with uniformly random actions. Run it on
two trees and compare the printed hashes::

    PYTHONPATH=/path/to/other/checkout python benchmarks/rollout_hash.py 2 60
    python benchmarks/rollout_hash.py 2 60
"""

from __future__ import annotations

import hashlib
import os
import sys

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402

import c3bf_gym  # noqa: E402
from c3bf_gym import CartesianImpedanceAction, SafetyFilter  # noqa: E402

#: (label, SafetyFilter settings): the default filter, the C3BF alone, the distance HOCBF, the
#: default filter protecting the tool only, and no filter (None: the environment's own step).
FILTERS = (("c3bf+hocbf", dict(barrier="c3bf")), ("c3bf", dict(barrier="c3bf", guard=None)),
           ("hocbf", dict(barrier="hocbf")), ("c3bf+hocbf ee", dict(barrier="c3bf", points="ee")),
           ("none", None))  # fmt: skip


def fingerprint(settings: dict | None, episodes: int, steps: int) -> tuple[str, str]:
    """``(everything, the steps alone)``: the second leaves out the safety report's numbers, so a
    change to the report alone shows as the first hash moving while the second stays."""
    digest, steps_only = hashlib.sha256(), hashlib.sha256()
    for scenario in ("static", "head_on", "crossing", "multi"):
        env = gym.make("C3BFReach-v0", scenario=scenario)
        env = env if settings is None else SafetyFilter(env, **settings)
        for episode in range(episodes):
            env.reset(seed=100 + episode)
            rng = np.random.default_rng(episode)
            for _ in range(steps):
                if episode % 2:
                    action = rng.choice([-1.0, 1.0], size=6).astype(np.float32)
                else:
                    action = rng.uniform(-1, 1, 6).astype(np.float32)
                obs, reward, _, _, info = env.step(action)
                data = env.unwrapped.data
                numbers = [reward, info["distance"], info["min_distance"], info["reward_effort"]]
                for array in (obs, data.qpos, data.qvel, np.array(numbers)):
                    steps_only.update(array.tobytes())
                    digest.update(array.tobytes())
                if settings is not None:  # every entry of the report, in a fixed order
                    digest.update(np.array([float(info["safety"][key]) for key in sorted(info["safety"])]).tobytes())
        env.close()
    return digest.hexdigest()[:16], steps_only.hexdigest()[:16]


def recipe_fingerprint(env_id: str, safety_filter: str | None, episodes: int, steps: int) -> str:
    """The recipe's stack on ``env_id`` (``CartesianImpedanceAction(residual=True)`` over
    ``SafetyFilter(safety_filter)``, or over the bare env for None): observations, rewards and
    the safety report's numbers of seeded episodes in ``static`` and ``multi``."""
    digest = hashlib.sha256()
    for scenario in ("static", "multi"):
        env = gym.make(env_id, scenario=scenario)
        env = CartesianImpedanceAction(env if safety_filter is None else SafetyFilter(env, safety_filter), residual=True)
        for episode in range(episodes):
            env.reset(seed=200 + episode)
            rng = np.random.default_rng(episode)
            for _ in range(steps):
                obs, reward, terminated, truncated, info = env.step(rng.uniform(-1, 1, 3).astype(np.float32))
                digest.update(obs.tobytes())
                digest.update(np.array([reward]).tobytes())
                if safety_filter is not None:
                    digest.update(np.array([float(info["safety"][key]) for key in sorted(info["safety"])
                                            if key != "solve_time"]).tobytes())  # fmt: skip
                if terminated or truncated:
                    break
        env.close()
    return digest.hexdigest()[:16]


def main() -> None:
    episodes = int(sys.argv[1]) if len(sys.argv) > 1 else 2
    steps = int(sys.argv[2]) if len(sys.argv) > 2 else 60
    print(f"c3bf_gym from {os.path.dirname(c3bf_gym.__file__)}")
    total, total_steps = hashlib.sha256(), hashlib.sha256()
    print(f"{'filter':<13} {'everything':<16} steps alone")
    for label, settings in FILTERS:
        value, steps_value = fingerprint(settings, episodes, steps)
        total.update(value.encode())
        total_steps.update(steps_value.encode())
        print(f"{label:<13} {value} {steps_value}")
    print(f"{'all':<13} {total.hexdigest()[:16]} {total_steps.hexdigest()[:16]}")
    print(f"\n{'recipe stack':<30} everything")
    for env_id in ("C3BFReach-v0", "C3BFReachPanda-v0"):
        for safety_filter in ("c3bf+hocbf", None):
            print(f"{env_id + ' ' + str(safety_filter):<30} {recipe_fingerprint(env_id, safety_filter, episodes, steps)}")


if __name__ == "__main__":
    main()
