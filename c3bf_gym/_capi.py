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

Only numba's documented interface is used: each array is :func:`numba.carray` of a typed pointer
that an intrinsic makes from its address (llvmlite IR), and the rebuild is generated per
structure type as Python source and compiled through :func:`numba.extending.overload`.
:func:`numba.carray` cannot be compiled without numba's reference counting (numba refuses a
function that returns an array it did not receive when ``_nrt=False``), so the kernel that calls
:func:`unpack` is compiled with it; the arrays it makes carry no reference count.
"""

from __future__ import annotations

import functools
import numbers

import numpy as np
from llvmlite import ir
from numba import carray, types
from numba.core.errors import TypingError
from numba.extending import intrinsic, overload

from c3bf_gym._compile_cache import KERNEL_OPTIONS  # (before any @njit(cache=True): the cache keys)

#: how the rebuild compiles: as the kernels, without a disk cache of its own (it is generated per
#: structure type; the kernels that call it cache it inside them). With numba's reference counting:
#: :func:`numba.carray` cannot be compiled without it (see :func:`unpack`).
_REBUILD_OPTIONS = {key: value for key, value in KERNEL_OPTIONS.items() if key != "cache"}

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


@functools.lru_cache(maxsize=None)
def _pointer_word(dtype):
    """An intrinsic ``(uint64) -> CPointer(dtype)``: an address as a typed pointer, which
    :func:`numba.carray` takes (one per dtype)."""

    @intrinsic
    def pointer_word(typingctx, word):
        def codegen(context, builder, signature, args):
            return builder.inttoptr(args[0], context.get_value_type(signature.return_type))

        return types.CPointer(dtype)(types.uint64), codegen

    return pointer_word


@functools.lru_cache(maxsize=None)
def _scalar_word(typ):
    """An intrinsic ``(uint64) -> typ`` for the numbers :func:`pack` writes: a bool (nonzero), an
    integer (its low ``bitwidth`` bits, two's complement) or a float64 (its bits), one per type."""

    @intrinsic
    def scalar_word(typingctx, word):
        def codegen(context, builder, signature, args):
            (value,) = args
            if isinstance(typ, types.Boolean):
                return builder.icmp_unsigned("!=", value, ir.Constant(ir.IntType(64), 0))
            if isinstance(typ, types.Integer):
                return builder.trunc(value, ir.IntType(typ.bitwidth)) if typ.bitwidth < 64 else value
            return builder.bitcast(value, ir.DoubleType())  # float64 (unpack's typing checked)

        return typ(types.uint64), codegen

    return scalar_word


@intrinsic
def _read_only(typingctx, array):
    """``array`` typed read-only: :func:`numba.carray` builds writable arrays, and numba converts a
    writable array to its read-only type (the same data) as it does for any argument."""
    target = array.copy(readonly=True)

    def codegen(context, builder, signature, args):
        return context.cast(builder, args[0], array, target)

    return target(array), codegen


@intrinsic
def _exactly(typingctx, value, like):
    """``value``, which must be of the type ``like`` refers to (the rebuild's last check)."""
    if value != like.instance_type:
        raise TypingError(f"unpack() rebuilt {value}, not {like.instance_type}")

    def codegen(context, builder, signature, args):
        return args[0]

    return value(value, like), codegen


def _packable(typ) -> bool:
    if isinstance(typ, types.BaseTuple):
        return all(map(_packable, typ.types))
    if isinstance(typ, types.Array):
        return typ.layout == "C" and typ.aligned  # read-only ones stay read-only (their type says so)
    return isinstance(typ, (types.Boolean, types.Integer)) or typ == types.float64


@functools.lru_cache(maxsize=None)
def _rebuild_source(typ) -> tuple[str, dict]:
    """Python source of ``impl(handle, like)``, which rebuilds a structure of numba type ``typ``
    from a handle in compiled code, and the globals it names: each array ``numba.carray`` of its
    address (a typed pointer) and shape, each number decoded from its word, each named tuple built
    by its class, in :func:`pack`'s order."""
    names: dict = {"carray": carray, "read_only": _read_only, "exactly": _exactly}
    at = [0]

    def name(value, prefix: str) -> str:
        key = f"{prefix}{len(names)}"
        names[key] = value
        return key

    def build(t) -> str:
        if isinstance(t, types.BaseTuple):
            items = [build(item) for item in t.types]
            if isinstance(t, types.BaseNamedTuple):
                return f"{name(t.instance_class, 'cls')}({', '.join(items)})"
            return f"({''.join(item + ', ' for item in items)})"
        start = at[0]
        if isinstance(t, types.Array):
            at[0] += 1 + t.ndim
            shape = "".join(f"handle[{start + 1 + d}], " for d in range(t.ndim))
            array = f"carray({name(_pointer_word(t.dtype), 'ptr')}(handle[{start}]), ({shape}))"
            return array if t.mutable else f"read_only({array})"
        at[0] += 1
        return f"{name(_scalar_word(t), 'num')}(handle[{start}])"

    body = build(typ)
    return f"def impl(handle, like):\n    return exactly({body}, like)\n", names


def unpack(handle, like):
    """In compiled code: the structure :func:`pack` wrote into ``handle`` (uint64 (w,)), of the numba
    type ``like`` (a type reference: pass ``numba.typeof(structure)`` from Python). The arrays are
    views of the packed arrays' memory (:func:`numba.carray` of each address), without reference
    counts: the caller must neither keep them nor return them to Python. Read-only arrays in
    ``like`` come back read-only. Nothing is checked at run time, so the handle must come from
    :func:`pack` of a structure of exactly that type, still alive.

    Raises:
        numba.core.errors.TypingError: when compiled, for a handle that is not a C-contiguous uint64
            vector or a type :func:`pack` does not write.
        TypeError: called from Python (there is nothing to rebuild the arrays into).
    """
    raise TypeError("unpack() runs in compiled code only (pass the structure itself from Python)")


@overload(unpack, jit_options=_REBUILD_OPTIONS)
def _unpack_compiled(handle, like):
    handle_ok = (isinstance(handle, types.Array) and handle.dtype == types.uint64 and handle.ndim == 1
                 and handle.layout == "C")
    if not (handle_ok and isinstance(like, types.TypeRef) and _packable(like.instance_type)):
        raise TypingError(
            f"unpack() takes a uint64 handle and the type of a structure pack() takes, got {handle}, {like}")
    source, names = _rebuild_source(like.instance_type)
    scope = dict(names)
    exec(compile(source, "<c3bf_gym._capi.unpack>", "exec"), scope)
    return scope["impl"]
