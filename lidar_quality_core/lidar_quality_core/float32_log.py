"""The natural logarithm of a float32 inside a compiled kernel (numba): :func:`log_f32`.

numpy's float32 ``np.log`` on x86-64 with AVX2 + FMA3 or AVX512F is a rational
approximation (numpy's ``simd_log_FLOAT``: mantissa in [sqrt(1/2), sqrt(2)), a 5/5
rational function of ``m - 1`` by fused multiply-adds, one division, plus the exponent
times ln 2; at most 3.83 ulp from the exact value). :func:`log_f32` performs the same
float32 operations in the same order, with numpy's coefficients, so on those machines
it returns the same bits as ``np.log`` for every float32 (the tests compare them), and
the features computed with it stay those the shipped models were trained on.

Why not ``np.log``: a kernel that needs the logarithm of values it reads (the entropy of
the LMS probabilities) would otherwise take them in a separate pass into a buffer, and
numpy's loop loads and stores through AVX masks, which cost several times the arithmetic
on AMD cores (3.3 ns per value on this project's 2-core machine, against 1.0 ns for this
function in a loop that LLVM vectorizes). Numba's own ``np.log`` in a kernel calls
libm's ``logf`` (correctly rounded, other bits, not vectorized).

numba's cache keys a kernel on its own file only: after a change here, delete the
caches of the kernels that inline this function (``lms/metric_kernels``' ``*.nbi`` /
``*.nbc``), or they keep the old code.

Use it in kernels compiled with ``error_model="numpy"`` (the division must not check for
zero, or the loop does not vectorize). Special values as numpy: NaN -> NaN, x < 0 ->
-NaN, +-0 -> -inf, +inf -> +inf; subnormals are scaled by 2**100 first, as numpy does.
"""
from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = ["log_f32"]

_F = np.float32
# numpy's NPY_COEFF_{P,Q}{0..5}_LOGf (numerator, denominator; index = power of m - 1)
_P0, _P1, _P2, _P3, _P4, _P5 = (_F(0.0), _F(9.999999999999998702752e-01),
                                _F(2.112677543073053063722e+00), _F(1.480000633576506585156e+00),
                                _F(3.808837741388407920751e-01), _F(2.589979117907922693523e-02))
_Q0, _Q1, _Q2, _Q3, _Q4, _Q5 = (_F(1.0), _F(2.612677543073109236779e+00),
                                _F(2.453006071784736363091e+00), _F(9.864942958519418960339e-01),
                                _F(1.546476374983906719538e-01), _F(5.875095403124574342950e-03))
_LN2 = _F(np.log(2.0))
_SQRT1_2 = _F(np.sqrt(0.5))
_FLT_MIN = np.finfo(np.float32).tiny
_TWO_100 = _F(2.0 ** 100)
_NAN, _INF = _F(np.nan), _F(np.inf)
_NEG_NAN_BITS = np.int32(np.array([0xFFC00000], np.uint32).view(np.int32)[0])


@intrinsic
def _bits(typingctx, x):
    """The int32 bit pattern of a float32."""
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(32))
    return types.int32(types.float32), codegen


@intrinsic
def _float(typingctx, b):
    """The float32 of an int32 bit pattern."""
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.FloatType())
    return types.float32(types.int32), codegen


@intrinsic
def _fma(typingctx, a, b, c):
    """``a * b + c`` rounded once (llvm.fma: the instruction where the CPU has it, an
    exact software fma otherwise)."""
    def codegen(context, builder, signature, args):
        f = ir.FloatType()
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(f, [f, f, f]),
                                            "llvm.fma.f32")
        return builder.call(fn, args)
    return types.float32(types.float32, types.float32, types.float32), codegen


@njit(inline="always")
def log_f32(x):
    """``np.log`` of one float32, branch-free (see the module doc)."""
    zero = _F(0.0)
    one = _F(1.0)
    negative = x < zero
    y = zero if negative else x
    subnormal = y < _FLT_MIN
    y = y * _TWO_100 if subnormal else y
    b = _bits(y)
    e = _F(np.int32((b >> 23) - 126))
    e = e - _F(100.0) if subnormal else e
    m = _float(np.int32((b & 0x7FFFFF) | (126 << 23)))          # in [0.5, 1)
    low = m <= _SQRT1_2
    m = m + m if low else m
    e = e - one if low else e
    m = m - one
    num = _fma(_fma(_fma(_fma(_fma(_P5, m, _P4), m, _P3), m, _P2), m, _P1), m, _P0)
    den = _fma(_fma(_fma(_fma(_fma(_Q5, m, _Q4), m, _Q3), m, _Q2), m, _Q1), m, _Q0)
    r = _fma(e, _LN2, num / den)
    r = _NAN if x != x else r
    r = _float(_NEG_NAN_BITS) if negative else r   # -NaN (-(NaN) keeps the sign)
    r = -_INF if x == zero else r
    return _INF if x == _INF else r
