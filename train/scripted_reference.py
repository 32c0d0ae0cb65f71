"""A scripted reference for the RL baselines: head straight for the goal, ignoring obstacles,
with each filter. It is the zero action of ``--action residual`` (target = tool + clip(goal -
tool, +-0.1 m)), i.e. the prior the residual agents start from.

It tells what the learned agents are compared with: how often a policy that only ever heads
for the goal ends an episode at it (is_success at the last step), and how often it collides,
on the same environment, wrappers, policy rate and evaluation seeds as `c3bf-gym evaluate`.
`--posture-stiffness` replaces the impedance controller's null-space pull (the arm's own by
default, `ReachRobot.posture_stiffness`) with each value given in turn: how the Panda's was chosen.
`--modulate off on` runs it with the straight step as it is and bent round the sensed obstacles
(`CartesianImpedanceAction(modulate=True)`, `c3bf-gym train --modulate`).

    python train/scripted_reference.py --episodes 50
    python train/scripted_reference.py --robot panda --episodes 200 --filters none c3bf+hocbf --posture-stiffness 20 5 2
    python train/scripted_reference.py --episodes 200 --filters none c3bf+hocbf --modulate off on
"""

from __future__ import annotations

import argparse
import itertools
import json

import gymnasium as gym
import numpy as np

from c3bf_gym.envs.reach import ROBOTS
from c3bf_gym.training import (
    DEFAULT_TRAIN_HZ,
    FINAL_EVAL_SEED,
    POLICY_RATES,
    TRAIN_FILTERS,
    by_scenario,
    env_kwargs,
    filter_config,
)
from c3bf_gym.wrappers import CartesianImpedanceAction, SafetyFilter, default_impedance


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--scenario", default="random")
    parser.add_argument("--seed", type=int, default=FINAL_EVAL_SEED, help="seed of episode 0 (as c3bf-gym evaluate)")
    parser.add_argument("--policy-hz", type=int, choices=POLICY_RATES, default=DEFAULT_TRAIN_HZ)
    parser.add_argument("--filters", nargs="+", choices=TRAIN_FILTERS, default=list(TRAIN_FILTERS))
    parser.add_argument("--robot", choices=list(ROBOTS), default="ur5e")
    parser.add_argument("--posture-stiffness", nargs="+", type=float, default=[None], metavar="K_Q",
                        help="the impedance controller's null-space stiffness [N m/rad] (default: the arm's own)")
    parser.add_argument("--modulate", nargs="+", choices=("off", "on"), default=["off"],
                        help="the straight step as it is, or bent round the sensed obstacles (default: off)")
    args = parser.parse_args()
    for stiffness, modulate, filter_name in itertools.product(args.posture_stiffness, args.modulate, args.filters):
        base = gym.make("C3BFReach-v0", scenario=args.scenario, **env_kwargs(args.policy_hz, robot=args.robot))
        env = CartesianImpedanceAction(base, residual=True, controller=default_impedance(base.unwrapped, stiffness),
                                       modulate=modulate == "on")  # fmt: skip
        config = filter_config(filter_name)
        if config is not None:  # as training.build_env stacks them
            env = SafetyFilter(env, config)
        straight = np.zeros(env.action_space.shape, dtype=np.float32)  # no correction: straight for the goal
        success, collided, kinds = [], [], []
        for episode in range(args.episodes):
            env.reset(seed=args.seed + episode)
            kinds.append(env.unwrapped.episode_scenario.name)
            done, info = False, {}
            while not done:
                _, _, terminated, truncated, info = env.step(straight)
                done = terminated or truncated
            success.append(float(info["is_success"]))
            collided.append(float(info["episode_cost"] > 0))
        env.close()
        result = {
            "robot": args.robot, "posture_stiffness": env.unwrapped.task_robot.posture_stiffness if stiffness is None else stiffness,
            "modulate": modulate == "on", "filter": filter_name, "policy_hz": args.policy_hz, "episodes": args.episodes,
            "success_rate": float(np.mean(success)), "collision_episodes": int(sum(collided)),
            "by_scenario": by_scenario(kinds, success, collided),
        }  # fmt: skip
        print(json.dumps(result), flush=True)


if __name__ == "__main__":
    main()
