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

__all__ = ["dot3", "dot4", "transform_point", "front_face_mask", "pairwise_sum"]


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
def transform_point(T, p0, p1, p2):
    """``T[:3, :3] @ p + T[:3, 3]`` of one point as NumPy's ``P @ R.T + t`` forms it (each
    row as OpenBLAS's gemm, :func:`dot3`, then the translation): (x, y, z)."""
    return (dot3(p0, p1, p2, T[0, 0], T[0, 1], T[0, 2]) + T[0, 3],
            dot3(p0, p1, p2, T[1, 0], T[1, 1], T[1, 2]) + T[1, 3],
            dot3(p0, p1, p2, T[2, 0], T[2, 1], T[2, 2]) + T[2, 3])


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


@njit
def _pairwise_block(a, lo, n):
    """One leaf of NumPy's pairwise summation: ``n <= 128`` terms, eight accumulators; in
    ``a``'s own type (float32 or float64)."""
    if n < 8:
        res = np.zeros(1, a.dtype)[0]
        for k in range(n):
            res += a[lo + k]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    k = 8
    m = n - n % 8
    while k < m:
        r0 += a[lo + k]
        r1 += a[lo + k + 1]
        r2 += a[lo + k + 2]
        r3 += a[lo + k + 3]
        r4 += a[lo + k + 4]
        r5 += a[lo + k + 5]
        r6 += a[lo + k + 6]
        r7 += a[lo + k + 7]
        k += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while k < n:
        res += a[lo + k]
        k += 1
    return res


@njit
def pairwise_sum(a, n):
    """``a[:n].sum()`` of a float32 or float64 array with NumPy's pairwise summation (halves
    split at multiples of 8 down to blocks of at most 128, in the array's type): the same
    rounding as ``ndarray.sum`` along a row. The recursion is unrolled into a stack (numba's
    cache does not keep recursive functions)."""
    if n <= 128:
        return _pairwise_block(a, 0, n)
    st_lo = np.empty(192, np.int64)
    st_n = np.empty(192, np.int64)
    st_up = np.empty(192, np.bool_)  # both halves done: add them
    vals = np.empty(64, a.dtype)
    st_lo[0], st_n[0], st_up[0] = 0, n, False
    top, nv = 1, 0
    while top > 0:
        top -= 1
        lo, m, up = st_lo[top], st_n[top], st_up[top]
        if up:
            vals[nv - 2] = vals[nv - 2] + vals[nv - 1]
            nv -= 1
        elif m <= 128:
            vals[nv] = _pairwise_block(a, lo, m)
            nv += 1
        else:
            m2 = m // 2
            m2 -= m2 % 8
            st_lo[top], st_n[top], st_up[top] = lo, m, True
            st_lo[top + 1], st_n[top + 1], st_up[top + 1] = lo + m2, m - m2, False
            st_lo[top + 2], st_n[top + 2], st_up[top + 2] = lo, m2, False
            top += 3
    return vals[0]
