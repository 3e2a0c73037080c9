"""``mimo_node``: LiDAR-MIMO merging of a multi-head detector with meta confidence and
predicted IoU (a shell around ``mimo_ros.pipeline.MimoProcessor``).

Inputs (sensor-data QoS, matched by stamp): ``input/head_0`` .. ``input/head_{K-1}``
(Detection3DArray, K = ``num_heads``), with ``use_variances`` also
``input/head_k/variance`` (BoxVarianceArray), with ``use_points`` also ``input/points``
(PointCloud2). Outputs (header of the first head present): ``output/detections`` (merged
Detection3DArray: mean box, merged class distribution in ``results`` top first, scaled so
the top score is the meta confidence; predictive variance of x, y, z, yaw on the pose
covariance diagonal; id ``"<head>:<id>"`` of the top member; see
``pipeline.output_messages``), ``output/uncertainty`` (ClusterUncertaintyArray, same
order; per frame the model ids, the message ``version`` and the drift monitor's verdict on
the window ending at the frame: ``drift_level``, ``drift_score``, ``drift_window_frames``,
``drift_quantities``, ``passthrough``: the confidences are the merged scores),
``output/markers`` (boxes coloured by confidence, ``publish_markers``; built
only while someone subscribes),
``/diagnostics`` (among its values the drift of the merged detections' features and
scores from the models' training data: ``drift.score``, ``drift.level``,
``drift.quantities``; ``drift_action: passthrough`` gives an out-of-domain frame the
merged scores as confidences and NaN predicted IoU). The heads' boxes are merged
(clusters of heads), so the output has one detection per cluster, not per input box;
unusable input boxes are left out and reported.

Autoware (``input_type: autoware``): the heads are autoware_perception_msgs/DetectedObjects
(classes by ``autoware_class_map``) and ``output/objects`` (DetectedObjects) replaces
``output/detections``: one object per merged detection, ``existence_probability`` = meta
confidence (``existence_fallback`` when there is none, counted as
``detections.fallback``), the classification as the scores above, the merged x / y / z /
yaw variances on ``pose_with_covariance`` with ``has_position_covariance``.

The heads and their variances are subscribed raw and decoded from their bytes
(``lidar_quality_core.detection_cdr``, same rules as ``boxes.detections_to_arrays``;
``box_variance_cdr``; ``autoware_cdr``): rclpy's deserialization of a 100-box head with 4
hypotheses per box costs far more than the whole frame. The outputs go out as bytes too
(``detection_cdr.encode_detections``, ``cluster_uncertainty_cdr``): the same messages,
without building and converting one Python message per box or cluster.

Stopped inputs: an input (a head, a variance topic, the cloud) that sends nothing for
``head_timeout`` seconds of stamp time while the others arrive is declared stopped
(``pipeline.InputLiveness``; diagnostic warning). From then on its slot of every matched
set is filled with a placeholder, so frames come out from the heads that remain (voting
over those heads; missing variances -> NaN aleatoric figures; missing cloud -> NaN point
features); the frames already waiting for it come out at once. Its next message makes it
live again. The synchroniser stays one ``SyncedInputs`` over all inputs: no subscription
is re-created, and the matching rules (exact / approximate, queues, counters) stay the
shared ones.

Frames: with ``transform_inputs`` (default) the node listens to ``/tf_static`` and ``/tf``
(``lidar_quality_ros.tf_listener``) and the processor moves the other heads and the cloud
into the first present head's frame (the output header's); a frame whose transform is
missing is dropped (``dropped.no_transform``, a warning naming the frames and the stamp).
"""
from __future__ import annotations

import threading
import time

from diagnostic_msgs.msg import DiagnosticStatus
from functools import partial

from lidar_quality_core.autoware_cdr import decode_detected_objects
from lidar_quality_core.box_variance_cdr import decode_box_variance_array
from lidar_quality_core.autoware_objects import AutowareOutput, parse_class_map
from lidar_quality_core.detection_cdr import decode_detection_array
from lidar_quality_core.thresholds import from_parameters as thresholds_from
from lidar_quality_msgs.msg import BoxVarianceArray, ClusterUncertaintyArray
from lidar_quality_ros.node_base import QualityNode
from lidar_quality_ros.runner import run_node
from sensor_msgs.msg import PointCloud2
from vision_msgs.msg import Detection3DArray
from visualization_msgs.msg import MarkerArray

from .pipeline import InputLiveness, MimoParameters, MimoProcessor, load_models


