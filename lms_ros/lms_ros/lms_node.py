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

* ``output/points``: the input points, same count, order, height and width, with fields
  ``x, y, z, label`` (uint16 predicted class), ``segment`` (int32, -1: none),
  ``confidence`` (float32, P(segment is a true positive, IoU_adj > 0)) and
  ``predicted_iou`` (float32); NaN for points without a segment (non-finite or (0, 0, 0),
  outside the image, lost their pixel to a nearer point, unusable probabilities) or in a
  segment with fewer than ``min_segment_points`` projected points; with
  ``output_all_fields`` every other field of ``input/points`` too, as received;
* ``output/segments``: SegmentQualityArray, every segment in id order (``segment`` of
  ``output/points`` is its id), excluded ones with NaN confidence; per frame the model
  ids, the message ``version`` and the drift monitor's verdict on the window ending at the
  frame (``drift_level``, ``drift_score``, ``drift_window_frames``, ``drift_quantities``,
  ``passthrough``: the segments are left unscored);
* ``output/markers``: centroids of the scored segments coloured by confidence
  (``publish_markers``; built only while someone subscribes);
* ``/diagnostics``, among its values the drift of the segments' metrics from the models'
  training data (``drift.score``, ``drift.level``, ``drift.quantities``, as in
  ``output/segments``:
  ``domain_profile``; ``drift_action: passthrough`` leaves an out-of-domain frame's
  segments unscored, NaN).

The frame work is :class:`lms_ros.pipeline.LmsProcessor` (no ROS; definitions in
:mod:`lms_ros.pipeline` and :mod:`lidar_quality_core.lms.segment_metrics`); this shell declares the
parameters, loads the models (refusing to start when they are missing or do not fit the
class map), subscribes, calls the processor and publishes. Clouds are taken as serialized
bytes and read in place (``lidar_quality_core.cloud_cdr``: the points a view of the
received bytes; bytes that are no little-endian PointCloud2 are dropped and counted as
``undecodable_input``); ``output/points`` is written as its serialized bytes and
published from them (``cloud_cdr.serialized_cloud``,
``lidar_quality_ros.serialized_publish``). A cloud that cannot be decoded
(missing field, wrong type, point counts that differ) drops the frame (counted as
``malformed_cloud``); renormalized or unusable probabilities raise throttled warnings,
the frame is processed, as is a cloud without an intensity field (the intensity metrics
read 0; throttled warning). The range image comes from the ``sensor`` preset or the
geometry parameters; the share of points without a pixel is a /diagnostics value
(``points.no_pixel_ratio``) with WARN / ERROR thresholds, and models trained on another
image geometry load with a logged warning and the value ``model.geometry``.
"""
from __future__ import annotations

from lidar_quality_msgs.msg import SegmentQualityArray
from lidar_quality_ros.node_base import QualityNode
from lidar_quality_ros.qos import output_qos
from lidar_quality_ros.runner import run_node
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import MarkerArray

from .pipeline import LmsParameters, LmsProcessor, geometry_mismatch, load_models


class LmsNode(QualityNode):
    def __init__(self, **kwargs):
        super().__init__("lms_node", **kwargs)
        p = self.declare_settings(LmsParameters)
        self.separate = p.separate_probabilities
        self.settings = p.settings.resolved()
        self.models = load_models(p, warn=self.get_logger().warning)
        self.processor = LmsProcessor(self.settings, self.models,
                                      all_fields=p.output_all_fields, drift=p.drift)

        self.create_output(PointCloud2, "output/points", output_qos(5))
        self.create_output(SegmentQualityArray, "output/segments")
        self.create_markers_output(p.publish_markers, MarkerArray)
        s = self.settings
        # the image in use and, when the models were trained on another one, what they
        # were trained on (load_models logged the warning)
        for key, value in (("classes", len(s.class_names)),
                           ("model.confidence", self.models.confidence_model_id),
                           ("model.iou", self.models.iou_model_id),
                           ("image", f"{s.sensor or 'custom'}: {s.channels} x {s.width}"),
                           ("model.geometry",
                            geometry_mismatch(self.models, s) or "as trained")):
            self.diag.set_value(key, value)
        topics = [(PointCloud2, "input/points")]
        if self.separate:
            topics.append((PointCloud2, "input/probabilities"))
        self.start_inputs(topics, hints={"input/probabilities": "set separate_probabilities: "
                                         "false if the probabilities are fields of input/points"})
        self.get_logger().info(
            f"lms_node ready ({len(s.class_names)} classes, image {s.channels} x {s.width}"
            f"{f' ({s.sensor})' if s.sensor else ''}, "
            f"models {self.models.confidence_model_id} / {self.models.iou_model_id}), "
            f"inputs: {', '.join(self.inputs.topics)}")

    def process(self, messages: list, markers: bool):
        return self.processor.process(messages[0], messages[1] if self.separate else None,
                                      markers=markers)


def main(args=None) -> int:
    return run_node(LmsNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
