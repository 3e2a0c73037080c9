"""``lms_node``: LidarMetaSeg confidence and predicted IoU per segment of a point-cloud
segmentation, online.

Inputs (relative names, sensor-data QoS):

* ``input/points``: a PointCloud2 with ``x, y, z``, an intensity field, optionally a
  ring field, and one probability field per class of ``class_names`` (``-`` / space ->
  ``_``), float32 or uint8 (value / 255);
* or, with ``separate_probabilities``, ``input/points`` (the points) and
  ``input/probabilities`` (the probability fields, the same points in the same order),
  matched by header stamp (``sync_*`` parameters).

Outputs (header copied from ``input/points``):

* ``output/points``: the input points, same count, order and layout, with fields
  ``x, y, z, intensity, label`` (uint16 predicted class), ``segment`` (int32, -1: none),
  ``confidence`` (float32, P(segment is a true positive, IoU_adj > 0)) and
  ``predicted_iou`` (float32); NaN for points without a segment (non-finite, outside the
  vertical field of view, unusable probabilities) or in a segment with fewer than
  ``min_segment_points`` projected points;
* ``output/segments``: SegmentQualityArray, every segment in id order (``segment`` of
  ``output/points`` is its id), excluded ones with NaN confidence;
* ``output/markers``: centroids of the scored segments coloured by confidence
  (``publish_markers``; built only while someone subscribes);
* ``/diagnostics``.

The frame work is :class:`lms_ros.pipeline.LmsProcessor` (no ROS; definitions in
:mod:`lms_ros.pipeline` and :mod:`lidar_quality_core.lms.segment_metrics`); this shell declares the
parameters, loads the models (refusing to start when they are missing or do not fit the
class map), subscribes, calls the processor and publishes. A cloud that cannot be decoded
(missing field, wrong type, point counts that differ) drops the frame (counted as
``malformed_cloud``); renormalized or unusable probabilities raise throttled warnings,
the frame is processed, as is a cloud without an intensity field (the intensity metrics
read 0; throttled warning).
"""
from __future__ import annotations

import time

from lidar_quality_core.meta_model import MetaModels
from lidar_quality_core.pointcloud import CloudFormatError
from lidar_quality_msgs.msg import SegmentQualityArray
from lidar_quality_ros.node_base import QualityNode
from lidar_quality_ros.params import declare
from lidar_quality_ros.qos import output_qos
from lidar_quality_ros.runner import run_node
from lidar_quality_ros.synced_inputs import SyncedInputs
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import MarkerArray

from .pipeline import LmsProcessor, LmsSettings, default_model_paths

_DEFAULTS = LmsSettings()


