"""Figures for the experiments and the training runs (matplotlib, Agg backend, PNG)."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from c3bf_gym.safety import GUARD_GAMMA
from c3bf_gym.metrics import EpisodeRecord
from c3bf_gym.training import FINAL_EVAL_FILE, filter_label

__all__ = [
    "barrier_figure",
    "barrier_quantity",
    "plot_barrier",
    "plot_clearance",
    "plot_sensing",
    "plot_summary",
    "plot_torques",
    "plot_training",
    "plot_trajectories",
    "trajectory_figure",
]

COLORS = {"none": "tab:red", "hocbf": "tab:orange", "c3bf": "tab:blue", "c3bf+hocbf": "tab:green", "c3bf+hocbf5": "tab:olive",
          "c3bf+hocbf20": "tab:purple"}  # fmt: skip
LABELS = {"none": "no filter", "hocbf": "distance HOCBF", "c3bf": "C3BF", "c3bf+hocbf": "C3BF + distance guard"}


_GUARDED = "c3bf+hocbf"


def _label(name: str) -> str:
    """A filter's legend label; ``"c3bf+hocbf5"`` (a guard with other gains) reads "C3BF + distance
    guard (γ 5)", and other settings follow in brackets as the run's label lists them."""
    rows, settings = _split(name)
    if rows.startswith(_GUARDED) and rows != _GUARDED:
        label = f"{LABELS[_GUARDED]} (γ {rows[len(_GUARDED):]})"
    else:
        label = LABELS.get(rows, rows)
    return label + (f" [{settings}]" if settings else "")


def _order(name: str) -> tuple[int, float, str]:
    """Table and legend order: no filter, HOCBF, C3BF, then the guarded C3BF by its gains; a
    filter with other settings after the same rows without."""
    rows, settings = _split(name)
    if rows.startswith(_GUARDED):
        return 3, float(rows[len(_GUARDED):] or GUARD_GAMMA), settings
    return {"none": 0, "hocbf": 1, "c3bf": 2}.get(rows, 4), 0.0, settings


def _split(name: str) -> tuple[str, str]:
    """A run's filter label (:func:`~c3bf_gym.training.filter_label`) as its rows' name and its
    other settings (``"c3bf+hocbf[allowance_level=true]"``: ``"c3bf+hocbf"``,
    ``"allowance_level=true"``)."""
    rows, _, settings = name.partition("[")
    return rows, settings.removesuffix("]")


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    _pyplot().close(fig)
    return path


#: The ``gid`` of the trajectory plots' contact markers.
CONTACT_GID = "contacts"


def plot_trajectories(records: Mapping[str, EpisodeRecord], title: str, path: Path) -> Path:
    """Tool paths of each filter with the obstacle paths, top (x-y) and side (x-z) views
    (:func:`trajectory_figure`, saved to ``path``)."""
    return _save(trajectory_figure(records, title), path)


