"""The paper's experiments: four scenarios, no filter vs distance HOCBF vs C3BF.

The nominal policy is the paper's: a Cartesian impedance controller tracking a minimum-jerk
path from the tool's start to the goal, at every physics step. Each seed fixes one episode
(goal, obstacle speeds and offsets inside the envelope), run once per filter, so the filters are
compared on identical episodes and the unfiltered run is the reference for tracking deviation.

Outputs (``--out``): ``table.csv``, ``table.json``, ``table.md`` (per scenario and filter),
``sensing.csv`` (perception-boundary study), ``figures/*.png`` and, with ``--video``,
``videos/*.gif``.
"""

from __future__ import annotations

import argparse
import csv
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from c3bf_gym.envs.reach import C3BFReachEnv
from c3bf_gym.safety import FILTERS
from c3bf_gym.safety.config import POINTS
from c3bf_gym.metrics import EpisodeRecord, summarize
from c3bf_gym.wrappers import ImpedanceHook, SafetyFilter, default_impedance

__all__ = ["ExperimentConfig", "MinimumJerk", "add_parser", "run_episode", "run_experiments"]

PAPER_SCENARIOS = ("static", "head_on", "crossing", "multi")
#: "none" and the named filters (:data:`~c3bf_gym.safety.FILTERS`): "c3bf" is the paper's filter,
#: the C3BF's rows alone, so the default set compares the barriers themselves; "c3bf+hocbf" is
#: ``SafetyFilter``'s default, the C3BF with its distance-HOCBF guard.
EXPERIMENT_FILTERS = ("none", *FILTERS)


