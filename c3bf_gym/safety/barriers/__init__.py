"""Control barrier functions turned into linear torque-space constraints.

Obstacle barriers (per arm point, see :mod:`.base`):

- :class:`C3BF` — collision-cone CBF (``"c3bf"``),
- :class:`DistanceHOCBF` — second-order CBF on the squared distance (``"hocbf"``),

and :class:`JointLimits` for joint position/velocity boxes, :class:`Floor` for the floor
under the arm and :class:`SelfCollision` for the arm's own links. All produce
:class:`Rows` ``A @ tau >= b``. The arithmetic runs in compiled kernels
(:mod:`c3bf_gym.safety._rows`).
"""

from __future__ import annotations

import inspect
from typing import Any

from .base import Barrier, BarrierTerms, Rows, distance_barrier
from .c3bf import C3BF
from .floor import Floor
from .hocbf import DistanceHOCBF
from .joint_limits import JointLimits
from .self_collision import SelfCollision

__all__ = [
    "BARRIERS",
    "Barrier",
    "BarrierTerms",
    "C3BF",
    "DistanceHOCBF",
    "Floor",
    "JointLimits",
    "Rows",
    "SelfCollision",
    "distance_barrier",
    "make_barrier",
]

BARRIERS: dict[str, type[Barrier]] = {"c3bf": C3BF, "hocbf": DistanceHOCBF}
"""Obstacle barriers by name."""


def make_barrier(name: str, **params: Any) -> Barrier:
    """Construct the obstacle barrier registered as ``name`` with ``params``.

    Args:
        name: a key of :data:`BARRIERS` (``"c3bf"`` or ``"hocbf"``).
        **params: constructor keyword arguments (e.g. ``gamma``, ``eps`` for
            ``"c3bf"``; ``gamma1``, ``gamma2`` for ``"hocbf"``).

    Raises:
        ValueError: on an unknown name (the message lists the valid choices), an
            unknown parameter (the message lists the valid ones) or an invalid
            parameter value.
    """
    try:
        cls = BARRIERS[name]
    except (KeyError, TypeError):
        choices = ", ".join(repr(k) for k in BARRIERS)
        raise ValueError(f"unknown barrier {name!r}; valid choices: {choices}") from None
    try:
        inspect.signature(cls).bind(**params)
    except TypeError as exc:
        valid = ", ".join(inspect.signature(cls).parameters)
        raise ValueError(
            f"invalid parameters for barrier {name!r} ({exc}); valid parameters: {valid}"
        ) from None
    return cls(**params)
