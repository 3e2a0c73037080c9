"""Where the real rosbag2 recordings are (``$LQ_REALBAGS`` or ``<repo>/../shared/realbags``):
four raw-packet bags of a ROS 2 lidar driver, with older metadata (see their README); and
``humble_metadata``, which gives a bag we write the metadata such recordings have."""
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


def humble_metadata(bag, *, storage_identifier="", serialization_format="", db_format=None):
    """Rewrite ``bag``'s metadata.yaml as older rosbag2 versions wrote it: version 5, the
    QoS profiles as one YAML string with numeric policies, no type hashes; with an empty
    ``storage_identifier`` and topic ``serialization_format`` (as in recordings we were
    given). ``db_format``: also set the sqlite3 file's own topic format (old recorders
    left it empty there too)."""
    import sqlite3

    import yaml

    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    qos = ("- history: 1\n  depth: 5\n  reliability: 2\n  durability: 2\n  deadline:\n"
           "    sec: 9223372036\n    nsec: 854775807\n  lifespan:\n    sec: 9223372036\n"
           "    nsec: 854775807\n  liveliness: 1\n  liveliness_lease_duration:\n"
           "    sec: 9223372036\n    nsec: 854775807\n  avoid_ros_namespace_conventions: false")
    old = {"version": 5, "storage_identifier": storage_identifier,
           "duration": meta["duration"], "starting_time": meta["starting_time"],
           "message_count": meta["message_count"],
           "topics_with_message_count": [
               {"topic_metadata": {"name": t["topic_metadata"]["name"],
                                   "type": t["topic_metadata"]["type"],
                                   "serialization_format": serialization_format,
                                   "offered_qos_profiles": qos},
                "message_count": t["message_count"]}
               for t in meta["topics_with_message_count"]],
           "compression_format": "", "compression_mode": "",
           "relative_file_paths": meta["relative_file_paths"], "files": meta["files"]}
    (bag / "metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information": old},
                                                      sort_keys=False))
    if db_format is not None:
        (db,) = bag.glob("*.db3")
        with sqlite3.connect(db) as c:
            c.execute("UPDATE topics SET serialization_format = ?", (db_format,))


#: A user's own topic names (Autoware-like) for every perception bag key (``--topic``).
USER_TOPICS = {"points": "/sensing/lidar/top/pointcloud",
               "points_gt": "/ground_truth/pointcloud",
               "gt_objects": "/ground_truth/objects",
               "detections": "/perception/object_recognition/detection/objects",
               "proposals": "/perception/object_recognition/detection/proposals",
               "segmentation": "/perception/segmentation/pointcloud",
               **{f"head_{k}{v}": f"/ensemble/member_{k}{v}" for k in range(4)
                  for v in ("", "/variance")}}


def user_named_copy(bag, dst, topics=USER_TOPICS):
    """``bag`` (default perception topic names) with every topic renamed as ``topics`` (key
    -> name) says, messages, log times and recorded QoS unchanged. Returns the ``--topic``
    arguments that name them."""
    from lidar_quality_ros.bag_io import BagWriter, bag_info, read_bag
    from lidar_quality_ros.perception_bag import topic_of

    rename = {topic_of(k): t for k, t in topics.items()}
    info = bag_info(bag)
    with BagWriter(dst) as w:
        for m in read_bag(bag):
            w.write(rename.get(m.topic, m.topic), m.msgtype, m.stamp_ns, m.raw,
                    qos=info.topics[m.topic].qos)
    present = {rename.get(t, t) for t in info.topics}
    return [a for k, t in topics.items() if t in present for a in ("--topic", f"{k}={t}")]
