"""Bag player node: replays a rosbag2 (MCAP or sqlite3) in real time, without rosbag2.

The ``rosbags``-based stand-in for ``ros2 bag play --clock`` (:mod:`.bag_io` reads the
bag: any rosbag2 ``ros2 bag`` reads, older metadata included). Every selected topic whose
message type is available here is published (the others are skipped, one warning per
type: a driver's raw packets without its message package) with its recorded QoS and timed
by the recorded log times (scaled by ``rate``); ``/clock`` carries the bag time, with every
message and at ``clock_rate`` in between. Messages go out as their recorded CDR bytes (rclpy
publishes serialized bytes as they are), so contents and header stamps are the original
ones and nothing is deserialised on the way (deserialising a 12 MB perception frame and
publishing message objects took ~135 ms on the 2-core machine, the raw bytes ~10 ms).
A looping player's /clock jumps back to the bag start at each pass, as with rosbag2.

    bag_player BAG [--topics T ...] [--rate 2] [--loop] [--start-offset S] [--delay S]
               [--remap /old:=/new ...] [--best-effort [PATTERN ...]] [--max-lateness S]
               [--publish-log PATH]
               [--ros-args ...]

In-process (tests, ``make demo``): ``ros.start(BagPlayer, parameters={"bag": path, ...})``,
then ``player.finished.wait()`` and ``player.summary()``.
"""
from __future__ import annotations

import argparse
import fnmatch
import itertools
import json
import re
import sys
import threading
import time
from collections import defaultdict, deque
from pathlib import Path

import numpy as np
from builtin_interfaces.msg import Time
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock

from .bag_io import UnknownTypes, bag_info, message_class, read_bag
from .params import declare
from .qos import output_qos
from .runner import run_node

#: Messages counted as late in the summary: published more than this behind schedule.
LATE_S = 0.010
#: Messages read ahead at most (besides prefetch_mb), for bags of many small messages.
_MAX_ITEMS = 10_000
#: Lateness samples kept per topic for the percentiles (a looping player runs for hours).
_SAMPLES = 100_000


def split_list(text: str) -> list[str]:
    """Items of a whitespace / comma separated parameter string."""
    return [t for t in re.split(r"[\s,]+", text.strip()) if t]


def parse_remaps(items: list[str]) -> dict[str, str]:
    """``["/old:=/new", ...]`` -> ``{"/old": "/new"}``."""
    out = {}
    for item in items:
        old, sep, new = item.partition(":=")
        if not sep or not old or not new:
            raise ValueError(f"remap {item!r}: expected OLD:=NEW")
        out[old] = new
    return out


def matches(patterns: list[str], topic: str, msgtype: str) -> bool:
    """Whether a topic name or its message type matches one of the glob ``patterns``."""
    return any(fnmatch.fnmatchcase(topic, p) or fnmatch.fnmatchcase(msgtype, p) for p in patterns)


def playback_qos(offers: list[QoSProfile], *, best_effort: bool = False) -> QoSProfile:
    """Publisher QoS from the QoS profiles offered when recording (as rosbag2 adapts them).

    No recorded profile: reliable, volatile, keep last 10. Otherwise reliable only if every
    recorded publisher was reliable, transient-local only if every one was, keep-last with
    the largest recorded depth (recorders that saw no depth store 0: then 10).
    ``best_effort`` forces best effort (e.g. sensor topics for sensor-data subscribers).
    """
    qos = output_qos(10)
    if offers:
        if not all(o.reliability == ReliabilityPolicy.RELIABLE for o in offers):
            qos.reliability = ReliabilityPolicy.BEST_EFFORT
        if all(o.durability == DurabilityPolicy.TRANSIENT_LOCAL for o in offers):
            qos.durability = DurabilityPolicy.TRANSIENT_LOCAL
        if all(o.history == HistoryPolicy.KEEP_ALL for o in offers):
            qos.history = HistoryPolicy.KEEP_ALL
        else:
            qos.depth = max([o.depth for o in offers if o.history == HistoryPolicy.KEEP_LAST
                             and o.depth > 0] or [10])
    if best_effort:
        qos.reliability = ReliabilityPolicy.BEST_EFFORT
    return qos


