"""Common shell of the suite's nodes: the frame contract (inputs matched, processed,
published, dropped or warned about and counted), diagnostics, synchronisation parameters,
warnings, the input watchdog, run-time parameter changes.

A node declares its parameters, builds its processor, creates its outputs
(:meth:`QualityNode.create_output`), subscribes (:meth:`QualityNode.start_inputs`) and
implements :meth:`QualityNode.process`: matched messages -> the processor's outputs
(``lidar_quality_core.frame``). The rest is here: timing, a ``FrameRejected`` frame
dropped and counted (with a throttled warning), the frame's issues warned per cause,
the messages published in order, the counts summed into ``/diagnostics``.

Never silent: bad input is logged once per cause and period (one cause does not hide
another) and shown in ``/diagnostics``; an input that never arrives, or stamps that
never match, are named after ``input_timeout`` seconds with the fix (WARN, then ERROR
after ``input_error_timeout``); another node of the same full name is reported. Every
parameter is read-only (read at start) unless the node applies changes
(``live`` in :meth:`QualityNode.declare_settings`), so ``ros2 param set`` is applied or refused, never
accepted and ignored.
"""
from __future__ import annotations

import functools
import threading
import time
from collections import Counter
from dataclasses import dataclass
from typing import Any, Callable, Sequence

from diagnostic_msgs.msg import DiagnosticStatus
from lidar_quality_core.frame import FrameRejected
from lidar_quality_core.input_watchdog import InputWatchdog
from lidar_quality_core.transforms import TransformBuffer
from lidar_quality_core.parameters import (ParamSpec, from_parameters, param,
                                           parameter_specs, validate)
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from .diagnostics import NodeDiagnostics
from .params import declare_spec
from .qos import output_qos
from .serialized_publish import is_serialized, publish_serialized
from .synced_inputs import SyncedInputs
from .threads import realtime_scheduling
from .tf_listener import TfListener

_LEVEL = {0: DiagnosticStatus.OK, 1: DiagnosticStatus.WARN, 2: DiagnosticStatus.ERROR}


@dataclass(frozen=True)
class CommonParameters:
    """Parameters every quality node declares (diagnostics and the input watchdog)."""

    diagnostics_period: float = param(
        1.0, "Seconds between /diagnostics publications (0 disables them).", min_value=0.0)
    diagnostics_window: float = param(
        10.0, "Seconds over which /diagnostics measures the fraction of lost frames.",
        min_value=0.1)
    drop_warn_fraction: float = param(
        0.05, "Fraction of frames lost over diagnostics_window above which /diagnostics "
        "reports WARN.", min_value=0.0, max_value=1.0)
    drop_error_fraction: float = param(
        0.25, "Fraction of frames lost over diagnostics_window above which /diagnostics "
        "reports ERROR (>= drop_warn_fraction).", min_value=0.0, max_value=1.0)
    input_timeout: float = param(
        2.0, "Seconds without a matched input set, while inputs arrive, after which the node "
        "logs which input is missing (or how far apart the stamps are) and /diagnostics "
        "reports WARN.", min_value=0.1)
    input_error_timeout: float = param(
        10.0, "Seconds without a matched input set, while inputs arrive, after which "
        "/diagnostics reports ERROR (>= input_timeout).", min_value=0.1)
    processing_warn_ms: float = param(
        0.0, "Processing time per frame [ms] (median of the last 50 frames) above which "
        "/diagnostics reports WARN, as Autoware's nodes do (0: off; the check against the "
        "input period stays).", min_value=0.0)
    processing_error_ms: float = param(
        0.0, "Processing time per frame [ms] (median of the last 50 frames) above which "
        "/diagnostics reports ERROR (0: off; >= processing_warn_ms when both are set).",
        min_value=0.0)
    realtime_priority: int = param(
        0, "SCHED_FIFO priority (1-99) for all of the node's threads once it has subscribed, "
        "so that a frame takes a core at once on a loaded machine instead of waiting behind "
        "other processes (Linux; needs CAP_SYS_NICE or an rtprio limit, `ulimit -r`). "
        "Refused: normal scheduling and a standing WARN in /diagnostics. 0: normal "
        "scheduling.", min_value=0, max_value=99)

    def validate(self) -> None:
        if self.drop_error_fraction < self.drop_warn_fraction:
            raise ValueError(f"parameter 'drop_error_fraction' = {self.drop_error_fraction} "
                             f"is below 'drop_warn_fraction' = {self.drop_warn_fraction}")
        if self.input_error_timeout < self.input_timeout:
            raise ValueError(f"parameter 'input_error_timeout' = {self.input_error_timeout} "
                             f"is below 'input_timeout' = {self.input_timeout}")
        if 0 < self.processing_error_ms < self.processing_warn_ms:
            raise ValueError(f"parameter 'processing_error_ms' = {self.processing_error_ms} "
                             f"is below 'processing_warn_ms' = {self.processing_warn_ms}")


