"""DAQP against the filter's current QP solver, on QPs recorded from the default filter.

(1) **Record.** ``SafetyFilter(gym.make("C3BFReach-v0", scenario=S))`` with its defaults (C3BF rows,
distance guard, floor and joint limits, weight "limits": u = τ / τ_max, box ±1) runs seeded
rollouts; a recorder installed as the env's torque hook calls ``SafetyHook.rows()`` and
``SafetyHook.relaxation_weights(m)`` and then the filter hook itself at every physics step (500 Hz)
and keeps per call: τ_nom, A, b, scale, weights, the filter's applied torque and status, qvel.
Cases: scenarios ``multi`` and ``head_on``, and ``none`` with 1 / 4 / 8 obstacles placed next to the
arm as ``filter_speed.py`` places them (re-placed every 50 policy steps); policies ``random``
(chattering ±1 torques: a random sign per joint and policy step) and ``adversarial``
(``filter_speed.adversarial_action``).

(2) **Replay**, in recorded order (warm starts carry over), the solvers interleaved call by call
(their order rotates per call), each timed around its whole call with ``perf_counter``:
``active_set`` (``TorqueQP(solver="active_set").solve_scaled``, the filter's current solver),
``proxsuite`` (``TorqueQP(solver="proxsuite")``), ``daqp_py`` (``daqp.Model``: set up once with
the largest row count, zero rows as padding; per call ``update(f, A, blower)`` and ``solve()``,
warm-started from the last working set) and ``daqp_nb`` (the same through DAQP's C API from numba
nopython code, ``daqp_numba.py``). Problem for all: min ½‖u − u_nom‖², |u| ≤ 1, (A diag(scale)) u ≥ b.
The recorded torque is checked against the replayed ``active_set`` one.

(3) **Infeasible calls.** Plain DAQP answers exit flag −1 (``INFEASIBLE``); two DAQP formulations
that always give a torque are run (cold, ``daqp.solve``) on every call: ``daqp_soft`` (the
obstacle rows, C3BF and guard, soft with DAQP's default rho_soft = 1e-6, w_soft = 0) and
``daqp_hier`` (hierarchical: level 0 the torque box (hard), level 1 joint position and speed,
floor and guard rows, level 2 the C3BF rows, then the cost). On the calls without a safe torque
(the current solver's verdict), each torque's largest row-normalised violation (N·m, the layer's
slack unit) of the speed rows, position rows, floor and guard rows, and C3BF rows is printed, and
the calls where the speed rows are violated although some torque in the box satisfies all of them
(checked by DAQP on box + speed rows alone).

Usage: ``MUJOCO_GL=egl python benchmarks/qp_solvers.py [--calls 2000] [--seed 0] [--quick] [--json PATH]``
"""

from __future__ import annotations

import argparse
import json
import time

_T0 = time.perf_counter()
import daqp  # noqa: E402

_T_DAQP_IMPORT = time.perf_counter() - _T0

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402

import c3bf_gym  # noqa: E402,F401  (registers C3BFReach-v0)
from c3bf_gym import SafetyFilter  # noqa: E402
import numba  # noqa: E402

from c3bf_gym import _kernels  # noqa: E402
from c3bf_gym.qp import TorqueQP  # noqa: E402
from filter_speed import adversarial_action, place_obstacles  # noqa: E402  (this folder)

_T1 = time.perf_counter()
import daqp_numba  # noqa: E402  (this folder)

_T_NB_IMPORT = time.perf_counter() - _T1

INF = daqp_numba.INF
SOLVERS = ("active_set", "as_kernel", "proxsuite", "daqp_py", "daqp_nb")
FEASIBLE_FLAGS = (1, 4)  # optimal, optimal (inexact)


# ----------------------------------------------------------------------------- recording


