"""The filter's shape of a protected geom: a capsule that contains it, computed from the model.

The barrier rows need, for every protected geom, the closest point to an obstacle's centre and
that point's dynamics in closed form. A capsule (a segment ``a``–``b`` swept by a ball of radius
``R``) gives both: the closest point slides along the segment, whose end points move rigidly with
the geom's body. So every protected geom is replaced by a capsule that contains it, held in the
geom's own frame (the frame of ``data.geom_xpos``, ``data.geom_xmat``):

============  ==========================================================================
geom type     enclosing capsule
============  ==========================================================================
capsule       itself: ``a, b = (0, 0, ∓half)``, ``R`` its radius
sphere        itself: ``a = b = 0``
cylinder      its axis and radius (every point of the cylinder lies within ``R`` of its axis)
ellipsoid     along its longest semi-axis ``s₀``, ``R`` the second longest ``s₁``
              (``y² + z² ≤ s₁² (y²/s₁² + z²/s₂²) ≤ s₁²``)
box, mesh     fitted to the corners, or to the vertices of the mesh's convex hull (what MuJoCo
              collides), by :func:`fit_capsule`; a capsule is convex, so containing the corners
              or hull vertices contains the whole geom
============  ==========================================================================

Planes, height fields and SDF geoms have no enclosing capsule and are refused.

A geom moved by joints the filter does not drive (a gripper's fingers) gets the capsule that holds
it over those joints' whole range, in the frame of the last body the arm alone moves
(:func:`protected_capsule`): the filter cannot steer the fingers, but it can keep obstacles off
everywhere they can be.
"""

from __future__ import annotations

from typing import NamedTuple

import mujoco
import numpy as np

__all__ = [
    "Capsule", "UnsupportedGeomError", "capsule_distances", "enclosing_capsule", "fit_capsule", "protected_capsule",
    "world_segments",
]

_T = mujoco.mjtGeom
_HINGE, _SLIDE = int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)


class UnsupportedGeomError(ValueError):
    """A geom with no enclosing capsule (a plane, a height field, an SDF); the message names it."""


class Capsule(NamedTuple):
    """A capsule: the points within ``radius`` of the segment ``a``–``b``.

    Attributes:
        a, b: (3,) the segment's end points [m] (equal for a sphere), in the geom's frame, or in
            body ``body``'s frame.
        radius: [m].
        source: the geom type it encloses ("capsule", "sphere", "cylinder", "ellipsoid", "box",
            "mesh").
        body: -1: ``a`` and ``b`` are in the geom's frame; else the body in whose frame they are
            (:func:`protected_capsule`).
    """

    a: np.ndarray
    b: np.ndarray
    radius: float
    source: str
    body: int = -1

    @property
    def half_length(self) -> float:
        """Half the segment's length [m]."""
        return 0.5 * float(np.linalg.norm(self.b - self.a))

    def volume(self) -> float:
        """[m³]."""
        return float(np.pi * self.radius**2 * (2.0 * self.half_length + 4.0 / 3.0 * self.radius))

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(P,) signed distances of ``points`` (P, 3), in the geom's frame, to the capsule's
        surface [m] (negative inside)."""
        ab = self.b - self.a
        length2 = float(ab @ ab)
        t = np.zeros(len(points)) if length2 == 0.0 else np.clip((points - self.a) @ ab / length2, 0.0, 1.0)
        return np.linalg.norm(points - (self.a + t[:, None] * ab), axis=1) - self.radius


def _axis_capsule(centre: np.ndarray, axis: np.ndarray, points: np.ndarray, radius: float) -> tuple | None:
    """The shortest segment on the line ``centre + t axis`` whose capsule of ``radius`` holds
    ``points``: ``(t0, t1)``, or None when ``radius`` is below the points' distance to the line."""
    rel = points - centre
    t = rel @ axis
    d2 = np.einsum("ij,ij->i", rel, rel) - t * t
    room = radius * radius - d2
    if np.any(room < 0.0):
        return None
    reach = np.sqrt(room)
    # each point p needs a segment end within reach of t_p: t1 >= t_p - reach_p, t0 <= t_p + reach_p
    t1, t0 = float(np.max(t - reach)), float(np.min(t + reach))
    if t0 > t1:  # a ball centred anywhere on [t1, t0] holds them: a sphere
        t0 = t1 = 0.5 * (t0 + t1)
    return t0, t1


