"""Cases and checks shared by the tests of the quality arrays written as bytes
(``segment_quality_cdr``, ``detection_quality_cdr``, ``cluster_uncertainty_cdr``)."""
import numpy as np
from rclpy.serialization import deserialize_message, serialize_message
from std_msgs.msg import Header


def random_header(rng) -> Header:
    """A header with a random stamp (negative seconds included) and frame_id length."""
    h = Header(frame_id="f" * int(rng.integers(0, 9)))
    h.stamp.sec, h.stamp.nanosec = int(rng.integers(-5, 2**31 - 1)), int(rng.integers(0, 10**9))
    return h


def random_version_fields(rng, seed: int) -> dict:
    """Random version-1 fields; the drift score NaN for even seeds, passthrough unless
    the seed is a multiple of 3."""
    return dict(version=1, drift_level=int(rng.integers(0, 6)),
                drift_score=float(np.float32(rng.uniform())) if seed % 2 else float("nan"),
                drift_window_frames=int(rng.integers(0, 60)),
                drift_quantities="q" * int(rng.integers(0, 7)), passthrough=bool(seed % 3))


def random_model_ids(rng) -> tuple[str, str]:
    """Confidence and IoU model ids of random lengths (empty included)."""
    return "m" * int(rng.integers(0, 9)), "r" * int(rng.integers(0, 9))


def decoded_like(data: bytes, want, message_class):
    """``data`` deserialized as ``message_class``, after checking that it has the length of
    ``want`` serialized by rclpy and the same header, model ids and version / drift
    fields (NaN-equal score); the entries are left to the caller."""
    assert len(data) == len(serialize_message(want))
    got = deserialize_message(data, message_class)
    assert got.header == want.header
    assert (got.confidence_model_id, got.iou_model_id) == (want.confidence_model_id,
                                                           want.iou_model_id)
    for k in ("version", "drift_level", "drift_window_frames", "drift_quantities",
              "passthrough"):
        assert getattr(got, k) == getattr(want, k), k
    np.testing.assert_array_equal(got.drift_score, want.drift_score)
    return got


def assert_entries_equal(got, want, exact, figures) -> None:
    """Entries of a decoded quality array against the message's: the ``exact`` fields
    equal, the float ``figures`` equal with NaN equal to NaN (field by field)."""
    assert len(got) == len(want)
    for a, b in zip(got, want):
        assert tuple(getattr(a, k) for k in exact) == tuple(getattr(b, k) for k in exact)
        np.testing.assert_array_equal([getattr(a, k) for k in figures],
                                      [getattr(b, k) for k in figures])
