"""Environments."""

from c3bf_gym.envs.reach import HOOK_STAGES, OBSERVATION_LAYOUT, OBSERVATION_SLICES, C3BFReachEnv, TorqueHook

__all__ = ["C3BFReachEnv", "HOOK_STAGES", "OBSERVATION_LAYOUT", "OBSERVATION_SLICES", "TorqueHook"]
