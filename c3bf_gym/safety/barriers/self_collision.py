"""The arm against itself as control-barrier rows in torque space: pairs of its protected capsules
that the model lets collide stay apart."""

from __future__ import annotations

import mujoco
import numpy as np
from numpy.typing import ArrayLike

from .. import _rows
from .base import Rows, require_positive, row_buffers

__all__ = ["SelfCollision"]


class SelfCollision:
    """Pairs of the arm's capsules kept at a distance ``d ≥ d_min`` between their axes, as ``P``
    rows ``A @ τ >= b``.

    Contact forces between the arm's own links are not in the filter's model ``ẍ = G τ + c``: a
    link pressed against another is pushed by a force no row predicts, which can drive joints
    past their speed bound and a link into an obstacle while every row reports held. So a pair
    that the model lets collide gets a row, the second-order barrier on the distance ``d``
    between the closest points of the two capsule axes (gain γ [1/s], a double root)::

        d̈ + 2γ ḋ + γ² (d − d_min) ≥ 0

    computed by :func:`c3bf_gym.safety._rows.self_collision_rows` (the math is there). With
    ``d_min`` the two radii plus the filter's margin, the capsules, which enclose the geoms, stay
    ``margin`` apart.

    Args:
        pairs: (P, 2) the capsule pairs, as indices into the arm's capsules
            (:attr:`~c3bf_gym.safety.dynamics.ArmModel.capsule_ids`' order).
        min_distance: (P,) each pair's ``d_min`` [m], >= 0.
        gamma: the rows' gain γ [1/s], finite and > 0.

    Raises:
        ValueError: ``pairs`` not of shape (P, 2), a negative index or a capsule paired with
            itself, ``min_distance`` not of shape (P,) or not finite and >= 0, or a gain that is
            not finite and > 0 (each message names the value).
    """

    def __init__(self, pairs: ArrayLike, min_distance: ArrayLike, gamma: float) -> None:
        pairs = np.array(pairs, dtype=np.int64)
        min_distance = np.array(min_distance, dtype=np.float64)
        if pairs.size == 0 and min_distance.size == 0:  # no pairs: any empty shape
            pairs, min_distance = pairs.reshape(0, 2), min_distance.reshape(0)
        if pairs.ndim != 2 or pairs.shape[1] != 2:
            raise ValueError(f"pairs must have shape (P, 2), one capsule pair per row; got {pairs.shape}")
        if min_distance.shape != (pairs.shape[0],):
            raise ValueError(f"min_distance must have shape (P,), one entry per pair; got {min_distance.shape} for "
                             f"{pairs.shape[0]} pairs")  # fmt: skip
        if (pairs < 0).any() or (pairs[:, 0] == pairs[:, 1]).any():
            raise ValueError(f"pairs must be two different capsule indices >= 0; got {pairs.tolist()}")
        if not (np.isfinite(min_distance).all() and (min_distance >= 0.0).all()):
            raise ValueError(f"min_distance must be finite and >= 0 [m]; got {min_distance}")
        self.pairs = np.ascontiguousarray(pairs)
        self.min_distance = min_distance
        self.gamma = require_positive("gamma", gamma)

    @classmethod
    def of_model(cls, model: mujoco.MjModel, arm, margin: float, gamma: float) -> SelfCollision:
        """The pairs of ``arm``'s capsules (:class:`~c3bf_gym.safety.dynamics.ArmModel`) whose geoms
        MuJoCo would let collide, and that the arm's joints can move relative to each other, kept
        ``margin`` [m] apart.

        MuJoCo's rules for two geoms (its documentation, "Collision detection"): on different
        bodies that are not welded together; their ``contype`` and ``conaffinity`` compatible;
        their bodies not parent and child (unless the model disables that filter); the pair not
        named in an ``<exclude>``; or the pair named in a ``<pair>``. A pair moved by exactly the
        same joints of the arm (a gripper's fingers beside its palm) keeps its distance whatever
        the torque, and gets no row."""
        geoms = [int(g) for g in arm.capsule_ids]
        body = model.geom_bodyid
        weld = model.body_weldid
        excluded = {(int(sig) >> 16, int(sig) & 0xFFFF) for sig in model.exclude_signature}
        explicit = {frozenset((int(a), int(b))) for a, b in zip(model.pair_geom1, model.pair_geom2)}
        parent_filter = not model.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_FILTERPARENT)
        pairs = []
        for i, gi in enumerate(geoms):
            for j in range(i + 1, len(geoms)):
                gj = geoms[j]
                if np.array_equal(arm.capsule_chain[i], arm.capsule_chain[j]):
                    continue
                if frozenset((gi, gj)) not in explicit:
                    wi, wj = int(weld[body[gi]]), int(weld[body[gj]])
                    compatible = (model.geom_contype[gi] & model.geom_conaffinity[gj]) or (
                        model.geom_contype[gj] & model.geom_conaffinity[gi])
                    related = parent_filter and (int(weld[model.body_parentid[wi]]) == wj
                                                 or int(weld[model.body_parentid[wj]]) == wi)  # fmt: skip
                    bodies = (int(body[gi]), int(body[gj]))
                    if wi == wj or not compatible or related or bodies in excluded or bodies[::-1] in excluded:
                        continue
                pairs.append((i, j))
        radius = arm.capsule_radius
        min_distance = [radius[i] + radius[j] + margin for i, j in pairs]
        return cls(np.array(pairs, dtype=np.int64).reshape(-1, 2), min_distance, gamma)

    @property
    def n_rows(self) -> int:
        """P, one row per pair."""
        return len(self.pairs)

    def rows(self, packed_ends: np.ndarray, out: Rows | None = None) -> Rows:
        """The rows for the current state, from the arm's packed capsule end dynamics
        ``packed_ends`` (2S, 3, 3 + nv), as :meth:`~c3bf_gym.safety.barriers.Floor.rows` reads
        them. Written into ``out`` (its first ``P`` rows) when given.

        Raises:
            ValueError: a pair names a capsule that ``packed_ends`` does not hold."""
        k = self.n_rows
        if k and int(self.pairs.max()) >= packed_ends.shape[0] // 2:
            raise ValueError(f"pairs name capsule {int(self.pairs.max())}, but packed_ends holds "
                             f"{packed_ends.shape[0] // 2} capsules")  # fmt: skip
        A, b = row_buffers(out, k, packed_ends.shape[2] - 3)
        _rows.self_collision_rows(packed_ends, self.pairs, self.min_distance, self.gamma, A[:k], b[:k])
        return Rows(A[:k], b[:k])
