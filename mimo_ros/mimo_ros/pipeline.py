"""LiDAR-MIMO frame pipeline: head messages -> merged detections, cluster features, meta
confidence / predicted IoU and the output messages (no rclpy; message classes only).

``mimo_node`` is a shell around :func:`process_frame`; the offline dataset / evaluation
code computes its features with :func:`frame_features` on the same messages, so offline
features are the online ones.

Conversions and conventions:

* Head messages (``vision_msgs/Detection3DArray``, the reference perception's convention):
  one ``results`` hypothesis per foreground class, ``score`` = its probability. The class
  distribution of a box has columns ``[background] + class_names`` (``background_index``
  0): a class without a hypothesis has probability 0, hypotheses of classes not in
  ``class_names`` are ignored, background = clip(1 - sum of the foreground probabilities,
  0, 1). ``merge_heads`` takes them with ``score_type="probabilities"`` (logits =
  log(max(p, 1e-12)), then softmax, which renormalises rows that do not sum to 1).
* A head box is left out of the clustering (``merge_heads`` noise, reported in
  ``MimoFrame.issues``) when ``detections_to_arrays`` flags it (non-finite centre / size /
  orientation, a size <= 0, no hypothesis, a non-finite score), when it has no hypothesis
  of a known class, or when a known-class score lies outside [0, 1].
* Predicted variances (``BoxVarianceArray``, optional): row ``detection_index`` of the
  head; an entry whose ``detection_id`` is set and differs from the detection's id, whose
  index is out of range, or whose values are negative / non-finite is ignored (NaN,
  reported). No variance message: all variances NaN, so the aleatoric variances, ATV and
  the predictive variances are NaN (the epistemic ones are not).
* Tilted head boxes (|roll| or |pitch| > ``boxes.TILT_TOLERANCE_DEG``) are merged as
  upright boxes with their yaw, and reported in ``MimoFrame.issues``.
* Frames (``MimoParameters.transform_inputs``, default true): everything is computed in
  the frame of the first head present (the output header's frame): the other heads' boxes
  (``transforms.Transform.apply_boxes``; their x / y variances turned with the transform's
  yaw) and the cloud's points are moved into it with the transform at their own stamp
  (``transforms.input_transforms``). The heads' frame, not the cloud's, so that the merged
  boxes come out in the frame the output message names and the heads' own merge is
  untouched by a cloud in another frame; the ``distance`` feature is then measured from
  the heads' origin (the models are trained with heads in the sensor frame, so heads in
  ``base_link`` shift it by the mount offset: train in the frame you run in). A missing
  transform drops the frame (``transforms.NoTransformError``, ``no_transform``). With
  ``transform_inputs`` false a differing frame_id is reported in ``MimoFrame.issues`` and
  the inputs are merged as if the frames were equal.
* Missing heads (``None`` in the head list: a head that stopped publishing, see
  :class:`InputLiveness`): the frame is merged over the heads present, and the voting
  rule uses K = their number (consensus of 2 heads needs 2 votes; with one head left, 1).
* Merged detection ids: ``"<head>:<id>"`` of the cluster's top (highest-confidence) member.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Sequence

import numpy as np

from lidar_quality_core.autoware_objects import (AutowareOutput, class_map_param,
                                                 existence_fallback_param, input_type_param,
                                                 objects_from_boxes)
from lidar_quality_core.box_geometry import as_boxes, inbox_point_stats
from lidar_quality_core.box_variance_cdr import DecodedVariances
from lidar_quality_core.cluster_uncertainty_cdr import encode_cluster_uncertainty_array
from lidar_quality_core.boxes import (DetectionArrays, arrays_to_detections,
                                      detections_to_arrays, tilt_issue)
from lidar_quality_core.detection_cdr import encode_detections
from lidar_quality_core.domain_profile import DomainCheck, DomainVerdict, DriftParameters
from lidar_quality_core.frame import FrameRejected
from lidar_quality_core.intensity import IntensityScale, intensity_scale_param
from lidar_quality_core.meta_model import MetaModels, model_path_param
from lidar_quality_core.model_store import models_dir
from lidar_quality_core.parameters import group, param
from lidar_quality_core.thresholds import (ConfidenceThresholds, class_thresholds_param,
                                           range_thresholds_param)
from lidar_quality_core.transforms import Transform, input_transforms, transform_tolerance_param

from lidar_quality_core.mimo.head_inputs import class_probabilities, ordered_variances
from lidar_quality_core.mimo.merging import HeadDetections, MergeConfig, MergeResult, merge_heads
from lidar_quality_core.mimo.outputs import output_tables
from lidar_quality_core.mimo.uncertainty import BOX_PARAMS

__all__ = ["DEFAULT_CLASS_NAMES", "STAT_FEATURES", "POINT_FEATURES", "MimoSettings",
           "MimoParameters", "load_models", "OUTPUT_SCORES", "head_detections", "MimoFrame",
           "frame_features", "default_model_paths",
           "MimoOutput", "process_frame", "output_messages", "NoHeadError", "MimoFrameOutputs",
           "MimoProcessor", "InputLiveness", "Arrival"]

DEFAULT_CLASS_NAMES = ("car", "truck", "pedestrian", "cyclist")
#: ``output_scores``: what output/detections' hypothesis scores are
OUTPUT_SCORES = ("confidence", "merged")
#: Cluster statistics of a merged detection (``feature_names`` order).
STAT_FEATURES = (("cluster_size", "head_fraction", "shannon_entropy", "aleatoric_entropy",
                  "mutual_information", "epistemic_total_variance", "aleatoric_total_variance")
                 + tuple(f"epistemic_var_{p}" for p in BOX_PARAMS)
                 + tuple(f"aleatoric_var_{p}" for p in BOX_PARAMS)
                 + ("score", "class", "distance"))
#: LMD own-box point features of the merged box (the same quantities as ``lidar_quality_core.lmd.features``).
POINT_FEATURES = ("points", "points_frac", "refl_max", "refl_mean", "refl_std")
_MODEL_PREFIX = {False: "mimo", True: "mimo_points"}


@dataclass(frozen=True)
class MimoSettings:
    """What turns K head messages into merged detections and their feature rows.

    Features (``feature_names``): ``cluster_size`` (members, may exceed K), ``head_fraction``
    (distinct heads among the members / heads of the frame), SE, AE, MI [bit], ETV, ATV,
    the epistemic (between-member) and aleatoric (mean predicted) variance of each box
    parameter, the merged ``score`` (probability of the merged label), ``class`` (index
    into ``class_names``), ``distance`` (BEV range of the merged centre [m]); with
    ``use_points`` also the LMD own-box point features of the merged box.
    """

    num_heads: int = param(
        2, "Number K of detector heads, subscribed as input/head_0 .. input/head_{K-1}.",
        min_value=1, max_value=16)
    merge: MergeConfig = group(MergeConfig(score_type="probabilities", background_index=0))
    use_points: bool = param(
        False, "Also subscribe to input/points and add the LMD in-box point features of the "
        "merged box (needs the points model).")
    class_names: tuple = param(
        list(DEFAULT_CLASS_NAMES), "Foreground class names of the heads' hypotheses, in the "
        "order of the meta models' class feature.")
    intensity_scale: str = intensity_scale_param("the reflectance features (use_points)")

    def feature_names(self) -> tuple[str, ...]:
        return STAT_FEATURES + (POINT_FEATURES if self.use_points else ())

    def validate(self) -> None:
        """Raise ``ValueError`` naming what is wrong."""
        if not isinstance(self.num_heads, (int, np.integer)) or self.num_heads < 1:
            raise ValueError(f"num_heads must be an integer >= 1, got {self.num_heads!r}")
        if self.merge.score_type != "probabilities" or self.merge.background_index != 0:
            raise ValueError("merge must take probabilities with the background in column 0 "
                             "(score_type='probabilities', background_index=0): that is what "
                             "head_detections builds from the messages")
        names = tuple(self.class_names)
        if not names or not all(isinstance(c, str) and c for c in names):
            raise ValueError(f"class_names must be non-empty strings, got {names!r}")
        if len(set(names)) != len(names):
            raise ValueError(f"class_names has duplicates: {names!r}")
        m = self.merge.min_cluster_size
        if m is not None and m > self.num_heads:
            raise ValueError(
                f"min_cluster_size {m} > num_heads {self.num_heads}: a cluster reaches more "
                "than K members only when one head puts several boxes on one object, so "
                "almost every object would be dropped (the voting rules need at most K: "
                "affirmative 1, consensus int(K/2 + 1), unanimous K; 0 takes the rule's)")


def default_model_paths(use_points: bool = False) -> tuple[Path, Path]:
    """Shipped classifier and regressor: ``models_dir()/mimo/<prefix>_{classifier,
    regressor}.joblib`` with prefix ``mimo`` (cluster statistics) or ``mimo_points``."""
    prefix = _MODEL_PREFIX[bool(use_points)]
    d = models_dir() / "mimo"
    return d / f"{prefix}_classifier.joblib", d / f"{prefix}_regressor.joblib"


@dataclass(frozen=True)
class MimoParameters:
    """Every parameter of mimo_node besides the common ones (``QualityNode``)."""

    settings: MimoSettings = group(MimoSettings())
    use_variances: bool = param(
        True, "Also subscribe to input/head_k/variance (BoxVarianceArray of head k, same "
        "stamps): the heads' predicted variances (ATV, aleatoric and predictive variance). "
        "Without them these are NaN and the output covariance is the epistemic part.")
    head_timeout: float = param(
        0.5, "Seconds (of stamp time) an input may send nothing while the others arrive before "
        "the node merges without it (warning in /diagnostics); it rejoins with its next "
        "message.", min_value=1e-3)
    min_confidence: float = param(
        0.0, "Publish on output/detections (output/objects) only merged detections with a "
        "meta confidence >= this (and not NaN); 0 keeps every one. output/uncertainty "
        "always lists all of them.", min_value=0.0, max_value=1.0)
    class_min_confidence: str = class_thresholds_param("output/detections (output/objects)")
    range_min_confidence: str = range_thresholds_param("output/detections (output/objects)")
    publish_markers: bool = param(True, "Publish output/markers (boxes coloured by confidence).")
    input_type: str = input_type_param("input/head_k", "output/detections")
    autoware_class_map: str = class_map_param()
    existence_fallback: float = existence_fallback_param(
        "the merged class score (the top merged class probability)")
    transform_inputs: bool = param(
        True, "Transform heads (and input/points) whose frame_id differs from the first head's "
        "into that frame (/tf_static, /tf); a frame whose transform is missing is dropped "
        "(counted as no_transform, with a warning naming the frames). false: merge as if "
        "the frames were equal (warning).")
    transform_tolerance: float = transform_tolerance_param()
    drift: DriftParameters = group(DriftParameters())
    output_scores: str = param(
        "confidence", "Hypothesis scores of output/detections: 'confidence' (the merged class "
        "distribution scaled so that the top score is the meta confidence) or 'merged' (the "
        "merged class distribution as it is).", choices=OUTPUT_SCORES, live=True)
    classifier_path: str = model_path_param(
        "classifier", "confidence", "models/mimo/mimo[_points]_classifier.joblib")
    regressor_path: str = model_path_param(
        "regressor", "predicted IoU", "models/mimo/mimo[_points]_regressor.joblib")


def load_models(params: MimoParameters, warn=None) -> MetaModels:
    """The meta models of ``params`` (the shipped pair of ``use_points`` unless paths are
    set), checked against the feature schema and the recorded training settings;
    ``RuntimeError`` saying what and why otherwise."""
    s = params.settings
    dc, dr = default_model_paths(s.use_points)
    try:
        return MetaModels(params.classifier_path or dc, params.regressor_path or dr,
                          s.feature_names(), settings=s, method="mimo", warn=warn)
    except Exception as exc:  # noqa: BLE001 - any load problem refuses the start
        raise RuntimeError(f"cannot load the MIMO meta models: {exc} (set classifier_path / "
                           "regressor_path, or ship the models in models/mimo/)") from exc


# ------------------------------------------------------------------ decoding
def _class_probabilities(arrays: DetectionArrays, class_names):
    """``(probs (n, 1 + C) with background column 0 and NaN rows for unusable boxes,
    usable (n,), has a known class (n,), all known scores in [0, 1] (n,))`` (module
    docstring; ``head_inputs.class_probabilities``)."""
    fg = np.full((len(arrays), len(class_names)), np.nan)
    scores = arrays.class_scores
    for c, name in enumerate(class_names):  # a column assignment each: column_stack is ~15 calls
        s = scores.get(name)
        if s is not None:
            fg[:, c] = s
    return class_probabilities(fg, np.asarray(arrays.valid, bool))


def _variance_entries(msg) -> tuple[np.ndarray, list, np.ndarray]:
    """``(detection_index (m,), detection_id (m), values (m, 7))`` of a BoxVarianceArray
    message or of its bytes decoded (``box_variance_cdr.DecodedVariances``)."""
    if isinstance(msg, DecodedVariances):
        return msg.index, msg.ids, msg.values
    v = msg.variances
    return (np.array([e.detection_index for e in v], np.int64), [e.detection_id for e in v],
            np.array([(e.x, e.y, e.z, e.length, e.width, e.height, e.yaw) for e in v],
                     np.float64).reshape(len(v), 7))


def _variances(msg, arrays: DetectionArrays, issues: list | None) -> np.ndarray:
    n = len(arrays)
    if msg is None:
        return np.full((n, 7), np.nan)
    idx, ids, vals = _variance_entries(msg)
    idx = np.asarray(idx, np.int64)
    if len(ids) == n and ids == arrays.ids:   # the usual case: entry k is detection k
        ordered, bad, in_order = ordered_variances(np.asarray(vals, np.float64), idx)
        if in_order:
            _note_ignored(issues, bad)
            return ordered
    # not in order: an entry names its detection by index, and by id unless the id is
    # empty (compared as object arrays: a Python loop over the entries cost 0.07 ms a head)
    match = (idx >= 0) & (idx < n)
    if len(ids):
        named = np.array(ids, dtype=object)
        same = named == ""
        same[match] |= np.array(arrays.ids, dtype=object)[idx[match]] == named[match]
        match &= same
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(vals) & (vals >= 0.0)
    bad = int((~match).sum()) + int((~ok[match].all(axis=1)).sum())
    var = np.full((n, 7), np.nan)
    var[idx[match]] = np.where(ok[match], vals[match], np.nan)  # repeated index: the last
    if len(ids) != n:
        _note(issues, f"{len(ids)} variances for {n} detections")
    _note_ignored(issues, bad)
    return var


def _note(issues, text):
    if issues is not None:
        issues.append(text)


def _note_ignored(issues, bad: int) -> None:
    if bad:
        _note(issues, f"{bad} variance entr{'y' if bad == 1 else 'ies'} ignored (index / id "
                      "mismatch, negative or non-finite)")


def _arrays(det_msg) -> DetectionArrays:
    if isinstance(det_msg, DetectionArrays):
        return det_msg
    decoded = getattr(det_msg, "arrays", None)
    return decoded if isinstance(decoded, DetectionArrays) else detections_to_arrays(det_msg)


def _turned_variances(var: np.ndarray, yaw: float) -> np.ndarray:
    """x / y variances of boxes turned by ``yaw`` (their covariance taken as 0)."""
    c2, s2 = np.cos(yaw) ** 2, np.sin(yaw) ** 2
    out = var.copy()
    out[:, 0] = c2 * var[:, 0] + s2 * var[:, 1]
    out[:, 1] = s2 * var[:, 0] + c2 * var[:, 1]
    return out


def head_detections(det_msg, variance_msg, settings: MimoSettings = MimoSettings(), *,
                    issues: list | None = None,
                    transform: Transform | None = None) -> tuple[HeadDetections, DetectionArrays]:
    """One head's ``HeadDetections`` (class scores = probabilities, background column 0)
    and the decoded arrays of its message. ``det_msg``: a Detection3DArray, or its
    ``DetectionArrays`` already decoded (also anything with such an ``arrays`` attribute,
    e.g. ``detection_cdr.DecodedDetections``). Unusable boxes get NaN class scores, so
    ``merge_heads`` leaves them out; what was wrong is appended to ``issues``.
    ``transform``: into the computation frame (boxes and variances moved; the returned
    arrays hold the moved boxes)."""
    arrays = _arrays(det_msg)
    if transform is not None:
        boxes, tilted = transform.apply_boxes(arrays.boxes)
        arrays = replace(arrays, boxes=boxes)
        if tilted:
            _note(issues, tilted)
    probs, usable, known, in_range = _class_probabilities(arrays, settings.class_names)
    if np.count_nonzero(usable) < len(usable):  # not usable.all(), cheaper once cold
        if issues is not None:
            bad = np.flatnonzero(~usable)
            why = [arrays.reasons[i] or ("no hypothesis of a known class" if not known[i]
                                         else "class score outside [0, 1]") for i in bad[:5]]
            issues.append(f"{len(bad)} unusable box(es): " + ", ".join(
                f"#{i}: {w}" for i, w in zip(bad, why)))
    tilt = tilt_issue(arrays)
    if tilt:
        _note(issues, tilt)
    var = _variances(variance_msg, arrays, issues)
    if transform is not None:
        yaw = transform.rpy()[2]
        if yaw:
            var = _turned_variances(var, yaw)
    return HeadDetections(arrays.boxes, probs, var), arrays


# ------------------------------------------------------------------ features
@dataclass
class MimoFrame:
    """One frame: the merge result, its feature rows and where the members came from."""

    merge: MergeResult
    features: np.ndarray                 # (C, F) float64, settings.feature_names() order
    heads_used: list[int]                # head indices present (merge head j = heads_used[j])
    arrays: list[DetectionArrays] = field(default_factory=list)  # per used head
    issues: list[str] = field(default_factory=list)              # input problems seen
    class_names: tuple = DEFAULT_CLASS_NAMES                      # foreground columns 1..

    def __len__(self) -> int:
        return len(self.merge)

    def top_heads(self) -> np.ndarray:
        """Head index (of the K inputs) of each merged detection's top member."""
        m = self.merge
        return np.asarray(self.heads_used, np.intp)[m.member_head[m.top_member]]

    def merged_ids(self, by_index: bool = False) -> list[str]:
        """``"<head>:<id>"`` of each merged detection's top member; ``by_index``: its index
        in its head instead of its id (as for Autoware objects, which have no id)."""
        m = self.merge
        heads = m.member_head[m.top_member].tolist()
        rows = m.member_index[m.top_member].tolist()
        if by_index:
            return [f"{self.heads_used[h]}:{r}" for h, r in zip(heads, rows)]
        prefix = [f"{k}:" for k in self.heads_used]
        ids = [a.ids for a in self.arrays]
        return [prefix[h] + str(ids[h][r]) for h, r in zip(heads, rows)]

    def class_labels(self) -> list[str]:
        """Class name of each merged detection."""
        return [self.class_names[c - 1] for c in self.merge.labels.tolist()]


