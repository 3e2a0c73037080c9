"""runner: the executor internals the orderly shutdown relies on (rclpy Jazzy)."""
import rclpy
from lidar_quality_ros import runner
from rclpy.context import Context


def test_executor_internals_are_the_ones_the_shutdown_uses():
    # _Stoppable reaches into rclpy's executors (Jazzy's shutdown skips its wait for
    # callbacks in flight): if a release renames these, it falls back to a plain shutdown
    # and this test fails, so the workaround is revisited rather than silently gone
    ctx = Context()
    rclpy.init(context=ctx)  # the test run's own domain, on loopback
    try:
        for cls in (runner._StoppableExecutor, runner._DrainingExecutor):
            ex = cls(context=ctx)
            try:
                assert hasattr(ex, "_shutdown_lock") and hasattr(ex, "_is_shutdown")
                assert hasattr(ex, "_guard")
                if cls is runner._DrainingExecutor:
                    assert hasattr(ex, "_work_tracker") and hasattr(ex, "_executor")
            finally:
                ex.shutdown(timeout_sec=0)
    finally:
        ctx.try_shutdown()
