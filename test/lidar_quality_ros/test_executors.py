"""SubmitOnceExecutor: every ready callback goes to the pool once, coroutine callbacks resume,
and the harness and multi-threaded nodes use it (a callback's error still fails the test:
test_testing)."""
import time

from rclpy.executors import MultiThreadedExecutor
from rclpy.task import Future
from std_msgs.msg import String

from lidar_quality_ros import runner
from lidar_quality_ros.executors import SubmitOnceExecutor
from lidar_quality_ros.qos import output_qos


def test_the_harness_and_multithreaded_nodes_use_it(ros):
    assert isinstance(ros.executor, SubmitOnceExecutor)
    assert isinstance(ros.executor, MultiThreadedExecutor)
    assert issubclass(runner._DrainingExecutor, SubmitOnceExecutor)


def test_each_message_is_handed_to_the_pool_once(ros):
    """rclpy's own MultiThreadedExecutor (Jazzy) resubmits a task until a pool thread starts
    it: thousands of submissions for a few dozen messages (module docstring)."""
    n = 30
    pub = ros.publisher(String, "burst", output_qos(n))
    col = ros.collector(String, "burst", output_qos(n))
    assert ros.wait_for_match(pub)
    before = ros.executor.submissions
    for i in range(n):
        pub.publish(String(data=str(i)))
    assert col.wait_for(n, timeout=10.0)
    assert [m.data for m in col.messages] == [str(i) for i in range(n)]
    # one task per message; the harness node has nothing else that runs meanwhile
    assert n <= ros.executor.submissions - before <= n + 2


def test_a_suspended_task_is_resumed(ros):
    """A started task that awaits a future is yielded again at the next wake-up once the
    future is done; it must be submitted again then (it started: not a queued duplicate)."""
    results = []

    async def work(word, fut):
        results.append(await fut)

    futures = {w: Future() for w in "abc"}
    tasks = [ros.executor.create_task(work, w, f) for w, f in futures.items()]
    pub = ros.publisher(String, "wake")
    col = ros.collector(String, "wake")
    assert ros.wait_for_match(pub)
    deadline = time.monotonic() + 5.0
    # each task ran up to its await and is suspended (started, not executing, not done):
    # setting the futures earlier would let a first run finish without a resubmission
    started = ros.executor._started
    while not all(t in started and started[t].is_set() and not t.executing() for t in tasks):
        assert time.monotonic() < deadline, "the tasks never ran up to their await"
        time.sleep(0.01)
    assert not any(t.done() for t in tasks)
    for w, f in futures.items():
        f.set_result(w)
    pub.publish(String(data="wake up"))  # the futures have no executor: wake it ourselves
    assert col.wait_for(1, timeout=5.0)
    while not all(t.done() for t in tasks):
        assert time.monotonic() < deadline, f"suspended tasks not resumed: {results}"
        time.sleep(0.01)
    assert sorted(results) == ["a", "b", "c"]
