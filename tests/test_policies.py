"""The set encoder of obstacle slots: order-free, blind to unsensed slots, and checked inputs."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

import c3bf_gym  # noqa: F401  (registers C3BFReach-v0)
from c3bf_gym.envs.reach import OBSERVATION_LAYOUT
from c3bf_gym.policies import ObstacleSetExtractor
from c3bf_gym.scenarios import MAX_OBSTACLES

OWN = 21  # joint_pos, joint_vel, tool_pos, tool_vel, goal_rel


def _slot_view(obs: np.ndarray) -> list[np.ndarray]:
    """The per-slot parts of an observation batch, each (batch, MAX_OBSTACLES, width)."""
    parts, start = [], OWN
    for _, size, _ in OBSERVATION_LAYOUT[5:]:
        parts.append(obs[:, start : start + size].reshape(len(obs), MAX_OBSTACLES, -1))
        start += size
    return parts


def _from_slots(own: np.ndarray, parts: list[np.ndarray]) -> np.ndarray:
    return np.concatenate([own] + [p.reshape(len(own), -1) for p in parts], axis=1)


@pytest.fixture(scope="module")
def multi_obs() -> np.ndarray:
    env = gym.make("C3BFReach-v0", scenario="multi")
    obs = []
    for seed in range(4):
        o, _ = env.reset(seed=seed)
        for _ in range(20):
            o, *_ = env.step(np.zeros(6))
        obs.append(o)
    env.close()
    batch = np.stack(obs)
    assert (batch[:, -MAX_OBSTACLES:].sum(axis=1) >= 2).all(), "several obstacles sensed"
    return batch


def _features(extractor: ObstacleSetExtractor, obs: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return extractor(torch.as_tensor(obs, dtype=torch.float32)).numpy()


def test_features_are_the_robot_entries_and_pooled_slots(multi_obs):
    torch.manual_seed(0)
    extractor = ObstacleSetExtractor(gym.spaces.Box(-np.inf, np.inf, (multi_obs.shape[1],)), slot_features=16)
    features = _features(extractor, multi_obs)
    assert extractor.features_dim == OWN + 2 * 16 == features.shape[1]
    np.testing.assert_array_equal(features[:, :OWN], multi_obs[:, :OWN])
    assert (features[:, OWN:] != 0).any()


def test_slot_order_does_not_matter(multi_obs):
    torch.manual_seed(1)
    extractor = ObstacleSetExtractor(gym.spaces.Box(-np.inf, np.inf, (multi_obs.shape[1],)))
    order = np.random.default_rng(0).permutation(MAX_OBSTACLES)
    shuffled = _from_slots(multi_obs[:, :OWN], [p[:, order] for p in _slot_view(multi_obs)])
    assert not np.array_equal(shuffled, multi_obs)
    np.testing.assert_allclose(_features(extractor, shuffled), _features(extractor, multi_obs), rtol=1e-5, atol=1e-5)


def test_unsensed_slots_are_ignored(multi_obs):
    torch.manual_seed(2)
    extractor = ObstacleSetExtractor(gym.spaces.Box(-np.inf, np.inf, (multi_obs.shape[1],)))
    parts = [p.copy() for p in _slot_view(multi_obs)]
    unsensed = parts[-1][..., 0] == 0
    assert unsensed.any()
    for part in parts[:-1]:
        part[unsensed] = 3.0  # anything: the flag says the slot is empty
    np.testing.assert_array_equal(_features(extractor, _from_slots(multi_obs[:, :OWN], parts)), _features(extractor, multi_obs))
    parts[-1][unsensed] = 1.0  # the same entries, now claimed sensed, do count
    assert not np.allclose(_features(extractor, _from_slots(multi_obs[:, :OWN], parts)), _features(extractor, multi_obs))


@pytest.mark.parametrize(
    "shape, slot_features, message",
    [
        ((84,), 64, r"needs a C3BFReach observation of shape \(2 n \+ 73,\) .* got \(84,\)"),
        ((73,), 64, r"needs a C3BFReach observation .* n >= 1 joints, got \(73,\)"),
        ((85,), 0, "slot_features must be an integer >= 1"),
        ((85,), 8.0, "slot_features must be an integer >= 1"),
        ((86,), {"extra_features": 6}, r"shape \(2 n \+ 79,\) .* \(6 extra entries appended\), got \(86,\)"),
        ((85,), {"extra_features": -1}, "extra_features must be an integer >= 0"),
        ((85,), {"extra_features": True}, "extra_features must be an integer >= 0"),
    ],
)
def test_bad_extractor_arguments(shape, slot_features, message):
    kwargs = slot_features if isinstance(slot_features, dict) else {"slot_features": slot_features}
    with pytest.raises(ValueError, match=message):
        ObstacleSetExtractor(gym.spaces.Box(-np.inf, np.inf, shape), **kwargs)


def test_extra_entries_pass_through_beside_the_robots_own(multi_obs):
    """Entries appended after the environment's observation (``FilterFeedback``'s correction) join
    the robot's own features; the slots are pooled as before."""
    extra = np.random.default_rng(0).uniform(-1, 1, (len(multi_obs), 6)).astype(np.float32)
    torch.manual_seed(3)
    plain = ObstacleSetExtractor(gym.spaces.Box(-np.inf, np.inf, (multi_obs.shape[1],)), slot_features=16)
    torch.manual_seed(3)
    wider = ObstacleSetExtractor(gym.spaces.Box(-np.inf, np.inf, (multi_obs.shape[1] + 6,)), slot_features=16,
                                 extra_features=6)  # fmt: skip
    assert wider.features_dim == plain.features_dim + 6
    features = _features(wider, np.concatenate([multi_obs, extra], axis=1))
    np.testing.assert_array_equal(features[:, : OWN + 6], np.concatenate([multi_obs[:, :OWN], extra], axis=1))
    np.testing.assert_allclose(features[:, OWN + 6 :], _features(plain, multi_obs)[:, OWN:], rtol=1e-6)


def test_extractor_reads_any_arms_observation():
    """The Panda's observation (7 joints: 87 entries) has its own slices; the extractor finds them
    from the length and gives every slot the same encoder."""
    env = gym.make("C3BFReachPanda-v0", scenario="multi")
    try:
        obs, _ = env.reset(seed=0)
        assert obs.shape == (87,)
        extractor = ObstacleSetExtractor(env.observation_space, slot_features=8)
        features = extractor(torch.as_tensor(obs[None]))
        assert features.shape == (1, extractor.features_dim) and torch.isfinite(features).all()
    finally:
        env.close()
