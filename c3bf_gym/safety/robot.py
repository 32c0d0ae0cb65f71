"""What the safety filter needs to know about a robot, read from any MuJoCo model.

:meth:`RobotDescription.from_model` reads the arm's joints, their torque limits, the protected
collision geoms, the tool site, the joint position and speed limits, and what the filter cannot
predict, and refuses a model the filter cannot protect with an error that names the joint,
actuator or geom at fault.

What the filter assumes of the model (and checks):

* the arm's joints (all of the model's, or those named by ``joints=``) are hinge or slide joints,
  each driven by exactly one torque motor (``<motor>``: direct transmission to the joint, no
  activation dynamics, a fixed gain and no bias), so that the filter's torque is the model's
  joint force;
* every other degree of freedom (a gripper's fingers, free bodies, the joints of other
  mechanisms) is left to the model. Its actuators' forces are not known when the filter runs,
  so each must be bounded: the filter's rows hold for every force within the bounds
  (:attr:`RobotDescription.unmodelled_force`). Obstacles are mocap bodies, or no bodies at all;
* every protected geom is on a body the arm's joints move, and they can move it (not only turn
  it about its own axis). The filter protects the capsule that contains it
  (:func:`~c3bf_gym.safety.geometry.enclosing_capsule`: capsules and spheres as they are;
  cylinders, ellipsoids, boxes and meshes enclosed); :meth:`RobotDescription.describe` lists them;
* torque limits are finite and symmetric per joint: the tightest of the joint's
  ``actuatorfrcrange`` (which bounds the total actuator force, gravity compensation included),
  ``gear × forcerange`` and ``gear × gain × ctrlrange`` of its motor, each taken as
  ``min(-low, high)``.

Contact and equality-constraint forces on the arm are not modelled: the arm must not touch
things, which is what the filter is for.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable
from dataclasses import dataclass

import mujoco
import numpy as np

from c3bf_gym import validation
from c3bf_gym.safety.geometry import Capsule, UnsupportedGeomError, protected_capsule, world_segments

__all__ = ["RobotDescription", "UnprotectedGeometryWarning", "UnsupportedModelError", "floor_height"]

_SURFACES = (int(mujoco.mjtGeom.mjGEOM_PLANE), int(mujoco.mjtGeom.mjGEOM_HFIELD), int(mujoco.mjtGeom.mjGEOM_SDF))
_JOINT_TYPES = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
_DIRECT = (int(mujoco.mjtTrn.mjTRN_JOINT), int(mujoco.mjtTrn.mjTRN_JOINTINPARENT))
_JOINT_DOFS = {int(mujoco.mjtJoint.mjJNT_FREE): 6, int(mujoco.mjtJoint.mjJNT_BALL): 3}  # hinges, slides: 1
_OBJ = mujoco.mjtObj


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
    count = {_OBJ.mjOBJ_GEOM: model.ngeom, _OBJ.mjOBJ_BODY: model.nbody, _OBJ.mjOBJ_SITE: model.nsite,
             _OBJ.mjOBJ_JOINT: model.njnt}[kind]  # fmt: skip
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


def _is_motor(model: mujoco.MjModel, a: int) -> bool:
    """A torque motor: no activation dynamics, a fixed gain and no bias."""
    return (int(model.actuator_dyntype[a]) == int(mujoco.mjtDyn.mjDYN_NONE)
            and int(model.actuator_gaintype[a]) == int(mujoco.mjtGain.mjGAIN_FIXED)
            and int(model.actuator_biastype[a]) == int(mujoco.mjtBias.mjBIAS_NONE))  # fmt: skip


def floor_height(model: mujoco.MjModel) -> float | None:
    """The height [m] of the floor the filter keeps the arm above: the first plane geom of the
    world body that stands upright (identity orientation); None without one."""
    plane = int(mujoco.mjtGeom.mjGEOM_PLANE)
    for g in range(model.ngeom):
        if model.geom_type[g] == plane and model.geom_bodyid[g] == 0 and np.allclose(model.geom_quat[g], (1, 0, 0, 0)):
            return float(model.geom_pos[g, 2])
    return None


def _chain(model: mujoco.MjModel, body: int) -> np.ndarray:
    """(nv,) bool: the dofs that move ``body`` (its own and its ancestors')."""
    mask = np.zeros(model.nv, dtype=bool)
    while body > 0:
        mask[model.body_dofadr[body] : model.body_dofadr[body] + model.body_dofnum[body]] = True
        body = model.body_parentid[body]
    return mask


@dataclass(frozen=True, eq=False)
class RobotDescription:
    """An arm as the safety filter sees it. Build it with :meth:`from_model`.

    Attributes:
        n: number of the arm's joints (its dofs; the filter's torque has this length).
        nv: the model's number of dofs (``n`` plus those left to the model).
        dof_ids: (n,) the arm's dofs, ascending.
        actuator_ids: (n,) the torque motor of each of the arm's dofs.
        torque_limit: (n,) symmetric torque bound [N m or N] of each of the arm's dofs.
        geom_ids: (S,) the protected collision geoms.
        capsules: (S,) the capsule the filter protects for each of them, in the geom's frame
            (:class:`~c3bf_gym.safety.geometry.Capsule`).
        site_id: the tool site, or -1 without one.
        joint_range: (n, 2) joint position limits [rad or m]; rows of a joint without limits are
            ``(-inf, inf)``.
        joint_speed_limit: (n,) joint speed bound [rad/s or m/s], or None when not given.
        gear: (n,) joint torque per unit of ``ctrl`` of each arm dof's motor: its gear times its
            gain (``gainprm[0]``, 1 for ``<motor>``).
        gravcomp_in_actuator: (n,) whether the dof's joint routes gravity compensation through
            its actuator (``actuatorgravcomp="true"``): then the joint torque is the motor's plus
            ``data.qfrc_gravcomp``.
        unmodelled_force: (nv,) per dof of the model, a bound on the generalised force [N m or N]
            the filter cannot predict: the joint's dry friction (``frictionloss``) and, on dofs
            that are not the arm's, the force their actuators may apply. The rows hold for every
            such force within the bounds.
    """

    n: int
    nv: int
    dof_ids: np.ndarray
    actuator_ids: np.ndarray
    torque_limit: np.ndarray
    geom_ids: np.ndarray
    capsules: tuple[Capsule, ...]
    site_id: int
    joint_range: np.ndarray
    joint_speed_limit: np.ndarray | None
    gear: np.ndarray
    gravcomp_in_actuator: np.ndarray
    unmodelled_force: np.ndarray

    @classmethod
    def from_model(
        cls,
        model: mujoco.MjModel,
        *,
        joints: Iterable[str | int] | None = None,
        geoms: Iterable[str | int] | None = None,
        bodies: Iterable[str | int] | None = None,
        group: int | None = None,
        site: str | int | None = None,
        joint_speed_limit: float | Iterable[float] | None = None,
    ) -> RobotDescription:
        """Read the description of the arm in ``model``.

        The arm: the joints ``joints`` (names or ids), or every joint of the model. The filter
        sets their torques; the model's other dofs keep whatever their own actuators do, within
        those actuators' force bounds.

        Protected geoms: the union of ``geoms`` (names or ids), the geoms of ``bodies`` and the
        geoms of geom group ``group`` (0-5); with none of the three, every geom on a body the
        arm's joints move that can collide (``contype`` or ``conaffinity`` nonzero), of any type
        but planes, height fields and SDFs (a gripper on the arm included). Each is protected as
        the capsule that contains it (:func:`~c3bf_gym.safety.geometry.enclosing_capsule`).

        Warns (:class:`UnprotectedGeometryWarning`), naming them: with the default selection, a
        body the arm moves whose geoms all have collisions switched off (so none is protected),
        and a colliding geom left out because the arm's joints cannot move it away (it lies on
        the axes of the hinges that move it).

        Args:
            model: a compiled MuJoCo model.
            joints: the arm's joints (None: all of the model's).
            geoms, bodies, group: the protected geoms (above).
            site: the tool site's name or id (None: none; the impedance controller needs one).
            joint_speed_limit: the joint speed bound [rad/s or m/s], one value or one per arm dof
                (None: none given; the filter's joint-speed rows then refuse to run).

        Raises:
            UnsupportedModelError: no actuators or no dofs; an arm joint that is not a hinge or
                slide joint, or without exactly one torque motor, or an actuator on it that is not
                a torque motor (named); an actuator on another dof whose force has no bound, or
                that does not drive a joint directly (named); a selected plane, height field or
                SDF geom (named), or one the arm's joints do not move, or cannot move away; no
                protected geom; an unknown name; a torque limit that is missing or not finite
                (named); a tool site the arm's joints do not move (named).
        """
        if model.nu == 0:
            raise UnsupportedModelError("the model has no actuators: the filter needs a torque motor on every joint")
        if model.nv == 0:
            raise UnsupportedModelError("the model has no degrees of freedom")
        dofs = cls._arm_dofs(model, joints)
        actuators = cls._motors(model, dofs, hint=joints is None)
        limit = np.array([cls._torque_limit(model, int(a)) for a in actuators])
        ids, capsules = cls._protected(model, dofs, geoms, bodies, group)
        site_id = -1 if site is None else _ids(model, _OBJ.mjOBJ_SITE, [site], "site")[0]
        if site_id >= 0 and not _chain(model, model.site_bodyid[site_id])[dofs].any():
            body = _name(model, _OBJ.mjOBJ_BODY, model.site_bodyid[site_id])
            raise UnsupportedModelError(f"site {_name(model, _OBJ.mjOBJ_SITE, site_id)} is on body {body}, which the "
                                        "arm's joints do not move: name a site on the arm's last link")  # fmt: skip
        joint_range = np.tile([-np.inf, np.inf], (len(dofs), 1))
        for i, dof in enumerate(dofs):
            j = model.dof_jntid[dof]
            if model.jnt_limited[j]:
                joint_range[i] = model.jnt_range[j]
        speed = cls._speed_limit(joint_speed_limit, len(dofs))
        gear = model.actuator_gear[actuators, 0] * model.actuator_gainprm[actuators, 0]  # joint torque per ctrl
        gravcomp = model.jnt_actgravcomp[model.dof_jntid[dofs]].astype(bool)
        unmodelled = model.dof_frictionloss.astype(float) + cls._other_forces(model, dofs)
        for array in (dofs, actuators, limit, ids, joint_range, gear, gravcomp, unmodelled, speed):
            if array is not None:
                array.setflags(write=False)
        return cls(len(dofs), int(model.nv), dofs, actuators, limit, ids, capsules, int(site_id), joint_range, speed,
                   gear, gravcomp, unmodelled)

    @staticmethod
    def _arm_dofs(model: mujoco.MjModel, joints: Iterable[str | int] | None) -> np.ndarray:
        """The dofs of ``joints`` (all joints when None), ascending; refuses other joint types."""
        chosen = range(model.njnt) if joints is None else sorted(set(_ids(model, _OBJ.mjOBJ_JOINT, joints, "joint")))
        if not chosen:
            raise UnsupportedModelError("joints= names no joint: name the arm's joints (or pass None for all of them)")
        for j in chosen:
            if int(model.jnt_type[j]) not in _JOINT_TYPES:
                kind = mujoco.mjtJoint(model.jnt_type[j]).name.removeprefix("mjJNT_").lower()
                raise UnsupportedModelError(
                    f"joint {_name(model, _OBJ.mjOBJ_JOINT, j)} is a {kind} joint: the arm's joints must be hinge or "
                    "slide joints (name the arm's joints with joints=; obstacles must be mocap bodies)"
                )
        return np.array(sorted(int(model.jnt_dofadr[j]) for j in chosen), dtype=int)

    @staticmethod
    def _motors(model: mujoco.MjModel, dofs: np.ndarray, hint: bool) -> np.ndarray:
        """(n,) the one torque motor of each of the arm's dofs."""
        actuator_of = dict.fromkeys(dofs.tolist(), -1)
        for a in range(model.nu):
            if int(model.actuator_trntype[a]) not in _DIRECT:
                continue
            dof = int(model.jnt_dofadr[model.actuator_trnid[a, 0]])
            if dof not in actuator_of:
                continue
            label = f"actuator {_name(model, _OBJ.mjOBJ_ACTUATOR, a)}"
            if not _is_motor(model, a):
                raise UnsupportedModelError(
                    f"{label} is not a torque motor (position, velocity or other servos add feedback the filter's "
                    "torque would not control): use <motor>"
                )
            if actuator_of[dof] >= 0:
                raise UnsupportedModelError(f"{label} drives a joint that actuator "
                                            f"{_name(model, _OBJ.mjOBJ_ACTUATOR, actuator_of[dof])} drives too")  # fmt: skip
            actuator_of[dof] = a
        for dof, a in actuator_of.items():
            if a < 0:
                joint = _name(model, _OBJ.mjOBJ_JOINT, model.dof_jntid[dof])
                extra = " (or name the arm's joints with joints=, leaving this one to the model)" if hint else ""
                raise UnsupportedModelError(f"joint {joint} has no torque motor: the filter needs one on every arm "
                                            f"joint{extra}")  # fmt: skip
        return np.array(list(actuator_of.values()), dtype=int)

    @classmethod
    def _other_forces(cls, model: mujoco.MjModel, dofs: np.ndarray) -> np.ndarray:
        """(nv,) the largest force the actuators of the dofs that are not the arm's can apply:
        ``max|forcerange|`` when force-limited, else ``|gear| max|ctrlrange|`` for a torque motor,
        capped by the joint's ``actuatorfrcrange``; 0 on the arm's dofs."""
        bound = np.zeros(model.nv)
        arm = set(dofs.tolist())
        for a in range(model.nu):
            label = f"actuator {_name(model, _OBJ.mjOBJ_ACTUATOR, a)}"
            trn = int(model.actuator_trntype[a])
            if trn in _DIRECT and int(model.jnt_dofadr[model.actuator_trnid[a, 0]]) in arm:
                continue
            if trn not in _DIRECT:
                raise UnsupportedModelError(f"{label} does not drive a joint directly (transmission "
                                            f"{mujoco.mjtTrn(trn).name}): the filter cannot bound its force on the "
                                            "arm")  # fmt: skip
            joint = model.actuator_trnid[a, 0]
            gear = abs(model.actuator_gear[a, 0])
            if model.actuator_forcelimited[a]:  # the actuator's force, which its gear scales onto the joint
                force = gear * np.abs(model.actuator_forcerange[a]).max()
            elif _is_motor(model, a) and model.actuator_ctrllimited[a]:
                force = gear * abs(model.actuator_gainprm[a, 0]) * np.abs(model.actuator_ctrlrange[a]).max()
            else:
                force = np.inf
            if model.jnt_actfrclimited[joint]:
                force = min(force, np.abs(model.jnt_actfrcrange[joint]).max())
            if not np.isfinite(force):
                raise UnsupportedModelError(f"{label} drives joint {_name(model, _OBJ.mjOBJ_JOINT, joint)}, which is "
                                            "not the arm's, with no force bound: set its forcerange (or the joint's "
                                            "actuatorfrcrange), so the filter can allow for it")  # fmt: skip
            dof = int(model.jnt_dofadr[joint])
            width = _JOINT_DOFS.get(int(model.jnt_type[joint]), 1)
            bound[dof : dof + width] += force
        return bound

    @classmethod
    def _protected(cls, model: mujoco.MjModel, dofs: np.ndarray, geoms, bodies, group) -> tuple[np.ndarray, tuple]:
        """The protected geoms (ascending) and their enclosing capsules (:meth:`from_model`)."""
        chosen: set[int] = set()
        if geoms is not None:
            chosen.update(_ids(model, _OBJ.mjOBJ_GEOM, geoms, "geom"))
        if bodies is not None:
            for body in _ids(model, _OBJ.mjOBJ_BODY, bodies, "body"):
                chosen.update(int(g) for g in np.flatnonzero(model.geom_bodyid == body))
        if group is not None:
            group = validation.integer("group", group, low=0)
            chosen.update(int(g) for g in np.flatnonzero(model.geom_group == group))
        explicit = geoms is not None or bodies is not None or group is not None
        if not explicit:
            chosen = cls._default_geoms(model, dofs)
        for g in sorted(chosen):
            if not _chain(model, model.geom_bodyid[g])[dofs].any():
                raise UnsupportedModelError(f"geom {_name(model, _OBJ.mjOBJ_GEOM, g)} is on a body the arm's joints "
                                            "do not move: nothing the filter does can move it away from an obstacle; "
                                            "leave it out")  # fmt: skip
        capsules = {}
        for g in sorted(chosen):
            try:
                capsules[g] = protected_capsule(model, g, dofs)
            except UnsupportedGeomError as error:
                raise UnsupportedModelError(str(error)) from None
        for g in [g for g in sorted(chosen) if cls._immovable(model, dofs, g, capsules[g])]:
            why = (f"geom {_name(model, _OBJ.mjOBJ_GEOM, g)} lies on the axis of the joints that move it: they only "
                   "turn it about itself, so nothing the filter does can move it away from an obstacle")
            if explicit:
                raise UnsupportedModelError(f"{why}; leave it out")
            warnings.warn(f"{why}; it is not protected", UnprotectedGeometryWarning, stacklevel=3)
            chosen.discard(g)
        if not chosen:
            raise UnsupportedModelError("no protected geom: select geoms by geoms, bodies or group")
        ids = np.array(sorted(chosen), dtype=int)
        return ids, tuple(capsules[g] for g in ids)

    @staticmethod
    def _speed_limit(value: float | Iterable[float] | None, n: int) -> np.ndarray | None:
        """The joint speed limits (n,) from one value or n of them (None: None)."""
        if value is None:
            return None
        values = np.full(n, float(value)) if np.ndim(value) == 0 else np.asarray(list(value), dtype=float)
        if values.shape != (n,) or not np.all(np.isfinite(values) & (values > 0)):
            raise UnsupportedModelError(f"joint_speed_limit must be one finite number > 0 or {n} of them (one per arm "
                                        f"dof), got {value!r}")  # fmt: skip
        return values

    def write_ctrl(self, model: mujoco.MjModel, data: mujoco.MjData, tau: np.ndarray) -> None:
        """Set ``data.ctrl`` so that the arm's motors apply the joint torques ``tau`` (n,) [N m or
        N] (the filter's output), in dof order: ``ctrl[actuator_ids] = (tau − g) / gear``, with
        ``g = data.qfrc_gravcomp`` on joints that route gravity compensation through their
        actuator (current after ``mj_step1`` or ``mj_forward``) and 0 elsewhere. Other actuators'
        ``ctrl`` is left as it is.

        A joint that routes gravity compensation through its actuator needs a ``ctrlrange`` with
        room for that torque on top of ``torque_limit`` (``assets/ur5e.xml`` gives ``ctrlrange``
        twice ``actuatorfrcrange``, which then bounds the total): the torque limit is read from the
        joint's force bounds, and ``ctrl`` must carry ``tau − g``.

        Raises:
            ValueError: ``tau`` not of shape (n,) or not finite; a ``ctrl`` outside its actuator's
                ``ctrlrange``, which MuJoCo would clamp, so the arm would not get ``tau`` (names
                the actuator).
        """
        tau = np.asarray(tau, dtype=float)
        if tau.shape != (self.n,) or not np.all(np.isfinite(tau)):
            raise ValueError(f"tau must be {self.n} finite joint torques, got {tau!r}")
        ctrl = tau - np.where(self.gravcomp_in_actuator, data.qfrc_gravcomp[self.dof_ids], 0.0)
        ctrl /= self.gear
        low, high = model.actuator_ctrlrange[self.actuator_ids].T
        limited = model.actuator_ctrllimited[self.actuator_ids].astype(bool)
        outside = limited & ((ctrl < low - 1e-9 * np.abs(low)) | (ctrl > high + 1e-9 * np.abs(high)))
        if outside.any():
            a = int(self.actuator_ids[np.flatnonzero(outside)[0]])
            raise ValueError(f"actuator {_name(model, _OBJ.mjOBJ_ACTUATOR, a)} would need ctrl "
                             f"{ctrl[outside][0]:.6g}, outside its ctrlrange {tuple(model.actuator_ctrlrange[a])}")  # fmt: skip
        data.ctrl[self.actuator_ids] = ctrl

    @staticmethod
    def _default_geoms(model: mujoco.MjModel, dofs: np.ndarray) -> set[int]:
        """Every colliding geom (not a plane, height field or SDF) on a body the arm's ``dofs``
        move; warns naming such bodies that carry geoms but none that collides."""
        moving = {b for b in range(1, model.nbody) if _chain(model, b)[dofs].any()}
        on_moving = [g for g in range(model.ngeom) if int(model.geom_bodyid[g]) in moving]
        chosen = {g for g in on_moving if int(model.geom_type[g]) not in _SURFACES
                  and (model.geom_contype[g] or model.geom_conaffinity[g])}  # fmt: skip
        bare = sorted({int(model.geom_bodyid[g]) for g in on_moving} - {int(model.geom_bodyid[g]) for g in chosen})
        if bare:
            names = ", ".join(_name(model, _OBJ.mjOBJ_BODY, b) for b in bare)
            warnings.warn(f"bodies {names} move with the arm but none of their geoms can collide (contype = "
                          "conaffinity = 0), so the default selection protects none of them; pass bodies=, geoms= or "
                          "group= to protect them", UnprotectedGeometryWarning, stacklevel=4)  # fmt: skip
        return chosen

    @staticmethod
    def _immovable(model: mujoco.MjModel, dofs: np.ndarray, geom: int, capsule: Capsule) -> bool:
        """Whether the arm's ``dofs`` cannot translate either end of ``capsule`` (on ``geom``),
        checked at the model's reference configuration and at one turned by 0.3 rad (0.03 m) per
        joint (within the limits): the geom lies on the axes of every hinge that moves it."""
        data = mujoco.MjData(model)
        jac = np.zeros((3, model.nv))
        for offset in (0.0, 0.3):
            data.qpos[:] = model.qpos0
            for j in range(model.njnt):
                if int(model.jnt_type[j]) not in _JOINT_TYPES:
                    continue
                step = offset if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE else 0.1 * offset
                low, high = model.jnt_range[j] if model.jnt_limited[j] else (-np.inf, np.inf)
                adr = model.jnt_qposadr[j]
                data.qpos[adr] = np.clip(data.qpos[adr] + step, low, high)
            mujoco.mj_kinematics(model, data)
            mujoco.mj_comPos(model, data)
            frame = model.geom_bodyid[geom] if capsule.body < 0 else capsule.body
            xpos, xmat = (data.geom_xpos[geom], data.geom_xmat[geom]) if capsule.body < 0 else \
                (data.xpos[frame], data.xmat[frame])  # fmt: skip
            for end in (capsule.a, capsule.b):
                mujoco.mj_jac(model, data, jac, None, xpos + xmat.reshape(3, 3) @ end, frame)
                if np.abs(jac[:, dofs]).max() > 1e-9:
                    return False
        return True

    def capsule_segments(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The protected capsules in world coordinates at ``data``'s kinematics (after
        ``mj_kinematics``, ``mj_step1`` or ``mj_forward``): axis end points ``a``, ``b`` (S, 3) and
        radii (S,) [m], in the order of :attr:`geom_ids` (to draw them, or to measure against them)."""
        local = np.array([(c.a, c.b) for c in self.capsules])
        body = np.array([c.body for c in self.capsules], dtype=int)
        a, b = world_segments(data, self.geom_ids, local, body)
        return a, b, np.array([c.radius for c in self.capsules])

    def describe(self, model: mujoco.MjModel) -> str:
        """A table of the protected geoms (name, body, type) and the capsules the filter protects
        in their place (radius, length) [m]: one line each."""
        lines = [f"{'geom':<24} {'body':<20} {'type':<10} {'radius':>8} {'length':>8}"]
        for g, capsule in zip(self.geom_ids, self.capsules, strict=True):
            geom = mujoco.mj_id2name(model, _OBJ.mjOBJ_GEOM, g) or f"#{g}"
            body = mujoco.mj_id2name(model, _OBJ.mjOBJ_BODY, model.geom_bodyid[g]) or f"#{model.geom_bodyid[g]}"
            lines.append(f"{geom:<24} {body:<20} {capsule.source:<10} {capsule.radius:8.4f} "
                         f"{2 * capsule.half_length:8.4f}")  # fmt: skip
        return "\n".join(lines)

    @staticmethod
    def _torque_limit(model: mujoco.MjModel, a: int) -> float:
        """The tightest symmetric bound on actuator ``a``'s joint force (module docstring)."""
        bounds = []
        joint = model.actuator_trnid[a, 0]
        if model.jnt_actfrclimited[joint]:
            bounds.append(model.jnt_actfrcrange[joint])
        gear = abs(model.actuator_gear[a, 0])
        if model.actuator_forcelimited[a]:  # the actuator's force, which its gear scales onto the joint
            bounds.append(np.sort(model.actuator_forcerange[a] * gear))
        if model.actuator_ctrllimited[a]:
            bounds.append(np.sort(model.actuator_ctrlrange[a] * gear * abs(model.actuator_gainprm[a, 0])))
        limits = [min(-low, high) for low, high in bounds]
        label = f"actuator {_name(model, _OBJ.mjOBJ_ACTUATOR, a)}"
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
        """Raise :class:`UnsupportedModelError` when no joint speed limit was given (the joint-limit
        rows need one per joint; a joint without position limits, a continuous one, gets speed
        rows only)."""
        if self.joint_speed_limit is None:
            raise UnsupportedModelError("the joint-limit rows need joint speed limits: pass joint_speed_limit= to "
                                        "RobotDescription.from_model, or build the filter with joint_limits=False")  # fmt: skip
