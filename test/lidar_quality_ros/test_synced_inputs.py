"""Stamp-synchronised subscriptions over real DDS: approximate matching, loss accounting."""
import time

from lidar_quality_ros.diagnostics import NodeDiagnostics
from lidar_quality_ros.synced_inputs import SyncedInputs
from rclpy.node import Node
from geometry_msgs.msg import PointStamped
from sensor_msgs.msg import PointCloud2
from node_shell_checks import wait_until


class _Pair(Node):
    def __init__(self, **kwargs):
        super().__init__("pair_node", **kwargs)
        self.sets = []
        self.diag = NodeDiagnostics(self, period_s=0)
        self.inputs = SyncedInputs(self, [(PointStamped, "a"), (PointStamped, "b")], self.sets.append,
                                   mode="approximate", slop_s=0.01, diagnostics=self.diag)


def _h(sec, nsec):
    m = PointStamped()
    m.header.frame_id = f"{sec}.{nsec}"
    m.header.stamp.sec, m.header.stamp.nanosec = sec, nsec
    return m


def test_approximate_pairs_and_counts(ros):
    node = ros.start(_Pair)
    pa, pb = ros.sensor_publisher(PointStamped, "a"), ros.sensor_publisher(PointStamped, "b")
    assert ros.wait_for_match(pa) and ros.wait_for_match(pb)
    pa.publish(_h(1, 0))
    time.sleep(0.05)
    pb.publish(_h(1, 5_000_000))       # 5 ms apart: a match
    time.sleep(0.05)
    pa.publish(_h(2, 0))
    time.sleep(0.05)
    pb.publish(_h(2, 50_000_000))      # 50 ms apart: no match
    time.sleep(0.05)
    pa.publish(_h(3, 0))
    time.sleep(0.05)
    pb.publish(_h(3, 0))
    assert wait_until(lambda: len(node.sets) == 2 and node.inputs.unmatched_dropped() == 2)
    assert [tuple(m.header.frame_id for m in s.messages) for s in node.sets] == [
        ("1.0", "1.5000000"), ("3.0", "3.0")]
    # a@2.0 and b@2.05 were superseded by the frame-3 match: both counted as lost
    assert node.inputs.unmatched_dropped() == 2
    assert node.diag.dropped == 2


class _Failing(Node):
    def __init__(self, **kwargs):
        super().__init__("failing_node", **kwargs)
        self.calls = 0
        self.diag = NodeDiagnostics(self, period_s=0)
        self.inputs = SyncedInputs(self, [(PointStamped, "a")], self._boom,
                                   diagnostics=self.diag)

    def _boom(self, synced):
        self.calls += 1
        raise RuntimeError("feature code bug")


def test_callback_exception_is_contained_and_counted(ros):
    node = ros.start(_Failing)
    pub = ros.sensor_publisher(PointStamped, "a")
    assert ros.wait_for_match(pub)
    for sec in (1, 2):
        pub.publish(_h(sec, 0))
        time.sleep(0.05)
    assert wait_until(lambda: node.diag.dropped == 2)
    assert node.calls == 2  # the node survived the first exception
    assert "feature code bug" in node.diag.status().message


def test_worker_keeps_order_and_counts_overrun():
    import threading

    from lidar_quality_ros.synced_inputs import OrderedWorker
    done, overruns = [], []
    gate = threading.Event()

    def slow(item):
        gate.wait(5.0)
        done.append(item)
    worker = OrderedWorker(slow, max_pending=2, on_overrun=overruns.append)
    for i in range(6):  # item 0 is taken at once and blocks; 1..5 pile up behind it
        worker.submit(i)
        time.sleep(0.02)
    gate.set()
    assert wait_until(worker.idle)
    assert done == [0, 4, 5] and sum(overruns) == 3
    worker.stop()


class _Slow(Node):
    def __init__(self, **kwargs):
        super().__init__("slow_node", **kwargs)
        self.seen = []
        self.diag = NodeDiagnostics(self, period_s=0)
        self.inputs = SyncedInputs(self, [(PointStamped, "a")], self._work,
                                   processing_queue_size=50, diagnostics=self.diag)

    def _work(self, synced):
        time.sleep(0.02)  # slower than the input: frames wait, in order
        self.seen.append(synced.messages[0].header.stamp.sec)


def test_frames_processed_in_input_order(ros):
    node = ros.start(_Slow)
    pub = ros.publisher(PointStamped, "a")  # reliable: every message arrives
    assert ros.wait_for_match(pub)
    for sec in range(1, 21):
        pub.publish(_h(sec, 0))
        # taken off DDS before the next (sensor QoS keeps only 5 there; a loaded machine
        # may take longer than a period), yet far faster than the 20 ms processing
        assert wait_until(lambda: node.diag.counts().get("received.a", 0) >= sec)
    assert wait_until(lambda: len(node.seen) == 20)
    assert node.seen == list(range(1, 21))
    assert node.diag.dropped == 0