def _decode_cloud(cloud):
    """``(xyz, intensity or None)`` of a PointCloud2 or an ``(xyz, intensity)`` pair."""
    if isinstance(cloud, tuple):
        return cloud
    from lidar_quality_core.pointcloud import xyz_intensity

    return xyz_intensity(cloud)


def _point_features(cloud, merge: MergeResult) -> np.ndarray:
    """LMD's own-box point quantities of the merged boxes (``POINT_FEATURES``:
    ``box_geometry.inbox_point_stats``); NaN for a box that is not finite, of size <= 0
    or with a non-finite score, and the reflectance columns NaN without intensity."""
    out = np.full((len(merge), len(POINT_FEATURES)), np.nan)
    if cloud is None or not len(merge):
        return out
    xyz, inten = _decode_cloud(cloud)
    no_intensity = inten is None
    if no_intensity:  # counts stay valid; reflectance statistics unknown (NaN below)
        inten = np.zeros(len(xyz), np.float32)
    b = as_boxes(merge.boxes)
    st, n_usable = inbox_point_stats(xyz, inten, b)
    out[:, 0] = st.count
    out[:, 1] = st.count / n_usable if n_usable else 0.0
    out[:, 2], out[:, 3], out[:, 4] = st.max, st.mean, st.std
    with np.errstate(invalid="ignore"):
        ok = (np.isfinite(b).all(axis=1) & np.isfinite(merge.scores)
              & (np.min(b[:, 3:6], axis=1, initial=np.inf) > 0.0))
    out[~ok] = np.nan
    if no_intensity:
        out[:, 2:] = np.nan
    return out


