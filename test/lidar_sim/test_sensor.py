"""Tests of the rotating-lidar model lidar_sim.sensor (beam layout, scan, noise model)."""
import numpy as np
import pytest

from lidar_sim.primitives import Primitives
from lidar_sim.sensor import (Scan, SensorConfig, beam_directions, column_azimuths, hdl32,
                              hdl64, scan, vls128)

QUIET = dict(range_noise_std=0.0, dropout_base=0.0, dropout_range=0.0, dropout_dark=0.0,
             intensity_noise_std=0.0, intensity_falloff_m=np.inf)


def wall(x=10.0, refl=0.6, cls=50, inst=7, width=400.0, yaw=0.0, y=0.0):
    """A thick vertical wall whose near face is the plane x = ``x`` (yaw 0)."""
    return Primitives(boxes=np.array([[x + 0.5, y, 0, 1.0, width, 400.0, yaw]]),
                      box_class=np.array([cls], np.int32), box_instance=np.array([inst], np.int32),
                      box_reflectivity=np.array([refl]), ground_z=None)


# ------------------------------------------------------------------------------ layout

def test_presets():
    for cfg, n, top, bottom in ((hdl64(), 64, 2.0, -24.8), (hdl32(), 32, 10.67, -30.67),
                                (vls128(), 128, 15.0, -25.0)):
        e = cfg.elevations_deg
        assert cfg.channels == n and len(e) == n and cfg.columns == 2048
        assert e[0] == pytest.approx(top) and e[-1] == pytest.approx(bottom)
        assert np.all(np.diff(e) < 0)  # ring 0 = top
    s = -np.diff(hdl64().elevations_deg)
    np.testing.assert_allclose(s[:31], 1 / 3, atol=0.01)  # upper block
    np.testing.assert_allclose(s[32:], 0.5, atol=0.03)  # lower block
    assert hdl64().elevations_deg[31] == pytest.approx(-8.33)
    np.testing.assert_allclose(-np.diff(hdl32().elevations_deg), 4 / 3, atol=0.01)
    e = vls128().elevations_deg
    s = -np.diff(e)
    near = np.abs(e[:-1]) < 3
    assert s[near].max() <= 0.13 and s[~near].max() > 0.5  # finer near the horizon
    assert hdl64(columns=1024, max_range=80.0).columns == 1024


def test_config_validation():
    with pytest.raises(ValueError):
        SensorConfig(np.array([-1.0, 0.0, 1.0]))  # ring 0 must be the top beam
    with pytest.raises(ValueError):
        SensorConfig(np.array([]))


def test_beam_directions_conventions():
    cfg = SensorConfig(np.array([10.0, 0.0, -10.0]), columns=8)
    d = beam_directions(cfg)
    assert d.shape == (3, 8, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0)
    np.testing.assert_allclose(np.rad2deg(np.arcsin(d[:, 0, 2])), [10, 0, -10])
    az = np.arctan2(d[1, :, 1], d[1, :, 0])
    # column 0 just left of straight back, clockwise from there, forward in the middle
    np.testing.assert_allclose(np.rad2deg(az), [157.5, 112.5, 67.5, 22.5, -22.5, -67.5,
                                                -112.5, -157.5])
    np.testing.assert_allclose(column_azimuths(cfg), az)
    # the SemanticKITTI range-image projection maps each beam back to its column
    cfg = hdl64()
    a = column_azimuths(cfg)
    u = np.floor(0.5 * (1 - a / np.pi) * cfg.columns).astype(int)
    np.testing.assert_array_equal(u, np.arange(cfg.columns))
    off = column_azimuths(SensorConfig(np.array([0.0]), columns=8, azimuth_offset_deg=10))
    np.testing.assert_allclose(np.rad2deg(off[1:3]), [122.5, 77.5])
    assert np.all((off >= -np.pi) & (off < np.pi))


# ------------------------------------------------------------------------------ scan

