"""A scripted reference for the RL baselines: head straight for the goal through the impedance
action (target = tool + clip(goal - tool, +-0.1 m)), ignoring obstacles, with each filter.

It bounds what the learned agents are compared with: how often a policy that only ever heads
for the goal ends an episode at it (is_success at the last step), and how often it collides,
on the same environment, wrappers and evaluation seeds as `c3bf-gym evaluate`.

    python train/scripted_reference.py --episodes 20
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from c3bf_gym.training import FILTERS, FINAL_EVAL_SEED, make_env


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--scenario", default="random")
    parser.add_argument("--seed", type=int, default=FINAL_EVAL_SEED, help="seed of episode 0 (as c3bf-gym evaluate)")
    parser.add_argument("--filters", nargs="+", choices=FILTERS, default=list(FILTERS))
    args = parser.parse_args()
    results = []
    for filter_name in args.filters:
        env = make_env(args.scenario, filter_name, "impedance", seed=args.seed)()
        success, collided = [], []
        for episode in range(args.episodes):
            obs, _ = env.reset(seed=args.seed + episode)
            done, info = False, {}
            while not done:
                action = np.clip(obs[18:21] / 0.1, -1.0, 1.0).astype(np.float32)  # goal - tool, per 0.1 m
                obs, _, terminated, truncated, info = env.step(action)
                done = terminated or truncated
            success.append(float(info["is_success"]))
            collided.append(float(info["episode_cost"] > 0))
        env.close()
        results.append(
            {"filter": filter_name, "episodes": args.episodes, "success_rate": float(np.mean(success)),
             "collision_episodes": int(sum(collided))}
        )  # fmt: skip
        print(json.dumps(results[-1]), flush=True)


if __name__ == "__main__":
    main()
