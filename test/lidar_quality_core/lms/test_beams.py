"""lidar_quality_core.lms.beams: ring field names, per-beam elevations estimated from a
cloud and kept across frames, the rows they give (elevation table or rank), presets."""
import numpy as np
import pytest
from lidar_quality_core.lms.beams import (RING_FIELD_NAMES, BeamTable, beam_elevations,
                                          elevation_deg, elevation_rows, find_ring_field,
                                          load_presets, parse_degrees, ring_field_names,
                                          rows_of_beams)
from lidar_quality_core.lms.projection import RangeImageConfig

# VLP-16 laser order (firing order): elevation of laser id 0..15, interleaved
VLP16_LASERS = (-15, 1, -13, 3, -11, 5, -9, 7, -7, 9, -5, 11, -3, 13, -1, 15)


def beam_cloud(elevations, per_beam=50, seed=0, noise=0.02):
    """(xyz, beam index) of points on cones of the given elevations, beam index = position
    in ``elevations``, ranges 2..30 m, all azimuths."""
    rng = np.random.default_rng(seed)
    b = np.repeat(np.arange(len(elevations)), per_beam)
    el = np.radians(np.asarray(elevations, float)[b] + rng.normal(0, noise, len(b)))
    az = rng.uniform(-np.pi, np.pi, len(b))
    r = rng.uniform(2, 30, len(b))
    xyz = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], 1)
    return xyz.astype(np.float32), b


def test_ring_field_names():
    assert ring_field_names("auto") == RING_FIELD_NAMES
    assert ring_field_names("AUTO")[:2] == ("ring", "channel")
    assert ring_field_names("ring") == ("ring",)
    assert ring_field_names(" laser_id, ring ") == ("laser_id", "ring")
    for bad in ("", " , "):
        with pytest.raises(ValueError, match="names no field"):
            ring_field_names(bad)


def test_find_ring_field_takes_the_first_candidate_the_cloud_has():
    assert find_ring_field(["x", "y", "z", "channel"], "auto") == "channel"
    assert find_ring_field(["x", "channel", "ring"], "auto") == "ring"
    assert find_ring_field(["x", "channel", "ring"], "channel, ring") == "channel"
    assert find_ring_field(["x", "channel"], "ring") is None     # `ring_field: ring` as before
    assert find_ring_field(["x", "y", "z"], "auto") is None


def test_elevation_deg_and_invalid_points():
    xyz = np.array([[1, 0, 1], [0, 0, 0], [np.nan, 0, 0], [0, 2, -2]], np.float32)
    el = elevation_deg(xyz)
    assert el[0] == pytest.approx(45) and el[3] == pytest.approx(-45)
    assert np.isnan(el[1]) and np.isnan(el[2])


def test_beam_elevations_is_the_median_per_beam():
    beam = np.array([0, 0, 0, 2, 2, 2, 2, 1, 1, 5])
    el = np.array([1.0, 3.0, 2.0, -1, -4, -2, -3, np.nan, 7.0, 9.0])
    out = beam_elevations(beam, el, 4)
    assert out[0] == 2.0 and out[2] == -2.5
    assert np.isnan(out[1])        # 1 finite point < 3
    assert np.isnan(out[3])        # no point; beam 5 is beyond n_beams and ignored


def test_interleaved_beams_take_rows_by_elevation():
    # beam index = VLP-16 laser id: rows must go down the elevations, not the ids
    xyz, b = beam_cloud(VLP16_LASERS)
    table = BeamTable(16)
    assert table.update(b, elevation_deg(xyz)) and table.n_known == 16
    np.testing.assert_allclose(table.elevations, VLP16_LASERS, atol=0.05)
    rank = table.rows(None, 16)
    expect = np.argsort(np.argsort(-np.asarray(VLP16_LASERS)))
    np.testing.assert_array_equal(rank, expect)
    # the elevation table of the sensor (any order) gives the same rows
    cfg = RangeImageConfig.from_elevations(sorted(VLP16_LASERS, reverse=True), 1800)
    np.testing.assert_array_equal(rows_of_beams(table.elevations, cfg, 16), expect)
    # fewer rows than beams: the lowest beams have none (counted by the caller)
    assert (table.rows(None, 10) == -1).sum() == 6