def test_ground_only_point_count_hdl64():
    h = 1.73
    P = Primitives(ground_z=-h)
    cfg = hdl64(**QUIET)
    s = scan(P, cfg, 0)
    e = np.deg2rad(cfg.elevations_deg)
    with np.errstate(divide="ignore"):
        r = np.where(e < 0, h / np.sin(-e), np.inf)
    seen = (r <= cfg.max_range) & (r >= cfg.min_range)
    assert len(s) == seen.sum() * cfg.columns
    # beams above the horizon and those reaching the ground beyond 120 m give nothing
    # 7 beams at or above the horizon (+2.0 ... +0.0006 deg) and 2 (-0.33, -0.67 deg) that
    # reach the ground beyond 120 m (asin(1.73 / 120) = 0.83 deg)
    assert (e >= 0).sum() == 7 and (np.isinf(r) | (r > 120)).sum() == 9
    assert len(s) == (64 - 9) * 2048
    np.testing.assert_allclose(s.range, r[s.ring], rtol=1e-6)
    np.testing.assert_allclose(s.xyz[:, 2], -h, atol=1e-4)
    # xyz along the beam of (ring, column)
    d = beam_directions(cfg)[s.ring, s.column]
    np.testing.assert_allclose(s.xyz, d * s.range[:, None], rtol=1e-5, atol=1e-4)
    # the default noise and dropout model removes a small share of the points
    s2 = scan(P, hdl64(), 1)
    assert 0.85 * len(s) < len(s2) < len(s)


def test_point_order_dtypes_and_ranges():
    P = Primitives(ground_z=-1.73)
    s = scan(P, hdl32(columns=256), 3)
    assert isinstance(s, Scan)
    assert s.xyz.dtype == np.float32 and s.xyz.shape == (len(s), 3)
    assert s.intensity.dtype == np.float32 and s.range.dtype == np.float32
    assert s.ring.dtype == np.uint16 and s.column.dtype == np.uint16
    assert s.semantic.dtype == np.int32 and s.instance.dtype == np.int32
    assert np.all((s.intensity >= 0) & (s.intensity <= 1))
    # column-major (firing order): by column, then top ring down
    key = s.column.astype(np.int64) * 1000 + s.ring
    assert np.all(np.diff(key) > 0)
    assert s.column.min() == 0 and s.column.max() == 255
    assert np.all(s.range >= 0.9) and np.all(s.range <= 120)


def test_wall_ranges_and_ground_truth():
    cfg = SensorConfig(np.array([5.0, 0.0, -5.0]), columns=720, **QUIET)
    s = scan(wall(10.0, refl=0.6, cls=50, inst=7), cfg, 0)
    d = beam_directions(cfg)[s.ring, s.column]
    np.testing.assert_allclose(s.range, 10.0 / d[:, 0], rtol=1e-6)
    dd = beam_directions(cfg)[..., 0]
    assert len(s) == np.sum((dd > 0) & (10.0 / dd <= cfg.max_range))
    assert np.all(s.semantic == 50) and np.all(s.instance == 7)


def test_intensity_falls_with_incidence():
    cfg = SensorConfig(np.array([0.0]), columns=360, **QUIET)
    s = scan(wall(10.0, refl=0.8), cfg, 0)
    az = column_azimuths(cfg)[s.column]
    np.testing.assert_allclose(s.intensity, 0.8 * np.cos(az), rtol=1e-5)
    near, grazing = np.abs(az) < np.deg2rad(10), np.abs(az) > np.deg2rad(70)
    assert s.intensity[near].min() > 2.5 * s.intensity[grazing].max()
    # a wall tilted by 60 deg: head-on beams now come in at 60 deg
    tilted = wall(10.0, refl=0.8, yaw=np.deg2rad(60), width=30.0)
    t = scan(tilted, cfg, 0)
    az = column_azimuths(cfg)[t.column]
    i0 = np.argmin(np.abs(az))
    assert t.intensity[i0] == pytest.approx(0.8 * np.cos(np.deg2rad(60)), rel=0.02)
    # mild range falloff on top of it
    far = scan(wall(60.0, refl=0.8), SensorConfig(np.array([0.0]), columns=360,
                                                  **{**QUIET, "intensity_falloff_m": 300.0}), 0)
    near_ = scan(wall(10.0, refl=0.8), SensorConfig(np.array([0.0]), columns=360,
                                                    **{**QUIET, "intensity_falloff_m": 300.0}), 0)
    c = (far.column == 180)
    assert far.intensity[c][0] < near_.intensity[near_.column == 180][0] < 0.8


