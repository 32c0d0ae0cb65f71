"""Tests for c3bf_gym/scenarios.py and the environment's use of it: every spawned obstacle keeps
the :class:`Envelope`'s promises, checked independently of the sampler's own checks.

The keep-out check here is exact (distance from the sphere centre to the solid cylinder, sampled
densely along the path) whereas ``Envelope.path_ok`` is a conservative shortcut, so a pass here
says the promise holds, not that the code agrees with itself.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from c3bf_gym import SCENARIOS, Envelope, ObstacleSpec, Scenario
from c3bf_gym.scenarios import ArmCapsules, ObstacleSampler, get_scenario

import reference

SEEDS = range(60)
EXPECTED_COUNT = {"static": 1, "head_on": 1, "crossing": 1, "multi": 4, "none": 0}
EXPECTED_KINDS = {
    "static": ["static"],
    "head_on": ["head_on"],
    "crossing": ["crossing"],
    "multi": ["static", "head_on", "crossing", "crossing"],
    "none": [],
}


# ----------------------------------------------------------------------------- independent geometry


def keep_out_gap(points: np.ndarray, envelope: Envelope) -> np.ndarray:
    """Distance from each point to the solid keep-out cylinder (0 inside)."""
    radial = np.maximum(np.hypot(points[:, 0], points[:, 1]) - envelope.keep_out_radius, 0.0)
    vertical = np.maximum.reduce([points[:, 2] - envelope.keep_out_height, -points[:, 2], np.zeros(len(points))])
    return np.hypot(radial, vertical)


def path_points(position, velocity, horizon: float, n: int = 2001) -> np.ndarray:
    t = np.linspace(0.0, horizon, n)
    return np.asarray(position)[None, :] + t[:, None] * np.asarray(velocity)[None, :]


def point_segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ab = b - a
    s = np.clip((points - a) @ ab / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(points - (a + s[:, None] * ab), axis=1), s


def capsule_clearance(env, centre: np.ndarray, radius: float) -> float:
    """Smallest sphere-to-capsule surface distance over the arm's capsule geoms (not the base
    cylinder, which the distance sensors cover exactly)."""
    u = env.unwrapped
    m, d = u.model, u.data
    gaps = []
    for gid in u.arm_geom_ids:
        if m.geom_type[gid] != mujoco.mjtGeom.mjGEOM_CAPSULE:
            continue
        axis = d.geom_xmat[gid].reshape(3, 3)[:, 2]
        a = d.geom_xpos[gid] - axis * m.geom_size[gid, 1]
        b = d.geom_xpos[gid] + axis * m.geom_size[gid, 1]
        dist, _ = point_segment_distance(centre[None], a, b)
        gaps.append(dist[0] - m.geom_size[gid, 0] - radius)
    return min(gaps)


def check_obstacle_in_envelope(env, slot: int, where: str) -> None:
    """The Envelope's promises for one active obstacle, in the current state."""
    u = env.unwrapped
    envelope = u.envelope
    pos, vel, r = u.obstacle_pos[slot].copy(), u.obstacle_vel[slot].copy(), float(u.obstacle_radius[slot])
    kind = u._obstacle_specs[slot].kind
    label = f"{where}, slot {slot} ({kind})"
    lo_r, hi_r = envelope.radius_range
    assert lo_r <= r <= hi_r, label
    # the sphere the physics and the sensors see has that radius
    assert u.model.geom_size[u.obstacle_geom_ids[slot], 0] == r, label
    speed = float(np.linalg.norm(vel))
    if kind == "static":
        assert speed == 0.0, label
    else:
        lo_s, hi_s = envelope.speed_range
        assert lo_s - 1e-12 <= speed <= hi_s + 1e-12, label
    assert envelope.contains(pos), label
    # spawn clearance: MuJoCo's exact signed distances to every arm geom (base, links, tool) ...
    assert u.distances[slot].min() >= envelope.spawn_clearance - 1e-9, label
    # ... and an independent sphere-capsule computation for the capsule geoms
    assert capsule_clearance(env, pos, r) >= envelope.spawn_clearance - 1e-9, label
    # the straight path over the horizon: out of the keep-out cylinder inflated by r, above the floor
    points = path_points(pos, vel, envelope.horizon)
    assert keep_out_gap(points, envelope).min() >= r - 1e-9, label
    assert (points[:, 2] - r).min() >= envelope.min_height - 1e-9, label


