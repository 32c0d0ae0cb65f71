"""The envelope the default filter states on every arm, and how the keep-out region moves it.

For the environment's arms (``C3BFReach-v0``'s UR5e, ``C3BFReachPanda-v0``'s Panda) and robosuite's
(``benchmarks/third_party.py``'s arms, their MJCF files from PyPI), prints
:func:`c3bf_gym.safety.filter_envelope` for 8 cm spheres sensed at 1 m (the environments'
defaults): the largest sphere speed with a safe escape, the sensing radius 0.4 m/s would need, and
the point that limits it, for the arm's own keep-out cylinder and, with ``--heights``, for other
keep-out heights at the same radius. With ``--spawns N``, for the environments' arms: of the moving
obstacles in the first N episodes of the ``random`` scenario (seeds 0 to N-1, as placed at reset),
how many appear closer to the arm (surface to surface) than the sensing range ``D(V)`` their speed
needs: the envelope's escape argument assumes an obstacle is first sensed that far out.

Usage::

    python benchmarks/envelope.py                                   # every arm, its own keep-out
    python benchmarks/envelope.py --arms ur5e panda --heights 0.45 0.5 0.6 0.65 0.7
    python benchmarks/envelope.py --arms iiwa --radius 0.2 --heights 0.45 0.9
    python benchmarks/envelope.py --arms ur5e panda --spawns 300
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np

import c3bf_gym  # noqa: F401  (registers the environments)
from c3bf_gym.safety import (
    FilterConfig,
    FilterEnvelope,
    UnprotectedGeometryWarning,
    filter_envelope,
)

sys.path.insert(0, str(Path(__file__).resolve().parent))
import third_party  # noqa: E402

ENVS = {"ur5e": "C3BFReach-v0", "panda": "C3BFReachPanda-v0"}
RADIUS = 0.08  # [m] the largest sphere of the environments' scenarios
CONFIG = FilterConfig(sensing_radius=1.0)  # the default filter at the environments' sensing radius


def _arm(name: str, cache: str | None):
    """(model, robot, home configuration, keep-out (radius, height)) of an arm by name."""
    if name in ENVS:
        env = gym.make(ENVS[name]).unwrapped
        model, robot = env.model, env.robot
        home = model.key_qpos[model.key("home").id][model.jnt_qposadr[model.dof_jntid[robot.dof_ids]]]
        return model, robot, home, (env.envelope.keep_out_radius, env.envelope.keep_out_height)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnprotectedGeometryWarning)
        model, robot, _ = third_party.build_scene(third_party.robosuite_assets(cache), name, 1)
    arm = third_party.ARMS[name]
    return model, robot, arm.init_qpos, arm.keep_out


def spawns_inside(name: str, envelope: FilterEnvelope, episodes: int) -> tuple[int, int]:
    """(moving obstacles placed at reset, those closer to the arm than ``envelope``'s
    ``min_sensing_range`` of their speed) over ``episodes`` resets of environment arm ``name``'s
    ``random`` scenario, seeds 0 to ``episodes - 1``; distances as the filter senses them
    (``obstacle_distances``: MuJoCo's, to every arm geom)."""
    env = gym.make(ENVS[name], scenario="random").unwrapped
    moving = inside = 0
    for seed in range(episodes):
        env.reset(seed=seed)
        speeds = np.linalg.norm(env.obstacles.velocity, axis=1)
        gaps = env.obstacle_distances()
        for k in np.flatnonzero(env.obstacles.active & (speeds > 0.0)):
            moving += 1
            inside += bool(gaps[k] < envelope.min_sensing_range(float(speeds[k])))
    env.close()
    return moving, inside


def main(argv: list[str] | None = None) -> list[dict]:
    choices = list(ENVS) + list(third_party.ARMS)
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--arms", nargs="+", default=choices, choices=choices, metavar="ARM",
                        help=f"from {', '.join(choices)} (default: all)")  # fmt: skip
    parser.add_argument("--radius", type=float, help="keep-out radius [m] (default: each arm's own)")
    parser.add_argument("--heights", type=float, nargs="+", help="keep-out heights [m] (default: each arm's own)")
    parser.add_argument("--configurations", type=int, default=128, help="drawn configurations (default 128)")
    parser.add_argument("--cache", help="robosuite download folder (third_party.py's --cache)")
    parser.add_argument("--spawns", type=int, default=0, metavar="N", help="the environments' arms: moving obstacles "
                        "of N random-scenario episodes placed inside the sensing range their speed needs")  # fmt: skip
    args = parser.parse_args(argv)
    rows = []
    print(f"default filter, spheres up to {RADIUS} m, sensing radius {CONFIG.sensing_radius} m")
    print(f"{'arm':<15} {'keep-out [m]':>13} {'max speed':>9} {'D(0.4)':>7}  limited by (point at its configuration [m])")
    for name in args.arms:
        model, robot, home, (radius, height) = _arm(name, args.cache)
        radius = radius if args.radius is None else args.radius
        for h in args.heights or [height]:
            start = time.perf_counter()
            envelope = filter_envelope(model, robot, CONFIG, obstacle_radius=RADIUS, keep_out_radius=radius,
                                       keep_out_height=h, configurations=args.configurations, qpos=home)  # fmt: skip
            needed = envelope.min_sensing_range(0.4)
            point = [round(float(x), 2) for x in envelope.limiting_point]
            print(f"{name:<15} {radius:>5.2f} x {h:<5.2f} {envelope.max_speed:>9.3f} {needed:>7.2f}  "
                  f"{envelope.limiting_geom} {point}  ({time.perf_counter() - start:.1f} s)")  # fmt: skip
            rows.append({"arm": name, "keep_out": [radius, h], "max_speed": envelope.max_speed,
                         "sensing_for_0.4": needed, "limiting_geom": envelope.limiting_geom, "limiting_point": point})
            if args.spawns and name in ENVS:
                moving, inside = spawns_inside(name, envelope, args.spawns)
                rows[-1]["spawned_inside"] = [inside, moving]
                print(f"{'':<15} {inside} of the {moving} moving obstacles of {args.spawns} episodes appear closer "
                      "than the sensing range their speed needs")  # fmt: skip
    return rows


if __name__ == "__main__":
    main()
