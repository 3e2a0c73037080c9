"""Common shell of the suite's nodes: diagnostics, synchronisation parameters, warnings,
the input watchdog, run-time parameter changes.

Never silent: bad input is logged once per cause and period (one cause does not hide
another) and shown in ``/diagnostics``; an input that never arrives, or stamps that
never match, are named after ``input_timeout`` seconds with the fix (WARN, then ERROR
after ``input_error_timeout``); another node of the same full name is reported. Every
parameter is read-only (read at start) unless the node applies changes
(:meth:`QualityNode.declare_live`), so ``ros2 param set`` is applied or refused, never
accepted and ignored.
"""
from __future__ import annotations

import threading
import time
from typing import Any, Callable

from diagnostic_msgs.msg import DiagnosticStatus
from lidar_quality_core.input_watchdog import InputWatchdog
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from .diagnostics import NodeDiagnostics
from .params import check_value, declare

_LEVEL = {0: DiagnosticStatus.OK, 1: DiagnosticStatus.WARN, 2: DiagnosticStatus.ERROR}


class QualityNode(Node):
    """Base of ``lmd_node``, ``lms_node`` and ``mimo_node``."""

    #: seconds between two log lines of the same warning cause
    warn_period_s = 5.0

    def __init__(self, name: str, **kwargs):
        super().__init__(name, **kwargs)
        self._live: dict[str, tuple[Callable[[Any], None], dict]] = {}
        self.add_on_set_parameters_callback(self._on_set_parameters)
        period = declare(self, "diagnostics_period", 1.0,
                         "Seconds between /diagnostics publications (0 disables them).",
                         min_value=0.0)
        window = declare(self, "diagnostics_window", 10.0,
                         "Seconds over which /diagnostics measures the fraction of lost "
                         "frames.", min_value=0.1)
        drop_warn = declare(self, "drop_warn_fraction", 0.05,
                            "Fraction of frames lost over diagnostics_window above which "
                            "/diagnostics reports WARN.", min_value=0.0, max_value=1.0)
        drop_error = declare(self, "drop_error_fraction", 0.25,
                             "Fraction of frames lost over diagnostics_window above which "
                             "/diagnostics reports ERROR (>= drop_warn_fraction).",
                             min_value=0.0, max_value=1.0)
        if drop_error < drop_warn:
            raise ValueError(f"parameter 'drop_error_fraction' = {drop_error} is below "
                             f"'drop_warn_fraction' = {drop_warn}")
        self.input_timeout = declare(
            self, "input_timeout", 2.0,
            "Seconds without a matched input set, while inputs arrive, after which the node "
            "logs which input is missing (or how far apart the stamps are) and /diagnostics "
            "reports WARN.", min_value=0.1)
        self.input_error_timeout = declare(
            self, "input_error_timeout", 10.0,
            "Seconds without a matched input set, while inputs arrive, after which "
            "/diagnostics reports ERROR (>= input_timeout).", min_value=0.1)
        if self.input_error_timeout < self.input_timeout:
            raise ValueError(f"parameter 'input_error_timeout' = {self.input_error_timeout} "
                             f"is below 'input_timeout' = {self.input_timeout}")
        self.diag = NodeDiagnostics(self, period_s=period, window_s=window,
                                    drop_warn=drop_warn, drop_error=drop_error)
        self._warned: dict[str, float] = {}
        self._warn_lock = threading.Lock()
        self._input_hints: dict[str, str] = {}
        self._issue_keys: set[str] = set()
        self._sync_params: dict = {}
        self._ticks = 0
        self._check_timer = None

    # ------------------------------------------------------------------ parameters
    def declare_sync_parameters(self) -> dict:
        """Declare and return the input synchronisation parameters."""
        self._sync_params = dict(
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
        return dict(self._sync_params)

    def declare_live(self, name: str, default: Any, description: str,
                     apply: Callable[[Any], None], **checks) -> Any:
        """Declare a parameter that ``ros2 param set`` changes at run time: a new value is
        checked (``min_value``, ``max_value``, ``choices``) and passed to ``apply``."""
        value = declare(self, name, default, description, read_only=False, **checks)
        self._live[name] = (apply, checks)
        return value

    def _on_set_parameters(self, params) -> SetParametersResult:
        for p in params:
            if p.name not in self._live:
                continue  # read-only ones never get here; use_sim_time is rclpy's own
            try:
                check_value(p.name, p.value, **self._live[p.name][1])
            except ValueError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
        for p in params:
            if p.name in self._live:
                self._live[p.name][0](p.value)
                self.get_logger().info(f"parameter {p.name} set to {p.value!r}")
        return SetParametersResult(successful=True)

    # ------------------------------------------------------------------ warnings
    def warn_input(self, key: str, message: str, level=DiagnosticStatus.WARN) -> None:
        """A log warning (at most once per ``warn_period_s`` for this cause) plus a standing
        diagnostics warning for bad or missing input."""
        now = time.monotonic()
        with self._warn_lock:
            last = self._warned.get(key)
            due = last is None or now - last >= self.warn_period_s
            if due:
                self._warned[key] = now
        # one call site per severity: rclpy refuses to log one call site at two severities
        if due and level == DiagnosticStatus.ERROR:
            self.get_logger().error(message)
        elif due:
            self.get_logger().warn(message)
        self.diag.warn(key, message, level)

    def report_issues(self, issues: dict[str, str]) -> None:
        """Warn each input problem of a frame under its own cause; clear the causes of
        earlier frames that this frame does not have (shown for a while longer)."""
        for key, text in issues.items():
            self.warn_input(key, text)
        for key in self._issue_keys - issues.keys():
            self.diag.clear(key)
        self._issue_keys |= issues.keys()

    # ------------------------------------------------------------------ watchdog
    def new_watchdog(self, n_inputs: int) -> InputWatchdog:
        """An ``InputWatchdog`` with the node's timeouts, for its ``SyncedInputs``."""
        return InputWatchdog(n_inputs, self.input_timeout, self.input_error_timeout,
                             start_s=time.monotonic())

    def watch_inputs(self, hints: dict[str, str] | None = None) -> None:
        """Check ``self.inputs`` (a ``SyncedInputs`` with a watchdog) every second;
        ``hints``: per input name, what else fixes its absence (a parameter)."""
        self._input_hints = dict(hints or {})
        self._check_timer = self.create_timer(
            1.0, self._check, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def input_fix(self, index: int) -> tuple[str, str]:
        """``("<name> (subscribed as <resolved topic>)", "remap it ... [or <hint>]")`` of
        input ``index`` of ``self.inputs``: how a log line names an absent input and its fix."""
        name = self.inputs.topics[index]
        resolved = self.inputs.subscriptions[index].topic_name
        hint = self._input_hints.get(name)
        return (f"{name} (subscribed as {resolved})",
                f"remap it to your topic (--ros-args -r {name}:=<topic>)"
                + (f" or {hint}" if hint else ""))

    def _check(self) -> None:
        self._ticks += 1
        inputs = getattr(self, "inputs", None)
        if inputs is not None and inputs.watchdog is not None:
            self._check_watchdog(inputs)
        if self._ticks % 5 == 2:
            self._check_duplicate_name()

    def _check_watchdog(self, inputs) -> None:
        v = inputs.watchdog.check(time.monotonic())
        self.diag.set_value("inputs.state", v.cause)
        if v.cause in ("ok", "idle"):
            self.diag.clear("inputs")
            return
        names = inputs.topics
        if v.cause == "missing":
            parts = ["{} has received nothing: {}".format(*self.input_fix(i)) for i in v.missing]
            arriving = [names[i] for i in range(len(names)) if i not in v.missing]
            msg = (f"no frame for {v.silent_s:.0f} s: " + "; ".join(parts)
                   + f" (arriving: {', '.join(arriving)})")
        else:
            worst = max(range(len(names)), key=lambda i: v.offset_ns[i])
            off_ms = v.offset_ns[worst] / 1e6
            sync = self._sync_params
            if sync.get("mode") == "approximate":
                fix = (f"sync_slop is {1e3 * sync['slop_s']:.1f} ms: raise it above "
                       f"{off_ms:.1f} ms")
            else:
                fix = (f"set sync_mode: approximate with sync_slop above {off_ms:.1f} ms "
                       "(or stamp the inputs with their cloud's stamp)")
            msg = (f"no frame for {v.silent_s:.0f} s: inputs arrive but never match; nearest "
                   f"stamp offset between {names[0]} and {names[worst]} is {off_ms:.1f} ms; "
                   + fix)
        self.warn_input("inputs", msg, _LEVEL[v.level])

    def _check_duplicate_name(self) -> None:
        me = (self.get_name(), self.get_namespace())
        n = sum(1 for entry in self.get_node_names_and_namespaces() if entry == me)
        if n > 1:
            full = self.get_fully_qualified_name()
            self.warn_input("duplicate_name",
                            f"{n} nodes are named {full}: each publishes every output, so "
                            "consumers get everything twice; stop one or give it another "
                            "name or namespace (--ros-args -r __node:=<name> / -r __ns:=<ns>)")
        else:
            self.diag.clear("duplicate_name")

    # ------------------------------------------------------------------ teardown
    def stop_processing(self) -> None:
        """Finish the frame in progress and stop the frame worker (before any teardown)."""
        inputs = getattr(self, "inputs", None)
        if inputs is not None:
            inputs.close()

    def destroy_node(self):
        self.stop_processing()
        return super().destroy_node()
