"""Stamp-synchronised subscriptions (our stand-in for message_filters).

Each input gets a subscription, read by an :class:`InputReader` thread of its own (not
by the node's executor); arrivals go through
``lidar_quality_core.time_sync.StampSynchronizer``. Matched sets are handed to one
worker thread that runs the user callback on them one at a time, in the order they were
matched: subscriptions never wait for a long frame (no lock is held while the callback
runs), outputs stay in input order, and a node that falls behind drops the oldest
waiting frame (counted as ``overrun``) instead of building up latency.
"""
from __future__ import annotations

import threading
import time
import traceback
from collections import deque
from functools import partial
from contextlib import ExitStack
from typing import Callable, Sequence

from lidar_quality_core.cloud_cdr import decode_point_cloud
from lidar_quality_core.input_watchdog import InputWatchdog
from lidar_quality_core.time_sync import StampSynchronizer, SyncedSet, stamp_to_ns
from rclpy.callback_groups import CallbackGroup
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.exceptions import InvalidHandle
from rclpy.guard_condition import GuardCondition
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.subscription import Subscription
from sensor_msgs.msg import PointCloud2

from .qos import SENSOR_QOS
from .serialized_take import BufferTaker, available as buffered_take_available
from .threads import name_os_thread, touch_memory

#: longest a node's start waits for its threads' warm-up (it goes on without it after)
_WARMUP_WAIT_S = 30.0


class OrderedWorker:
    """Runs ``fn(item)`` on a thread of its own, in submission order, keeping at most
    ``max_pending`` items waiting; ``on_overrun(n)`` hears of the items it discarded.
    ``warmup()``, if given, runs first on the thread; ``ready`` is set after it
    (``warmup_error`` says why it failed, else None)."""

    def __init__(self, fn: Callable, max_pending: int, on_overrun: Callable[[int], None],
                 name: str = "lq_frame_worker", warmup: Callable[[], None] | None = None):
        if max_pending < 1:
            raise ValueError(f"max_pending must be >= 1, got {max_pending}")
        self._fn, self._max, self._on_overrun = fn, max_pending, on_overrun
        self._warmup, self.warmup_error = warmup, None
        self.ready = threading.Event()
        self._pending: deque = deque()
        self._cond = threading.Condition()
        self._stopping = False
        self._busy = False
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def submit(self, item) -> None:
        with self._cond:
            if self._stopping:
                return
            discarded = 0
            while len(self._pending) >= self._max:
                self._pending.popleft()
                discarded += 1
            self._pending.append(item)
            self._cond.notify()
        if discarded:
            self._on_overrun(discarded)

    def idle(self) -> bool:
        with self._cond:
            return not self._pending and not self._busy

    def _loop(self) -> None:
        name_os_thread("lq_frames")
        _warm_up(self)
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._pending or self._stopping)
                if not self._pending:
                    return
                item = self._pending.popleft()
                self._busy = True
            try:
                self._fn(item)
            finally:
                with self._cond:
                    self._busy = False

    def stop(self, timeout: float = 5.0) -> None:
        """Finish the item being processed, discard the waiting ones, end the thread."""
        with self._cond:
            self._stopping = True
            self._pending.clear()
            self._cond.notify_all()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout)


def _warm_up(owner) -> None:
    """Run an OrderedWorker's or InputReader's ``_warmup`` on its thread, then set ``ready``."""
    try:
        if owner._warmup is not None:
            owner._warmup()
    except MemoryError as exc:  # the frames pay their own first touch (said at start-up)
        owner.warmup_error = f"MemoryError: {exc}"
    finally:
        owner.ready.set()


WITH_INFO = Subscription.CallbackType.WithMessageInfo


class ReadByInputReader(CallbackGroup):
    """A callback group no executor runs: its subscriptions are read by an InputReader."""

    def can_execute(self, entity) -> bool:
        return False

    def beginning_execution(self, entity) -> bool:
        return False

    def ending_execution(self, entity) -> None:
        pass