def test_beam_table_keeps_its_first_estimates_and_adds_new_beams():
    xyz, b = beam_cloud([10, 0, -10])
    t = BeamTable(8)
    t.update(b[b < 2], elevation_deg(xyz)[b < 2])
    v, first = t.version, t.elevations.copy()
    assert t.n_known == 2 and np.isnan(t.elevations[2])
    rows = t.rows(None, 3)
    assert rows[:3].tolist() == [0, 1, -1]
    # a later frame: beam 2 appears, beams 0 / 1 move a little (noise): kept as they were
    xyz2, b2 = beam_cloud([10.3, 0.3, -10], seed=1)
    assert t.update(b2, elevation_deg(xyz2)) and t.version == v + 1
    np.testing.assert_array_equal(t.elevations[:2], first[:2])
    assert t.rows(None, 3)[:3].tolist() == [0, 1, 2]
    assert not t.update(b2, elevation_deg(xyz2))     # nothing new: rows stay cached


def test_rows_of_beams_outside_the_table_and_elevation_rows():
    cfg = RangeImageConfig.from_elevations([2.0, 0.0, -2.0], 100)   # edges 3, 1, -1, -3
    rows = rows_of_beams([2.9, 0.5, -1.5, -3.5, np.nan], cfg, 3)
    assert rows.tolist() == [0, 1, 2, -1, -1]
    assert elevation_rows([3.1, 1.2, 0.9, np.nan], cfg).tolist() == [-1, 0, 1, -1]


def test_parse_degrees():
    assert parse_degrees("15, 13 ,-1.5") == (15.0, 13.0, -1.5)
    assert parse_degrees("") == () and parse_degrees("[2, -2]") == (2.0, -2.0)
    assert parse_degrees([1, 2.5]) == (1.0, 2.5)
    with pytest.raises(ValueError, match="'abc'"):
        parse_degrees("1, abc")
    with pytest.raises(ValueError, match="outside"):
        parse_degrees("95")


def test_presets_from_yaml(tmp_path):
    p = tmp_path / "s.yaml"
    p.write_text("A:\n  channels: 3\n  fov_up_deg: 2\n  fov_down_deg: -2\n"
                 "  azimuth_resolution_deg: 0.2\n"
                 "B:\n  elevations_deg: [-1, 5, 2]\n  azimuth_resolution_deg: 0.1\n")
    pr = load_presets(p)
    assert pr["A"].elevations_deg == (2.0, 0.0, -2.0) and pr["A"].width == 1800
    assert pr["B"].elevations_deg == (5.0, 2.0, -1.0) and pr["B"].channels == 3
    assert pr["B"].range_config().shape == (3, 3600)


@pytest.mark.parametrize("text, word", [
    ("A:\n  channels: 3\n  azimuth_resolution_deg: 0.2\n", "needs elevations_deg"),
    ("A:\n  elevations_deg: [1, 2]\n  channels: 3\n  azimuth_resolution_deg: 0.2\n",
     "channels 3 but 2"),
    ("A:\n  elevations_deg: [1, 1]\n  azimuth_resolution_deg: 0.2\n", "same elevation"),
    ("A:\n  elevations_deg: [1, 2]\n", "azimuth_resolution_deg"),
    ("A:\n  elevations_deg: [1, 2]\n  azimuth_resolution_deg: 0.2\n  rows: 2\n",
     "unknown keys"),
    ("- A\n", "mapping"),
])
def test_bad_presets_are_named(tmp_path, text, word):
    p = tmp_path / "s.yaml"
    p.write_text(text)
    with pytest.raises(ValueError, match=word):
        load_presets(p)
