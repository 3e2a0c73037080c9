"""``main()`` helper for the node executables: init, spin, clean exit on SIGINT / SIGTERM."""
from __future__ import annotations

import rclpy
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor


def run_node(node_factory, args=None, *, num_threads: int = 2) -> int:
    """Create the node, spin it until shut down and return the process exit code.

    rclpy's signal handlers turn SIGINT and SIGTERM into a context shutdown, which ends
    ``spin`` with ``ExternalShutdownException``: both exit with code 0. A node that
    cannot start (bad parameters, unreadable model) logs the reason and returns 2.
    """
    rclpy.init(args=args)
    node = None
    code = 0
    try:
        node = node_factory()
        executor = MultiThreadedExecutor(num_threads=num_threads)
        executor.add_node(node)
        try:
            executor.spin()
        finally:
            executor.shutdown(timeout_sec=1.0)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as exc:  # noqa: BLE001 - any start-up failure becomes exit code 2
        if node is not None:
            raise
        rclpy.logging.get_logger("lidar_quality").fatal(f"node failed to start: {exc}")
        code = 2
    finally:
        if node is not None:
            # The node's own logger would also publish to /rosout, whose context may
            # already be shut down by the signal.
            rclpy.logging.get_logger(node.get_name()).info("shutting down")
            node.destroy_node()
        rclpy.try_shutdown()
    return code