def cluster_features(merge: MergeResult, settings: MimoSettings, k_used: int,
                     cloud=None) -> np.ndarray:
    """(C, F) feature rows of a merge result (``settings.feature_names()`` order)."""
    st = merge.stats
    C = len(merge)
    out = np.empty((C, len(settings.feature_names())))
    out[:, 0] = st.cluster_size
    out[:, 1] = merge.head_fraction(k_used)
    out[:, 2] = st.shannon_entropy
    out[:, 3] = st.aleatoric_entropy
    out[:, 4] = st.mutual_information
    out[:, 5] = st.epistemic_total_variance
    out[:, 6] = st.aleatoric_total_variance
    out[:, 7:14] = st.epistemic_variance
    out[:, 14:21] = st.aleatoric_variance
    out[:, 21] = merge.scores
    out[:, 22] = merge.labels - 1  # column 0 is the background
    out[:, 23] = np.hypot(merge.boxes[:, 0], merge.boxes[:, 1])
    if settings.use_points:
        out[:, len(STAT_FEATURES):] = _point_features(cloud, merge)
    return out


def _frame_id(msg) -> str | None:
    """frame_id of a message (or ``DecodedDetections``) with a header, else None."""
    header = getattr(msg, "header", None)
    return None if header is None else getattr(header, "frame_id", None)


