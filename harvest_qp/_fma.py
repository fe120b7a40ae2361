"""``fma(a, b, c)``: a * b + c rounded once, for numba kernels (LLVM's ``llvm.fma``: correctly
rounded on every machine; the FMA instruction where the CPU has one).

Shared by the kernels that reproduce numpy's fused dot products bit for bit
(:mod:`harvest_qp.references._kernels`, :mod:`harvest_qp.perception._unveiling_kernels`).
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.extending import intrinsic


@intrinsic
def fma(typingctx, a, b, c):
    """a * b + c rounded once (float64)."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        double = ir.DoubleType()
        function = builder.module.declare_intrinsic("llvm.fma", [double], ir.FunctionType(double, [double] * 3))
        return builder.call(function, args)

    return sig, codegen