class _Prefetcher:
    """Reads the bag ahead of the schedule in a thread, at most ``max_bytes`` buffered.

    Yields the messages of each pass and ``None`` at the end of a pass.
    """

    def __init__(self, path, topics, start_ns: int, passes, max_bytes: int, stop: threading.Event):
        self._args = (path, topics, start_ns)
        self._passes, self._max_bytes, self._stop = passes, max_bytes, stop
        self._items: deque = deque()
        self._bytes = 0
        self._cond = threading.Condition()
        self.error: BaseException | None = None
        self.primed = threading.Event()  # buffer full (or bag read): playback may start
        self._thread = threading.Thread(target=self._run, name="bag_reader", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            for _ in self._passes:
                for msg in read_bag(*self._args[:2], start_ns=self._args[2]):
                    if not self._put(msg, len(msg.raw)):
                        return
                if not self._put(None, 0):
                    return
                self.primed.set()  # a whole pass is buffered
        except BaseException as exc:  # noqa: BLE001 - handed to the player thread
            self.error = exc
        finally:
            self._put(StopIteration, 0, force=True)
            self.primed.set()

    def _put(self, item, size: int, force: bool = False) -> bool:
        with self._cond:
            # one item is always let through, however large
            def room():
                return (force or self._stop.is_set() or not self._items
                        or (self._bytes + size <= self._max_bytes and len(self._items) < _MAX_ITEMS))
            if not room():
                self.primed.set()
            while not room():
                self._cond.wait(0.1)  # the owner sets the stop event without notifying
            if self._stop.is_set() and not force:
                return False
            self._items.append((item, size))
            self._bytes += size
            self._cond.notify_all()
            return True

    def get(self):
        """Next message, ``None`` at the end of a pass, ``StopIteration`` at the end."""
        with self._cond:
            while not (self._items or self._stop.is_set()):
                self._cond.wait(0.1)
            if not self._items:
                return StopIteration
            item, size = self._items.popleft()
            self._bytes -= size
            self._cond.notify_all()
        if item is StopIteration and self.error is not None:
            raise self.error
        return item

    def close(self) -> None:
        with self._cond:
            self._cond.notify_all()  # the stop event is set by the owner
        self._thread.join(timeout=5.0)


class _Stats:
    """Per-topic counts, bytes and lateness (publication time minus scheduled time)."""

    def __init__(self):
        self.count: dict[str, int] = defaultdict(int)
        self.bytes: dict[str, int] = defaultdict(int)
        self.late: dict[str, deque] = defaultdict(lambda: deque(maxlen=_SAMPLES))
        self.late_max: dict[str, float] = defaultdict(float)
        self.n_late: dict[str, int] = defaultdict(int)
        self.publish_s: dict[str, deque] = defaultdict(lambda: deque(maxlen=_SAMPLES))
        self.first_due = self.last_due = self.last_done = None
        self.cpu_first = self.cpu_last = 0.0   # process CPU time at the first / last publish
        self.passes = 0
        self.shifts, self.shifted_s = 0, 0.0  # schedule shifts (max_lateness) and their sum
        self.lock = threading.Lock()  # summary() may be called during playback

    def shift(self, seconds: float) -> None:
        with self.lock:
            self.shifts += 1
            self.shifted_s += seconds

    def record(self, topic: str, nbytes: int, due: float, start: float, done: float) -> None:
        late = max(0.0, start - due)
        with self.lock:
            self.count[topic] += 1
            self.bytes[topic] += nbytes
            self.late[topic].append(late)
            self.late_max[topic] = max(self.late_max[topic], late)
            self.n_late[topic] += late > LATE_S
            self.publish_s[topic].append(done - start)
            self.cpu_last = time.process_time()
            if self.first_due is None:
                self.first_due = due
                self.cpu_first = self.cpu_last
            self.last_due, self.last_done = due, done


def _ms(values, q) -> float:
    return round(float(np.percentile(np.fromiter(values, float), q)) * 1e3, 2) if values else 0.0


class BagPlayer(Node):
    """Publishes the messages of a rosbag2 directory on their topics, timed by log time."""

    def __init__(self, node_name: str = "bag_player", **kwargs):
        super().__init__(node_name, **kwargs)
        bag = declare(self, "bag", "", "Path of the rosbag2 directory to play (MCAP or sqlite3).")
        topics = split_list(declare(self, "topics", "",
                                    "Topics to play, separated by spaces or commas (empty: all)."))
        exclude = split_list(declare(self, "exclude_topics", "",
                                     "Topics not to play, separated by spaces or commas."))
        remaps = parse_remaps(split_list(declare(
            self, "remap", "", "Topic remappings OLD:=NEW (bag topic -> published topic), "
            "separated by spaces or commas.")))
        self._rate = declare(self, "rate", 1.0, "Playback speed: 2.0 plays twice as fast as recorded.",
                             min_value=1e-3, max_value=1e3)
        self._loop = declare(self, "loop", False, "Play the bag over and over until stopped.")
        offset = declare(self, "start_offset", 0.0, "Start this many seconds into the bag.",
                         min_value=0.0)
        self._delay = declare(self, "delay", 0.0, "Seconds to wait before the first message "
                              "(after wait_for_subscribers).", min_value=0.0)
        publish_clock = declare(self, "clock", True, "Publish the bag time on /clock "
                                "(rosgraph_msgs/Clock) for use_sim_time nodes; a /clock topic "
                                "recorded in the bag is then not played.")
        clock_rate = declare(self, "clock_rate", 40.0, "/clock publications per second between "
                             "messages (besides one with every message; 0: only with messages).",
                             min_value=0.0, max_value=1e4)
        best_effort = split_list(declare(
            self, "best_effort", "", "Publish these topics best effort whatever their recorded "
            "QoS: glob patterns on topic names or message types, e.g. 'sensor_msgs/msg/*'."))
        self._wait_subs = declare(self, "wait_for_subscribers", 0, "Before playing, wait until "
                                  "every topic has this many subscribers (0: do not wait).",
                                  min_value=0)
        self._wait_timeout = declare(self, "wait_timeout", 30.0, "Longest wait for subscribers "
                                     "[s]; then play anyway (with a warning).", min_value=0.0)
        prefetch_mb = declare(self, "prefetch_mb", 128.0, "Megabytes of messages read ahead of "
                              "the schedule.", min_value=1.0)
        self._max_late = declare(
            self, "max_lateness", 0.0, "Longest a message may go out behind its schedule [s] "
            "before the rest of the playback is shifted later by that lateness: a stall of the "
            "player or the machine then delays the bag, as it would a live sensor, instead of "
            "publishing the late messages in a burst that overruns subscribers' queues "
            "(0: never shift, late messages go out at once, as ros2 bag play does).",
            min_value=0.0)
        publish_log = declare(self, "publish_log", "", "Write one line per published message "
                              "to this file: bag topic, log time [ns], system time of the "
                              "publish call [ns] (latency measurements; empty: none).")

        if not bag:
            raise ValueError("parameter 'bag' is empty: give the rosbag2 directory to play")
        path = Path(bag).expanduser()
        if not (path / "metadata.yaml").is_file():
            raise FileNotFoundError(f"bag not found: {path} is not a rosbag2 directory "
                                    "(no metadata.yaml)")
        info = bag_info(path)
        unknown = sorted(set(topics + exclude) - set(info.topics))
        if unknown:
            raise ValueError(f"topics not in the bag {path}: {unknown}; it has {sorted(info.topics)}")
        offset_ns = int(round(offset * 1e9))
        if offset_ns > info.end_ns - info.start_ns:
            raise ValueError(f"start_offset {offset} s is past the end of the bag "
                             f"({(info.end_ns - info.start_ns) / 1e9:.3f} s)")
        self.bag = path
        self._b0 = info.start_ns + offset_ns
        self._end_ns = info.end_ns
        self._clock_period = 1.0 / clock_rate if clock_rate > 0 else 0.0
        self._clock_pub = (self.create_publisher(Clock, "/clock", output_qos(10))
                           if publish_clock else None)

        for fix in info.fixes:
            self.get_logger().info(f"{path}: metadata read with a correction: {fix}")
        # publishing needs the message class: a type unknown here (a driver's raw packets)
        # is skipped, with one warning per type
        skipped = UnknownTypes(self.get_logger().warn, "not played")
        selected = [t for t in (topics or sorted(info.topics)) if t not in exclude]
        playable = skipped.check_all({t: info.topics[t].msgtype for t in selected})
        self.skipped_types = skipped.seen
        self._pubs, self._names = {}, {}
        for topic in playable:
            t = info.topics[topic]
            name = remaps.get(topic, topic)
            if publish_clock and name == "/clock":
                self.get_logger().info(f"not playing the recorded {topic}: /clock comes from the player")
                continue
            cls = message_class(t.msgtype)
            qos = playback_qos(t.qos, best_effort=matches(best_effort, topic, t.msgtype))
            self._pubs[topic] = self.create_publisher(cls, name, qos)
            self._names[topic] = self._pubs[topic].topic_name
        if not self._pubs:
            why = "; ".join(f"{', '.join(ts)}: {ty}" for ty, ts in skipped.seen.items())
            raise ValueError(f"nothing to play in {path}: " + (
                f"every selected topic has a message type not available here ({why})"
                if why else "no playable topic selected"))
        counts = [info.topics[t].count for t in self._pubs]
        # gap between the end of a pass and the next one: about one period of the
        # busiest topic, so frames do not come back to back at the loop seam
        span = self._end_ns - self._b0
        self._loop_gap_ns = span // (max(counts) - 1) if max(counts) > 1 else 0
        if span + self._loop_gap_ns == 0:  # a bag of one instant: loop it once a second
            self._loop_gap_ns = 10**9

        self.finished = threading.Event()   # run_node returns when set
        self.error: str | None = None
        self.stats = _Stats()
        self._stop = threading.Event()
        self._last_clock: int | None = None
        self._next_tick = 0.0
        self._prefetch_bytes = int(prefetch_mb * 1e6)
        self._plog = open(publish_log, "w", buffering=1 << 16) if publish_log else None
        self.get_logger().info(
            f"playing {path} ({len(self._pubs)} topics, {sum(counts)} messages, "
            f"{span / 1e9:.2f} s) at rate {self._rate}" + (", looping" if self._loop else ""))
        self._thread = threading.Thread(target=self._play, name="bag_player", daemon=True)
        self._thread.start()

    # playback ---------------------------------------------------------------------
    def _play(self) -> None:
        reader = None
        try:
            passes = itertools.repeat(None) if self._loop else [None]
            reader = _Prefetcher(self.bag, set(self._pubs), self._b0, passes,
                                 self._prefetch_bytes, self._stop)
            self._wait_for_subscribers()
            if self._delay > 0:
                self._wait_until(time.monotonic() + self._delay, t0=float("inf"), limit_ns=self._b0)
            # filling the read-ahead buffer competes for the GIL: done before the first message
            reader.primed.wait(timeout=30.0)
            t0 = time.monotonic()
            self._last_clock = None
            while not self._stop.is_set():
                msg = reader.get()
                if msg is StopIteration:
                    break
                if msg is None:  # end of a pass: the next one starts one period later
                    self.stats.passes += 1
                    t0 += (self._end_ns - self._b0 + self._loop_gap_ns) / self._rate / 1e9
                    self._last_clock = None  # the clock jumps back with the bag, as in rosbag2
                    continue
                due = t0 + (msg.stamp_ns - self._b0) / self._rate / 1e9
                self._wait_until(due, t0=t0, limit_ns=msg.stamp_ns)
                if self._stop.is_set():
                    break
                start = time.monotonic()
                if self._max_late and start - due > self._max_late:
                    t0 += start - due  # counted below with this message's lateness
                    self.stats.shift(start - due)
                if self._clock_pub is not None and msg.stamp_ns != self._last_clock:
                    self._publish_clock(msg.stamp_ns)
                if self._plog is not None:
                    self._plog.write(f"{msg.topic} {msg.stamp_ns} {time.time_ns()}\n")
                self._pubs[msg.topic].publish(msg.raw)
                self.stats.record(msg.topic, len(msg.raw), due, start, time.monotonic())
            if not self._stop.is_set():
                self._flush()
        except Exception as exc:  # noqa: BLE001 - reported, and main() exits with 1
            self.error = f"{type(exc).__name__}: {exc}"
            self.get_logger().error(f"playback failed: {self.error}")
        finally:
            if reader is not None:
                self._stop.set()
                reader.close()
            if self._plog is not None:
                self._plog.close()
            if self.error is None:
                self.get_logger().info(format_summary(self.summary()).splitlines()[1])
            self.finished.set()

    def _wait_for_subscribers(self) -> None:
        if not self._wait_subs:
            return
        deadline = time.monotonic() + self._wait_timeout
        while not self._stop.is_set():
            waiting = [p.topic_name for p in self._pubs.values()
                       if p.get_subscription_count() < self._wait_subs]
            if not waiting:
                return
            if time.monotonic() > deadline:
                self.get_logger().warn(f"playing although {waiting} have fewer than "
                                       f"{self._wait_subs} subscribers after {self._wait_timeout} s")
                return
            self._stop.wait(0.02)

    def _wait_until(self, due: float, *, t0: float, limit_ns: int) -> None:
        """Sleep until ``due``, publishing /clock every clock period meanwhile (bag time
        of the wall time, never past ``limit_ns``, the next message's log time)."""
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= due:
                return
            if self._clock_pub is None or not self._clock_period:
                self._stop.wait(due - now)
                continue
            if now >= self._next_tick:
                bag_now = self._b0 + int(max(0.0, now - t0) * self._rate * 1e9)
                self._publish_clock(min(bag_now, limit_ns))
                self._next_tick = max(self._next_tick + self._clock_period, now)
            self._stop.wait(min(due, self._next_tick) - now)

    def _publish_clock(self, stamp_ns: int) -> None:
        if self._last_clock is not None:
            stamp_ns = max(stamp_ns, self._last_clock)  # never backwards within a pass
        self._last_clock = stamp_ns
        sec, nsec = divmod(stamp_ns, 10**9)
        self._clock_pub.publish(Clock(clock=Time(sec=sec, nanosec=nsec)))

    def _flush(self) -> None:
        """Let reliable subscribers receive the last messages before the process exits."""
        deadline = time.monotonic() + 2.0
        for pub in [*self._pubs.values(), self._clock_pub]:
            if pub is None:
                continue
            left = deadline - time.monotonic()
            if left <= 0:
                break
            pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9)))

    # control and results ---------------------------------------------------------------
    def stop_processing(self) -> None:
        """Stop playing and join the playback thread (before any teardown)."""
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=10.0)

    def destroy_node(self):
        self.stop_processing()
        return super().destroy_node()

    def summary(self) -> dict:
        """Messages per topic, achieved speed and lateness of the playback so far."""
        with self.stats.lock:
            return self._summary(self.stats)

    def _summary(self, s: _Stats) -> dict:
        # the recorded span at ``rate``: a schedule shift (max_lateness) is time lost, not
        # part of the bag
        scheduled = (s.last_due - s.first_due - s.shifted_s) if s.first_due is not None else 0.0
        actual = (s.last_done - s.first_due) if s.first_due is not None else 0.0
        every = [v for d in s.late.values() for v in d]
        total_bytes = sum(s.bytes.values())
        topics = {}
        for t in sorted(s.count):
            topics[t] = dict(
                published_as=self._names[t], count=s.count[t],
                hz=round(s.count[t] / actual, 3) if actual > 0 else 0.0,
                mb=round(s.bytes[t] / 1e6, 3), late_ms_p50=_ms(s.late[t], 50),
                late_ms_p99=_ms(s.late[t], 99), late_ms_max=round(s.late_max[t] * 1e3, 2),
                late_over_10ms=s.n_late[t], publish_ms_p50=_ms(s.publish_s[t], 50),
                publish_ms_p99=_ms(s.publish_s[t], 99))
        return dict(
            bag=str(self.bag), rate=self._rate, passes=s.passes,
            skipped_types={ty: list(ts) for ty, ts in self.skipped_types.items()},
            messages=sum(s.count.values()), wall_s=round(actual, 3),
            # achieved playback speed: rate x scheduled span / time it took
            achieved_rate=round(self._rate * scheduled / actual, 4) if actual > 0 else 0.0,
            mb_per_s=round(total_bytes / 1e6 / actual, 1) if actual > 0 else 0.0,
            late_ms_p50=_ms(every, 50), late_ms_p99=_ms(every, 99),
            late_ms_max=round(max(s.late_max.values(), default=0.0) * 1e3, 2),
            late_over_10ms=sum(s.n_late.values()),
            # max_lateness: how often and by how much the rest of the playback was delayed
            shifts=s.shifts, shifted_ms=round(s.shifted_s * 1e3, 1),
            # the whole process (reading, publishing, /clock) from the first to the last publish
            cpu_s=round(s.cpu_last - s.cpu_first, 3), topics=topics)