def _frame_id_mismatches(named) -> list[str]:
    """``"head 1 frame_id 'x' differs from head 0 'y'"`` for each ``(name, message)`` whose
    frame_id differs from the first one's (inputs without a header are skipped)."""
    ids = [(name, f) for name, f in ((n, _frame_id(m)) for n, m in named) if f is not None]
    if not ids:
        return []
    ref_name, ref = ids[0]
    return [f"{name} frame_id {f!r} differs from {ref_name} {ref!r} (merged as if equal)"
            for name, f in ids[1:] if f != ref]


def frame_features(head_msgs: Sequence, variance_msgs: Sequence | None = None,
                   settings: MimoSettings = MimoSettings(), cloud_msg=None, *,
                   transforms: dict | None = None,
                   intensity: IntensityScale | None = None) -> MimoFrame:
    """Decode the heads of one frame (``None``: head missing), merge them and compute the
    features. ``variance_msgs``: one ``BoxVarianceArray`` or ``None`` per head (or None).
    ``cloud_msg``: a PointCloud2 or ``(xyz, intensity)``, used when ``settings.use_points``
    (None there: the point features are NaN). ``transforms``: ``{"head k" | "input/points":
    Transform}`` into the first present head's frame (``transforms.input_transforms``);
    given (even empty), frame_id differences are the caller's business; None: they are
    reported and merged as if equal. ``intensity``: the stream's ``IntensityScale`` (None:
    a new one of ``settings.intensity_scale``, deciding on this frame alone). Raises
    ``ValueError`` without any head."""
    if len(head_msgs) != settings.num_heads:
        raise ValueError(f"{len(head_msgs)} head messages for num_heads={settings.num_heads}")
    if variance_msgs is None:
        variance_msgs = [None] * len(head_msgs)
    elif len(variance_msgs) != len(head_msgs):
        raise ValueError(f"{len(variance_msgs)} variance messages for {len(head_msgs)} heads")
    used = [k for k, m in enumerate(head_msgs) if m is not None]
    if not used:
        raise ValueError("no head message in this frame")
    issues: list[str] = []
    if transforms is None:
        issues += _frame_id_mismatches([(f"head {k}", head_msgs[k]) for k in used]
                                       + [("input/points", cloud_msg)])
        transforms = {}
    if cloud_msg is not None and settings.use_points:
        from lidar_quality_core.pointcloud import padding_mask
        xyz, inten = _decode_cloud(cloud_msg)
        if inten is not None:
            scale = intensity if intensity is not None else IntensityScale(settings.intensity_scale)
            inten = scale.scale(inten)
        padding = padding_mask(xyz)  # an organized cloud's (0, 0, 0): no point (as LMD)
        if padding.any():
            xyz = np.array(xyz, dtype=np.float32)
            xyz[padding] = np.nan
        if "input/points" in transforms:
            xyz = transforms["input/points"].apply_points(xyz)
        cloud_msg = (xyz, inten)
    heads, arrays = [], []
    for k in used:
        mine: list[str] = []
        h, a = head_detections(head_msgs[k], variance_msgs[k], settings, issues=mine,
                               transform=transforms.get(f"head {k}"))
        heads.append(h)
        arrays.append(a)
        issues += [f"head {k}: {t}" for t in mine]
    merge = merge_heads(heads, settings.merge, num_heads=len(used))
    return MimoFrame(merge, cluster_features(merge, settings, len(used), cloud_msg), used,
                     arrays, issues, tuple(settings.class_names))


