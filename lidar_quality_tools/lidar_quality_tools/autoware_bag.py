"""A perception bag with its detection topics as Autoware's DetectedObjects.

Every vision_msgs/Detection3DArray topic of the bag (the detector's detections and
proposals, the multi-head detector's heads) is rewritten as
autoware_perception_msgs/DetectedObjects (``autoware_objects.objects_from_detections``:
same header, order and boxes, classes by the default class map, scores as float32, ids
dropped: an object's id is its index); the heads' BoxVarianceArray entries name their
detection by that index too (``detection_id`` = ``detection_index``). Every other message
is copied as it is, with its log time and recorded QoS.
``make demo AUTOWARE=1`` replays such a bag into the nodes with ``input_type: autoware``.

    python -m lidar_quality_tools.autoware_bag --bag IN --out OUT
"""
from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

#: changes whenever the conversion does: a twin written by another version is rewritten
FORMAT = "2"
DET = "vision_msgs/msg/Detection3DArray"
VARIANCES = "lidar_quality_msgs/msg/BoxVarianceArray"
OBJECTS = "autoware_perception_msgs/msg/DetectedObjects"


def convert(bag: Path | str, out: Path | str) -> dict[str, int]:
    """Write ``out`` from ``bag`` (module docstring); returns messages converted per topic.
    ``out`` appears whole or not at all (written beside it, then renamed)."""
    from lidar_quality_core.autoware_objects import objects_from_detections
    from lidar_quality_msgs.msg import BoxVarianceArray
    from lidar_quality_ros.bag_io import BagWriter, bag_info, read_bag
    from rclpy.serialization import deserialize_message
    from vision_msgs.msg import Detection3DArray

    out = Path(out)
    info = bag_info(bag)
    tmp = out.with_name(out.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    converted: dict[str, int] = {}
    with BagWriter(tmp) as w:
        for m in read_bag(bag):
            t = info.topics[m.topic]
            if m.msgtype == DET:
                objects = objects_from_detections(deserialize_message(m.raw, Detection3DArray))
                w.write(m.topic, OBJECTS, m.stamp_ns, objects, qos=t.qos)
                converted[m.topic] = converted.get(m.topic, 0) + 1
            elif m.msgtype == VARIANCES:
                var = deserialize_message(m.raw, BoxVarianceArray)
                for v in var.variances:
                    v.detection_id = str(v.detection_index)
                w.write(m.topic, m.msgtype, m.stamp_ns, var, qos=t.qos)
                converted[m.topic] = converted.get(m.topic, 0) + 1
            else:
                w.write(m.topic, m.msgtype, m.stamp_ns, m.raw, qos=t.qos, source=t)
    shutil.rmtree(out, ignore_errors=True)
    tmp.rename(out)
    return converted


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bag", type=Path, required=True, help="perception bag (rosbag2 directory)")
    ap.add_argument("--out", type=Path, required=True, help="the bag to write")
    a = ap.parse_args(argv)
    if not (a.bag / "metadata.yaml").is_file():
        print(f"autoware_bag: {a.bag} is not a rosbag2 directory (no metadata.yaml)",
              file=sys.stderr)
        return 2
    done = convert(a.bag, a.out)
    print(f"autoware_bag: {a.out}: " + (", ".join(f"{t} {n}" for t, n in sorted(done.items()))
                                        or "no Detection3DArray topic") + " converted")
    return 0


if __name__ == "__main__":
    sys.exit(main())