def fit_capsule(points: np.ndarray, source: str = "points") -> Capsule:
    """A small capsule containing every one of ``points`` (P, 3) [m].

    For each candidate axis (the points' principal axes and the frame's axes), the axis line
    passes through the centre of the points' bounding rectangle across it; for radii from the
    points' largest distance to that line up to 1.6 times it, :func:`_axis_capsule` gives the
    shortest segment that holds them all. The capsule of least volume over axes and radii is
    returned, after a check that it holds every point (to 1e-9 m). Not the minimal capsule in
    general, but a few percent from it on link-shaped point sets.

    Raises:
        ValueError: no points, or points that are not finite.
    """
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0 or not np.all(np.isfinite(points)):
        raise ValueError(f"fit_capsule takes finite points of shape (P, 3) with P >= 1, got shape {points.shape}")
    mean = points.mean(axis=0)
    _, vectors = np.linalg.eigh(np.cov((points - mean).T) if len(points) > 1 else np.eye(3))
    axes = list(vectors.T[::-1]) + list(np.eye(3))
    best: Capsule | None = None
    for axis in axes:
        axis = axis / np.linalg.norm(axis)
        # the line through the middle of the points' extent across the axis
        u = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        w = np.cross(axis, u)
        across = np.stack([points @ u, points @ w], axis=1)
        mid = 0.5 * (across.min(axis=0) + across.max(axis=0))
        centre = mid[0] * u + mid[1] * w
        rel = points - centre
        t = rel @ axis
        r_min = float(np.sqrt(np.max(np.einsum("ij,ij->i", rel, rel) - t * t).clip(0.0)))
        for radius in r_min * np.linspace(1.0, 1.6, 25) + 1e-12:
            span = _axis_capsule(centre, axis, points, radius)
            if span is None:
                continue
            candidate = Capsule(centre + span[0] * axis, centre + span[1] * axis, float(radius), source)
            if best is None or candidate.volume() < best.volume():
                best = candidate
    assert best is not None  # radius r_min (+1e-12) always holds the points
    if np.max(best.distance(points)) > 1e-9:
        raise ArithmeticError("fit_capsule: the fitted capsule does not hold every point")  # a bug, never input
    return best


def _box_corners(half: np.ndarray) -> np.ndarray:
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
    return signs * half


def _mesh_points(model: mujoco.MjModel, mesh: int) -> np.ndarray:
    """The vertices of mesh ``mesh``'s convex hull (MuJoCo collides meshes as their hull), or all
    its vertices when the model keeps no hull; in the frame of a geom that uses it."""
    start, count = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
    vertices = model.mesh_vert[start : start + count].astype(float)
    graph = model.mesh_graphadr[mesh]
    if graph >= 0:  # mesh_graph: numvert, numface, then vert_edgeadr, vert_globalid, ...
        numvert = int(model.mesh_graph[graph])
        ids = model.mesh_graph[graph + 2 + numvert : graph + 2 + 2 * numvert]
        vertices = vertices[ids]
    return vertices


