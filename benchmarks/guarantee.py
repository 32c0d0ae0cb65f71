"""The long guarantee sweep: does the filter keep every obstacle off the arm?

Episodes of ``C3BFReach-v0`` over the paper's four scenarios (static, head_on, crossing, multi),
for two policies (uniformly random torques; an adversary that drives the arm point nearest to an
obstacle straight at it at full torque), three filters (whole-arm or tool-only C3BF, whole-arm or
tool-only distance HOCBF, and none). Collisions are the environment's own signal
(``info["cost"]``: MuJoCo's signed distances at every physics step), independent of the filter.
Seeds are shared across configurations (episode ``i`` uses seed ``--seed + i`` everywhere), so
configurations are compared on the same episodes.

Per configuration it prints: episodes, episodes with a collision, collision steps, the smallest
clearance seen (m; negative = penetration), infeasible steps (the QP needed slack), the
intervention rate (share of steps the filter changed the torque), and the largest per-step mean
filter time. Per-episode rows go to ``episodes.csv`` and the table to ``summary.json`` in
``--out``. Episodes run in ``--workers`` processes.

Usage::

    python benchmarks/guarantee.py --quick                 # smoke run (~1 min)
    python benchmarks/guarantee.py --episodes 200 --out results/guarantee
    python benchmarks/guarantee.py --episodes 200 --filters c3bf/whole_arm --margin 0.03   # a wider margin
    python benchmarks/guarantee.py --episodes 200 --filters c3bf/whole_arm --guard none    # the C3BF alone
"""

from __future__ import annotations

import argparse
import csv
import json
import multiprocessing as mp
import os
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

SCENARIOS = ("static", "head_on", "crossing", "multi")
POLICIES = ("random", "adversarial")
FILTERS = (("c3bf", "whole_arm"), ("hocbf", "whole_arm"), ("c3bf", "ee"), ("hocbf", "ee"), ("none", "-"))


@dataclass
class Episode:
    scenario: str
    policy: str
    barrier: str
    points: str
    seed: int
    steps: int = 0
    collision_steps: int = 0
    min_clearance: float = float("inf")
    infeasible_steps: int = 0
    interventions: int = 0
    max_filter_ms: float = 0.0
    wall_s: float = 0.0


# ----------------------------------------------------------------------------- policies


def adversarial_action(u) -> np.ndarray:
    """Full torque (as the env's action: a fraction of each joint's limit on top of gravity
    compensation) along Jᵀ (o − x)/‖o − x‖ for the arm capsule point x nearest to any obstacle o
    (surface to surface), scaled so the largest joint is at its limit."""
    import mujoco

    m, d = u.model, u.data
    best = None
    for k in np.flatnonzero(u.obstacle_active):
        centre = u.obstacle_pos[k]
        for gid in u.arm_geom_ids:
            if m.geom_type[gid] != mujoco.mjtGeom.mjGEOM_CAPSULE or m.body_dofnum[m.geom_bodyid[gid]] == 0:
                continue
            axis = d.geom_xmat[gid].reshape(3, 3)[:, 2] * m.geom_size[gid, 1]
            a, ab = d.geom_xpos[gid] - axis, 2 * axis
            x = a + np.clip((centre - a) @ ab / (ab @ ab), 0.0, 1.0) * ab
            gap = np.linalg.norm(centre - x) - m.geom_size[gid, 0] - u.obstacle_radius[k]
            if best is None or gap < best[0]:
                best = (gap, x, m.geom_bodyid[gid], centre.copy())
    if best is None:
        return np.zeros(6, np.float32)
    _, x, body, centre = best
    jac = np.zeros((3, m.nv))
    mujoco.mj_jac(m, d, jac, None, x, body)
    action = jac.T @ ((centre - x) / max(np.linalg.norm(centre - x), 1e-9)) / u.torque_limit
    peak = np.abs(action).max()
    return np.zeros(6, np.float32) if peak < 1e-12 else np.clip(action / peak, -1, 1).astype(np.float32)


# ----------------------------------------------------------------------------- one episode


