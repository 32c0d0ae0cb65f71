"""The filter's QP (c3bf_gym/safety/priority_qp.py and _qp.py, DAQP through _daqp.py): against
proxsuite (the independent oracle) on random feasible problems, by priority on infeasible ones, and in closed
loop the joint-speed bound that the former weighted relaxation let go (the safety-core issue's
defect 3)."""

from __future__ import annotations

import pickle

import gymnasium as gym
import numpy as np
import pytest

from c3bf_gym import SafetyFilter
from c3bf_gym.safety import _step
from c3bf_gym.safety._qp import RELAXED
from c3bf_gym.safety.controller import ROW_KINDS
from c3bf_gym.safety.priority_qp import PriorityQP

proxqp = pytest.importorskip("proxsuite").proxqp


def _oracle(tau_nom, A, b, scale, lo, hi, H=None) -> tuple[np.ndarray, bool]:
    """proxsuite's solution of min ½ (u − u_nom)ᵀ H (u − u_nom) (``u_nom = τ_nom/s``; ``H`` None: the
    identity), (A s) u ≥ b, lo ≤ u ≤ hi, and whether it reached the requested accuracy (it does
    not on an infeasible problem)."""
    n = len(tau_nom)
    H = np.eye(n) if H is None else H
    rows = A * scale
    result = proxqp.dense.solve(H, -H @ (tau_nom / scale), None, None, np.vstack([rows, np.eye(n)]),
                                np.concatenate([b, lo]), np.concatenate([np.full(len(b), 1e20), hi]),
                                eps_abs=1e-10, eps_rel=0.0, max_iter=10_000)  # fmt: skip
    return result.x, result.info.status == proxqp.PROXQP_SOLVED


def _problem(rng, n, m):
    """A random problem whose rows hold strictly somewhere inside the box, around a nominal
    torque outside the feasible set."""
    A = rng.normal(size=(m, n))
    x0 = rng.uniform(-0.5, 0.5, n)
    b = A @ x0 - rng.uniform(0.0, 0.3, m)
    return rng.uniform(-2.0, 2.0, n), A, b


@pytest.mark.parametrize("seed", range(30))
def test_feasible_problems_match_proxsuite(seed):
    rng = np.random.default_rng(seed)
    n, m = int(rng.integers(2, 8)), int(rng.integers(1, 40))
    scale = rng.uniform(0.5, 3.0, n)
    tau_nom, A, b = _problem(rng, n, m)
    A = A / scale  # so the scaled rows are the feasible ones
    lo, hi = -np.ones(n), np.ones(n)
    qp = PriorityQP(n, lo, hi, m, 0)
    result = qp.solve_scaled(tau_nom, A, b, scale, n_obstacle_rows=0)
    oracle, converged = _oracle(tau_nom, A, b, scale, lo, hi)
    assert converged and result.feasible and result.status == "solved" and result.slack == 0.0
    np.testing.assert_allclose(result.tau, oracle, atol=1e-6)
    assert np.all(result.tau >= lo) and np.all(result.tau <= hi)


def test_a_metric_matches_proxsuite_and_a_fresh_workspace():
    """The cost ``½ (u − u_nom)ᵀ (I + KᵀK) (u − u_nom)`` (the filter's tool metric): one warm
    workspace through problems whose metric changes at every solve gives proxsuite's answer in
    that metric, and a fresh workspace's, and not the identity metric's."""
    rng = np.random.default_rng(11)
    n, capacity = 6, 25
    lo, hi = -np.ones(n), np.ones(n)
    warm = PriorityQP(n, lo, hi, capacity, 0, metric_rows=3)
    moved = 0
    for _ in range(30):
        m = int(rng.integers(1, capacity + 1))
        scale = rng.uniform(0.5, 3.0, n)
        tau_nom, A, b = _problem(rng, n, m)
        A = A / scale
        W = rng.normal(size=(3, n)) * rng.uniform(0.1, 3.0)
        H = np.eye(n) + W.T @ W
        got = warm.solve_scaled(tau_nom, A, b, scale, n_obstacle_rows=0, metric=W)
        assert got.feasible and got.status == "solved"
        oracle, converged = _oracle(tau_nom, A, b, scale, lo, hi, H)
        assert converged
        np.testing.assert_allclose(got.tau, oracle, atol=1e-6)
        fresh = PriorityQP(n, lo, hi, capacity, 0, metric_rows=3).solve_scaled(tau_nom, A, b, scale, 0, metric=W)
        np.testing.assert_allclose(got.tau, fresh.tau, atol=1e-9)
        plain = PriorityQP(n, lo, hi, capacity, 0).solve_scaled(tau_nom, A, b, scale, 0).tau
        moved += np.linalg.norm(plain - oracle) > 1e-3
    assert moved > 20  # the metric changes the answer: it is in use


