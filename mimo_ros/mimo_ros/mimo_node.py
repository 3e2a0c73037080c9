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
order), ``output/markers`` (boxes coloured by confidence, ``publish_markers``; built
only while someone subscribes),
``/diagnostics``. The heads' boxes are merged (clusters of heads), so the output has one
detection per cluster, not per input box; unusable input boxes are left out and reported.

The heads are subscribed raw and decoded from their bytes
(``lidar_quality_core.detection_cdr``, same rules as ``boxes.detections_to_arrays``):
rclpy's deserialization of a 100-box head with 4 hypotheses per box costs far more than
the whole frame.

Stopped inputs: an input (a head, a variance topic, the cloud) that sends nothing for
``head_timeout`` seconds of stamp time while the others arrive is declared stopped
(``pipeline.InputLiveness``; diagnostic warning). From then on its slot of every matched
set is filled with a placeholder, so frames come out from the heads that remain (voting
over those heads; missing variances -> NaN aleatoric figures; missing cloud -> NaN point
features); the frames already waiting for it come out at once. Its next message makes it
live again. The synchroniser stays one ``SyncedInputs`` over all inputs: no subscription
is re-created, and the matching rules (exact / approximate, queues, counters) stay the
shared ones.
"""
from __future__ import annotations

import threading
import time

from diagnostic_msgs.msg import DiagnosticStatus
from lidar_quality_core.detection_cdr import decode_detection_array
from lidar_quality_core.meta_model import MetaModels
from lidar_quality_msgs.msg import BoxVarianceArray, ClusterUncertaintyArray
from lidar_quality_ros.node_base import QualityNode
from lidar_quality_ros.params import declare
from lidar_quality_ros.qos import output_qos
from lidar_quality_ros.runner import run_node
from lidar_quality_ros.synced_inputs import SyncedInputs
from sensor_msgs.msg import PointCloud2
from vision_msgs.msg import Detection3DArray
from visualization_msgs.msg import MarkerArray

from lidar_quality_core.mimo.clustering import VOTING_RULES
from .pipeline import (DEFAULT_CLASS_NAMES, InputLiveness, MimoProcessor, MimoSettings,
                       NoHeadError, default_model_paths, settings_from_parameters)


class MimoNode(QualityNode):
    def __init__(self, **kwargs):
        super().__init__("mimo_node", **kwargs)
        self.settings = self._declare_settings()
        self.use_variances = declare(
            self, "use_variances", True,
            "Also subscribe to input/head_k/variance (BoxVarianceArray of head k, same "
            "stamps): the heads' predicted variances (ATV, aleatoric and predictive variance). "
            "Without them these are NaN and the output covariance is the epistemic part.")
        self.head_timeout = declare(
            self, "head_timeout", 0.5,
            "Seconds (of stamp time) an input may send nothing while the others arrive "
            "before the node merges without it (warning in /diagnostics); it rejoins with "
            "its next message.", min_value=1e-3)
        self.publish_markers = declare(self, "publish_markers", True,
                                       "Publish output/markers (boxes coloured by confidence).")
        scores = self.declare_live(
            "output_scores", "confidence",
            "Hypothesis scores of output/detections: 'confidence' (the merged class "
            "distribution scaled so that the top score is the meta confidence) or 'merged' "
            "(the merged class distribution as it is).",
            lambda v: setattr(self.processor, "scores", v), choices=("confidence", "merged"))
        self.models = self._load_models()
        self.processor = MimoProcessor(self.settings, self.models, scores=scores)

        K = self.settings.num_heads
        topics = [(Detection3DArray, f"input/head_{k}") for k in range(K)]
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
        self._partial_frames = 0
        self.pub_detections = self.create_publisher(Detection3DArray, "output/detections",
                                                    output_qos())
        self.pub_uncertainty = self.create_publisher(ClusterUncertaintyArray,
                                                     "output/uncertainty", output_qos())
        self.pub_markers = (self.create_publisher(MarkerArray, "output/markers", output_qos())
                            if self.publish_markers else None)
        # heads arrive as bytes, decoded straight to arrays: rclpy's own deserialization
        # of a 100-box head (400 hypotheses) costs tens of ms per message
        self._stopped_since: dict[int, float] = {}
        self.inputs = SyncedInputs(self, topics, self.on_frame, diagnostics=self.diag,
                                   on_arrival=self._on_arrival, **sync,
                                   raw_decoders={f"input/head_{k}": decode_detection_array
                                                 for k in range(K)},
                                   watchdog=self.new_watchdog(len(topics)))
        self.watch_inputs({**{f"input/head_{k}": f"set num_heads: {k}" for k in range(1, K)},
                           **{f"input/head_{k}/variance": "set use_variances: false"
                              for k in range(K)},
                           "input/points": "set use_points: false (with the models "
                                           "trained without points)"})
        self.diag.set_value("inputs_stopped", "none")
        self.get_logger().info(
            f"mimo_node ready, inputs: {', '.join(self.inputs.topics)}; models: "
            f"{self.models.confidence_model_id}, {self.models.iou_model_id}")

    # ---------------------------------------------------------------- set-up
    def _declare_settings(self) -> MimoSettings:
        num_heads = declare(self, "num_heads", 2,
                            "Number K of detector heads, subscribed as input/head_0 .. "
                            "input/head_{K-1}.", min_value=1, max_value=16)
        eps = declare(self, "eps", 0.5,
                      "DBSCAN radius on the distance 1 - rotated BEV IoU, in (0, 1): boxes "
                      "with BEV IoU >= 1 - eps are neighbours.", min_value=0.0, max_value=1.0)
        voting = declare(self, "voting", "consensus",
                         "Minimum cluster size rule over the K heads: affirmative (1), "
                         "consensus (int(K/2 + 1)) or unanimous (K).", choices=VOTING_RULES)
        min_size = declare(self, "min_cluster_size", 0,
                           "DBSCAN min_samples; 0: from the voting rule.", min_value=0)
        class_aware = declare(self, "class_aware", False,
                              "Cluster only boxes whose labels agree (default: class ignored, "
                              "as LiDAR-MIMO).")
        temperature = declare(self, "temperature", 1.0,
                              "Temperature T of the merged class distribution "
                              "softmax(mean member logits / T).", min_value=1e-6)
        use_points = declare(self, "use_points", False,
                             "Also subscribe to input/points and add the LMD in-box point "
                             "features of the merged box (needs the points model).")
        class_names = declare(self, "class_names", list(DEFAULT_CLASS_NAMES),
                              "Foreground class names of the heads' hypotheses, in the order "
                              "of the meta models' class feature.")
        return settings_from_parameters(dict(
            num_heads=num_heads, eps=eps, voting=voting, min_cluster_size=min_size,
            class_aware=class_aware, temperature=temperature, use_points=use_points,
            class_names=class_names))

    def _load_models(self) -> MetaModels:
        cpath = declare(self, "classifier_path", "",
                        "Meta classifier (confidence) file; empty: the shipped "
                        "models/mimo/mimo[_points]_classifier.joblib.")
        rpath = declare(self, "regressor_path", "",
                        "Meta regressor (predicted IoU) file; empty: the shipped "
                        "models/mimo/mimo[_points]_regressor.joblib.")
        dc, dr = default_model_paths(self.settings.use_points)
        try:
            return MetaModels(cpath or dc, rpath or dr, self.settings.feature_names(),
                              settings=self.settings, method="mimo",
                              warn=self.get_logger().warning)
        except Exception as exc:  # noqa: BLE001 - any load problem refuses the start
            raise RuntimeError(f"mimo_node: cannot load its meta models: {exc} (set "
                               "classifier_path / regressor_path, or ship the models in "
                               "models/mimo/)") from exc

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
    def on_frame(self, synced) -> None:
        t0 = time.perf_counter()
        K = self.settings.num_heads
        msgs = synced.messages
        heads = list(msgs[:K])
        variances = list(msgs[K:2 * K]) if self.use_variances else None
        cloud = msgs[-1] if self.settings.use_points else None
        # markers cost about as much as the rest of the frame: only for a listener
        markers = self.pub_markers is not None and self.pub_markers.get_subscription_count() > 0
        try:
            res = self.processor.process(heads, variances, cloud, markers=markers)
        except NoHeadError:
            self.diag.frame_dropped("no_head")
            return
        if res.counts["partial_frames"]:
            self._partial_frames += 1
            self.diag.set_value("frames_partial", self._partial_frames)
        self.report_issues(res.issues)
        self.pub_detections.publish(res.out.detections)
        self.pub_uncertainty.publish(res.out.uncertainty)
        if res.markers is not None:
            self.pub_markers.publish(res.markers)
        self.diag.frame_processed((time.perf_counter() - t0) * 1e3)


def main(args=None) -> int:
    return run_node(MimoNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
