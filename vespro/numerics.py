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
import numpy as np
from numba.extending import intrinsic

from .jit import njit

__all__ = ["dot3", "dot4", "front_face_mask"]


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


@njit
def front_face_mask(T, face_normals, face_offsets):
    """:func:`vespro.imageedges.front_faces` of one pose ``T`` (4, 4), compiled, (F,) bool: the face test's
    products as NumPy's (``np.matmul``'s OpenBLAS order: ``dot3``, and for the offset its
    matrix-vector kernel's order), the same bits."""
    F = face_normals.shape[0]
    front = np.empty(F, np.bool_)
    for f in range(F):
        n0, n1, n2 = face_normals[f, 0], face_normals[f, 1], face_normals[f, 2]
        a0 = dot3(n0, n1, n2, T[0, 0], T[0, 1], T[0, 2])
        a1 = dot3(n0, n1, n2, T[1, 0], T[1, 1], T[1, 2])
        a2 = dot3(n0, n1, n2, T[2, 0], T[2, 1], T[2, 2])
        front[f] = face_offsets[f] + dot3(a1, a0, a2, T[1, 3], T[0, 3], T[2, 3]) < 0
    return front