class Recorder:
    """Installed as the env's "filter" torque hook: records the QP of every physics step."""

    def __init__(self, hook) -> None:
        self.hook = hook
        self.calls: list[dict] = []

    def __call__(self, tau_nom):
        hook = self.hook
        A, b, _, _, _ = hook.rows()
        m = len(b)
        w = hook.relaxation_weights(m)
        rec = {"tau_nom": np.array(tau_nom, np.float64), "A": A.copy(), "b": b.copy(),
               "weights": None if w is None else w.copy(),
               "m_obs": m - hook._n_floor_rows - hook._n_joint_rows, "n_floor": hook._n_floor_rows,
               "n_joint": hook._n_joint_rows, "qvel": hook.env.data.qvel.copy()}
        tau = hook(tau_nom)
        rec["tau"] = np.array(tau, np.float64)
        rec["status"] = hook.last.status
        rec["feasible"] = bool(hook.last.feasible)
        self.calls.append(rec)
        return tau


def record(scenario: str, policy: str, obstacles: int | None, calls: int, seed: int):
    env = SafetyFilter(gym.make("C3BFReach-v0", scenario=scenario))
    u = env.unwrapped
    hook = env.hook
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    if obstacles:
        place_obstacles(u, obstacles, rng)
    rec = Recorder(hook)
    u.remove_torque_hook("filter")
    u.add_torque_hook(rec, "filter")
    steps, episode = 0, 0
    while len(rec.calls) < calls:
        if policy == "adversarial":
            action = adversarial_action(u)
        else:
            action = rng.choice(np.array([-1.0, 1.0], np.float32), 6)
        _, _, term, trunc, _ = env.step(action)
        steps += 1
        if term or trunc or (obstacles and steps % 50 == 0):
            episode += 1
            env.reset(seed=seed + episode)
            if obstacles:
                place_obstacles(u, obstacles, rng)
    env.close()
    return rec.calls[:calls], hook.qp.max_rows, hook._scale.copy(), hook.qp.tau_min.copy(), hook.qp.tau_max.copy()


# ----------------------------------------------------------------------------- solvers


class Layer:
    """``TorqueQP.solve_scaled`` (the layer as the filter's non-fused path calls it), timed whole."""

    def __init__(self, n, max_rows, lo, hi, solver):
        self.qp = TorqueQP(n, max_rows, lo, hi, solver=solver)

    def solve(self, tau_nom, A, b, scale, w):
        A2 = A.copy()  # solve_scaled scales A in place
        t0 = time.perf_counter()
        r = self.qp.solve_scaled(tau_nom, A2, b, scale, w)
        dt = time.perf_counter() - t0
        return r.tau, r.feasible, 0, dt


class ActiveSetKernel:
    """The current solver's compiled step alone (``_kernels.qp_step``, what the fused hook kernel runs),
    called through an entry point compiled for its argument types (no dispatcher type resolution),
    as ``TorqueQP._solve`` calls it; the layer's ``finish_step`` runs after the timed call (it hands
    the rare step-cap cases to proxsuite, untimed here)."""

    def __init__(self, n, max_rows, lo, hi):
        self.qp = TorqueQP(n, max_rows, lo, hi, solver="active_set")
        self.bufs = self.qp.step_buffers()
        self.entry = None

    def solve(self, tau_nom, A, b, scale, w):
        qp = self.qp
        A2 = A.copy()
        args = (tau_nom, A2, b, scale, w, qp._m_prev, qp._kr, qp.active_set_max_iter, qp.active_tol,
                qp.row_slack_weight, qp._diag_W, *self.bufs)
        if self.entry is None:
            self.entry = _kernels.qp_step.compile(tuple(numba.typeof(a) for a in args))
        t0 = time.perf_counter()
        status, steps, k, active, slack = self.entry(*args)
        dt = time.perf_counter() - t0
        r = qp.finish_step(status, len(b), steps, k, active, slack, w, t0)
        return r.tau, r.feasible, 0, dt