def start_and_goal(env) -> tuple[np.ndarray, np.ndarray]:
    """Tool position and goal right after reset (the arm has not moved yet)."""
    u = env.unwrapped
    return u.data.site_xpos[u.ee_site_id].copy(), u.goal.copy()


# ----------------------------------------------------------------------------- envelope at reset


@pytest.mark.parametrize("scenario", list(SCENARIOS))
def test_every_spawn_at_reset_respects_the_envelope(make_env, scenario):
    env = make_env(scenario=scenario)
    u = env.unwrapped
    seen_kinds = set()
    for seed in SEEDS:
        env.reset(seed=seed)
        active = np.flatnonzero(u.obstacle_active)
        kinds = [u._obstacle_specs[s].kind for s in active]
        if scenario in EXPECTED_COUNT:
            assert len(active) == EXPECTED_COUNT[scenario], f"seed {seed}"
            assert kinds == EXPECTED_KINDS[scenario], f"seed {seed}"
        else:  # the mixture: one of the four paper scenarios
            assert kinds in [EXPECTED_KINDS[n] for n in ("static", "head_on", "crossing", "multi")], seed
        seen_kinds.add(tuple(kinds))
        # active slots come first; unused slots are parked beyond the sensor cutoff
        assert list(active) == list(range(len(active)))
        for slot in range(len(active), u.obstacle_active.size):
            assert np.all(u.distances[slot] == 3.0)
        for slot in active:
            check_obstacle_in_envelope(env, slot, f"{scenario} seed {seed}")
    if scenario == "random":
        assert len(seen_kinds) == 4, "the mixture should draw all four scenarios over 60 seeds"


def test_envelope_ranges_are_plumbed_from_the_constructor(make_env):
    env = make_env(scenario="multi", obstacle_speed_range=(0.3, 0.3), obstacle_radius_range=(0.05, 0.05))
    u = env.unwrapped
    for seed in range(10):
        env.reset(seed=seed)
        for slot in np.flatnonzero(u.obstacle_active):
            assert u.obstacle_radius[slot] == 0.05
            speed = np.linalg.norm(u.obstacle_vel[slot])
            assert speed == 0.0 if u._obstacle_specs[slot].kind == "static" else speed == pytest.approx(0.3)


# ----------------------------------------------------------------------------- motion by kind


def test_obstacles_move_as_their_kind_says(make_env):
    counted = {"static": 0, "head_on": 0, "crossing": 0}
    for scenario in ("static", "head_on", "crossing", "multi"):
        env = make_env(scenario=scenario)
        u = env.unwrapped
        for seed in SEEDS:
            env.reset(seed=seed)
            start, goal = start_and_goal(env)
            direction = (goal - start) / np.linalg.norm(goal - start)
            for slot in np.flatnonzero(u.obstacle_active):
                spec = u._obstacle_specs[slot]
                pos, vel = u.obstacle_pos[slot].copy(), u.obstacle_vel[slot].copy()
                label = f"{scenario} seed {seed} slot {slot}"
                points = path_points(pos, vel, u.envelope.horizon)
                gap, _ = point_segment_distance(points, start, goal)
                nearest = int(np.argmin(gap))
                # every kind meets the middle part of the start-goal path (static ones sit on it),
                # up to the lateral jitter (sigma 2 cm per axis)
                f_lo, f_hi = spec.path_fraction
                middle, _ = point_segment_distance(
                    points, start + f_lo * (goal - start), start + f_hi * (goal - start)
                )
                assert middle.min() < 0.1, label
                counted[spec.kind] += 1
                if spec.kind == "static":
                    assert not vel.any(), label
                    continue
                speed = np.linalg.norm(vel)
                cos_angle = float(vel @ direction) / speed
                if spec.kind == "head_on":
                    # straight down the path, from beyond the goal towards the tool's start
                    assert cos_angle == pytest.approx(-1.0, abs=1e-9), label
                    assert float((pos - start) @ vel) < 0, f"{label}: radial velocity to the start must be < 0"
                    assert np.linalg.norm(pos - start) > np.linalg.norm(goal - start) * spec.path_fraction[0]
                else:
                    # across the path at 50-90 deg, meeting it in the middle part of the segment,
                    # some time after spawning and within the horizon
                    angle = math.degrees(math.acos(np.clip(cos_angle, -1.0, 1.0)))
                    assert 50.0 - 1e-6 <= angle <= 90.0 + 1e-6, label
                    meet = nearest / (len(points) - 1) * u.envelope.horizon
                    assert 0.3 < meet < 3.0, f"{label}: meets the path at t={meet:.2f}s"
                    # it does cross: its distance to the path line first shrinks, then grows
                    assert gap[0] > gap[nearest] + 0.03 and gap[-1] > gap[nearest] + 0.03, label
    assert min(counted.values()) >= 60


