"""``log_f32`` over arrays, and whether numpy's own float32 log is the same function on
this machine (its AVX2 + FMA3 / AVX512F loop): the reference logs of the float32 log and
LMS entropy tests."""
import platform

import numpy as np
from lidar_quality_core.float32_log import log_f32
from numba import njit


@njit(error_model="numpy")
def _log_array(x, out):
    for i in range(x.shape[0]):
        out[i] = log_f32(x[i])


def log_array(x) -> np.ndarray:
    """``log_f32`` of every value of ``x`` (any shape), float32."""
    x = np.ascontiguousarray(x, dtype=np.float32)
    out = np.empty_like(x)
    _log_array(x.reshape(-1), out.reshape(-1))
    return out


def numpy_runs_simd_log() -> bool:
    """numpy's float32 log is its AVX2 + FMA3 or AVX512F loop on this machine."""
    from numpy._core._multiarray_umath import __cpu_features__ as f

    return (platform.machine().lower() in ("x86_64", "amd64")
            and bool(f.get("AVX512F") or (f.get("AVX2") and f.get("FMA3"))))


def reference_log(x) -> np.ndarray:
    """numpy's float32 log where it is log_f32's algorithm, else log_f32 itself (what the
    kernels compute there; test_float32_log holds it within 4 ulp of the exact log)."""
    if numpy_runs_simd_log():
        with np.errstate(all="ignore"):
            return np.log(np.asarray(x, dtype=np.float32))
    return log_array(x)
