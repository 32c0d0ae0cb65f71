"""How much of the RL task a safe agent can win: an open-loop search over the residual action,
under the filter, on the evaluation episodes.

The residual agents' failures could be the task's (no action under the filter reaches the goal
in time) or the learner's. This separates them. For each evaluation episode (the same seeded
episodes as `c3bf-gym evaluate`, on the recipe's environment: `TrainConfig`'s defaults, the
default filter) it first runs the zero action, the residual's prior. Where that ends off the goal
it searches the action sequence with the cross-entropy method: piecewise-constant actions over
`--segments` equal parts of the episode, scored by the tool's distance to the goal at the last
step, each candidate replayed from the episode's seed (the environment is deterministic). The
search knows the whole episode in advance, which no agent does: an episode it wins has a safe
way to the goal in time; one it loses may still have one it did not find. Collisions come from the
environment's own signed distances (`info["cost"]`), not from the filter.

    python train/oracle.py                      # every evaluation episode the zero action loses
    python train/oracle.py --episodes 43 94 181 # these episodes (indices from FINAL_EVAL_SEED)

Prints one JSON line per episode searched, then a summary by scenario.
"""

from __future__ import annotations

import argparse
import json
import time
from collections import defaultdict

import numpy as np

from c3bf_gym.envs.reach import ROBOTS
from c3bf_gym.training import FINAL_EVAL_SEED, TrainConfig, build_env


def rollout(env, seed: int, actions: np.ndarray) -> tuple[float, float, bool]:
    """The episode of ``seed`` under ``actions`` (one row per policy step, repeated if shorter):
    the tool's final distance to the goal [m], the episode's collision steps, and success."""
    env.reset(seed=seed)
    collisions, done, step, info = 0.0, False, 0, {}
    while not done:
        _, _, terminated, truncated, info = env.step(actions[min(step, len(actions) - 1)])
        collisions += info["cost"]
        done, step = terminated or truncated, step + 1
    return float(info["distance"]), collisions, bool(info["is_success"])


def search(env, seed: int, steps: int, segments: int, samples: int, elites: int, iterations: int,
           rng: np.random.Generator) -> float:  # fmt: skip
    """The cross-entropy method over ``segments`` constant actions: the least final distance [m]
    of a candidate with no collision step (inf if every candidate collided)."""
    mean, spread = np.zeros((segments, 3)), np.full((segments, 3), 0.7)
    best = np.inf
    per_segment = -(-steps // segments)
    for _ in range(iterations):
        candidates = np.clip(mean + spread * rng.standard_normal((samples, segments, 3)), -1.0, 1.0)
        candidates[0] = mean
        scores = np.empty(samples)
        for i, plan in enumerate(candidates):
            actions = np.repeat(plan, per_segment, axis=0).astype(np.float32)
            final, collisions, _ = rollout(env, seed, actions)
            scores[i] = final + collisions  # 1 m per collision step: more than the tool is ever off the goal
            if collisions == 0:
                best = min(best, final)
        elite = candidates[np.argsort(scores)[:elites]]
        mean, spread = elite.mean(axis=0), elite.std(axis=0) + 0.05
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, nargs="+", default=None,
                        help="episode indices from FINAL_EVAL_SEED (default: 0 to --count - 1)")  # fmt: skip
    parser.add_argument("--count", type=int, default=200, help="evaluation episodes when --episodes is not given")
    parser.add_argument("--robot", choices=list(ROBOTS), default="ur5e")
    parser.add_argument("--segments", type=int, default=10, help="constant actions per episode")
    parser.add_argument("--samples", type=int, default=48, help="candidates per iteration")
    parser.add_argument("--elites", type=int, default=8)
    parser.add_argument("--iterations", type=int, default=6)
    args = parser.parse_args()
    for name in ("count", "segments", "samples", "elites", "iterations"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    if args.elites > args.samples:
        parser.error(f"--elites ({args.elites}) must not exceed --samples ({args.samples})")
    config = TrainConfig(robot=args.robot)
    env = build_env("random", **config.env_options())
    tolerance = env.unwrapped.success_tolerance
    steps = env.spec.max_episode_steps
    episodes = args.episodes if args.episodes is not None else range(args.count)
    wins, counts = defaultdict(lambda: [0, 0, 0]), defaultdict(int)
    for episode in episodes:
        seed = FINAL_EVAL_SEED + episode
        final, collisions, success = rollout(env, seed, np.zeros((1, 3), np.float32))
        scenario = env.unwrapped.episode_scenario.name
        counts[scenario] += 1
        wins[scenario][0] += success
        if success:
            continue
        start = time.perf_counter()
        best = search(env, seed, steps, args.segments, args.samples, args.elites, args.iterations,
                                       np.random.default_rng(episode))  # fmt: skip
        found = best < tolerance
        wins[scenario][1] += found
        print(json.dumps({"episode": episode, "scenario": scenario, "zero_action_final": round(final, 4),
                          "zero_action_collisions": collisions, "searched_final": round(best, 4),
                          "searched_success": found, "seconds": round(time.perf_counter() - start, 1)}), flush=True)  # fmt: skip
    env.close()
    summary = {name: {"episodes": counts[name], "zero_action": wins[name][0] / counts[name],
                      "zero_action_or_searched": (wins[name][0] + wins[name][1]) / counts[name]}
               for name in sorted(counts)}  # fmt: skip
    print(json.dumps({"robot": args.robot, "filter": config.filter, "by_scenario": summary}), flush=True)


if __name__ == "__main__":
    main()