# ----------------------------------------------------------------------------- motion over time


def test_constant_velocity_until_respawn_and_respawns_keep_the_envelope(make_env):
    respawns = 0
    # (env kwargs, action amplitude, seeds): the paper scenarios under random torques, and fast
    # obstacles (outside the default envelope) that leave the workspace several times an episode
    configs = [({"scenario": name}, 0.3, range(3)) for name in ("head_on", "crossing", "multi", "random")]
    configs.append(({"scenario": "multi", "obstacle_speed_range": (0.6, 1.0)}, 0.05, range(4)))
    for config, amplitude, seeds in configs:
        env = make_env(**config)
        scenario = config["scenario"]
        u = env.unwrapped
        low, high = (np.asarray(c) for c in u.envelope.workspace)
        for seed in seeds:
            env.reset(seed=seed)
            rng = np.random.default_rng(seed)
            truncated = False
            while not truncated:
                pos, vel = u.obstacle_pos.copy(), u.obstacle_vel.copy()
                active = u.obstacle_active.copy()
                radius = u.obstacle_radius.copy()
                action = rng.uniform(-amplitude, amplitude, 6).astype(np.float32)
                _, _, _, truncated, _ = env.step(action)
                for slot in np.flatnonzero(active):
                    predicted = pos[slot] + vel[slot] * u.dt
                    left = bool(np.any(predicted < low) or np.any(predicted > high))
                    label = f"{scenario} seed {seed} t={u.data.time:.2f} slot {slot}"
                    if not left:
                        assert u.obstacle_active[slot], label
                        np.testing.assert_allclose(u.obstacle_pos[slot], predicted, rtol=0, atol=1e-12, err_msg=label)
                        np.testing.assert_array_equal(u.obstacle_vel[slot], vel[slot], err_msg=label)
                        assert u.obstacle_radius[slot] == radius[slot], label
                    elif u.obstacle_active[slot]:  # left the workspace: redrawn inside the envelope
                        respawns += 1
                        check_obstacle_in_envelope(env, slot, f"respawn {label}")
                    else:  # or retired to its parking spot
                        assert not u.obstacle_vel[slot].any() and u.distances[slot].min() >= 3.0, label
                # never-used slots stay parked
                assert not u.obstacle_active[~active].any()
    assert respawns >= 10, f"only {respawns} respawns seen: the respawn check was not exercised"


# ----------------------------------------------------------------------------- scenarios.py units


@settings(max_examples=300, deadline=None)
@given(
    start=st.tuples(st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(-0.1, 1.2)),
    velocity=st.tuples(st.floats(-0.4, 0.4), st.floats(-0.4, 0.4), st.floats(-0.4, 0.4)),
    radius=st.floats(0.01, 0.1),
)
def test_path_ok_implies_path_clear(start, velocity, radius):
    """Whatever ``path_ok`` accepts really stays out of the inflated keep-out and above the floor."""
    envelope = Envelope()
    start, velocity = np.array(start), np.array(velocity)
    if envelope.path_ok(start, velocity, radius):
        points = path_points(start, velocity, envelope.horizon)
        assert keep_out_gap(points, envelope).min() >= radius - 1e-9
        assert (points[:, 2] - radius).min() >= envelope.min_height - 1e-9