def test_a_metric_keeps_the_rows_priorities():
    """Conflicting rows with a metric: the prioritised solve still holds level 1 wherever the box
    allows, gives what ``daqp.solve`` (DAQP's documented Python interface) gives on the same
    levels in that metric, and a warm workspace gives a fresh one's answers."""
    daqp = pytest.importorskip("daqp")
    rng = np.random.default_rng(5)
    n, checked = 6, 0
    warm = PriorityQP(n, -np.ones(n), np.ones(n), 10, 10, metric_rows=3)
    for _ in range(40):
        m1, m2 = int(rng.integers(1, 10)), int(rng.integers(1, 10))
        _, A1, b1 = _problem(rng, n, m1)
        A2 = rng.normal(size=(m2, n))
        b2 = rng.uniform(0.5, 3.0, m2) * np.linalg.norm(A2, axis=1)  # far beyond: conflicts
        tau_nom, W = rng.uniform(-2.0, 2.0, n), rng.normal(size=(3, n))
        A, b = np.vstack([A2, A1]), np.concatenate([b2, b1])
        result = warm.solve_scaled(tau_nom, A, b, np.ones(n), n_obstacle_rows=m2, metric=W)
        fresh = PriorityQP(n, -np.ones(n), np.ones(n), 10, 10, metric_rows=3).solve_scaled(
            tau_nom, A, b, np.ones(n), n_obstacle_rows=m2, metric=W)
        np.testing.assert_allclose(result.tau, fresh.tau, atol=1e-9)
        if result.feasible:
            continue
        checked += 1
        assert ((A1 @ result.tau - b1) / np.linalg.norm(A1, axis=1)).min() >= -1e-6
        assert np.all(np.abs(result.tau) <= 1.0)
        H = np.eye(n) + W.T @ W
        norm1, norm2 = np.linalg.norm(A1, axis=1), np.linalg.norm(A2, axis=1)
        rows = np.vstack([A1 / norm1[:, None], A2 / norm2[:, None]])  # level 1, then the barrier's
        x, _, flag, _ = daqp.solve(H, -H @ tau_nom, rows, np.concatenate([np.ones(n), np.full(m1 + m2, 1e30)]),
                                   np.concatenate([-np.ones(n), b1 / norm1, b2 / norm2]), np.zeros(n + m1 + m2, np.intc),
                                   break_points=np.array([n, n + m1, n + m1 + m2], np.intc))  # fmt: skip
        assert flag >= 1
        np.testing.assert_allclose(result.tau, x, atol=1e-6)
    assert checked > 10


@pytest.mark.parametrize(("rows", "metric", "message"), [
    (3, None, "metric_rows=3: pass metric"),
    (0, np.zeros((3, 2)), "metric_rows=0: pass metric"),
    (3, np.zeros((2, 2)), r"shape \(3, 2\)"),
    (3, np.full((3, 2), np.nan), "finite"),
    (-1, None, "metric_rows must be an integer >= 0"),
    (2.5, None, "metric_rows must be an integer >= 0"),
])
def test_a_bad_metric_is_refused(rows, metric, message):
    with pytest.raises(ValueError, match=message):
        PriorityQP(2, -np.ones(2), np.ones(2), 2, 0, metric_rows=rows).solve_scaled(
            np.zeros(2), np.eye(2), np.zeros(2), np.ones(2), metric=metric)


def test_a_pickled_qp_keeps_its_metric_rows():
    qp = pickle.loads(pickle.dumps(PriorityQP(2, -np.ones(2), np.ones(2), 2, 0, metric_rows=3)))
    assert qp.metric_rows == 3 and qp.buffers.metric.shape == (3, 2)


def test_warm_start_does_not_change_the_answer():
    """Consecutive solves start from the previous working set: each answer equals a fresh
    workspace's, through row counts that grow and shrink."""
    rng = np.random.default_rng(7)
    n, capacity = 6, 30
    warm = PriorityQP(n, -np.ones(n), np.ones(n), capacity, 0)
    for _ in range(40):
        m = int(rng.integers(0, capacity + 1))
        tau_nom, A, b = _problem(rng, n, m)
        scale = np.ones(n)
        got = warm.solve_scaled(tau_nom, A, b, scale, n_obstacle_rows=0).tau.copy()
        fresh = PriorityQP(n, -np.ones(n), np.ones(n), capacity, 0).solve_scaled(tau_nom, A, b, scale, 0).tau
        np.testing.assert_allclose(got, fresh, atol=1e-9)


