"""A Stable-Baselines3 replay buffer that stores the action the safety filter applied (needs SB3).

Under a safety filter the transition an agent sees, ``(s, r, s')``, is the outcome of the
filtered action, not of the one the policy chose. An off-policy learner that stores the chosen
action learns the value of an action that was never carried out wherever the filter acted.
:class:`AppliedActionReplayBuffer` stores the applied one instead, as Cheng, Orosz, Murray and
Burdick (AAAI 2019) train on the action after their barrier compensator; the policy itself is
unchanged and still acts through the filter.

Use it through ``SAC(..., replay_buffer_class=AppliedActionReplayBuffer)`` on environments
wrapped in :class:`~c3bf_gym.wrappers.AppliedAction`, or the training option
``applied_action=True`` (``c3bf-gym train --applied-action``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from stable_baselines3.common.buffers import ReplayBuffer

__all__ = ["AppliedActionReplayBuffer"]


class AppliedActionReplayBuffer(ReplayBuffer):
    """SB3's :class:`~stable_baselines3.common.buffers.ReplayBuffer`, storing each environment's
    ``info["applied_action"]`` (:class:`~c3bf_gym.wrappers.AppliedAction`) in place of the action
    the policy chose. Everything else (observations, rewards, sampling) is SB3's.

    ``add`` receives the actions as SB3 stores them, scaled to ``[-1, 1]``; the environments'
    action spaces must already be ``Box(-1, 1)`` (every Cartesian action mode's is), so that the
    applied action, in the environment's units, is in the buffer's units too.

    Raises:
        ValueError: (from ``add``) an environment's info has no ``"applied_action"`` (it is not
            wrapped in :class:`~c3bf_gym.wrappers.AppliedAction`), or one of another shape than
            the action's; or, at construction, an action space other than ``Box(-1, 1)``.
    """

    def __init__(self, buffer_size: int, observation_space: Any, action_space: Any, *args: Any, **kwargs: Any) -> None:
        low, high = getattr(action_space, "low", None), getattr(action_space, "high", None)
        if low is None or not (np.all(low == -1.0) and np.all(high == 1.0)):
            raise ValueError(f"AppliedActionReplayBuffer needs a Box(-1, 1) action space, got {action_space}")
        super().__init__(buffer_size, observation_space, action_space, *args, **kwargs)

    def add(self, obs: np.ndarray, next_obs: np.ndarray, action: np.ndarray, reward: np.ndarray, done: np.ndarray,
            infos: list[dict[str, Any]]) -> None:  # fmt: skip
        applied = np.empty_like(action)
        for i, info in enumerate(infos):
            if "applied_action" not in info:
                raise ValueError("AppliedActionReplayBuffer stores info['applied_action'], and this environment's info "
                                 "has none: wrap it in c3bf_gym.wrappers.AppliedAction")  # fmt: skip
            value = np.asarray(info["applied_action"])
            if value.shape != applied[i].shape:
                raise ValueError(f"info['applied_action'] has shape {value.shape}, the action {applied[i].shape}")
            applied[i] = value
        super().add(obs, next_obs, applied, reward, done, infos)
