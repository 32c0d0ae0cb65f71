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
    rows ``A @ τ >= b``, and ``Q`` more between capsules and fixed parts of the arm.

    Contact forces between the arm's own links are not in the filter's model ``ẍ = G τ + c``
    (only the joint-limit rows take the last physics step's, as an estimate of the next): a link
    pressed against another is pushed by a force no obstacle row predicts, which can drive joints
    past their speed bound and a link into an obstacle while every row reports held. So a pair
    that the model lets collide gets a row, the second-order barrier on the distance ``d``
    between the closest points of the two capsule axes (gain γ [1/s], a double root)::

        d̈ + 2γ ḋ + γ² (d − d_min) ≥ 0

    computed by :func:`c3bf_gym.safety._rows.self_collision_rows` (the math is there). With
    ``d_min`` the two radii plus the filter's margin, the capsules, which enclose the geoms, stay
    ``margin`` apart.

    Parts of the arm that no joint moves are partners too: a geom on the base, or one that lies
    on the axis of every hinge that turns it (the Sawyer's head), which the filter does not
    protect against obstacles, since nothing it does moves them, but can keep the other links
    off (:func:`c3bf_gym.safety._rows.fixed_partner_rows`).

    Args:
        pairs: (P, 2) the capsule pairs, as indices into the arm's capsules
            (:attr:`~c3bf_gym.safety.dynamics.ArmModel.capsule_ids`' order).
        min_distance: (P,) each pair's ``d_min`` [m], >= 0.
        gamma: the rows' gain γ [1/s], finite and > 0.
        fixed: ``(capsules, ends, min_distance)``, the pairs with fixed parts: (Q,) capsule
            indices, the parts' axes packed as the arm's capsule ends ((2Q, 3, 3 + nv): the ends
            ``a`` then ``b`` in world coordinates [m] in column 0, zero velocity, acceleration and
            ``G``) and (Q,) each pair's ``d_min`` [m]; None: none.

    Raises:
        ValueError: ``pairs`` not of shape (P, 2), a negative index or a capsule paired with
            itself, ``min_distance`` not of shape (P,) or not finite and >= 0, or a gain that is
            not finite and > 0 (each message names the value).
    """

    def __init__(self, pairs: ArrayLike, min_distance: ArrayLike, gamma: float, fixed: tuple | None = None) -> None:
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
        if fixed is None:
            fixed = (np.zeros(0, np.int64), np.zeros((0, 3, 3)), np.zeros(0))
        capsules, ends, fixed_min = (np.ascontiguousarray(x) for x in fixed)
        q = capsules.shape[0]
        if capsules.shape != (q,) or ends.ndim != 3 or ends.shape[:2] != (2 * q, 3) or fixed_min.shape != (q,):
            raise ValueError(f"fixed must be (capsules (Q,), ends (2Q, 3, 3 + nv), min_distance (Q,)); got shapes "
                             f"{capsules.shape}, {ends.shape}, {fixed_min.shape}")  # fmt: skip
        if (capsules < 0).any() or not (np.isfinite(fixed_min).all() and (fixed_min >= 0.0).all()):
            raise ValueError(f"fixed capsules must be indices >= 0 and their min_distance finite and >= 0 [m]; got "
                             f"{capsules.tolist()} and {fixed_min}")  # fmt: skip
        self.fixed_capsules = capsules.astype(np.int64)
        self.fixed_ends = ends.astype(np.float64)
        self.fixed_min = fixed_min.astype(np.float64)
        #: (Q,) the geom of each fixed part (-1: not known; :meth:`of_model` names them)
        self.fixed_geoms = np.full(q, -1, dtype=np.int64)

    @classmethod
    def of_model(cls, model: mujoco.MjModel, arm, margin: float, gamma: float) -> SelfCollision:
        """The pairs of ``arm``'s capsules (:class:`~c3bf_gym.safety.dynamics.ArmModel`) whose geoms
        MuJoCo would let collide, and that the arm's joints can move relative to each other, kept
        ``margin`` [m] apart; and the pairs of its capsules with fixed parts of the same arm.

        MuJoCo's rules for two geoms (its documentation, "Collision detection"): on different
        bodies that are not welded together; their ``contype`` and ``conaffinity`` compatible;
        their bodies not parent and child (unless the model disables that filter, or the parent
        is welded to the world); the pair not named in an ``<exclude>``; or the pair named in a
        ``<pair>``. A pair moved by exactly the same joints of the arm (a gripper's fingers beside
        its palm) keeps its distance whatever the torque, and gets no row.

        A fixed part is a colliding geom of the arm's kinematic tree that is not protected and
        that no joint of the model can move (:meth:`~c3bf_gym.safety.RobotDescription.from_model`'s
        test, on every dof), held by its enclosing capsule where the model's reference
        configuration puts it. A capsule already within ``d_min`` of a fixed part there (the
        Sawyer's link 0 resting on its base) gets no row for it: no torque would part them, and
        :class:`~c3bf_gym.safety.SafetyController` warns of such contacts instead."""
        from c3bf_gym.safety.geometry import UnsupportedGeomError, enclosing_capsule, world_segments
        from c3bf_gym.safety.robot import RobotDescription

        geoms = [int(g) for g in arm.capsule_ids]
        rules = _Rules(model)
        pairs = []
        for i, gi in enumerate(geoms):
            for j in range(i + 1, len(geoms)):
                if not np.array_equal(arm.capsule_chain[i], arm.capsule_chain[j]) and rules.collide(gi, geoms[j]):
                    pairs.append((i, j))
        radius = arm.capsule_radius
        min_distance = [radius[i] + radius[j] + margin for i, j in pairs]

        data = mujoco.MjData(model)
        mujoco.mj_kinematics(model, data)
        a, b = arm.capsule_segments(data)
        root = model.body_rootid[model.geom_bodyid[geoms[0]]]
        every_dof = np.arange(model.nv)
        fixed, fixed_ends, fixed_min, fixed_geoms = [], [], [], []
        for g in range(model.ngeom):
            if g in geoms or model.body_rootid[model.geom_bodyid[g]] != root:
                continue
            partners = [i for i, gi in enumerate(geoms) if rules.collide(gi, g)]
            if not partners:  # (before fitting a capsule to a mesh: the costly part)
                continue
            try:
                capsule = enclosing_capsule(model, g)
            except UnsupportedGeomError:
                continue
            if not RobotDescription._immovable(model, every_dof, g, capsule):
                continue
            end_a, end_b = world_segments(data, np.array([g]), np.array([[capsule.a, capsule.b]]), np.array([-1]))
            ends = (end_a[0], end_b[0])
            for i in partners:
                d_min = radius[i] + capsule.radius + margin
                if _segment_distance(a[i], b[i], *ends) > d_min:
                    fixed.append(i)
                    fixed_geoms.append(g)
                    fixed_ends.append(ends)
                    fixed_min.append(d_min)
        packed = np.zeros((2 * len(fixed), 3, 3 + model.nv))
        for k, (end_a, end_b) in enumerate(fixed_ends):
            packed[k, :, 0], packed[len(fixed) + k, :, 0] = end_a, end_b
        rows = cls(np.array(pairs, dtype=np.int64).reshape(-1, 2), min_distance, gamma,
                   (np.array(fixed, dtype=np.int64), packed, np.array(fixed_min, dtype=np.float64)))
        rows.fixed_geoms[:] = fixed_geoms
        return rows

    @property
    def n_rows(self) -> int:
        """P + Q, one row per pair."""
        return len(self.pairs) + len(self.fixed_capsules)

    def rows(self, packed_ends: np.ndarray, out: Rows | None = None) -> Rows:
        """The rows for the current state, from the arm's packed capsule end dynamics
        ``packed_ends`` (2S, 3, 3 + nv), as :meth:`~c3bf_gym.safety.barriers.Floor.rows` reads
        them. Written into ``out`` (its first ``P`` rows) when given.

        Raises:
            ValueError: a pair names a capsule that ``packed_ends`` does not hold."""
        k, p = self.n_rows, len(self.pairs)
        largest = max(int(self.pairs.max(initial=-1)), int(self.fixed_capsules.max(initial=-1)))
        if largest >= packed_ends.shape[0] // 2:
            raise ValueError(f"pairs name capsule {largest}, but packed_ends holds {packed_ends.shape[0] // 2} "
                             "capsules")  # fmt: skip
        if len(self.fixed_capsules) and self.fixed_ends.shape[2] != packed_ends.shape[2]:
            raise ValueError(f"the fixed parts are packed for {self.fixed_ends.shape[2] - 3} dofs, packed_ends for "
                             f"{packed_ends.shape[2] - 3}")  # fmt: skip
        A, b = row_buffers(out, k, packed_ends.shape[2] - 3)
        _rows.self_collision_rows(packed_ends, self.pairs, self.min_distance, self.gamma, A[:p], b[:p])
        _rows.fixed_partner_rows(packed_ends, self.fixed_capsules, self.fixed_ends, self.fixed_min, self.gamma,
                                 A[p:k], b[p:k])
        return Rows(A[:k], b[:k])


class _Rules:
    """MuJoCo's filters of geom pairs (:meth:`SelfCollision.of_model`), read once from a model."""

    def __init__(self, model: mujoco.MjModel) -> None:
        self.model = model
        self.excluded = {(int(sig) >> 16, int(sig) & 0xFFFF) for sig in model.exclude_signature}
        self.explicit = {frozenset((int(a), int(b))) for a, b in zip(model.pair_geom1, model.pair_geom2)}
        self.parent_filter = not model.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_FILTERPARENT)

    def collide(self, g1: int, g2: int) -> bool:
        """Whether MuJoCo generates contacts between geoms ``g1`` and ``g2``."""
        model = self.model
        if frozenset((g1, g2)) in self.explicit:
            return True
        b1, b2 = int(model.geom_bodyid[g1]), int(model.geom_bodyid[g2])
        w1, w2 = int(model.body_weldid[b1]), int(model.body_weldid[b2])
        if w1 == w2:
            return False
        if not ((model.geom_contype[g1] & model.geom_conaffinity[g2]) or
                (model.geom_contype[g2] & model.geom_conaffinity[g1])):
            return False
        parent1 = int(model.body_weldid[model.body_parentid[w1]])
        parent2 = int(model.body_weldid[model.body_parentid[w2]])
        if self.parent_filter and w1 and w2 and (parent1 == w2 or parent2 == w1):  # (not a world-welded parent)
            return False
        return (b1, b2) not in self.excluded and (b2, b1) not in self.excluded


def _segment_distance(a1: np.ndarray, b1: np.ndarray, a2: np.ndarray, b2: np.ndarray) -> float:
    """The distance between segments ``a1``-``b1`` and ``a2``-``b2`` [m]."""
    s, t = _rows._segment_params(tuple(a1), tuple(b1 - a1), tuple(a2), tuple(b2 - a2))
    return float(np.linalg.norm(a1 + s * (b1 - a1) - a2 - t * (b2 - a2)))