class DaqpModel:
    """``daqp.Model`` (Python API) set up once for ``max_rows`` rows, warm-started by update."""

    def __init__(self, n, max_rows, lo, hi):
        self.n, self.M = n, max_rows
        self.A = np.zeros((max_rows, n))
        self.bu = np.r_[hi, np.full(max_rows, INF)]
        self.bl = np.r_[lo, np.full(max_rows, -INF)]
        self.f = np.zeros(n)
        self.model = daqp.Model()
        t = time.perf_counter()
        self.model.setup(np.eye(n), self.f, self.A, self.bu, self.bl, np.zeros(n + max_rows, np.intc))
        self.setup_time = time.perf_counter() - t

    def solve(self, tau_nom, A, b, scale, w):
        t0 = time.perf_counter()
        m, n = len(b), self.n
        self.A[:m] = A * scale
        self.A[m:] = 0.0
        self.bl[n:n + m] = b
        self.bl[n + m:] = -INF
        self.model.update(f=-tau_nom / scale, A=self.A, blower=self.bl)
        x, _, flag, _ = self.model.solve()
        dt = time.perf_counter() - t0
        return x, flag in FEASIBLE_FLAGS, flag, dt


class DaqpNumba:
    def __init__(self, n, max_rows, lo, hi):
        self.ws = daqp_numba.DaqpWorkspace(n, max_rows, lo, hi)
        self.args = self.ws.args()
        self.entry = None

    def solve(self, tau_nom, A, b, scale, w):
        """Through an entry point compiled for the argument types, as :class:`ActiveSetKernel`."""
        args = (tau_nom, A, b, scale, len(b), *self.args)
        if self.entry is None:
            self.entry = daqp_numba.solve.compile(tuple(numba.typeof(a) for a in args))
        t0 = time.perf_counter()
        flag, _ = self.entry(*args)
        dt = time.perf_counter() - t0
        return self.ws.x, flag in FEASIBLE_FLAGS, flag, dt


def split_rows(c):
    """Index arrays of the row groups of a recorded call (filter.py's row order)."""
    m_obs, nf, nj = c["m_obs"], c["n_floor"], c["n_joint"]
    n = nj // 4
    c3bf = np.arange(0, m_obs, 2)
    guard = np.arange(1, m_obs, 2)
    floor = np.arange(m_obs, m_obs + nf)
    j0 = m_obs + nf
    pos = np.arange(j0, j0 + 2 * n)
    speed = np.arange(j0 + 2 * n, j0 + 4 * n)
    return {"c3bf": c3bf, "guard": guard, "floor": floor, "pos": pos, "speed": speed}


def daqp_cold(c, scale, lo, hi, mode):
    """``daqp.solve`` in u: mode "plain", "soft" (obstacle rows soft) or "hier" (levels). Returns (τ, flag, s)."""
    A, b = c["A"] * scale, c["b"]
    n, m = len(scale), len(b)
    g = split_rows(c)
    sense = np.zeros(n + m, np.intc)
    bp = np.zeros(0, np.intc)
    if mode == "soft":
        sense[n + np.r_[g["c3bf"], g["guard"]].astype(int)] = daqp_numba.SOFT
    elif mode == "hier":
        mid = np.r_[g["pos"], g["speed"], g["floor"], g["guard"]].astype(int)
        order = np.r_[mid, g["c3bf"]].astype(int)
        A, b = A[order], b[order]
        levels = [n] + ([n + len(mid)] if len(mid) else []) + ([n + m] if len(g["c3bf"]) else [])
        bp = np.array(levels, np.intc) if len(levels) > 1 else bp
    elif mode == "speed_only":  # box + speed rows: can some torque in the box hold the speed bound?
        A, b = A[g["speed"]], b[g["speed"]]
        m = len(b)
        sense = np.zeros(n + m, np.intc)
    t = time.perf_counter()
    x, _, flag, _ = daqp.solve(np.eye(n), -c["tau_nom"] / scale, np.ascontiguousarray(A), np.r_[hi, np.full(m, INF)],
                               np.r_[lo, b], sense, break_points=bp)
    return x * scale, flag, time.perf_counter() - t