class InputReader:
    """Takes the messages and QoS events (lost messages, incompatible QoS) of
    ``subscriptions`` on a thread of its own and calls their callbacks there.

    Why not the executor: rclpy's executor rebuilds its whole wait set in Python for
    every wake (every subscription, timer, service and event handler of the node) and
    wraps each callback in a task; and a subscription's QoS event in a wait set wakes it
    on every message of that subscription (Fast DDS notifies the listener's waiters on
    data), ready or not. Measured in lmd_node at 10 Hz: 175 wait-set builds per second
    for 2 timer callbacks, 2-3 ms of CPU per frame on the executor thread alone. Here
    the wait set holds the inputs and one guard condition (their QoS events every
    ``EVENT_POLL_S``), is allocated once, and a wake costs a few calls into rcl (the
    calls rclpy's own ``wait_for_message`` makes). Create the ``subscriptions`` in a
    :class:`ReadByInputReader` group, so that the executor never takes their messages.

    ``optional`` subscriptions (use_sim_time's /clock, /tf) are read here too, moved out
    of the executor with their events; one of them destroyed under us (use_sim_time
    turned off) is left out from then on, while a destroyed input ends the reader.
    ``warmup()``, if given, runs first on the thread; ``ready`` is set after it
    (``warmup_error`` says why it failed, else None). ``buffered``: raw subscriptions
    (callbacks without message info) whose messages are taken into buffers of the
    reader's own and handed over as read-only uint8 views of them
    (:class:`~lidar_quality_ros.serialized_take.BufferTaker`)."""

    #: seconds between two checks of the QoS events (``_wait_and_take``)
    EVENT_POLL_S = 0.2

    def __init__(self, node, subscriptions: Sequence, name: str, on_error: Callable[[str], None],
                 optional: Sequence = (), warmup: Callable[[], None] | None = None,
                 buffered: Sequence = ()):
        self._events_due = 0.0  # monotonic time of the next QoS event check
        self._required = list(subscriptions)
        # raw subscriptions whose messages are taken into buffers of the reader's own
        # (serialized_take: one copy fewer than rclpy's take); callbacks without info only
        self._takers = {id(s): BufferTaker() for s in buffered
                        if s.raw and s._callback_type is not WITH_INFO}
        # optional ones first: a transform or clock that came with a frame is in before it
        self._subs = [s for s in optional if s not in self._required] + self._required
        moved = ReadByInputReader()
        for sub in self._subs:  # the executor never waits on them, nor on their events
            if not isinstance(sub.callback_group, ReadByInputReader):
                for entity in (sub, *sub.event_handlers):
                    entity.callback_group = moved
                    moved.add_entity(entity)
        self._node = node
        self._context = node.context
        self._on_error = on_error
        self._stopping = False
        self._wake = GuardCondition(None, None, context=self._context)
        self._wake_handle = self._wake.handle
        self._entries = self._entries_of(self._subs)
        self._warmup, self.warmup_error = warmup, None
        self.ready = threading.Event()
        with self._context.handle:
            self._wait_set = _rclpy.WaitSet(len(self._subs), 1, 0, 0, 0,
                                            sum(len(s.event_handlers) for s in self._subs),
                                            self._context.handle)
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()
        # out of the middleware before the context goes, even for a node never closed
        self._context.on_shutdown(self._stop_soon)

    def _stop_soon(self) -> None:
        self._stopping = True
        try:
            self._wake.trigger()
        except InvalidHandle:
            pass

    def _loop(self) -> None:
        name_os_thread("lq_inputs")
        _warm_up(self)
        # Every handle is held (entered) for the reader's life, not per wake: entering
        # some 20 handles per wake cost as much as the wait itself. A subscription is then
        # only destroyed once released: an optional one that left the node is released by
        # _prune, the rest when the thread ends.
        held: dict = {}
        try:
            with ExitStack() as always:
                for h in (self._context.handle, self._wake.handle):
                    always.enter_context(h)
                for sub in self._subs:
                    held[sub] = stack = ExitStack()
                    for entity in (sub.handle, *sub.event_handlers):
                        stack.enter_context(entity)
                self._read(held)
        except (InvalidHandle, RuntimeError):
            pass  # destroyed or shut down under us: nothing left to read
        finally:
            for taker in self._takers.values():
                taker.close()
            for stack in held.values():
                stack.close()

    def _read(self, held: dict) -> None:
        checked = time.monotonic()
        while not self._stopping and self._context.ok():
            if time.monotonic() - checked > 1.0:
                checked = time.monotonic()
                self._prune(held)
            try:
                todo = self._wait_and_take()
            except InvalidHandle:
                # an optional subscription destroyed since the last check (its events
                # refuse to be waited on): leave it out; anything else ends the reader
                if not self._prune(held):
                    raise
                continue
            except Exception as exc:  # noqa: BLE001 - said and counted; the inputs go on
                if self._stopping or not self._context.ok():
                    return  # shut down under the wait: not a lost message
                self._on_error(f"input reader: {type(exc).__name__}: {exc}")
                time.sleep(0.1)
                continue
            for callback, what, args in todo:
                if self._stopping:
                    return
                try:
                    callback(*args)
                except Exception as exc:  # noqa: BLE001 - a bug costs this message, not the reader
                    self._on_error(f"{what} callback failed: {type(exc).__name__}: {exc}")

    def _prune(self, held: dict) -> bool:
        """Release the optional subscriptions the node destroyed (use_sim_time turned off
        destroys /clock's; rclpy destroys them once we let go); True if there were any."""
        if len(self._subs) == len(self._required):
            return False
        current = {id(s) for s in self._node.subscriptions}
        gone = [s for s in self._subs if s not in self._required and id(s) not in current]
        self._subs = [s for s in self._subs if s not in gone]
        self._entries = [e for e in self._entries if e[0] not in gone]
        for sub in gone:
            held.pop(sub).close()
        return bool(gone)

    def _entries_of(self, subs) -> list:
        """Per subscription what a wake reads of it, looked up once (each is a property
        or a call into rcl; the topic name takes the handle's lock): ``(sub, handle,
        pointer, taker, topic, label, with_info)``."""
        out = []
        for sub in subs:
            topic = sub.topic_name
            out.append((sub, sub.handle, sub.handle.pointer, self._takers.get(id(sub)), topic,
                        f"input {topic}", sub._callback_type is WITH_INFO))
        return out

    def _wait_and_take(self) -> list:
        ws = self._wait_set
        subs = self._subs
        entries = self._entries
        ws.clear_entities()
        for entry in entries:
            ws.add_subscription(entry[1])
        ws.add_guard_condition(self._wake_handle)
        # The QoS events join the wait set every EVENT_POLL_S, not on every wake: three per
        # subscription (lost messages, incompatible QoS, incompatible type), each added and
        # checked through rclpy's Python, cost a MIMO wake ~35 us (18 events, measured).
        # An event stays latched in the middleware until taken, so none is missed; it is
        # handled up to EVENT_POLL_S later.
        timeout = 500_000_000  # only so that a node destroyed without close() lets go
        left = self._events_due - time.monotonic()
        events = [e for sub in subs for e in sub.event_handlers] if left <= 0 else ()
        for e in events:
            e.add_to_wait_set(ws)
        if not events:
            timeout = min(timeout, int(left * 1e9) + 1)
        ws.wait(timeout)
        ready = ws.get_ready_entities("subscription")
        todo = []
        if events:
            self._events_due = time.monotonic() + self.EVENT_POLL_S
        for e in events:
            if e.is_ready(ws):
                data = e.take_data()
                if data:
                    todo.append((e.callback, "QoS event", (data,)))
        for sub, handle, pointer, taker, topic, what, with_info in entries:
            if pointer not in ready:
                continue
            try:
                data = NotImplemented if taker is None else taker.take(pointer)
                if data is not NotImplemented:  # taken into our buffer (None: nothing)
                    if data is not None:
                        todo.append((sub.callback, what, (data,)))
                    continue
                info = handle.take_message(sub.msg_type, sub.raw)
            except Exception as exc:  # noqa: BLE001 - one bad message, not the reader
                self._on_error(f"cannot take a message on {topic}: "
                               f"{type(exc).__name__}: {exc}")
                continue
            if info is not None:  # (message, message info), as the executor hands them
                todo.append((sub.callback, what, info if with_info else info[:1]))
        return todo

    def stop(self, timeout: float = 5.0) -> None:
        """Stop reading (the message being handled finishes) and end the thread."""
        self._stop_soon()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout)
        self._wake.destroy()


