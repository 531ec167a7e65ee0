"""Bit-exact building blocks of the compiled kernels (:mod:`vespro.jit`).

The kernels keep the NumPy code's arithmetic operation for operation. Its
small matrix products (points times a 3x3 rotation) go to OpenBLAS, whose
gemm kernels accumulate each entry as an FMA chain over k in order,
``fma(a2, b2, fma(a1, b1, fma(a0, b0, 0)))`` (x86-64 with FMA, as here);
:func:`dot3` does the same, so projections agree to the last bit. Products
with a single row (one point) go to gemv instead and round differently: there
the kernels agree to rounding only.
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.extending import intrinsic

from .jit import njit

__all__ = ["dot3", "dot4"]


def _fma_codegen(context, builder, sig, args):
    lt = context.get_value_type(sig.return_type)
    fn = builder.module.declare_intrinsic("llvm.fma", [lt], ir.FunctionType(lt, [lt, lt, lt]))
    return builder.call(fn, list(args) + [ir.Constant(lt, 0.0)] * (3 - len(args)))


@intrinsic
def _fma(typingctx, a, b, c):
    """``a * b + c`` rounded once (``llvm.fma``), for three floats of one type."""
    if isinstance(a, types.Float) and a == b and b == c:
        return a(a, b, c), _fma_codegen


@intrinsic
def _fma0(typingctx, a, b):
    """``fma(a, b, +0)``: ``a * b``, except that -0 becomes +0."""
    if isinstance(a, types.Float) and a == b:
        return a(a, b), _fma_codegen


@njit
def dot3(a0, a1, a2, b0, b1, b2):
    """A 3-term dot product as OpenBLAS's gemm forms one entry of a matrix product (from a
    zero accumulator: a zero sum is +0, never -0)."""
    return _fma(a2, b2, _fma(a1, b1, _fma0(a0, b0)))


@njit
def dot4(a0, a1, a2, a3, b0, b1, b2, b3):
    """A 4-term dot product as OpenBLAS forms it (``a @ b`` of two 4-vectors, a matrix
    product's entry over four terms): an FMA chain in order, from a zero accumulator."""
    return _fma(a3, b3, _fma(a2, b2, _fma(a1, b1, _fma0(a0, b0))))
