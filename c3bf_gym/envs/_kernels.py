"""The reaching environment's per-step work in compiled code (numba): its physics steps
(:func:`policy_steps`: MuJoCo's own ``mj_step2`` and ``mj_step1``, with the obstacles' motion
and the distance sensors' minimum between them, under the torque, the Cartesian impedance
controller, the safety filter or both), its observation (:func:`observe`) and the check for
obstacles that left the workspace (:func:`departed`).

A policy step is ``frame_skip`` physics steps; in Python each cost two calls into the bindings
and two numpy operations on top of the physics, about as much again as the physics itself, and
the observation a dozen numpy operations. :func:`policy_steps` runs any number of steps in one
call. It calls the C functions of the ``libmujoco`` that the ``mujoco`` package loaded (the same
library, so the same model and data structures) by address (:func:`c3bf_gym._capi.call_void`):
ctypes reads the addresses here, and the compiled code receives them as data (:class:`Physics`).

MuJoCo's fatal errors (``mju_error``) are C++ exceptions in the Python bindings and cannot cross
compiled frames; the steps here are those of the environment's own scene, which allocates
nothing per step beyond its fixed arena.
"""

from __future__ import annotations

import ctypes
import glob
import os
from typing import NamedTuple

import mujoco
import numpy as np
from numba import njit

from c3bf_gym._compile_cache import KERNEL_OPTIONS, STEP_KERNEL_OPTIONS  # (before any @njit: the cache keys)
from c3bf_gym._capi import call_void
from c3bf_gym.controllers._kernels import impedance_substep
from c3bf_gym.safety.substep import filter_substep

__all__ = ["Drive", "Observed", "Physics", "departed", "entry", "observe", "policy_steps"]


def _libmujoco() -> ctypes.CDLL:
    """The ``libmujoco`` shipped in (and loaded by) the ``mujoco`` package."""
    folder = os.path.dirname(mujoco.__file__)
    found = sorted(glob.glob(os.path.join(folder, "libmujoco.so*")) + glob.glob(os.path.join(folder, "libmujoco*.dylib"))
                   + glob.glob(os.path.join(folder, "mujoco.dll")))  # fmt: skip
    if not found:
        raise ImportError(f"found no libmujoco shared library in {folder}: the mujoco package's layout is not the one "
                          f"c3bf_gym knows (mujoco {mujoco.__version__})")  # fmt: skip
    return ctypes.CDLL(found[0])


_lib = _libmujoco()
#: the entries of :attr:`Physics.functions`
STEP1, STEP2 = range(2)
_FUNCTIONS = np.array([ctypes.cast(_lib.mj_step1, ctypes.c_void_p).value,
                       ctypes.cast(_lib.mj_step2, ctypes.c_void_p).value], dtype=np.uint64)  # fmt: skip


class Physics(NamedTuple):
    """What :func:`policy_steps` works on (views of the environment's ``MjData``, updated in place).

    Attributes:
        functions: uint64 (2,) the addresses of ``mj_step1`` and ``mj_step2``.
        pointers: uint64 (2,) the addresses of the ``MjModel`` and the ``MjData``.
        obstacle_pos: (K, 3) the obstacles' mocap positions [m].
        displacement: (K, 3) each obstacle's motion per physics step [m].
        distances: (K, G) the distance sensors' readings [m].
        cutoff: the sensors' cutoff [m]: the largest distance they read.
    """

    functions: np.ndarray
    pointers: np.ndarray
    obstacle_pos: np.ndarray
    displacement: np.ndarray
    distances: np.ndarray
    cutoff: float

    @classmethod
    def of(cls, model: mujoco.MjModel, data: mujoco.MjData, obstacle_pos: np.ndarray, displacement: np.ndarray,
           distances: np.ndarray, cutoff: float) -> Physics:
        """The structure for ``model`` and ``data``, which must outlive it."""
        return cls(_FUNCTIONS, np.array([model._address, data._address], dtype=np.uint64), obstacle_pos, displacement,
                   distances, float(cutoff))


