"""Per-episode records and summaries, shared by the experiments and the RL evaluation.

Safety numbers come from the environment's own geometric signals (``info["cost"]``,
``info["min_distance"]``: MuJoCo distances between obstacles and every arm geom), never from what
the filter believes; the filter's view (``info["safety"]``) is recorded beside them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["EpisodeRecord", "summarize"]


@dataclass
class EpisodeRecord:
    """What happened in one episode, one entry per policy step (arrays after :meth:`finish`)."""

    dt: float
    time: list[float] = field(default_factory=list)
    tool: list[np.ndarray] = field(default_factory=list)
    obstacles: list[np.ndarray] = field(default_factory=list)  # (K, 3) active obstacle centres
    obstacle_radius: np.ndarray | None = None
    goal: np.ndarray | None = None
    reward: list[float] = field(default_factory=list)
    cost: list[float] = field(default_factory=list)
    min_distance: list[float] = field(default_factory=list)
    goal_distance: list[float] = field(default_factory=list)
    success: list[bool] = field(default_factory=list)
    min_h: list[float] = field(default_factory=list)
    min_constraint: list[float] = field(default_factory=list)
    correction: list[float] = field(default_factory=list)
    intervened: list[bool] = field(default_factory=list)
    feasible: list[bool] = field(default_factory=list)
    tau_nominal: list[np.ndarray] = field(default_factory=list)
    tau: list[np.ndarray] = field(default_factory=list)
    solve_times: list[float] = field(default_factory=list)  # per physics step [s]

    @classmethod
    def start(cls, env) -> EpisodeRecord:
        """A record for the episode ``env`` (unwrapped ``C3BFReachEnv``) has just reset into."""
        active = env.obstacle_active.copy()
        record = cls(dt=env.dt, obstacle_radius=env.obstacle_radius[active].copy())
        record.goal = env.goal.copy()
        record._active = active
        record._add_state(env)
        return record

    def _add_state(self, env) -> None:
        self.time.append(float(env.data.time))
        self.tool.append(env.data.site_xpos[env.ee_site_id].copy())
        self.obstacles.append(env.obstacle_pos[self._active].copy())

    def add(self, env, reward: float, info: dict[str, Any]) -> None:
        """Append one policy step (``info`` from ``env.step``)."""
        self._add_state(env)
        self.reward.append(float(reward))
        self.cost.append(float(info["cost"]))
        self.min_distance.append(float(info["min_distance"]))
        self.goal_distance.append(float(info["distance"]))
        self.success.append(bool(info["is_success"]))
        safety = info.get("safety")
        if safety is not None:
            self.min_h.append(float(safety["min_h"]))
            self.min_constraint.append(float(safety["min_constraint"]))
            self.correction.append(float(safety["correction"]))
            self.intervened.append(bool(safety["intervened"]))
            self.feasible.append(bool(safety["feasible"]))

    def contact_steps(self) -> np.ndarray:
        """Indices of the policy steps with contact (``info["cost"] > 0``: some arm geom touched
        an obstacle)."""
        return np.flatnonzero(np.asarray(self.cost, dtype=float) > 0)

    def as_arrays(self) -> dict[str, np.ndarray]:
        return {
            name: np.asarray(getattr(self, name))
            for name in (
                "time", "tool", "reward", "cost", "min_distance", "goal_distance", "success", "min_h",
                "min_constraint", "correction", "intervened", "feasible", "tau_nominal", "tau", "solve_times",
            )
        }  # fmt: skip


def summarize(record: EpisodeRecord, reference: EpisodeRecord | None = None) -> dict[str, float]:
    """Scalar metrics of one episode.

    ``reference`` (the same episode without a filter) gives ``tracking_deviation``: the mean
    distance between the two tool paths [m].
    """
    cost = np.asarray(record.cost)
    success = np.asarray(record.success, dtype=bool)
    reached = np.flatnonzero(success)
    out: dict[str, float] = {
        "return": float(np.sum(record.reward)),
        "collision": float(cost.sum() > 0),
        "collision_steps": float(cost.sum()),
        "min_clearance": float(np.min(record.min_distance)) if record.min_distance else np.nan,
        "reached": float(len(reached) > 0),
        "time_to_goal": float(record.time[reached[0] + 1]) if len(reached) else np.nan,
        "final_success": float(success[-1]) if len(success) else np.nan,
    }
    if record.intervened:
        solve = np.asarray(record.solve_times) * 1e6
        out.update(
            intervention_share=float(np.mean(record.intervened)),
            infeasible_steps=float(np.sum(~np.asarray(record.feasible))),
            mean_correction=float(np.mean(record.correction)),
            solve_us_median=float(np.median(solve)) if len(solve) else np.nan,
            solve_us_p99=float(np.percentile(solve, 99)) if len(solve) else np.nan,
        )
    if reference is not None:
        n = min(len(record.tool), len(reference.tool))
        gap = np.linalg.norm(np.asarray(record.tool[:n]) - np.asarray(reference.tool[:n]), axis=1)
        out["tracking_deviation"] = float(gap.mean())
        out["tracking_deviation_max"] = float(gap.max())
    return out
