"""The replay buffer that stores the action the safety filter applied."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from c3bf_gym.replay import AppliedActionReplayBuffer

OBS = gym.spaces.Box(-np.inf, np.inf, shape=(4,))
ACTIONS = gym.spaces.Box(-1.0, 1.0, shape=(3,), dtype=np.float32)


def _add(buffer, action, infos):
    n = len(infos)
    buffer.add(np.zeros((n, 4)), np.ones((n, 4)), action, np.zeros(n), np.zeros(n), infos)


def test_the_buffer_stores_each_environments_applied_action():
    buffer = AppliedActionReplayBuffer(10, OBS, ACTIONS, device="cpu", n_envs=2)
    chosen = np.array([[0.5, 0.5, 0.5], [-0.5, 0.0, 1.0]], np.float32)
    applied = [np.array([0.1, 0.2, 0.3], np.float32), np.array([-1.0, 0.0, 1.0], np.float32)]
    _add(buffer, chosen, [{"applied_action": a} for a in applied])
    np.testing.assert_array_equal(buffer.actions[0], np.stack(applied))
    np.testing.assert_array_equal(chosen, [[0.5, 0.5, 0.5], [-0.5, 0.0, 1.0]])  # the caller's array is left alone
    for sampled in buffer.sample(8).actions.numpy():  # and what the learner samples
        assert any(np.array_equal(sampled, a) for a in applied)


def test_the_buffer_refuses_infos_without_an_applied_action_and_other_action_spaces():
    buffer = AppliedActionReplayBuffer(10, OBS, ACTIONS, device="cpu")
    with pytest.raises(ValueError, match="wrap it in c3bf_gym.wrappers.AppliedAction"):
        _add(buffer, np.zeros((1, 3), np.float32), [{}])
    with pytest.raises(ValueError, match=r"info\['applied_action'\] has shape \(2,\), the action \(3,\)"):
        _add(buffer, np.zeros((1, 3), np.float32), [{"applied_action": np.zeros(2)}])
    assert buffer.size() == 0  # nothing was stored by the refused calls
    with pytest.raises(ValueError, match=r"needs a Box\(-1, 1\) action space"):
        AppliedActionReplayBuffer(10, OBS, gym.spaces.Box(-2.0, 2.0, shape=(3,)), device="cpu")