@njit(**STEP_KERNEL_OPTIONS)
def _advance(physics, lowest):
    """One physics step: ``mj_step2`` (integrate the controls in ``data.ctrl``), every obstacle
    moves by its displacement, ``mj_step1`` (kinematics, dynamics and sensors of the new state).
    Returns the smaller of ``lowest`` and the smallest distance sensor reading."""
    model, data = physics.pointers[0], physics.pointers[1]
    pos, displacement, distances = physics.obstacle_pos, physics.displacement, physics.distances
    call_void(physics.functions[STEP2], model, data)
    for k in range(pos.shape[0]):
        for i in range(3):
            pos[k, i] += displacement[k, i]
    call_void(physics.functions[STEP1], model, data)
    for k in range(distances.shape[0]):
        for g in range(distances.shape[1]):
            if distances[k, g] < lowest:
                lowest = distances[k, g]
    return lowest


class Drive(NamedTuple):
    """The torque side of :func:`policy_steps`: views of the environment's arrays, made once.

    Attributes:
        gravity: (n,) ``data.qfrc_gravcomp``, the gravity compensation MuJoCo adds [N m].
        ctrl: (n,) ``data.ctrl``, written: the applied torque minus ``gravity`` [N m].
        inv_limit: (n,) 1 / the torque limits [1/(N m)].
        tau_nom, tau: (n,) scratch: the nominal and the filtered total torque [N m].
        effort_rows: (frame_skip, n), written: row ``s`` is physics step ``s``'s ``ctrl * inv_limit``.
    """

    gravity: np.ndarray
    ctrl: np.ndarray
    inv_limit: np.ndarray
    tau_nom: np.ndarray
    tau: np.ndarray
    effort_rows: np.ndarray


@njit(**STEP_KERNEL_OPTIONS)
def policy_steps(physics, n, torque, drive, nominal, call):
    """``n`` physics steps (:func:`_advance`) from a state whose ``mj_step1`` has run, each with
    the torque of the stack the arguments name; ``drive.ctrl`` (:class:`Drive`) becomes the
    applied torque minus gravity before each step, and row ``s`` of ``drive.effort_rows`` that
    control over the limits.

    * ``nominal`` and ``call`` None: ``torque`` (n,) [N m] itself.
    * ``nominal``: the Cartesian impedance controller
      (:func:`c3bf_gym.controllers._kernels.impedance_substep` on a
      :class:`~c3bf_gym.controllers._kernels.BoundImpedance`; ``torque`` is not read). It
      refreshes the arm's ``Minv`` on every state it is the first to see.
    * ``call``: the safety filter (a :class:`~c3bf_gym.safety.substep.FilterCall`, the protocol
      of :mod:`c3bf_gym.safety.substep`) on the nominal total torque: ``torque + drive.gravity``
      (the gravity compensation ``data.qfrc_gravcomp``, current for the state about to be
      integrated), or the controller's. It stops before integrating a call whose status is
      invalid input (< 0) or, with ``call.halt``, infeasible (> 0).

    Returns ``(physics steps done, smallest distance sensor reading over the new states (cutoff at
    most), the last filter call's status (0 without a filter))``. The ``None`` tests are resolved
    when numba compiles the function for its argument types: each stack is its own machine code.
    """
    lowest = physics.cutoff
    status = 0
    gravity, ctrl, tau_nom, tau = drive.gravity, drive.ctrl, drive.tau_nom, drive.tau
    for s in range(n):
        # the state's dynamics: stale on every state after the first (2), the filter's word on the first
        stage = 2
        if call is not None:
            if s == 0:
                stage = call.stage
        if nominal is None:
            if call is None:
                for j in range(ctrl.shape[0]):
                    ctrl[j] = torque[j]
            else:
                for j in range(tau_nom.shape[0]):
                    tau_nom[j] = torque[j] + gravity[j]
        else:
            impedance_substep(stage, nominal, tau_nom)
            stage = min(stage, 1)  # it refreshed Minv and qacc_free in the filter's arm arrays
            if call is None:
                for j in range(ctrl.shape[0]):
                    ctrl[j] = tau_nom[j] - gravity[j]
        if call is not None:
            status = filter_substep(stage, tau_nom, tau, call.buffers)
            if status < 0 or (call.halt and status > 0):
                return s, lowest, status
            for j in range(ctrl.shape[0]):
                ctrl[j] = tau[j] - gravity[j]
        for j in range(ctrl.shape[0]):
            drive.effort_rows[s, j] = ctrl[j] * drive.inv_limit[j]
        lowest = _advance(physics, lowest)
    return n, lowest, status


