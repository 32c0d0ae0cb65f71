"""Nominal controllers."""

from c3bf_gym.controllers.impedance import CartesianImpedance, ImpedanceHook
from c3bf_gym.controllers.modulation import modulate

__all__ = ["CartesianImpedance", "ImpedanceHook", "modulate"]