class _Hooked(Node):
    """Reports arrivals; stands in for input b with None (what mimo_node does for a head
    that stopped)."""

    def __init__(self, **kwargs):
        super().__init__("hooked_node", **kwargs)
        self.sets, self.arrivals = [], []
        self.inputs = SyncedInputs(self, [(PointStamped, "a"), (PointStamped, "b")],
                                   self.sets.append, on_arrival=self._arrived)

    def _arrived(self, index, stamp_ns):
        self.arrivals.append((index, stamp_ns))
        if index == 0:
            self.inputs.inject(1, stamp_ns, None)


def test_arrival_hook_and_inject(ros):
    node = ros.start(_Hooked)
    pa = ros.sensor_publisher(PointStamped, "a")
    assert ros.wait_for_match(pa)
    pa.publish(_h(4, 7))
    assert wait_until(lambda: len(node.sets) == 1)
    assert node.arrivals == [(0, 4_000_000_007)]
    assert node.sets[0].messages[0].header.frame_id == "4.7" and node.sets[0].messages[1] is None


def test_a_cloud_lost_in_transport_is_counted_and_said(ros):
    # A cloud larger than the shared-memory profile carries never reaches the node; Fast
    # DDS reports it lost when the next message arrives. The node (a real lms_node process)
    # counts it in /diagnostics and says why, instead of losing it without a trace. The
    # publisher is test/scripts/cloud_probe.py: a 1 MB cloud, then 72 MB (above the 64 MiB
    # segment) while the node is stopped for a moment, then 1 kB ones.
    import subprocess
    import sys
    from pathlib import Path

    from diagnostic_msgs.msg import DiagnosticArray
    from node_shell_checks import diag_values, executable

    probe = Path(__file__).resolve().parents[1] / "scripts" / "cloud_probe.py"
    diag = ros.collector(DiagnosticArray, "/diagnostics")
    node = ros.spawn([str(executable("lms_ros", "lms_node")), "--ros-args",
                      "-r", "__node:=lms_lost_test", "-r", "input/points:=/lq_probe/cloud",
                      "-p", "diagnostics_period:=0.2"],
                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    assert wait_until(lambda: ros.node.get_subscriptions_info_by_topic("/lq_probe/cloud"),
                      timeout=30.0), "lms_node did not subscribe"
    pub = ros.spawn([sys.executable, str(probe), "pub", "1,72", str(node.pid)],
                    stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    assert pub.wait(timeout=120) == 0, pub.stdout.read()

    def lost():
        for m in list(diag.messages):
            for s in m.status:
                if (s.hardware_id == "/lms_lost_test"
                        and int(diag_values(s).get("dropped.message_lost", 0)) >= 1):
                    return s
        return None

    assert wait_until(lambda: lost() is not None, timeout=10.0), [
        diag_values(s) for m in diag.messages for s in m.status][-1:]
    status = lost()
    assert "lost in transport" in status.message and "LQ_SHM_SEGMENT_MB" in status.message


class _Clocked(Node):
    """One input plus use_sim_time's /clock, both read by the input thread."""

    def __init__(self, **kwargs):
        super().__init__("clocked_node", **kwargs)
        self.sets, self.threads = [], set()
        clock_subs = [s for s in self.subscriptions if s.topic_name == "/clock"]
        self.inputs = SyncedInputs(self, [(PointStamped, "a")], self._got,
                                   on_arrival=self._arrived, also_read=clock_subs)

    def _arrived(self, index, stamp_ns):
        import threading
        self.threads.add(threading.current_thread().name)

    def _got(self, synced):
        self.sets.append(synced.messages[0].header.stamp.sec)


def test_inputs_and_the_clock_are_read_by_the_input_thread_not_the_executor(ros):
    from rclpy.parameter import Parameter
    from rosgraph_msgs.msg import Clock

    node = ros.start(_Clocked, {"use_sim_time": True})
    # the executor never takes these messages: their callback group refuses it
    for sub in node.inputs.reader._subs:
        assert not sub.callback_group.can_execute(sub)
        assert all(not h.callback_group.can_execute(h) for h in sub.event_handlers)
    topics = [s.topic_name for s in node.inputs.reader._subs]
    assert topics == ["/clock", node.inputs.subscriptions[0].topic_name]
    clock = ros.publisher(Clock, "/clock")
    pa = ros.sensor_publisher(PointStamped, "a")
    assert ros.wait_for_match(clock) and ros.wait_for_match(pa)
    c = Clock()
    c.clock.sec = 1234
    clock.publish(c)
    assert wait_until(lambda: node.get_clock().now().nanoseconds == 1234 * 10**9)
    pa.publish(_h(1, 0))
    assert wait_until(lambda: node.sets == [1])
    assert node.threads == {"clocked_node_inputs"}
    # use_sim_time off: rclpy destroys the /clock subscription under the reader, which
    # leaves it out and goes on reading the inputs
    node.set_parameters([Parameter("use_sim_time", value=False)])
    assert wait_until(lambda: len(node.inputs.reader._subs) == 1)
    pa.publish(_h(2, 0))
    assert wait_until(lambda: node.sets == [1, 2])
    assert node.get_clock().now().nanoseconds > 1234 * 10**9 * 1000  # the system clock again


class _BadExtra(Node):
    """One input plus an extra subscription read by the input thread whose callback fails
    (a bug in a /tf or /clock handler): counted, said once per cause, inputs go on."""

    def __init__(self, **kwargs):
        super().__init__("bad_extra_node", **kwargs)
        self.sets = []
        self.diag = NodeDiagnostics(self, period_s=0)
        extra = self.create_subscription(PointStamped, "b", self._boom, 10)
        self.inputs = SyncedInputs(self, [(PointStamped, "a")], self.sets.append,
                                   diagnostics=self.diag, also_read=[extra])

    def _boom(self, msg):
        raise RuntimeError("handler bug")

    def warn_input(self, key, message, level=None, *, transient=False):
        self.diag.warn(key, message, transient=transient)


def test_a_failing_callback_on_the_input_thread_is_counted_and_said(ros):
    from diagnostic_msgs.msg import DiagnosticStatus

    node = ros.start(_BadExtra)
    pa, pb = ros.sensor_publisher(PointStamped, "a"), ros.publisher(PointStamped, "b")
    assert ros.wait_for_match(pa) and ros.wait_for_match(pb)
    pb.publish(_h(1, 0))
    assert wait_until(lambda: node.diag.counts().get("dropped.undecodable_input", 0) == 1)
    status = node.diag.status()
    assert status.level == DiagnosticStatus.WARN
    assert "callback failed: RuntimeError: handler bug" in status.message
    pa.publish(_h(2, 0))  # the input thread reads on
    assert wait_until(lambda: [s.messages[0].header.stamp.sec for s in node.sets] == [2])


def test_worker_warms_up_on_its_own_thread_before_the_first_item():
    import threading

    from lidar_quality_ros.synced_inputs import OrderedWorker
    events = []
    worker = OrderedWorker(lambda item: events.append(("item", item)), max_pending=2,
                           on_overrun=print, name="warm_worker",
                           warmup=lambda: events.append(("warmup",
                                                         threading.current_thread().name)))
    assert worker.ready.wait(5.0)
    worker.submit(1)
    assert wait_until(lambda: len(events) == 2)
    assert events == [("warmup", "warm_worker"), ("item", 1)]
    worker.stop()


class _Warm(Node):
    def __init__(self, **kwargs):
        super().__init__("warm_node", **kwargs)
        self.sets = []
        self.inputs = SyncedInputs(self, [(PointStamped, "a")], self.sets.append,
                                   warmup_memory_mb=16)


def test_inputs_are_ready_only_after_both_threads_warmed_up(ros):
    node = ros.start(_Warm)
    # set before the constructor returned (the subscriptions exist only then)
    assert node.inputs.worker.ready.is_set() and node.inputs.reader.ready.is_set()
    assert node.inputs.warmup_s > 0
    pub = ros.sensor_publisher(PointStamped, "a")
    assert ros.wait_for_match(pub)
    pub.publish(_h(1, 0))
    assert wait_until(lambda: len(node.sets) == 1)


class _WarmFails(Node):
    """A node whose warm-up the machine cannot afford: said once, in /diagnostics too."""

    def __init__(self, **kwargs):
        super().__init__("warm_fails_node", **kwargs)
        self.sets = []
        self.diag = NodeDiagnostics(self, period_s=0)
        self.inputs = SyncedInputs(self, [(PointStamped, "a")], self.sets.append,
                                   diagnostics=self.diag, warmup_memory_mb=8)

    def warn_input(self, key, message, level=None, *, transient=False):
        self.diag.warn(key, message, transient=transient)


def test_a_failed_warm_up_is_said_and_the_inputs_go_on(ros, monkeypatch):
    from diagnostic_msgs.msg import DiagnosticStatus
    from lidar_quality_ros import synced_inputs

    def cannot(megabytes):
        raise MemoryError(f"{megabytes} MB")
    monkeypatch.setattr(synced_inputs, "touch_memory", cannot)
    node = ros.start(_WarmFails)
    assert node.inputs.worker.warmup_error == "MemoryError: 6.0 MB"
    status = node.diag.status()
    assert status.level == DiagnosticStatus.WARN
    assert ("warm-up (warmup_memory_mb) incomplete, the first frames may be slow: frame "
            "thread: MemoryError: 6.0 MB; input thread: MemoryError: 2.0 MB") in status.message
    pa = ros.sensor_publisher(PointStamped, "a")
    assert ros.wait_for_match(pa)
    pa.publish(_h(1, 0))
    assert wait_until(lambda: len(node.sets) == 1)


class _Cloud(Node):
    """One PointCloud2 input: taken as bytes and read by cloud_cdr."""

    def __init__(self, **kwargs):
        super().__init__("cloud_node", **kwargs)
        self.sets = []
        self.diag = NodeDiagnostics(self, period_s=0)
        self.inputs = SyncedInputs(self, [(PointCloud2, "points")], self.sets.append,
                                   diagnostics=self.diag)

    def warn_input(self, key, message, level=None, *, transient=False):
        self.diag.warn(key, message, transient=transient)


def test_a_cloud_input_arrives_as_a_view_of_its_bytes_and_bad_bytes_are_counted(ros):
    import numpy as np
    from diagnostic_msgs.msg import DiagnosticStatus
    from lidar_quality_core.cloud_cdr import DecodedCloud
    from lidar_quality_core.pointcloud import create_xyz_cloud, xyz_intensity
    from std_msgs.msg import Header

    node = ros.start(_Cloud)
    assert node.inputs.subscriptions[0].raw
    pub = ros.sensor_publisher(PointCloud2, "points")
    assert ros.wait_for_match(pub)
    rng = np.random.default_rng(3)
    xyz = rng.normal(size=(1000, 3)).astype(np.float32)
    inten = rng.random(1000).astype(np.float32)
    h = Header(frame_id="lidar")
    h.stamp.sec, h.stamp.nanosec = 5, 17
    pub.publish(create_xyz_cloud(h, xyz, inten))
    assert wait_until(lambda: len(node.sets) == 1)
    got = node.sets[0].messages[0]
    assert isinstance(got, DecodedCloud) and got.header == h
    assert not got.data.flags.writeable
    # taken into the reader's own buffer (serialized_take), lent while the set holds it
    (taker,) = node.inputs.reader._takers.values()
    assert taker.lent() == 1
    back = xyz_intensity(got)
    assert np.array_equal(back[0], xyz) and np.array_equal(back[1], inten)
    # bytes that are no PointCloud2 (another encapsulation): this message only, counted, said
    pub.publish(b"\x00\x00\x00\x00" + bytes(40))
    assert wait_until(lambda: node.diag.counts().get("dropped.undecodable_input", 0) == 1)
    status = node.diag.status()
    assert status.level == DiagnosticStatus.WARN and "cannot decode it" in status.message
    h.stamp.sec = 6
    pub.publish(create_xyz_cloud(h, xyz, inten))
    assert wait_until(lambda: len(node.sets) == 2)


def test_without_rcl_takes_clouds_come_through_rclpy_and_the_node_says_why(ros, monkeypatch,
                                                                          capfd):
    """Where serialized_take cannot load rcl, the clouds are taken by rclpy (bytes, one copy
    more), the same cloud arrives, and the reason is logged once at start."""
    import numpy as np
    from lidar_quality_core.cloud_cdr import DecodedCloud
    from lidar_quality_core.pointcloud import create_xyz_cloud, xyz_intensity
    from std_msgs.msg import Header

    import lidar_quality_ros.synced_inputs as si

    monkeypatch.setattr(si, "buffered_take_available", lambda: (False, "librcl.so left out"))
    node = ros.start(_Cloud)
    assert node.inputs.reader._takers == {}
    assert "clouds taken by rclpy (copied once more): librcl.so left out" in capfd.readouterr().err
    pub = ros.sensor_publisher(PointCloud2, "points")
    assert ros.wait_for_match(pub)
    xyz = np.random.default_rng(4).normal(size=(500, 3)).astype(np.float32)
    inten = np.arange(500, dtype=np.float32)
    h = Header(frame_id="lidar")
    h.stamp.sec = 7
    pub.publish(create_xyz_cloud(h, xyz, inten))
    assert wait_until(lambda: len(node.sets) == 1)
    got = node.sets[0].messages[0]
    assert isinstance(got, DecodedCloud) and got.header == h
    back = xyz_intensity(got)
    assert np.array_equal(back[0], xyz) and np.array_equal(back[1], inten)
