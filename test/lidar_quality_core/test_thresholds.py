"""Publication thresholds: floor, per class, per range bin, on a hand-built frame."""
import numpy as np
import pytest
from lidar_quality_core.thresholds import (ConfidenceThresholds, from_parameters,
                                           parse_class_thresholds, parse_range_thresholds)

# boxes at 10, 40 and 70 m (bird's-eye), two classes
BOXES = np.array([[10, 0, 0, 4, 2, 1.5, 0], [0, 40, 0, 4, 2, 1.5, 0], [42, -56, 0, 4, 2, 1.5, 0],
                  [6, 8, 0, 0.6, 0.6, 1.7, 0], [24, 32, 0, 0.6, 0.6, 1.7, 0],
                  [0, -70, 0, 0.6, 0.6, 1.7, 0], [3, 4, 0, 4, 2, 1.5, 0]])
LABELS = ["car", "car", "car", "pedestrian", "pedestrian", "pedestrian", "car"]
CONF = np.array([0.45, 0.55, 0.65, 0.15, 0.25, 0.65, np.nan])


def test_largest_applicable_threshold_decides():
    th = from_parameters(0.1, "car:0.5 pedestrian:0.2", "30:0.3, 60:0.6")
    assert th.range_edges == (30.0, 60.0) and th.per_range == (0.0, 0.3, 0.6)
    assert th.bin_names() == ["0-30m", "30-60m", ">=60m"]
    assert th.bins(BOXES).tolist() == [0, 1, 2, 0, 1, 2, 0]
    kept, removed = th.keep(CONF, LABELS, BOXES)
    # car 10 m: max(0.1, 0.5, 0) = 0.5 > 0.45 | car 40 m: 0.5 <= 0.55 | car 70 m: 0.6 <= 0.65
    # ped 10 m: 0.2 > 0.15 | ped 40 m: 0.3 > 0.25 | ped 70 m: 0.6 <= 0.65 | NaN: removed
    assert kept.tolist() == [False, True, True, False, False, True, False]
    assert removed == {"removed.car.0-30m": 2, "removed.pedestrian.0-30m": 1,
                       "removed.pedestrian.30-60m": 1}


def test_no_threshold_keeps_everything_nan_included():
    kept, removed = ConfidenceThresholds().keep(CONF, LABELS, BOXES)
    assert kept.all() and not removed
    # a class threshold only for cars: NaN pedestrians pass, NaN cars do not
    kept, _ = from_parameters(0.0, "car:0.1", "").keep([np.nan, np.nan], ["car", "pedestrian"],
                                                      BOXES[:2])
    assert kept.tolist() == [False, True]


@pytest.mark.parametrize("cls, rng, match", [
    ("car", "", "expected class_name:value"),
    ("car:1.5", "", "expected class_name:value"),
    ("", "30", "expected from_metres:value"),
    ("", "far:0.2", "expected from_metres:value"),
    ("", "30:1.2", r"thresholds must lie in \[0, 1\]"),
    ("", "0:0.2", "positive and ascending"),
])
def test_malformed_tables_refused(cls, rng, match):
    with pytest.raises(ValueError, match=match):
        from_parameters(0.0, cls, rng)


def test_parsers():
    assert parse_class_thresholds("a:0.1,b:0.2") == {"a": 0.1, "b": 0.2}
    assert parse_range_thresholds("60:0.6 30:0.3") == ((30.0, 60.0), (0.0, 0.3, 0.6))
    assert parse_range_thresholds("") == ((), ())