class MinimumJerk:
    """Minimum-jerk motion from ``start`` to ``goal`` in ``duration`` s, then holding the goal."""

    def __init__(self, start: np.ndarray, goal: np.ndarray, duration: float) -> None:
        self.start, self.delta, self.duration = np.array(start), np.array(goal) - start, float(duration)

    def __call__(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        s = min(max(t / self.duration, 0.0), 1.0)
        pos = 10 * s**3 - 15 * s**4 + 6 * s**5
        vel = (30 * s**2 - 60 * s**3 + 30 * s**4) / self.duration if s < 1.0 else 0.0
        acc = (60 * s - 180 * s**2 + 120 * s**3) / self.duration**2 if s < 1.0 else 0.0
        return self.start + pos * self.delta, vel * self.delta, acc * self.delta


@dataclass
class ExperimentConfig:
    """Options of ``c3bf-gym experiments`` (see ``--help``)."""

    out: Path = Path("results")
    scenarios: tuple[str, ...] = PAPER_SCENARIOS
    filters: tuple[str, ...] = ("none", "hocbf", "c3bf")
    seeds: int = 3
    first_seed: int = 0
    points: str = "whole_arm"
    gamma: float | None = None
    margin: float = 0.02
    duration: float = 5.0
    move_time: float = 2.5
    video: bool = False
    sensing_radii: tuple[float, ...] = (0.01, 0.05, 0.2, 1.0)
    sensing_speeds: tuple[float, ...] = (0.4, 1.5)
    sensing_seeds: int = 2
    progress: bool = True
    env_kwargs: dict[str, Any] = field(default_factory=dict)

    def validate(self) -> None:
        from c3bf_gym.scenarios import get_scenario

        for s in self.scenarios:
            get_scenario(s)
        for f in self.filters:
            if f not in EXPERIMENT_FILTERS:
                raise ValueError(f"unknown filter {f!r}; valid choices: {', '.join(map(repr, EXPERIMENT_FILTERS))}")
        if self.points not in POINTS:
            raise ValueError(f"unknown points {self.points!r}; valid choices: {', '.join(map(repr, POINTS))}")
        if self.seeds < 1 or self.sensing_seeds < 0:
            raise ValueError("seeds must be >= 1 and sensing_seeds >= 0")
        if not (self.duration > 0 and self.move_time > 0):
            raise ValueError("duration and move_time must be > 0 (s)")
        if any(not r > 0 for r in self.sensing_radii):
            raise ValueError(f"sensing radii must be > 0 (m), got {self.sensing_radii}")
        if any(not v >= 0 for v in self.sensing_speeds):
            raise ValueError(f"sensing speeds must be >= 0 (m/s), got {self.sensing_speeds}")


def run_episode(
    scenario: str,
    filter_name: str,
    seed: int,
    config: ExperimentConfig,
    env_kwargs: dict[str, Any] | None = None,
    filter_kwargs: dict[str, Any] | None = None,
    render: bool = False,
) -> tuple[EpisodeRecord, list[np.ndarray]]:
    """One episode with the impedance controller as nominal policy; returns (record, frames)."""
    kwargs = {**config.env_kwargs, **(env_kwargs or {})}
    base = C3BFReachEnv(scenario=scenario, render_mode="rgb_array" if render else None, width=400, height=300, **kwargs)
    env = base
    if filter_name != "none":
        env = SafetyFilter(base, filter_name, points=config.points, gamma=config.gamma, margin=config.margin,
                           **(filter_kwargs or {}))  # fmt: skip
        env.hook.record_times()
    env.reset(seed=seed)
    start = base.data.site_xpos[base.ee_site_id].copy()
    goal = base.goal.copy()
    hook = ImpedanceHook(base, default_impedance(base), MinimumJerk(start, goal, config.move_time))
    base.add_torque_hook(hook, stage="nominal")
    record = EpisodeRecord.start(base)
    frames = [base.render()] if render else []
    zero = np.zeros(base.action_space.shape, dtype=np.float32)
    for step in range(int(round(config.duration / base.dt))):
        _, reward, terminated, truncated, info = env.step(zero)
        record.add(base, reward, info)
        if filter_name != "none":
            record.tau_nominal.append(env.hook.report.tau_nominal)
            record.tau.append(env.hook.report.tau)
        if render and step % 2 == 1:
            frames.append(base.render())
        if terminated or truncated:
            break
    if filter_name != "none":
        record.solve_times = env.hook.solve_times
    env.close()
    return record, frames


def _aggregate(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per (scenario, filter) aggregate of per-episode summaries."""
    def mean(key: str) -> float:
        values = [r[key] for r in rows if key in r and np.isfinite(r[key])]
        return float(np.mean(values)) if values else float("nan")

    solve = np.concatenate([r["_solve_times"] for r in rows]) * 1e6 if "_solve_times" in rows[0] else np.array([])
    return {
        "episodes": len(rows),
        "collision_episodes": int(sum(r["collision"] for r in rows)),
        "collision_steps": int(sum(r["collision_steps"] for r in rows)),
        "min_clearance_m": float(min(r["min_clearance"] for r in rows)),
        "reached": mean("reached"),
        "time_to_goal_s": mean("time_to_goal"),
        "tracking_deviation_m": mean("tracking_deviation"),
        "intervention_share": mean("intervention_share"),
        "infeasible_steps": int(sum(r.get("infeasible_steps", 0) for r in rows)),
        "mean_correction_Nm": mean("mean_correction"),
        "solve_us_median": float(np.median(solve)) if len(solve) else float("nan"),
        "solve_us_p99": float(np.percentile(solve, 99)) if len(solve) else float("nan"),
    }


COLUMNS = (
    "scenario", "filter", "episodes", "collision_episodes", "collision_steps", "min_clearance_m", "reached",
    "time_to_goal_s", "tracking_deviation_m", "intervention_share", "infeasible_steps", "mean_correction_Nm",
    "solve_us_median", "solve_us_p99",
)  # fmt: skip


def _markdown(rows: Sequence[dict[str, Any]], columns: Sequence[str]) -> str:
    def fmt(v: Any) -> str:
        if isinstance(v, float):
            return "n/a" if not np.isfinite(v) else f"{v:.3g}"
        return str(v)

    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(fmt(r[c]) for c in columns) + " |" for r in rows]
    return "\n".join(lines)


def _write_table(rows: list[dict[str, Any]], columns: Sequence[str], stem: Path) -> str:
    stem.parent.mkdir(parents=True, exist_ok=True)
    with open(stem.with_suffix(".csv"), "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(columns), extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    stem.with_suffix(".json").write_text(json.dumps(rows, indent=2))
    text = _markdown(rows, columns)
    stem.with_suffix(".md").write_text(text + "\n")
    return text


def _progress(total: int, enabled: bool, desc: str):
    from tqdm import tqdm

    return tqdm(total=total, disable=not enabled, desc=desc, unit="episode")


def run_experiments(config: ExperimentConfig) -> dict[str, Any]:
    """Run everything ``config`` asks for; write tables and figures; return the tables."""
    from c3bf_gym import plots

    config.validate()
    out = Path(config.out)
    figures = out / "figures"
    seeds = range(config.first_seed, config.first_seed + config.seeds)
    per_episode: dict[tuple[str, str], list[dict[str, Any]]] = {}
    bar = _progress(len(config.scenarios) * len(config.filters) * config.seeds, config.progress, "experiments")
    for scenario in config.scenarios:
        for seed in seeds:
            records: dict[str, EpisodeRecord] = {}
            for filter_name in config.filters:
                record, _ = run_episode(scenario, filter_name, seed, config)
                records[filter_name] = record
                bar.update()
            reference = records.get("none")
            for filter_name, record in records.items():
                summary = summarize(record, None if filter_name == "none" else reference)
                if record.solve_times:
                    summary["_solve_times"] = np.asarray(record.solve_times)
                per_episode.setdefault((scenario, filter_name), []).append(summary)
            if seed == config.first_seed:
                title = f"{scenario} (seed {seed})"
                plots.plot_trajectories(records, title, figures / f"{scenario}_trajectories.png")
                plots.plot_clearance(records, title, config.margin, figures / f"{scenario}_clearance.png")
                if any(r.min_h for r in records.values()):
                    plots.plot_barrier(records, title, figures / f"{scenario}_barrier.png")
                if "c3bf" in records:
                    plots.plot_torques(records["c3bf"], title, figures / f"{scenario}_torques.png")
    bar.close()
    table = [{"scenario": s, "filter": f, **_aggregate(rows)} for (s, f), rows in per_episode.items()]
    text = _write_table(table, COLUMNS, out / "table")
    if {"hocbf", "c3bf"} & set(config.filters):
        summary_rows = [{**r, "reached": r["reached"], "mean_correction": r["mean_correction_Nm"], "tracking_deviation": r["tracking_deviation_m"]} for r in table]
        plots.plot_summary(summary_rows, figures / "summary_c3bf_vs_hocbf.png")
    result: dict[str, Any] = {"table": table, "markdown": text}
    if config.sensing_seeds and config.sensing_radii:
        result["sensing"] = _sensing_study(config, out, figures)
    if config.video:
        _videos(config, out / "videos")
    (out / "config.json").write_text(json.dumps({**asdict(config), "out": str(config.out)}, indent=2, default=str))
    return result


def _sensing_study(config: ExperimentConfig, out: Path, figures: Path) -> str:
    """Collision rate against the sensing radius at the envelope's top speed and beyond.

    Each (speed, scenario, seed) episode is also run without a filter, whose collision rate
    (independent of the radius) is the reference: a radius is safe when the filter keeps the
    episodes that collide unfiltered collision-free.
    """
    from c3bf_gym import plots

    filters = [f for f in config.filters if f != "none"] or ["c3bf"]
    scenarios = [s for s in ("head_on", "crossing") if s in config.scenarios] or ["head_on"]
    seeds = range(config.first_seed, config.first_seed + config.sensing_seeds)
    runs = [("none", None)] + [(f, r) for f in filters for r in config.sensing_radii]
    rows = []
    bar = _progress(len(config.sensing_speeds) * len(runs) * len(scenarios) * len(seeds), config.progress, "sensing sweep")
    for speed in config.sensing_speeds:
        for filter_name, radius in runs:
            collisions, infeasible, substeps = 0, 0, 0
            for scenario in scenarios:
                for seed in seeds:
                    env_kwargs: dict[str, Any] = {"obstacle_speed_range": (speed, speed)}
                    if radius is not None:
                        env_kwargs["sensing_radius"] = radius
                    record, _ = run_episode(scenario, filter_name, seed, config, env_kwargs=env_kwargs)
                    collisions += int(np.sum(record.cost) > 0)
                    infeasible += int(np.sum(~np.asarray(record.feasible))) if record.feasible else 0
                    substeps += len(record.feasible)
                    bar.update()
            episodes = len(scenarios) * len(seeds)
            rows.append(
                {
                    "filter": filter_name,
                    "sensing_radius": float("nan") if radius is None else radius,
                    "obstacle_speed": speed,
                    "episodes": episodes,
                    "collision_episodes": collisions,
                    "collision_rate": collisions / episodes,
                    "infeasible_share": infeasible / substeps if substeps else float("nan"),
                }
            )
    bar.close()
    columns = ("filter", "sensing_radius", "obstacle_speed", "episodes", "collision_episodes", "collision_rate", "infeasible_share")
    text = _write_table(rows, columns, out / "sensing")
    plots.plot_sensing(rows, figures / "sensing_boundary.png")
    return text


def _videos(config: ExperimentConfig, folder: Path) -> None:
    import os
    import sys

    import imageio.v3 as iio

    if sys.platform.startswith("linux") and not os.environ.get("DISPLAY"):
        os.environ.setdefault("MUJOCO_GL", "egl")  # headless: offscreen rendering through EGL
    folder.mkdir(parents=True, exist_ok=True)
    for scenario in config.scenarios:
        _, frames = run_episode(scenario, "c3bf", config.first_seed, config, render=True)
        iio.imwrite(folder / f"{scenario}_c3bf.gif", np.stack(frames), duration=40, loop=0)


def add_parser(sub: argparse._SubParsersAction) -> None:
    from c3bf_gym.cli import _nonnegative_float, _nonnegative_int, _positive_float, _positive_int
    from c3bf_gym.scenarios import SCENARIOS

    p = sub.add_parser(
        "experiments",
        help="the paper's experiments: 4 scenarios x {no filter, HOCBF, C3BF} (the main job)",
        description="Run the Cartesian impedance controller as nominal policy on the paper's scenarios "
        "with no filter, the distance HOCBF and the C3BF filter over seeded episodes; write a results "
        "table (CSV, JSON, markdown), figures per scenario, a C3BF-vs-HOCBF summary figure and a "
        "perception-boundary (sensing radius) study.",
    )
    p.add_argument("--out", type=Path, default=Path("results"), help="output directory (default: results)")
    p.add_argument("--seeds", type=_positive_int, default=ExperimentConfig.seeds, help="seeded episodes per scenario and filter")
    p.add_argument("--first-seed", type=_nonnegative_int, default=0)
    p.add_argument("--scenarios", nargs="+", choices=[s for s in SCENARIOS if s not in ("random", "none")], default=list(PAPER_SCENARIOS))
    p.add_argument("--filters", nargs="+", choices=EXPERIMENT_FILTERS, default=list(ExperimentConfig.filters),
                   help="'c3bf': the paper's C3BF alone; 'c3bf+hocbf': SafetyFilter's default, with its distance guard")  # fmt: skip
    p.add_argument("--points", choices=POINTS, default="whole_arm", help="protect the whole arm or only the tool (the paper)")
    p.add_argument("--gamma", type=_positive_float, default=None, help="class-K gain [1/s] (default: the barrier's, 5)")
    p.add_argument("--margin", type=_nonnegative_float, default=ExperimentConfig.margin, help="extra clearance [m]")
    p.add_argument("--duration", type=_positive_float, default=ExperimentConfig.duration, help="episode length [s]")
    p.add_argument("--sensing-radius", dest="sensing_radii", nargs="*", type=_positive_float,
                   default=list(ExperimentConfig.sensing_radii),
                   help="radii [m] of the perception-boundary sweep (none: skip the sweep)")  # fmt: skip
    p.add_argument("--sensing-speeds", nargs="+", type=_nonnegative_float, default=list(ExperimentConfig.sensing_speeds),
                   help="obstacle speeds [m/s] of the sweep: the envelope's top (0.4) and beyond")  # fmt: skip
    p.add_argument("--sensing-seeds", type=_nonnegative_int, default=ExperimentConfig.sensing_seeds,
                   help="episodes per radius, speed and scenario (head_on, crossing)")  # fmt: skip
    p.add_argument("--video", action="store_true", help="also record a GIF per scenario (C3BF, first seed)")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    config = ExperimentConfig(
        out=args.out, scenarios=tuple(args.scenarios), filters=tuple(args.filters), seeds=args.seeds,
        first_seed=args.first_seed, points=args.points, gamma=args.gamma, margin=args.margin,
        duration=args.duration, video=args.video, sensing_radii=tuple(args.sensing_radii),
        sensing_speeds=tuple(args.sensing_speeds),
        sensing_seeds=args.sensing_seeds if args.sensing_radii else 0, progress=not args.no_progress,
    )  # fmt: skip
    result = run_experiments(config)
    print(result["markdown"])
    if "sensing" in result:
        print()
        print(result["sensing"])
    print(f"\nresults written to {args.out}/ (table.csv, table.json, table.md, figures/)")
    return 0