def format_summary(summary: dict) -> str:
    """Text table of :meth:`BagPlayer.summary`."""
    lines = [f"bag_player: {summary['bag']}"]
    lines.append(f"played {summary['messages']} messages in {summary['wall_s']:.2f} s: achieved "
                 f"rate {summary['achieved_rate']:.3f} (asked {summary['rate']}), "
                 f"{summary['mb_per_s']} MB/s; late p50 {summary['late_ms_p50']} ms, p99 "
                 f"{summary['late_ms_p99']} ms, max {summary['late_ms_max']} ms, "
                 f"{summary['late_over_10ms']} more than 10 ms late"
                 + (f"; schedule shifted {summary['shifts']} times by {summary['shifted_ms']} ms "
                    "in all (max_lateness)" if summary.get("shifts") else ""))
    lines.append(f"{'topic':<32} {'msgs':>6} {'Hz':>8} {'MB':>9} {'late p99 ms':>12} "
                 f"{'late max ms':>12} {'pub p99 ms':>11}")
    for t, v in summary["topics"].items():
        lines.append(f"{v['published_as']:<32} {v['count']:>6} {v['hz']:>8.2f} {v['mb']:>9.2f} "
                     f"{v['late_ms_p99']:>12.2f} {v['late_ms_max']:>12.2f} {v['publish_ms_p99']:>11.2f}")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="bag_player", description=__doc__.split("\n\n")[0],
                                epilog="ROS arguments go after --ros-args (e.g. -r /a:=/b, -p rate:=2.0).")
    p.add_argument("bag", nargs="?", help="rosbag2 directory (MCAP or sqlite3)")
    p.add_argument("--topics", nargs="+", metavar="TOPIC", help="play only these topics")
    p.add_argument("--exclude-topics", nargs="+", metavar="TOPIC", help="do not play these topics")
    p.add_argument("--rate", type=float, help="playback speed (default 1.0)")
    p.add_argument("-l", "--loop", action="store_true", default=None, help="play until stopped")
    p.add_argument("--start-offset", type=float, metavar="S", help="start S seconds into the bag")
    p.add_argument("-d", "--delay", type=float, metavar="S", help="wait S seconds before playing")
    p.add_argument("-m", "--remap", nargs="+", action="extend", metavar="OLD:=NEW",
                   help="publish bag topic OLD on NEW")
    p.add_argument("--best-effort", nargs="*", metavar="PATTERN",
                   help="publish matching topics (glob on name or type) best effort; "
                        "no pattern: sensor_msgs/msg/*")
    p.add_argument("--no-clock", dest="clock", action="store_false", default=None,
                   help="do not publish /clock")
    p.add_argument("--clock-rate", type=float, metavar="HZ", help="/clock rate between messages (default 40)")
    p.add_argument("--wait-for-subscribers", type=int, metavar="N",
                   help="wait until every topic has N subscribers")
    p.add_argument("--wait-timeout", type=float, metavar="S", help="longest wait for subscribers")
    p.add_argument("--max-lateness", type=float, metavar="S",
                   help="shift the rest of the playback when a message is more than S seconds "
                        "late, instead of publishing the late messages at once (default 0: never)")
    p.add_argument("--prefetch-mb", type=float, metavar="MB", help="read-ahead buffer (default 128)")
    p.add_argument("--summary-json", type=Path, metavar="PATH", help="also write the summary as JSON")
    p.add_argument("--publish-log", type=Path, metavar="PATH",
                   help="write 'topic log_ns publish_ns' per published message")
    return p


