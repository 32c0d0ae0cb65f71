"""A probe of the filter's QP metric: does a correction the tool does not feel keep the zero action
at the goal?

The filter returns the torque nearest the nominal one in the metric ``FilterConfig.weight``
(``"limits"``: ‖u − u_nom‖² in the scaled torque ``u = τ / τ_max``). Every joint's change weighs
the same there, whether it moves the tool or only the elbow. Where crossing spheres press on the
upper arm with the tool at the goal, the nearest torque can push the tool off it. A 6-joint arm
reaching a point has three joints' worth of motion the tool does not feel. This probe measures
what a metric that prefers those corrections does to the task, with the residual action's prior,
the zero action, on the evaluation episodes (the recipe's environment, ``TrainConfig``'s defaults,
the seeds of ``c3bf-gym evaluate``).

The probe's metric is ``H = I + GᵀG / a²``, with ``G = J M⁻¹ diag(τ_max)`` the tool's
acceleration [m/s²] per unit of ``u`` (``J`` the tool site's translational Jacobian, ``M`` the
arm's inertia) and ``a`` [m/s²] = ``--tool-acceleration``: a change of ``u`` that changes the
tool's acceleration by ``a`` costs as much as a unit change of ``u`` itself. It replaces the
environment's filter hook with a Python one that takes the filter's own rows
(``SafetyController.rows()``) and the torque box, and solves ``min ½ (u − u_nom)ᵀ H (u − u_nom)``
with DAQP with every row hard, in one level. Where that has no solution, the step takes the
filter's own torque (its levels of priority, which the probe does not reproduce) and is counted.
Collisions come from the environment's own signed distances (``info["episode_cost"]``), not from
the filter. This is a measurement, not the filter: it runs in Python at every physics step.

    python train/tool_metric.py                         # the default filter and a = 10, 200 episodes
    python train/tool_metric.py --tool-acceleration 1 --episodes 43 94 181
    python train/tool_metric.py --model runs/RUN/model.zip  # a trained recipe agent instead of the zero action

``--in-filter`` runs the filter's own metric instead (``FilterConfig(weight="tool",
tool_acceleration=a)``, compiled, with the filter's levels of priority), not the probe's hook:

    python train/tool_metric.py --in-filter --tool-acceleration 3 10

``--model`` runs a Stable-Baselines3 model trained on the recipe's environment (its deterministic
action) in place of the zero action: an agent trained under the default filter, under the probe's
metric, which it never trained with.

Prints one JSON line per metric, with its episodes, then a summary by scenario.
"""

from __future__ import annotations

import argparse
import json
import time
from collections import defaultdict

import daqp
import mujoco
import numpy as np

from c3bf_gym.envs.reach import ROBOTS
from c3bf_gym.training import FINAL_EVAL_SEED, TrainConfig, build_env

#: DAQP's "no bound"
_INF = 1e30


class ToolMetric:
    """A filter hook: the filter's rows and torque box, solved in the metric ``I + GᵀG / a²``
    (the module docstring); the filter's own torque where that QP has no solution."""

    def __init__(self, env, tool_acceleration: float) -> None:
        self.base = env.unwrapped
        self.filter = self.base.torque_hook("filter")
        self.limit = np.asarray(self.base.robot.torque_limit, dtype=float)
        self.weight = 1.0 / tool_acceleration**2
        model = self.base.model
        self.jacobian, self.inertia = np.zeros((3, model.nv)), np.zeros((model.nv, model.nv))
        self.calls = self.fallbacks = 0

    def __call__(self, tau_nom: np.ndarray) -> np.ndarray:
        base, limit, n = self.base, self.limit, len(self.limit)
        A, b, *_ = self.filter.rows()
        mujoco.mj_jacSite(base.model, base.data, self.jacobian, None, base.ee_site_id)
        mujoco.mj_fullM(base.model, base.data, self.inertia)
        G = self.jacobian[:, :n] @ np.linalg.inv(self.inertia)[:n, :n] * limit
        H = np.eye(n) + self.weight * G.T @ G
        scaled = A * limit
        norm = np.linalg.norm(scaled, axis=1)
        keep = norm > 1e-12  # a row no torque changes is the filter's to report
        rows = np.vstack([np.eye(n), scaled[keep] / norm[keep, None]])
        upper = np.concatenate([np.ones(n), np.full(int(keep.sum()), _INF)])
        lower = np.concatenate([-np.ones(n), b[keep] / norm[keep]])
        u_nom = np.clip(np.asarray(tau_nom, dtype=float) / limit, -1.0, 1.0)
        u, _, flag, _ = daqp.solve(H, -H @ u_nom, rows, upper, lower, np.zeros(len(upper), np.int32))
        self.calls += 1
        if flag < 0:
            self.fallbacks += 1
            return self.filter(tau_nom)
        return u * limit


