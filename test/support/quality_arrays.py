"""Checks shared by the tests of the quality arrays written as bytes
(``segment_quality_cdr``, ``cluster_uncertainty_cdr``)."""
import numpy as np
from rclpy.serialization import deserialize_message, serialize_message


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
