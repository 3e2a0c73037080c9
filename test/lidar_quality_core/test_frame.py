"""The processors' frame contract (lidar_quality_core.frame)."""
from lidar_quality_core.frame import FrameOutputs, FrameRejected
from lidar_quality_core.pointcloud import CloudFormatError
from lidar_quality_core.transforms import NoTransformError
from mimo_ros.pipeline import NoHeadError


def test_every_rejection_names_its_drop_reason():
    # the reasons are the /diagnostics dropped.<reason> keys and process_bag's summary keys
    reasons = {cls: cls("x").reason for cls in (FrameRejected, CloudFormatError,
                                               NoHeadError, NoTransformError)}
    assert reasons == {FrameRejected: "processing_error", CloudFormatError: "malformed_cloud",
                       NoHeadError: "no_head", NoTransformError: "no_transform"}
    assert all(issubclass(c, ValueError) for c in reasons)     # callers catching ValueError
    assert CloudFormatError.cause == "cloud" and NoHeadError.cause is None


def test_outputs_default_to_nothing_to_warn_count_or_say():
    out = FrameOutputs({"output/points": 1})
    assert (out.markers, out.issues, out.counts, out.notes, out.values) == (None, {}, {}, [], {})
    assert FrameOutputs({}).issues is not out.issues          # no shared mutable default
