"""The safety package's layers read bottom-up (c3bf_gym/safety/__init__.py): the barriers and their
compiled rows (_rows.py, on _dynamics.py) import nothing of the QP, so computing ``h`` or a row
loads neither the DAQP binding (_daqp.py) nor ``daqp``. Each check runs in a fresh interpreter,
since this test process has long imported everything."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

import c3bf_gym
import c3bf_gym.safety

#: the modules of the QP layer and above, and the solver itself
QP_MODULES = ("daqp", "c3bf_gym.safety._daqp", "c3bf_gym.safety._qp", "c3bf_gym.safety._step",
              "c3bf_gym.safety.priority_qp", "c3bf_gym.safety.controller")  # fmt: skip


def loaded_after(statement: str) -> set[str]:
    """The modules of :data:`QP_MODULES` in ``sys.modules`` after ``statement`` in a fresh interpreter."""
    probe = f"import json, sys\n{statement}\nprint(json.dumps([m for m in {QP_MODULES!r} if m in sys.modules]))"
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    return set(json.loads(done.stdout.strip().splitlines()[-1]))


@pytest.mark.parametrize("statement", [
    "import c3bf_gym.safety.barriers",
    "import c3bf_gym.safety._rows",
    "from c3bf_gym.safety import FilterConfig",
    "from c3bf_gym.safety.barriers import C3BF",
])  # fmt: skip
def test_the_rows_load_no_qp(statement):
    assert loaded_after(statement) == set()


def test_the_probe_sees_the_qp_where_it_is_loaded():
    """The fused step imports the QP and its binding: the check above can fail."""
    assert loaded_after("import c3bf_gym.safety._step") == {"daqp", "c3bf_gym.safety._daqp", "c3bf_gym.safety._qp",
                                                             "c3bf_gym.safety._step"}


@pytest.mark.parametrize("package", [c3bf_gym, c3bf_gym.safety])
def test_every_exported_name_resolves(package):
    """The packages import their exports when first read: each name in ``__all__`` is there, and
    an unknown one is an ``AttributeError``."""
    assert sorted(package.__all__) == sorted(package._EXPORTS)
    for name in package.__all__:
        assert getattr(package, name) is not None, name
    assert set(package.__all__) <= set(dir(package))
    with pytest.raises(AttributeError, match="no attribute 'not_a_name'"):
        package.not_a_name  # noqa: B018


def test_no_kernel_takes_more_than_eight_positional_arguments():
    """The compiled functions take named structures: a reordering of a long positional list is a
    silent bug (issue 33)."""
    import inspect
    from importlib import import_module

    from numba.core.registry import CPUDispatcher

    names = ("c3bf_gym.safety._dynamics", "c3bf_gym.safety._rows", "c3bf_gym.safety._qp", "c3bf_gym.safety._step",
             "c3bf_gym.safety._daqp", "c3bf_gym.controllers._kernels", "c3bf_gym.envs._kernels")  # fmt: skip
    kernels = {f"{name}.{key}": f for name in names for key, f in vars(import_module(name)).items()
               if isinstance(f, CPUDispatcher) and f.py_func.__module__ == name}  # fmt: skip
    assert len(kernels) >= 30
    wide = {key: len(inspect.signature(f.py_func).parameters) for key, f in kernels.items()}
    assert {key: count for key, count in wide.items() if count > 8} == {}
