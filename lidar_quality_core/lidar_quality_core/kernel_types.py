"""Array types for the explicit signatures of the package's compiled kernels (numba).

A kernel compiled for :func:`array_in` arguments accepts read-only arrays (a message's
buffer, a caller's frozen array) as well as writable ones; :func:`array_out` is for the
arrays it writes.
"""
from __future__ import annotations

from numba import types

__all__ = ["array_in", "array_out", "F1", "F2", "I1"]


def array_in(dtype, ndim: int = 1, layout: str = "C", aligned: bool = True) -> types.Array:
    """An input array type: read-only, so that read-only and writable arrays match it;
    with ``aligned=False`` also views whose items are not aligned (fields of a message's
    packed records; x86 reads them at the same speed)."""
    return types.Array(dtype, ndim, layout, readonly=True, aligned=aligned)


def array_out(dtype, ndim: int = 1) -> types.Array:
    """An output array type: writable, C-contiguous."""
    return types.Array(dtype, ndim, "C")


#: the input types the kernels use most: float64 vectors and matrices, int64 vectors
F1 = array_in(types.float64)
F2 = array_in(types.float64, 2)
I1 = array_in(types.int64)
