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
  The only way a detection disappears is ``min_confidence`` > 0: detections below it, or
  with NaN confidence, are not published (they stay in ``output/quality``).
* ``output/quality``: DetectionQualityArray, one entry per scored detection (filtered or
  not): index and id, class, original score (top hypothesis before re-scoring),
  confidence, predicted IoU (NaN for invalid boxes), and the two model ids.
* ``output/markers``: boxes of the published detections coloured by confidence, labelled
  ``"<class> c=0.87 iou=0.62"`` (``publish_markers``; built only while subscribed).
* ``/diagnostics``.

The frame work is :class:`lmd_ros.pipeline.LmdProcessor` (no ROS); this shell declares
parameters, loads the models (refusing to start when they are missing or invalid),
subscribes, calls the processor and publishes. The Detection3DArray inputs are taken as
serialized bytes and decoded by ``lidar_quality_core.detection_cdr`` (rclpy's own
deserialization of a reference-detector proposal array costs 100-300 ms, the whole LMD
frame ~12 ms), and ``output/detections`` is published as bytes built from them (every
field copied, scores replaced); little-endian CDR only (what ROS 2 writes on x86 / ARM),
other bytes are dropped and counted (``undecodable_input``). A malformed cloud (or one without an
intensity field) drops the frame (counted as ``malformed_cloud``); invalid boxes and a
frame_id mismatch between the inputs raise throttled warnings, the frame is processed.
"""
from __future__ import annotations

import time

from lidar_quality_core.detection_cdr import decode_detection_array
from lidar_quality_core.meta_model import MetaModels
from lidar_quality_core.pointcloud import CloudFormatError
from lidar_quality_msgs.msg import DetectionQualityArray
from lidar_quality_ros.node_base import QualityNode
from lidar_quality_ros.params import declare
from lidar_quality_ros.qos import output_qos
from lidar_quality_ros.runner import run_node
from lidar_quality_ros.synced_inputs import SyncedInputs
from sensor_msgs.msg import PointCloud2
from vision_msgs.msg import Detection3DArray
from visualization_msgs.msg import MarkerArray

from .pipeline import MODES, LmdProcessor, LmdSettings, default_model_paths

_DEFAULTS = LmdSettings()


class LmdNode(QualityNode):
    def __init__(self, **kwargs):
        super().__init__("lmd_node", **kwargs)
        self.settings = self._declare_settings()
        try:
            self.settings.validate()
        except ValueError as exc:
            raise ValueError(f"invalid parameter: {exc}") from None
        min_conf = self.declare_live(
            "min_confidence", 0.0,
            "Publish on output/detections only detections with a meta confidence >= this "
            "(and not NaN); 0 keeps every detection. output/quality always lists all of them.",
            lambda v: setattr(self.processor, "min_confidence", float(v)),
            min_value=0.0, max_value=1.0)
        self.publish_markers = declare(self, "publish_markers", True,
                                       "Publish output/markers (boxes coloured by "
                                       "confidence; built only while someone subscribes).")
        self.models = self._load_models()
        self.processor = LmdProcessor(self.settings, self.models, min_confidence=min_conf)

        mode = self.settings.proposal_mode
        topics = [(PointCloud2, "input/points")]
        if mode != "exact":
            topics.append((Detection3DArray, "input/detections"))
        if mode != "none":
            topics.append((Detection3DArray, "input/proposals"))
        self.pub_detections = self.create_publisher(Detection3DArray, "output/detections",
                                                    output_qos())
        self.pub_quality = self.create_publisher(DetectionQualityArray, "output/quality",
                                                 output_qos())
        self.pub_markers = (self.create_publisher(MarkerArray, "output/markers", output_qos())
                            if self.publish_markers else None)
        for key, value in (("proposal_mode", mode),
                           ("model.confidence", self.models.confidence_model_id),
                           ("model.iou", self.models.iou_model_id)):
            self.diag.set_value(key, value)
        self._counts = {"detections.in": 0, "detections.out": 0, "detections.invalid": 0}
        # Detection arrays arrive as bytes, decoded by detection_cdr: rclpy's own
        # deserialization of ~450 proposals x 4 hypotheses costs 100-300 ms per frame.
        raw = {t: decode_detection_array for _, t in topics if t != "input/points"}
        self.inputs = SyncedInputs(self, topics, self.on_frame, diagnostics=self.diag,
                                   raw_decoders=raw, watchdog=self.new_watchdog(len(topics)),
                                   **self.declare_sync_parameters())
        self.watch_inputs({
            "input/proposals": "set proposal_mode: none if your detector publishes no "
                               "pre-NMS proposals (with the none-mode models)",
            "input/detections": "set proposal_mode: exact if only proposals are published "
                                "(the node then runs the NMS)"})
        self.get_logger().info(
            f"lmd_node ready ({mode} mode, models {self.models.confidence_model_id} / "
            f"{self.models.iou_model_id}), inputs: {', '.join(self.inputs.topics)}")

    def _declare_settings(self) -> LmdSettings:
        d = _DEFAULTS
        return LmdSettings(
            proposal_mode=declare(
                self, "proposal_mode", d.proposal_mode,
                "Proposal sets: 'threshold' (input/detections + input/proposals, proposals "
                "with BEV IoU > iou_threshold), 'exact' (input/proposals only: the node runs "
                "NMS, sets are the NMS pre-images) or 'none' (input/detections only). The "
                "models must be trained for the same mode.", choices=MODES),
            iou_threshold=declare(
                self, "iou_threshold", d.iou_threshold,
                "threshold mode: a proposal joins a detection's set when their BEV IoU is "
                "above this, in [0, 1).", min_value=0.0, max_value=1.0),
            proposal_score_threshold=declare(
                self, "proposal_score_threshold", d.proposal_score_threshold,
                "threshold mode: proposals scoring <= this are ignored."),
            nms_iou_threshold=declare(
                self, "nms_iou_threshold", d.nms_iou_threshold,
                "exact mode: BEV IoU above which the node's class-agnostic NMS suppresses a "
                "proposal (reference detector: 0.1).", min_value=0.0, max_value=1.0),
            nms_score_threshold=declare(
                self, "nms_score_threshold", d.nms_score_threshold,
                "exact mode: proposals scoring below this take no part in the NMS."),
            class_names=tuple(declare(
                self, "class_names", list(d.class_names),
                "Class names in the order of the models' class feature (class id = "
                "position); a detection of another class gets NaN confidence.")),
        )

    def _load_models(self) -> MetaModels:
        mode = self.settings.proposal_mode
        dc, dr = default_model_paths(mode)
        cpath = declare(self, "classifier_path", "",
                        "Meta classifier (model store file with manifest); empty: the "
                        "shipped models/lmd/lmd_<proposal_mode>_classifier.joblib.",
                        read_only=True) or str(dc)
        rpath = declare(self, "regressor_path", "",
                        "Meta regressor (predicted IoU); empty: the shipped "
                        "models/lmd/lmd_<proposal_mode>_regressor.joblib.",
                        read_only=True) or str(dr)
        try:
            # the recorded training settings first: exact and threshold share a schema
            return MetaModels(cpath, rpath, self.settings.feature_names(),
                              settings=self.settings, method="lmd",
                              warn=self.get_logger().warning)
        except Exception as exc:  # noqa: BLE001 - any load failure refuses the start
            raise RuntimeError(f"cannot load the LMD meta models for proposal_mode "
                               f"'{mode}' ({len(self.settings.feature_names())} features): "
                               f"{exc}") from exc

    def on_frame(self, synced) -> None:
        t0 = time.perf_counter()
        msgs = dict(zip(self.inputs.topics, synced.messages))
        markers = self.pub_markers is not None and self.pub_markers.get_subscription_count() > 0
        try:
            out = self.processor.process(msgs["input/points"], msgs.get("input/detections"),
                                         msgs.get("input/proposals"), markers=markers)
        except CloudFormatError as exc:
            self.warn_input("cloud", f"dropping frame: malformed input/points: {exc}")
            self.diag.frame_dropped("malformed_cloud")
            return
        self.diag.clear("cloud")
        self.report_issues(out.issues)
        self.pub_detections.publish(out.detections)
        self.pub_quality.publish(out.quality)
        if out.markers is not None:
            self.pub_markers.publish(out.markers)
        c = self._counts
        c["detections.in"] += len(out.kept)
        c["detections.out"] += int(out.kept.sum())
        c["detections.invalid"] += int((~out.frame.valid).sum())
        for key, value in c.items():
            self.diag.set_value(key, value)
        self.diag.frame_processed((time.perf_counter() - t0) * 1e3)


def main(args=None) -> int:
    return run_node(LmdNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