class MimoNode(QualityNode):
    def __init__(self, **kwargs):
        super().__init__("mimo_node", **kwargs)
        p = self.declare_settings(MimoParameters, live={
            "output_scores": lambda v: setattr(self.processor, "scores", v)})
        self.settings, self.use_variances = p.settings, p.use_variances
        self.head_timeout = p.head_timeout
        self.models = load_models(p, warn=self.get_logger().warning)
        transforms = self.listen_transforms(p.transform_inputs, p.transform_tolerance)
        self.autoware = (AutowareOutput(parse_class_map(p.autoware_class_map),
                                        p.existence_fallback)
                         if p.input_type == "autoware" else None)
        self.processor = MimoProcessor(self.settings, self.models, scores=p.output_scores,
                                       transforms=transforms,
                                       transform_inputs=p.transform_inputs,
                                       autoware=self.autoware,
                                       thresholds=thresholds_from(p.min_confidence,
                                                                  p.class_min_confidence,
                                                                  p.range_min_confidence),
                                       drift=p.drift,
                                       # published as it is: bytes spare building and
                                       # converting a message per cluster
                                       serialized_uncertainty=True)

        K = self.settings.num_heads
        if self.autoware is not None:
            from autoware_perception_msgs.msg import DetectedObjects
            head_type, out_name = DetectedObjects, "output/objects"
        else:
            head_type, out_name = Detection3DArray, "output/detections"
        topics = [(head_type, f"input/head_{k}") for k in range(K)]
        if self.use_variances:
            topics += [(BoxVarianceArray, f"input/head_{k}/variance") for k in range(K)]
        if self.settings.use_points:
            topics.append((PointCloud2, "input/points"))
        sync = self.declare_sync_parameters()
        self.liveness = InputLiveness(
            len(topics), int(round(self.head_timeout * 1e9)),
            slop_ns=int(round(sync["slop_s"] * 1e9)) if sync["mode"] == "approximate" else 0,
            window=max(64, sync["queue_size"] * len(topics)))
        self._arrival_lock = threading.Lock()
        self.create_output(head_type, out_name)
        self.create_output(ClusterUncertaintyArray, "output/uncertainty")
        self.create_markers_output(p.publish_markers, MarkerArray)
        self._stopped_since: dict[int, float] = {}
        # heads arrive as bytes, decoded straight to arrays: rclpy's own deserialization
        # of a 100-box head (400 hypotheses) costs tens of ms per message
        decode = (decode_detection_array if self.autoware is None
                  else partial(decode_detected_objects, class_map=self.autoware.class_map))
        self.start_inputs(
            topics, sync=sync, on_arrival=self._on_arrival,
            raw_decoders={**{f"input/head_{k}": decode for k in range(K)},
                          **{f"input/head_{k}/variance": decode_box_variance_array
                             for k in range(K)}},
            hints={**{f"input/head_{k}": f"set num_heads: {k}" for k in range(1, K)},
                   **{f"input/head_{k}/variance": "set use_variances: false" for k in range(K)},
                   "input/points": "set use_points: false (with the models trained without "
                                   "points)"})
        self.diag.set_value("inputs_stopped", "none")
        self.get_logger().info(
            f"mimo_node ready, inputs: {', '.join(self.inputs.topics)}; models: "
            f"{self.models.confidence_model_id}, {self.models.iou_model_id}")

    # ---------------------------------------------------------------- stopped inputs
    def _on_arrival(self, index: int, stamp_ns: int) -> None:
        # one lock: placeholders of concurrent arrivals reach the synchroniser in order
        with self._arrival_lock:
            change = self.liveness.arrival(index, stamp_ns, self.inputs.sync.last_stamp_ns)
            for j, stamp in change.placeholders:
                self.inputs.inject(j, stamp, None)
        topics = self.inputs.topics
        for j in change.stopped:
            self._stopped_since[j] = time.monotonic()
            self._warn_stopped(j)
        for j in change.resumed:
            self._stopped_since.pop(j, None)
            self.diag.clear(f"stopped.{topics[j]}")
            self.get_logger().info(f"{topics[j]} is back")
        if change.stopped or change.resumed:
            stopped = [topics[j] for j in self.liveness.stopped]
            self.diag.set_value("inputs_stopped", ",".join(stopped) or "none")

    def _warn_stopped(self, j: int, level=DiagnosticStatus.WARN) -> None:
        who, fix = self.input_fix(j)
        self.warn_input(
            f"stopped.{self.inputs.topics[j]}",
            f"{who} sent nothing for > {self.head_timeout} s of stamp time while the other "
            f"inputs arrive: merging without it; if it is not published, {fix}", level)

    @property
    def output_scores(self) -> str:
        """Hypothesis scores of output/detections (parameter ``output_scores``, live)."""
        return self.processor.scores

    def _check(self) -> None:
        super()._check()
        # an input stopped for longer than input_error_timeout is an error, not a hiccup
        now = time.monotonic()
        for j, since in list(self._stopped_since.items()):
            if now - since >= self.input_error_timeout:
                self._warn_stopped(j, DiagnosticStatus.ERROR)

    # ---------------------------------------------------------------- frames
    def process(self, messages: list, markers: bool):
        K = self.settings.num_heads
        variances = messages[K:2 * K] if self.use_variances else None
        cloud = messages[-1] if self.settings.use_points else None
        return self.processor.process(messages[:K], variances, cloud, markers=markers)


def main(args=None) -> int:
    return run_node(MimoNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
