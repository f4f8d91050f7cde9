"""Calls into the Embree library and raw memory access from numba-compiled code.

Embree's query functions are declared as ``@intrinsic`` calls *by name*: the library is in
LLVM's process symbol table (``library.Api`` loads it there), so compiled code holds no raw
addresses and numba caches the kernels that use these on disk (``__pycache__``). Addresses
are given as integers (a buffer's ``ctypes.data``, a field of a structure Embree hands a
filter).

numba's cache is invalidated only by changes to the file of the cached function: after
editing this file, delete ``scene/embree/__pycache__/*.nb[ic]`` (or touch ``kernels.py``) so
the kernels compile again.
"""

from __future__ import annotations

from numba import types
from numba.core import cgutils
from numba.extending import intrinsic


def _codegen(name: str, nargs: int):
    """Code calling the library's ``void name(void*, ...)`` by symbol name, its pointer
    arguments given as integers (addresses)."""

    def codegen(context, builder, signature, values):
        ptr = cgutils.voidptr_t
        fnty = cgutils.ir.FunctionType(cgutils.ir.VoidType(), [ptr] * nargs)
        fn = cgutils.get_or_insert_function(builder.module, fnty, name)
        builder.call(fn, [builder.inttoptr(v, ptr) for v in values])
        return context.get_dummy_value()

    return codegen


def _external3(name: str):
    @intrinsic
    def call(typingctx, a, b, c):
        if all(isinstance(x, types.Integer) for x in (a, b, c)):
            return types.void(a, b, c), _codegen(name, 3)
        return None

    return call


def _external4(name: str):
    @intrinsic
    def call(typingctx, a, b, c, d):
        if all(isinstance(x, types.Integer) for x in (a, b, c, d)):
            return types.void(a, b, c, d), _codegen(name, 4)
        return None

    return call


rtc_intersect1 = _external3("rtcIntersect1")  # (scene, rayhit, args)
rtc_occluded1 = _external3("rtcOccluded1")  # (scene, ray, args)
rtc_intersect8 = _external4("rtcIntersect8")  # (valid, scene, rayhit8, args)
rtc_occluded8 = _external4("rtcOccluded8")  # (valid, scene, ray8, args)


def _memory(width: int, kind: str):
    """Intrinsics loading (``kind="load"``) or storing a ``width``-bit word at an address
    given as an integer: the tie filter reads Embree's structures through them."""
    is_float = width == 32 and kind.endswith("f")

    def llvm_type():
        return cgutils.ir.FloatType() if is_float else cgutils.ir.IntType(width)

    value_type = types.float32 if is_float else types.int32 if width == 32 else types.int64
    if kind.startswith("load"):
        @intrinsic
        def load(typingctx, addr):
            if isinstance(addr, types.Integer):
                def codegen(context, builder, signature, values):
                    ptr = builder.inttoptr(values[0], cgutils.ir.PointerType(llvm_type()))
                    return builder.load(ptr)

                return value_type(addr), codegen
            return None

        return load

    @intrinsic
    def store(typingctx, addr, value):
        if isinstance(addr, types.Integer):
            def codegen(context, builder, signature, values):
                ptr = builder.inttoptr(values[0], cgutils.ir.PointerType(llvm_type()))
                v = context.cast(builder, values[1], signature.args[1], value_type)
                builder.store(v, ptr)
                return context.get_dummy_value()

            return types.void(addr, value), codegen
        return None

    return store


load_i64 = _memory(64, "load")
load_i32 = _memory(32, "load")
load_f32 = _memory(32, "loadf")
store_i32 = _memory(32, "store")
store_f32 = _memory(32, "storef")
