"""Addresses in compiled (numba) code: calling a C function by its address, and handing a kernel
its buffers as one array of addresses.

**C functions.** The package calls two C libraries from its kernels: DAQP (the filter's QP solver,
:mod:`c3bf_gym.safety._daqp`) and MuJoCo (the environment's physics steps,
:mod:`c3bf_gym.envs._kernels`). ctypes reads each function's address once; the compiled code
receives it as data and calls through it (:func:`call_void`), so no address is compiled in and
numba caches the calling code on disk like every other kernel.

**Buffers by address.** numba converts every array argument of a call from Python on its own,
which for the filter's ~80 buffers is a sizeable part of a call (the speed page has the figures).
:func:`pack` writes a structure of arrays (nested tuples and named tuples of C-contiguous arrays
and numbers; read-only arrays stay read-only) into one uint64 array, and :func:`unpack`, in
compiled code, rebuilds the same structure from it, typed as the structure's numba type: one
array crosses from Python instead of eighty. The rebuilt arrays borrow the memory of the packed
ones, so whoever calls with a handle keeps the packed structure alive, and the kernels that take
them must not keep them (the filter's, compiled without reference counting, cannot).
"""

from __future__ import annotations

import numbers

import numpy as np
from llvmlite import ir
from numba import types
from numba.core.errors import TypingError
from numba.extending import intrinsic
from numba.np.arrayobj import make_array, populate_array

__all__ = ["call_void", "pack", "unpack"]


@intrinsic
def call_void(typingctx, fn, first, second):
    """``void fn(void* first, void* second)`` at address ``fn`` (all three uint64)."""
    sig = types.none(types.uint64, types.uint64, types.uint64)

    def codegen(context, builder, signature, args):
        fn_addr, first_v, second_v = args
        ptr = ir.IntType(8).as_pointer()
        callee = builder.inttoptr(fn_addr, ir.FunctionType(ir.VoidType(), [ptr, ptr]).as_pointer())
        builder.call(callee, [builder.inttoptr(first_v, ptr), builder.inttoptr(second_v, ptr)])
        return context.get_dummy_value()

    return sig, codegen


def pack(value) -> np.ndarray:
    """``value`` (a tuple or named tuple, nested, of arrays, bools, ints and floats) as the uint64
    handle :func:`unpack` rebuilds it from: depth first, an array as its address then its shape,
    a number as one word (an int in two's complement, a float's bits).

    Raises:
        ValueError: an array that is not C-contiguous and aligned, which the typed rebuild could
            not describe (pass a contiguous copy the caller keeps, or the structure itself
            without a handle).
        TypeError: a leaf of another kind.
    """
    words: list[int] = []

    def visit(leaf) -> None:
        if isinstance(leaf, tuple):
            for item in leaf:
                visit(item)
        elif isinstance(leaf, np.ndarray):
            flags = leaf.flags
            if not (flags.c_contiguous and flags.aligned):
                raise ValueError(f"pack() takes C-contiguous, aligned arrays; got one of shape {leaf.shape} with "
                                 f"c_contiguous={flags.c_contiguous}, aligned={flags.aligned}")
            words.append(leaf.ctypes.data)
            words.extend(leaf.shape)
        elif isinstance(leaf, (bool, np.bool_, numbers.Integral)):
            words.append(int(leaf) & 0xFFFF_FFFF_FFFF_FFFF)
        elif isinstance(leaf, numbers.Real):
            words.append(int(np.float64(leaf).view(np.uint64)))
        else:
            raise TypeError(f"pack() takes tuples of arrays and numbers, not {type(leaf).__name__}")

    visit(value)
    return np.array(words, np.uint64)


def _rebuild(context, builder, typ, word, at: list[int]):
    """The LLVM value of numba type ``typ`` read from the handle's words from ``at[0]`` on (advanced
    past them): ``word(i)`` loads word ``i`` as an i64."""
    i64 = ir.IntType(64)
    if isinstance(typ, types.BaseTuple):
        return context.make_tuple(builder, typ, [_rebuild(context, builder, t, word, at) for t in typ.types])
    start = at[0]
    if isinstance(typ, types.Array):
        at[0] += 1 + typ.ndim
        item = context.get_data_type(typ.dtype)
        itemsize = context.get_abi_sizeof(item)
        shape = [word(start + 1 + d) for d in range(typ.ndim)]
        strides, stride = [], ir.Constant(i64, itemsize)
        for extent in reversed(shape):  # C order: the last axis is contiguous
            strides.insert(0, stride)
            stride = builder.mul(stride, extent)
        array = make_array(typ)(context, builder)
        populate_array(array, data=builder.inttoptr(word(start), item.as_pointer()), shape=shape, strides=strides,
                       itemsize=ir.Constant(i64, itemsize), meminfo=None)
        return array._getvalue()
    at[0] += 1
    if isinstance(typ, types.Boolean):
        return builder.icmp_unsigned("!=", word(start), ir.Constant(i64, 0))
    if isinstance(typ, types.Integer):
        return builder.trunc(word(start), ir.IntType(typ.bitwidth)) if typ.bitwidth < 64 else word(start)
    return builder.bitcast(word(start), ir.DoubleType())  # float64 (unpack's typing checked)


def _packable(typ) -> bool:
    if isinstance(typ, types.BaseTuple):
        return all(map(_packable, typ.types))
    if isinstance(typ, types.Array):
        return typ.layout == "C" and typ.aligned  # read-only ones stay read-only (their type says so)
    return isinstance(typ, (types.Boolean, types.Integer)) or typ == types.float64


@intrinsic
def unpack(typingctx, handle, like):
    """In compiled code: the structure :func:`pack` wrote into ``handle`` (uint64 (w,)), of the numba
    type ``like`` (a type reference: pass ``numba.typeof(structure)`` from Python). The arrays are
    views of the packed arrays' memory, without reference counts: the caller must neither keep them
    nor return them to Python. Nothing is checked at run time, so the handle must come from
    :func:`pack` of a structure of exactly that type, still alive."""
    handle_ok = (isinstance(handle, types.Array) and handle.dtype == types.uint64 and handle.ndim == 1
                 and handle.layout == "C")
    if not (handle_ok and isinstance(like, types.TypeRef) and _packable(like.instance_type)):
        raise TypingError(
            f"unpack() takes a uint64 handle and the type of a structure pack() takes, got {handle}, {like}")
    typ = like.instance_type

    def codegen(context, builder, signature, args):
        words = builder.bitcast(make_array(signature.args[0])(context, builder, args[0]).data,
                                ir.IntType(64).as_pointer())

        def word(i):
            return builder.load(builder.gep(words, [ir.Constant(ir.IntType(64), i)]))

        return _rebuild(context, builder, typ, word, [0])

    return typ(handle, like), codegen
