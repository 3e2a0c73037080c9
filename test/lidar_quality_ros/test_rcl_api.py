"""rcl_api: the rcl / rcutils C functions, loaded from the libraries rclpy mapped."""
import ctypes

from lidar_quality_ros import rcl_api


def test_loaded_once_from_rclpys_libraries_with_every_function():
    api = rcl_api.load()
    assert api is not None, rcl_api.why_not()  # rclpy is imported here, so rcl is mapped
    assert rcl_api.load() is api and rcl_api.why_not() == ""
    assert all(callable(f) for f in api)
    # a serialized message made and freed by rcutils, as the takers' buffers are
    msg = rcl_api.Serialized()
    alloc = api.allocator()
    assert api.init(ctypes.byref(msg), 64, ctypes.byref(alloc)) == 0
    assert msg.buffer_capacity == 64 and msg.buffer_length == 0
    assert api.fini(ctypes.byref(msg)) == 0


def test_an_rcl_error_carries_rcutils_message_and_resets_it():
    api = rcl_api.load()
    # rcl sets its error string on a null publisher, then returns an error code
    ret = api.publish(None, ctypes.byref(rcl_api.Serialized()), None)
    assert ret != 0
    err = rcl_api.rcl_error(f"rcl_publish_serialized_message failed ({ret})")
    assert isinstance(err, RuntimeError)
    text = str(err)
    assert text.startswith(f"rcl_publish_serialized_message failed ({ret}): ")
    assert "publisher" in text
    assert api.error().str.decode() == "error not set"   # reset: the next error starts clean