def run_episode(task: tuple[str, str, str, str, int, int, float | None, str, float | None]) -> Episode:
    scenario, policy, barrier, points, seed, steps, margin, guard, guard_gamma = task
    import gymnasium as gym

    import c3bf_gym  # noqa: F401  (registers C3BFReach-v0)
    from c3bf_gym import SafetyFilter

    start = time.perf_counter()
    env = gym.make("C3BFReach-v0", scenario=scenario)
    if barrier != "none":
        guarded = barrier == "c3bf" and guard == "auto"  # the only filter here with a guard
        env = SafetyFilter(env, barrier=barrier, points=points, guard=guard, guard_gamma=guard_gamma if guarded else None,
                           **({} if margin is None else {"margin": margin}))
    u = env.unwrapped
    out = Episode(scenario, policy, barrier, points, seed)
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    for _ in range(steps):
        action = rng.uniform(-1, 1, 6).astype(np.float32) if policy == "random" else adversarial_action(u)
        _, _, terminated, truncated, info = env.step(action)
        out.steps += 1
        out.collision_steps += int(info["cost"] > 0)
        out.min_clearance = min(out.min_clearance, float(info["min_distance"]))
        if barrier != "none":
            out.infeasible_steps += int(info["safety_infeasible"])
            out.interventions += int(info["safety_intervened"])
            out.max_filter_ms = max(out.max_filter_ms, 1e3 * info["safety"]["solve_time"])
        if terminated or truncated:
            break
    env.close()
    out.wall_s = time.perf_counter() - start
    return out


# ----------------------------------------------------------------------------- sweep


def summarise(episodes: list[Episode]) -> list[dict]:
    groups: dict[tuple, list[Episode]] = {}
    for e in episodes:
        groups.setdefault((e.scenario, e.policy, e.barrier, e.points), []).append(e)
    rows = []
    for (scenario, policy, barrier, points), group in groups.items():
        steps = sum(e.steps for e in group)
        rows.append({
            "scenario": scenario, "policy": policy, "barrier": barrier, "points": points,
            "episodes": len(group),
            "collision_episodes": sum(e.collision_steps > 0 for e in group),
            "collision_steps": sum(e.collision_steps for e in group),
            "min_clearance": min(e.min_clearance for e in group),
            "infeasible_steps": sum(e.infeasible_steps for e in group),
            "intervention_rate": sum(e.interventions for e in group) / max(steps, 1),
            "max_filter_ms": max(e.max_filter_ms for e in group),
            "steps": steps,
        })  # fmt: skip
    order = {name: i for i, name in enumerate(SCENARIOS + POLICIES)}
    filters = {f: i for i, f in enumerate(FILTERS)}
    rows.sort(key=lambda r: (order[r["scenario"]], order[r["policy"]], filters[(r["barrier"], r["points"])]))
    return rows


