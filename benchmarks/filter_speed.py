"""Cost of the safety filter per physics step (the hook).

**Hook latency.** The whole-arm C3BF filter hook, timed call by call while it filters a real
rollout at 500 Hz (after 5 untimed warm-up steps): the environment (scenario ``none``) gets 1, 4
or 8 obstacles placed by hand around the arm (0.07-0.3 m from it, drifting slowly, all within the
sensing radius so every one adds a row per link; re-placed every 50 steps), and an adversarial
policy drives the arm point nearest to an obstacle straight at it, so the rows bind and the QP
has work to do (``--policy random``: uniformly random torques instead). Every ``hook(tau)`` call
is timed as a whole; with ``--split`` also (same call, no second evaluation) its rows
(``SafetyHook.rows``: arm dynamics, barrier, joint limits) and QP solve (the QP object's
``solve_scaled``), for a hook that calls them: the whole-arm hook runs both in one kernel
(``_step.filter_substep``, which a call from Python enters through ``filter_substep_at``), so its
split columns stay empty ("nan"). Median, p99, max and mean in µs of all calls, the median of the
solved ones, and median and p99 of the relaxed ones (no torque satisfied every row: the rows gave
way), and the QP's status counts.

**The same calls in compiled code.** Each latency run is repeated with the same seed while
:class:`Replay` records every call's inputs; then every call is replayed in order with its inputs
restored (untimed, in Python) and :func:`c3bf_gym.safety._step.filter_substep` alone timed in
compiled code with the CPU's time-stamp counter (x86 only): the call an environment's compiled
policy step makes between two physics steps, without what a call from Python adds around it. The
replay must give every recorded torque bit for bit (it replays the same solves, warm starts
included); the script says so beside the median, p99 and mean, or says that it did not.
``--no-replay`` skips it (the package's versions before the fused kernel lack what it records).

``--guard auto none`` compares the filter with and without its guard (``SafetyFilter(guard=...)``:
the distance HOCBF's rows beside the C3BF's, or the C3BF's alone; label ``/unguarded``): each
obstacle count runs ``--latency-rounds`` rounds (default 2) of ``--calls / rounds`` calls per
variant, the order rotating per round and round r using seed ``--seed + r`` for both, so machine
noise and the arrangements hit the variants alike; then the ratios of the first over the second.

Env steps with and without the filter, against the bare physics: ``benchmarks/env_speed.py``.

Usage: ``python benchmarks/filter_speed.py [--calls 3000] [--obstacles 1 4 8] [--policy adversarial]
[--guard G [G ...]] [--latency-rounds R] [--split] [--profile] [--no-replay] [--json PATH]``. The script also times
other versions of the package (``PYTHONPATH=/path/to/other/checkout``): it prints which
``c3bf_gym`` it imported, so two trees can be timed alternately with the same script.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import math
import platform
import pstats
import time

import gymnasium as gym
import mujoco
import numpy as np
from llvmlite import ir
from numba import njit
from numba.core import cgutils, types
from numba.extending import intrinsic

import c3bf_gym  # noqa: F401  (registers C3BFReach-v0)
from c3bf_gym import SafetyFilter
from c3bf_gym.envs.reach import DISTANCE_CUTOFF
from c3bf_gym.safety import _step


def place_obstacles(u, count: int, rng: np.random.Generator) -> None:
    """``count`` obstacles 0.07-0.3 m from the arm near random links, slowly drifting, none
    overlapping another or inside the scenarios' keep-out cylinder around the base."""
    m, d = u.model, u.data
    links = u.arm.capsule_ids[1:]  # link2 ... tool (link1 sits on the base axis)
    placed: list[tuple[np.ndarray, float]] = []
    slot = 0
    while slot < count:
        gid = rng.choice(links)
        axis = d.geom_xmat[gid].reshape(3, 3)[:, 2] * m.geom_size[gid, 1]
        on_axis = d.geom_xpos[gid] + rng.uniform(-1.0, 1.0) * axis
        side = rng.normal(size=3)
        side -= (side @ axis) / (axis @ axis) * axis
        side /= np.linalg.norm(side)
        radius = rng.uniform(0.04, 0.07)
        centre = on_axis + side * (m.geom_size[gid, 0] + radius + rng.uniform(0.08, 0.3))
        if centre[2] < radius + 0.05 or any(np.linalg.norm(centre - c) < radius + r + 0.02 for c, r in placed):
            continue
        if np.hypot(centre[0], centre[1]) < 0.3 + radius and centre[2] < 0.45 + radius:
            continue  # the scenarios' keep-out cylinder around the base (nothing can dodge there)
        u.place_obstacle(slot, centre, rng.uniform(-0.05, 0.05, 3), radius)
        if u.obstacle_distances()[slot] < 0.07:  # too close to some other link: park it again
            u.obstacle_active[slot] = False
            u.obstacle_vel[slot] = 0.0
            u.obstacle_pos[slot] = (slot * 2.0 * DISTANCE_CUTOFF, 0.0, -50.0)
            continue
        placed.append((centre, radius))
        slot += 1
    mujoco.mj_forward(m, d)
    u.state_version += 1


