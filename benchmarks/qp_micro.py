"""Micro-benchmark of c3bf_gym.qp.TorqueQP.solve (n = 6, 24/48/72/92 rows), both solvers.

Random feasible problems that drift a little every call, as a warm-started
filter sees them.  Each row k is A_k τ ≥ A_k τ* − δ_k with a slowly moving
feasible τ*, so a few rows bind; τ_nom lies outside the safe set on a
fraction of the calls ("binding") and inside it otherwise ("safe", fast path).
Problem generation is done before timing.  Each ``--solver`` gets its own layer and
they solve the same calls interleaved (the order alternates per call), so machine
noise hits them alike.  Prints, per solver, median / p99 of the layer's own
``solve_time`` and of the iteration count, the status counts and the calls the
active-set solver handed to proxsuite ("fb"); then the median and p99 ratios of
the first solver over the second, and the largest torque difference between them.

Usage:  PYTHONPATH=. python benchmarks/qp_micro.py [--calls 3000] [--solver active_set proxsuite]
"""

import argparse

import numpy as np

from c3bf_gym.qp import SOLVERS, TorqueQP


def make_sequence(rng, n, m, calls, binding):
    lo, hi = -np.full(n, 50.0), np.full(n, 50.0)
    A = rng.normal(size=(m, n))
    tau_star = rng.uniform(-5, 5, n)
    delta = rng.uniform(0.0, 2.0, m)
    tau_nom = rng.uniform(-20, 20, n)
    seq = []
    for _ in range(calls):
        A = A + 0.005 * rng.normal(size=A.shape)
        tau_star = np.clip(tau_star + 0.01 * rng.normal(size=n), -40, 40)
        tau_nom = tau_nom + 0.05 * rng.normal(size=n)
        b = A @ tau_star - delta
        if not binding:  # shift rows so tau_nom is safe
            b = np.minimum(b, A @ tau_nom - 0.1)
        seq.append((tau_nom.copy(), A.copy(), b.copy()))
    return lo, hi, seq


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--calls", type=int, default=3000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--solver", nargs="+", choices=SOLVERS, default=list(SOLVERS),
                    help="TorqueQP solvers to compare (default: both; ratios are first / second)")
    args = ap.parse_args()
    n = 6
    print(f"{'rows':>4} {'case':>8} {'solver':>10} {'median_us':>10} {'p99_us':>8} {'it_med':>6} {'it_p99':>6} "
          f"{'fb':>4} statuses")
    for m in (24, 48, 72, 92):
        for binding in (True, False):
            rng = np.random.default_rng(args.seed + m)
            lo, hi, seq = make_sequence(rng, n, m, args.calls, binding)
            qps = [TorqueQP(n, m, lo, hi, solver=s) for s in args.solver]
            times = [[] for _ in qps]
            iters = [[] for _ in qps]
            stat = [{} for _ in qps]
            diff = 0.0
            for k, (tn, A, b) in enumerate(seq):
                order = range(len(qps)) if k % 2 == 0 else reversed(range(len(qps)))
                taus = {}
                for i in order:
                    r = qps[i].solve(tn, A, b)
                    taus[i] = r.tau.copy()
                    if k >= 20:  # skip the cold start
                        times[i].append(r.solve_time)
                        iters[i].append(r.iterations)
                        stat[i][r.status] = stat[i].get(r.status, 0) + 1
                diff = max(diff, max(float(np.abs(t - taus[0]).max()) for t in taus.values()))
            case = "binding" if binding else "safe"
            for i, qp in enumerate(qps):
                t = np.array(times[i]) * 1e6
                it = np.array(iters[i])
                print(f"{m:>4} {case:>8} {qp.solver:>10} {np.median(t):10.1f} {np.percentile(t, 99):8.1f}"
                      f" {np.median(it):6.0f} {np.percentile(it, 99):6.0f} {qp.active_set_fallbacks:>4} {stat[i]}")
            if len(qps) > 1:
                t0, t1 = (np.array(times[i]) for i in (0, 1))
                print(f"{m:>4} {case:>8} {'ratio':>10} {np.median(t0) / np.median(t1):10.2f}"
                      f" {np.percentile(t0, 99) / np.percentile(t1, 99):8.2f}   max |Δτ| {diff:.1e}")


if __name__ == "__main__":
    main()