def run(robot: str, episodes: list[int], tool_acceleration: float | None, model=None,
        in_filter: bool = False) -> dict:
    """The zero action (or ``model``'s deterministic action) on ``episodes`` (indices from
    ``FINAL_EVAL_SEED``) under the default filter (``tool_acceleration`` None), the probe's
    metric, or (``in_filter``) the filter's own ``"tool"`` metric: per-episode records and the
    counts."""
    settings = {}
    if in_filter and tool_acceleration is not None:
        settings = {"weight": "tool", "tool_acceleration": tool_acceleration}
    env = build_env("random", **TrainConfig(robot=robot, filter_settings=settings).env_options())
    if model is not None and model.observation_space.shape != env.observation_space.shape:
        raise ValueError(f"the model sees observations of shape {model.observation_space.shape}, the recipe's "
                         f"{robot} environment gives {env.observation_space.shape}: not a recipe run")  # fmt: skip
    hook = None
    if tool_acceleration is not None and not in_filter:
        hook = ToolMetric(env, tool_acceleration)
        env.unwrapped.remove_torque_hook("filter")
        env.unwrapped.add_torque_hook(hook, "filter")
    zero = np.zeros(env.action_space.shape, np.float32)
    policy = (lambda obs: zero) if model is None else (lambda obs: model.predict(obs, deterministic=True)[0])
    env.reset(seed=FINAL_EVAL_SEED)  # as evaluate starts; each episode below is reseeded
    records, clock = [], time.perf_counter()
    for episode in episodes:
        final, collisions, success = _rollout(env, FINAL_EVAL_SEED + episode, policy)
        records.append({"episode": episode, "scenario": env.unwrapped.episode_scenario.name,
                        "final": round(final, 4), "collisions": collisions, "success": success})  # fmt: skip
    env.close()
    return {"tool_acceleration": tool_acceleration, "in_filter": in_filter, "seconds": round(time.perf_counter() - clock, 1),
            "calls": hook.calls if hook else None, "fallbacks": hook.fallbacks if hook else None,
            "episodes": records}  # fmt: skip


def _rollout(env, seed: int, policy) -> tuple[float, float, bool]:
    """The episode of ``seed`` under ``policy`` (observation -> action): the tool's final distance
    to the goal [m], the episode's collision steps, and success."""
    obs, _ = env.reset(seed=seed)
    collisions, done, info = 0.0, False, {}
    while not done:
        obs, _, terminated, truncated, info = env.step(policy(obs))
        collisions += info["cost"]
        done = terminated or truncated
    return float(info["distance"]), collisions, bool(info["is_success"])


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robot", choices=list(ROBOTS), default="ur5e")
    parser.add_argument("--episodes", type=int, nargs="+", default=list(range(200)),
                        help="evaluation episode indices (default: the 200 of c3bf-gym evaluate)")  # fmt: skip
    parser.add_argument("--tool-acceleration", type=float, nargs="+", default=[10.0], metavar="A",
                        help="the metric's a [m/s^2], one run each, beside the default filter's")  # fmt: skip
    parser.add_argument("--model", help="a recipe run's SB3 SAC model.zip, in place of the zero action")
    parser.add_argument("--in-filter", action="store_true",
                        help="the filter's own weight='tool' metric (with its levels), not the probe's hook")  # fmt: skip
    args = parser.parse_args(argv)
    if any(not a > 0.0 for a in args.tool_acceleration) or any(e < 0 for e in args.episodes):
        parser.error("--tool-acceleration must be > 0 m/s^2 and --episodes >= 0")
    model = None
    if args.model:
        from stable_baselines3 import SAC

        model = SAC.load(args.model, device="cpu")
    results = []
    for tool_acceleration in (None, *args.tool_acceleration):
        result = run(args.robot, args.episodes, tool_acceleration, model, args.in_filter)
        results.append(result)
        print(json.dumps(result), flush=True)
    for result in results:
        counts, wins, collided = defaultdict(int), defaultdict(int), defaultdict(int)
        for record in result["episodes"]:
            counts[record["scenario"]] += 1
            wins[record["scenario"]] += record["success"]
            collided[record["scenario"]] += record["collisions"] > 0
        label = "default filter" if result["tool_acceleration"] is None else f"a = {result['tool_acceleration']:g}"
        label += " (in the filter)" if result["in_filter"] and result["tool_acceleration"] is not None else ""
        print(f"{label}: " + ", ".join(f"{name} {wins[name]}/{counts[name]} ({collided[name]} collided)"
                                       for name in counts), flush=True)  # fmt: skip
    return results


if __name__ == "__main__":
    main()
