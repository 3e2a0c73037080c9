"""A multi-threaded rclpy executor that hands each ready callback to its pool once.

Why: rclpy 7.1 (Jazzy) yields a task from ``wait_for_ready_callbacks`` again and again
until a pool thread has started it, and ``MultiThreadedExecutor`` submits it again each
time. The spinning thread then loops at full speed, holding the GIL the pool thread needs
to start the task (ros2/rclpy#1223; changed after Jazzy). Measured in the test harness
(2-vCPU Intel Xeon, 2026-12-05): 21 clouds replayed in 1 s made about 5000 submissions,
0.5-8 s of CPU in the spinning thread, callbacks up to 2.6 s late and a bag player in the
same process up to 2.6 s behind its schedule.

Here a task submitted and not yet started is not submitted again: the spinning thread
waits, the GIL released, until a pool thread starts it. A task that started and is
suspended (a coroutine callback awaiting a future) is submitted again when it is yielded
again, as rclpy does.
"""
from __future__ import annotations

import threading
import weakref

from rclpy.executors import (ConditionReachedException, ExternalShutdownException,
                             MultiThreadedExecutor, ShutdownException, TimeoutException)

__all__ = ["SubmitOnceExecutor"]

_WAIT_S = 0.05  # longest wait for a pool thread to start a task before looking again


class SubmitOnceExecutor(MultiThreadedExecutor):
    """``MultiThreadedExecutor`` without the resubmission loop (module docstring)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        # task -> set once a pool thread has started it (weak: done tasks leave rclpy's list)
        self._started: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
        self.submissions = 0  # tasks handed to the pool (a test reads it)

    def _spin_once_impl(self, timeout_sec=None, wait_condition=lambda: False) -> None:
        try:
            handler, _entity, _node = self.wait_for_ready_callbacks(
                timeout_sec, None, wait_condition)
        except (ExternalShutdownException, ShutdownException, TimeoutException,
                ConditionReachedException):
            return
        started = self._started.get(handler)
        if started is not None and not started.is_set():
            started.wait(_WAIT_S)  # in the pool's queue: let a pool thread take it
            return
        started = threading.Event()
        self._started[handler] = started
        self.submissions += 1
        self._executor.submit(_run, handler, started)
        self._futures.append(handler)
        for future in self._futures[:]:
            if future.done():
                self._futures.remove(future)
                future.result()  # raise any exception of the callback here, as rclpy does


def _run(handler, started: threading.Event) -> None:
    started.set()
    handler()