def enclosing_capsule(model: mujoco.MjModel, geom: int) -> Capsule:
    """The capsule the filter protects in place of geom ``geom`` (the module's table), in the
    geom's frame.

    Raises:
        UnsupportedGeomError: a plane, height field or SDF geom (named).
    """
    kind = int(model.geom_type[geom])
    size = model.geom_size[geom].astype(float)
    zero = np.zeros(3)
    if kind == _T.mjGEOM_SPHERE:
        return Capsule(zero, zero.copy(), float(size[0]), "sphere")
    if kind in (_T.mjGEOM_CAPSULE, _T.mjGEOM_CYLINDER):
        source = "capsule" if kind == _T.mjGEOM_CAPSULE else "cylinder"
        return Capsule(np.array([0.0, 0.0, -size[1]]), np.array([0.0, 0.0, size[1]]), float(size[0]), source)
    if kind == _T.mjGEOM_ELLIPSOID:
        order = np.argsort(size)[::-1]
        half = np.zeros(3)
        half[order[0]] = size[order[0]]
        return Capsule(-half, half, float(size[order[1]]), "ellipsoid")
    if kind == _T.mjGEOM_BOX:
        return fit_capsule(_box_corners(size), "box")
    if kind == _T.mjGEOM_MESH:
        return fit_capsule(_mesh_points(model, int(model.geom_dataid[geom])), "mesh")
    name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, geom) or f"#{geom}"
    type_name = mujoco.mjtGeom(kind).name.removeprefix("mjGEOM_").lower()
    raise UnsupportedGeomError(f"geom {name!r} is a {type_name}: it has no enclosing capsule, so the filter cannot "
                               "protect it; leave it out of the protected geoms")


#: Samples of a hinge's range when sweeping a geom over it (the chords' sagitta is added).
_HINGE_SAMPLES = 9
#: At most this many joints the filter does not drive may move one protected geom.
_MAX_SWEPT_JOINTS = 3


def _core(model: mujoco.MjModel, geom: int) -> tuple[np.ndarray, float]:
    """Points (P, 3) in the geom's frame and a radius whose Minkowski sum holds the geom: a
    primitive's enclosing segment ends and capsule radius, a box's corners or a mesh's hull
    vertices with radius 0."""
    kind = int(model.geom_type[geom])
    if kind == _T.mjGEOM_BOX:
        return _box_corners(model.geom_size[geom].astype(float)), 0.0
    if kind == _T.mjGEOM_MESH:
        return _mesh_points(model, int(model.geom_dataid[geom])), 0.0
    capsule = enclosing_capsule(model, geom)
    return np.stack([capsule.a, capsule.b]), capsule.radius


