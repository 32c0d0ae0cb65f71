"""Micro-benchmark of c3bf_gym.qp.TorqueQP.solve (n = 6, 24/48/72 rows).

Random feasible problems that drift a little every call, as a warm-started
filter sees them.  Each row k is A_k τ ≥ A_k τ* − δ_k with a slowly moving
feasible τ*, so a few rows bind; τ_nom lies outside the safe set on a
fraction of the calls ("binding") and inside it otherwise ("safe", fast path).
Problem generation is done before timing.  Prints median / p99 of the
layer's own ``solve_time`` and of the iteration count.

Usage:  PYTHONPATH=. python benchmarks/qp_micro.py [--calls 3000]
"""

import argparse

import numpy as np

from c3bf_gym.qp import TorqueQP


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
    args = ap.parse_args()
    n = 6
    print(f"{'rows':>4} {'case':>8} {'median_us':>10} {'p99_us':>8} {'it_med':>6} {'it_p99':>6} {'statuses'}")
    for m in (24, 48, 72):
        for binding in (True, False):
            rng = np.random.default_rng(args.seed + m)
            lo, hi, seq = make_sequence(rng, n, m, args.calls, binding)
            qp = TorqueQP(n, m, lo, hi)
            times, iters, stat = [], [], {}
            for k, (tn, A, b) in enumerate(seq):
                r = qp.solve(tn, A, b)
                if k >= 20:  # skip the cold start
                    times.append(r.solve_time)
                    iters.append(r.iterations)
                    stat[r.status] = stat.get(r.status, 0) + 1
            t = np.array(times) * 1e6
            it = np.array(iters)
            print(f"{m:>4} {'binding' if binding else 'safe':>8} {np.median(t):10.1f} {np.percentile(t, 99):8.1f}"
                  f" {np.median(it):6.0f} {np.percentile(it, 99):6.0f} {stat}")


if __name__ == "__main__":
    main()