def violations(c, tau):
    """Largest row-normalised violation (N·m) per row group of τ (0 when all hold)."""
    A, b = c["A"], c["b"]
    r = (b - A @ tau) / np.maximum(np.linalg.norm(A, axis=1), 1e-12)
    return {k: float(max(0.0, r[idx].max())) if len(idx) else 0.0 for k, idx in split_rows(c).items()}


# ----------------------------------------------------------------------------- replay


def stats_us(t):
    t = np.asarray(t) * 1e6
    return float(np.median(t)), float(np.percentile(t, 99)), float(t.mean())


def replay(calls, max_rows, scale, lo, hi, seed):
    n = len(scale)
    t = time.perf_counter()
    make = {
        "active_set": lambda: Layer(n, max_rows, lo, hi, "active_set"),
        "as_kernel": lambda: ActiveSetKernel(n, max_rows, lo, hi),
        "proxsuite": lambda: Layer(n, max_rows, lo, hi, "proxsuite"),
        "daqp_py": lambda: DaqpModel(n, max_rows, lo, hi),
        "daqp_nb": lambda: DaqpNumba(n, max_rows, lo, hi),
    }
    solvers, setup = {}, {}
    for name, f in make.items():
        t = time.perf_counter()
        solvers[name] = f()
        setup[name] = time.perf_counter() - t
    times = {k: [] for k in SOLVERS}
    taus = {k: np.zeros((len(calls), n)) for k in SOLVERS}
    feas = {k: np.zeros(len(calls), bool) for k in SOLVERS}
    flags = {k: np.zeros(len(calls), int) for k in ("daqp_py", "daqp_nb")}
    first = {}
    rot = list(SOLVERS)
    for i, c in enumerate(calls):
        tau_nom, A, b, w = c["tau_nom"], c["A"], c["b"], c["weights"]
        j = i % len(rot)
        order = rot[j:] + rot[:j]
        for name in order:
            x, ok, flag, dt = solvers[name].solve(tau_nom, A, b, scale, w)
            taus[name][i] = np.clip(x, lo, hi) * scale
            feas[name][i] = ok
            if name in flags:
                flags[name][i] = flag
            if i == 0:
                first[name] = dt
            else:
                times[name].append(dt)
    # cold DAQP formulations (not interleaved: behaviour, and their cost as one-shot Python calls)
    cold = {mode: {"tau": np.zeros((len(calls), n)), "flag": np.zeros(len(calls), int), "t": []}
            for mode in ("soft", "hier", "speed_only")}
    for i, c in enumerate(calls):
        for mode, d in cold.items():
            tau, flag, dt = daqp_cold(c, scale, lo, hi, mode)
            d["tau"][i], d["flag"][i] = tau, flag
            d["t"].append(dt)
    return times, taus, feas, flags, cold, setup, first