def test_path_ok_known_cases():
    envelope = Envelope()
    r = 0.05
    # straight through the base, low: rejected; the same path high above the keep-out: accepted
    assert not envelope.path_ok(np.array([0.8, 0.0, 0.3]), np.array([-0.3, 0.0, 0.0]), r)
    assert envelope.path_ok(np.array([0.8, 0.0, 0.6]), np.array([-0.3, 0.0, 0.0]), r)
    # far from the base and moving away from it: accepted
    assert envelope.path_ok(np.array([0.6, 0.0, 0.3]), np.array([0.1, 0.0, 0.0]), r)
    # dipping through the floor within the horizon: rejected
    assert not envelope.path_ok(np.array([0.6, 0.0, 0.3]), np.array([0.0, 0.0, -0.1]), r)
    # a static sphere touching the inflated keep-out: rejected
    assert not envelope.path_ok(np.array([0.34, 0.0, 0.3]), np.zeros(3), r)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"speed_range": (-0.1, 0.2)}, "speed_range"),
        ({"speed_range": (0.4, 0.1)}, "low <= high"),
        ({"radius_range": (0.0, 0.1)}, "radius_range"),
        ({"radius_range": (-0.1, 0.1)}, "radius_range"),
        ({"radius_range": (0.1, 0.05)}, "low <= high"),
        ({"spawn_clearance": -0.1}, "spawn_clearance"),
        ({"horizon": float("nan")}, "horizon"),
        ({"workspace": ((0, 0, 0), (1, 1, 0))}, "workspace"),
    ],
)
def test_envelope_validation(kwargs, message):
    with pytest.raises(ValueError, match=message):
        Envelope(**kwargs)


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: Envelope(speed_range=(0.1, 0.2, 0.3)), r"speed_range must be \(low, high\).*got \(0.1, 0.2, 0.3\)"),
        (lambda: Envelope(radius_range=0.05), r"radius_range must be \(low, high\).*both > 0 \[m\], got 0.05"),
        (lambda: Envelope(spawn_clearance="0.2"), r"spawn_clearance must be a finite number >= 0 \[m\], got '0.2'"),
        (lambda: Envelope(horizon=True), r"horizon must be a finite number >= 0 \[s\], got True"),
        (lambda: Envelope(workspace="big"), r"workspace must be \(\(xlo, ylo, zlo\), \(xhi, yhi, zhi\)\)"),
        (lambda: ObstacleSpec("static", path_fraction=(0.1, 0.2, 0.3)), r"path_fraction must be \(low, high\)"),
        (lambda: ObstacleSpec("head_on", meet_time=(1.0,)), r"meet_time must be \(low, high\).*both > 0 \[s\]"),
        (lambda: ObstacleSpec("crossing", crossing_angle="60"), r"crossing_angle must be \(low, high\).*got '60'"),
        (lambda: ObstacleSpec("static", lateral_jitter=-0.01), r"lateral_jitter must be a finite number >= 0 \[m\]"),
        (lambda: ObstacleSpec("static", lateral_jitter="0.02"), r"lateral_jitter must be a finite number"),
        (lambda: ObstacleSpec(3), r"unknown obstacle kind 3; valid choices: 'static', 'head_on', 'crossing'"),
        # a static obstacle at the tool's start sits inside the arm, whatever the envelope
        (lambda: ObstacleSpec("static", path_fraction=(0, 0)), r"path_fraction.*high > 0.*got \(0, 0\)"),
    ],
)
def test_envelope_and_spec_fields_name_field_value_and_form(make, message):
    with pytest.raises(ValueError, match=message):
        make()


def test_numpy_numbers_are_numbers_in_envelope_and_spec():
    envelope = Envelope(speed_range=(np.float32(0.1), np.int64(1)), spawn_clearance=np.float32(0.1))
    assert envelope.speed_range == (float(np.float32(0.1)), 1.0) and type(envelope.spawn_clearance) is float
    spec = ObstacleSpec("crossing", path_fraction=np.array([0.3, 0.6]), lateral_jitter=np.float32(0.01))
    assert spec.path_fraction == (0.3, 0.6) and type(spec.lateral_jitter) is float
    assert spec == ObstacleSpec("crossing", path_fraction=(0.3, 0.6), lateral_jitter=float(np.float32(0.01)))
    hash(spec)


