"""A permutation-invariant observation encoder for Stable-Baselines3 policies (needs torch).

``C3BFReach-v0`` observes obstacles in fixed slots (``OBSERVATION_LAYOUT``): a one-obstacle
scenario fills slot 0 only, ``multi`` fills slots 0-3. A plain MLP learns each slot separately,
so what it learns about the obstacle in slot 0 from the one-obstacle episodes says nothing about
slots 1-3, which it only ever sees in ``multi`` episodes. :class:`ObstacleSetExtractor` treats
the sensed obstacles as a set instead (Deep Sets, Zaheer et al., NeurIPS 2017): one small network
``phi`` encodes every slot the same way, and the policy sees the robot's own features beside the
max and the sum of ``phi`` over the sensed slots. What is learnt about an obstacle in one slot
holds in every slot, and the encoding does not depend on the slots' order.

Use it through ``policy_kwargs=dict(features_extractor_class=ObstacleSetExtractor)`` or the
training option ``obstacle_encoder="set"``.
"""

from __future__ import annotations

import gymnasium as gym
import torch
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

from c3bf_gym.envs.reach import observation_slices
from c3bf_gym.scenarios import MAX_OBSTACLES

__all__ = ["ObstacleSetExtractor"]

#: Observation parts given to ``phi`` with every obstacle slot, as context: where the goal is
#: and how the tool moves, relative to which an obstacle matters.
_CONTEXT = ("goal_rel", "tool_vel")
#: Per-slot parts, each ``MAX_OBSTACLES * width`` long and slot-major.
_PER_SLOT = ("obstacle_rel_pos", "obstacle_vel", "obstacle_radius", "obstacle_sensed")


class ObstacleSetExtractor(BaseFeaturesExtractor):
    """Features = the robot's own observation entries ++ max and sum of ``phi`` over sensed slots.

    Args:
        observation_space: ``C3BFReach-v0``'s observation space (its size is checked), possibly
            with ``extra_features`` entries appended (e.g. by
            :class:`~c3bf_gym.wrappers.FilterFeedback`).
        slot_features: width of ``phi``'s output (and of its hidden layer).
        extra_features: entries after the environment's own observation, passed through beside
            the robot's own entries.
    """

    def __init__(self, observation_space: gym.spaces.Box, slot_features: int = 64, extra_features: int = 0) -> None:
        if isinstance(extra_features, bool) or not isinstance(extra_features, int) or extra_features < 0:
            raise ValueError(f"extra_features must be an integer >= 0, got {extra_features!r}")
        # the arm's joints, from the observation's length 2 n + 73 (c3bf_gym.envs.reach.observation_layout)
        fixed = sum(s.stop - s.start for s in observation_slices(0).values()) + extra_features
        shape = observation_space.shape
        n_joints = (shape[0] - fixed) // 2 if len(shape) == 1 else -1
        if n_joints < 1 or shape != (2 * n_joints + fixed,):
            appended = f" ({extra_features} extra entries appended)" if extra_features else ""
            raise ValueError(f"ObstacleSetExtractor needs a C3BFReach observation of shape (2 n + {fixed},) for an arm of "
                             f"n >= 1 joints{appended}, got {shape}")  # fmt: skip
        parts = observation_slices(n_joints)
        if isinstance(slot_features, bool) or not isinstance(slot_features, int) or slot_features < 1:
            raise ValueError(f"slot_features must be an integer >= 1, got {slot_features!r}")
        size = max(s.stop for s in parts.values())
        own = torch.cat([torch.arange(s.start, s.stop) for name, s in parts.items() if name not in _PER_SLOT]
                        + [torch.arange(size, size + extra_features)])  # fmt: skip
        context = torch.cat([torch.arange(parts[n].start, parts[n].stop) for n in _CONTEXT])
        # (MAX_OBSTACLES, per-slot width) indices: slot k's entries of every per-slot part.
        columns = []
        for name in _PER_SLOT:
            s = parts[name]
            width = (s.stop - s.start) // MAX_OBSTACLES
            columns.append(torch.arange(s.start, s.stop).reshape(MAX_OBSTACLES, width))
        slot = torch.cat(columns, dim=1)
        sensed = torch.arange(parts["obstacle_sensed"].start, parts["obstacle_sensed"].stop)
        super().__init__(observation_space, features_dim=len(own) + 2 * slot_features)
        # index buffers: they follow the module to its device, and are not saved with it
        for name, index in (("_own", own), ("_context", context), ("_slot", slot), ("_sensed", sensed)):
            self.register_buffer(name, index, persistent=False)
        self.phi = nn.Sequential(
            nn.Linear(slot.shape[1] + len(context), slot_features), nn.ReLU(),
            nn.Linear(slot_features, slot_features), nn.ReLU(),
        )  # fmt: skip

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        slots = observations[:, self._slot]  # (batch, slots, width)
        context = observations[:, self._context].unsqueeze(1).expand(-1, slots.shape[1], -1)
        encoded = self.phi(torch.cat([slots, context], dim=2))  # >= 0 (ReLU)
        sensed = observations[:, self._sensed].unsqueeze(2)  # 1 sensed, 0 not
        encoded = encoded * sensed  # an unsensed slot contributes 0 to the max and to the sum
        pooled = torch.cat([encoded.max(dim=1).values, encoded.sum(dim=1)], dim=1)
        return torch.cat([observations[:, self._own], pooled], dim=1)
