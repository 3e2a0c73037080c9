"""log_f32 against numpy's float32 log: the same bits where numpy runs its AVX2 / AVX512F
loop (x86-64 machines like this project's), within numpy's 3.83 ulp of the exact value
everywhere; numpy's special values."""
import numpy as np
import pytest
from float32_logs import log_array, numpy_runs_simd_log


def patterns(step: int, start: int = 0) -> np.ndarray:
    """Every ``step``-th float32 bit pattern (both signs, NaN, inf, subnormals)."""
    return np.arange(start, 1 << 32, step, dtype=np.uint64).astype(np.uint32).view(np.float32)


def ulp_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a - b| in float32 ulps (finite values of one sign)."""
    return np.abs(a.view(np.int32).astype(np.int64) - b.view(np.int32).astype(np.int64))


def test_same_bits_as_numpy():
    if not numpy_runs_simd_log():
        pytest.skip("numpy's float32 log here is not its AVX2/AVX512F loop (another "
                    "machine class): test_close_to_the_exact_log covers log_f32")
    x = patterns(253, start=17)                       # 17M patterns, all exponents
    with np.errstate(all="ignore"):
        ref = np.log(x)
    got = log_array(x)
    nan = np.isnan(ref)
    np.testing.assert_array_equal(np.isnan(got), nan)
    diff = np.flatnonzero(ref[~nan].view(np.uint32) != got[~nan].view(np.uint32))
    assert diff.size == 0, f"{diff.size} values differ, e.g. x = {x[~nan][diff[:5]]}"


def test_close_to_the_exact_log():
    x = patterns(4099, start=3)
    x = x[np.isfinite(x) & (x > 0)]
    exact = np.log(x.astype(np.float64)).astype(np.float32)
    got = log_array(x)
    assert ulp_distance(got, exact).max() <= 4
    # the largest error numpy states for its loop is at 0x3f486945 (3.83 ulp)
    worst = np.array([0x3F486945], np.uint32).view(np.float32)
    assert abs(float(log_array(worst)[0]) - np.log(float(worst[0]))) < 4 * 2.0 ** -24


def test_special_values():
    tiny = np.finfo(np.float32).tiny
    x = np.array([np.nan, -np.nan, -1.0, -np.inf, -1e-45, 0.0, -0.0, np.inf, 1.0, 2.0,
                  1e-45, tiny / 2, tiny, 0.5], np.float32)
    got = log_array(x)
    assert np.isnan(got[:5]).all()
    assert np.signbit(got[2:5]).all()                 # negative input: -NaN, as numpy
    np.testing.assert_array_equal(got[5:8], [-np.inf, -np.inf, np.inf])
    assert got[8] == 0.0 and not np.signbit(got[8])
    exact = np.log(x[9:].astype(np.float64))
    np.testing.assert_allclose(got[9:], exact, rtol=4 * 2.0 ** -24)   # subnormals too
