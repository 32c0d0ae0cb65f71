"""Nominal controllers."""

from c3bf_gym.controllers.impedance import CartesianImpedance, ImpedanceHook

__all__ = ["CartesianImpedance", "ImpedanceHook"]
