"""``lmd_node``: LidarMetaDetect meta confidence and predicted IoU per 3D detection, online.

Inputs (relative names, sensor-data QoS, matched by header stamp), by ``proposal_mode``:

* ``threshold`` (default): ``input/points``, ``input/detections`` (post-NMS),
  ``input/proposals`` (pre-NMS); a detection's proposal set is every proposal with BEV
  IoU > ``iou_threshold`` (the authors' rule);
* ``exact``: ``input/points``, ``input/proposals``; the node runs the NMS itself
  (``nms_iou_threshold``, ``nms_score_threshold``) and its survivors, in NMS order, are
  the detections (ids of the proposals kept); proposal sets are the exact NMS pre-images;
* ``none``: ``input/points``, ``input/detections`` (detectors without proposals).

Outputs (header copied from the input detections, or the proposals in exact mode):

* ``output/detections``: the same Detection3D messages in the same order with the same
  ids; in each, every ``results[].hypothesis.score`` is multiplied by
  ``confidence / top score``, so that the top hypothesis scores the meta confidence and
  the class distribution keeps its shape (a top score <= 0 cannot be scaled: the top
  hypothesis is set to the confidence). A detection whose box is invalid (non-finite,
  size <= 0, no hypothesis, class not in ``class_names``) is kept with NaN scores.
  The only way a detection disappears is a threshold: ``min_confidence`` > 0,
  ``class_min_confidence`` (per class), ``range_min_confidence`` (per range bin);
  detections below the largest that applies, or with NaN confidence, are not published
  (they stay in ``output/quality``; counted as ``removed.<class>.<bin>``).
* ``output/quality``: DetectionQualityArray, one entry per scored detection (filtered or
  not): index and id, class, original score (top hypothesis before re-scoring),
  confidence, predicted IoU (NaN for invalid boxes); per frame the two model ids, the
  message ``version`` (``MESSAGE_VERSION``) and the drift monitor's verdict on the window
  ending at the frame: ``drift_level`` (``DRIFT_OFF`` / ``DRIFT_WARMING_UP`` /
  ``DRIFT_OK`` / ``DRIFT_WARN`` / ``DRIFT_ERROR``), ``drift_score`` (NaN before a score),
  ``drift_window_frames``, ``drift_quantities`` and ``passthrough`` (the confidences are
  the detector's own scores, ``drift_action: passthrough``).
* ``output/markers``: boxes of the published detections coloured by confidence, labelled
  ``"<class> c=0.87 iou=0.62"`` (``publish_markers``; built only while subscribed).
* ``/diagnostics``, among its values the drift of the inputs from the models' training
  data (``drift.score``, ``drift.level``, ``drift.quantities``, as in ``output/quality``:
  ``domain_profile``;
  ``drift_warn`` / ``drift_error``; ``drift_action: passthrough`` gives an out-of-domain
  frame the detector's own scores and NaN predicted IoU).

Autoware (``input_type: autoware``): ``input/detections`` and ``input/proposals`` are
autoware_perception_msgs/DetectedObjects (classes by ``autoware_class_map``), and
``output/objects`` (DetectedObjects) replaces ``output/detections``: the same objects in
the same order, ``existence_probability`` = meta confidence (``existence_fallback`` when
there is none, counted as ``detections.fallback``), classification probabilities scaled
as the hypothesis scores above (``lidar_quality_core.autoware_objects``).

The frame work is :class:`lmd_ros.pipeline.LmdProcessor` (no ROS); this shell declares
parameters, loads the models (refusing to start when they are missing or invalid),
subscribes, calls the processor and publishes. The Detection3DArray inputs are taken as
serialized bytes and decoded by ``lidar_quality_core.detection_cdr`` (rclpy's own
deserialization of a reference-detector proposal array costs 100-300 ms, the whole LMD
frame ~12 ms), and ``output/detections`` is published as bytes built from them (every
field copied, scores replaced), ``output/quality`` too
(``lidar_quality_core.detection_quality_cdr``, the same message); little-endian CDR
only (what ROS 2 writes on x86 / ARM), other bytes are dropped and counted
(``undecodable_input``). The cloud is taken as bytes too and read in place
(``lidar_quality_core.cloud_cdr``, the points a view of the received bytes). A
malformed cloud (or one without an intensity field) drops the frame (counted as
``malformed_cloud``); invalid boxes raise throttled warnings, the frame is processed.

Frames: with ``transform_inputs`` (default) the node listens to ``/tf_static`` and ``/tf``
(``lidar_quality_ros.tf_listener``, tf2's QoS) and the processor moves detections and
proposals in another frame into the cloud's; a frame whose transform is missing is
dropped (``dropped.no_transform``, a warning naming the frames and the stamp). With
``transform_inputs: false`` a frame_id mismatch is a throttled warning and the frame is
processed as if the frames were equal.
"""
from __future__ import annotations