def trajectory_figure(records: Mapping[str, EpisodeRecord], title: str):
    """The figure of :func:`plot_trajectories`. The tool's position at every contact step (the
    environment's geometric ``cost``: some arm geom touches an obstacle) is marked with an x in
    the filter's colour, one marker per contact step and view (artists with gid
    :data:`CONTACT_GID`)."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.8))
    any_record = next(iter(records.values()))
    obstacles = np.asarray(any_record.obstacles)  # (T, K, 3)
    for ax, (i, j), view in zip(axes, ((0, 1), (0, 2)), ("top view", "side view")):
        for k in range(obstacles.shape[1] if obstacles.ndim == 3 else 0):
            path_k = obstacles[:, k]
            ax.plot(path_k[:, i], path_k[:, j], "--", color="0.45", lw=1, label="obstacle path" if k == 0 else None)
            radius = any_record.obstacle_radius[k]
            for where, alpha in ((0, 0.25), (-1, 0.5)):
                ax.add_patch(plt.Circle((path_k[where, i], path_k[where, j]), radius, color="0.3", alpha=alpha))
        for name, record in records.items():
            tool = np.asarray(record.tool)
            ax.plot(tool[:, i], tool[:, j], color=COLORS.get(name), lw=2, label=LABELS.get(name, name))
            hits = tool[record.contact_steps() + 1]  # tool[0] is the reset state, tool[s + 1] after step s
            if len(hits):
                ax.plot(hits[:, i], hits[:, j], "X", mfc=COLORS.get(name), mec="k", ms=7, mew=0.6, ls="none", gid=CONTACT_GID,
                        label=f"contact ({LABELS.get(name, name)}, {len(hits)} steps)")  # fmt: skip
        tool0 = np.asarray(any_record.tool)[0]
        ax.plot(tool0[i], tool0[j], "ko", ms=6, label="start")
        ax.plot(any_record.goal[i], any_record.goal[j], "g*", ms=14, label="goal")
        ax.set_xlabel("xyz"[i] + " [m]")
        ax.set_ylabel("xyz"[j] + " [m]")
        ax.set_title(view)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, loc="best")
    fig.suptitle(f"{title}: tool trajectories (obstacles shaded at spawn and at the end; x: tool at a contact step)")
    return fig


def plot_clearance(records: Mapping[str, EpisodeRecord], title: str, margin: float, path: Path) -> Path:
    """Smallest obstacle-to-arm distance over time per filter, zero (contact) marked."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8, 3.6))
    for name, record in records.items():
        ax.plot(record.time[1:], record.min_distance, color=COLORS.get(name), label=LABELS.get(name, name))
    ax.axhline(0.0, color="k", lw=1.2, label="contact")
    ax.axhline(margin, color="k", lw=0.8, ls=":", label=f"filter margin {margin:g} m")
    ax.set_ylim(min(-0.02, ax.get_ylim()[0]), min(ax.get_ylim()[1], 0.6))
    ax.set_xlabel("time [s]")
    ax.set_ylabel("min distance arm-obstacle [m]")
    ax.set_title(f"{title}: clearance (MuJoCo geometry, every arm geom)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, path)


def barrier_quantity(name: str) -> tuple[str, str]:
    """``(symbol, definition)`` of what ``info["safety"]["min_h"]`` holds under the filter
    ``name``: the barrier's own rows' value (not the guard's), the C3BF's ``h`` or the distance
    HOCBF's ``ψ₁``, both in m²/s (p, v: the obstacle's position and velocity relative to the
    point, r: the inflated radius)."""
    if name.startswith("c3bf"):
        return "h", "C3BF h = ⟨p, v⟩ + ‖v‖ √(‖p‖² − r²)"
    if name == "hocbf":
        return "ψ₁", "HOCBF ψ₁ = ḣ + γ₁h, h = ‖p‖² − r²"
    return "h", "barrier value h"


def plot_barrier(records: Mapping[str, EpisodeRecord], title: str, path: Path) -> Path:
    """:func:`barrier_figure`, saved to ``path``."""
    return _save(barrier_figure(records, title), path)


def barrier_figure(records: Mapping[str, EpisodeRecord], title: str):
    """The smallest barrier value over time, each filter's panel titled and labelled with the
    quantity it shows (:func:`barrier_quantity`: the C3BF's h, the HOCBF's ψ₁), above the QP
    constraint value (min_k A_k τ − b_k); one column per filter that recorded a barrier."""
    plt = _pyplot()
    filtered = {n: r for n, r in records.items() if r.min_h}
    fig, axes = plt.subplots(2, len(filtered), figsize=(5.5 * len(filtered), 5.5), squeeze=False)
    for col, (name, record) in enumerate(filtered.items()):
        t = record.time[1:]
        h = np.asarray(record.min_h, dtype=float)
        g = np.asarray(record.min_constraint, dtype=float)
        symbol, quantity = barrier_quantity(name)
        axes[0, col].plot(t, np.where(np.isfinite(h), h, np.nan), color=COLORS.get(name))
        axes[0, col].axhline(0.0, color="k", lw=1)
        axes[0, col].set_title(f"{LABELS.get(name, name)}: min over rows of\n{quantity}", fontsize=10)
        axes[0, col].set_ylabel(f"min {symbol} [m²/s]")
        axes[1, col].plot(t, np.where(np.isfinite(g), g, np.nan), color=COLORS.get(name))
        axes[1, col].axhline(0.0, color="k", lw=1)
        axes[1, col].set_title("QP constraint value min(Aτ − b) (>= 0: all rows hold)", fontsize=10)
        axes[1, col].set_ylabel("min(Aτ − b) [row units]")
        axes[1, col].set_xlabel("time [s]")
        for ax in axes[:, col]:
            ax.grid(alpha=0.3)
    fig.suptitle(f"{title}: barrier and constraint over time (inf = no sensed obstacle, not drawn)")
    fig.tight_layout()
    return fig


def plot_torques(record: EpisodeRecord, title: str, path: Path) -> Path:
    """Nominal (impedance controller) vs filtered torque per joint."""
    plt = _pyplot()
    nominal, filtered = np.asarray(record.tau_nominal), np.asarray(record.tau)
    t = record.time[1:]
    fig, axes = plt.subplots(2, 3, figsize=(12, 5.5), sharex=True)
    for j, ax in enumerate(axes.flat):
        ax.plot(t, nominal[:, j], color="0.5", lw=1.2, label="nominal")
        ax.plot(t, filtered[:, j], color=COLORS["c3bf"], lw=1.2, label="filtered")
        ax.set_title(f"joint {j + 1}")
        ax.grid(alpha=0.3)
    for ax in axes[1]:
        ax.set_xlabel("time [s]")
    for ax in axes[:, 0]:
        ax.set_ylabel("torque [N m]")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(f"{title}: nominal vs filtered torque (C3BF)")
    return _save(fig, path)


def plot_summary(rows: Sequence[Mapping[str, float | str]], path: Path) -> Path:
    """C3BF vs HOCBF across scenarios on the metrics that show conservativeness."""
    plt = _pyplot()
    metrics = (
        ("intervention_share", "share of steps the filter intervened"),
        ("mean_correction", "mean correction ‖τ − τ_nom‖ [N m]"),
        ("tracking_deviation", "deviation from unfiltered path [m]"),
        ("reached", "goal reached (share of episodes)"),
    )
    scenarios = sorted({str(r["scenario"]) for r in rows}, key=lambda s: ["static", "head_on", "crossing", "multi"].index(s) if s in ("static", "head_on", "crossing", "multi") else 9)
    filters = [f for f in ("hocbf", "c3bf") if any(r["filter"] == f for r in rows)]
    fig, axes = plt.subplots(1, len(metrics), figsize=(4.2 * len(metrics), 3.8))
    x = np.arange(len(scenarios))
    width = 0.8 / max(len(filters), 1)
    for ax, (key, label) in zip(axes, metrics):
        for i, f in enumerate(filters):
            values = [next((float(r[key]) for r in rows if r["scenario"] == s and r["filter"] == f), np.nan) for s in scenarios]
            ax.bar(x + (i - (len(filters) - 1) / 2) * width, values, width, color=COLORS[f], label=LABELS[f])
        ax.set_xticks(x, scenarios, rotation=20)
        ax.set_title(label, fontsize=9)
        ax.grid(alpha=0.3, axis="y")
    axes[0].legend(fontsize=8)
    fig.suptitle("C3BF vs distance HOCBF (same episodes, same nominal controller)")
    return _save(fig, path)


def plot_sensing(rows: Sequence[Mapping[str, float | str]], path: Path) -> Path:
    """Collision rate against the sensing radius, one panel per obstacle speed; the unfiltered
    collision rate (independent of the radius) as a horizontal reference."""
    plt = _pyplot()
    speeds = sorted({float(r["obstacle_speed"]) for r in rows})
    fig, axes = plt.subplots(1, len(speeds), figsize=(5 * len(speeds), 3.8), squeeze=False)
    for ax, speed in zip(axes[0], speeds):
        here = [r for r in rows if float(r["obstacle_speed"]) == speed]
        for f in sorted({str(r["filter"]) for r in here}):
            sel = sorted((r for r in here if r["filter"] == f), key=lambda r: float(r["sensing_radius"]))
            if f == "none":
                ax.axhline(float(sel[0]["collision_rate"]), color=COLORS["none"], ls="--", label=LABELS["none"])
                continue
            radii = [float(r["sensing_radius"]) for r in sel]
            ax.plot(radii, [float(r["collision_rate"]) for r in sel], "o-", color=COLORS.get(f), label=LABELS.get(f, f))
        ax.set_title(f"obstacles at {speed:g} m/s")
        ax.set_xlabel("sensing radius [m]")
        ax.set_xscale("log")
        ax.set_ylim(-0.05, 1.05)
        ax.grid(alpha=0.3)
    axes[0, 0].set_ylabel("collision episodes (share)")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle("Perception boundary: the filter only sees obstacles within the sensing radius")
    return _save(fig, path)


def _trailing_mean(x: np.ndarray, window: int) -> np.ndarray:
    """Mean of the last ``window`` values at each index (fewer at the start)."""
    sums = np.convolve(x, np.ones(window), mode="full")[: len(x)]
    return sums / np.minimum(np.arange(1, len(x) + 1), window)


def _read_episodes(run: Path) -> dict[str, np.ndarray]:
    with open(run / "episodes.csv") as fh:
        rows = list(csv.DictReader(fh))
    return {key: np.array([float(r[key]) for r in rows]) for key in (rows[0] if rows else {})}


def _final_evaluation(run: Path, evaluation: str = FINAL_EVAL_FILE) -> tuple[tuple[float, float, int] | None, dict]:
    """A run's final model, from its ``evaluation`` file (``c3bf-gym evaluate --json``'s format,
    read once): ``(success rate, mean return, episodes)`` and the success per concrete scenario
    (empty for runs evaluated before it was recorded). For the default ``final_eval.json``, runs
    made before it was recorded fall back to their last periodic evaluation in
    ``evaluations.npz`` (None without either); any other file must exist."""
    final = run / evaluation
    if final.exists():
        result = json.loads(final.read_text())
        return (result["success_rate"], result["return_mean"], result["episodes"]), result.get("by_scenario", {})
    if evaluation != FINAL_EVAL_FILE:
        raise FileNotFoundError(f"{run} has no {evaluation} (write it with: c3bf-gym evaluate {run / 'model.zip'} --episodes N --json {final})")
    if (run / "evaluations.npz").exists():
        evals = np.load(run / "evaluations.npz")
        if "successes" in evals and len(evals["successes"]):
            return (float(np.mean(evals["successes"][-1])), float(np.mean(evals["results"][-1])), evals["successes"].shape[1]), {}
    return None, {}


def _scenario_table(keys: Sequence[tuple[str, str, str]], groups: Mapping[tuple[str, str, str], list]) -> list[str]:
    """Markdown rows: each group's final success per concrete scenario, mean (per seed), with
    the number of episodes of that scenario per model. Empty if no run recorded the split."""
    from c3bf_gym.scenarios import SCENARIOS

    seen = {name for entries in groups.values() for config, _ in entries for name in config["_by_scenario"]}
    if not seen:
        return []
    names = [n for n in SCENARIOS if n in seen] + sorted(seen - set(SCENARIOS))
    lines = ["| algo | action | filter | " + " | ".join(names) + " |", "|---" * (3 + len(names)) + "|"]
    for key in keys:
        cells = []
        for name in names:
            rows = [c["_by_scenario"][name] for c, _ in groups[key] if name in c["_by_scenario"]]
            if not rows:
                cells.append("n/a")
                continue
            rates = [r["success_rate"] for r in rows]
            episodes = ", ".join(sorted({str(r["episodes"]) for r in rows}))
            cells.append(f"{np.mean(rates):.2f} ({', '.join(f'{x:.2f}' for x in rates)}; {episodes} ep.)")
        lines.append(f"| {' | '.join(key)} | " + " | ".join(cells) + " |")
    return lines


#: Line styles of the action modes when one figure holds several.
ACTION_STYLES = {"impedance": "-", "residual": "--", "torque": ":"}


#: Training options that runs averaged together must share (anything but the seed and where the
#: run was written), with the value a run's config.json means when it predates the option.
_RECIPE = {
    "scenario": "random", "timesteps": None, "n_envs": 1, "policy_hz": None, "normalize_obs": False,
    "distance_weight": 0.0, "action_weight": 0.0, "obstacle_encoder": "flat", "hyperparams": {}, "robot": "ur5e",
}  # fmt: skip


def _check_recipe(key: tuple[str, str, str], entries: list[tuple[dict, dict]]) -> None:
    """Raise if the runs of one group were trained differently: their mean would mean nothing."""
    differ = [k for k, default in _RECIPE.items() if len({json.dumps(c.get(k, default), sort_keys=True) for c, _ in entries}) > 1]
    if differ:
        raise ValueError(
            f"runs grouped as {' '.join(key)} differ in {', '.join(differ)} ({', '.join(c['_run'] for c, _ in entries)}); "
            "plot runs of one recipe together"
        )


def _run_groups(runs: Sequence[Path], evaluation: str) -> dict[tuple[str, str, str], list[tuple[dict, dict[str, np.ndarray]]]]:
    """The runs with a finished training episode, as ``(config, episodes)`` grouped by (algorithm,
    action mode, filter label), each config holding its summary, final evaluation and path;
    FileNotFoundError for a folder that is not a run, ValueError when no run has an episode or
    the runs of a group were trained differently."""
    groups: dict[tuple[str, str, str], list[tuple[dict, dict[str, np.ndarray]]]] = {}
    for run in runs:
        config_file = run / "config.json"
        if not config_file.exists() or not (run / "episodes.csv").exists():
            raise FileNotFoundError(f"{run} is not a run directory (needs config.json and episodes.csv)")
        config = json.loads(config_file.read_text())
        data = _read_episodes(run)
        if not data:
            continue
        summary = run / "summary.json"
        config["_summary"] = json.loads(summary.read_text()) if summary.exists() else {}
        config["_final"], config["_by_scenario"] = _final_evaluation(run, evaluation)
        config["_run"] = str(run)
        # the C3BF with its guard is its own group per guard gain ("c3bf+hocbf", "c3bf+hocbf5"), and each
        # filter per set of other settings ("c3bf+hocbf[allowance_level=true]")
        name = filter_label(config["filter"], config.get("guard_gamma"), config.get("filter_settings"))
        groups.setdefault((config["algo"], config["action"], name), []).append((config, data))
    if not groups:
        raise ValueError("no run has a finished training episode to plot")
    for key, entries in groups.items():
        _check_recipe(key, entries)
    return groups


def _table_row(key: tuple[str, str, str], entries: list[tuple[dict, dict[str, np.ndarray]]], horizon: float) -> str:
    """One group's row of :func:`plot_training`'s table."""
    algo, action, name = key
    costs = [int(c["_summary"].get("training_cost", d["cumulative_cost"][-1])) for c, d in entries]
    finals = [c["_final"] for c, _ in entries if c["_final"] is not None]
    head = f"| {algo} | {action} | {name} | {len(entries)} | {int(horizon)} | {sum(costs)} ({', '.join(map(str, costs))}) |"
    # episodes where the QP had no solution (the filter applied its least-violating torque);
    # runs from before episodes.csv recorded it count as n/a
    infeasible = [int(np.count_nonzero(d["infeasible"])) if "infeasible" in d else None for _, d in entries]
    head += (f" {sum(infeasible)} ({', '.join(map(str, infeasible))}) |" if None not in infeasible else " n/a |")
    if not finals:
        return f"{head} n/a | n/a | n/a |"
    succ, ret, episodes = zip(*finals)
    per_seed = ", ".join(f"{x:.2f}" for x in succ)
    return f"{head} {np.mean(succ):.2f} ({per_seed}) | {np.mean(ret):.1f} | {', '.join(sorted(set(map(str, episodes))))} |"


#: :func:`plot_training`'s time to competence: the training success rate, a trailing mean over
#: :data:`COMPETENCE_WINDOW` episodes, first at or above :data:`COMPETENCE`.
COMPETENCE = 0.9
COMPETENCE_WINDOW = 50


def _competence_table(keys: Sequence[tuple[str, str, str]], groups: Mapping[tuple[str, str, str], list]) -> list[str]:
    """Per group: the training steps (and minutes, the run's wall time pro rata) at which each
    seed's training success first reached :data:`COMPETENCE` over the last
    :data:`COMPETENCE_WINDOW` episodes (the stochastic policy's own episodes, exploration
    included); "-" for a seed that never did."""
    lines = [f"| algo | action | filter | training steps to {COMPETENCE:g} success (per seed) "
             f"| minutes, pro rata of the run's wall time (per seed) | seeds that reached it |",
             "|---|---|---|---|---|---|"]  # fmt: skip
    for key in keys:
        steps, minutes = [], []
        for config, data in groups[key]:
            reached = np.flatnonzero(_trailing_mean(data["success"], COMPETENCE_WINDOW) >= COMPETENCE)
            reached = reached[reached >= COMPETENCE_WINDOW - 1]  # a full window
            step = int(data["timesteps"][reached[0]]) if reached.size else None
            wall = config["_summary"].get("wall_time_s")
            steps.append("-" if step is None else str(step))
            minutes.append("-" if step is None or wall is None else f"{wall * step / data['timesteps'][-1] / 60:.1f}")
        done = sum(x != "-" for x in steps)
        lines.append(f"| {' | '.join(key)} | {', '.join(steps)} | {', '.join(minutes)} | {done} of {len(steps)} |")
    return lines


def plot_training(runs: Sequence[Path], path: Path, window: int = 20, evaluation: str = FINAL_EVAL_FILE) -> str:
    """Learning curves grouped by (algorithm, action mode, filter): mean and min-max over seeds.

    Returns a markdown table, one row per group: training collision steps and training episodes
    with an infeasible step (total and per seed), and the final models' success rate and return
    (per seed and mean) with the number of evaluation episodes per model; then, when the
    evaluations recorded it, a second table of the final success per concrete scenario (the
    components of ``random``); last, the time to competence (:func:`_competence_table`). The
    final models' numbers come from each run's ``evaluation`` file: ``final_eval.json``
    (written by the run) by default, or a longer evaluation written by ``c3bf-gym evaluate
    --json`` into the run directory (``FileNotFoundError`` if a run lacks
    it). Runs of one group must share their training options but the seed (``ValueError``
    otherwise).
    """
    plt = _pyplot()
    groups = _run_groups(runs, evaluation)
    keys = sorted(groups, key=lambda k: (k[0], k[1], *_order(k[2])))
    several_modes = len({k[:2] for k in keys}) > 1
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    grid_len = 200
    lines = [
        "| algo | action | filter | seeds | timesteps | training collision steps (per seed) "
        "| training episodes with an infeasible step (per seed) "
        "| final success (per seed) | final return | eval episodes per model |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for key in keys:
        algo, action, name = key
        entries = groups[key]
        horizon = min(d["timesteps"][-1] for _, d in entries)
        grid = np.linspace(0, horizon, grid_len)
        curves = {"return": [], "success": [], "cumulative_cost": []}
        for _, d in entries:
            for curve in curves:
                values = d[curve] if curve == "cumulative_cost" else _trailing_mean(d[curve], window)
                curves[curve].append(np.interp(grid, d["timesteps"], values))
        label = _label(name) + (f", {algo} {action}" if several_modes else "")
        for ax, curve, title in zip(axes, curves, ("episode return", "success (end of episode)", "cumulative collision steps")):
            stack = np.array(curves[curve])
            ax.plot(grid, stack.mean(0), ACTION_STYLES.get(action, "-"), color=COLORS.get(name),
                    label=f"{label} ({len(entries)} seeds)")  # fmt: skip
            ax.fill_between(grid, stack.min(0), stack.max(0), color=COLORS.get(name), alpha=0.2)
            ax.set_title(title)
            ax.set_xlabel("timesteps")
            ax.grid(alpha=0.3)
        lines.append(_table_row(key, entries, horizon))
    axes[0].legend(fontsize=8)
    fig.suptitle(f"Training curves (moving average over {window} episodes; band: min-max over seeds)")
    _save(fig, path)
    by_scenario = _scenario_table(keys, groups)
    return "\n".join(lines + ([""] + by_scenario if by_scenario else []) + [""] + _competence_table(keys, groups))
