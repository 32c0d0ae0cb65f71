"""The environment's cost against the bare physics it runs on, and against Gymnasium's Pusher-v5.

Per policy step, in interleaved rounds (every configuration once per round, the order rotating
from round to round, so that machine noise hits all alike), the median over rounds of:

* ``bare``: ``mujoco.mj_step(model, data, nstep=frame_skip)`` on the environment's own model
  (its distance sensors included), replaying the unfiltered configuration's own policy steps: a
  seeded run of ``unfiltered`` with random actions is recorded first (the physics state before
  each step, obstacles included, and the torque it applied), and each step runs again from that
  state with that torque, the obstacles standing still within it. The physics a policy step
  cannot avoid (the 1× of the ratios);
* ``bare, reset states``: the same with random controls (±0.4 of the torque limits) from the
  states of seeded resets (a new one every 250 steps), the obstacles standing where the reset put
  them: nearly still arms with far-away obstacles, cheaper physics than an episode's (the 1×
  before the replay; for reference);
* ``bare, parked``: the same from the ``home`` keyframe, where every obstacle is parked far below
  the floor, so its 64 distance sensors cost next to nothing (the baseline before; for reference);
* ``unfiltered``: ``C3BFReach-v0``'s ``step`` with random actions;
* ``filtered``: the same under the default ``SafetyFilter``, with random actions and with the
  adversary of ``benchmarks/guarantee.py`` (the arm point nearest an obstacle driven at it; the
  adversary's own computation is not timed);
* ``impedance``: the environment under the residual Cartesian impedance controller
  (``CartesianImpedanceAction(residual=True)``), random residual actions;
* ``recipe``: the training recipe's stack, ``SafetyFilter(CartesianImpedanceAction(residual=True))``
  with random residual actions: its ratio to ``filtered random`` (the filtered torque env) is the
  one the design targets (≤ 1.2), printed on its own line as the median of the rounds' ratios;
* ``Pusher-v5``: Gymnasium's MuJoCo arm, for reference (5 physics steps of 10 ms per step,
  against our 10 of 2 ms, so its steps are not the same amount of physics);
* with ``--compare SETTING=VALUE ...``: ``filtered random``, ``filtered adversarial`` and
  ``recipe`` again, under the default filter with those settings changed (``FilterConfig``
  fields, e.g. ``allowance_level=true``), in the same rounds; their cost against the default
  filter's is printed on its own line, as medians of the rounds' ratios.

Only ``step`` calls are timed; episodes are reset between them, untimed. Resets are timed apart,
per scenario (``--reset-samples`` each): the median and p99, in ms. A breakdown line estimates
where the time goes from the rounds' differences: the bare physics per physics step, the
environment's own work per policy step (unfiltered − bare), and what the filter adds per physics
step ((filtered − unfiltered) / frame_skip). ``--profile`` prints cProfile's top functions for one
round of unfiltered and filtered steps (the filter's calls are inside one compiled call there).

Usage::

    python benchmarks/env_speed.py                              # 5 rounds x 1000 steps, scenario multi
    python benchmarks/env_speed.py --rounds 9 --profile --json results/env_speed.json
    python benchmarks/env_speed.py --points ee                  # the filter protecting the tool sphere only
    python benchmarks/env_speed.py --compare allowance_level=true   # a filter option's cost, side by side
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import statistics
import sys
import time
from pathlib import Path

import gymnasium as gym
import mujoco
import numpy as np

import c3bf_gym  # noqa: F401  (registers C3BFReach-v0)
from c3bf_gym import CartesianImpedanceAction, FilterConfig, SafetyFilter
from c3bf_gym.cli import add_filter_settings
from c3bf_gym.scenarios import SCENARIOS

sys.path.insert(0, str(Path(__file__).resolve().parent))
from guarantee import adversarial_action  # noqa: E402  (the sweep's adversary)

CONFIGS = ("bare", "bare, reset states", "bare, parked", "unfiltered", "filtered random", "filtered adversarial",
           "impedance", "recipe", "Pusher-v5")
#: The configurations ``--compare`` times again under the changed filter (names suffixed by " *").
COMPARED = ("filtered random", "filtered adversarial", "recipe")


def _policy_runner(env: gym.Env, steps: int, seed: int, adversarial: bool):
    """``run() -> seconds spent in env.step`` over ``steps`` steps: random actions drawn from a
    seeded generator (or the adversary's), resets at episode ends untimed."""
    rng = np.random.default_rng(seed)
    shape, low, high = env.action_space.shape, env.action_space.low, env.action_space.high
    env.reset(seed=seed)

    def run() -> float:
        spent = 0.0
        step, clock = env.step, time.perf_counter
        for _ in range(steps):
            action = adversarial_action(env.unwrapped) if adversarial else rng.uniform(low, high, shape).astype(np.float32)
            start = clock()
            _, _, terminated, truncated, _ = step(action)
            spent += clock() - start
            if terminated or truncated:
                env.reset()
        return spent

    run()  # warm-up: first-call costs (allocation, compiled code loading) out of round 1
    return run


def _replay_runner(env_id: str, scenario: str, steps: int, seed: int):
    """``run()`` for ``mj_step(nstep=frame_skip)`` on a fresh ``MjData`` of the env's model from
    the recorded states of ``steps`` unfiltered steps with random actions (seeded as
    :func:`_policy_runner`'s), each with the torque that step applied."""
    env = gym.make(env_id, scenario=scenario)
    base = env.unwrapped
    model, frame_skip = base.model, base.frame_skip
    spec = mujoco.mjtState.mjSTATE_INTEGRATION  # positions, velocities, mocap (obstacles), warm start
    states = np.empty((steps, mujoco.mj_stateSize(model, spec)))
    torques = np.empty((steps, model.nu))
    rng = np.random.default_rng(seed)
    shape, low, high = env.action_space.shape, env.action_space.low, env.action_space.high
    env.reset(seed=seed)
    for k in range(steps):
        mujoco.mj_getState(model, base.data, states[k], spec)
        _, _, terminated, truncated, _ = env.step(rng.uniform(low, high, shape).astype(np.float32))
        torques[k] = base.data.ctrl
        if terminated or truncated:
            env.reset()
    data = mujoco.MjData(model)

    def run() -> float:
        spent = 0.0
        clock = time.perf_counter
        for k in range(steps):
            mujoco.mj_setState(model, data, states[k], spec)
            data.ctrl[:] = torques[k]
            start = clock()
            mujoco.mj_step(model, data, nstep=frame_skip)
            spent += clock() - start
        return spent

    run()
    return env, run


def _bare_runner(env_id: str, scenario: str, steps: int, seed: int, parked: bool = False):
    """``run()`` for ``mj_step(nstep=frame_skip)`` on a fresh ``MjData`` of the env's model, from
    the state of a seeded reset of ``scenario`` (``parked``: from the ``home`` keyframe), starting
    again from a new one every 250 steps (an episode's length)."""
    env = gym.make(env_id, scenario=scenario)
    env.reset(seed=seed)
    model, frame_skip = env.unwrapped.model, env.unwrapped.frame_skip
    data = mujoco.MjData(model)
    episodes = iter(range(seed, seed + 1_000_000))

    def restart() -> None:
        if parked:
            mujoco.mj_resetDataKeyframe(model, data, 0)
        else:
            env.reset(seed=next(episodes))
            mujoco.mj_copyData(data, model, env.unwrapped.data)

    restart()
    controls = np.random.default_rng(seed).uniform(-1, 1, (steps, model.nu)) * model.actuator_ctrlrange[:, 1] * 0.2

    def run() -> float:
        spent = 0.0
        clock = time.perf_counter
        for k in range(steps):
            data.ctrl[:] = controls[k]
            start = clock()
            mujoco.mj_step(model, data, nstep=frame_skip)
            spent += clock() - start
            if k % 250 == 249:
                restart()
        return spent

    run()
    return env, run


def reset_times(env_id: str, samples: int, seed: int) -> dict[str, dict[str, float]]:
    """Per scenario, median and p99 of ``reset`` in ms over ``samples`` seeded resets."""
    out = {}
    for scenario in SCENARIOS:
        if scenario == "none":
            continue
        env = gym.make(env_id, scenario=scenario)
        env.reset(seed=seed)
        times = []
        for i in range(samples):
            start = time.perf_counter()
            env.reset(seed=seed + i)
            times.append(time.perf_counter() - start)
        env.close()
        out[scenario] = {"median_ms": 1e3 * statistics.median(times), "p99_ms": 1e3 * float(np.percentile(times, 99))}
    return out


def profile(run, label: str, top: int = 15) -> None:
    profiler = cProfile.Profile()
    profiler.enable()
    run()
    profiler.disable()
    print(f"\ncProfile, one round of {label} steps (top {top} by own time):")
    pstats.Stats(profiler).sort_stats("tottime").print_stats(top)


def _breakdown(per_step: dict[str, list[float]], frame_skip: int) -> dict[str, float]:
    """Where a policy step's time goes, from the rounds' own pairs (µs): the bare physics per
    physics step, the environment's own work per policy step (unfiltered − bare) and what the
    filter adds per physics step ((filtered − unfiltered) / frame_skip: its rows and QP, and the
    hook's bookkeeping). The filtered and unfiltered episodes differ (the filter changes the
    torques), so these are estimates of each part, not an exact split."""
    def median_of(a: str, b: str | None = None, scale: float = 1.0) -> float:
        pairs = zip(per_step[a], per_step[b]) if b else ((t, 0.0) for t in per_step[a])
        return statistics.median((x - y) / scale for x, y in pairs)

    return {"physics_us": median_of("bare", scale=frame_skip), "env_us": median_of("unfiltered", "bare"),
            "filter_random_us": median_of("filtered random", "unfiltered", frame_skip),
            "filter_adversarial_us": median_of("filtered adversarial", "unfiltered", frame_skip)}  # fmt: skip


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds (default 5)")
    parser.add_argument("--steps", type=int, default=1000, help="policy steps per configuration per round (default 1000)")
    parser.add_argument("--scenario", default="multi", choices=[s for s in SCENARIOS if s != "none"],
                        help="C3BFReach scenario of the step timing (default multi: 4 obstacles)")  # fmt: skip
    parser.add_argument("--env", default="C3BFReach-v0", choices=["C3BFReach-v0", "C3BFReachPanda-v0"])
    parser.add_argument("--points", default="whole_arm", choices=["whole_arm", "ee"],
                        help="what the filtered configurations protect: the whole arm (default) or the tool sphere")
    parser.add_argument("--reset-samples", type=int, default=200, help="timed resets per scenario (default 200; 0: none)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--profile", action="store_true", help="print the cProfile breakdown of unfiltered and filtered steps")
    parser.add_argument("--json", type=Path, help="also write the results as JSON here")
    add_filter_settings(parser, "--compare", note=": times the filtered configurations again with them, side by side")
    args = parser.parse_args(argv)
    if args.rounds < 1 or args.steps < 1 or args.reset_samples < 0:
        parser.error("--rounds and --steps must be >= 1, --reset-samples >= 0")
    default = FilterConfig(points=args.points)
    try:
        compared = default.replace(**dict(args.compare)) if args.compare else None
    except (TypeError, ValueError) as error:
        parser.error(f"--compare: {error}")

    bare_env, run_bare = _replay_runner(args.env, args.scenario, args.steps, args.seed)
    reset_env, run_reset = _bare_runner(args.env, args.scenario, args.steps, args.seed)
    parked_env, run_parked = _bare_runner(args.env, args.scenario, args.steps, args.seed, parked=True)
    def make(residual: bool = False) -> gym.Env:
        env = gym.make(args.env, scenario=args.scenario)
        return CartesianImpedanceAction(env, residual=True) if residual else env

    def filtered(config: FilterConfig, suffix: str = "") -> dict[str, gym.Env]:
        """The configurations of :data:`COMPARED` under the filter ``config``, named with ``suffix``."""
        return {f"filtered random{suffix}": SafetyFilter(make(), config),
                f"filtered adversarial{suffix}": SafetyFilter(make(), config),
                f"recipe{suffix}": SafetyFilter(make(residual=True), config)}  # fmt: skip

    envs = {"unfiltered": make(), **filtered(default), "impedance": make(residual=True),
            "Pusher-v5": gym.make("Pusher-v5")}  # fmt: skip
    configs = CONFIGS
    if compared is not None:
        envs |= filtered(compared, " *")
        configs = CONFIGS + tuple(f"{name} *" for name in COMPARED)
    runs = {"bare": run_bare, "bare, reset states": run_reset, "bare, parked": run_parked}
    for name, env in envs.items():
        runs[name] = _policy_runner(env, args.steps, args.seed, adversarial=name.startswith("filtered adversarial"))
    frame_skip, dt = bare_env.unwrapped.frame_skip, bare_env.unwrapped.dt
    print(f"{args.env}, scenario {args.scenario}: {frame_skip} physics steps ({dt * 1e3:.0f} ms) per policy step; "
          f"{args.rounds} rounds x {args.steps} steps per configuration, interleaved")  # fmt: skip
    per_step: dict[str, list[float]] = {name: [] for name in configs}
    for r in range(args.rounds):
        order = configs[r % len(configs):] + configs[: r % len(configs)]
        for name in order:
            per_step[name].append(1e6 * runs[name]() / args.steps)
    ratios = {name: [t / b for t, b in zip(per_step[name], per_step["bare"])] for name in configs}
    header = f"{'configuration':<22} | {'µs/step median':>14} {'min':>8} {'max':>8} | {'× bare (median of rounds)':>26}"
    print(header)
    print("-" * len(header))
    for name in configs:
        t = per_step[name]
        print(f"{name:<22} | {statistics.median(t):>14.0f} {min(t):>8.0f} {max(t):>8.0f} | {statistics.median(ratios[name]):>26.2f}")
    recipe = statistics.median(r / f for r, f in zip(per_step["recipe"], per_step["filtered random"]))
    impedance = statistics.median(i / u for i, u in zip(per_step["impedance"], per_step["unfiltered"]))
    print(f"\nthe recipe's stack (residual impedance + filter) ÷ the filtered torque env: {recipe:.2f} "
          f"(target <= 1.2); the impedance controller alone ÷ the unfiltered env: {impedance:.2f} (medians of the rounds' ratios)")
    changed = {}
    if compared is not None:
        changed = {name: statistics.median(a / b for a, b in zip(per_step[f"{name} *"], per_step[name]))
                   for name in COMPARED}  # fmt: skip
        settings = ", ".join(f"{k}={v}" for k, v in args.compare)
        print(f"with {settings} (*) ÷ the default filter: "
              + ", ".join(f"{name} {ratio:.2f}" for name, ratio in changed.items()) + " (medians of the rounds' ratios)")
    breakdown = _breakdown(per_step, frame_skip)
    print(f"\nbreakdown (medians of the rounds' differences): the bare physics {breakdown['physics_us']:.1f} µs per "
          f"physics step; the environment's own work {breakdown['env_us']:.0f} µs per policy step (unfiltered − bare); "
          f"the filter {breakdown['filter_random_us']:.1f} µs per physics step with random torques and "
          f"{breakdown['filter_adversarial_us']:.1f} with the adversary ((filtered − unfiltered) / {frame_skip})")
    resets = reset_times(args.env, args.reset_samples, args.seed) if args.reset_samples else {}
    if resets:
        print(f"\nreset, {args.reset_samples} seeded resets per scenario [ms]: "
              + ", ".join(f"{s} {v['median_ms']:.2f} (p99 {v['p99_ms']:.2f})" for s, v in resets.items()))  # fmt: skip
    if args.profile:
        profile(runs["unfiltered"], "unfiltered")
        profile(runs["filtered random"], "filtered (random actions)")
    result = {
        "env": args.env, "scenario": args.scenario, "rounds": args.rounds, "steps": args.steps, "frame_skip": frame_skip,
        "us_per_step": per_step, "ratio_to_bare": {k: statistics.median(v) for k, v in ratios.items()}, "reset_ms": resets,
        "breakdown": breakdown, "recipe_to_filtered": recipe, "impedance_to_unfiltered": impedance,
        "compared": {"settings": dict(args.compare), "to_default": changed} if compared is not None else None,
    }  # fmt: skip
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2))
    for env in (*envs.values(), bare_env, reset_env, parked_env):
        env.close()
    return result


if __name__ == "__main__":
    main()
