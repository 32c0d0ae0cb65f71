"""The safety filter inside a simulator's own compiled loop: the seam between a simulator and
:class:`~c3bf_gym.safety.SafetyController`.

A simulator that runs its physics steps in numba-compiled code (``C3BFReachEnv`` does:
:func:`c3bf_gym.envs._kernels.policy_steps`) calls the filter there, once per physics step,
instead of coming back to Python. The protocol is three names:

* ``call = controller.compiled_call(version)``
  (:meth:`~c3bf_gym.safety.SafetyController.compiled_call`), once per policy step, before the
  loop, gives a :class:`FilterCall`, or None: that filter must then be called from Python
  (``controller(tau_nom)``);
* in the loop, after each ``mj_step1`` and before the ``mj_step2`` that integrates the torque,
  ``status = filter_substep(stage, tau_nom, tau, call.buffers)`` writes into ``tau`` (n,) the
  safe total joint torque [N m] for the nominal one ``tau_nom`` (n,): the torque the actuators
  apply plus MuJoCo's gravity compensation ``data.qfrc_gravcomp``. ``stage`` is ``call.stage`` on
  the first call; on every later call it is 2 (a new state: the filter refreshes the arm's
  ``Minv``, ``qacc_free`` and capsule ends), or 1 when the caller refreshed ``Minv`` and
  ``qacc_free`` on this state in the filter's own arm arrays (the Cartesian impedance
  controller's kernel does);
* the loop stops before integrating a call whose status is invalid input (< 0) or, with
  ``call.halt``, infeasible (> 0). After the loop, ``controller.failure(status)``
  (:meth:`~c3bf_gym.safety.SafetyController.failure`) is the exception that status calls for, or
  None (a solved call, or a relaxed one without ``halt``): the caller raises it.

The filter's report (``SafetyController.report``, ``last``) accumulates inside the calls, as it
does from Python; the calls are not timed (``solve_time`` NaN). Every call is the same compiled
arithmetic as ``SafetyController.__call__``'s, so both give the same torques bit for bit.
"""

from __future__ import annotations

from typing import NamedTuple

from c3bf_gym.safety._step import StepBuffers, filter_substep

__all__ = ["FilterCall", "StepBuffers", "filter_substep"]


class FilterCall(NamedTuple):
    """What a compiled loop needs to call the filter at each physics step of one policy step
    (:meth:`~c3bf_gym.safety.SafetyController.compiled_call`).

    Attributes:
        buffers: the filter's :class:`~c3bf_gym.safety._step.StepBuffers`, updated in place:
            :func:`filter_substep`'s last argument.
        stage: the first call's stage: which of the arm's dynamics are stale for the state the
            loop starts from (2: ``Minv``, ``qacc_free`` and the capsule ends; 1: the ends; 0: none).
        halt: stop at an infeasible call (the filter was built with ``on_infeasible="raise"``).
    """

    buffers: StepBuffers
    stage: int
    halt: bool