def analyse(name, calls, times, taus, feas, flags, cold):
    n_calls = len(calls)
    rec_tau = np.array([c["tau"] for c in calls])
    rec_feas = np.array([c["feasible"] for c in calls])
    out = {"case": name, "calls": n_calls, "rows_median": int(np.median([len(c["b"]) for c in calls])),
           "rows_max": int(max(len(c["b"]) for c in calls)),
           "recorded_infeasible": int((~rec_feas).sum()),
           "max_qd": float(max(np.abs(c["qvel"]).max() for c in calls)),
           "replay_vs_recorded_max_dtau": float(np.abs(taus["active_set"] - rec_tau).max())}
    out["time_us"] = {k: stats_us(v) for k, v in times.items()}
    out["time_us"].update({f"daqp_{m}_cold": stats_us(cold[m]["t"]) for m in ("soft", "hier")})
    allf = np.logical_and.reduce([feas[k] for k in SOLVERS])
    out["all_feasible"] = int(allf.sum())
    for ref in ("proxsuite", "active_set"):
        out[f"max_dtau_vs_{ref}"] = {k: float(np.abs(taus[k][allf] - taus[ref][allf]).max()) if allf.any() else
                                     float("nan") for k in SOLVERS if k != ref}
    out["infeasible"] = {k: int((~feas[k]).sum()) for k in SOLVERS}
    out["verdict_disagree_vs_active_set"] = {k: int((feas[k] != feas["active_set"]).sum()) for k in SOLVERS}
    fl = {}
    for k in ("daqp_py", "daqp_nb"):
        vals, cnt = np.unique(flags[k], return_counts=True)
        fl[k] = {daqp_numba.EXIT.get(int(v), str(v)): int(c) for v, c in zip(vals, cnt)}
    for mode in ("soft", "hier"):
        vals, cnt = np.unique(cold[mode]["flag"], return_counts=True)
        fl[f"daqp_{mode}"] = {daqp_numba.EXIT.get(int(v), str(v)): int(c) for v, c in zip(vals, cnt)}
    out["daqp_flags"] = fl
    # hier / soft agree with the hard optimum where it exists
    out["max_dtau_on_feasible"] = {f"daqp_{m}": float(np.abs(cold[m]["tau"][allf] - taus["proxsuite"][allf]).max())
                                   if allf.any() else float("nan") for m in ("soft", "hier")}
    # infeasible calls (the current solver's verdict): what gives way
    inf_idx = np.flatnonzero(~feas["active_set"])
    variants = {"current": taus["active_set"], "proxsuite": taus["proxsuite"], "daqp_soft": cold["soft"]["tau"],
                "daqp_hier": cold["hier"]["tau"]}
    holdable = cold["speed_only"]["flag"] > 0
    out["infeasible_calls"] = len(inf_idx)
    out["speed_holdable_on_infeasible"] = int(holdable[inf_idx].sum())
    viol = {}
    for v, T in variants.items():
        worst = {"speed": 0.0, "pos": 0.0, "floor": 0.0, "guard": 0.0, "c3bf": 0.0}
        broken = 0
        for i in inf_idx:
            d = violations(calls[i], T[i])
            for k in worst:
                worst[k] = max(worst[k], d[k])
            broken += holdable[i] and d["speed"] > 1e-6
        worst["speed_broken_though_holdable"] = int(broken)
        viol[v] = worst
    out["violations"] = viol
    return out