class LmsNode(QualityNode):
    def __init__(self, **kwargs):
        super().__init__("lms_node", **kwargs)
        self.settings = self._declare_settings()
        try:
            self.settings.validate()
        except ValueError as exc:
            raise ValueError(f"invalid parameter: {exc}") from None
        self.separate = declare(self, "separate_probabilities", False,
                                "Take the probabilities from a second cloud on "
                                "input/probabilities (same points, same order, matched by "
                                "stamp) instead of fields of input/points.", read_only=True)
        self.publish_markers = declare(self, "publish_markers", True,
                                       "Publish output/markers (segment centroids coloured by "
                                       "confidence; built only while someone subscribes).",
                                       read_only=True)
        self.models = self._load_models()
        self.processor = LmsProcessor(self.settings, self.models)

        self.pub_points = self.create_publisher(PointCloud2, "output/points", output_qos(5))
        self.pub_segments = self.create_publisher(SegmentQualityArray, "output/segments",
                                                  output_qos())
        self.pub_markers = (self.create_publisher(MarkerArray, "output/markers", output_qos())
                            if self.publish_markers else None)
        for key, value in (("classes", len(self.settings.class_names)),
                           ("model.confidence", self.models.confidence_model_id),
                           ("model.iou", self.models.iou_model_id)):
            self.diag.set_value(key, value)
        self._counts = dict.fromkeys(("points.in", "points.invalid", "points.out_of_view",
                                      "points.renormalized", "segments", "segments.scored"), 0)
        topics = [(PointCloud2, "input/points")]
        if self.separate:
            topics.append((PointCloud2, "input/probabilities"))
        self.inputs = SyncedInputs(self, topics, self.on_frame, diagnostics=self.diag,
                                   watchdog=self.new_watchdog(len(topics)),
                                   **self.declare_sync_parameters())
        self.watch_inputs({"input/probabilities": "set separate_probabilities: false if the "
                                                  "probabilities are fields of input/points"})
        s = self.settings
        self.get_logger().info(
            f"lms_node ready ({len(s.class_names)} classes, image {s.channels} x {s.width}, "
            f"models {self.models.confidence_model_id} / {self.models.iou_model_id}), "
            f"inputs: {', '.join(self.inputs.topics)}")

    def _declare_settings(self) -> LmsSettings:
        d = _DEFAULTS
        return LmsSettings(
            class_names=tuple(declare(
                self, "class_names", list(d.class_names),
                "Class map: class c (the models' class order) reads the probability field "
                "named class_names[c] with '-' and ' ' replaced by '_'.", read_only=True)),
            channels=declare(self, "channels", d.channels,
                             "Range image rows (sensor beams).", min_value=1, read_only=True),
            fov_up_deg=declare(self, "fov_up_deg", d.fov_up_deg,
                               "Upper edge of the vertical field of view [deg] (rows from "
                               "elevation when the cloud has no ring field).",
                               min_value=-90.0, max_value=90.0, read_only=True),
            fov_down_deg=declare(self, "fov_down_deg", d.fov_down_deg,
                                 "Lower edge of the vertical field of view [deg], below "
                                 "fov_up_deg.", min_value=-90.0, max_value=90.0,
                                 read_only=True),
            width=declare(self, "width", d.width,
                          "Range image columns = 360 deg / horizontal resolution.",
                          min_value=1, read_only=True),
            use_ring=declare(self, "use_ring", d.use_ring,
                             "Take the image row from the cloud's ring field when it has one.",
                             read_only=True),
            ring_zero_top=declare(self, "ring_zero_top", d.ring_zero_top,
                                  "Ring 0 is the top beam (Ouster, lidar_sim); false: ring 0 "
                                  "is the lowest beam (Velodyne drivers).", read_only=True),
            ring_field=declare(self, "ring_field", d.ring_field,
                               "Name of the ring (beam index) field.", read_only=True),
            min_segment_points=declare(
                self, "min_segment_points", d.min_segment_points,
                "Segments with fewer projected points (SP) get no confidence (NaN); the "
                "models must be trained with the same value.", min_value=1, read_only=True),
            sum_tolerance=declare(
                self, "sum_tolerance", d.sum_tolerance,
                "Per-point probabilities summing outside 1 +- this are renormalized (with a "
                "warning); uint8 input adds the quantization bound n * 0.5 / 255.",
                min_value=0.0, max_value=0.999, read_only=True),
        )

    def _load_models(self) -> MetaModels:
        dc, dr = default_model_paths()
        cpath = declare(self, "classifier_path", "",
                        "Meta classifier (model store file with manifest); empty: the "
                        "shipped models/lms/lms_classifier.joblib.", read_only=True) or str(dc)
        rpath = declare(self, "regressor_path", "",
                        "Meta regressor (predicted IoU_adj); empty: the shipped "
                        "models/lms/lms_regressor.joblib.", read_only=True) or str(dr)
        names = self.settings.metric_names()
        try:
            return MetaModels(cpath, rpath, names, settings=self.settings, method="lms",
                              warn=self.get_logger().warning)
        except Exception as exc:  # noqa: BLE001 - any load failure refuses the start
            hint = (" (class_names must be the class map the models were trained with)"
                    if "schema" in str(exc) else "")
            raise RuntimeError(
                f"cannot load the LMS meta models for {len(self.settings.class_names)} classes "
                f"({len(names)} metrics): {exc}{hint}") from exc

    def on_frame(self, synced) -> None:
        t0 = time.perf_counter()
        points = synced.messages[0]
        probs = synced.messages[1] if self.separate else None
        markers = self.pub_markers is not None and self.pub_markers.get_subscription_count() > 0
        try:
            out = self.processor.process(points, probs, markers=markers)
        except CloudFormatError as exc:
            self.warn_input("cloud", f"dropping frame: {exc}")
            self.diag.frame_dropped("malformed_cloud")
            return
        self.diag.clear("cloud")
        self.report_issues(out.issues)
        self.pub_points.publish(out.points)
        self.pub_segments.publish(out.segments)
        if out.markers is not None:
            self.pub_markers.publish(out.markers)
        c, res = self._counts, out.result
        c["points.in"] += len(out.inp)
        c["points.invalid"] += out.inp.n_invalid_points
        c["points.out_of_view"] += int(res.projection.out_of_fov.sum())
        c["points.renormalized"] += out.inp.n_renormalized
        c["segments"] += res.n_segments
        c["segments.scored"] += len(res.kept_ids)
        for key, value in c.items():
            self.diag.set_value(key, value)
        self.diag.frame_processed((time.perf_counter() - t0) * 1e3)


def main(args=None) -> int:
    return run_node(LmsNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
