"""Calling a C function by its address from compiled (numba) code.

The package calls two C libraries from its kernels: DAQP (the filter's QP solver,
:mod:`c3bf_gym.safety._daqp`) and MuJoCo (the environment's physics steps,
:mod:`c3bf_gym.envs._kernels`). ctypes reads each function's address once; the compiled code
receives it as data and calls through it, so no address is compiled in and numba caches the
calling code on disk like every other kernel.
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.extending import intrinsic

__all__ = ["call_void"]


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
