"""Common shell of the suite's nodes: diagnostics, synchronisation parameters, warnings."""
from __future__ import annotations

from rclpy.node import Node

from .diagnostics import NodeDiagnostics
from .params import declare


class QualityNode(Node):
    """Base of ``lmd_node``, ``lms_node`` and ``mimo_node``."""

    def __init__(self, name: str, **kwargs):
        super().__init__(name, **kwargs)
        period = declare(self, "diagnostics_period", 1.0,
                         "Seconds between /diagnostics publications (0 disables them).",
                         min_value=0.0)
        self.diag = NodeDiagnostics(self, period_s=period)

    def declare_sync_parameters(self) -> dict:
        """Declare and return the input synchronisation parameters."""
        return dict(
            mode=declare(self, "sync_mode", "exact",
                         "How inputs are matched by header stamp: 'exact' (equal stamps) or "
                         "'approximate' (stamps within sync_slop).",
                         choices=("exact", "approximate")),
            slop_s=declare(self, "sync_slop", 0.05,
                           "Largest stamp spread [s] of a matched input set in approximate mode.",
                           min_value=0.0),
            queue_size=declare(self, "sync_queue_size", 10,
                               "Messages kept per input while waiting for their match; older "
                               "ones are dropped and counted in /diagnostics.", min_value=1),
            processing_queue_size=declare(
                self, "processing_queue_size", 2,
                "Matched frames waiting for processing; when the node falls behind, the "
                "oldest waiting frame is dropped (counted as overrun in /diagnostics).",
                min_value=1),
        )

    def stop_processing(self) -> None:
        """Finish the frame in progress and stop the frame worker (before any teardown)."""
        inputs = getattr(self, "inputs", None)
        if inputs is not None:
            inputs.close()

    def destroy_node(self):
        self.stop_processing()
        return super().destroy_node()

    def warn_input(self, key: str, message: str) -> None:
        """Throttled log warning plus a standing diagnostics warning for bad input."""
        self.get_logger().warn(message, throttle_duration_sec=5.0)
        self.diag.warn(key, message)
