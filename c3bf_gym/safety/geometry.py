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
"""

from __future__ import annotations

from typing import NamedTuple

import mujoco
import numpy as np

__all__ = ["Capsule", "UnsupportedGeomError", "enclosing_capsule", "fit_capsule"]

_T = mujoco.mjtGeom


class UnsupportedGeomError(ValueError):
    """A geom with no enclosing capsule (a plane, a height field, an SDF); the message names it."""


class Capsule(NamedTuple):
    """A capsule in a geom's frame: the points within ``radius`` of the segment ``a``–``b``.

    Attributes:
        a, b: (3,) the segment's end points in the geom's frame [m] (equal for a sphere).
        radius: [m].
        source: the geom type it encloses ("capsule", "sphere", "cylinder", "ellipsoid", "box",
            "mesh").
    """

    a: np.ndarray
    b: np.ndarray
    radius: float
    source: str

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
