"""rosbag2 output of the simulator, written with ``rosbags`` (no ROS installation needed).

Topics (all stamped with the scan time, frame_id = the lidar frame):

- ``/lidar/points`` sensor_msgs/PointCloud2: x, y, z, intensity (float32), ring (uint16),
  exactly what a real sensor driver publishes;
- ``/lidar/points_gt`` sensor_msgs/PointCloud2: the ground truth of each point of
  ``/lidar/points``, same order: ``label`` (uint16, our class id, see ``classes``) and
  ``instance`` (uint16, 0 = none). A separate cloud keeps the sensor cloud free of
  ground truth, so nodes under test cannot see it;
- ``/lidar/gt_objects`` vision_msgs/Detection3DArray: ground-truth boxes (centre pose,
  size l, w, h), one hypothesis with the class name and score 1, id = instance id;
- ``/clock`` rosgraph_msgs/Clock.

Bag format version 9 (accepted by Jazzy's ``ros2 bag play``), MCAP by default or sqlite3.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from lidar_quality_core.boxes import yaw_to_quaternion
from lidar_quality_core.pointcloud import pack_cloud
from lidar_quality_core.rosbag_types import typestore

TOPICS = {"points": "/lidar/points", "points_gt": "/lidar/points_gt",
          "objects": "/lidar/gt_objects", "clock": "/clock"}
TYPES = {"points": "sensor_msgs/msg/PointCloud2", "points_gt": "sensor_msgs/msg/PointCloud2",
         "objects": "vision_msgs/msg/Detection3DArray", "clock": "rosgraph_msgs/msg/Clock"}


class SimBagWriter:
    """Context manager writing simulated frames into a new bag directory."""

    def __init__(self, path: Path | str, *, storage: str = "mcap", frame_id: str = "lidar"):
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugins = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}
        if storage not in plugins:
            raise ValueError(f"storage must be one of {sorted(plugins)}, got {storage!r}")
        self.ts = typestore()
        self.frame_id = frame_id
        self._writer = Writer(Path(path), version=9, storage_plugin=plugins[storage])
        self._conns = {}

    def __enter__(self):
        self._writer.open()
        for key, topic in TOPICS.items():
            self._conns[key] = self._writer.add_connection(topic, TYPES[key], typestore=self.ts)
        return self

    def __exit__(self, *exc):
        self._writer.close()

    # message builders -----------------------------------------------------------
    def _header(self, stamp_ns: int):
        t = self.ts.types
        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
        return t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec),
                                        frame_id=self.frame_id)

    def cloud(self, stamp_ns: int, columns: dict):
        t = self.ts.types
        packed = pack_cloud(columns)
        fields = [t["sensor_msgs/msg/PointField"](name=n, offset=o, datatype=d, count=c)
                  for n, o, d, c in packed.fields]
        return t["sensor_msgs/msg/PointCloud2"](
            header=self._header(stamp_ns), height=packed.height, width=packed.width,
            fields=fields, is_bigendian=packed.is_bigendian, point_step=packed.point_step,
            row_step=packed.point_step * packed.width,
            data=np.frombuffer(packed.data, dtype=np.uint8), is_dense=packed.is_dense)

    def detections(self, stamp_ns: int, boxes: np.ndarray, class_names, ids):
        t = self.ts.types
        header = self._header(stamp_ns)
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
        quat = yaw_to_quaternion(boxes[:, 6])
        dets = []
        for i, b in enumerate(boxes.tolist()):
            pose = t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](x=b[0], y=b[1], z=b[2]),
                orientation=t["geometry_msgs/msg/Quaternion"](*quat[i].tolist()))
            hyp = t["vision_msgs/msg/ObjectHypothesisWithPose"](
                hypothesis=t["vision_msgs/msg/ObjectHypothesis"](class_id=str(class_names[i]), score=1.0),
                pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)))
            bbox = t["vision_msgs/msg/BoundingBox3D"](
                center=pose, size=t["geometry_msgs/msg/Vector3"](x=b[3], y=b[4], z=b[5]))
            dets.append(t["vision_msgs/msg/Detection3D"](header=header, results=[hyp], bbox=bbox,
                                                         id=str(ids[i])))
        return t["vision_msgs/msg/Detection3DArray"](header=header, detections=dets)

    # writing --------------------------------------------------------------------
    def _write(self, key: str, stamp_ns: int, msg) -> None:
        self._writer.write(self._conns[key], int(stamp_ns),
                           self.ts.serialize_cdr(msg, TYPES[key]))

    def write_frame(self, stamp_ns: int, *, xyz, intensity, ring, label, instance,
                    gt_boxes, gt_class_names, gt_ids) -> None:
        """One scan: sensor cloud, per-point ground truth, ground-truth boxes, clock."""
        t = self.ts.types
        self._write("clock", stamp_ns, t["rosgraph_msgs/msg/Clock"](clock=self._header(stamp_ns).stamp))
        self._write("points", stamp_ns, self.cloud(stamp_ns, {
            "x": np.asarray(xyz)[:, 0].astype(np.float32), "y": np.asarray(xyz)[:, 1].astype(np.float32),
            "z": np.asarray(xyz)[:, 2].astype(np.float32),
            "intensity": np.asarray(intensity, dtype=np.float32),
            "ring": np.asarray(ring, dtype=np.uint16)}))
        self._write("points_gt", stamp_ns, self.cloud(stamp_ns, {
            "label": np.asarray(label, dtype=np.uint16),
            "instance": np.asarray(instance, dtype=np.uint16)}))
        self._write("objects", stamp_ns, self.detections(stamp_ns, gt_boxes, gt_class_names, gt_ids))