# ------------------------------------------------------------------ outputs
@dataclass
class MimoOutput:
    """Everything the node publishes for one frame (markers aside)."""

    frame: MimoFrame
    confidence: np.ndarray        # (C,) meta confidence
    predicted_iou: np.ndarray     # (C,)
    detections: object            # vision_msgs/Detection3DArray (or its CDR bytes), or
    #                               autoware_perception_msgs/DetectedObjects
    uncertainty: object           # lidar_quality_msgs/ClusterUncertaintyArray
    fallback: int | None = None   # DetectedObjects: objects given the fallback existence
    kept: np.ndarray | None = None  # (C,) published on the detections output (thresholds)
    removed: dict = field(default_factory=dict)  # "removed.<class>.<bin>" -> count
    verdict: DomainVerdict | None = None         # the drift check's (None: not checked)


def output_messages(header, frame: MimoFrame, confidence, predicted_iou, *,
                    scores: str = "confidence", confidence_model_id: str = "",
                    iou_model_id: str = "", serialized: bool = False,
                    autoware: AutowareOutput | None = None, kept=None,
                    drift: DomainVerdict | None = None, serialized_uncertainty: bool = False):
    """``(Detection3DArray, ClusterUncertaintyArray)`` of the merged detections; with
    ``serialized`` the detections as CDR bytes (``detection_cdr.encode_detections``, the
    same message; a publisher takes them as they are, ~5x cheaper than building and
    serializing the message objects).

    Detections: mean box (yaw of the top member), id ``"<head>:<id>"``, one hypothesis
    per foreground class, highest first, pose covariance diagonal = predictive variance of
    x, y, z and yaw (roll, pitch 0). ``scores="confidence"``: the merged class distribution
    scaled by confidence / p(label), so the top hypothesis carries the meta confidence and
    the ratios between classes are the merged distribution's (NaN confidence: unscaled);
    ``"merged"``: the merged distribution as it is. Where the heads' predicted variances
    are unknown (no variance input) the covariance is the epistemic variance alone, a lower
    bound (ATV in the uncertainty message is then NaN).

    ``autoware``: the detections as autoware_perception_msgs/DetectedObjects instead
    (``autoware_objects.objects_from_boxes``: existence_probability = confidence, the same
    class scores, x / y / z / yaw variances on the pose covariance); the detections
    element is then ``(DetectedObjects, objects given the fallback existence)``.
    ``kept`` (C,) bool: only those go into the detections message (thresholds); the
    uncertainty message lists every merged detection (``detection_index`` = its index among
    them, ``detection_id`` = the published detection's id) and carries the message version
    and the drift check's verdict (``drift``; None: not checked, drift_level DRIFT_OFF).
    ``serialized_uncertainty``: that message as CDR bytes
    (``cluster_uncertainty_cdr``, the same message).
    """
    from lidar_quality_msgs.msg import ClusterUncertainty, ClusterUncertaintyArray

    m = frame.merge
    names = frame.class_names
    conf = np.asarray(confidence, np.float64).reshape(-1)
    iou = np.asarray(predicted_iou, np.float64).reshape(-1)
    if len(conf) != len(m) or len(iou) != len(m):
        raise ValueError(f"{len(conf)} confidences / {len(iou)} IoUs for {len(m)} detections")
    if scores not in OUTPUT_SCORES:
        raise ValueError(f"scores must be 'confidence' or 'merged', got {scores!r}")
    st = m.stats
    ids = frame.merged_ids()
    labels = frame.class_labels()
    r = np.arange(len(m)) if kept is None else np.flatnonzero(kept)
    fg_r, cov_r, figures = output_tables(m, conf, iou, r, scale=scores == "confidence")
    boxes, ids_r = m.boxes[r], [ids[i] for i in r.tolist()]
    if autoware is not None:
        own = autoware.existence_fallback < 0  # the merged score, as on the vision output
        dets = objects_from_boxes(
            header, boxes, names, fg_r, conf[r], variance=cov_r[:, [0, 1, 2, 5]],
            fallback=m.scores[r] if own else np.full(len(r), autoware.existence_fallback),
            class_map=autoware.class_map)
    elif serialized:
        dets = encode_detections(header, boxes, names, fg_r, ids=ids_r, covariance_diagonal=cov_r)
    else:
        dets = arrays_to_detections(header, boxes, [labels[i] for i in r.tolist()], m.scores[r],
                                    ids=ids_r,
                                    class_scores={n: fg_r[:, c] for c, n in enumerate(names)},
                                    covariance_diagonal=cov_r)
    verdict = (drift or DomainVerdict({})).message_fields(ClusterUncertaintyArray)
    if serialized_uncertainty:
        return dets, encode_cluster_uncertainty_array(
            header, confidence_model_id, iou_model_id, ids, labels, st.cluster_size,
            figures, **verdict)
    size = st.cluster_size.tolist()
    se, ae, mi = (st.shannon_entropy.tolist(), st.aleatoric_entropy.tolist(),
                  st.mutual_information.tolist())
    etv, atv = st.epistemic_total_variance.tolist(), st.aleatoric_total_variance.tolist()
    cl, il = conf.tolist(), iou.tolist()
    unc = ClusterUncertaintyArray(header=header, confidence_model_id=confidence_model_id,
                                  iou_model_id=iou_model_id, **verdict)
    unc.clusters = [ClusterUncertainty(detection_index=i, detection_id=ids[i],
                                       class_id=labels[i], cluster_size=size[i],
                                       shannon_entropy=se[i], aleatoric_entropy=ae[i],
                                       mutual_information=mi[i],
                                       epistemic_total_variance=etv[i],
                                       aleatoric_total_variance=atv[i], confidence=cl[i],
                                       predicted_iou=il[i])
                    for i in range(len(m))]
    return dets, unc