def adversarial_action(u) -> np.ndarray:
    """Full torque driving the arm capsule point nearest to any obstacle straight at it."""
    m, d = u.model, u.data
    best = None
    for k in np.flatnonzero(u.obstacle_active):
        centre = u.obstacle_pos[k]
        for gid in u.arm.capsule_ids:
            axis = d.geom_xmat[gid].reshape(3, 3)[:, 2] * m.geom_size[gid, 1]
            a, ab = d.geom_xpos[gid] - axis, 2 * axis
            x = a + np.clip((centre - a) @ ab / (ab @ ab), 0.0, 1.0) * ab
            gap = np.linalg.norm(centre - x) - m.geom_size[gid, 0] - u.obstacle_radius[k]
            if best is None or gap < best[0]:
                best = (gap, x, m.geom_bodyid[gid], centre)
    if best is None:
        return np.zeros(6, np.float32)
    _, x, body, centre = best
    jac = np.zeros((3, m.nv))
    mujoco.mj_jac(m, d, jac, None, x, body)
    action = jac.T @ ((centre - x) / np.linalg.norm(centre - x)) / u.torque_limit
    return np.clip(action / max(np.abs(action).max(), 1e-12), -1, 1).astype(np.float32)


def _rows_of_last_call(qp) -> int:
    """The row count of the QP's last solve: its DAQP problem's constraints less the box (older
    versions of the filter kept it as ``buffers.plain.used[0]``, or ``_m_prev``)."""
    if not hasattr(qp, "buffers"):
        return qp._m_prev
    plain = qp.buffers.plain
    if hasattr(plain, "problem"):
        from c3bf_gym.safety._daqp import PROBLEM_M

        return int(plain.problem[PROBLEM_M]) - len(plain.x)
    return int(plain.used[0])


@intrinsic
def _cycles(typingctx):
    """The CPU's time-stamp counter (``llvm.readcyclecounter``), read in compiled code."""

    def codegen(context, builder, signature, args):
        counter = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.IntType(64), []),
                                                 "llvm.readcyclecounter")
        return builder.call(counter, [])

    return types.uint64(), codegen


@njit
def _read_cycles():
    return _cycles()


#: the replay reads the x86 time-stamp counter: elsewhere ``llvm.readcyclecounter`` may read a
#: register user code cannot (AArch64's cycle counter), so the replay is skipped
REPLAY_MACHINES = ("x86_64", "AMD64", "i686", "i386")


def cycles_per_second() -> float:
    """The time-stamp counter's rate: ticks over ``time.perf_counter_ns`` across 0.3 s, after a
    first read that compiles the reader outside the window."""
    _read_cycles()
    start, counted = time.perf_counter_ns(), _read_cycles()
    time.sleep(0.3)
    return (_read_cycles() - counted) / ((time.perf_counter_ns() - start) * 1e-9)