@dataclass(frozen=True)
class SyncParameters:
    """How a node matches its inputs (``SyncedInputs``)."""

    sync_mode: str = param(
        "exact", "How inputs are matched by header stamp: 'exact' (equal stamps) or "
        "'approximate' (stamps within sync_slop).", choices=("exact", "approximate"))
    sync_slop: float = param(
        0.05, "Largest stamp spread [s] of a matched input set in approximate mode.",
        min_value=0.0)
    sync_queue_size: int = param(
        10, "Messages kept per input while waiting for their match; older ones are dropped "
        "and counted in /diagnostics.", min_value=1)
    processing_queue_size: int = param(
        2, "Matched frames waiting for processing; when the node falls behind, the oldest "
        "waiting frame is dropped (counted as overrun in /diagnostics).", min_value=1)
    warmup_memory_mb: float = param(
        128.0, "Memory [MB] the frame thread (3/4) and the input thread (1/4) write and free "
        "at start-up, before subscribing, so that the first frames reuse it instead of "
        "faulting fresh pages in (slow on virtual machines: up to 3 ms per MB). About one "
        "frame's peak memory; 0: none.", min_value=0.0)

    def synced_inputs_kwargs(self) -> dict:
        return dict(mode=self.sync_mode, slop_s=self.sync_slop, queue_size=self.sync_queue_size,
                    processing_queue_size=self.processing_queue_size,
                    warmup_memory_mb=self.warmup_memory_mb)


#: every parameter the base class and the synchroniser declare, for tables and checks
BASE_PARAMETERS = parameter_specs(CommonParameters) + parameter_specs(SyncParameters)


