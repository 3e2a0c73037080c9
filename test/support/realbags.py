"""Where the real rosbag2 recordings are (``$LQ_REALBAGS`` or ``<repo>/../shared/realbags``):
four raw-packet bags of a ROS 2 lidar driver, with older metadata (see their README)."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

#: bag -> (topic, message type, message count, metadata corrections bag_io makes)
REAL_BAGS = {
    "qt128_packets": ("/pandar_packets", "pandar_msgs/msg/PandarScan", 2,
                      ["empty storage_identifier: sqlite3 (from the files)"]),
    "vlp16_packets": ("/velodyne_packets", "velodyne_msgs/msg/VelodyneScan", 4, []),
    "vls128_packets": ("/velodyne_packets", "velodyne_msgs/msg/VelodyneScan", 4,
                       ["empty serialization_format of /velodyne_packets: cdr"]),
    "xt32_packets": ("/pandar_packets", "pandar_msgs/msg/PandarScan", 4, []),
}


def realbags_dir() -> Path:
    env = os.environ.get("LQ_REALBAGS")
    return Path(env) if env else Path(__file__).resolve().parents[3] / "shared" / "realbags"


def real_bag(name: str) -> Path:
    """The bag's directory; the test is skipped, saying so, when it is not there."""
    path = realbags_dir() / name
    if not (path / "metadata.yaml").exists():
        pytest.skip(f"real rosbag2 recording {name} not found in {realbags_dir()} "
                    "(set LQ_REALBAGS)")
    return path
