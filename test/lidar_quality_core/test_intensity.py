"""Intensity scale (lidar_quality_core.intensity): auto recognises 0..1 and 0..255 clouds."""
import numpy as np
import pytest

from lidar_quality_core.intensity import AUTO_FRAMES, IntensityScale


def test_fixed_modes():
    v = np.array([0.0, 100.0, 255.0], np.float32)
    assert IntensityScale("unit").scale(v) is not None
    np.testing.assert_array_equal(IntensityScale("unit").scale(v), v)
    np.testing.assert_allclose(IntensityScale("byte").scale(v), [0, 100 / 255, 1], rtol=1e-6)
    with pytest.raises(ValueError, match="intensity_scale"):
        IntensityScale("percent")


def test_auto_recognises_unit_and_byte_clouds():
    rng = np.random.default_rng(0)
    unit = rng.uniform(0, 1, 1000).astype(np.float32)
    byte = np.round(unit * 255).astype(np.float32)
    a, b = IntensityScale(), IntensityScale()
    sa, sb = a.scale(unit), b.scale(byte)
    assert (a.decided, b.decided) == ("unit", "byte")
    assert "[0, 1]" in a.note and "0..255" in b.note
    np.testing.assert_allclose(sa, sb, atol=0.5 / 255 + 1e-7)  # the same scan, both scales
    assert a.scale(unit) is not None and a.note is None     # decided: said once


def test_auto_changes_its_mind_only_within_the_first_frames():
    s = IntensityScale()
    s.factor(np.array([0.2, 0.4]))          # a dark first frame of a 0..255 sensor
    assert s.decided == "unit"
    assert s.factor(np.array([3.0, 200.0])) == pytest.approx(1 / 255)
    assert s.decided == "byte" and "changed after the first frames" in s.note
    late = IntensityScale()
    for _ in range(AUTO_FRAMES):
        late.factor(np.array([0.5]))
    assert late.factor(np.array([200.0])) == 1.0 and late.note is None   # fixed by then


def test_auto_ignores_non_finite_and_empty_and_names_16_bit_values():
    s = IntensityScale()
    assert s.factor(np.array([np.nan, np.inf, 0.5])) == 1.0
    assert s.factor(np.zeros(0)) == 1.0
    w = IntensityScale()
    w.factor(np.array([40000.0]))
    assert w.decided == "byte" and "16-bit" in w.note