class QualityNode(Node):
    """Base of ``lmd_node``, ``lms_node``, ``mimo_node`` and the reference perception nodes."""

    #: seconds between two log lines of the same warning cause
    warn_period_s = 5.0

    def __init_subclass__(cls, **kwargs):
        # A node whose start fails (bad parameter, missing models) must not stay in the ROS
        # graph: the exception's traceback keeps it alive, and a later node of the same name
        # saw "2 nodes are named ..." (clean-clone CI). The outermost __init__ destroys it.
        super().__init_subclass__(**kwargs)
        init = cls.__init__

        @functools.wraps(init)
        def __init__(self, *args, **kw):
            try:
                init(self, *args, **kw)
            except BaseException:
                if type(self) is cls:
                    self._destroy_after_failed_start()
                raise

        cls.__init__ = __init__

    def _destroy_after_failed_start(self) -> None:
        try:
            self.destroy_node()
        except Exception:  # noqa: BLE001 - Node.__init__ itself failed: nothing to destroy
            pass

    def __init__(self, name: str, **kwargs):
        super().__init__(name, **kwargs)
        self._live: dict[str, tuple[Callable[[Any], None], ParamSpec]] = {}
        self.add_on_set_parameters_callback(self._on_set_parameters)
        c = self.declare_settings(CommonParameters)
        self.input_timeout, self.input_error_timeout = c.input_timeout, c.input_error_timeout
        self.realtime_priority = c.realtime_priority
        self.diag = NodeDiagnostics(self, period_s=c.diagnostics_period,
                                    window_s=c.diagnostics_window,
                                    drop_warn=c.drop_warn_fraction,
                                    drop_error=c.drop_error_fraction,
                                    processing_warn_ms=c.processing_warn_ms,
                                    processing_error_ms=c.processing_error_ms)
        self._warned: dict[str, float] = {}
        self._warn_lock = threading.Lock()
        self._input_hints: dict[str, str] = {}
        self._issue_keys: set[str] = set()
        self._sync_params: dict = {}
        self._ticks = 0
        self._check_timer = None
        self._outputs: dict = {}
        self.pub_markers = None
        self._counts: Counter = Counter()
        self._drop_causes: set[str] = set()

    # ------------------------------------------------------------------ parameters
    def declare_sync_parameters(self) -> dict:
        """Declare the input synchronisation parameters; ``SyncedInputs`` keywords."""
        self._sync_params = self.declare_settings(SyncParameters).synced_inputs_kwargs()
        return dict(self._sync_params)

    def declare_settings(self, cls, live: dict[str, Callable[[Any], None]] | None = None):
        """Declare the parameters of settings class ``cls`` (one declaration each, in its
        fields' metadata) and return the instance, validated (``parameters.validate``);
        ``live``: per run-time parameter, the function that applies a new value."""
        live = dict(live or {})
        values = {}
        for spec in parameter_specs(cls):
            if spec.live and spec.name not in live:
                raise ValueError(f"parameter {spec.name!r} is live but has no apply function")
            values[spec.name] = declare_spec(self, spec)
            if spec.live:  # after declaring: the start-up value is not a change to apply
                self._live[spec.name] = (live.pop(spec.name), spec)
        if live:
            raise ValueError(f"apply functions for parameters that are not live: {sorted(live)}")
        settings = from_parameters(cls, values)
        try:
            validate(settings)
        except ValueError as exc:
            raise ValueError(f"invalid parameter: {exc}") from None
        return settings

    def _on_set_parameters(self, params) -> SetParametersResult:
        for p in params:
            if p.name not in self._live:
                continue  # read-only ones never get here; use_sim_time is rclpy's own
            try:
                self._live[p.name][1].check(p.value)
            except ValueError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
        for p in params:
            if p.name in self._live:
                self._live[p.name][0](p.value)
                self.get_logger().info(f"parameter {p.name} set to {p.value!r}")
        return SetParametersResult(successful=True)

    # ------------------------------------------------------------------ warnings
    def warn_input(self, key: str, message: str, level=DiagnosticStatus.WARN, *,
                   transient: bool = False) -> None:
        """A log warning (at most once per ``warn_period_s`` for this cause) plus a standing
        diagnostics warning for bad or missing input (``transient``: an event, shown for the
        diagnostics' hold time unless raised again)."""
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
        self.diag.warn(key, message, level, transient=transient)

    def report_issues(self, issues: dict[str, str], errors=frozenset()) -> None:
        """Warn each input problem of a frame under its own cause (``errors``: the causes
        at level ERROR); clear the causes of earlier frames that this frame does not have
        (shown for a while longer)."""
        for key, text in issues.items():
            self.warn_input(key, text, DiagnosticStatus.ERROR if key in errors
                            else DiagnosticStatus.WARN)
        for key in self._issue_keys - issues.keys():
            self.diag.clear(key)
        self._issue_keys |= issues.keys()

    # ------------------------------------------------------------------ frames
    def listen_transforms(self, enabled: bool, tolerance_s: float):
        """Listen to /tf_static and /tf when ``enabled`` (``self.tf``, a ``TfListener``);
        the transform buffer for the processor, or None."""
        self.tf = None
        if enabled:
            self.tf = TfListener(self, TransformBuffer(extrapolation_tolerance_s=tolerance_s),
                                 on_bad=lambda text: self.warn_input("tf", text))
        return self.tf.buffer if self.tf else None

    def create_output(self, msg_type, name: str, qos=None):
        """A publisher of one of :meth:`process`'s output messages (name = topic)."""
        pub = self.create_publisher(msg_type, name, qos if qos is not None else output_qos())
        self._outputs[name] = pub
        return pub

    def create_markers_output(self, enabled: bool, msg_type) -> None:
        """``output/markers``, built only while someone subscribes."""
        self.pub_markers = (self.create_publisher(msg_type, "output/markers", output_qos())
                            if enabled else None)

    def start_inputs(self, topics: Sequence[tuple[type, str]], *, hints=None,
                     sync: dict | None = None, **kwargs) -> SyncedInputs:
        """Subscribe to ``topics`` (matched by stamp, frames to :meth:`process`), with the
        input watchdog; ``hints``: per input, what else fixes its absence."""
        sync = self.declare_sync_parameters() if sync is None else sync
        # use_sim_time's /clock (every few ms from a bag player) and /tf on the input
        # thread too: each message would otherwise wake the executor (see InputReader)
        also_read = [sub for sub in self.subscriptions if sub.topic_name == "/clock"]
        tf = getattr(self, "tf", None)
        also_read += tf.subscriptions if tf is not None else []
        self.inputs = SyncedInputs(self, topics, self._run_frame, diagnostics=self.diag,
                                   watchdog=self.new_watchdog(len(topics)), also_read=also_read,
                                   **sync, **kwargs)
        self.watch_inputs(hints)
        self.diag.set_value("warmup_ms", round(self.inputs.warmup_s * 1e3, 1))
        self._set_scheduling()
        return self.inputs

    def _set_scheduling(self) -> None:
        """``realtime_priority``, once the input and frame threads exist (later threads
        inherit it); ``scheduling`` in /diagnostics says what the node runs with."""
        if self.realtime_priority <= 0:
            self.diag.set_value("scheduling", "normal")
            return
        n, refused = realtime_scheduling(self.realtime_priority)
        if refused:
            self.diag.set_value("scheduling", "normal (realtime_priority refused)")
            self.warn_input("realtime_priority", f"{refused}; running with normal scheduling")
            return
        self.diag.set_value("scheduling", f"SCHED_FIFO {self.realtime_priority}")
        self.get_logger().info(
            f"SCHED_FIFO priority {self.realtime_priority} on the node's {n} threads")

    def process(self, messages: list, markers: bool):
        """One matched input set (in ``self.inputs.topics`` order) -> the frame's outputs
        (``messages``, ``markers``, ``issues``, ``counts``); ``FrameRejected`` drops it."""
        raise NotImplementedError

    def _run_frame(self, synced) -> None:
        t0 = time.perf_counter()
        # markers cost about as much as the rest of a frame: only for a listener
        markers = self.pub_markers is not None and self.pub_markers.get_subscription_count() > 0
        try:
            out = self.process(list(synced.messages), markers)
        except FrameRejected as exc:
            if exc.cause:
                self._drop_causes.add(exc.cause)
                self.warn_input(exc.cause, f"dropping frame: {exc}")
            self.diag.frame_dropped(exc.reason)
            return
        for cause in self._drop_causes:
            self.diag.clear(cause)
        self.report_issues(out.issues, out.errors)
        for name, msg in out.messages.items():
            if is_serialized(msg):   # CDR bytes: published from where they are
                publish_serialized(self._outputs[name], msg)
            else:
                self._outputs[name].publish(msg)
        if out.markers is not None and self.pub_markers is not None:
            self.pub_markers.publish(out.markers)
        counts = self._counts
        for key, n in out.counts.items():
            counts[key] += n
        for text in out.notes:
            self.get_logger().info(text)
        self.diag.set_values([*((key, counts[key]) for key in out.counts),
                              *out.values.items()])
        self.diag.frame_processed((time.perf_counter() - t0) * 1e3)

    # ------------------------------------------------------------------ watchdog
    def new_watchdog(self, n_inputs: int) -> InputWatchdog:
        """An ``InputWatchdog`` with the node's timeouts, for its ``SyncedInputs``."""
        return InputWatchdog(n_inputs, self.input_timeout, self.input_error_timeout,
                             start_s=time.monotonic())

    def watch_inputs(self, hints: dict[str, str] | None = None) -> None:
        """Check ``self.inputs`` (a ``SyncedInputs`` with a watchdog) every second;
        ``hints``: per input name, what else fixes its absence (a parameter)."""
        self._input_hints = dict(hints or {})
        if self.diag.period_s == 1.0:  # on the diagnostics' tick, just before it publishes
            self.diag.before_publish.append(self._check)
            return
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