def test_runs_of_calls_with_no_safe_torque_give_a_fresh_workspaces_answers():
    """Calls with no safe torque come in runs; after one, the prioritised solve goes first and the
    warm starts of both solves carry on. Through runs of infeasible and feasible problems of two
    levels, every status and answer equals a fresh workspace's."""
    rng = np.random.default_rng(11)
    n, m1, m2 = 6, 8, 8
    warm = PriorityQP(n, -np.ones(n), np.ones(n), m1, m2)
    statuses = []
    for run in range(12):
        infeasible = run % 2 == 0
        for _ in range(int(rng.integers(1, 6))):
            tau_nom, A, b = _problem(rng, n, m2 + m1)  # rows 0 … m2-1: level 2
            if infeasible:
                b[:3] = rng.uniform(1.5, 3.0, 3) * np.linalg.norm(A[:3], axis=1)  # beyond the box
            got = warm.solve_scaled(tau_nom, A, b, np.ones(n), n_obstacle_rows=m2)
            fresh = PriorityQP(n, -np.ones(n), np.ones(n), m1, m2).solve_scaled(tau_nom, A, b, np.ones(n), m2)
            assert got.status == fresh.status
            np.testing.assert_allclose(got.tau, fresh.tau, atol=1e-7)
            assert got.slack == pytest.approx(fresh.slack, abs=1e-7)
            statuses.append(got.status)
    assert statuses.count("relaxed") > 10 and statuses.count("solved") > 10


def test_prioritised_solves_through_level_sizes_that_change_give_a_fresh_workspaces_answers():
    """The prioritised problem is sized to the rows in use at every solve, level by level: through
    warm-started runs whose level sizes grow, shrink and empty out (a level's placeholder zero row),
    every status, answer and slack equals a fresh workspace's, and the rows of priority 1 hold."""
    rng = np.random.default_rng(5)
    n, cap1, cap2 = 6, 12, 10
    warm = PriorityQP(n, -np.ones(n), np.ones(n), cap1, cap2)
    sizes = set()
    for _ in range(60):
        m1, m2 = int(rng.integers(0, cap1 + 1)), int(rng.integers(0, cap2 + 1))
        _, A1, b1 = _problem(rng, n, m1)
        A2 = rng.normal(size=(m2, n))
        b2 = rng.uniform(0.5, 3.0, m2) * np.linalg.norm(A2, axis=1)  # beyond the box: level 2 gives way
        tau_nom = rng.uniform(-2.0, 2.0, n)
        A, b = np.vstack([A2, A1]), np.concatenate([b2, b1])
        got = warm.solve_scaled(tau_nom, A, b, np.ones(n), n_obstacle_rows=m2)
        fresh = PriorityQP(n, -np.ones(n), np.ones(n), cap1, cap2).solve_scaled(tau_nom, A, b, np.ones(n), m2)
        assert got.status == fresh.status
        np.testing.assert_allclose(got.tau, fresh.tau, atol=1e-7)
        assert got.slack == pytest.approx(fresh.slack, abs=1e-7)
        if m1:
            assert ((A1 @ got.tau - b1) / np.linalg.norm(A1, axis=1)).min() >= -1e-6
        sizes.add((m1 > 0, m2 > 0, got.status))
    assert {(True, True, "relaxed"), (False, True, "relaxed"), (True, False, "solved")} <= sizes