@njit
def _timed_substep(stage, tau_nom, tau, buffers):
    """One compiled filter call, as an environment's compiled policy step makes it between two
    physics steps; returns ``(status, time-stamp counter ticks)``."""
    start = _cycles()
    status = _step.filter_substep(stage, tau_nom, tau, buffers)
    return status, _cycles() - start


class Replay:
    """The hook's calls again, each timed inside compiled code (no Python in the timed window).

    While the latency run goes, :meth:`record` keeps, for every call, what the fused kernel
    reads (every writable array of the arm's and the obstacles' kernel structures), the QP's
    cold-start flags (a reset between calls), the nominal torque and the answer. :meth:`run`
    restores each call's inputs in Python, untimed, then times
    :func:`c3bf_gym.safety._step.filter_substep` alone, and checks that every call gives the
    recorded torque bit for bit: it replays the same solves, warm starts included.

    Every call is replayed at stage 2 (the arm's dynamics computed in the call), which is what
    the recorded calls ran: the hook loop calls the filter once per physics step, each on a new
    state.
    """

    def __init__(self, hook) -> None:
        self.hook = hook
        self.buffers = hook._bound or hook._bind()
        arm, obstacles = self.buffers[:2]
        self.arrays = [a for a in (*arm, *obstacles) if isinstance(a, np.ndarray) and a.flags.writeable]
        self.cold = hook.qp.buffers.cold
        self.frames: list[tuple] = []

    def record(self, tau_nom: np.ndarray) -> None:
        self.frames.append(([a.copy() for a in self.arrays], self.cold.copy(), np.array(tau_nom, np.float64)))

    def answer(self, tau: np.ndarray) -> None:
        self.frames[-1] += (np.array(tau, np.float64),)

    def run(self) -> tuple[list[float], bool]:
        """Every recorded call once, in order: ``(seconds per call, all torques equal)``."""
        rate = cycles_per_second()
        tau = np.empty(len(self.hook._limit))
        ticks, same = [], True
        for arrays, cold, tau_nom, want in self.frames:
            for target, value in zip(self.arrays, arrays):
                np.copyto(target, value)
            np.copyto(self.cold, cold)
            status, counted = _timed_substep(2, tau_nom, tau, self.buffers)
            ticks.append(counted)
            same = same and status >= 0 and np.array_equal(tau, want)
        return [t / rate for t in ticks], same


class TimedHook:
    """Installed in place of the filter hook: times each call and, with ``split``, its rows / QP
    parts (timers wrapped around ``SafetyHook.rows`` and the QP's solve; they see only a hook that
    calls them, not the fused whole-arm kernel, and cost the timed calls ~1 µs)."""

    def __init__(self, hook, profiler: cProfile.Profile | None = None, split: bool = False,
                 replay: Replay | None = None) -> None:
        self.hook = hook
        self.profiler = profiler
        self.replay = replay
        self.calls = 0
        self.total: list[float] = []
        self.rows: list[float] = []
        self.qp: list[float] = []
        self.status: dict[str, int] = {}
        self.sensed: list[int] = []
        self.n_rows: list[int] = []
        self.relaxed: list[bool] = []
        self.compiled: list[float] = []  # the same calls replayed, compiled only (Replay)
        self.compiled_same = True
        if not split:
            return
        rows = hook.rows

        def timed_rows():
            start = time.perf_counter()
            out = rows()
            self.rows.append(time.perf_counter() - start)
            return out

        def timed(solve):
            def timed_solve(*args):
                start = time.perf_counter()
                result = solve(*args)
                self.qp.append(time.perf_counter() - start)
                return result

            return timed_solve

        hook.rows = timed_rows  # instance attributes shadow the methods for this hook only
        # the hook calls its QP's solve_scaled (solve in older versions of the filter)
        for name in ("solve", "solve_scaled"):
            if hasattr(hook.qp, name):
                setattr(hook.qp, name, timed(getattr(hook.qp, name)))

    def _record(self) -> None:
        """The call's QP outcome, sensed obstacles (the policy step's largest) and row count."""
        hook = self.hook
        result = hook.last
        self.calls += 1
        self.status[result.status] = self.status.get(result.status, 0) + 1
        self.relaxed.append(result.status == "relaxed")
        self.sensed.append(hook.report.sensed)
        self.n_rows.append(_rows_of_last_call(hook.qp))


    def __call__(self, tau: np.ndarray) -> np.ndarray:
        if self.replay is not None:
            self.replay.record(tau)
        if self.profiler is not None:
            self.profiler.enable()
            out = self.hook(tau)
            self.profiler.disable()
        else:
            start = time.perf_counter()
            out = self.hook(tau)
            self.total.append(time.perf_counter() - start)
        if self.replay is not None:
            self.replay.answer(out)
        self._record()
        return out


