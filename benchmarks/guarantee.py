"""The long guarantee sweep: does the filter keep every obstacle off the arm?

Episodes of ``C3BFReach-v0`` (or ``--env C3BFReachPanda-v0``, the same task on the Panda) over the paper's four scenarios (static, head_on, crossing, multi),
for two policies (uniformly random torques; an adversary that drives the arm point nearest to an
obstacle straight at it at full torque), and filters named as ``c3bf_gym.FILTERS`` names them, each
protecting the whole arm or the tool only: by default the default filter (``c3bf+hocbf``: the C3BF
with its distance-HOCBF guard) and the distance HOCBF, whole-arm and tool-only, and no filter; the
paper's C3BF alone (``c3bf``) on request. Collisions are the environment's own signal
(``info["cost"]``: MuJoCo's signed distances at every physics step), independent of the filter.
Seeds are shared across configurations (episode ``i`` uses seed ``--seed + i`` everywhere), so
configurations are compared on the same episodes.

Per configuration it prints: episodes, episodes with a collision, collision steps, the smallest
clearance seen (m; negative = penetration), infeasible steps (policy steps where rows gave way
beyond their allowance: ``info["safety_infeasible"]``), the same per 1,000 physics steps
(``infeas/1k``) and the physics steps per 1,000 where only the barrier's rows gave way, within
their allowance (``raised/1k``: held with a raised gain, ``StepSafety.gain_raised_steps``), the
policy steps where a row of the last priority (guard, floor, joint limits) gave way (``hard``), the
largest joint speed over the filter's bound seen at the end of a policy step (``max qd``), the
intervention rate (share of steps the filter changed the torque), and the largest per-step mean
filter time. Per-episode rows go to ``episodes.csv`` and the table to ``summary.json`` in
``--out``. Episodes run in ``--workers`` processes, or as Ray tasks with ``--ray`` (the ``rllib``
extra installs Ray): on a local Ray instance of ``--workers`` CPUs, or on the cluster at
``--address``. Each episode depends only on its task, so the tables are the same either way.

Usage::

    python benchmarks/guarantee.py --quick                 # smoke run (~1 min)
    python benchmarks/guarantee.py --episodes 200 --out results/guarantee
    python benchmarks/guarantee.py --episodes 200 --filters c3bf+hocbf/whole_arm --margin 0.03   # a wider margin
    python benchmarks/guarantee.py --episodes 200 --filters c3bf/whole_arm                       # the C3BF alone
    python benchmarks/guarantee.py --episodes 600 --filters c3bf+hocbf/whole_arm --joint-range-reserve 0.3 --untimed
    python benchmarks/guarantee.py --episodes 600 --filters c3bf+hocbf/whole_arm --allowance-level --untimed
    python benchmarks/guarantee.py --episodes 600 --filters c3bf+hocbf/whole_arm --untimed --set joint_speed_fraction=0.4
    python benchmarks/guarantee.py --episodes 600 --ray --address auto                           # on a Ray cluster
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

from c3bf_gym.cli import add_filter_settings
from c3bf_gym.safety import GUARD_GAMMA, FilterConfig
from c3bf_gym.training import filter_config

SCENARIOS = ("static", "head_on", "crossing", "multi")
#: The rows that give way last (priority 1): ``hard`` counts policy steps where any of them did.
HARD_ROWS = ("guard", "floor", "joint_limits", "unmovable", "self_collision")
ENVS = ("C3BFReach-v0", "C3BFReachPanda-v0")
POLICIES = ("random", "adversarial")
#: (filter name, points) in table order; DEFAULT_FILTERS run unless --filters says otherwise.
FILTERS = (("c3bf+hocbf", "whole_arm"), ("c3bf", "whole_arm"), ("hocbf", "whole_arm"), ("c3bf+hocbf", "ee"),
           ("c3bf", "ee"), ("hocbf", "ee"), ("none", "-"))  # fmt: skip
DEFAULT_FILTERS = (("c3bf+hocbf", "whole_arm"), ("hocbf", "whole_arm"), ("c3bf+hocbf", "ee"), ("hocbf", "ee"),
                   ("none", "-"))  # fmt: skip


@dataclass
class Episode:
    scenario: str
    policy: str
    filter: str
    points: str
    seed: int
    steps: int = 0
    collision_steps: int = 0
    min_clearance: float = float("inf")
    infeasible_steps: int = 0
    infeasible_physics_steps: int = 0
    hard_steps: int = 0
    gain_raised_physics_steps: int = 0
    physics_steps: int = 0
    max_speed_ratio: float = 0.0
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
        return np.zeros(m.nu, np.float32)
    _, x, body, centre = best
    jac = np.zeros((3, m.nv))
    mujoco.mj_jac(m, d, jac, None, x, body)
    action = jac.T @ ((centre - x) / max(np.linalg.norm(centre - x), 1e-9)) / u.torque_limit
    peak = np.abs(action).max()
    return np.zeros(m.nu, np.float32) if peak < 1e-12 else np.clip(action / peak, -1, 1).astype(np.float32)


# ----------------------------------------------------------------------------- one episode


def run_episode(task: tuple[str, str, str, str, int, int, str, bool, dict]) -> Episode:
    """One seeded episode: ``(scenario, policy, filter name, points, seed, steps, env id, timed,
    the filter's other FilterConfig settings)``."""
    scenario, policy, name, points, seed, steps, env_id, timed, settings = task
    import gymnasium as gym

    import c3bf_gym  # noqa: F401  (registers C3BFReach-v0)
    from c3bf_gym import SafetyFilter

    start = time.perf_counter()
    env = gym.make(env_id, scenario=scenario)
    filtered = name != "none"
    if filtered:
        env = SafetyFilter(env, name, points=points, **settings)
        if timed:  # every call timed (max_filter_ms), so through the hook's __call__: the same torques as the
            env.hook.record_times()  # env's compiled policy step, bit for bit (tests/test_filter.py)
    u = env.unwrapped
    out = Episode(scenario, policy, name, points, seed)
    speed_bound = env.hook.joint_speed_bound if filtered else None
    if filtered and not timed:
        out.max_filter_ms = np.nan  # the compiled policy step does not time the filter
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    for _ in range(steps):
        action = (rng.uniform(-1, 1, env.action_space.shape).astype(np.float32) if policy == "random"
                  else adversarial_action(u))  # fmt: skip
        _, _, terminated, truncated, info = env.step(action)
        out.steps += 1
        out.collision_steps += int(info["cost"] > 0)
        out.min_clearance = min(out.min_clearance, float(info["min_distance"]))
        out.physics_steps += u.frame_skip
        if filtered:
            out.infeasible_steps += int(info["safety_infeasible"])
            out.infeasible_physics_steps += info["safety"]["infeasible_steps"]
            out.hard_steps += any(info["safety"][f"violation_{kind}"] > 0.0 for kind in HARD_ROWS)
            out.gain_raised_physics_steps += info["safety"]["gain_raised_steps"]
            if speed_bound is not None:
                speed = np.abs(u.data.qvel[env.hook.robot.dof_ids]) / speed_bound
                out.max_speed_ratio = max(out.max_speed_ratio, float(speed.max()))
            out.interventions += int(info["safety_intervened"])
            if timed:
                report = env.hook.report  # wall-clock time is kept off info (deterministic)
                out.max_filter_ms = max(out.max_filter_ms, 1e3 * report.solve_time / max(report.substeps, 1))
                env.hook.solve_times.clear()  # only the report's sum is kept
        if terminated or truncated:
            break
    env.close()
    out.wall_s = time.perf_counter() - start
    return out


# ----------------------------------------------------------------------------- sweep


def _spell(entry: tuple[str, str]) -> str:
    """A (filter, points) pair as --filters spells it: "c3bf+hocbf/whole_arm", or "none"."""
    return entry[0] if entry[0] == "none" else "/".join(entry)


def summarise(episodes: list[Episode]) -> list[dict]:
    groups: dict[tuple, list[Episode]] = {}
    for e in episodes:
        groups.setdefault((e.scenario, e.policy, e.filter, e.points), []).append(e)
    rows = []
    for (scenario, policy, name, points), group in groups.items():
        steps = sum(e.steps for e in group)
        rows.append({
            "scenario": scenario, "policy": policy, "filter": name, "points": points,
            "episodes": len(group),
            "collision_episodes": sum(e.collision_steps > 0 for e in group),
            "collision_steps": sum(e.collision_steps for e in group),
            "min_clearance": min(e.min_clearance for e in group),
            "infeasible_steps": sum(e.infeasible_steps for e in group),
            "infeasible_per_1000_physics_steps": 1e3 * sum(e.infeasible_physics_steps for e in group)
            / max(sum(e.physics_steps for e in group), 1),
            "gain_raised_per_1000_physics_steps": 1e3 * sum(e.gain_raised_physics_steps for e in group)
            / max(sum(e.physics_steps for e in group), 1),
            "hard_steps": sum(e.hard_steps for e in group),
            "max_speed_ratio": max(e.max_speed_ratio for e in group),
            "intervention_rate": sum(e.interventions for e in group) / max(steps, 1),
            "max_filter_ms": max(e.max_filter_ms for e in group),
            "steps": steps,
        })  # fmt: skip
    order = {name: i for i, name in enumerate(SCENARIOS + POLICIES)}
    filters = {f: i for i, f in enumerate(FILTERS)}
    rows.sort(key=lambda r: (order[r["scenario"]], order[r["policy"]], filters[(r["filter"], r["points"])]))
    return rows


def run_tasks(tasks: list[tuple], workers: int, use_ray: bool = False, address: str | None = None):
    """Yield :func:`run_episode`'s results, in order of completion: from a pool of ``workers``
    fresh processes, or (``use_ray``) as Ray tasks of one CPU each on a local Ray instance of
    ``workers`` CPUs, or on the cluster at ``address``."""
    if not use_ray:
        ctx = mp.get_context("spawn")  # fresh interpreters: no MuJoCo state or GL context inherited
        with ctx.Pool(workers) as pool:
            yield from pool.imap_unordered(run_episode, tasks, chunksize=1)
        return
    import ray

    started = not ray.is_initialized()
    if started:
        ray.init(address=address, include_dashboard=False, log_to_driver=False,
                 **({"num_cpus": workers} if address is None else {}))  # fmt: skip
    try:
        remote = ray.remote(num_cpus=1)(run_episode)
        pending = [remote.remote(task) for task in tasks]
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            yield ray.get(done[0])
    finally:
        if started:
            ray.shutdown()


def print_table(rows: list[dict]) -> None:
    header = (f"{'scenario':<9} {'policy':<11} {'filter':<21} | {'episodes':>8} {'coll.ep':>7} {'coll.steps':>10} "
              f"{'min clear.':>10} {'infeas.steps':>12} {'infeas/1k':>9} {'raised/1k':>9} {'hard':>5} {'max qd':>6} "
              f"{'interv.':>7} {'max ms':>8}")  # fmt: skip
    print(header)
    print("-" * len(header))
    for r in rows:
        name = "none" if r["filter"] == "none" else f"{r['filter']}/{r['points']}"
        print(f"{r['scenario']:<9} {r['policy']:<11} {name:<21} | {r['episodes']:>8} {r['collision_episodes']:>7} "
              f"{r['collision_steps']:>10} {r['min_clearance']:>10.4f} {r['infeasible_steps']:>12} "
              f"{r['infeasible_per_1000_physics_steps']:>9.2f} {r['gain_raised_per_1000_physics_steps']:>9.2f} "
              f"{r['hard_steps']:>5} "
              f"{r['max_speed_ratio']:>6.2f} "
              f"{100 * r['intervention_rate']:>6.1f}% {r['max_filter_ms']:>8.1f}")  # fmt: skip


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=200, help="episodes per configuration (default 200)")
    parser.add_argument("--steps", type=int, default=250, help="steps per episode (default 250: a full episode)")
    parser.add_argument("--workers", type=int, default=2, help="worker processes, or a local Ray instance's CPUs (default 2)")
    parser.add_argument("--ray", action="store_true", help="run the episodes as Ray tasks (the rllib extra installs Ray)")
    parser.add_argument("--address", help="with --ray: the cluster to join (e.g. auto); default: a local Ray instance")
    parser.add_argument("--seed", type=int, default=0, help="seed of episode 0 (episode i uses seed + i)")
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), choices=SCENARIOS)
    parser.add_argument("--policies", nargs="+", default=list(POLICIES), choices=POLICIES)
    parser.add_argument("--filters", nargs="+", default=[_spell(f) for f in DEFAULT_FILTERS],
                        choices=[_spell(f) for f in FILTERS],
                        help="filter/points combinations (filter names: c3bf_gym.FILTERS)")  # fmt: skip
    parser.add_argument("--margin", type=float, help=f"the filters' margin [m] (default {FilterConfig.margin})")
    parser.add_argument("--guard-gamma", type=float,
                        help=f"the gains [1/s] of c3bf+hocbf's guard (default {GUARD_GAMMA:g})")
    parser.add_argument("--joint-range-reserve", type=float,
                        help="the filters' joint range reserve [rad] (default 0: none; FilterConfig.joint_range_reserve)")
    parser.add_argument("--allowance-level", action="store_true",
                        help="the barrier's rows held within their allowance before any gives way beyond it "
                             "(FilterConfig.allowance_level; needs a guard: c3bf+hocbf)")  # fmt: skip
    add_filter_settings(parser, "--set", note=" (every filtered configuration; see also the options above)")
    parser.add_argument("--env", choices=ENVS, default=ENVS[0], help="the environment (robot)")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/guarantee"), help="output directory")
    parser.add_argument("--untimed", action="store_true",
                        help="run the filter inside the environment's compiled policy step, as training does (the "
                             "same torques, faster); the filter is then not timed: max_filter_ms is nan")
    parser.add_argument("--quick", action="store_true", help="smoke run: 2 episodes of 100 steps per configuration")
    args = parser.parse_args(argv)
    if args.quick:
        args.episodes, args.steps = 2, 100
    if args.episodes < 1 or args.steps < 1 or args.workers < 1:
        parser.error("--episodes, --steps and --workers must be >= 1")
    if args.margin is not None and not (np.isfinite(args.margin) and args.margin >= 0):
        parser.error(f"--margin must be a finite number >= 0 (m), got {args.margin}")
    if args.joint_range_reserve is not None and not (np.isfinite(args.joint_range_reserve) and args.joint_range_reserve >= 0):
        parser.error(f"--joint-range-reserve must be a finite number >= 0 (rad), got {args.joint_range_reserve}")
    if args.guard_gamma is not None and not (np.isfinite(args.guard_gamma) and args.guard_gamma > 0):
        parser.error(f"--guard-gamma must be a finite number > 0 (1/s), got {args.guard_gamma}")
    if args.address is not None and not args.ray:
        parser.error("--address is the Ray cluster of --ray; add --ray")
    if args.ray:
        try:
            import ray  # noqa: F401
        except ImportError:
            parser.error('--ray needs Ray: pip install "c3bf-gym[rllib]"')
    guarded = {"guard_gamma": args.guard_gamma, "allowance_level": args.allowance_level or None}
    for key, value in guarded.items():
        if value is not None and not any(f.startswith("c3bf+hocbf/") for f in args.filters):
            parser.error(f"--{key.replace('_', '-')} is a setting of c3bf+hocbf's guard; --filters has no c3bf+hocbf")

    filters = [tuple(f.split("/")) if f != "none" else ("none", "-") for f in args.filters]
    common = {"margin": args.margin, "joint_range_reserve": args.joint_range_reserve}

    def settings(name: str) -> dict:
        """The FilterConfig settings given for filter ``name`` (the guard's only where it has one)."""
        chosen = {**common, **(guarded if name == "c3bf+hocbf" else {})}
        return {**{key: value for key, value in chosen.items() if value is not None}, **dict(args.set)}

    options = {key for key, value in {**common, **guarded}.items() if value is not None}
    twice = sorted(options & {key for key, _ in args.set})
    if twice:
        parser.error(f"--set gives {', '.join(twice)}, which its own option gives too: give each setting once")
    if args.set and all(b == "none" for b, _ in filters):
        parser.error("--set changes the filters' settings; --filters has no filter")
    for name in sorted({b for b, _ in filters if b != "none"}):
        try:
            filter_config(name, None, dict(args.set))  # refuses the settings that name the filter's rows
            FilterConfig.named(name, **settings(name))
        except ValueError as error:
            parser.error(f"--set for filter {name}: {error}")

    tasks = [(s, p, b, pts, args.seed + i, args.steps, args.env, not args.untimed, settings(b))
             for s in args.scenarios for p in args.policies for b, pts in filters for i in range(args.episodes)]  # fmt: skip
    where = (f"Ray at {args.address}" if args.address else f"a local Ray instance of {args.workers} CPUs") if args.ray else f"{args.workers} workers"
    print(f"{args.env}: {len(tasks)} episodes ({args.episodes} per configuration, {args.steps} steps) on {where}"
          + ("" if args.margin is None else f", filter margin {args.margin} m")
          + ("" if args.guard_gamma is None else f", guard gains {args.guard_gamma:g}")
          + ("" if args.joint_range_reserve is None else f", joint range reserve {args.joint_range_reserve:g} rad")
          + (", the barrier's allowance level" if args.allowance_level else "")
          + "".join(f", {key}={value!r}" for key, value in args.set))
    start = time.perf_counter()
    episodes = []
    for done, episode in enumerate(run_tasks(tasks, args.workers, args.ray, args.address), 1):
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
        for e in sorted(episodes, key=lambda e: (e.scenario, e.policy, e.filter, e.points, e.seed)):
            writer.writerow(asdict(e))
    meta = {"episodes_per_configuration": args.episodes, "steps": args.steps, "seed": args.seed, "margin": args.margin,
            "guard_gamma": args.guard_gamma, "joint_range_reserve": args.joint_range_reserve, "allowance_level": args.allowance_level, "set": dict(args.set), "env": args.env, "workers": args.workers, "ray": args.address or args.ray, "quick": args.quick, "cpu_count": os.cpu_count()}  # fmt: skip
    with open(args.out / "summary.json", "w") as f:
        json.dump({"settings": meta, "configurations": rows}, f, indent=2)
    print(f"wrote {args.out / 'episodes.csv'} and {args.out / 'summary.json'}")
    return rows


if __name__ == "__main__":
    main()
