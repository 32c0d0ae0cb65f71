"""The paper's experiments: four scenarios, no filter vs distance HOCBF vs C3BF.

The nominal policy is the paper's: a Cartesian impedance controller tracking a minimum-jerk
path from the tool's start to the goal, at every physics step. Each seed fixes one episode
(goal, obstacle speeds and offsets inside the envelope), run once per filter, so the filters are
compared on identical episodes and the unfiltered run is the reference for tracking deviation.

Outputs (``--out``): ``table.csv``, ``table.json``, ``table.md`` (per scenario and filter),
``sensing.csv``, ``sensing.json``, ``sensing.md`` (perception-boundary sweep), ``config.json``
(the options and the code version), ``figures/*.png`` and, with ``--video``, ``videos/*.gif``.
``scripts/regenerate_tables.py`` writes the docs' tables (``docs/results/experiments_ur5e/``,
``experiments_panda/``) from the committed copies of ``table.json`` and ``sensing.json`` with
:func:`markdown_table`.
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
from c3bf_gym.safety import FILTERS, FilterConfig
from c3bf_gym.safety.config import POINTS
from c3bf_gym.metrics import EpisodeRecord, summarize
from c3bf_gym.wrappers import ImpedanceHook, SafetyFilter, default_impedance

__all__ = [
    "ExperimentConfig", "MinimumJerk", "add_parser", "annotate_frame", "config_from_args", "markdown_table", "project",
    "run_episode", "run_experiments",
]  # fmt: skip

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


#: The scenarios of the perception-boundary sweep (its obstacles approach the arm); it runs on
#: those of them that ``--scenarios`` selects.
SENSING_SCENARIOS = ("head_on", "crossing")

#: ``--quick``: a smoke run of every output (1 seed, 3-s episodes, a sweep of 2 radii at one speed
#: with 1 seed). Replaces only the options left at their defaults.
QUICK: dict[str, Any] = {
    "seeds": (0,),
    "duration": 3.0,
    "sensing_radii": (0.05, 1.0),
    "sensing_speeds": (0.4,),
    "sensing_seeds": (0,),
}


@dataclass
class ExperimentConfig:
    """Options of ``c3bf-gym experiments`` (see ``--help``); the defaults are the main job's.

    ``robot`` names the arm (:data:`~c3bf_gym.envs.reach.ROBOTS`: ``ur5e``, ``C3BFReach-v0``'s,
    or ``panda``, ``C3BFReachPanda-v0``'s). ``seeds`` and ``sensing_seeds`` are seed ids (one
    episode per seed). ``table`` runs the
    results table with its figures; ``sensing`` runs the perception-boundary sweep on the
    :data:`SENSING_SCENARIOS` among ``scenarios``, skipped when there is none.
    """

    out: Path = Path("results")
    robot: str = "ur5e"
    scenarios: tuple[str, ...] = PAPER_SCENARIOS
    filters: tuple[str, ...] = ("none", "hocbf", "c3bf")
    seeds: tuple[int, ...] = (0, 1, 2)
    points: str = "whole_arm"
    gamma: float | None = None
    margin: float = FilterConfig.margin
    duration: float = 5.0
    move_time: float = 2.5
    video: bool = False
    table: bool = True
    sensing: bool = True
    sensing_radii: tuple[float, ...] = (0.01, 0.05, 0.2, 1.0)
    sensing_speeds: tuple[float, ...] = (0.4, 1.5)
    sensing_seeds: tuple[int, ...] = (0, 1)
    progress: bool = True
    env_kwargs: dict[str, Any] = field(default_factory=dict)

    @property
    def sensing_scenarios(self) -> tuple[str, ...]:
        """The scenarios the sensing sweep runs on: :data:`SENSING_SCENARIOS` among ``scenarios``."""
        return tuple(s for s in SENSING_SCENARIOS if s in self.scenarios)

    def validate(self) -> None:
        from c3bf_gym.envs.reach import ROBOTS
        from c3bf_gym.scenarios import get_scenario

        if self.robot not in ROBOTS:
            raise ValueError(f"unknown robot {self.robot!r}; valid choices: {', '.join(map(repr, ROBOTS))}")
        if "robot" in self.env_kwargs:
            raise ValueError("env_kwargs must not hold 'robot': set ExperimentConfig.robot")
        for s in self.scenarios:
            get_scenario(s)
        for f in self.filters:
            if f not in EXPERIMENT_FILTERS:
                raise ValueError(f"unknown filter {f!r}; valid choices: {', '.join(map(repr, EXPERIMENT_FILTERS))}")
        if self.points not in POINTS:
            raise ValueError(f"unknown points {self.points!r}; valid choices: {', '.join(map(repr, POINTS))}")
        for name in ("seeds", "sensing_seeds"):
            ids = getattr(self, name)
            if not ids or any(isinstance(i, bool) or not isinstance(i, (int, np.integer)) or i < 0 for i in ids):
                raise ValueError(f"{name} must be one or more seed ids (whole numbers >= 0), got {ids}")
            if len(set(ids)) != len(ids):
                raise ValueError(f"{name} repeats a seed id: {ids}")
        if not (self.duration > 0 and self.move_time > 0):
            raise ValueError("duration and move_time must be > 0 (s)")
        if not self.sensing_radii or any(not r > 0 for r in self.sensing_radii):
            raise ValueError(f"sensing radii must be one or more values > 0 (m), got {self.sensing_radii}")
        if not self.sensing_speeds or any(not v >= 0 for v in self.sensing_speeds):
            raise ValueError(f"sensing speeds must be one or more values >= 0 (m/s), got {self.sensing_speeds}")
        if not (self.table or self.sensing):
            raise ValueError("nothing to run: the table and the sensing sweep are both off")
        if self.sensing and not self.table and not self.sensing_scenarios:
            raise ValueError(f"the sensing sweep runs on {' and '.join(SENSING_SCENARIOS)} only; --scenarios selects neither")


def run_episode(
    scenario: str,
    filter_name: str,
    seed: int,
    config: ExperimentConfig,
    env_kwargs: dict[str, Any] | None = None,
    filter_kwargs: dict[str, Any] | None = None,
    render: bool = False,
) -> tuple[EpisodeRecord, list[np.ndarray]]:
    """One episode with the impedance controller as nominal policy; returns (record, frames).

    With ``render``, frames (400 x 300 RGB, every second policy step: real time at 25 fps) carry
    :func:`annotate_frame`'s overlay: the filter's name, the simulated time and a ring on the goal.
    """
    kwargs = {**config.env_kwargs, **(env_kwargs or {})}
    base = C3BFReachEnv(scenario=scenario, robot=config.robot, render_mode="rgb_array" if render else None,
                        width=400, height=300, **kwargs)  # fmt: skip
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

    def frame() -> np.ndarray:
        pixel = project(base, goal, base.camera_name)
        return annotate_frame(base.render(), f"{FILTER_TITLES.get(filter_name, filter_name)}   t = {base.data.time:.2f} s", pixel)

    frames = [frame()] if render else []
    zero = np.zeros(base.action_space.shape, dtype=np.float32)
    for step in range(int(round(config.duration / base.dt))):
        _, reward, terminated, truncated, info = env.step(zero)
        record.add(base, reward, info)
        if filter_name != "none":
            record.tau_nominal.append(env.hook.report.tau_nominal)
            record.tau.append(env.hook.report.tau)
        if render and step % 2 == 1:
            frames.append(frame())
        if terminated or truncated:
            break
    if filter_name != "none":
        record.solve_times = env.hook.solve_times
    env.close()
    return record, frames


#: The filters' names in the videos' overlay.
FILTER_TITLES = {"none": "no filter", "hocbf": "distance HOCBF", "c3bf": "C3BF", "c3bf+hocbf": "C3BF + distance guard"}


def project(env: C3BFReachEnv, point: np.ndarray, camera: str) -> tuple[float, float] | None:
    """Pixel ``(column, row)`` of the world ``point`` [m] in ``env``'s rendered frames from the
    fixed camera named ``camera`` (pinhole: MuJoCo's vertical field of view, square pixels);
    None when the point is behind the camera."""
    import mujoco

    cam = mujoco.mj_name2id(env.model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
    rel = env.data.cam_xmat[cam].reshape(3, 3).T @ (np.asarray(point, dtype=float) - env.data.cam_xpos[cam])
    if rel[2] >= 0.0:  # MuJoCo cameras look along their -z axis
        return None
    focal = 0.5 * env.height / np.tan(np.deg2rad(env.model.cam_fovy[cam]) / 2)
    return 0.5 * env.width + focal * rel[0] / -rel[2], 0.5 * env.height - focal * rel[1] / -rel[2]


#: Height of the overlay's text box [px], in the frame's top-left corner.
OVERLAY_HEIGHT = 24


def annotate_frame(frame: np.ndarray, text: str, goal: tuple[float, float] | None = None) -> np.ndarray:
    """A copy of the RGB ``frame`` with ``text`` in white on a dark box in its top-left corner
    (:data:`OVERLAY_HEIGHT` px high, as wide as the text) and, at the pixel ``goal`` (column,
    row; if given), a bright green ring with a cross and the word "goal"."""
    from PIL import Image, ImageDraw, ImageFont

    image = Image.fromarray(np.ascontiguousarray(frame[..., :3]))
    draw = ImageDraw.Draw(image)
    font = ImageFont.load_default(size=14)
    draw.rectangle((0, 0, 12 + draw.textlength(text, font=font), OVERLAY_HEIGHT), fill=(20, 20, 20))
    draw.text((6, 4), text, fill=(255, 255, 255), font=font)
    if goal is not None:
        u, v = goal
        for radius, color in ((11, (0, 0, 0)), (9, (60, 255, 60))):
            draw.ellipse((u - radius, v - radius, u + radius, v + radius), outline=color, width=3)
        draw.line((u - 4, v, u + 4, v), fill=(60, 255, 60), width=2)
        draw.line((u, v - 4, u, v + 4), fill=(60, 255, 60), width=2)
        draw.text((u + 13, v - 8), "goal", fill=(60, 255, 60), font=font, stroke_width=2, stroke_fill=(0, 0, 0))
    return np.asarray(image)


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


#: The results table's columns (``table.*``, ``docs/results/experiments_*/experiments_table.md``).
COLUMNS = (
    "scenario", "filter", "episodes", "collision_episodes", "collision_steps", "min_clearance_m", "reached",
    "time_to_goal_s", "tracking_deviation_m", "intervention_share", "infeasible_steps", "mean_correction_Nm",
    "solve_us_median", "solve_us_p99",
)  # fmt: skip


#: The sensing sweep's columns (``sensing.*``, ``docs/results/experiments_*/sensing_table.md``).
SENSING_COLUMNS = (
    "filter", "sensing_radius", "obstacle_speed", "episodes", "collision_episodes", "collision_rate", "infeasible_share",
)  # fmt: skip


def markdown_table(rows: Sequence[dict[str, Any]], columns: Sequence[str]) -> str:
    """``rows`` as a markdown table of ``columns`` (floats to 3 significant digits, NaN as n/a):
    the format of ``table.md``, ``sensing.md`` and the tables in ``docs/`` written from their JSON."""

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
    text = markdown_table(rows, columns)
    stem.with_suffix(".md").write_text(text + "\n")
    return text


def _progress(total: int, enabled: bool, desc: str):
    from tqdm import tqdm

    return tqdm(total=total, disable=not enabled, desc=desc, unit="episode")


def run_experiments(config: ExperimentConfig) -> dict[str, Any]:
    """Run everything ``config`` asks for; write tables and figures; return the tables.

    The result holds ``table`` (rows) and ``markdown`` when ``config.table``, ``sensing`` (the
    sweep's markdown) when the sweep ran, and ``notes`` (why a part asked for did not run).
    """
    config.validate()
    out = Path(config.out)
    figures = out / "figures"
    result: dict[str, Any] = {"notes": []}
    if config.table:
        result["table"], result["markdown"] = _table(config, out, figures)
    if config.sensing and config.sensing_scenarios:
        result["sensing"] = _sensing_study(config, out, figures)
    elif config.sensing:
        result["notes"].append(f"sensing sweep skipped: it runs on {' and '.join(SENSING_SCENARIOS)}, and --scenarios selects neither")
    if config.video:
        _videos(config, out / "videos")
    from c3bf_gym.training import _code_version

    settings = {**asdict(config), "out": str(config.out), "code": _code_version()}
    (out / "config.json").write_text(json.dumps(settings, indent=2, default=str))
    return result


def _table(config: ExperimentConfig, out: Path, figures: Path) -> tuple[list[dict[str, Any]], str]:
    """Every (scenario, seed) episode under every filter: the results table, the figures of the
    first seed's episodes and the C3BF-vs-HOCBF summary figure."""
    from c3bf_gym import plots

    per_episode: dict[tuple[str, str], list[dict[str, Any]]] = {}
    bar = _progress(len(config.scenarios) * len(config.filters) * len(config.seeds), config.progress, "experiments")
    for scenario in config.scenarios:
        for seed in config.seeds:
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
            if seed == config.seeds[0]:
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
        summary_rows = [{**r, "mean_correction": r["mean_correction_Nm"], "tracking_deviation": r["tracking_deviation_m"]} for r in table]
        plots.plot_summary(summary_rows, figures / "summary_c3bf_vs_hocbf.png")
    return table, text


def _sensing_study(config: ExperimentConfig, out: Path, figures: Path) -> str:
    """Collision rate against the sensing radius at the envelope's top speed and beyond, on
    ``config.sensing_scenarios``.

    Each (speed, scenario, seed) episode is also run without a filter, whose collision rate
    (independent of the radius) is the reference: a radius is safe when the filter keeps the
    episodes that collide unfiltered collision-free. The filters are ``config.filters`` but
    "none" (``c3bf`` if that leaves none).
    """
    from c3bf_gym import plots

    filters = [f for f in config.filters if f != "none"] or ["c3bf"]
    scenarios = config.sensing_scenarios
    runs = [("none", None)] + [(f, r) for f in filters for r in config.sensing_radii]
    rows = []
    episodes = len(scenarios) * len(config.sensing_seeds)
    bar = _progress(len(config.sensing_speeds) * len(runs) * episodes, config.progress, "sensing sweep")
    for speed in config.sensing_speeds:
        for filter_name, radius in runs:
            collisions, infeasible, substeps = 0, 0, 0
            for scenario in scenarios:
                for seed in config.sensing_seeds:
                    env_kwargs: dict[str, Any] = {"obstacle_speed_range": (speed, speed)}
                    if radius is not None:
                        env_kwargs["sensing_radius"] = radius
                    record, _ = run_episode(scenario, filter_name, seed, config, env_kwargs=env_kwargs)
                    collisions += int(np.sum(record.cost) > 0)
                    infeasible += int(np.sum(~np.asarray(record.feasible))) if record.feasible else 0
                    substeps += len(record.feasible)
                    bar.update()
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
    text = _write_table(rows, SENSING_COLUMNS, out / "sensing")
    plots.plot_sensing(rows, figures / "sensing_boundary.png")
    return text


def _videos(config: ExperimentConfig, folder: Path) -> None:
    """``{scenario}_{filter}.gif`` per selected scenario and filter, on the first seed's episode."""
    import os
    import sys

    import imageio.v3 as iio

    if sys.platform.startswith("linux") and not os.environ.get("DISPLAY"):
        os.environ.setdefault("MUJOCO_GL", "egl")  # headless: offscreen rendering through EGL
    folder.mkdir(parents=True, exist_ok=True)
    for scenario in config.scenarios:
        for filter_name in config.filters:
            _, frames = run_episode(scenario, filter_name, config.seeds[0], config, render=True)
            iio.imwrite(folder / f"{scenario}_{filter_name}.gif", np.stack(frames), duration=40, loop=0)


def add_parser(sub: argparse._SubParsersAction) -> None:
    from c3bf_gym.cli import _nonnegative_float, _nonnegative_int, _positive_float, _positive_int, add_robot, subcommand
    from c3bf_gym.scenarios import SCENARIOS

    d = ExperimentConfig()  # the defaults live there
    p = subcommand(
        sub, "experiments", "the paper's experiments: 4 scenarios x {no filter, HOCBF, C3BF} (the main job)",
        "Run the Cartesian impedance controller as nominal policy on the paper's scenarios "
        "with no filter, the distance HOCBF and the C3BF filter over seeded episodes; write a results "
        "table (table.csv, .json, .md), figures per scenario, a C3BF-vs-HOCBF summary figure and a "
        "perception-boundary (sensing radius) sweep (sensing.csv, .json, .md). With its defaults it is "
        "the main job.", defaults=ExperimentConfig,
    )
    p.add_argument("--out", type=Path, default=d.out, help="output directory")
    add_robot(p, d.robot)
    seeds = p.add_mutually_exclusive_group()
    seeds.add_argument("--seeds", nargs="+", type=_nonnegative_int, default=list(d.seeds), metavar="SEED",
                       help="seed ids: one episode per seed, scenario and filter (the same episode for every filter)")  # fmt: skip
    seeds.add_argument("--num-seeds", type=_positive_int, default=None, metavar="N",
                       help="N seeds, FIRST_SEED .. FIRST_SEED+N-1, instead of --seeds")  # fmt: skip
    p.add_argument("--first-seed", type=_nonnegative_int, default=0, help="the first seed of --num-seeds")
    p.add_argument("--scenarios", nargs="+", choices=[name for name, s in SCENARIOS.items() if s.obstacles], default=list(d.scenarios),
                   help="scenarios of the table; the sensing sweep runs on those of them it supports "
                        f"({', '.join(SENSING_SCENARIOS)})")  # fmt: skip
    p.add_argument("--filters", nargs="+", choices=EXPERIMENT_FILTERS, default=list(d.filters),
                   help="'c3bf': the paper's C3BF alone; 'c3bf+hocbf': SafetyFilter's default, with its distance guard")  # fmt: skip
    p.add_argument("--points", choices=POINTS, default=d.points, help="protect the whole arm or only the tool (the paper)")
    p.add_argument("--gamma", type=_positive_float, default=d.gamma, help="class-K gain [1/s] (None: the barrier's, 5)")
    p.add_argument("--margin", type=_nonnegative_float, default=d.margin, help="extra clearance [m]")
    p.add_argument("--duration", type=_positive_float, default=d.duration, help="episode length [s]")
    p.add_argument("--move-time", type=_positive_float, default=d.move_time, help="duration of the nominal minimum-jerk path [s]")
    parts = p.add_mutually_exclusive_group()
    parts.add_argument("--no-sensing", action="store_true", help="skip the sensing sweep")
    parts.add_argument("--sensing-only", action="store_true", help="run only the sensing sweep (no table, no per-scenario figures)")
    p.add_argument("--sensing-radius", dest="sensing_radii", nargs="+", type=_positive_float, metavar="R",
                   default=list(d.sensing_radii), help="radii [m] of the sensing sweep")  # fmt: skip
    p.add_argument("--sensing-speeds", nargs="+", type=_nonnegative_float, default=list(d.sensing_speeds), metavar="V",
                   help="obstacle speeds [m/s] of the sensing sweep: the envelope's top (0.4) and beyond")  # fmt: skip
    p.add_argument("--sensing-seeds", nargs="+", type=_nonnegative_int, default=list(d.sensing_seeds), metavar="SEED",
                   help="seed ids of the sensing sweep: one episode per seed, radius, speed and scenario")  # fmt: skip
    p.add_argument("--video", action="store_true",
                   help="also write a GIF per scenario and filter (first seed) to OUT/videos")  # fmt: skip
    quick = p.add_argument("--quick", action="store_true")
    options = {a.dest: a.option_strings[0] for a in p._actions}
    preset = ", ".join(f"{options[k]} {' '.join(map(str, v)) if isinstance(v, tuple) else v}" for k, v in QUICK.items())
    quick.help = f"a smoke run of every output in about 20 s: {preset} (options set to other values than their defaults win)"
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=_run)


def config_from_args(args: argparse.Namespace) -> ExperimentConfig:
    """The :class:`ExperimentConfig` of parsed ``c3bf-gym experiments`` options (``ValueError``
    for ``--first-seed`` without ``--num-seeds``)."""
    d = ExperimentConfig()
    if args.num_seeds is not None:
        seeds = tuple(range(args.first_seed, args.first_seed + args.num_seeds))
    elif args.first_seed != 0:
        raise ValueError("--first-seed only applies with --num-seeds (--seeds takes the seed ids themselves)")
    else:
        seeds = tuple(args.seeds)
    values: dict[str, Any] = {
        "out": args.out, "robot": args.robot, "scenarios": tuple(args.scenarios), "filters": tuple(args.filters), "seeds": seeds,
        "points": args.points, "gamma": args.gamma, "margin": args.margin, "duration": args.duration,
        "move_time": args.move_time, "video": args.video, "table": not args.sensing_only, "sensing": not args.no_sensing,
        "sensing_radii": tuple(args.sensing_radii), "sensing_speeds": tuple(args.sensing_speeds),
        "sensing_seeds": tuple(args.sensing_seeds), "progress": not args.no_progress,
    }  # fmt: skip
    if args.quick:
        values.update({k: v for k, v in QUICK.items() if values[k] == getattr(d, k)})
    return ExperimentConfig(**values)


def _run(args: argparse.Namespace) -> int:
    result = run_experiments(config_from_args(args))
    for key in ("markdown", "sensing"):
        if key in result:
            print(result[key], end="\n\n")
    for note in result["notes"]:
        print(note)
    print(f"results written to {args.out}/ (config.json" + (", table.*" if "markdown" in result else "")
          + (", sensing.*" if "sensing" in result else "") + ", figures/" + (", videos/" if args.video else "") + ")")  # fmt: skip
    return 0