def protected_capsule(model: mujoco.MjModel, geom: int, arm_dofs: np.ndarray) -> Capsule:
    """The capsule the filter protects for geom ``geom`` when it drives the dofs ``arm_dofs``.

    A geom that only the arm's dofs move gets :func:`enclosing_capsule`, in its own frame. A geom
    that other dofs move too (a finger on a gripper's joints) gets a capsule in the frame of its
    *mount*, the last body on its chain that the arm's dofs alone move, holding the geom at every
    position of the other joints between the mount and it: slide joints at both ends of their
    range (the geom's points move on straight lines between them), hinges at
    :data:`_HINGE_SAMPLES` angles, with the largest sagitta of the arcs between samples (from the
    geom's farthest reach from each hinge's axis) added to the radius.

    Raises:
        UnsupportedGeomError: a plane, height field or SDF geom; a geom moved by a joint the
            filter does not drive that is not a limited hinge or slide joint, or by more than
            :data:`_MAX_SWEPT_JOINTS` of them (named).
    """
    arm = np.zeros(model.nv, dtype=bool)
    arm[np.asarray(arm_dofs, dtype=int)] = True
    path, body = [], int(model.geom_bodyid[geom])
    while body > 0:
        path.append(body)
        body = int(model.body_parentid[body])
    others = [b for b in path if not arm[model.body_dofadr[b] : model.body_dofadr[b] + model.body_dofnum[b]].all()]
    if not others:
        return enclosing_capsule(model, geom)
    mount = int(model.body_parentid[others[-1]])  # the body above the highest one another dof moves
    name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, geom) or f"#{geom}"
    below = path[: path.index(others[-1]) + 1]
    if any(arm[model.body_dofadr[b] : model.body_dofadr[b] + model.body_dofnum[b]].any() for b in below):
        raise UnsupportedGeomError(f"geom {name!r} is moved by a joint the filter drives below one it does not: "
                                   "the arm's joints must come first on its chain")
    joints = [j for b in others for j in range(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b])]
    values, step = [], np.zeros(len(joints))
    for i, j in enumerate(joints):
        jname = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) or f"#{j}"
        kind = int(model.jnt_type[j])
        if kind not in (_HINGE, _SLIDE) or not model.jnt_limited[j]:
            raise UnsupportedGeomError(f"geom {name!r} is moved by joint {jname!r}, which the filter does not drive "
                                       "and which is not a limited hinge or slide joint: its reach is unknown")
        low, high = model.jnt_range[j]
        if kind == _SLIDE:
            values.append((low, high))
        else:
            values.append(tuple(np.linspace(low, high, _HINGE_SAMPLES)))
            step[i] = (high - low) / (_HINGE_SAMPLES - 1)
    if len(joints) > _MAX_SWEPT_JOINTS:
        raise UnsupportedGeomError(f"geom {name!r} is moved by {len(joints)} joints the filter does not drive; at most "
                                   f"{_MAX_SWEPT_JOINTS} are swept")
    core, radius = _core(model, geom)
    data = mujoco.MjData(model)
    swept, reach = [], np.zeros(len(joints))
    for setting in np.array(np.meshgrid(*values, indexing="ij")).reshape(len(joints), -1).T:
        data.qpos[:] = model.qpos0
        data.qpos[model.jnt_qposadr[joints]] = setting
        mujoco.mj_kinematics(model, data)
        world = data.geom_xpos[geom] + core @ data.geom_xmat[geom].reshape(3, 3).T
        swept.append((world - data.xpos[mount]) @ data.xmat[mount].reshape(3, 3))
        for i, j in enumerate(joints):  # the core points' distance from each hinge's axis
            rel = world - data.xanchor[j]
            along = rel @ data.xaxis[j]
            reach[i] = max(reach[i], float(np.sqrt(np.max(np.einsum("ij,ij->i", rel, rel) - along**2).clip(0.0))))
    # between two samples a point at distance r from a hinge's axis moves on an arc that leaves the
    # chord (inside the fitted capsule, which holds both ends) by at most r (1 − cos(δ/2))
    sagitta = float(np.sum((reach + radius) * (1.0 - np.cos(0.5 * step))))
    fitted = fit_capsule(np.concatenate(swept), enclosing_capsule(model, geom).source)
    return fitted._replace(radius=fitted.radius + radius + sagitta, body=mount)


def world_segments(data: mujoco.MjData, geom_ids: np.ndarray, local: np.ndarray,
                   body: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The capsules' axis end points in world coordinates [m], (S, 3) each, at ``data``'s
    kinematics (after ``mj_kinematics``, ``mj_step1`` or ``mj_forward``).

    Args:
        data: the model's data.
        geom_ids: (S,) the protected geoms.
        local: (S, 2, 3) each capsule's ends ``a``, ``b`` in its frame (:class:`Capsule`).
        body: (S,) -1 where the frame is the geom's, else the body whose frame it is.
    """
    geom_frame = body[:, None] < 0
    pos = np.where(geom_frame, data.geom_xpos[geom_ids], data.xpos[body])
    mat = np.where(geom_frame, data.geom_xmat[geom_ids], data.xmat[body]).reshape(-1, 3, 3)
    ends = pos[:, None, :] + np.einsum("sij,sej->sei", mat, local)
    return ends[:, 0], ends[:, 1]


def capsule_distances(points: np.ndarray, a: np.ndarray, b: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """(..., S) the signed distances [m] from ``points`` (..., 3) to the surfaces of the S capsules
    about the segments ``a``–``b`` ((S, 3) each) with radii ``radius`` (S,), negative inside: for
    instance the ends and radii :meth:`~c3bf_gym.safety.RobotDescription.capsule_segments` gives.
    A segment of length 0 is a sphere. Subtract a sphere's radius for its surface distance."""
    axis = b - a
    rel = points[..., None, :] - a
    length2 = np.einsum("si,si->s", axis, axis)
    along = np.clip(np.einsum("...si,si->...s", rel, axis) / np.where(length2 > 0.0, length2, 1.0), 0.0, 1.0)
    return np.linalg.norm(rel - along[..., None] * axis, axis=-1) - radius