def process_frame(header, head_msgs, variance_msgs, settings: MimoSettings, models, *,
                  cloud_msg=None, scores: str = "confidence",
                  serialized: bool = False, transforms: dict | None = None,
                  intensity: IntensityScale | None = None,
                  autoware: AutowareOutput | None = None,
                  thresholds: ConfidenceThresholds | None = None,
                  domain: DomainCheck | None = None,
                  serialized_uncertainty: bool = False) -> MimoOutput:
    """The node's work for one frame, decode to output messages: ``frame_features``,
    ``models.predict`` (a ``MetaModels``), the drift check (``domain``; its ``passthrough``
    puts the merged scores in place of the confidences), ``thresholds`` (what is
    published), ``output_messages`` (``serialized``: the detections as bytes;
    ``serialized_uncertainty``: the uncertainty message as bytes)."""
    frame = frame_features(head_msgs, variance_msgs, settings, cloud_msg,
                           transforms=transforms, intensity=intensity)
    conf, iou = models.predict(frame.features)
    verdict = None
    if domain is not None:
        verdict = domain(frame_quantities(frame, models.feature_names))
        if verdict.passthrough:
            conf, iou = frame.merge.scores.astype(np.float64), np.full(len(conf), np.nan)
    kept, removed = (thresholds or ConfidenceThresholds()).keep(
        conf, frame.class_labels(), frame.merge.boxes)
    dets, unc = output_messages(header, frame, conf, iou, scores=scores,
                                confidence_model_id=models.confidence_model_id,
                                iou_model_id=models.iou_model_id, serialized=serialized,
                                autoware=autoware, kept=kept, drift=verdict,
                                serialized_uncertainty=serialized_uncertainty)
    n_fallback = None
    if autoware is not None:
        (dets, n_fallback) = dets
    return MimoOutput(frame, conf, iou, dets, unc, n_fallback, kept, dict(removed), verdict)


def frame_quantities(frame: MimoFrame, feature_names) -> list:
    """What the drift monitor compares with the training profile (as ``mimo-train``
    records it): every feature of the merged detections and their scores, as one matrix
    (``DriftMonitor.add``). (Not their number: how many objects a frame holds is the
    scene's, and differs between the training sequences themselves.)"""
    return [(tuple(feature_names) + ("detector score",),
             np.column_stack([frame.features, frame.merge.scores]))]


class NoHeadError(FrameRejected):
    """A matched set without any head message (every head stopped or undecodable)."""

    reason = "no_head"


@dataclass
class MimoFrameOutputs:
    """One frame's outputs as the node publishes them, with the input problems seen
    (``issues``: cause -> text) and the frame's counts."""

    out: MimoOutput
    issues: dict
    counts: dict
    markers: object = None       # MarkerArray, or None when not asked for
    notes: list = field(default_factory=list)     # decisions to log once (info)
    values: dict = field(default_factory=dict)    # diagnostics values of this frame
    errors: frozenset = frozenset()               # keys of ``issues`` at level ERROR

    @property
    def messages(self) -> dict:
        out = "output/detections" if self.out.fallback is None else "output/objects"
        return {out: self.out.detections, "output/uncertainty": self.out.uncertainty}


