"""The safety filter on your own MuJoCo arm, without Gymnasium.

Loads an MJCF arm, adds a mocap ball, and drives the tool with a Cartesian impedance controller
(c3bf_gym.controllers.CartesianImpedance) along a straight minimum-jerk path while the ball
crosses that path at the moment the tool gets there. The same seconds run twice, without and
with the filter (c3bf_gym.safety.SafetyController), and the script prints the lowest clearance
between the ball and the protected geoms (MuJoCo's own mj_geomDistance, independent of the
filter) and how often the filter intervened.

    python examples/own_arm.py path/to/arm.xml --site tool --bodies link2 link3 \\
        --joint-speed-limit 2.0

What the model needs (the filter checks and names what is missing): a torque motor (<motor>) on
every joint, torque limits (ctrlrange, forcerange or the joint's actuatorfrcrange), collision geoms
on the links to protect (meshes, boxes and cylinders are enclosed by capsules; the script prints
them), a tool site, and joint ranges. The project's own arms run as they are:

    python examples/own_arm.py assets/ur5e.xml --site ee_site --joint-speed-limit 3.14159
    python examples/own_arm.py assets/panda.xml --site ee_site --joint-speed-limit 2.175

MuJoCo Menagerie models often use position servos for actuators: replace them by <motor>
actuators; the filter refuses, by name, any model it cannot protect. The mujoco-menagerie package
downloads Menagerie's models on first use; pass the path of the downloaded arm's XML.
"""

from __future__ import annotations

import argparse
import sys

import mujoco
import numpy as np

from c3bf_gym.controllers import CartesianImpedance
from c3bf_gym.safety import FilterConfig, MocapSpheres, RobotDescription, SafetyController

BALL = "c3bf_example_ball"


def load(path: str, radius: float) -> mujoco.MjModel:
    """The model at ``path`` with a mocap ball (no contacts: clearance is measured, not felt)."""
    spec = mujoco.MjSpec.from_file(path)
    body = spec.worldbody.add_body(name=BALL, mocap=True, pos=[0.0, 0.0, -10.0])
    body.add_geom(name=BALL, type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[radius, 0, 0], contype=0, conaffinity=0,
                  rgba=[0.9, 0.2, 0.15, 0.8])  # fmt: skip
    return spec.compile()