def print_case(o):
    print(f"\n== {o['case']}: {o['calls']} calls, rows median {o['rows_median']} (max {o['rows_max']}), "
          f"recorded relaxed {o['recorded_infeasible']}, max |qd| {o['max_qd']:.2f} rad/s, "
          f"replay vs recorded torque {o['replay_vs_recorded_max_dtau']:.1e} N·m")
    print(f"   {'solver':<16}{'med_us':>8}{'p99_us':>9}{'mean_us':>9}{'infeas':>7}{'disagree':>9}"
          f"{'dτ_vs_prox':>11}{'dτ_vs_cur':>10}")
    for k, (med, p99, mean) in o["time_us"].items():
        inf = o["infeasible"].get(k, "")
        dis = o["verdict_disagree_vs_active_set"].get(k, "")
        dp = o["max_dtau_vs_proxsuite"].get(k, o["max_dtau_on_feasible"].get(k.removesuffix("_cold"), float("nan")))
        dc = o["max_dtau_vs_active_set"].get(k, float("nan"))
        dp_s = "" if k == "proxsuite" else f"{dp:.1e}"
        dc_s = "" if k in ("active_set",) or k.endswith("cold") else f"{dc:.1e}"
        print(f"   {k:<16}{med:8.1f}{p99:9.1f}{mean:9.1f}{inf!s:>7}{dis!s:>9}{dp_s:>11}{dc_s:>10}")
    print(f"   all-feasible calls {o['all_feasible']}; DAQP flags {o['daqp_flags']}")
    print(f"   infeasible calls {o['infeasible_calls']} (speed rows alone holdable on {o['speed_holdable_on_infeasible']}); "
          "largest violation [N·m, row-normalised]:")
    print(f"   {'variant':<11}{'speed':>9}{'pos':>9}{'floor':>9}{'guard':>9}{'c3bf':>9}{'speed broken/holdable':>23}")
    for v, d in o["violations"].items():
        print(f"   {v:<11}{d['speed']:9.3g}{d['pos']:9.3g}{d['floor']:9.3g}{d['guard']:9.3g}{d['c3bf']:9.3g}"
              f"{d['speed_broken_though_holdable']:>23}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--calls", type=int, default=2000, help="recorded physics steps per case (default 2000)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="200 calls per case, 4 cases (under a minute)")
    ap.add_argument("--json", metavar="PATH")
    args = ap.parse_args(argv)
    cases = [("multi", "random", None), ("multi", "adversarial", None), ("head_on", "random", None),
             ("head_on", "adversarial", None)] + [("none", p, k) for k in (1, 4, 8) for p in ("random", "adversarial")]
    calls = args.calls
    if args.quick:
        cases = [("multi", "random", None), ("head_on", "adversarial", None), ("none", "adversarial", 4),
                 ("none", "random", 8)]
        calls = 200
    # first-call cost of the DAQP-from-numba kernel (compiled at every process start: not cacheable)
    ws = daqp_numba.DaqpWorkspace(6, 10, -np.ones(6), np.ones(6))
    t = time.perf_counter()
    daqp_numba.solve(np.zeros(6), np.zeros((1, 6)), np.zeros(1), np.ones(6), 1, *ws.args())
    nb_compile = time.perf_counter() - t
    t = time.perf_counter()
    TorqueQP(6, 10, -np.ones(6), np.ones(6))  # loads the project's cached kernels
    as_first = time.perf_counter() - t
    print(f"import daqp {_T_DAQP_IMPORT * 1e3:.1f} ms; import daqp_numba (ctypes bindings) {_T_NB_IMPORT * 1e3:.1f} ms; "
          f"numba compile of daqp_numba.solve (first call) {nb_compile:.2f} s; first TorqueQP(active_set) "
          f"(kernels from numba's cache) {as_first:.2f} s")
    results = []
    for k, (scenario, policy, obstacles) in enumerate(cases):
        name = f"{scenario}{'' if obstacles is None else f'/{obstacles}obs'}/{policy}"
        t = time.perf_counter()
        rec, max_rows, scale, lo, hi = record(scenario, policy, obstacles, calls, args.seed + 100 * k)
        t_rec = time.perf_counter() - t
        t = time.perf_counter()
        times, taus, feas, flags, cold, setup, first = replay(rec, max_rows, scale, lo, hi, args.seed)
        t_rep = time.perf_counter() - t
        o = analyse(name, rec, times, taus, feas, flags, cold)
        o["setup_s"], o["first_call_s"], o["record_s"], o["max_rows"] = setup, first, t_rec, max_rows
        o["replay_s"] = t_rep
        print_case(o)
        print("   setup ms " + ", ".join(f"{k} {v * 1e3:.2f}" for k, v in setup.items()) + "; first call µs "
              + ", ".join(f"{k} {v * 1e6:.0f}" for k, v in first.items())
              + f"; recording {t_rec:.1f} s, replay {t_rep:.1f} s")
        results.append(o)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"nb_compile_s": nb_compile, "daqp_import_s": _T_DAQP_IMPORT, "cases": results}, fh, indent=1)
    return results


if __name__ == "__main__":
    main()