class MimoProcessor:
    """mimo_node's frame contract without ROS: the K head messages (``None``: a head that
    stopped), their variance messages (or None) and the cloud (a PointCloud2, an ``(xyz,
    intensity)`` pair or None) in; the output messages, issues and counts out. The node
    and ``process_bag`` both call it.

    A malformed cloud costs the point features (NaN), not the frame (issue ``cloud``);
    head problems are issue ``heads``. No head at all raises :class:`NoHeadError`.
    ``scores`` (``confidence`` | ``merged``) may be changed between frames.

    Frames: with ``transform_inputs`` the other heads and the cloud are moved into the
    first present head's frame with ``transforms`` (a ``transforms.TransformBuffer``, a
    ``lookup(target, source, stamp_ns)`` callable, or None: no transform known); a missing
    one raises ``transforms.NoTransformError`` (the frame is dropped). Without, inputs in
    other frames are merged as if equal (issues ``heads`` and ``cloud_frame_id``).
    ``transforms`` may be replaced between frames."""

    def __init__(self, settings: MimoSettings, models, *, scores: str = "confidence",
                 transforms=None, transform_inputs: bool = True,
                 transform_tolerance: float = 0.05, autoware: AutowareOutput | None = None,
                 thresholds: ConfidenceThresholds | None = None,
                 drift: DriftParameters | None = None, serialized_uncertainty: bool = False):
        settings.validate()
        if scores not in OUTPUT_SCORES:
            raise ValueError(f"scores must be 'confidence' or 'merged', got {scores!r}")
        self.settings, self.models, self.scores = settings, models, scores
        self.transforms, self.transform_inputs = transforms, bool(transform_inputs)
        #: for whoever builds the buffer (process_bag: one per bag)
        self.transform_tolerance = float(transform_tolerance)
        #: DetectedObjects output (Autoware) instead of Detection3DArray
        self.autoware = autoware
        #: what is published on the detections output (min_confidence, per class / range)
        self.thresholds = thresholds
        #: live inputs against the models' training data (``domain_profile``)
        self.domain = DomainCheck(getattr(models, "domain_profile", None), drift)
        #: output/uncertainty as CDR bytes (the node, which only publishes it), not a
        #: message object (``process_bag`` reads its fields)
        self.serialized_uncertainty = bool(serialized_uncertainty)
        self.new_stream()

    def new_stream(self) -> None:
        """Forget what one input stream taught: the intensity scale decided, the drift
        window (``process_bag``: each bag of a batch is a new stream)."""
        self.intensity = IntensityScale(self.settings.intensity_scale)
        self.domain.reset()

    def process(self, heads: Sequence, variances: Sequence | None = None, cloud=None, *,
                markers: bool = False) -> MimoFrameOutputs:
        from lidar_quality_core.pointcloud import CloudFormatError

        s = self.settings
        present = [h for h in heads if h is not None]
        if not present:
            raise NoHeadError("no head message in this frame")
        header = present[0].header
        issues: dict[str, str] = {}
        xyz = None
        if s.use_points and cloud is not None:
            try:
                xyz = _decode_cloud(cloud)
            except CloudFormatError as exc:  # degrade: point features NaN, boxes still out
                issues["cloud"] = f"malformed input/points, point features NaN: {exc}"
            else:
                frame_id = getattr(getattr(cloud, "header", None), "frame_id", None)
                if (not self.transform_inputs and frame_id is not None
                        and frame_id != header.frame_id):
                    issues["cloud_frame_id"] = (
                        f"input/points frame_id {frame_id!r} differs from the "
                        f"heads' {header.frame_id!r} (point features computed as if equal)")
        moved = None
        if self.transform_inputs:
            t = self.transforms
            named = {f"head {k}": h for k, h in enumerate(heads) if h is not None}
            if xyz is not None:
                named["input/points"] = cloud
            moved, notes = input_transforms(
                header.frame_id, named, None if t is None else getattr(t, "lookup", t),
                fix=" (publish it on /tf_static or /tf, or set transform_inputs: false to "
                    "merge as if the frames were equal)")
            if notes:
                issues["frame_id"] = "; ".join(notes)
        self.intensity.note = None
        out = process_frame(header, list(heads), variances, s, self.models, cloud_msg=xyz,
                            scores=self.scores, serialized=True, transforms=moved,
                            intensity=self.intensity, autoware=self.autoware,
                            thresholds=self.thresholds, domain=self.domain,
                            serialized_uncertainty=self.serialized_uncertainty)
        if out.frame.issues:
            issues["heads"] = "; ".join(out.frame.issues)
        mk = None
        if markers:
            from lidar_quality_ros.markers import box_markers

            r = np.flatnonzero(out.kept)  # the published detections
            labels = out.frame.class_labels()
            texts = [f"{labels[i]} {out.confidence[i]:.2f}" for i in r.tolist()]
            mk = box_markers(header, out.frame.merge.boxes[r], out.confidence[r], texts,
                             ns="mimo")
        counts = {"boxes.in": sum(len(a) for a in out.frame.arrays),
                  "detections.out": int(out.kept.sum()),
                  "frames_partial": int(len(present) < len(heads)),
                  **({} if out.fallback is None else {"detections.fallback": out.fallback}),
                  **out.removed}
        values = {"intensity_scale": self.intensity.decided} if s.use_points else {}
        values.update(out.verdict.values)
        if out.verdict.issue:
            issues["domain_drift"] = out.verdict.issue
        return MimoFrameOutputs(out, issues, counts, mk,
                                [self.intensity.note] if self.intensity.note else [], values,
                                frozenset({"domain_drift"}) if out.verdict.error else
                                frozenset())