def min_jerk(start: np.ndarray, goal: np.ndarray, duration: float, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Position, velocity and acceleration of a minimum-jerk move from ``start`` to ``goal``."""
    s = min(max(t / duration, 0.0), 1.0)
    delta = goal - start
    pos = 10 * s**3 - 15 * s**4 + 6 * s**5
    vel = (30 * s**2 - 60 * s**3 + 30 * s**4) / duration if s < 1.0 else 0.0
    acc = (60 * s - 180 * s**2 + 120 * s**3) / duration**2 if s < 1.0 else 0.0
    return start + pos * delta, vel * delta, acc * delta


def picture(model: mujoco.MjModel, robot: RobotDescription, path: str) -> None:
    """A PNG of the arm at its start with the capsules the filter protects drawn over it
    (translucent), from a camera that looks at the arm: what ``robot.describe`` lists, seen."""
    import imageio.v3 as iio  # the experiments extra

    data = mujoco.MjData(model)
    if model.nkey:
        mujoco.mj_resetDataKeyframe(model, data, 0)
    mujoco.mj_forward(model, data)
    a, b, radius = robot.capsule_segments(data)
    camera = mujoco.MjvCamera()
    mujoco.mjv_defaultFreeCamera(model, camera)
    camera.lookat[:] = (a + b).mean(axis=0) / 2
    camera.distance, camera.azimuth, camera.elevation = 2.5 * np.ptp(np.vstack([a, b]), axis=0).max() + 0.5, 135, -20
    with mujoco.Renderer(model, 480, 640) as renderer:
        renderer.update_scene(data, camera)
        scene = renderer.scene
        for start, end, r in zip(a, b, radius, strict=True):
            if scene.ngeom == scene.maxgeom:
                break
            geom = scene.geoms[scene.ngeom]
            mujoco.mjv_initGeom(geom, mujoco.mjtGeom.mjGEOM_CAPSULE, np.zeros(3), np.zeros(3), np.eye(3).ravel(),
                                np.array([0.1, 0.6, 1.0, 0.35], dtype=np.float32))  # fmt: skip
            if np.allclose(start, end):  # a sphere
                mujoco.mjv_initGeom(geom, mujoco.mjtGeom.mjGEOM_SPHERE, np.full(3, r), start, np.eye(3).ravel(),
                                    np.array([0.1, 0.6, 1.0, 0.35], dtype=np.float32))  # fmt: skip
            else:
                mujoco.mjv_connector(geom, mujoco.mjtGeom.mjGEOM_CAPSULE, r, start, end)
            scene.ngeom += 1
        iio.imwrite(path, renderer.render())


def run(model: mujoco.MjModel, robot: RobotDescription, args: argparse.Namespace, ball: tuple | None,
        filtered: bool) -> dict:
    """One rollout of ``args.seconds``; ``ball`` = (start, velocity) or None (parked far away)."""
    data = mujoco.MjData(model)
    if model.nkey:
        mujoco.mj_resetDataKeyframe(model, data, 0)
    ball_id = model.geom(BALL).id
    mocap = model.body(BALL).mocapid[0]
    start_ball, velocity = ball if ball is not None else (np.array([0.0, 0.0, -10.0]), np.zeros(3))
    data.mocap_pos[mocap] = start_ball
    mujoco.mj_forward(model, data)
    spheres = MocapSpheres(model, [BALL])
    config = FilterConfig(margin=args.margin)
    controller = SafetyController(model, data, robot, spheres, config)  # also the arm model for the nominal
    arm = controller.arm
    nominal = CartesianImpedance(stiffness=300.0, posture=data.qpos.copy(), max_force=150.0)
    start = data.site_xpos[robot.site_id].copy()
    goal = start + np.asarray(args.move)
    lowest, interventions, infeasible, path = np.inf, 0, 0, []
    for step in range(int(round(args.seconds / model.opt.timestep))):
        mujoco.mj_step1(model, data)
        t = data.time
        lowest = min(lowest, min(mujoco.mj_geomDistance(model, data, ball_id, g, 10.0, None) for g in robot.geom_ids))
        path.append(data.site_xpos[robot.site_id].copy())
        arm.update(data)
        site = arm.site_dynamics(data)
        jac = site.jac[0]
        target = min_jerk(start, goal, args.move_time, t)
        tau = nominal.torque(data.qpos, data.qvel, site.pos[0], site.vel[0], jac, site.c[0] - jac @ arm.qacc_free,
                             arm.Minv, data.qfrc_bias, *target)  # fmt: skip
        tau = np.clip(tau, -robot.torque_limit, robot.torque_limit)
        if filtered:
            spheres.velocity[0] = velocity
            tau, report = controller.filter(tau)
            interventions += report.intervened
            infeasible += not report.feasible
        robot.write_ctrl(model, data, tau)  # gear, actuator order, gravity compensation through the motors
        mujoco.mj_step2(model, data)
        data.mocap_pos[mocap] += velocity * model.opt.timestep
    return {"lowest": lowest, "interventions": interventions, "infeasible": infeasible, "path": np.array(path)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)  # fmt: skip
    parser.add_argument("model", help="path to the arm's MJCF")
    parser.add_argument("--site", required=True, help="the tool site the controller drives")
    parser.add_argument("--bodies", nargs="+", help="protect the geoms of these bodies")
    parser.add_argument("--group", type=int, help="protect the geoms of this geom group")
    parser.add_argument("--joint-speed-limit", type=float, default=2.0, help="joint speed bound [rad/s]")
    parser.add_argument("--move", type=float, nargs=3, default=(0.0, 0.3, -0.1), help="tool displacement [m]")
    parser.add_argument("--move-time", type=float, default=2.0, help="duration of the move [s]")
    parser.add_argument("--seconds", type=float, default=3.0, help="length of each rollout [s]")
    parser.add_argument("--ball-radius", type=float, default=0.05, help="[m]")
    parser.add_argument("--ball-speed", type=float, default=0.4, help="[m/s]")
    parser.add_argument("--margin", type=float, default=FilterConfig.margin, help="the filter's margin [m]")
    parser.add_argument("--picture", help="also write a PNG of the arm with its protected capsules drawn over it")
    args = parser.parse_args(argv)

    model = load(args.model, args.ball_radius)
    robot = RobotDescription.from_model(model, bodies=args.bodies, group=args.group, site=args.site,
                                        joint_speed_limit=args.joint_speed_limit)  # fmt: skip
    print(f"{model.nv} joints, protecting {', '.join(model.geom(g).name or str(g) for g in robot.geom_ids)}")
    print(robot.describe(model))
    if args.picture:
        picture(model, robot, args.picture)
        print(f"wrote {args.picture}")
    # where the tool is halfway through its move, without a ball: the ball meets it there
    path = run(model, robot, args, None, filtered=False)["path"]
    meet_step = int(round(0.5 * args.move_time / model.opt.timestep))
    meet = path[min(meet_step, len(path) - 1)]
    heading = path[-1] - path[0]
    across = np.cross(heading, [0.0, 0.0, 1.0])
    across = across / np.linalg.norm(across) if np.linalg.norm(across) > 1e-9 else np.array([1.0, 0.0, 0.0])
    travel = args.ball_speed * meet_step * model.opt.timestep
    ball = (meet + travel * across, -args.ball_speed * across)
    for filtered in (False, True):
        result = run(model, robot, args, ball, filtered)
        name = "filtered  " if filtered else "unfiltered"
        print(f"{name}: lowest clearance {1e3 * result['lowest']:+.1f} mm"
              + (f", {result['interventions']} interventions, {result['infeasible']} infeasible physics steps"
                 if filtered else ""))  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
