"""What the safety filter needs to know about a robot, read from any MuJoCo model.

:meth:`RobotDescription.from_model` reads the actuated joints, their torque limits, the protected
collision geoms, the tool site and the joint position and speed limits, and refuses a model the
filter cannot protect with an error that names the joint, actuator or geom at fault.

What the filter assumes of the model (and checks):

* every degree of freedom belongs to a hinge or slide joint of the arm and is driven by exactly
  one torque motor (``<motor>``: direct transmission to the joint, no activation dynamics, a
  fixed gain and no bias), so that the filter's torque is the model's joint force. Obstacles
  are not bodies with dofs: mocap bodies, or no bodies at all;
* every protected geom is on a body the joints move, and some joint can move it (not only turn
  it about its own axis). The filter protects the capsule that contains it
  (:func:`~c3bf_gym.safety.geometry.enclosing_capsule`: capsules and spheres as they are;
  cylinders, ellipsoids, boxes and meshes enclosed); :meth:`RobotDescription.describe` lists them;
* torque limits are finite and symmetric per joint: the tightest of the joint's
  ``actuatorfrcrange`` (which bounds the total actuator force, gravity compensation included),
  the actuator's ``forcerange`` and ``gear × ctrlrange``, each taken as ``min(-low, high)``.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import warnings

import mujoco
import numpy as np

from c3bf_gym import validation
from c3bf_gym.safety.geometry import Capsule, UnsupportedGeomError, enclosing_capsule

__all__ = ["RobotDescription", "UnprotectedGeometryWarning", "UnsupportedModelError"]

_SURFACES = (int(mujoco.mjtGeom.mjGEOM_PLANE), int(mujoco.mjtGeom.mjGEOM_HFIELD), int(mujoco.mjtGeom.mjGEOM_SDF))
_JOINT_TYPES = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))


class UnsupportedModelError(ValueError):
    """The model has something the safety filter cannot protect (the message names it)."""


class UnprotectedGeometryWarning(UserWarning):
    """Moving geometry that the filter will not protect, or cannot move away (the message names
    it and says why)."""


def _name(model: mujoco.MjModel, kind: mujoco.mjtObj, index: int) -> str:
    name = mujoco.mj_id2name(model, kind, index)
    return repr(name) if name else f"#{index} (unnamed)"


def _ids(model: mujoco.MjModel, kind: mujoco.mjtObj, names: Iterable[str | int], what: str) -> list[int]:
    """Indices of named (or indexed) objects; an unknown name lists the valid ones."""
    count = {mujoco.mjtObj.mjOBJ_GEOM: model.ngeom, mujoco.mjtObj.mjOBJ_BODY: model.nbody,
             mujoco.mjtObj.mjOBJ_SITE: model.nsite}[kind]  # fmt: skip
    out = []
    for name in names:
        index = name if isinstance(name, (int, np.integer)) and not isinstance(name, bool) else None
        if index is None:
            index = mujoco.mj_name2id(model, kind, str(name)) if isinstance(name, str) else -1
        if not 0 <= index < count:
            valid = [n for n in (mujoco.mj_id2name(model, kind, i) for i in range(count)) if n]
            raise UnsupportedModelError(f"unknown {what} {name!r}; the model's named {what}s: {', '.join(valid)}")
        out.append(int(index))
    return out


@dataclass(frozen=True, eq=False)
class RobotDescription:
    """An arm as the safety filter sees it. Build it with :meth:`from_model`.

    Attributes:
        n: number of joints (= the model's dofs).
        actuator_ids: (n,) the torque motor of each dof, in dof order.
        torque_limit: (n,) symmetric torque bound [N m or N] of each dof.
        geom_ids: (S,) the protected collision geoms.
        capsules: (S,) the capsule the filter protects for each of them, in the geom's frame
            (:class:`~c3bf_gym.safety.geometry.Capsule`).
        site_id: the tool site, or -1 without one.
        joint_range: (n, 2) joint position limits [rad or m]; rows of a joint without limits are
            ``(-inf, inf)``.
        joint_speed_limit: (n,) joint speed bound [rad/s or m/s], or None when not given.
        gear: (n,) each dof's motor gear (joint torque per unit of ``ctrl``).
        gravcomp_in_actuator: (n,) whether the dof's joint routes gravity compensation through
            its actuator (``actuatorgravcomp="true"``): then the joint torque is the motor's plus
            ``data.qfrc_gravcomp``.
    """

    n: int
    actuator_ids: np.ndarray
    torque_limit: np.ndarray
    geom_ids: np.ndarray
    capsules: tuple[Capsule, ...]
    site_id: int
    joint_range: np.ndarray
    joint_speed_limit: np.ndarray | None
    gear: np.ndarray
    gravcomp_in_actuator: np.ndarray

    @classmethod
    def from_model(
        cls,
        model: mujoco.MjModel,
        *,
        geoms: Iterable[str | int] | None = None,
        bodies: Iterable[str | int] | None = None,
        group: int | None = None,
        site: str | int | None = None,
        joint_speed_limit: float | Iterable[float] | None = None,
    ) -> RobotDescription:
        """Read the description of the arm in ``model``.

        Protected geoms: the union of ``geoms`` (names or ids), the geoms of ``bodies`` and the
        geoms of geom group ``group`` (0-5); with none of the three, every geom on a body the
        joints move that can collide (``contype`` or ``conaffinity`` nonzero), of any type but
        planes, height fields and SDFs. Each is protected as the capsule that contains it
        (:func:`~c3bf_gym.safety.geometry.enclosing_capsule`).

        Warns (:class:`UnprotectedGeometryWarning`), naming them: with the default selection, a
        moving body whose geoms all have collisions switched off (so none is protected), and a
        colliding geom left out because no joint can move it away (it lies on the axes of the
        hinges that move it).

        Args:
            model: a compiled MuJoCo model.
            geoms, bodies, group: the protected geoms (above).
            site: the tool site's name or id (None: none; the impedance controller needs one).
            joint_speed_limit: the joint speed bound [rad/s or m/s], one value or one per dof
                (None: none given; the filter's joint-speed rows then refuse to run).

        Raises:
            UnsupportedModelError: no actuators or no dofs; a dof without exactly one torque
                motor, or an actuator that is not a torque motor (named); a ball or free joint
                (named); a selected plane, height field or SDF geom (named), or one on a body no
                joint moves, or that no joint can move away; no protected geom; an unknown name;
                a torque limit that is missing or not finite (named); a tool site on a body no
                joint moves (named).
        """
        if model.nu == 0:
            raise UnsupportedModelError("the model has no actuators: the filter needs a torque motor on every joint")
        if model.nv == 0:
            raise UnsupportedModelError("the model has no degrees of freedom")
        for j in range(model.njnt):
            if int(model.jnt_type[j]) not in _JOINT_TYPES:
                kind = mujoco.mjtJoint(model.jnt_type[j]).name.removeprefix("mjJNT_").lower()
                raise UnsupportedModelError(
                    f"joint {_name(model, mujoco.mjtObj.mjOBJ_JOINT, j)} is a {kind} joint: the filter supports hinge "
                    "and slide joints only (obstacles must be mocap bodies, not free bodies)"
                )
        actuator_of = np.full(model.nv, -1)
        for a in range(model.nu):
            label = f"actuator {_name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, a)}"
            trn = int(model.actuator_trntype[a])
            if trn not in (int(mujoco.mjtTrn.mjTRN_JOINT), int(mujoco.mjtTrn.mjTRN_JOINTINPARENT)):
                raise UnsupportedModelError(f"{label} does not drive a joint directly (transmission "
                                            f"{mujoco.mjtTrn(trn).name}): the filter needs torque motors")  # fmt: skip
            motor = (int(model.actuator_dyntype[a]) == int(mujoco.mjtDyn.mjDYN_NONE)
                     and int(model.actuator_gaintype[a]) == int(mujoco.mjtGain.mjGAIN_FIXED)
                     and int(model.actuator_biastype[a]) == int(mujoco.mjtBias.mjBIAS_NONE))  # fmt: skip
            if not motor:
                raise UnsupportedModelError(
                    f"{label} is not a torque motor (position, velocity or other servos add feedback the filter's "
                    "torque would not control): use <motor>"
                )
            dof = int(model.jnt_dofadr[model.actuator_trnid[a, 0]])
            if actuator_of[dof] >= 0:
                raise UnsupportedModelError(f"{label} drives a joint that actuator "
                                            f"{_name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, actuator_of[dof])} drives too")  # fmt: skip
            actuator_of[dof] = a
        for dof in np.flatnonzero(actuator_of < 0):
            joint = _name(model, mujoco.mjtObj.mjOBJ_JOINT, model.dof_jntid[dof])
            raise UnsupportedModelError(f"joint {joint} has no torque motor: the filter needs one on every joint")
        limit = np.array([cls._torque_limit(model, int(a)) for a in actuator_of])

        chosen: set[int] = set()
        if geoms is not None:
            chosen.update(_ids(model, mujoco.mjtObj.mjOBJ_GEOM, geoms, "geom"))
        if bodies is not None:
            for body in _ids(model, mujoco.mjtObj.mjOBJ_BODY, bodies, "body"):
                chosen.update(int(g) for g in np.flatnonzero(model.geom_bodyid == body))
        if group is not None:
            group = validation.integer("group", group, low=0)
            chosen.update(int(g) for g in np.flatnonzero(model.geom_group == group))
        explicit = geoms is not None or bodies is not None or group is not None
        if not explicit:
            chosen = cls._default_geoms(model)
        for g in sorted(chosen):
            label = f"geom {_name(model, mujoco.mjtObj.mjOBJ_GEOM, g)}"
            if not model.body_dofnum[cls._root_chain(model, model.geom_bodyid[g])].any():
                raise UnsupportedModelError(f"{label} is on a body no joint moves: nothing the filter does can move it "
                                            "away from an obstacle; leave it out")  # fmt: skip
        capsules = {}
        for g in sorted(chosen):
            try:
                capsules[g] = enclosing_capsule(model, g)
            except UnsupportedGeomError as error:
                raise UnsupportedModelError(str(error)) from None
        frozen = [g for g in sorted(chosen) if cls._immovable(model, g, capsules[g])]
        for g in frozen:
            label = f"geom {_name(model, mujoco.mjtObj.mjOBJ_GEOM, g)}"
            why = (f"{label} lies on the axis of the joints that move it: they only turn it about itself, so nothing "
                   "the filter does can move it away from an obstacle")
            if explicit:
                raise UnsupportedModelError(f"{why}; leave it out")
            warnings.warn(f"{why}; it is not protected", UnprotectedGeometryWarning, stacklevel=2)
            chosen.discard(g)
        if not chosen:
            raise UnsupportedModelError("no protected geom: select geoms by geoms, bodies or group")

        site_id = -1 if site is None else _ids(model, mujoco.mjtObj.mjOBJ_SITE, [site], "site")[0]
        if site_id >= 0 and not model.body_dofnum[cls._root_chain(model, model.site_bodyid[site_id])].any():
            body = _name(model, mujoco.mjtObj.mjOBJ_BODY, model.site_bodyid[site_id])
            raise UnsupportedModelError(f"site {_name(model, mujoco.mjtObj.mjOBJ_SITE, site_id)} is on body {body}, "
                                        "which no joint moves: name a site on the arm's last link")  # fmt: skip
        joint_range = np.tile([-np.inf, np.inf], (model.nv, 1))
        for dof in range(model.nv):
            j = model.dof_jntid[dof]
            if model.jnt_limited[j]:
                joint_range[dof] = model.jnt_range[j]
        speed = None
        if joint_speed_limit is not None:
            values = np.broadcast_to(np.asarray(joint_speed_limit, dtype=float), (model.nv,)).copy() \
                if np.ndim(joint_speed_limit) == 0 else np.asarray(list(joint_speed_limit), dtype=float)  # fmt: skip
            if values.shape != (model.nv,) or not np.all(np.isfinite(values) & (values > 0)):
                raise UnsupportedModelError(f"joint_speed_limit must be one finite number > 0 or {model.nv} of them "
                                            f"(one per dof), got {joint_speed_limit!r}")  # fmt: skip
            speed = values
        for array in (limit, joint_range) + (() if speed is None else (speed,)):
            array.setflags(write=False)
        ids = np.array(sorted(chosen))
        ids.setflags(write=False)
        actuators = actuator_of.astype(int)
        actuators.setflags(write=False)
        gear = model.actuator_gear[actuators, 0].copy()
        gravcomp = model.jnt_actgravcomp[model.dof_jntid].astype(bool)
        for array in (gear, gravcomp):
            array.setflags(write=False)
        return cls(int(model.nv), actuators, limit, ids, tuple(capsules[g] for g in ids), int(site_id), joint_range,
                   speed, gear, gravcomp)

    def write_ctrl(self, model: mujoco.MjModel, data: mujoco.MjData, tau: np.ndarray) -> None:
        """Set ``data.ctrl`` so that the arm's motors apply the joint torques ``tau`` (n,) [N m or
        N] (the filter's output), in dof order: ``ctrl[actuator_ids] = (tau − g) / gear``, with
        ``g = data.qfrc_gravcomp`` on joints that route gravity compensation through their
        actuator (current after ``mj_step1`` or ``mj_forward``) and 0 elsewhere. Other actuators'
        ``ctrl`` is left as it is.

        Raises:
            ValueError: ``tau`` not of shape (n,) or not finite; a ``ctrl`` outside its actuator's
                ``ctrlrange``, which MuJoCo would clamp, so the arm would not get ``tau`` (names
                the actuator).
        """
        tau = np.asarray(tau, dtype=float)
        if tau.shape != (self.n,) or not np.all(np.isfinite(tau)):
            raise ValueError(f"tau must be {self.n} finite joint torques, got {tau!r}")
        ctrl = tau - np.where(self.gravcomp_in_actuator, data.qfrc_gravcomp, 0.0)
        ctrl /= self.gear
        low, high = model.actuator_ctrlrange[self.actuator_ids].T
        limited = model.actuator_ctrllimited[self.actuator_ids].astype(bool)
        outside = limited & ((ctrl < low - 1e-9 * np.abs(low)) | (ctrl > high + 1e-9 * np.abs(high)))
        if outside.any():
            a = int(self.actuator_ids[np.flatnonzero(outside)[0]])
            raise ValueError(f"actuator {_name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, a)} would need ctrl "
                             f"{ctrl[outside][0]:.6g}, outside its ctrlrange {tuple(model.actuator_ctrlrange[a])}")  # fmt: skip
        data.ctrl[self.actuator_ids] = ctrl

    @classmethod
    def _default_geoms(cls, model: mujoco.MjModel) -> set[int]:
        """Every colliding geom (not a plane, height field or SDF) on a moving body; warns naming
        the moving bodies that carry geoms but none that collides."""
        moving = {b for b in range(1, model.nbody) if model.body_dofnum[cls._root_chain(model, b)].any()}
        on_moving = [g for g in range(model.ngeom) if int(model.geom_bodyid[g]) in moving]
        chosen = {g for g in on_moving if int(model.geom_type[g]) not in _SURFACES
                  and (model.geom_contype[g] or model.geom_conaffinity[g])}  # fmt: skip
        bare = sorted({int(model.geom_bodyid[g]) for g in on_moving} - {int(model.geom_bodyid[g]) for g in chosen})
        if bare:
            names = ", ".join(_name(model, mujoco.mjtObj.mjOBJ_BODY, b) for b in bare)
            warnings.warn(f"bodies {names} move with the arm but none of their geoms can collide (contype = "
                          "conaffinity = 0), so the default selection protects none of them; pass bodies=, geoms= or "
                          "group= to protect them", UnprotectedGeometryWarning, stacklevel=3)  # fmt: skip
        return chosen

    @staticmethod
    def _immovable(model: mujoco.MjModel, geom: int, capsule: Capsule) -> bool:
        """Whether no joint can translate either end of ``capsule`` (on ``geom``), checked at the
        model's reference configuration and at one turned by 0.3 rad (0.03 m) per joint (within
        the limits): the geom lies on the axes of every hinge that moves it."""
        data = mujoco.MjData(model)
        jac = np.zeros((3, model.nv))
        for offset in (0.0, 0.3):
            data.qpos[:] = model.qpos0
            for j in range(model.njnt):
                step = offset if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE else 0.1 * offset
                low, high = model.jnt_range[j] if model.jnt_limited[j] else (-np.inf, np.inf)
                adr = model.jnt_qposadr[j]
                data.qpos[adr] = np.clip(data.qpos[adr] + step, low, high)
            mujoco.mj_kinematics(model, data)
            mujoco.mj_comPos(model, data)
            xmat = data.geom_xmat[geom].reshape(3, 3)
            for end in (capsule.a, capsule.b):
                mujoco.mj_jac(model, data, jac, None, data.geom_xpos[geom] + xmat @ end, model.geom_bodyid[geom])
                if np.abs(jac).max() > 1e-9:
                    return False
        return True

    def describe(self, model: mujoco.MjModel) -> str:
        """A table of the protected geoms (name, body, type) and the capsules the filter protects
        in their place (radius, length) [m]: one line each."""
        lines = [f"{'geom':<24} {'body':<20} {'type':<10} {'radius':>8} {'length':>8}"]
        for g, capsule in zip(self.geom_ids, self.capsules, strict=True):
            geom = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or f"#{g}"
            body = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, model.geom_bodyid[g]) or f"#{model.geom_bodyid[g]}"
            lines.append(f"{geom:<24} {body:<20} {capsule.source:<10} {capsule.radius:8.4f} "
                         f"{2 * capsule.half_length:8.4f}")  # fmt: skip
        return "\n".join(lines)

    @staticmethod
    def _root_chain(model: mujoco.MjModel, body: int) -> list[int]:
        """``body`` and its ancestors up to (not including) the world body."""
        chain = []
        while body > 0:
            chain.append(int(body))
            body = model.body_parentid[body]
        return chain

    @staticmethod
    def _torque_limit(model: mujoco.MjModel, a: int) -> float:
        """The tightest symmetric bound on actuator ``a``'s joint force (module docstring)."""
        bounds = []
        joint = model.actuator_trnid[a, 0]
        if model.jnt_actfrclimited[joint]:
            bounds.append(model.jnt_actfrcrange[joint])
        if model.actuator_forcelimited[a]:
            bounds.append(model.actuator_forcerange[a])
        if model.actuator_ctrllimited[a]:
            gear = abs(model.actuator_gear[a, 0])
            bounds.append(np.sort(model.actuator_ctrlrange[a] * gear))
        limits = [min(-low, high) for low, high in bounds]
        label = f"actuator {_name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, a)}"
        if not limits:
            raise UnsupportedModelError(f"{label} has no torque limit: set its ctrlrange or forcerange, or the joint's "
                                        "actuatorfrcrange")  # fmt: skip
        value = float(min(limits))
        if not (np.isfinite(value) and value > 0):
            raise UnsupportedModelError(f"{label}'s torque limits do not contain zero or are not finite "
                                        f"({[tuple(b) for b in bounds]})")  # fmt: skip
        return value

    def joint_limited(self) -> np.ndarray:
        """(n,) whether each dof has finite position limits."""
        return np.all(np.isfinite(self.joint_range), axis=1)

    def require_joint_limits(self, model: mujoco.MjModel) -> None:
        """Raise :class:`UnsupportedModelError` naming the first joint without position limits,
        or when no joint speed limit was given (the joint-limit rows need both)."""
        for dof in np.flatnonzero(~self.joint_limited()):
            joint = _name(model, mujoco.mjtObj.mjOBJ_JOINT, model.dof_jntid[dof])
            raise UnsupportedModelError(f"joint {joint} has no position limits (limited=\"true\" range=...), which the "
                                        "filter's joint-limit rows need; add them, or build the filter with "
                                        "joint_limits=False")  # fmt: skip
        if self.joint_speed_limit is None:
            raise UnsupportedModelError("the joint-limit rows need joint speed limits: pass joint_speed_limit= to "
                                        "RobotDescription.from_model, or build the filter with joint_limits=False")  # fmt: skip
