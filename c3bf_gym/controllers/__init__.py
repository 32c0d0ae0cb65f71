"""Nominal controllers."""

from c3bf_gym.controllers.impedance import CartesianImpedance

__all__ = ["CartesianImpedance"]