def hook_latency(count: int, calls: int, seed: int, policy: str = "adversarial", profile: bool = False,
                 split: bool = False, guard: str = "auto", replay: bool = False) -> TimedHook:
    env = SafetyFilter(gym.make("C3BFReach-v0", scenario="none"), barrier="c3bf",
                       **({} if guard == "auto" else {"guard": None}))
    u = env.unwrapped
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    place_obstacles(u, count, rng)
    for _ in range(5):  # warm-up, untimed: first calls load compiled kernels and build solver data
        env.step(adversarial_action(u) if policy == "adversarial" else rng.uniform(-1, 1, 6).astype(np.float32))
    # those steps ran the filter inside the env's compiled policy step; the calls timed below come
    # from Python, whose compiled entry point loads on its first call: load it here, untimed
    env.hook(np.zeros(u.model.nu))
    env.reset(seed=seed)
    place_obstacles(u, count, rng)
    profiler = cProfile.Profile() if profile else None
    timed = TimedHook(env.hook, profiler, split, Replay(env.hook) if replay else None)
    u.remove_torque_hook("filter")
    u.add_torque_hook(timed, "filter")
    steps = 0
    while timed.calls < calls:
        if steps and steps % 50 == 0:  # a fresh arrangement now and then (obstacles drift away)
            env.reset(seed=seed + steps)
            place_obstacles(u, count, rng)
        action = adversarial_action(u) if policy == "adversarial" else rng.uniform(-1, 1, 6).astype(np.float32)
        env.step(action)
        steps += 1
    if timed.replay is not None:  # before close: the recorded arrays are views of the env's data
        timed.compiled, timed.compiled_same = timed.replay.run()
        timed.replay = None
    env.close()
    if profiler is not None:
        stream = io.StringIO()
        stats = pstats.Stats(profiler, stream=stream).sort_stats("tottime")
        stats.print_stats(15)
        print(f"\ncProfile of {timed.calls} filter hook calls with {count} obstacles (top 15 by own time):")
        print(stream.getvalue())
    return timed


def us(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values) * 1e6, q)) if values else math.nan


def variant_name(guard: str) -> str:
    """A latency variant's label: "default", or "unguarded" without the guard."""
    return "unguarded" if guard == "none" else "default"