@pytest.mark.parametrize(
    "make, message",
    [
        # obstacles and a mixture: the obstacles used to be ignored without a word
        (
            lambda: Scenario("both", (ObstacleSpec("static"),), mixture=("static", "head_on")),
            r"scenario 'both' has both obstacles and a mixture",
        ),
        (lambda: Scenario("typo", mixture=("static", "head-on")), r"unknown scenario 'head-on'; valid choices: 'static'"),
        (lambda: Scenario("nested", mixture=("static", "random")), r"'random' is itself a mixture"),
        (lambda: Scenario("bad", (ObstacleSpec("static"), "crossing")), r"obstacles must be ObstacleSpec.*'crossing'"),
        (lambda: Scenario("bad", ObstacleSpec("static")), r"obstacles must be ObstacleSpec"),
        (lambda: Scenario("bad", mixture="static"), r"mixture must be a tuple of scenario names"),
        (lambda: Scenario(3), r"name must be a string"),
    ],
)
def test_scenario_is_validated_when_built(make, message):
    with pytest.raises(ValueError, match=message):
        make()


def test_scenario_accepts_lists_and_stores_tuples():
    scenario = Scenario("listed", [ObstacleSpec("static"), ObstacleSpec("crossing")])
    assert scenario.obstacles == (ObstacleSpec("static"), ObstacleSpec("crossing"))
    assert Scenario("mix", mixture=["static", "multi"]).mixture == ("static", "multi")
    hash(scenario)


def test_obstacle_spec_and_scenario_validation():
    with pytest.raises(ValueError, match=r"valid choices: 'static', 'head_on', 'crossing'"):
        ObstacleSpec("orbiting")
    with pytest.raises(ValueError, match="meet_time"):
        ObstacleSpec("head_on", meet_time=(0.0, 1.0))
    with pytest.raises(ValueError, match="path_fraction"):
        ObstacleSpec("static", path_fraction=(0.7, 0.3))
    with pytest.raises(ValueError) as excinfo:
        get_scenario("crosing")
    assert all(repr(name) in str(excinfo.value) for name in SCENARIOS)


def test_mixture_resolves_to_its_components_uniformly():
    rng = np.random.default_rng(0)
    mixture = SCENARIOS["random"]
    draws = [mixture.resolve(rng).name for _ in range(4000)]
    assert set(draws) == set(mixture.mixture)
    for name in mixture.mixture:
        assert abs(draws.count(name) / len(draws) - 1 / len(mixture.mixture)) < 0.03
    plain = SCENARIOS["multi"]
    assert plain.resolve(rng) is plain
    weighted = [SCENARIOS["random_multi"].resolve(rng).name for _ in range(4000)]  # a name repeated weighs more
    assert abs(weighted.count("multi") / len(weighted) - 0.5) < 0.03
    assert all(abs(weighted.count(name) / len(weighted) - 1 / 6) < 0.03 for name in ("static", "head_on", "crossing"))


def test_sampler_gives_up_when_nothing_fits():
    everywhere = ArmCapsules(np.zeros((1, 3)), np.zeros((1, 3)), np.array([50.0]))  # a ball around every candidate
    sampler = ObstacleSampler(Envelope(), max_attempts=20)
    rng = np.random.default_rng(0)
    assert sampler.sample(ObstacleSpec("static"), np.array([0.4, 0, 0.4]), np.array([0.5, 0.2, 0.3]), rng,
                          everywhere) is None


def test_sampler_is_driven_only_by_its_generator():
    sampler = ObstacleSampler(Envelope())
    start, goal = np.array([0.45, 0.1, 0.45]), np.array([0.5, -0.3, 0.25])
    spec = ObstacleSpec("crossing")
    a = sampler.sample(spec, start, goal, np.random.default_rng(42), ArmCapsules.none())
    b = sampler.sample(spec, start, goal, np.random.default_rng(42), ArmCapsules.none())
    c = sampler.sample(spec, start, goal, np.random.default_rng(43), ArmCapsules.none())
    assert np.array_equal(a.position, b.position) and np.array_equal(a.velocity, b.velocity) and a.radius == b.radius
    assert not np.array_equal(a.position, c.position)


