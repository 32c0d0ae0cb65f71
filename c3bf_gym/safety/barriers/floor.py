"""The floor as control-barrier rows in torque space: every protected capsule stays above it."""

from __future__ import annotations

import mujoco
import numpy as np
from numpy.typing import ArrayLike

from .. import _rows
from .base import Rows, require_positive, row_buffers

__all__ = ["Floor"]


class Floor:
    """Capsule ends kept at ``z ≥ z_min`` above the floor, as ``F`` rows ``A @ τ >= b``.

    Each end's height has relative degree two, so each row is the second-order barrier
    (gain γ [1/s], a double root)::

        z̈ + 2γ ż + γ² (z − z_min) ≥ 0,   z̈ = G_z τ + c_z

    with ``G_z`` and ``c_z`` the end's vertical acceleration per unit torque and at zero torque.
    The lowest point of a capsule over a horizontal plane is always one of its ends, so rows at
    both ends of every capsule (one for a sphere, a capsule of length 0) keep it whole above the
    floor.

    Args:
        ends: (F,) the capsule ends that get a row, as indices into the arm's packed capsule
            ends (``0 … S-1`` the ends a, ``S … 2S-1`` the ends b of its ``S`` capsules).
        min_height: (F,) each end's lowest allowed height ``z_min`` [m] (the floor, plus the
            capsule's radius, plus the filter's margin).
        gamma: the rows' gain γ [1/s], finite and > 0.

    Raises:
        ValueError: ``ends`` and ``min_height`` of different lengths or not 1-D, a negative
            end index, a non-finite height, or a gain that is not finite and > 0.
    """

    def __init__(self, ends: ArrayLike, min_height: ArrayLike, gamma: float) -> None:
        ends = np.array(ends, dtype=np.int64)
        min_height = np.array(min_height, dtype=np.float64)
        if ends.ndim != 1 or min_height.ndim != 1:
            raise ValueError(f"ends and min_height must be 1-D, one entry per row; got shapes {ends.shape} and "
                             f"{min_height.shape}")  # fmt: skip
        if ends.shape != min_height.shape:
            raise ValueError(f"ends and min_height must have one entry each per row; got {ends.shape[0]} and "
                             f"{min_height.shape[0]}")  # fmt: skip
        if (ends < 0).any() or not np.isfinite(min_height).all():
            raise ValueError(f"ends must be indices >= 0 and min_height finite [m]; got {ends} and {min_height}")
        self.ends = ends
        self.min_height = min_height
        self.gamma = require_positive("gamma", gamma)

    @classmethod
    def of_model(cls, model: mujoco.MjModel, arm, margin: float, gamma: float) -> Floor:
        """The floor of ``model`` for the capsules of ``arm``
        (:class:`~c3bf_gym.safety.dynamics.ArmModel`), with ``margin`` [m] of clearance: the
        first upright plane geom of the world body (:func:`~c3bf_gym.safety.robot.floor_height`);
        no rows without one. Capsules moved only by hinges about vertical axes (a link on the
        base's pan joint) keep their height and get no row: theirs could only be a constant,
        possibly unsatisfiable, ``0 ≥ b``."""
        from c3bf_gym.safety.robot import floor_height

        floor = floor_height(model)
        if floor is None:
            return cls((), (), gamma)
        scratch = mujoco.MjData(model)
        mujoco.mj_kinematics(model, scratch)
        hinge = model.jnt_type == int(mujoco.mjtJoint.mjJNT_HINGE)
        level = hinge & (np.abs(scratch.xaxis[:, 2]) > 1.0 - 1e-12)  # (njnt,) hinges about world z
        moving = np.array([not level[model.dof_jntid[np.flatnonzero(chain)]].all() for chain in arm.capsule_chain])
        # both ends of a capsule; one of a sphere (its two ends coincide)
        ends = np.flatnonzero(np.concatenate([moving, moving & (arm.capsule_length > 0.0)]))
        radius = np.tile(arm.capsule_radius, 2)[ends]
        return cls(ends, floor + radius + margin, gamma)

    @property
    def n_rows(self) -> int:
        """F, one row per end."""
        return len(self.ends)

    def rows(self, packed_ends: np.ndarray, out: Rows | None = None) -> Rows:
        """The rows for the current state, from the arm's packed capsule end dynamics
        ``packed_ends`` (2S, 3, 3 + nv): per end and axis its position, velocity and acceleration
        at zero torque, then the acceleration per unit generalised force (the arm's
        ``ArmArrays.ends``; :meth:`~c3bf_gym.safety.dynamics.ArmModel.end_dynamics` refreshes
        them). ``A_k = G_z``, ``b_k = −γ² (z − z_min) − 2γ ż − c_z``, computed by
        :func:`c3bf_gym.safety._rows.floor_rows`, the fused kernel's code. Written into ``out``
        (its first ``F`` rows) when given."""
        k = self.n_rows
        A, b = row_buffers(out, k, packed_ends.shape[2] - 3)
        _rows.floor_rows(packed_ends, self.ends, self.min_height, self.gamma, A[:k], b[:k])
        return Rows(A[:k], b[:k])