def test_dark_surfaces_drop_more_returns():
    cfg = SensorConfig(np.linspace(10, -10, 64), columns=1024,
                       **{**QUIET, "dropout_dark": 0.4})
    two = Primitives(  # bright wall on the left (y > 0), dark one on the right
        boxes=np.array([[20.5, 50.0, 0, 1.0, 100, 400, 0.0], [20.5, -50.0, 0, 1.0, 100, 400, 0.0]]),
        box_class=np.array([1, 2], np.int32), box_instance=np.array([1, 2], np.int32),
        box_reflectivity=np.array([0.9, 0.05]), ground_z=None)
    s = scan(two, cfg, np.random.default_rng(0))
    ref = scan(two, SensorConfig(cfg.elevations_deg, columns=1024, **QUIET), 0)
    n_bright, n_dark = np.sum(ref.semantic == 1), np.sum(ref.semantic == 2)
    assert n_bright == n_dark > 10000  # symmetric scene: same number of beams on each
    bright, dark = np.sum(s.semantic == 1), np.sum(s.semantic == 2)
    assert bright / n_bright == pytest.approx(1 - 0.4 * 0.1 ** 2, abs=0.01)
    assert dark / n_dark == pytest.approx(1 - 0.4 * 0.95 ** 2, abs=0.015)
    assert dark < 0.75 * bright


def test_dropout_grows_with_range():
    cfg = SensorConfig(np.linspace(5, -5, 32), columns=1024,
                       **{**QUIET, "dropout_base": 0.02, "dropout_range": 0.5})
    d = beam_directions(cfg)
    fwd = np.abs(np.arctan2(d[..., 1], d[..., 0])) < np.deg2rad(30)
    kept = {}
    for x in (10.0, 100.0):
        s = scan(wall(x, refl=1.0), cfg, np.random.default_rng(1))
        kept[x] = np.sum(fwd[s.ring, s.column]) / fwd.sum()
        expect = np.mean(1 - 0.02 - 0.5 * (x / d[fwd][:, 0] / 120) ** 2)
        assert kept[x] == pytest.approx(expect, abs=0.015)
    assert kept[100.0] < kept[10.0] - 0.3


def test_range_noise_statistics():
    cfg = SensorConfig(np.linspace(5, -5, 32), columns=1024, **{**QUIET, "range_noise_std": 0.05})
    s = scan(wall(10.0), cfg, np.random.default_rng(2))
    d = beam_directions(cfg)[s.ring, s.column]
    err = s.range - 10.0 / d[:, 0]
    assert len(err) > 10000
    assert abs(err.mean()) < 0.003 and err.std() == pytest.approx(0.05, rel=0.05)
    # the noise is along the beam
    np.testing.assert_allclose(s.xyz / s.range[:, None], d, atol=1e-5)


def test_min_and_max_range():
    cfg = SensorConfig(np.array([1.0, -1.0]), columns=64, **QUIET)
    cage = Primitives(boxes=np.array([[0.0, 0, 0, 1.0, 1.0, 1.0, 0.0]]),
                      box_class=np.array([1], np.int32), box_instance=np.array([1], np.int32),
                      box_reflectivity=np.array([0.5]), ground_z=None)
    assert len(scan(cage, cfg, 0)) == 0  # everything at 0.5 m < min_range
    assert len(scan(wall(150.0), cfg, 0)) == 0
    assert len(scan(wall(110.0), cfg, 0)) > 0


def test_origin_offset_and_regions():
    P = Primitives(ground_z=-1.73, ground_regions=np.array([[-1e3, 1e3, -3.0, 3.0]]),
                   ground_class=np.array([40], np.int32), ground_reflectivity=np.array([0.2]),
                   default_ground_class=72)
    cfg = SensorConfig(np.array([-30.0]), columns=64, **QUIET)
    s = scan(P, cfg, 0, origin=(0, 0, 1.0))
    np.testing.assert_allclose(s.range, 2.73 / np.sin(np.deg2rad(30)), rtol=1e-6)
    np.testing.assert_allclose(s.xyz[:, 2], -2.73, atol=1e-4)  # relative to the sensor
    lateral = np.abs(s.xyz[:, 1]) <= 3.0
    assert np.all(s.semantic[lateral] == 40) and np.all(s.semantic[~lateral] == 72)
    assert lateral.any() and (~lateral).any()


def test_seeded_scans_are_reproducible():
    P = Primitives(ground_z=-1.73)
    cfg = hdl32(columns=512)
    a, b, c = scan(P, cfg, 5), scan(P, cfg, 5), scan(P, cfg, 6)
    for f in ("xyz", "intensity", "ring", "column", "semantic", "instance", "range"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    assert len(a) != len(c) or not np.array_equal(a.range, c.range)