def summary(timed: list[TimedHook]) -> dict:
    """The table row of the hook timers ``timed`` (calls pooled)."""
    pool = {key: [v for t in timed for v in getattr(t, key)] for key in ("total", "rows", "qp", "sensed")}
    status: dict[str, int] = {}
    for t in timed:
        for k, v in t.status.items():
            status[k] = status.get(k, 0) + v
    relaxed_total = [v for t in timed for v, relaxed in zip(t.total, t.relaxed) if relaxed]
    solved_total = [v for t in timed for v, relaxed in zip(t.total, t.relaxed) if not relaxed]
    compiled = [v for t in timed for v in t.compiled]
    return {
        "compiled_median_us": us(compiled, 50), "compiled_p99_us": us(compiled, 99),
        "compiled_mean_us": float(np.mean(compiled) * 1e6) if compiled else math.nan,
        "compiled_same_torques": all(t.compiled_same for t in timed) if compiled else None,
        "total_median_us": us(pool["total"], 50), "total_p99_us": us(pool["total"], 99),
        "total_max_us": us(pool["total"], 100), "total_mean_us": float(np.mean(pool["total"]) * 1e6),
        "relaxed_median_us": us(relaxed_total, 50),
        "solved_median_us": us(solved_total, 50),
        "relaxed_p99_us": us(relaxed_total, 99),
        "rows_median_us": us(pool["rows"], 50), "rows_p99_us": us(pool["rows"], 99),
        "qp_median_us": us(pool["qp"], 50), "qp_p99_us": us(pool["qp"], 99), "qp_max_us": us(pool["qp"], 100),
        "status": status,
        "sensed_median": float(np.median(pool["sensed"])),
        "rows_count": int(np.median([n for t in timed for n in t.n_rows])),
    }  # fmt: skip


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--calls", type=int, default=3000, help="timed hook calls per obstacle count (default 3000)")
    parser.add_argument("--obstacles", type=int, nargs="+", default=[1, 4, 8], help="obstacle counts (default 1 4 8)")
    parser.add_argument("--policy", choices=("adversarial", "random"), default="adversarial",
                        help="policy during the latency runs (default adversarial: the rows bind)")
    parser.add_argument("--guard", nargs="+", choices=("auto", "none"),
                        help="the filter's guard in the latency runs (default: SafetyFilter's, 'auto'); two are "
                             "compared")  # fmt: skip
    parser.add_argument("--latency-rounds", type=int,
                        help="interleaved latency rounds per obstacle count (default 1, or 2 with two variants)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--split", action="store_true",
                        help="also time the rows and the QP apart (only a hook that calls them: not the fused whole-arm kernel)")
    parser.add_argument("--profile", action="store_true", help="print a cProfile top-15 of the filtered steps (4 obstacles)")
    parser.add_argument("--no-throughput", action="store_true", help=argparse.SUPPRESS)  # accepted: throughput moved to env_speed.py
    parser.add_argument("--no-replay", action="store_true",
                        help="skip replaying the calls in compiled code (Replay; older trees of the package lack it)")
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON to PATH")
    args = parser.parse_args(argv)
    if not args.no_replay and platform.machine() not in REPLAY_MACHINES:
        print(f"no compiled replay on {platform.machine()}: it reads the x86 time-stamp counter")
        args.no_replay = True
    if args.calls < 1 or any(not 1 <= k <= 8 for k in args.obstacles):
        parser.error("--calls must be >= 1 and obstacle counts in 1..8")
    variants = list(dict.fromkeys(args.guard or ["auto"]))  # the guards compared
    rounds = args.latency_rounds or (2 if len(variants) > 1 else 1)
    if rounds < 1 or args.calls < rounds:
        parser.error("--latency-rounds must be >= 1 and <= --calls")

    out: dict = {"hook": {}, "package": c3bf_gym.__file__}
    print(f"c3bf_gym from {c3bf_gym.__file__}")
    print(f"filter hook per physics step, whole-arm C3BF, {args.policy} policy, {args.calls} calls each [µs]"
          + (f", {' vs '.join(map(variant_name, variants))} in {rounds} interleaved rounds" if len(variants) > 1 else ""))
    label = len(variants) > 1 or rounds > 1  # one line per variant, headed by its name
    header = (f"{'obst':>4} {'variant':>10} " if label else f"{'obst':>4} ") + (
              f"{'sensed':>6} {'rows':>4} | {'total med':>9} {'p99':>7} {'max':>8} {'mean':>6} | {'solved med':>10} | {'relaxed med':>11} {'p99':>6} | "
              f"{'rows med':>8} {'p99':>6} | {'QP med':>7} {'p99':>7} {'max':>8} |  QP status")  # fmt: skip
    print(header)
    print("-" * len(header))
    for count in args.obstacles:
        timed: dict = {s: [] for s in variants}
        per_round = args.calls // rounds
        for r in range(rounds):
            for s in variants[r % len(variants):] + variants[: r % len(variants)]:  # rotate who goes first
                timed[s].append(hook_latency(count, per_round, args.seed + r, args.policy,
                                            split=args.split, guard=s))
                if not args.no_replay:  # the same calls again, recorded (which would disturb the timing above)
                    again = hook_latency(count, per_round, args.seed + r, args.policy, guard=s, replay=True)
                    timed[s][-1].compiled, timed[s][-1].compiled_same = again.compiled, again.compiled_same
        rows_by_variant = {s: summary(timed[s]) for s in variants}
        out["hook"][count] = ({variant_name(s): row for s, row in rows_by_variant.items()} if len(variants) > 1
                              else rows_by_variant[variants[0]])
        for s, row in rows_by_variant.items():
            status = ", ".join(f"{k} {v}" for k, v in sorted(row["status"].items()))
            head = f"{count:>4} {variant_name(s):>10} " if label else f"{count:>4} "
            print(f"{head}{row['sensed_median']:>6.0f} {row['rows_count']:>4} | {row['total_median_us']:>9.0f} "
                  f"{row['total_p99_us']:>7.0f} {row['total_max_us']:>8.0f} {row['total_mean_us']:>6.0f} | "
                  f"{row['solved_median_us']:>10.0f} | "
                  f"{row['relaxed_median_us']:>11.0f} "
                  f"{row['relaxed_p99_us']:>6.0f} | {row['rows_median_us']:>8.0f} "
                  f"{row['rows_p99_us']:>6.0f} | {row['qp_median_us']:>7.0f} {row['qp_p99_us']:>7.0f} "
                  f"{row['qp_max_us']:>8.0f} |  {status}")  # fmt: skip
        if len(variants) > 1:
            a, b = (rows_by_variant[s] for s in variants[:2])
            print(f"{count:>4} {'ratio':>10} {'':>11} | {a['total_median_us'] / b['total_median_us']:>9.2f} "
                  f"{a['total_p99_us'] / b['total_p99_us']:>7.2f} {'':>8} {a['total_mean_us'] / b['total_mean_us']:>6.2f} | "
                  f"{a['solved_median_us'] / b['solved_median_us']:>10.2f} | "
                  f"{a['relaxed_median_us'] / b['relaxed_median_us']:>11.2f} "
                  f"{a['relaxed_p99_us'] / b['relaxed_p99_us']:>6.2f} | {'':>15} | "
                  f"{a['qp_median_us'] / b['qp_median_us']:>7.2f} {a['qp_p99_us'] / b['qp_p99_us']:>7.2f}")
    if not args.no_replay:
        print("\nthe same calls replayed in compiled code, each timed alone (what an environment's compiled policy "
              "step runs between two physics steps) [µs]")
        for count, rows in out["hook"].items():
            for name, row in (rows.items() if len(variants) > 1 else [("", rows)]):
                print(f"{count:>4} {name:>10} | median {row['compiled_median_us']:5.1f}  p99 {row['compiled_p99_us']:5.1f}  "
                      f"mean {row['compiled_mean_us']:5.1f} | torques as called from Python: "
                      f"{'equal, bit for bit' if row['compiled_same_torques'] else 'NOT EQUAL (the replay is not faithful)'}")
    if args.profile:
        hook_latency(4, min(args.calls, 2000), args.seed, args.policy, profile=True)

    return _write(out, args.json)


def _write(out: dict, path: str | None) -> dict:
    if path:
        with open(path, "w") as f:
            json.dump(out, f, indent=1, default=str)
    return out


if __name__ == "__main__":
    main()
