"""The obstacles the safety filter must keep off the arm, at the current physics time.

An :class:`Obstacles` holds up to ``capacity`` spheres as fixed arrays, which its owner keeps
current (in place: the filter's compiled kernel binds to these arrays once) before every filter
call: centre positions, velocities and accelerations in the world frame, radii and which slots are
active. The C3BF's guarantee assumes constant-velocity obstacles (zero acceleration); a known
acceleration enters the rows as ``a_o``.

* :class:`~c3bf_gym.envs.C3BFReachEnv` exposes its scenario's obstacles as one
  (``env.obstacles``), views of its own arrays.
* :class:`MocapSpheres` reads the positions and radii of MuJoCo mocap spheres; the caller supplies
  their velocities (mocap bodies have none in MuJoCo).
* Anything else: build an :class:`Obstacles` and write its arrays, or subclass it and override
  :meth:`Obstacles.refresh`, which the filter calls before reading them.
"""

from __future__ import annotations

from collections.abc import Iterable

import mujoco
import numpy as np

from c3bf_gym import validation

__all__ = ["MocapSpheres", "Obstacles"]


class Obstacles:
    """Up to ``capacity`` spheres, as arrays updated in place.

    Args:
        capacity: the number of slots K (>= 1); the filter sizes its QP for K active obstacles.
        position, velocity, acceleration: optional (K, 3) float64 arrays to use as the storage
            (e.g. views of a simulator's arrays) [m, m/s, m/s²]; new zeroed arrays otherwise.
        radius: optional (K,) float64 storage [m].
        active: optional (K,) bool storage; inactive slots add no rows.
        distances: optional (K, G) float64 array of each obstacle's signed surface distance to
            G arm geoms [m], kept current by the owner (e.g. MuJoCo distance sensors). The filter
            senses an obstacle when its smallest entry is within the sensing radius. None: the
            filter measures the distance to its protected geoms itself.

    Attributes:
        position, velocity, acceleration, radius, active, distances: the arrays above.

    Raises:
        ValueError: a given array of the wrong shape or dtype, or a capacity < 1.
    """

    def __init__(
        self,
        capacity: int,
        *,
        position: np.ndarray | None = None,
        velocity: np.ndarray | None = None,
        acceleration: np.ndarray | None = None,
        radius: np.ndarray | None = None,
        active: np.ndarray | None = None,
        distances: np.ndarray | None = None,
    ) -> None:
        k = validation.integer("capacity", capacity, low=1)
        self.capacity = k
        self.position = self._storage("position", position, (k, 3), np.float64)
        self.velocity = self._storage("velocity", velocity, (k, 3), np.float64)
        self.acceleration = self._storage("acceleration", acceleration, (k, 3), np.float64)
        self.radius = self._storage("radius", radius, (k,), np.float64)
        self.active = self._storage("active", active, (k,), np.bool_)
        if distances is not None and (distances.ndim != 2 or distances.shape[0] != k or distances.dtype != np.float64):
            raise ValueError(f"distances must be a ({k}, G) float64 array, got {distances.shape} {distances.dtype}")
        self.distances = distances

    @staticmethod
    def _storage(name: str, array: np.ndarray | None, shape: tuple[int, ...], dtype: type) -> np.ndarray:
        if array is None:
            return np.zeros(shape, dtype=dtype)
        if not isinstance(array, np.ndarray) or array.shape != shape or array.dtype != dtype:
            got = f"{array.shape} {array.dtype}" if isinstance(array, np.ndarray) else type(array).__name__
            raise ValueError(f"{name} must be a {shape} {np.dtype(dtype).name} array, got {got}")
        return array

    def set(self, slot: int, position: Iterable[float], radius: float, velocity: Iterable[float] = (0.0, 0.0, 0.0),
            acceleration: Iterable[float] = (0.0, 0.0, 0.0)) -> None:
        """Make ``slot`` an active sphere of ``radius`` [m] at ``position`` [m], moving with
        ``velocity`` [m/s] and ``acceleration`` [m/s²]; ValueError on non-finite values, a
        radius <= 0 or a slot out of range."""
        slot = validation.integer("slot", slot, low=0)
        if slot >= self.capacity:
            raise ValueError(f"slot must be < capacity {self.capacity}, got {slot}")
        values = {}
        for name, value in (("position", position), ("velocity", velocity), ("acceleration", acceleration)):
            vector = np.asarray(value, dtype=np.float64)
            if vector.shape != (3,) or not np.all(np.isfinite(vector)):
                raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
            values[name] = vector
        radius = validation.number("radius", radius, low=0.0, low_open=True, unit="m")
        self.position[slot] = values["position"]
        self.velocity[slot] = values["velocity"]
        self.acceleration[slot] = values["acceleration"]
        self.radius[slot] = radius
        self.active[slot] = True

    def clear(self, slot: int | None = None) -> None:
        """Deactivate ``slot`` (None: every slot)."""
        self.active[slice(None) if slot is None else slot] = False

    def refresh(self, data: mujoco.MjData) -> None:
        """Bring the arrays up to date with ``data``; called by the filter before every use. The
        base class's arrays are kept current by their owner, so this does nothing."""


class MocapSpheres(Obstacles):
    """Obstacles that are sphere geoms on MuJoCo mocap bodies.

    Positions (the geoms' world centres) and radii (``geom_size``) are read from the model and
    ``data`` at every filter call; velocities and accelerations are the caller's to set (MuJoCo's
    mocap bodies have none), e.g. ``spheres.velocity[i] = v`` while moving ``data.mocap_pos``
    by ``v dt`` per step. Every sphere is active unless :meth:`clear` deactivates it.

    Args:
        model: the compiled model.
        bodies: names (or ids) of mocap bodies, each with exactly one sphere geom.

    Raises:
        ValueError: an unknown body (the message lists the mocap bodies), a body that is not a
            mocap body, or one without exactly one sphere geom.
    """

    def __init__(self, model: mujoco.MjModel, bodies: Iterable[str | int]) -> None:
        mocap_bodies = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b) or f"#{b}"
                        for b in range(model.nbody) if model.body_mocapid[b] >= 0]  # fmt: skip
        geoms = []
        for body in bodies:
            index = body if isinstance(body, (int, np.integer)) else mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, str(body))
            if not 0 <= index < model.nbody or model.body_mocapid[index] < 0:
                raise ValueError(f"{body!r} is not a mocap body; the model's mocap bodies: {', '.join(mocap_bodies)}")
            spheres = np.flatnonzero((model.geom_bodyid == index) & (model.geom_type == mujoco.mjtGeom.mjGEOM_SPHERE))
            if len(spheres) != 1:
                raise ValueError(f"mocap body {body!r} must have exactly one sphere geom, it has {len(spheres)}")
            geoms.append(int(spheres[0]))
        if not geoms:
            raise ValueError(f"no mocap bodies given; the model's mocap bodies: {', '.join(mocap_bodies)}")
        super().__init__(len(geoms))
        self.geom_ids = np.array(geoms)
        self.active[:] = True
        self._model = model

    def refresh(self, data: mujoco.MjData) -> None:
        """Positions from ``data.geom_xpos`` and radii from ``model.geom_size`` (needs
        ``mj_kinematics``, which ``mj_step1`` and ``mj_forward`` run, after moving the bodies)."""
        np.take(data.geom_xpos, self.geom_ids, axis=0, out=self.position)
        np.take(self._model.geom_size[:, 0], self.geom_ids, out=self.radius)