def print_table(rows: list[dict]) -> None:
    header = (f"{'scenario':<9} {'policy':<11} {'filter':<16} | {'episodes':>8} {'coll.ep':>7} {'coll.steps':>10} "
              f"{'min clear.':>10} {'infeas.steps':>12} {'interv.':>7} {'max ms':>8}")  # fmt: skip
    print(header)
    print("-" * len(header))
    for r in rows:
        name = "none" if r["barrier"] == "none" else f"{r['barrier']}/{r['points']}"
        print(f"{r['scenario']:<9} {r['policy']:<11} {name:<16} | {r['episodes']:>8} {r['collision_episodes']:>7} "
              f"{r['collision_steps']:>10} {r['min_clearance']:>10.4f} {r['infeasible_steps']:>12} "
              f"{100 * r['intervention_rate']:>6.1f}% {r['max_filter_ms']:>8.1f}")  # fmt: skip


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=200, help="episodes per configuration (default 200)")
    parser.add_argument("--steps", type=int, default=250, help="steps per episode (default 250: a full episode)")
    parser.add_argument("--workers", type=int, default=2, help="worker processes (default 2)")
    parser.add_argument("--seed", type=int, default=0, help="seed of episode 0 (episode i uses seed + i)")
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), choices=SCENARIOS)
    parser.add_argument("--policies", nargs="+", default=list(POLICIES), choices=POLICIES)
    parser.add_argument("--filters", nargs="+", default=[f"{b}/{p}" if b != "none" else b for b, p in FILTERS],
                        choices=[f"{b}/{p}" if b != "none" else b for b, p in FILTERS],
                        help="barrier/points combinations (default: all, and no filter)")  # fmt: skip
    parser.add_argument("--margin", type=float, help="the filters' margin [m] (default: SafetyFilter's, 0.02)")
    parser.add_argument("--guard", choices=("auto", "none"), default="auto",
                        help="the filters' guard (SafetyFilter's: 'auto', the distance HOCBF beside the C3BF; "
                             "'none', the barrier's rows alone)")  # fmt: skip
    parser.add_argument("--guard-gamma", type=float, help="the guard's gains [1/s] (default: SafetyFilter's, 10)")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/guarantee"), help="output directory")
    parser.add_argument("--quick", action="store_true", help="smoke run: 2 episodes of 100 steps per configuration")
    args = parser.parse_args(argv)
    if args.quick:
        args.episodes, args.steps = 2, 100
    if args.episodes < 1 or args.steps < 1 or args.workers < 1:
        parser.error("--episodes, --steps and --workers must be >= 1")
    if args.margin is not None and not (np.isfinite(args.margin) and args.margin >= 0):
        parser.error(f"--margin must be a finite number >= 0 (m), got {args.margin}")
    if args.guard_gamma is not None and not (np.isfinite(args.guard_gamma) and args.guard_gamma > 0):
        parser.error(f"--guard-gamma must be a finite number > 0 (1/s), got {args.guard_gamma}")
    if args.guard_gamma is not None and args.guard == "none":
        parser.error("--guard-gamma sets the guard's gains; it needs --guard auto")

    filters = [tuple(f.split("/")) if f != "none" else ("none", "-") for f in args.filters]
    tasks = [(s, p, b, pts, args.seed + i, args.steps, args.margin, args.guard, args.guard_gamma)
             for s in args.scenarios for p in args.policies for b, pts in filters for i in range(args.episodes)]  # fmt: skip
    print(f"{len(tasks)} episodes ({args.episodes} per configuration, {args.steps} steps) on {args.workers} workers"
          + ("" if args.margin is None else f", filter margin {args.margin} m") + f", guard {args.guard}" + ("" if args.guard_gamma is None else f" (gains {args.guard_gamma:g})"))
    start = time.perf_counter()
    ctx = mp.get_context("spawn")  # fresh interpreters: no MuJoCo state or GL context inherited
    with ctx.Pool(args.workers) as pool:
        episodes = []
        for done, episode in enumerate(pool.imap_unordered(run_episode, tasks, chunksize=1), 1):
            episodes.append(episode)
            if done % max(1, len(tasks) // 10) == 0:
                print(f"  {done}/{len(tasks)} episodes, {time.perf_counter() - start:.0f} s", flush=True)
    rows = summarise(episodes)
    print_table(rows)
    print(f"wall time {time.perf_counter() - start:.1f} s")

    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / "episodes.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=[fl.name for fl in fields(Episode)])
        writer.writeheader()
        for e in sorted(episodes, key=lambda e: (e.scenario, e.policy, e.barrier, e.points, e.seed)):
            writer.writerow(asdict(e))
    meta = {"episodes_per_configuration": args.episodes, "steps": args.steps, "seed": args.seed, "margin": args.margin,
            "guard": args.guard, "guard_gamma": args.guard_gamma, "workers": args.workers, "quick": args.quick, "cpu_count": os.cpu_count()}  # fmt: skip
    with open(args.out / "summary.json", "w") as f:
        json.dump({"settings": meta, "configurations": rows}, f, indent=2)
    print(f"wrote {args.out / 'episodes.csv'} and {args.out / 'summary.json'}")
    return rows


if __name__ == "__main__":
    main()