def test_conflicting_rows_give_way_by_priority():
    """Rows of priority 1 hold whenever the box allows it; only the barrier's rows give way."""
    lo, hi = -np.ones(2), np.ones(2)
    qp = PriorityQP(2, lo, hi, 2, 1)
    # row 0 is the barrier's (n_obstacle_rows=1): u0 <= -0.5; row 1 (priority 1): u0 >= 0.5
    A = np.array([[-1.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    b = np.array([0.5, 0.5, -2.0])
    result = qp.solve_scaled(np.array([-2.0, 0.3]), A, b, np.ones(2), n_obstacle_rows=1)
    assert not result.feasible and result.status == "relaxed"
    assert result.tau[0] == pytest.approx(0.5, abs=1e-9) and result.tau[1] == pytest.approx(0.3, abs=1e-9)
    assert result.slack == pytest.approx(1.0, abs=1e-9)  # the barrier's row, violated by 1
    # the same rows with the roles swapped (rows 0 and 1 exchanged): the other one gives way
    swapped = qp.solve_scaled(np.array([-2.0, 0.3]), A[[1, 0, 2]], b[[1, 0, 2]], np.ones(2), n_obstacle_rows=1)
    assert swapped.tau[0] == pytest.approx(-0.5, abs=1e-9)
    # a priority-1 row beyond the box's reach is met as nearly as the box allows
    beyond = qp.solve_scaled(np.zeros(2), A[1:2], np.array([1.5]), np.ones(2), n_obstacle_rows=0)
    assert beyond.tau[0] == pytest.approx(1.0) and beyond.slack == pytest.approx(0.5)


def test_stride_marks_every_other_obstacle_row_as_the_barriers():
    """With a guard (stride 2) the obstacle rows alternate barrier, guard: the guard's hold."""
    qp = PriorityQP(1, -np.ones(1), np.ones(1), 1, 1)
    A = np.array([[-1.0], [1.0]])  # barrier: u <= -0.2; guard: u >= 0.2
    b = np.array([0.2, 0.2])
    result = qp.solve_scaled(np.zeros(1), A, b, np.ones(1), n_obstacle_rows=2, stride=2)
    assert result.status == "relaxed" and result.tau[0] == pytest.approx(0.2, abs=1e-9)


def _reserve_problem(guard, barrier):
    """Two joints, one obstacle (barrier row 0, guard row 1: ``u0 >= guard``, ``u0 >= barrier``),
    then the joint limits' 8 rows: joint 0's upper position row ``u0 <= 0.2`` drawn 0.3 inside
    its range (``u0 <= 0.5``); the other rows do not bind."""
    A = np.array([[1.0, 0.0], [1.0, 0.0],
                  [-1.0, 0.0], [0.0, -1.0], [1.0, 0.0], [0.0, 1.0],  # position: upper, lower
                  [-1.0, 0.0], [0.0, -1.0], [1.0, 0.0], [0.0, 1.0]])  # speed: upper, lower
    b = np.array([barrier, guard, -0.2, -1.0, -1.0, -1.0, -1.0, -1.0, -1.0, -1.0])
    return A, b


def test_the_joint_range_reserve_gives_way_after_the_barrier_and_before_the_range():
    """With a reserve the position rows inside the range are a level of their own: the guard takes
    the joint into its reserve (and the report counts that as held), the range itself holds at
    the guard's priority, and the barrier's rows still give way first."""
    qp = PriorityQP(2, -np.ones(2), np.ones(2), 9, 1, reserve=np.full(4, 0.3))
    ones = np.ones(2)
    A, b = _reserve_problem(guard=0.4, barrier=-1.0)  # the guard needs 0.2 of the 0.3 reserve
    into = qp.solve_scaled(np.zeros(2), A, b, ones, n_obstacle_rows=2, stride=2)
    assert into.status == "relaxed" and into.tau[0] == pytest.approx(0.4, abs=1e-9)
    assert into.slack == pytest.approx(0.0, abs=1e-9)  # the reserve was used, no row lost
    assert qp.buffers.residual[2] == pytest.approx(0.0, abs=1e-9)
    A, b = _reserve_problem(guard=0.7, barrier=-1.0)  # beyond the range: the guard and the range share level 1
    beyond = qp.solve_scaled(np.zeros(2), A, b, ones, n_obstacle_rows=2, stride=2)
    assert beyond.tau[0] == pytest.approx(0.6, abs=1e-6)
    assert beyond.slack == pytest.approx(0.1, abs=1e-6)  # guard and range each 0.1 off, the reserve's 0.3 reported
    assert qp.buffers.residual[2] == pytest.approx(-0.1, abs=1e-6)
    A, b = _reserve_problem(guard=-1.0, barrier=0.4)  # the barrier's row against the reserve: the barrier gives way
    first = qp.solve_scaled(np.zeros(2), A, b, ones, n_obstacle_rows=2, stride=2)
    assert first.tau[0] == pytest.approx(0.2, abs=1e-9) and first.slack == pytest.approx(0.2, abs=1e-9)
    # without a reserve the position row is the range itself: the guard gives way with it
    plain = PriorityQP(2, -np.ones(2), np.ones(2), 9, 1).solve_scaled(
        np.zeros(2), *_reserve_problem(guard=0.4, barrier=-1.0), ones, n_obstacle_rows=2, stride=2)
    assert plain.tau[0] == pytest.approx(0.3, abs=1e-6) and plain.slack == pytest.approx(0.1, abs=1e-6)


def test_the_allowance_level_holds_the_barriers_rows_within_their_allowance_first():
    """Two barrier rows in conflict, one with an allowance: the allowance level holds the other
    as written and lets the first give way within its allowance, where one level of least squares
    over both rows violates each by half the conflict."""
    A = np.array([[1.0], [-1.0]])  # u >= 0.5 (no allowance), u <= 0.2 (allowance 0.4: u <= 0.6)
    b = np.array([0.5, -0.2])
    spread = PriorityQP(1, -np.ones(1), np.ones(1), 1, 2).solve_scaled(np.zeros(1), A, b, np.ones(1), 2)
    assert spread.status == "relaxed" and spread.tau[0] == pytest.approx(0.35, abs=1e-9)
    qp = PriorityQP(1, -np.ones(1), np.ones(1), 1, 2, allowance_level=True)
    ranked = qp.solve_scaled(np.zeros(1), A, b, np.ones(1), 2, allowance=np.array([0.0, 0.4]))
    assert ranked.status == "relaxed" and ranked.tau[0] == pytest.approx(0.5, abs=1e-9)
    np.testing.assert_allclose(qp.buffers.residual[:2], [0.0, -0.3], atol=1e-9)  # within its 0.4
    # an allowance too small for the conflict: the loosened rows share it by least squares, and the
    # rows as written come only after them
    short = qp.solve_scaled(np.zeros(1), A, b, np.ones(1), 2, allowance=np.array([0.0, 0.1]))
    assert short.tau[0] == pytest.approx(0.4, abs=1e-9)  # u >= 0.5 and u <= 0.3 split the 0.2
    # with no allowance the level is empty and the answer is the one-level QP's, bit for bit
    none = qp.solve_scaled(np.zeros(1), A, b, np.ones(1), 2)
    assert none.tau[0] == spread.tau[0] and none.slack == spread.slack
    # with nothing in conflict the allowance changes nothing
    free = qp.solve_scaled(np.array([0.3]), A[:1], np.array([0.1]), np.ones(1), 1, allowance=np.array([0.4]))
    assert free.feasible and free.tau[0] == pytest.approx(0.3)


def test_the_allowance_level_comes_after_the_joint_range_reserve():
    """Below the reserve: a barrier row within its allowance does not take a joint into its
    reserve, and the rows give way as without the level; a reserve the barrier does not need
    leaves the barrier's row held within its allowance."""
    qp = PriorityQP(2, -np.ones(2), np.ones(2), 9, 1, reserve=np.full(4, 0.3), allowance_level=True)
    A, b = _reserve_problem(guard=-1.0, barrier=0.4)  # the barrier's row wants 0.2 of the 0.3 reserve
    short = qp.solve_scaled(np.zeros(2), A, b, np.ones(2), n_obstacle_rows=2, stride=2,
                            allowance=np.array([0.1] + [0.0] * 9))
    assert short.tau[0] == pytest.approx(0.2, abs=1e-9)  # loosened to u0 >= 0.3: the reserve holds it at 0.2
    assert short.slack == pytest.approx(0.2, abs=1e-9)  # the barrier's row as written, 0.2 off
    within = qp.solve_scaled(np.zeros(2), A, b, np.ones(2), n_obstacle_rows=2, stride=2,
                             allowance=np.array([0.3] + [0.0] * 9))
    assert within.tau[0] == pytest.approx(0.2, abs=1e-9)  # loosened to u0 >= 0.1: held
    assert qp.buffers.residual[0] == pytest.approx(-0.2, abs=1e-9)  # within its 0.3


def _speed_problem(barrier, guard=-1.0):
    """Two joints, one obstacle (barrier row 0, guard row 1: ``u0 >= barrier``, ``u0 >= guard``),
    then the joint limits' 8 rows: joint 0's upper speed row ``u0 <= 0.2`` binds, the others do
    not."""
    A, b = _reserve_problem(guard=guard, barrier=barrier)
    b[2] = -1.0  # the position row no longer binds
    b[6] = -0.2  # speed upper, joint 0: u0 <= 0.2
    return A, b


def test_the_speed_reserve_gives_way_before_the_barrier_and_its_copy_holds_at_level_1():
    """With a speed reserve the speed rows at the nominal bound are the last level: the barrier's
    row takes the joint past it into the reserve (the report counts that as held), not past the
    filter's bound; the guard too cannot take it beyond the filter's bound, which is level 1;
    without a conflict the nominal bound holds."""
    reserve = np.array([0.1, 0.0, 0.1, 0.0])  # speed rows, upper then lower: joint 0's (joint 1 keeps none)
    qp = PriorityQP(2, -np.ones(2), np.ones(2), 9, 1, speed_reserve=reserve)
    ones = np.ones(2)
    into = qp.solve_scaled(np.zeros(2), *_speed_problem(barrier=0.25), ones, n_obstacle_rows=2, stride=2)
    assert into.status == "relaxed" and into.tau[0] == pytest.approx(0.25, abs=1e-9)
    assert into.slack == pytest.approx(0.0, abs=1e-9)  # within the speed reserve: no row lost
    assert qp.buffers.residual[6] == pytest.approx(0.0, abs=1e-9)
    past = qp.solve_scaled(np.zeros(2), *_speed_problem(barrier=0.4), ones, n_obstacle_rows=2, stride=2)
    assert past.tau[0] == pytest.approx(0.3, abs=1e-9) and past.slack == pytest.approx(0.1, abs=1e-9)
    assert qp.buffers.residual[0] == pytest.approx(-0.1, abs=1e-9)  # the barrier gave way, the filter's bound held
    guard = qp.solve_scaled(np.zeros(2), *_speed_problem(barrier=-1.0, guard=0.4), ones, n_obstacle_rows=2,
                            stride=2)
    assert guard.tau[0] == pytest.approx(0.35, abs=1e-6)  # the guard and the filter's bound share level 1
    free = qp.solve_scaled(np.array([0.5, 0.0]), *_speed_problem(barrier=-1.0), ones, n_obstacle_rows=2, stride=2)
    assert free.feasible and free.tau[0] == pytest.approx(0.2, abs=1e-9)  # the nominal torque keeps the nominal bound
    # without a speed reserve the speed bound is level 1: the barrier gives way at the bound
    plain = PriorityQP(2, -np.ones(2), np.ones(2), 9, 1).solve_scaled(
        np.zeros(2), *_speed_problem(barrier=0.25), ones, n_obstacle_rows=2, stride=2)
    assert plain.tau[0] == pytest.approx(0.2, abs=1e-9) and plain.slack == pytest.approx(0.05, abs=1e-9)


def test_the_speed_reserve_and_the_range_reserve_keep_their_levels_together():
    """Both at once: the position rows' reserve above the barrier, the speed rows' reserve below
    it, in one workspace of five levels (pickled as built)."""
    qp = PriorityQP(2, -np.ones(2), np.ones(2), 9, 1, reserve=np.full(4, 0.3), allowance_level=True,
                    speed_reserve=np.full(4, 0.1))
    assert qp.buffers.capacity.tolist() == [9, 4, 1, 1, 4]
    A, b = _reserve_problem(guard=-1.0, barrier=0.4)  # the barrier's row against the range's reserve
    b[6] = -0.3
    first = qp.solve_scaled(np.zeros(2), A, b, np.ones(2), n_obstacle_rows=2, stride=2)
    assert first.tau[0] == pytest.approx(0.2, abs=1e-9) and first.slack == pytest.approx(0.2, abs=1e-9)
    A, b = _speed_problem(barrier=0.25)
    b[2] = -0.3  # the range's reserve does not bind
    b[6] = -0.2
    into = pickle.loads(pickle.dumps(qp)).solve_scaled(np.zeros(2), A, b, np.ones(2), n_obstacle_rows=2, stride=2)
    assert into.tau[0] == pytest.approx(0.25, abs=1e-9) and into.slack == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("allowance, message", [
    (np.array([-0.1, 0.0]), "allowance must be finite, >= 0"), (np.array([np.nan, 0.0]), "allowance must be finite"),
    (np.zeros(3), r"of shape \(2,\)")])
def test_a_bad_allowance_is_refused(allowance, message):
    qp = PriorityQP(1, -np.ones(1), np.ones(1), 1, 2, allowance_level=True)
    with pytest.raises(ValueError, match=message):
        qp.solve_scaled(np.zeros(1), np.array([[1.0], [-1.0]]), np.array([0.5, -0.2]), np.ones(1), 2,
                        allowance=allowance)
    with pytest.raises(ValueError, match="built without allowance_level"):
        PriorityQP(1, -np.ones(1), np.ones(1), 1, 2).solve_scaled(
            np.zeros(1), np.array([[1.0]]), np.array([0.5]), np.ones(1), 1, allowance=np.zeros(1))
    with pytest.raises(ValueError, match="allowance_level needs barrier rows"):
        PriorityQP(1, -np.ones(1), np.ones(1), 1, 0, allowance_level=True)


@pytest.mark.parametrize("reserve, level1, message", [
    (np.full(3, 0.3), 9, r"reserve must be \(4,\)"), (np.array([0.3, -0.1, 0.3, 0.3]), 9, "finite and >= 0"),
    (np.full(4, np.nan), 9, "finite and >= 0"), (np.full(4, 0.3), 7, "at least 8 priority-1 rows")])
def test_a_bad_reserve_is_refused(reserve, level1, message):
    with pytest.raises(ValueError, match=message):
        PriorityQP(2, -np.ones(2), np.ones(2), level1, 1, reserve=reserve)
    with pytest.raises(ValueError, match=message.replace("reserve", "speed_reserve")):
        PriorityQP(2, -np.ones(2), np.ones(2), level1, 1, speed_reserve=reserve)


def test_random_infeasible_problems_keep_priority_one_where_the_box_allows():
    """Random conflicts: whenever the priority-1 rows can hold within the box (proxsuite finds a
    point), the solution holds them, and the barrier's rows' violation is no more than needed by
    proxsuite's measure: the solution is at least as good as the best point that holds level 1."""
    rng = np.random.default_rng(3)
    n, checked = 6, 0
    for _ in range(60):
        m1, m2 = int(rng.integers(1, 10)), int(rng.integers(1, 10))
        _, A1, b1 = _problem(rng, n, m1)
        A2 = rng.normal(size=(m2, n))
        b2 = rng.uniform(0.5, 3.0, m2) * np.linalg.norm(A2, axis=1)  # far beyond: conflicts
        tau_nom = rng.uniform(-2.0, 2.0, n)
        qp = PriorityQP(n, -np.ones(n), np.ones(n), m1, m2)
        result = qp.solve_scaled(tau_nom, np.vstack([A2, A1]), np.concatenate([b2, b1]), np.ones(n),
                                 n_obstacle_rows=m2)  # fmt: skip
        if result.feasible:
            continue
        checked += 1
        level1 = (A1 @ result.tau - b1) / np.linalg.norm(A1, axis=1)
        assert level1.min() >= -1e-6
        assert np.all(np.abs(result.tau) <= 1.0)
    assert checked > 10


def test_rows_no_torque_can_change():
    """A zero row with b > 0 never holds: left out of the solve, its b in the slack; with b <= 0
    it holds and changes nothing."""
    qp = PriorityQP(2, -np.ones(2), np.ones(2), 1, 1)
    A = np.array([[0.0, 0.0], [1.0, 0.0]])
    result = qp.solve_scaled(np.zeros(2), A, np.array([0.25, 0.5]), np.ones(2), n_obstacle_rows=1)
    assert not result.feasible and result.slack == pytest.approx(0.25) and result.tau[0] == pytest.approx(0.5)
    held = qp.solve_scaled(np.zeros(2), A, np.array([-1.0, 0.5]), np.ones(2), n_obstacle_rows=1)
    assert held.feasible and held.slack == 0.0


@pytest.mark.parametrize("length", [1e-8, 1e-5, 1e-3, 1e-2, 1.0, 1e3])
def test_short_rows_that_torque_can_still_change_are_solved_as_any_other(length):
    """A row far shorter than the others (a point the joints barely move) but above the length
    below which no torque can change it: held where it can be, like its unit-length twin. DAQP
    takes a row whose squared length is below its zero tolerance (1e-11) for a zero row, and a zero
    row that cannot hold for an infeasible problem: handed such a row as it is, the whole QP failed
    and fell back to the nominal torque."""
    qp = PriorityQP(2, -np.ones(2), np.ones(2), 3, 1)
    A = np.array([[length, 0.0], [1.0, 0.0], [0.0, 1.0]])  # u0 >= 0.1 (scaled by its length), u0 >= 0.5
    b = np.array([0.1 * length, 0.5, -2.0])
    result = qp.solve_scaled(np.zeros(2), A, b, np.ones(2), n_obstacle_rows=1)
    assert result.status == "solved" and result.tau[0] == pytest.approx(0.5, abs=1e-9)
    # residuals are the normalised rows', whatever the rows' lengths: u0 - 0.1, u0 - 0.5, u1 + 2
    np.testing.assert_allclose(qp.buffers.residual[:3], [0.4, 0.0, 2.0], atol=1e-9)
    # out of reach by its own length: it gives way, the others hold
    far = qp.solve_scaled(np.zeros(2), A, np.array([2.0 * length, 0.5, -2.0]), np.ones(2), n_obstacle_rows=1)
    assert far.status == "relaxed" and far.tau[0] == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("length", [1e-3, 0.02, 1.0, 1e3])
@pytest.mark.parametrize("need", [1e-5, 5e-4])
def test_a_binding_row_holds_to_the_same_tolerance_whatever_its_length(length, need):
    """A row that binds by a small amount (``u0 ≥ need``, scaled by ``length``) is held, as its
    unit-length twin is: the QP's tolerance is the normalised rows' (``ACTIVE_TOL``) for every
    row. DAQP's own test of a violated row is in the row's units, so a short row handed to it as
    it is would stay violated and the call would come back relaxed."""
    qp = PriorityQP(2, -np.ones(2), np.ones(2), 2, 0)
    A = np.array([[length, 0.0], [0.0, 1.0]])
    result = qp.solve_scaled(np.zeros(2), A, np.array([need * length, -2.0]), np.ones(2))
    assert result.status == "solved" and result.slack == 0.0
    assert result.tau[0] == pytest.approx(need, rel=1e-9)


def test_bad_input_is_refused():
    qp = PriorityQP(2, -np.ones(2), np.ones(2), 2, 0)
    A = np.eye(2)
    with pytest.raises(ValueError, match="NaN or inf"):
        qp.solve_scaled(np.array([np.nan, 0.0]), A, np.zeros(2), np.ones(2))
    with pytest.raises(ValueError, match="NaN or inf"):
        qp.solve_scaled(np.zeros(2), A, np.array([np.inf, 0.0]), np.ones(2))
    with pytest.raises(ValueError, match="exceed"):
        qp.solve_scaled(np.zeros(2), np.eye(3, 2), np.zeros(3), np.ones(2))
    with pytest.raises(ValueError, match="1 barrier rows and 1 others exceed the 0 and 2"):
        qp.solve_scaled(np.zeros(2), A, np.zeros(2), np.ones(2), n_obstacle_rows=1)  # no barrier level
    with pytest.raises(ValueError, match="stride"):
        qp.solve_scaled(np.zeros(2), A, np.zeros(2), np.ones(2), stride=0)
    with pytest.raises(ValueError, match="shape"):
        qp.solve_scaled(np.zeros(3), A, np.zeros(2), np.ones(2))


def test_the_joint_speed_bound_holds_under_chattering_torques():
    """Chattering ±1 torques in multi with the default filter: the joint speeds stay within their
    bound (it is holdable on every step), to within one physics step's discretisation, with no
    collision; the steps with no safe torque report what gave way, and it was the barrier's rows
    (the weighted relaxation this replaced reached 2.7× the bound here, issue defect 3)."""
    env = SafetyFilter(gym.make("C3BFReach-v0", scenario="multi"))
    fastest, collisions, gave_way = 0.0, 0.0, set()
    for episode in range(3):
        env.reset(seed=episode)
        rng = np.random.default_rng(episode)
        for _ in range(250):
            *_, info = env.step(rng.choice([-1.0, 1.0], size=6).astype(np.float32))
            fastest = max(fastest, float(np.abs(env.unwrapped.data.qvel).max()))
            collisions += info["cost"]
            gave_way |= {key.removeprefix("violation_") for key, value in info["safety"].items()
                         if key.startswith("violation_") and value > 0.0}
    bound = env.hook.joint_limits.qd_max.max()
    env.close()
    assert fastest / bound <= 1.001 and collisions == 0
    assert gave_way <= {"barrier", "unmovable"} and "barrier" in gave_way


def test_only_a_guarded_filters_barrier_rows_give_way_first():
    """Beside a guard the barrier's rows are priority 2; without one (the C3BF or the HOCBF
    alone) they are the only rows keeping obstacles off, and share priority 1 with the joint
    limits and the floor (ranked below them, the unguarded C3BF let links reach obstacles)."""
    guarded = SafetyFilter(gym.make("C3BFReach-v0"), "c3bf+hocbf").hook
    capacity = guarded.obstacles.capacity * len(guarded.arm.capsule_ids)
    assert guarded.qp._levels[1] == capacity and guarded._low_priority_span(2 * capacity + 36) == 2 * capacity
    for name in ("c3bf", "hocbf"):
        alone = SafetyFilter(gym.make("C3BFReach-v0"), name).hook
        assert alone.qp._levels == (capacity + alone.floor.n_rows + 24, 0) and alone._low_priority_span(50) == 0


@pytest.mark.parametrize("name", ["c3bf+hocbf", "c3bf"])
def test_violations_are_folded_by_the_kind_row_kinds_names(name):
    """The compiled fold of a step's residuals into the report (``violation_<kind>``) gives, for
    each kind of row, the largest violation above the QP's tolerance over the rows
    :meth:`~c3bf_gym.safety.SafetyController.row_kinds` calls that kind, rows no torque can change
    counting as "unmovable"; and it keeps a larger value the report already holds."""
    hook = SafetyFilter(gym.make("C3BFReach-v0"), name).hook
    rng = np.random.default_rng(3)
    m = 3 * hook._per_obstacle + hook.floor.n_rows + hook._n_joint_rows
    residual = rng.normal(scale=0.1, size=m)
    residual[rng.choice(m, 5, replace=False)] = -5e-7  # violated by less than the tolerance: held
    norm = rng.uniform(0.5, 2.0, m)
    unmovable = rng.choice(m, 4, replace=False)
    norm[unmovable] = 0.0
    residual[unmovable] = (-0.3, -0.2, 0.0, 0.0)  # −b_k: two of them headed into an obstacle
    hook.qp.buffers.residual[:m], hook.qp.buffers.norm[:m] = residual, norm
    want = dict.fromkeys(ROW_KINDS, 0.0)
    for kind, r, k_norm in zip(hook.row_kinds(m), residual, norm):
        key = kind if k_norm > 0.0 else "unmovable"
        if -r > max(want[key], 1e-6):
            want[key] = -r
    assert {k for k, v in want.items() if v > 0} == {*hook.row_kinds(m), "unmovable"}  # every kind gave way
    hook.begin_step()

    def fold():  # one call whose rows gave way, with these residuals
        hook._record(RELAXED, m, 0.0, False, 0, 0, 0, 0.0, 0.0, 0.0, np.zeros(6), np.zeros(6))
        return hook.report.violation

    assert fold() == want
    floor = _step.T_VIOLATION + ROW_KINDS.index("floor")
    hook._tally.values[floor] = held = want["floor"] + 1.0  # an earlier physics step of the step gave way more
    assert fold() == {**want, "floor": held}
