"""The harness itself: private domains, isolation between worlds, collection timeouts."""
import os

from lidar_quality_ros.testing import RosHarness
from std_msgs.msg import String


def test_each_world_has_its_own_domain(ros):
    with RosHarness() as other:
        assert other.domain_id != ros.domain_id
        assert other.env()["ROS_DOMAIN_ID"] == str(other.domain_id)
        assert other.env()["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
        pub = ros.publisher(String, "shared_name")
        mine = ros.collector(String, "shared_name")
        theirs = other.collector(String, "shared_name")
        assert ros.wait_for_match(pub)
        for _ in range(5):
            pub.publish(String(data="hello"))
        assert mine.wait_for(5, timeout=10.0)
        assert not theirs.wait_for(1, timeout=1.0), "a message crossed into another domain"
        assert pub.get_subscription_count() == 1


def test_collector_times_out(ros):
    col = ros.collector(String, "silence")
    assert not col.wait_for(1, timeout=0.3)
    assert len(col) == 0


def test_loopback_environment():
    assert os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "LOCALHOST"
    assert "ROS_DOMAIN_ID" in os.environ


def test_callback_exceptions_fail_the_test():
    import pytest
    harness = RosHarness()
    pub = harness.publisher(String, "explode")

    def boom(msg):
        raise ValueError("callback bug")
    harness.node.create_subscription(String, "explode", boom, 10)
    assert harness.wait_for_match(pub)
    pub.publish(String(data="x"))
    import time
    deadline = time.monotonic() + 5
    while not harness.errors and time.monotonic() < deadline:
        time.sleep(0.02)
    with pytest.raises(AssertionError, match="callback bug"):
        harness.close()
