"""The DAQP solver with priority levels (c3bf_gym/safety/priority_qp.py, FilterConfig(solver="daqp")):
against proxsuite on random feasible problems, by priority on infeasible ones, and in closed loop
the joint-speed bound that the weighted relaxation lets go (the safety-core issue's defect 3)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from c3bf_gym import SafetyFilter
from c3bf_gym.qp import TorqueQP
from c3bf_gym.safety.priority_qp import PriorityQP

pytest.importorskip("daqp")


def _problem(rng, n, m):
    """A random box-scaled problem around a nominal torque outside the feasible set."""
    A = rng.normal(size=(m, n))
    x0 = rng.uniform(-0.5, 0.5, n)  # a strictly feasible point inside the box
    b = A @ x0 - rng.uniform(0.0, 0.3, m)
    tau_nom = rng.uniform(-2.0, 2.0, n)
    return tau_nom, A, b


@pytest.mark.parametrize("seed", range(20))
def test_feasible_problems_match_proxsuite(seed):
    rng = np.random.default_rng(seed)
    n, m = 6, int(rng.integers(1, 30))
    tau_nom, A, b = _problem(rng, n, m)
    scale = rng.uniform(0.5, 3.0, n)
    lo, hi = -np.ones(n), np.ones(n)
    daqp = PriorityQP(n, lo, hi).solve_scaled(tau_nom, A, b, scale)
    oracle = TorqueQP(n, m, lo, hi, solver="proxsuite", eps_abs=1e-10).solve_scaled(tau_nom, A, b, scale)
    assert daqp.feasible and daqp.status == "solved" and oracle.feasible
    np.testing.assert_allclose(daqp.tau, oracle.tau, atol=1e-6)


def test_conflicting_rows_give_way_by_priority():
    """Level 1 holds whenever the box allows it; only level 2 gives way."""
    lo, hi = -np.ones(2), np.ones(2)
    qp = PriorityQP(2, lo, hi)
    A = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0]])
    b = np.array([0.5, 0.5, -2.0])  # u0 >= 0.5 (level 1) against u0 <= -0.5 (level 2); the third holds
    result = qp.solve_scaled(np.array([-2.0, 0.3]), A, b, np.ones(2), levels=np.array([1, 2, 1]))
    assert not result.feasible and result.status == "relaxed"
    assert result.tau[0] == pytest.approx(0.5, abs=1e-9) and result.tau[1] == pytest.approx(0.3, abs=1e-9)
    assert result.slack == pytest.approx(1.0, abs=1e-9)  # the level-2 row, violated by 1
    swapped = qp.solve_scaled(np.array([-2.0, 0.3]), A, b, np.ones(2), levels=np.array([2, 1, 1]))
    assert swapped.tau[0] == pytest.approx(-0.5, abs=1e-9)
    # a level-1 row beyond the box's reach is met as nearly as the box allows
    beyond = qp.solve_scaled(np.zeros(2), A[:1], np.array([1.5]), np.ones(2), levels=np.array([1]))
    assert beyond.tau[0] == pytest.approx(1.0) and beyond.slack == pytest.approx(0.5)


def test_rows_no_torque_can_change():
    """A zero row with b > 0 never holds: left out of the solve, its violation in the slack; with
    b <= 0 it holds and changes nothing."""
    qp = PriorityQP(2, -np.ones(2), np.ones(2))
    A = np.array([[0.0, 0.0], [1.0, 0.0]])
    result = qp.solve_scaled(np.zeros(2), A, np.array([0.25, 0.5]), np.ones(2), levels=np.array([2, 1]))
    assert not result.feasible and result.slack == pytest.approx(0.25) and result.tau[0] == pytest.approx(0.5)
    held = qp.solve_scaled(np.zeros(2), A, np.array([-1.0, 0.5]), np.ones(2))
    assert held.feasible and held.slack == 0.0
    with pytest.raises(ValueError, match="NaN or inf"):
        qp.solve_scaled(np.array([np.nan, 0.0]), A, np.zeros(2), np.ones(2))


def _max_joint_speed(solver: str, episodes: int = 3) -> tuple[float, float]:
    env = SafetyFilter(gym.make("C3BFReach-v0", scenario="multi"), solver=solver)
    fastest, collision_steps = 0.0, 0.0
    for episode in range(episodes):
        env.reset(seed=episode)
        rng = np.random.default_rng(episode)
        for _ in range(250):
            *_, info = env.step(rng.choice([-1.0, 1.0], size=6).astype(np.float32))
            fastest = max(fastest, float(np.abs(env.unwrapped.data.qvel).max()))
            collision_steps += info["cost"]
    bound = env.hook.joint_limits.qd_max.max()
    env.close()
    return fastest / bound, collision_steps


def test_daqp_holds_the_joint_speed_bound_under_chattering_torques():
    """Chattering ±1 torques in multi: the weighted relaxation lets the joint speeds run past
    their bound; by priority the bound holds (it is feasible on every step with the box), to
    within one physics step's discretisation."""
    ratio, collisions = _max_joint_speed("daqp")
    assert ratio <= 1.001 and collisions == 0
    weighted, _ = _max_joint_speed("active_set")
    assert weighted > 1.2  # the defect the priorities fix, on the same episodes