from functools import partial

from lidar_quality_core.autoware_cdr import decode_detected_objects
from lidar_quality_core.autoware_objects import parse_class_map
from lidar_quality_core.detection_cdr import decode_detection_array
from lidar_quality_core.thresholds import from_parameters as thresholds_from
from lidar_quality_msgs.msg import DetectionQualityArray
from lidar_quality_ros.node_base import QualityNode
from lidar_quality_ros.runner import run_node
from sensor_msgs.msg import PointCloud2
from vision_msgs.msg import Detection3DArray
from visualization_msgs.msg import MarkerArray

from .pipeline import LmdParameters, LmdProcessor, load_models


class LmdNode(QualityNode):
    def __init__(self, **kwargs):
        super().__init__("lmd_node", **kwargs)
        p = self.declare_settings(LmdParameters, live={
            "min_confidence": lambda v: setattr(self.processor, "min_confidence", float(v))})
        self.settings = p.settings
        self.models = load_models(p, warn=self.get_logger().warning)
        transforms = self.listen_transforms(p.transform_inputs, p.transform_tolerance)
        self.processor = LmdProcessor(p.settings, self.models, min_confidence=p.min_confidence,
                                      transforms=transforms,
                                      transform_inputs=p.transform_inputs,
                                      existence_fallback=p.existence_fallback,
                                      thresholds=thresholds_from(p.min_confidence,
                                                                 p.class_min_confidence,
                                                                 p.range_min_confidence),
                                      drift=p.drift,
                                      # published as it is: bytes spare building and
                                      # converting a message per detection
                                      serialized_quality=True)

        mode = p.settings.proposal_mode
        self.autoware = p.input_type == "autoware"
        if self.autoware:
            from autoware_perception_msgs.msg import DetectedObjects
            self.class_map = parse_class_map(p.autoware_class_map)
            det_type, out_name = DetectedObjects, "output/objects"
        else:
            det_type, out_name = Detection3DArray, "output/detections"
        topics = [(PointCloud2, "input/points")]
        if mode != "exact":
            topics.append((det_type, "input/detections"))
        if mode != "none":
            topics.append((det_type, "input/proposals"))
        self.create_output(det_type, out_name)
        self.create_output(DetectionQualityArray, "output/quality")
        self.create_markers_output(p.publish_markers, MarkerArray)
        for key, value in (("proposal_mode", mode), ("input_type", p.input_type),
                           ("model.confidence", self.models.confidence_model_id),
                           ("model.iou", self.models.iou_model_id)):
            self.diag.set_value(key, value)
        # Detection arrays arrive as bytes, decoded by detection_cdr: rclpy's own
        # deserialization of ~450 proposals x 4 hypotheses costs 100-300 ms per frame.
        decode = (partial(decode_detected_objects, class_map=self.class_map) if self.autoware
                  else decode_detection_array)
        self.start_inputs(topics, raw_decoders={
            t: decode for _, t in topics if t != "input/points"}, hints={
            "input/proposals": "set proposal_mode: none if your detector publishes no "
                               "pre-NMS proposals (with the none-mode models)",
            "input/detections": "set proposal_mode: exact if only proposals are published "
                                "(the node then runs the NMS)"})
        self.get_logger().info(
            f"lmd_node ready ({mode} mode, models {self.models.confidence_model_id} / "
            f"{self.models.iou_model_id}), inputs: {', '.join(self.inputs.topics)}")

    def process(self, messages: list, markers: bool):
        msgs = dict(zip(self.inputs.topics, messages))
        return self.processor.process(msgs["input/points"], msgs.get("input/detections"),
                                      msgs.get("input/proposals"), markers=markers)


def main(args=None) -> int:
    return run_node(LmdNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