class Observed(NamedTuple):
    """What :func:`observe` reads: views of the environment's arrays, made once.

    Attributes:
        qpos, qvel: (n,) the joints [rad, rad/s].
        tool: (3,) the tool site's position [m]; tool_velocity (6,) its (angular, linear)
            velocity [rad/s, m/s], written by ``mj_objectVelocity`` before the call.
        goal: (3,) the goal [m].
        position, velocity, radius, active: the obstacle slots (K, 3), (K, 3), (K,), (K,) bool.
        distances: (K, G) their distance sensors [m].
    """

    qpos: np.ndarray
    qvel: np.ndarray
    tool: np.ndarray
    tool_velocity: np.ndarray
    goal: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    radius: np.ndarray
    active: np.ndarray
    distances: np.ndarray


@njit(**KERNEL_OPTIONS)
def observe(seen, sensing_radius, obs):
    """The observation (:func:`~c3bf_gym.envs.reach.observation_layout`) into ``obs`` (float64),
    returned as a new float32 array: joints, tool position and velocity, goal minus tool, then
    per obstacle slot its centre minus the tool, velocity, radius and sensed flag, all zero for a
    slot not sensed (inactive, or farther than ``sensing_radius`` [m] from every arm geom by its
    distance sensors)."""
    n = seen.qpos.shape[0]
    slots = seen.position.shape[0]
    for j in range(n):
        obs[j] = seen.qpos[j]
        obs[n + j] = seen.qvel[j]
    at = 2 * n
    for i in range(3):
        obs[at + i] = seen.tool[i]
        obs[at + 3 + i] = seen.tool_velocity[3 + i]
        obs[at + 6 + i] = seen.goal[i] - seen.tool[i]
    rel, vel, rad, flag = at + 9, at + 9 + 3 * slots, at + 9 + 6 * slots, at + 9 + 7 * slots
    for k in range(slots):
        nearest = np.inf
        for g in range(seen.distances.shape[1]):
            nearest = min(nearest, seen.distances[k, g])
        sensed = 1.0 if seen.active[k] and nearest <= sensing_radius else 0.0
        for i in range(3):
            obs[rel + 3 * k + i] = (seen.position[k, i] - seen.tool[i]) * sensed
            obs[vel + 3 * k + i] = seen.velocity[k, i] * sensed
        obs[rad + k] = seen.radius[k] * sensed
        obs[flag + k] = sensed
    return obs.astype(np.float32)


@njit(**STEP_KERNEL_OPTIONS)
def departed(position, active, low, high):
    """Whether an active obstacle (``position`` (K, 3), ``active`` (K,)) lies outside the box
    ``low``-``high`` (3,) [m]."""
    for k in range(position.shape[0]):
        if active[k]:
            for i in range(3):
                if position[k, i] < low[i] or position[k, i] > high[i]:
                    return True
    return False


def entry(kernel, *arguments):
    """``kernel``'s compiled entry point for arguments of the types of ``arguments``: called
    directly, it skips the dispatcher's type resolution (several microseconds per call on
    structures of arrays, as much as a physics step). The caller keeps to those types."""
    import numba

    return kernel.compile(tuple(numba.typeof(a) for a in arguments))