def cli_parameters(ns: argparse.Namespace) -> dict:
    """Parameter overrides of the options given on the command line (the others keep the
    node's defaults or the --ros-args values)."""
    out = {"bag": ns.bag, "rate": ns.rate, "loop": ns.loop, "start_offset": ns.start_offset,
           "delay": ns.delay, "clock": ns.clock, "clock_rate": ns.clock_rate,
           "wait_for_subscribers": ns.wait_for_subscribers, "wait_timeout": ns.wait_timeout,
           "prefetch_mb": ns.prefetch_mb, "max_lateness": ns.max_lateness,
           "publish_log": str(ns.publish_log) if ns.publish_log else None,
           "topics": " ".join(ns.topics) if ns.topics else None,
           "exclude_topics": " ".join(ns.exclude_topics) if ns.exclude_topics else None,
           "remap": " ".join(ns.remap) if ns.remap else None,
           "best_effort": (None if ns.best_effort is None
                           else " ".join(ns.best_effort) or "sensor_msgs/msg/*")}
    return {k: v for k, v in out.items() if v is not None}


def main(args: list[str] | None = None) -> int:
    from rclpy.parameter import Parameter
    from rclpy.utilities import remove_ros_args

    argv = ["bag_player", *(sys.argv[1:] if args is None else args)]
    ns = build_parser().parse_args(remove_ros_args(argv)[1:])
    overrides = [Parameter(k, value=v) for k, v in cli_parameters(ns).items()]
    made: list[BagPlayer] = []

    def factory():
        made.append(BagPlayer(parameter_overrides=overrides))
        return made[0]

    code = run_node(factory, args=argv)
    if made:
        summary = made[0].summary()
        print(format_summary(summary), flush=True)
        if ns.summary_json:
            ns.summary_json.parent.mkdir(parents=True, exist_ok=True)
            ns.summary_json.write_text(json.dumps(summary, indent=1))
        if made[0].error and not code:
            code = 1
    return code


if __name__ == "__main__":
    sys.exit(main())
