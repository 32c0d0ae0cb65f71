"""What a filtered step costs without the filter's QP, and without its rows too: the floor that any
faster QP, or any faster rows, leaves under the filtered step.

The script copies the ``c3bf_gym`` package it imports into a temporary folder once per variant
and edits the copy's :func:`c3bf_gym.safety._step.filter_substep`, the filter's call at every
physics step (the package itself is not touched):

* ``no QP``: the QP (``solve_call``) is replaced by the nominal torque clipped to the torque
  limits. The rows are built as always (the arm's dynamics, the capsule ends, every barrier,
  guard, floor and joint-limit row), then reported as held.
* ``no rows, no QP``: the rows are left out too (``filter_rows``, which also computes the
  arm's dynamics). What remains is the filtered path's own work: the wrapper's Python once per
  policy step, the compiled policy step's calls and their report.

``filter`` is an unedited copy, so that every variant is compiled and imported alike. Every
variant runs ``benchmarks/env_speed.py`` (``--reset-samples 0``) in its own process, the variants
alternating (the order rotating from run to run), ``--runs`` times. With random torques, the two
edited filters apply what the unfiltered environment applies (the same joint torques, to
rounding), so their filtered steps follow the unfiltered trajectory: before timing, the script
checks in every edited variant that joint positions and velocities stay within
:data:`SAME_STEPS_TOL` of the unfiltered environment's over :data:`SAME_STEPS` steps, resets
included. The difference between their filtered and unfiltered steps, the breakdown line's
"filter per physics step", is then what their remaining parts cost. (The adversary's column is
not comparable across variants: without the QP it drives the arm into the obstacles, whose
contacts make the physics itself dearer.)

Printed per variant and run: the filtered step with random torques × the bare physics, and the
filter per physics step [µs]; then the budget a filtered step of 2× the bare physics leaves the
filter, ``(2 − unfiltered ×) × the bare physics per physics step`` (median over all runs).

Usage: ``python benchmarks/filter_parts.py [--runs 4] [--rounds 5] [--steps 500] [--env ID]
[--json PATH]``. The copies compile their kernels on first use (about 15 s each).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import stat
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
KERNELS = Path("safety") / "_step.py"
#: the text of filter_substep each edit replaces, and its replacement
_ROWS = "    m, min_h, inside, n_sensed = filter_rows(stage, arm, obstacles, params, A, b, tally.row_h)\n"
_NO_ROWS = "    m, min_h, inside, n_sensed = 0, np.inf, False, 0\n"
_QP = "    status, iterations, n_active, slack = solve_call(tau_nom, A[:m], b[:m], scale, params.dofs, layout, tally, qp)\n"
_NO_QP = ("    for j in range(tau_nom.shape[0]):\n"
          "        qp.u[j] = min(max(tau_nom[j] / scale[j], qp.lo[j]), qp.hi[j])\n"
          "    for k in range(m):\n"
          "        qp.norm[k] = 1.0\n"
          "        qp.residual[k] = 1.0\n"
          "    status, iterations, n_active, slack = 0, 0, 0, 0.0\n")  # fmt: skip
VARIANTS = {"filter": (), "no QP": ((_QP, _NO_QP),), "no rows, no QP": ((_ROWS, _NO_ROWS), (_QP, _NO_QP))}
#: the check of an edited variant: policy steps (episodes are 250, so resets are included) and the
#: largest difference allowed from the unfiltered environment's joint positions [rad] and velocities
#: [rad/s] (the torques agree to rounding, not bit for bit)
SAME_STEPS, SAME_STEPS_TOL = 600, 1e-6
#: ``--same-steps``' exit status when the trajectories differ (1 is Python's for an exception)
DIFFERS = 3


def edited_copy(package: Path, edits: tuple, root: Path) -> Path:
    """A copy of ``package`` (the ``c3bf_gym`` folder) under ``root``, its ``filter_substep`` edited by
    ``edits`` (pairs of old and new text; none: a plain copy); returns ``root`` (the folder to put
    on ``PYTHONPATH``). A checkout's package finds its MJCF
    files in the top-level ``assets/`` beside it: that is copied too.

    Raises:
        SystemExit: an edit's text is not in the kernel exactly once (the kernel changed since
            this script was written: update the edits).
    """
    shutil.copytree(package, root / "c3bf_gym", ignore=shutil.ignore_patterns("_numba_cache", "__pycache__"))
    if not (package / "assets").is_dir():
        shutil.copytree(package.parent / "assets", root / "assets")
    for path in root.rglob("*"):  # a read-only install's modes came along: the copy is edited and holds its cache
        path.chmod(path.stat().st_mode | stat.S_IWUSR)
    kernels = root / "c3bf_gym" / KERNELS
    source = kernels.read_text()
    for old, new in edits:
        if source.count(old) != 1:
            raise SystemExit(f"filter_parts.py: {KERNELS} no longer holds this line of filter_substep once; "
                             f"update the script's edits:\n{old}")  # fmt: skip
        source = source.replace(old, new)
    kernels.write_text(source)
    return root


def same_steps(env_id: str, steps: int, seed: int) -> int | None:
    """The first policy step at which the default ``SafetyFilter`` of the imported package, given
    random actions, leaves the unfiltered environment's trajectory (a joint position or velocity
    more than :data:`SAME_STEPS_TOL` apart), or None if it never does in ``steps`` steps."""
    import gymnasium as gym
    import numpy as np

    import c3bf_gym  # noqa: F401  (registers the environments)
    from c3bf_gym import SafetyFilter

    plain, filtered = gym.make(env_id, scenario="multi"), SafetyFilter(gym.make(env_id, scenario="multi"))
    plain.reset(seed=seed)
    filtered.reset(seed=seed)
    rng = np.random.default_rng(seed)
    a, b = plain.unwrapped.data, filtered.unwrapped.data
    for step in range(steps):
        action = rng.uniform(plain.action_space.low, plain.action_space.high).astype(np.float32)
        *_, a_end, a_cut, _ = plain.step(action)
        *_, b_end, b_cut, _ = filtered.step(action)
        if not (np.allclose(a.qpos, b.qpos, rtol=0, atol=SAME_STEPS_TOL)
                and np.allclose(a.qvel, b.qvel, rtol=0, atol=SAME_STEPS_TOL)):
            return step
        if a_end or a_cut or b_end or b_cut:
            plain.reset()
            filtered.reset()
    return None


def _run(root: Path, argv: list[str]) -> subprocess.CompletedProcess:
    """This script's Python on ``argv`` with the copy in ``root`` first on the path, its compiled
    code cached in the copy (a ``NUMBA_CACHE_DIR`` of the caller's would keep it after the copy is
    gone)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(root), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env.pop("NUMBA_CACHE_DIR", None)
    return subprocess.run([sys.executable, *argv], env=env, capture_output=True, text=True)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=4, help="env_speed.py runs per variant, alternated (default 4)")
    parser.add_argument("--rounds", type=int, default=5, help="env_speed.py's --rounds (default 5)")
    parser.add_argument("--steps", type=int, default=500, help="env_speed.py's --steps (default 500)")
    parser.add_argument("--env", default="C3BFReach-v0", choices=["C3BFReach-v0", "C3BFReachPanda-v0"])
    parser.add_argument("--json", type=Path, help="also write the results as JSON here")
    parser.add_argument("--same-steps", type=int, metavar="N", help=argparse.SUPPRESS)  # the check, in a variant's process
    args = parser.parse_args(argv)
    if args.same_steps is not None:
        step = same_steps(args.env, args.same_steps, 0)
        if step is not None:
            print(f"the filtered trajectory leaves the unfiltered one at policy step {step}")
            raise SystemExit(DIFFERS)
        return {}
    if args.runs < 1 or args.rounds < 1 or args.steps < 1:
        parser.error("--runs, --rounds and --steps must be >= 1")

    import c3bf_gym

    package = Path(c3bf_gym.__file__).resolve().parent
    print(f"c3bf_gym from {package}; {args.env}, scenario multi, random torques; "
          f"{args.runs} alternated runs of env_speed.py --rounds {args.rounds} --steps {args.steps}")  # fmt: skip
    results: dict[str, list[dict]] = {name: [] for name in VARIANTS}
    with tempfile.TemporaryDirectory(prefix="filter_parts_") as tmp:
        roots = {name: edited_copy(package, edits, Path(tmp) / str(i)) for i, (name, edits) in enumerate(VARIANTS.items())}
        for name, edits in VARIANTS.items():
            if not edits:
                continue
            check = _run(roots[name], [__file__, "--env", args.env, "--same-steps", str(SAME_STEPS)])
            if check.returncode == DIFFERS:
                raise SystemExit(f"filter_parts.py: the {name!r} variant does not step as the unfiltered env does "
                                 f"({check.stdout.strip()}), so its difference would not be its parts' cost")  # fmt: skip
            if check.returncode != 0:
                raise SystemExit(f"filter_parts.py: the check of the {name!r} variant failed:\n{check.stderr[-2000:]}")
        names = list(VARIANTS)
        for run in range(args.runs):
            for name in names[run % len(names):] + names[: run % len(names)]:
                out = roots[name] / f"env_speed_{run}.json"
                done = _run(roots[name], [str(HERE / "env_speed.py"), "--env", args.env, "--rounds", str(args.rounds),
                                          "--steps", str(args.steps), "--reset-samples", "0", "--json", str(out)])  # fmt: skip
                if done.returncode != 0:
                    raise SystemExit(f"filter_parts.py: env_speed.py failed for {name!r}:\n{done.stderr[-2000:]}")
                results[name].append(json.loads(out.read_text()))

    def column(name: str, pick, digits: int) -> str:
        return ", ".join(f"{pick(r):.{digits}f}" for r in results[name])

    width = max(map(len, VARIANTS)) + 2
    print(f"\n{'':<{width}}| filtered step, random torques, × bare physics | filter per physics step [µs]")
    for name in VARIANTS:
        print(f"{name:<{width}}| {column(name, lambda r: r['ratio_to_bare']['filtered random'], 2):<46} | "
              f"{column(name, lambda r: r['breakdown']['filter_random_us'], 1)}")  # fmt: skip
    every = [r for runs in results.values() for r in runs]
    unfiltered = statistics.median(r["ratio_to_bare"]["unfiltered"] for r in every)
    physics = statistics.median(r["breakdown"]["physics_us"] for r in every)
    budget = (2.0 - unfiltered) * physics
    print(f"\nthe unfiltered step {unfiltered:.2f}× the bare physics ({physics:.1f} µs per physics step), medians over "
          f"all runs: a filtered step of 2× leaves the filter {budget:.1f} µs per physics step")  # fmt: skip
    result = {"env": args.env, "runs": results, "unfiltered_ratio": unfiltered, "physics_us": physics,
              "budget_us_for_2x": budget}  # fmt: skip
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
