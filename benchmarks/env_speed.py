"""Step throughput of ``C3BFReach-v0`` next to Gymnasium's ``Pusher-v5``.

Both environments are made with ``gymnasium.make`` (so both carry the usual TimeLimit /
OrderEnforcing / PassiveEnvChecker wrappers), step pre-sampled random actions and reset when an
episode ends; the reset time is part of the measurement. The two are timed in alternating
rounds so that machine noise (frequency scaling, other processes) hits both alike; the median
over rounds is the headline.

Two rates per environment:

* steps/s: policy steps per wall second (what an RL loop sees);
* simulated s per wall s: steps/s x ``env.dt``. The environments step different amounts of time
  (C3BF: 10 x 2 ms = 20 ms; Pusher: 5 x 10 ms = 50 ms), so this is the fairer physics comparison.

Usage: ``python benchmarks/env_speed.py [--rounds 5] [--steps 2000] [--scenario random]``
"""

from __future__ import annotations

import argparse
import statistics
import time

import gymnasium as gym
import numpy as np

import c3bf_gym  # noqa: F401  (registers C3BFReach-v0)


def make_runner(env_id: str, steps: int, seed: int, **kwargs):
    return runner_for(gym.make(env_id, **kwargs), steps, seed)


def runner_for(env: gym.Env, steps: int, seed: int):
    """``(env, run)``: ``run()`` steps ``env`` through ``steps`` pre-sampled random actions
    (resetting at episode ends) and returns steps per wall second."""
    env.reset(seed=seed)
    env.action_space.seed(seed)
    actions = np.stack([env.action_space.sample() for _ in range(steps)])
    # one untimed warm-up episode chunk: first-call costs (allocation, caches) out of round 1
    for action in actions[:50]:
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
    env.reset(seed=seed)

    def run() -> float:
        """Step through all actions once; return steps per wall second."""
        step, reset = env.step, env.reset
        start = time.perf_counter()
        for action in actions:
            _, _, terminated, truncated, _ = step(action)
            if terminated or truncated:
                reset()
        return len(actions) / (time.perf_counter() - start)

    return env, run


def main(argv: list[str] | None = None) -> dict[str, list[float]]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=5, help="alternating timing rounds (default 5)")
    parser.add_argument("--steps", type=int, default=2000, help="steps per environment per round (default 2000)")
    parser.add_argument("--scenario", default="random", help="C3BFReach scenario (default: random, the env default)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.rounds < 1 or args.steps < 1:
        parser.error("--rounds and --steps must be >= 1")

    c3bf, run_c3bf = make_runner("C3BFReach-v0", args.steps, args.seed, scenario=args.scenario)
    pusher, run_pusher = make_runner("Pusher-v5", args.steps, args.seed)
    dt_c, dt_p = c3bf.unwrapped.dt, pusher.unwrapped.dt

    print(f"C3BFReach-v0 (scenario={args.scenario}, dt={dt_c * 1e3:.0f} ms) vs Pusher-v5 (dt={dt_p * 1e3:.0f} ms); "
          f"{args.rounds} rounds x {args.steps} steps each, alternating")
    header = f"{'round':>6} | {'C3BF st/s':>10} {'Pusher st/s':>11} {'ratio':>6} | {'C3BF sim/s':>10} {'Pusher sim/s':>12} {'ratio':>6}"
    print(header)
    print("-" * len(header))
    results: dict[str, list[float]] = {"c3bf": [], "pusher": []}
    for r in range(args.rounds):
        # alternate which goes first, so neither always follows the other
        if r % 2 == 0:
            c, p = run_c3bf(), run_pusher()
        else:
            p, c = run_pusher(), run_c3bf()
        results["c3bf"].append(c)
        results["pusher"].append(p)
        print(_row(str(r + 1), c, p, dt_c, dt_p))
    print("-" * len(header))
    c_med, p_med = statistics.median(results["c3bf"]), statistics.median(results["pusher"])
    print(_row("median", c_med, p_med, dt_c, dt_p))
    ratios = [c / p for c, p in zip(results["c3bf"], results["pusher"])]
    print(f"median of per-round ratios: steps/s {statistics.median(ratios):.3f}, "
          f"simulated s/s {statistics.median(ratios) * dt_c / dt_p:.3f}")
    c3bf.close()
    pusher.close()
    return results


def _row(label: str, c: float, p: float, dt_c: float, dt_p: float) -> str:
    return (
        f"{label:>6} | {c:>10.0f} {p:>11.0f} {c / p:>6.3f} | "
        f"{c * dt_c:>10.1f} {p * dt_p:>12.1f} {c * dt_c / (p * dt_p):>6.3f}"
    )


if __name__ == "__main__":
    main()
