"""Tests for c3bf_gym/_capi.py: buffers handed to compiled code by address (pack / unpack)."""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np
import pytest
from numba import njit
from numba.core.errors import TypingError

from c3bf_gym._capi import pack, unpack


class Inner(NamedTuple):
    matrix: np.ndarray
    flags: np.ndarray
    count: int


class Outer(NamedTuple):
    vector: np.ndarray
    inner: Inner
    gain: float
    on: bool
    ids: np.ndarray


@njit
def _read_and_write(handle, like):
    s = unpack(handle, like)
    s.vector[0] = 42.0  # writes reach the packed array
    s.inner.matrix[1, 2] = -1.0
    total = 0.0
    for i in range(s.inner.matrix.shape[0]):
        for j in range(s.inner.matrix.shape[1]):
            total += s.inner.matrix[i, j] * (i + 1)
    return (total, s.vector.shape[0], s.inner.matrix.shape, s.inner.flags[0], s.inner.flags[1], s.inner.count,
            s.gain, s.on, s.ids[2], s.ids.shape[0])


def _structure() -> Outer:
    ids = np.array([3, -7, 11, 2**40], np.int64)
    ids.setflags(write=False)  # read-only arrays stay read-only
    return Outer(np.arange(3.0), Inner(np.arange(12.0).reshape(3, 4), np.array([False, True]), -5), 0.1, True, ids)


def test_unpack_rebuilds_what_pack_wrote_and_shares_its_memory():
    structure = _structure()
    handle = pack(structure)
    got = _read_and_write(handle, numba.typeof(structure))
    matrix = np.arange(12.0).reshape(3, 4)
    matrix[1, 2] = -1.0
    assert got == ((matrix * np.arange(1, 4)[:, None]).sum(), 3, (3, 4), False, True, -5, 0.1, True, 11, 4)
    assert structure.vector[0] == 42.0 and structure.inner.matrix[1, 2] == -1.0


def test_unpack_keeps_the_structures_numba_type():
    structure = _structure()

    @njit
    def identity(handle, like):
        return unpack(handle, like).ids

    assert numba.typeof(identity(pack(structure), numba.typeof(structure))) == numba.typeof(structure.ids)
    assert not numba.typeof(structure.ids).mutable


def test_pack_refuses_arrays_it_cannot_describe():
    with pytest.raises(ValueError, match="C-contiguous"):
        pack((np.zeros((4, 4))[:, 1],))
    with pytest.raises(TypeError, match="tuples of arrays and numbers, not str"):
        pack((np.zeros(2), "name"))


def test_unpack_rejects_a_type_pack_does_not_write():
    @njit
    def read(handle, like):
        return unpack(handle, like)

    strided = np.zeros((4, 4))[:, 1]
    with pytest.raises(TypingError, match="unpack\\(\\) takes a uint64 handle"):
        read(pack((np.zeros(1),)), numba.typeof((strided,)))
    with pytest.raises(TypingError, match="unpack\\(\\) takes a uint64 handle"):
        read(np.zeros(2), numba.typeof((np.zeros(1),)))