class SyncedInputs:
    """Subscribe to ``topics`` (list of ``(msg_type, topic)``) and call ``callback(set)``
    for every matched set, on the worker thread, in matching order.

    ``on_arrival(index, stamp_ns)``, if given, hears of every message before it is
    matched; with :meth:`inject` a node can stand in for an input that stopped (e.g.
    ``None`` messages, so the other inputs' sets still complete).

    ``raw_decoders`` maps topics to ``fn(bytes) -> obj with .header.stamp``: those are
    subscribed with ``raw=True`` and decoded on arrival (messages rclpy would deserialize
    far too slowly, e.g. ``detection_cdr.decode_detection_array``); bytes that do not
    decode are dropped and counted (``undecodable_input``). PointCloud2 inputs are always
    taken so, read by ``cloud_cdr.decode_point_cloud`` (the points a view into the
    received bytes: rclpy's message would copy them twice more), the bytes taken into
    the input reader's own buffers (``serialized_take``: one copy fewer than rclpy's raw
    take; rclpy's take where that is not available, said once at start).

    ``watchdog`` (an ``InputWatchdog`` over the same inputs) hears of every arrival and
    every matched set, so the node can tell why nothing comes out.

    ``also_read``: other subscriptions of the node that the input thread reads too (the
    /clock of use_sim_time, /tf): frequent small messages that would otherwise wake the
    executor (see :class:`InputReader`).

    ``warmup_memory_mb``: memory the frame thread (3/4) and the input thread (1/4) touch
    before the first subscription exists and before this returns (``threads.touch_memory``);
    ``warmup_s`` is what it took."""

    def __init__(self, node, topics: Sequence[tuple[type, str]],
                 callback: Callable[[SyncedSet], None], *, mode: str = "exact",
                 slop_s: float = 0.0, queue_size: int = 10, processing_queue_size: int = 2,
                 qos=SENSOR_QOS, diagnostics=None,
                 on_arrival: Callable[[int, int], None] | None = None,
                 raw_decoders: dict[str, Callable[[bytes], object]] | None = None,
                 watchdog: InputWatchdog | None = None, also_read: Sequence = (),
                 warmup_memory_mb: float = 0.0):
        self.topics = [t for _, t in topics]
        self.watchdog = watchdog
        self._decoders = {t: decode_point_cloud for m, t in topics if m is PointCloud2}
        self._decoders.update(raw_decoders or {})
        self._on_arrival = on_arrival
        self.sync = StampSynchronizer(len(topics), mode=mode,
                                      slop_ns=int(round(slop_s * 1e9)) if mode == "approximate" else 0,
                                      queue_size=queue_size)
        self._callback = callback
        self._diag = diagnostics
        self._logger = node.get_logger()
        t_warm = time.monotonic()
        frame_mb, input_mb = 0.75 * warmup_memory_mb, 0.25 * warmup_memory_mb
        self.worker = OrderedWorker(
            self._run, processing_queue_size, self._overrun, name=f"{node.get_name()}_frames",
            warmup=partial(touch_memory, frame_mb) if frame_mb > 0 else None)
        self.worker.ready.wait(_WARMUP_WAIT_S)
        self._warn = getattr(node, "warn_input", None)
        read_here = ReadByInputReader()
        self.subscriptions = [
            node.create_subscription(
                msg_type, topic, self._make_cb(i), qos, callback_group=read_here,
                raw=topic in self._decoders,
                event_callbacks=SubscriptionEventCallbacks(message_lost=self._make_lost_cb(i)))
            for i, (msg_type, topic) in enumerate(topics)
        ]
        # clouds into the reader's own buffers (the points a view of them: no copy to bytes)
        buffered, why_not = [], ""
        clouds = [s for (m, _), s in zip(topics, self.subscriptions) if m is PointCloud2]
        if clouds:
            ok, why_not = buffered_take_available()
            buffered = clouds if ok else []
        if why_not:
            self._logger.info(f"clouds taken by rclpy (copied once more): {why_not}")
        self.reader = InputReader(node, self.subscriptions, f"{node.get_name()}_inputs",
                                  self._reader_error, optional=also_read,
                                  warmup=partial(touch_memory, input_mb) if input_mb > 0 else None,
                                  buffered=buffered)
        self.reader.ready.wait(_WARMUP_WAIT_S)
        self.warmup_s = time.monotonic() - t_warm
        self._report_warmup()
        if diagnostics is not None:
            diagnostics.add_source(self._stats, self.unmatched_dropped, self.frames_lost)

    def _make_cb(self, index: int):
        topic = self.topics[index]
        decode = self._decoders.get(topic)

        def on_message(msg) -> None:
            if self._diag is not None:
                self._diag.input_received(topic)
            if decode is not None:
                try:
                    msg = decode(msg)
                except Exception as exc:  # noqa: BLE001 - bad bytes cost this message only
                    self._dropped("undecodable_input", f"undecodable.{topic}",
                                  f"dropping a message on {topic}: cannot decode it: {exc}")
                    return
            stamp = msg.header.stamp
            try:
                stamp_ns = stamp_to_ns(stamp.sec, stamp.nanosec)
            except ValueError as exc:
                # nanosec >= 1e9 passes the wire (uint32): it must cost this message, not
                # the node (an exception here stops the executor; found by fuzzing).
                self._dropped("invalid_stamp", f"invalid_stamp.{topic}",
                              f"dropping a message on {topic}: {exc}")
                return
            if self.watchdog is not None:
                self.watchdog.arrival(index, stamp_ns, time.monotonic())
            if self._on_arrival is not None:
                self._on_arrival(index, stamp_ns)
            self.inject(index, stamp_ns, msg)
        return on_message

    def _make_lost_cb(self, index: int):
        topic = self.topics[index]

        def on_lost(info) -> None:
            # the middleware lost messages before they reached us (e.g. a cloud larger than
            # the DDS profile carries): without this they would be counted nowhere
            n = int(info.total_count_change)
            text = (f"{info.total_count} message(s) on {topic} lost in transport before they "
                    "reached the node (a cloud larger than the shared-memory profile carries? "
                    "see LQ_SHM_SEGMENT_MB in the README)")
            self._dropped("message_lost", f"lost.{topic}", text, n)
        return on_lost

    def _dropped(self, reason: str, cause: str, text: str, n: int = 1):
        """Count ``n`` dropped under ``reason`` and warn under ``cause``: through the node's
        per-cause warnings (shown in /diagnostics for their hold time) when it has them.
        The warning first: a /diagnostics message published between the two (the
        warning's log line takes a while) then never shows the count without its cause."""
        if self._warn is not None:
            self._warn(cause, text, transient=True)
        else:
            self._logger.warn(text, throttle_duration_sec=5.0)
        if self._diag is not None:
            self._diag.frame_dropped(reason, n)

    def inject(self, index: int, stamp_ns: int, msg) -> None:
        """Queue ``msg`` for input ``index`` at ``stamp_ns`` as if it had arrived (not
        counted as received in the diagnostics) and process the set it completes."""
        for matched in self.sync.add(index, stamp_ns, msg):
            if self.watchdog is not None:
                self.watchdog.matched(time.monotonic())
            self.worker.submit(matched)

    def _report_warmup(self) -> None:
        """Say, once at start-up, a warm-up that failed or did not finish in time."""
        problems = [f"{what}: {t.warmup_error or f'not done after {_WARMUP_WAIT_S:g} s'}"
                    for what, t in (("frame thread", self.worker), ("input thread", self.reader))
                    if t.warmup_error or not t.ready.is_set()]
        if not problems:
            return
        text = ("start-up warm-up (warmup_memory_mb) incomplete, the first frames may be "
                f"slow: {'; '.join(problems)}")
        if self._warn is not None:
            self._warn("warmup", text, transient=True)
        else:
            self._logger.warn(text)

    def _reader_error(self, text: str) -> None:
        self._dropped("undecodable_input", "input_error", f"dropping a message: {text}")

    def _overrun(self, n: int) -> None:
        self._dropped("overrun", "overrun",
                      f"processing falls behind the input: dropped {n} waiting frame(s)", n)

    def _run(self, matched: SyncedSet) -> None:
        # A bug or an unforeseen input must cost one frame, never the node.
        try:
            self._callback(matched)
        except Exception as exc:  # noqa: BLE001 - a bug or bad input costs this frame only
            # the traceback in the log; /diagnostics keeps the one-line cause
            self._logger.error(f"frame at stamp {matched.stamp_ns} ns dropped: "
                               f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}",
                               throttle_duration_sec=5.0)
            if self._diag is not None:
                self._diag.frame_dropped("processing_error")
                self._diag.warn("processing_error", f"processing error: {type(exc).__name__}: {exc}")

    def _stats(self) -> dict[str, str]:
        s = self.sync.stats()
        out = {"sync.matched": str(s.matched), "sync.resets": str(s.resets)}
        for i, topic in enumerate(self.topics):
            out[f"sync.late.{topic}"] = str(s.late[i])
            out[f"sync.dropped.{topic}"] = str(s.dropped[i])
        return out

    def unmatched_dropped(self) -> int:
        """Input messages lost by the synchroniser (late, overflow, unmatched, reset)."""
        s = self.sync.stats()
        return sum(s.dropped) + sum(s.late)

    def frames_lost(self) -> int:
        """Frames the synchroniser lost, estimated as the most messages lost on one input
        (a frame lost on every input is one frame, not one per input)."""
        s = self.sync.stats()
        return max(d + late for d, late in zip(s.dropped, s.late))

    def close(self) -> None:
        self.reader.stop()
        self.worker.stop()