def test_custom_scenario_in_the_env(make_env):
    scenario = Scenario("two_crossings", (ObstacleSpec("crossing", crossing_angle=(89.0, 90.0)),) * 2)
    env = make_env(scenario=scenario)
    u = env.unwrapped
    env.reset(seed=0)
    start, goal = start_and_goal(env)
    direction = (goal - start) / np.linalg.norm(goal - start)
    assert u.obstacle_active.sum() == 2
    for slot in range(2):
        cos_angle = u.obstacle_vel[slot] @ direction / np.linalg.norm(u.obstacle_vel[slot])
        assert abs(cos_angle) < math.sin(math.radians(1.0)) + 1e-9


def test_env_names_the_mixture_component_of_each_episode(make_env):
    env = make_env(scenario="random")
    u = env.unwrapped
    assert u.episode_scenario is SCENARIOS["random"]  # before the first reset
    counts = {"static": 1, "head_on": 1, "crossing": 1, "multi": 4}
    seen = set()
    for seed in range(30):
        env.reset(seed=seed)
        name = u.episode_scenario.name
        seen.add(name)
        assert u.obstacle_active.sum() == counts[name]  # the obstacles placed are that component's
    assert seen == set(SCENARIOS["random"].mixture)


def test_compiled_sampler_gives_the_numpy_loops_samples_bit_for_bit():
    """Every kind, random paths (some too short for a static obstacle to clear the arm), an arm of
    capsules near the path's start: the compiled attempts draw and accept exactly what the numpy
    loop they replaced did (``reference.sample_obstacle``, its norms summed in order on every CPU),
    and leave the generator in the same state; so seeded episodes stay what they were."""
    envelope = Envelope()
    sampler = ObstacleSampler(envelope)
    cases = np.random.default_rng(5)
    accepted = rejected = 0
    for case in range(300):
        spec = ObstacleSpec(("static", "head_on", "crossing")[case % 3], lateral_jitter=0.02 * (case % 2))
        start = np.array([0.45, 0.0, 0.45]) + cases.uniform(-0.1, 0.1, 3)
        goal = start + cases.uniform(-0.5, 0.5, 3) * (case % 5 != 0)  # every fifth: a path of length 0
        a = start + cases.uniform(-0.1, 0.1, (4, 3))
        arm = ArmCapsules(a, a + cases.uniform(-0.3, 0.3, (4, 3)), cases.uniform(0.03, 0.06, 4))
        ours, theirs = np.random.default_rng(case), np.random.default_rng(case)
        got = sampler.sample(spec, start, goal, ours, arm)
        want = reference.sample_obstacle(envelope, spec, start, goal, theirs, arm.a, arm.b, arm.radius)
        assert (got is None) == (want is None)
        if got is not None:
            assert np.array_equal(got.position, want[0]) and np.array_equal(got.velocity, want[1])
            assert got.radius == want[2]
        assert ours.bit_generator.state == theirs.bit_generator.state
        accepted += got is not None
        rejected += got is None
    assert accepted > 100 and rejected > 10


def test_sampler_and_arm_capsules_refuse_bad_input():
    sampler = ObstacleSampler(Envelope())
    start, goal, rng = np.zeros(3) + 0.4, np.array([0.5, 0.2, 0.3]), np.random.default_rng(0)
    with pytest.raises(ValueError, match=r"a and b of shape \(G, 3\) and radius of shape \(G,\)"):
        ArmCapsules(np.zeros((2, 3)), np.zeros((2, 2)), np.ones(2))
    with pytest.raises(ValueError, match="all finite"):
        ArmCapsules(np.full((1, 3), np.nan), np.zeros((1, 3)), np.ones(1))
    with pytest.raises(ValueError, match="radius must be >= 0"):
        ArmCapsules(np.zeros((1, 3)), np.zeros((1, 3)), -np.ones(1))
    with pytest.raises(TypeError, match="needs an ObstacleSpec and ArmCapsules"):
        sampler.sample(ObstacleSpec("static"), start, goal, rng, (np.zeros((0, 3)),) * 2 + (np.zeros(0),))
    with pytest.raises(ValueError, match=r"start and goal must be finite points of shape \(3,\)"):
        sampler.sample(ObstacleSpec("static"), start[:2], goal, rng, ArmCapsules.none())
    assert ArmCapsules([[0.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]], [0.1]).clearance([1.0, 0.0, 0.5], 0.2) == pytest.approx(0.7)
