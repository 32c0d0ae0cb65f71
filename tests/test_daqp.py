"""Tests for c3bf_gym/safety/_daqp.py: DAQP's C API through its documented structs and functions only,
checked against ``daqp.solve`` at import, its workspace memory guarded, and nothing leaked."""

from __future__ import annotations

import gc

import numpy as np
import pytest

import daqp
from c3bf_gym.safety import _daqp


def _rss_mib() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * 4096 / 2**20


def test_the_compiled_call_solves_what_the_import_check_solves():
    """daqp_call (compiled, the filter's) and the import check's ctypes calls give the same answer,
    and the import check's answer is daqp.solve's (else the module would not import)."""
    n, lo, hi = 3, -np.ones(3), np.ones(3)
    answers = []
    for call in (_daqp._call_from_python, lambda b, mask: _daqp.daqp_call(b, mask)[0]):
        work = _daqp.DaqpWorkspace(n, 2, lo, hi, break_points=[n, n + 1, n + 2])
        buffers = work.buffers
        buffers.A[:] = [[1.0, 1.0, 0.0], [-1.0, -1.0, 0.0]]
        buffers.lower[n:] = [1.5, -0.5]
        buffers.f[:] = [-0.2, 0.7, -0.5]
        flag = call(buffers, _daqp.UPDATE_M | _daqp.UPDATE_V | _daqp.UPDATE_D | _daqp.UPDATE_SENSE)
        answers.append((flag, buffers.x.tobytes()))
    assert answers[0] == answers[1] and answers[0][0] >= 1


def test_the_import_check_fails_loudly_when_daqp_answers_otherwise(monkeypatch):
    solve = daqp.solve

    def shifted(*args, **kwargs):
        x, fval, flag, info = solve(*args, **kwargs)
        return x + 1e-6, fval, flag, info

    monkeypatch.setattr(daqp, "solve", shifted)
    with pytest.raises(ImportError, match=f"disagrees with daqp.solve on daqp {_daqp.DAQP_VERSION} \\(one level"):
        _daqp._self_check()


def test_a_workspace_larger_than_its_reserve_fails_loudly(monkeypatch):
    """DAQP 0.11.0's workspace is 328 bytes: with less reserved, setup writes into the zeroed guard
    (which it reads as NULL fields, so nothing runs on memory it does not own) and the check says so."""
    monkeypatch.setattr(_daqp, "WORKSPACE_BYTES", 256)
    with pytest.raises(RuntimeError, match="wrote past the 256 bytes"):
        _daqp.DaqpWorkspace(3, 2, -np.ones(3), np.ones(3))


def test_workspaces_free_what_daqp_allocated():
    """Building, solving and dropping workspaces (one and two levels) leaves the process's memory
    where it was: their settings, LDP and hierarchy are freed (a leak was ~21 MiB per 1000)."""
    n, rows = 7, 150
    lo, hi = -np.ones(n), np.ones(n)

    def churn(count: int) -> None:
        for i in range(count):
            work = _daqp.DaqpWorkspace(n, rows, lo, hi, break_points=None if i % 2 else [n, n + 100, n + rows])
            work.buffers.A[:5] = np.random.default_rng(i).normal(size=(5, n))
            work.buffers.lower[n:n + 5] = 0.1
            _daqp._call_from_python(work.buffers, _daqp.UPDATE_M | _daqp.UPDATE_V | _daqp.UPDATE_D | _daqp.UPDATE_SENSE)
            del work
        gc.collect()

    churn(200)  # the allocator's first growth
    before = _rss_mib()
    churn(1000)
    assert _rss_mib() - before < 8.0