# ------------------------------------------------------------------ head fallback
@dataclass
class Arrival:
    """What one arrival changed: placeholders ``(input, stamp_ns)`` to add for stopped
    inputs (oldest first), inputs that were just declared stopped, and ones that resumed."""

    placeholders: list[tuple[int, int]] = field(default_factory=list)
    stopped: list[int] = field(default_factory=list)
    resumed: list[int] = field(default_factory=list)


class InputLiveness:
    """Which inputs of a stamp-synchronised set still publish, and the placeholders that
    let the others' frames through without them.

    Time is stamp time: an input is *stopped* once "now" is more than ``timeout_ns`` ahead
    of its own newest stamp (or of the first stamp seen, if it never sent anything). "Now"
    for input j is the second newest stamp among the other inputs' messages, not the
    newest: one message stamped in the future (a bad clock, a corrupt header) must not
    declare every other input stopped; a real stop is seen one message later. This is
    deterministic, works with replayed bags and sim time, and needs no timer: nothing is
    declared stopped while no input arrives at all. From
    then on every stamp seen on a live input (and not yet matched) gets a placeholder for
    each stopped input, so the synchroniser completes the set with ``None`` in that slot;
    when the stopped input declares itself stopped, the stamps still waiting in the queues
    get theirs at once (oldest first), so those frames come out too. A message of a stopped
    input makes it live again (recovery); a placeholder already used for its stamp makes
    that message late (counted by the synchroniser). Stamps jumping back by more than
    ``reset_ns`` behind "now", or every live input having gone back in time (a looped bag,
    however short), forget everything (all inputs live). In approximate mode a
    placeholder is added only if its stamp is more than ``slop_ns`` after the previous one
    of that input, so one frame gets one placeholder. Thread-safe.
    """

    def __init__(self, n_inputs: int, timeout_ns: int, *, slop_ns: int = 0,
                 window: int = 64, reset_ns: int = 1_000_000_000):
        if n_inputs < 1 or timeout_ns <= 0:
            raise ValueError(f"need n_inputs >= 1 and timeout_ns > 0, got {n_inputs}, {timeout_ns}")
        self.n, self.timeout_ns, self.slop_ns = int(n_inputs), int(timeout_ns), int(slop_ns)
        self.window, self.reset_ns = int(window), int(reset_ns)
        self.lock = threading.Lock()
        self._reset()

    def _reset(self) -> None:
        self._newest: list[int | None] = [None] * self.n
        self._top2: list[list[int]] = [[] for _ in range(self.n)]  # two newest stamps each
        self._backward: set[int] = set()   # inputs whose stamps went back since the reset
        self._first: int | None = None
        self._stopped: set[int] = set()
        self._last_placeholder: list[int | None] = [None] * self.n
        self._pending: list[int] = []  # recent distinct stamps of live inputs, sorted
        self._second: int | None = None  # _now() of the current _top2

    @property
    def stopped(self) -> list[int]:
        with self.lock:
            return sorted(self._stopped)

    def arrival(self, index: int, stamp_ns: int, last_matched_ns: int | None = None) -> Arrival:
        """Input ``index`` delivered a message stamped ``stamp_ns``; ``last_matched_ns`` is
        the synchroniser's last emitted stamp (placeholders at or before it would be late)."""
        with self.lock:
            return self._arrival(index, stamp_ns, last_matched_ns)

    def _now(self, exclude: int | None = None) -> int | None:
        """Second newest stamp among the inputs other than ``exclude`` (None: too few)."""
        stamps = [s for j, top in enumerate(self._top2) if j != exclude for s in top]
        if len(stamps) < 2:
            return None
        stamps.sort(reverse=True)
        return stamps[1]

    def _arrival(self, i, t, last_matched):
        out = Arrival()
        now = self._second
        if self._newest[i] is not None and t < self._newest[i]:
            self._backward.add(i)
        live = set(range(self.n)) - self._stopped
        if ((now is not None and t < now - self.reset_ns)
                or (len(live) > 0 and live <= self._backward)):
            out.resumed = sorted(self._stopped)
            self._reset()
        if self._first is None:
            self._first = t
        if self._newest[i] is None or t > self._newest[i]:
            self._newest[i] = t
        top = self._top2[i]
        if t not in top:
            top.append(t)
            top.sort(reverse=True)
            del top[2:]
        if i in self._stopped:
            self._stopped.discard(i)
            self._last_placeholder[i] = None
            out.resumed.append(i)
        # the stamp waits for its set: remember it for inputs that stop later
        p = self._pending
        if t not in p:
            p.append(t)
            p.sort()
            del p[:-self.window]
        if last_matched is not None:
            del p[:sum(1 for s in p if s <= last_matched)]
        # leaving an input out can only lower the second newest stamp: an input within the
        # timeout of the overall one is live without sorting the others' stamps for it
        latest = self._second = self._now()
        for j in range(self.n):
            if j != i and j not in self._stopped:
                ref = self._newest[j] if self._newest[j] is not None else self._first
                if latest is None or latest - ref <= self.timeout_ns:
                    continue
                now = self._now(exclude=j)
                if now is not None and now - ref > self.timeout_ns:
                    self._stopped.add(j)
                    out.stopped.append(j)
        for j in sorted(self._stopped):
            last = self._last_placeholder[j]
            for s in p:
                if (last is None or s > last + self.slop_ns) and (
                        last_matched is None or s > last_matched):
                    out.placeholders.append((j, s))
                    last = s
            self._last_placeholder[j] = last
        out.placeholders.sort(key=lambda js: js[1])
        return out
