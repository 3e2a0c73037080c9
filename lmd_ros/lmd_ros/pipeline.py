"""LidarMetaDetect per frame: messages -> features -> meta models -> output messages.

Shared by ``lmd_node`` (through :class:`LmdProcessor`, the node's whole frame callback
body), training and evaluation (through :func:`frame_features`, so that a model is
trained on exactly the features the node computes). No rclpy: messages are handled
duck-typed; the message classes of the outputs are imported when a processor is built.
Detection arrays come as Detection3DArray messages (bags, tests) or as
``detection_cdr.DecodedDetections`` (the node, which takes them as bytes: rclpy's
deserialization of a few hundred proposals costs more than the whole frame); both give
the same features.

Proposal modes (``LmdSettings.proposal_mode``, see :mod:`lidar_quality_core.lmd.features`):

* ``"exact"``: only proposals come in; we run class-agnostic rotated BEV NMS on them
  (``nms_iou_threshold``, proposals scoring below ``nms_score_threshold`` or invalid take
  no part) and the survivors, in NMS order (descending score), are the detections we
  score; the proposal set of a survivor is its exact NMS pre-image.
* ``"threshold"``: post-NMS detections and pre-NMS proposals come separately; the set of
  a detection is every proposal scoring above ``proposal_score_threshold`` whose BEV IoU
  with it is above ``iou_threshold`` (the authors' rule).
* ``"none"``: detections only (17 features).

Invalid boxes: a detection whose box cannot be used (``boxes.detections_to_arrays``
reasons: non-finite values, size <= 0, no hypothesis, ...), whose class is not in
``class_names`` ("unknown class", since the model never saw it) or whose score lies
outside [0, 1] gets an all-NaN feature row, ``valid = False``, NaN confidence and NaN
predicted IoU. It stays in the output.

Scores outside [0, 1] (logits, a bug, 1e6): the meta models were trained on detector
probabilities, and a score feature outside their range gives a confidence that looks
fine and means nothing. So such a box is not scored (NaN confidence, above), and a
proposal with such a score is treated like an invalid proposal: it takes no part in the
exact mode's NMS and belongs to no proposal set (the other members' statistics stay in
the models' domain). Both are reported (issue ``"scores"``), with the range seen.

Tilted boxes (|roll| or |pitch| > ``boxes.TILT_TOLERANCE_DEG``): features take the box as
upright with its yaw (the box is kept and scored); reported (issue ``"roll_pitch"``).

Frames (``LmdParameters.transform_inputs``, default true): the features are computed in
the cloud's frame. Detections and proposals whose ``frame_id`` differs from the cloud's are
moved into it (``transforms.Transform.apply_boxes``: centre by the full transform, yaw plus
the transform's yaw; a tilting transform is reported, issue ``"transform"``) with the
transform at their own stamp from the processor's ``transforms`` (a
``transforms.TransformBuffer`` or any ``lookup(target, source, stamp_ns)``). No transform:
the frame is dropped (``transforms.NoTransformError``, counted as ``no_transform``). The
outputs keep the input detections' header and boxes (same order, same ids): only the
computation happens in the cloud's frame. With ``transform_inputs`` false the frames are
taken as equal (issue ``"frame_id"``).

The cloud must have x, y, z and an intensity field (``intensity``, ``reflectance`` or
``i``): the reflectance statistics are model inputs, so a cloud without one is refused
(:class:`~lidar_quality_core.pointcloud.CloudFormatError`), like a malformed one.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from lidar_quality_core.autoware_cdr import DecodedObjects, encode_detected_objects
from lidar_quality_core.autoware_objects import (class_map_param, existence_fallback_param,
                                                 input_type_param)
from lidar_quality_core.boxes import DetectionArrays, detections_to_arrays, tilt_issue
from lidar_quality_core.domain_profile import DomainCheck, DriftParameters
from lidar_quality_core.detection_cdr import (DecodedDetections, encode_detection_array,
                                              rescaled_scores)
from lidar_quality_core.detection_quality_cdr import encode_detection_quality_array
from lidar_quality_core.intensity import IntensityScale, intensity_scale_param
from lidar_quality_core.meta_model import MetaModels, model_path_param
from lidar_quality_core.model_store import models_dir
from lidar_quality_core.parameters import check_fields, group, param
from lidar_quality_core.box_geometry import count_points_in_boxes
from lidar_quality_core.pointcloud import (CloudFormatError, PaddingNote, blank_padding,
                                           padding_counts, xyz_intensity_view)
from lidar_quality_core.thresholds import (ConfidenceThresholds, class_thresholds_param,
                                           range_thresholds_param)
from lidar_quality_core.transforms import Transform, input_transforms, transform_tolerance_param
from lidar_quality_core.lmd import features
from lidar_quality_core.lmd.proposal_sets import nms_preimages

__all__ = ["MODES", "LmdSettings", "LmdParameters", "LmdFrame", "frame_features",
           "default_model_paths", "load_models", "take_detections", "LmdOutputs",
           "LmdProcessor", "frame_id_mismatch"]

MODES = features.MODES


@dataclass(frozen=True)
class LmdSettings:
    """Feature settings; a model is valid only for the settings it was trained with
    (its feature schema is :meth:`feature_names`). Fields made with ``param`` are
    lmd_node's parameters (declared from here)."""

    proposal_mode: str = param(
        "threshold",
        "Proposal sets: 'threshold' (input/detections + input/proposals, proposals with BEV "
        "IoU > iou_threshold), 'exact' (input/proposals only: the node runs NMS, sets are the "
        "NMS pre-images) or 'none' (input/detections only). The models must be trained for "
        "the same mode.", choices=MODES)
    iou_threshold: float = param(
        0.5, "threshold mode: a proposal joins a detection's set when their BEV IoU is above "
        "this.", min_value=0.0, max_value=1.0, open_max=True)
    proposal_score_threshold: float = param(
        0.0, "threshold mode: proposals scoring <= this are ignored.")
    nms_iou_threshold: float = param(
        0.1, "exact mode: BEV IoU above which the node's class-agnostic NMS suppresses a "
        "proposal (reference detector: 0.1).", min_value=0.0, max_value=1.0)
    nms_score_threshold: float = param(
        0.1, "exact mode: proposals scoring below this take no part in the NMS.")
    class_names: tuple = param(
        ["car", "truck", "pedestrian", "cyclist"],
        "Class names in the order of the models' class feature (class id = position); a "
        "detection of another class gets NaN confidence.")
    intensity_scale: str = intensity_scale_param("the reflectance features")
    #: Append the detector's per-class scores (``class_score_<name>``, in ``class_names``
    #: order) to the paper's features (features module: optional extras).
    class_score_features: bool = False

    def feature_names(self) -> tuple[str, ...]:
        return features.feature_names(self.proposal_mode,
                                      self.class_names if self.class_score_features else None)

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first bad setting."""
        check_fields(self)
        names = tuple(self.class_names)
        if not names or not all(isinstance(c, str) and c for c in names):
            raise ValueError(f"class_names must be non-empty strings, got {list(names)}")
        if len(set(names)) != len(names):
            raise ValueError(f"class_names has duplicates: {list(names)}")


@dataclass(frozen=True)
class LmdParameters:
    """Every parameter of lmd_node besides the common ones (``QualityNode``)."""

    settings: LmdSettings = group(LmdSettings())
    min_confidence: float = param(
        0.0, "Publish on output/detections only detections with a meta confidence >= this "
        "(and not NaN); 0 keeps every detection. output/quality always lists all of them.",
        min_value=0.0, max_value=1.0, live=True)
    class_min_confidence: str = class_thresholds_param("output/detections (output/objects)")
    range_min_confidence: str = range_thresholds_param("output/detections (output/objects)")
    publish_markers: bool = param(
        True, "Publish output/markers (boxes coloured by confidence; built only while someone "
        "subscribes).")
    input_type: str = input_type_param("input/detections and input/proposals",
                                       "output/detections")
    autoware_class_map: str = class_map_param()
    existence_fallback: float = existence_fallback_param("the detector's own")
    transform_inputs: bool = param(
        True, "Transform input/detections and input/proposals into input/points' frame "
        "(/tf_static, /tf) when their frame_id differs; a frame whose transform is missing is "
        "dropped (counted as no_transform, with a warning naming the frames). false: compute "
        "as if the frames were equal (warning frame_id).")
    transform_tolerance: float = transform_tolerance_param()
    drift: DriftParameters = group(DriftParameters())
    classifier_path: str = model_path_param(
        "classifier", "confidence", "models/lmd/lmd_<proposal_mode>_classifier.joblib")
    regressor_path: str = model_path_param(
        "regressor", "predicted IoU", "models/lmd/lmd_<proposal_mode>_regressor.joblib")


def default_model_paths(mode: str) -> tuple[Path, Path]:
    """(classifier, regressor) shipped for ``mode``: ``models_dir()/lmd/lmd_<mode>_*.joblib``."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    d = models_dir() / "lmd"
    return d / f"lmd_{mode}_classifier.joblib", d / f"lmd_{mode}_regressor.joblib"


def load_models(params: LmdParameters, warn=None) -> MetaModels:
    """The meta models of ``params`` (the shipped pair of the proposal mode unless paths
    are set), checked against the feature schema and the recorded training settings;
    ``RuntimeError`` saying what and why otherwise."""
    s = params.settings
    dc, dr = default_model_paths(s.proposal_mode)
    try:
        # the recorded training settings first: exact and threshold share a schema
        return MetaModels(params.classifier_path or str(dc), params.regressor_path or str(dr),
                          s.feature_names(), settings=s, method="lmd", warn=warn)
    except Exception as exc:  # noqa: BLE001 - any load failure refuses the start
        raise RuntimeError(f"cannot load the LMD meta models for proposal_mode "
                           f"'{s.proposal_mode}' ({len(s.feature_names())} features): "
                           f"{exc}") from exc


@dataclass
class LmdFrame:
    """Features of one frame, row ``i`` = box ``i`` of ``detections`` = detection
    ``rows[i]`` of ``source`` (the input detections, or the proposals in exact mode)."""

    detections: DetectionArrays  # the boxes scored, in output order
    messages: list | None        # their Detection3D messages (None for decoded bytes input)
    features: np.ndarray         # (n, F) float64, all-NaN rows for invalid boxes
    valid: np.ndarray            # (n,) bool
    n_points: int                # finite points used (|X|)
    header: object = None        # header of the scored boxes' array (output header)
    source: object = None        # Detection3DArray or DecodedDetections they come from
    rows: np.ndarray | None = None  # (n,) their rows in ``source``
    #: input problems seen while computing the features (``"scores"``, ``"roll_pitch"``,
    #: ``"transform"``)
    issues: dict = field(default_factory=dict)
    #: header of the frame ``detections.boxes`` are in: the cloud's when they were moved
    boxes_header: object = None
    points_in: int = 0           # points of the cloud
    n_padding: int = 0           # of which exact (0, 0, 0) padding (left out, like NaN)


def take_detections(arr: DetectionArrays, idx) -> DetectionArrays:
    """Rows ``idx`` of ``arr`` (in that order)."""
    idx = np.asarray(idx, dtype=np.int64).reshape(-1)
    pick = idx.tolist()
    return DetectionArrays(
        boxes=arr.boxes[idx], scores=arr.scores[idx], labels=[arr.labels[i] for i in pick],
        ids=[arr.ids[i] for i in pick], roll_pitch=arr.roll_pitch[idx], valid=arr.valid[idx],
        reasons=[arr.reasons[i] for i in pick],
        class_scores={c: v[idx] for c, v in arr.class_scores.items()})


def _mark_unknown_classes(arr: DetectionArrays, class_names) -> DetectionArrays:
    """``arr`` with detections of a class outside ``class_names`` made invalid (a copy
    where anything changes: the input's arrays stay as decoded)."""
    known = set(class_names)
    bad = [i for i, lab in enumerate(arr.labels) if arr.valid[i] and lab not in known]
    if not bad:
        return arr
    arr = replace(arr, valid=arr.valid.copy(), reasons=list(arr.reasons))
    for i in bad:
        arr.valid[i] = False
        arr.reasons[i] = f"unknown class {arr.labels[i]!r}"
    return arr


def _unit_range_violations(arr: DetectionArrays) -> np.ndarray:
    """(N,) bool: valid boxes whose score lies outside [0, 1]."""
    with np.errstate(invalid="ignore"):
        return arr.valid & ((arr.scores < 0.0) | (arr.scores > 1.0))


def _mark_out_of_range_scores(arr: DetectionArrays, bad: np.ndarray) -> DetectionArrays:
    """``arr`` with the ``bad`` boxes made invalid, reason "score s outside [0, 1]" (a copy
    where anything changes)."""
    if not bad.any():
        return arr
    arr = replace(arr, valid=arr.valid.copy(), reasons=list(arr.reasons))
    for i in np.flatnonzero(bad).tolist():
        arr.valid[i] = False
        arr.reasons[i] = f"score {arr.scores[i]:.6g} outside [0, 1]"
    return arr


def _score_note(topic: str, arr: DetectionArrays, bad: np.ndarray, effect: str) -> str:
    s = arr.scores[bad]
    return (f"{topic}: {int(bad.sum())} of {len(arr)} boxes score outside [0, 1] "
            f"({s.min():.6g} .. {s.max():.6g}; the meta models take probabilities): {effect}")


def _exact_nms(props: DetectionArrays, settings: LmdSettings):
    """(keep, suppressed_by) over all proposals; invalid ones take no part."""
    return nms_preimages(props.boxes, props.scores, props.valid, settings.nms_iou_threshold,
                         settings.nms_score_threshold)


def _arrays(dets) -> DetectionArrays:
    read = getattr(dets, "arrays", None)  # DecodedDetections, DecodedObjects
    return read if isinstance(read, DetectionArrays) else detections_to_arrays(dets)


def _messages(dets, rows) -> list | None:
    if isinstance(dets, (DecodedDetections, DecodedObjects)):
        return None
    msgs = dets.detections
    return [msgs[i] for i in rows.tolist()]


def _moved(arr: DetectionArrays, t: Transform | None, name: str, notes: list) -> DetectionArrays:
    """``arr`` with its boxes in the cloud's frame (a copy; the input stays as decoded)."""
    if t is None:
        return arr
    boxes, issue = t.apply_boxes(arr.boxes)
    if issue:
        notes.append(f"{name}: {issue}")
    return replace(arr, boxes=boxes)


def _holds_origin(dets: DetectionArrays, props: DetectionArrays | None) -> bool:
    """A detection or proposal box contains (0, 0, 0), where the padding points are."""
    boxes = dets.boxes if props is None else np.concatenate([dets.boxes, props.boxes])
    return bool(count_points_in_boxes(np.zeros((1, 3)), boxes).any())


def frame_features(cloud_msg, detections_msg, proposals_msg, settings: LmdSettings, *,
                   transforms: dict | None = None,
                   intensity: IntensityScale | None = None) -> LmdFrame:
    """Features of one frame from its messages (PointCloud2, Detection3DArray,
    Detection3DArray; the two arrays may also come as ``detection_cdr.DecodedDetections``).
    ``detections_msg`` is unused (may be None) in exact mode, ``proposals_msg`` is None in
    none mode. ``transforms``: ``{"input/detections" | "input/proposals": Transform}`` into
    the cloud's frame, for inputs in another frame (``transforms.input_transforms``).
    ``intensity``: the stream's ``IntensityScale`` (its ``auto`` decision spans frames; None:
    a new one of ``settings.intensity_scale``, deciding on this frame alone); its decision
    note, when made, is in the frame's ``notes`` (logged once, not a warning).

    Raises ``CloudFormatError`` for a malformed cloud or one without intensity,
    ``ValueError`` for a missing input of the mode.
    """
    mode = settings.proposal_mode
    if mode not in MODES:
        raise ValueError(f"proposal_mode must be one of {MODES}, got {mode!r}")
    try:
        xyz, inten = xyz_intensity_view(cloud_msg)
    except CloudFormatError as exc:
        raise CloudFormatError(f"malformed input/points: {exc}") from exc
    if inten is None:
        raise CloudFormatError("input/points has no intensity field (intensity / reflectance / "
                               "i): the reflectance features need it")
    scale = intensity if intensity is not None else IntensityScale(settings.intensity_scale)
    inten = scale.scale(inten)
    # exact (0, 0, 0): an organized cloud's no-return padding, not a point (NaN stays truthy).
    # xyz is mostly a view into the message (no copy of the cloud): padding is then only
    # counted, and blanked in a copy only if a box could hold it (one containing the
    # sensor's origin), so that no box ever counts it
    n_padding, n_finite = padding_counts(xyz, inten)
    if mode != "none" and proposals_msg is None:
        raise ValueError(f'proposal mode "{mode}" needs the proposals')
    transforms = transforms or {}
    scores_notes, tilt_notes, moved_notes = [], [], []
    props = _arrays(proposals_msg) if mode != "none" else None
    if props is not None:
        props = _moved(props, transforms.get("input/proposals"), "input/proposals", moved_notes)
    prop_scores = None if props is None else props.scores
    if props is not None:
        bad = _unit_range_violations(props)
        if bad.any():
            prop_scores = np.where(bad, np.nan, props.scores)  # NaN score: in no set
            props = _mark_out_of_range_scores(props, bad)
            scores_notes.append(_score_note(
                "input/proposals", props, bad, "left out of NMS and of every proposal set"
                if mode == "exact" else "left out of every proposal set"))
        tilt = tilt_issue(props, "proposals")
        if tilt:
            tilt_notes.append(f"input/proposals: {tilt}")
    if mode == "exact":
        keep, sup = _exact_nms(props, settings)
        dets = take_detections(props, keep)
        source, rows = proposals_msg, keep
        kw = dict(preimage=features.ProposalSets.from_nms(sup, keep))
    else:
        if detections_msg is None:
            raise ValueError(f'proposal mode "{mode}" needs the detections')
        dets = _moved(_arrays(detections_msg), transforms.get("input/detections"),
                      "input/detections", moved_notes)
        source, rows = detections_msg, np.arange(len(dets))
        kw = (dict(iou_threshold=settings.iou_threshold,
                   proposal_score_threshold=settings.proposal_score_threshold)
              if mode == "threshold" else {})
        bad = _unit_range_violations(dets)
        if bad.any():
            dets = _mark_out_of_range_scores(dets, bad)
            scores_notes.append(_score_note("input/detections", dets, bad,
                                            "not scored (NaN confidence)"))
        tilt = tilt_issue(dets, "detections")
        if tilt:
            tilt_notes.append(f"input/detections: {tilt}")
    dets = _mark_unknown_classes(dets, settings.class_names)
    extra = None
    if settings.class_score_features:
        nan = np.full(len(dets), np.nan)
        extra = np.column_stack([dets.class_scores.get(c, nan) for c in settings.class_names]
                                ) if len(dets) else np.zeros((0, len(settings.class_names)))
    if n_padding and _holds_origin(dets, props):
        xyz = np.array(xyz)
        blank_padding(xyz, inten)
    X = features.compute_features(
        xyz, inten, dets.boxes, dets.scores, dets.labels,
        proposals=None if props is None else (props.boxes, prop_scores),
        mode=mode, class_names=settings.class_names, class_scores=extra,
        n_usable=n_finite, **kw)
    valid = dets.valid.copy()
    X[~valid] = np.nan
    issues = {}
    if scores_notes:
        issues["scores"] = "; ".join(scores_notes)
    if tilt_notes:
        issues["roll_pitch"] = "; ".join(tilt_notes)
    if moved_notes:
        issues["transform"] = "; ".join(moved_notes)
    moved = ("input/proposals" if mode == "exact" else "input/detections") in transforms
    return LmdFrame(dets, _messages(source, rows), X, valid, n_finite,
                    source.header, source, rows, issues,
                    cloud_msg.header if moved else source.header, len(xyz), n_padding)


@dataclass
class LmdOutputs:
    """What one frame publishes, plus the input problems the node reports."""

    frame: LmdFrame
    confidence: np.ndarray     # (n,) NaN for invalid boxes
    predicted_iou: np.ndarray  # (n,)
    kept: np.ndarray           # (n,) bool: published on output/detections
    detections: object         # Detection3DArray, or serialized bytes for decoded input
    #                            (Detection3DArray; DetectedObjects for Autoware input)
    quality: object            # DetectionQualityArray (every scored box, kept or not)
    markers: object = None     # MarkerArray, or None when not asked for
    #: input problems by key (``"detections"``, ``"frame_id"``, ``"scores"``,
    #: ``"roll_pitch"``, ``"transform"``); absent key = no problem
    issues: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)     # decisions to log once (info)
    values: dict = field(default_factory=dict)    # diagnostics values of this frame
    errors: frozenset = frozenset()               # keys of ``issues`` at level ERROR
    #: Autoware input: objects whose existence_probability is the fallback (else None)
    fallback: int | None = None
    #: detections not published, by "removed.<class>.<range bin>" (thresholds)
    removed: dict = field(default_factory=dict)

    @property
    def messages(self) -> dict:
        out = "output/detections" if self.fallback is None else "output/objects"
        return {out: self.detections, "output/quality": self.quality}

    @property
    def counts(self) -> dict:
        f = self.frame
        return {"points.in": f.points_in, "points.padding": f.n_padding,
                # as LMS: invalid = not used (NaN / inf or padding), of which padding
                "points.invalid": f.points_in - f.n_points,
                "detections.in": len(self.kept), "detections.out": int(self.kept.sum()),
                "detections.invalid": int((~self.frame.valid).sum()),
                **({} if self.fallback is None else {"detections.fallback": self.fallback}),
                **self.removed}


class LmdProcessor:
    """The node's frame work without ROS: decode, features, meta models, output messages.

    ``models``: a ``MetaModels`` loaded with ``settings.feature_names()``.
    ``min_confidence``: detections with a confidence below it (or NaN, when > 0) are not
    published on output/detections; 0 keeps all. ``thresholds``: per-class and per-range
    thresholds besides (``thresholds.ConfidenceThresholds``; its floor is replaced by
    ``min_confidence``, which may change between frames). ``transform_inputs``: move detections and
    proposals in another frame into the cloud's with ``transforms`` (a
    ``transforms.TransformBuffer``, a ``lookup(target, source, stamp_ns)`` callable, or
    None: no transform known, such frames are dropped); false: frames taken as equal.
    ``transforms`` may be replaced between frames (process_bag: one buffer per bag).
    """

    def __init__(self, settings: LmdSettings, models, *, min_confidence: float = 0.0,
                 transforms=None, transform_inputs: bool = True,
                 transform_tolerance: float = 0.05, existence_fallback: float = -1.0,
                 thresholds: ConfidenceThresholds | None = None,
                 drift: DriftParameters | None = None, serialized_quality: bool = False):
        settings.validate()
        if tuple(models.feature_names) != settings.feature_names():
            raise ValueError("models were loaded for another feature schema than the settings'")
        if not 0.0 <= min_confidence <= 1.0:
            raise ValueError(f"min_confidence must be in [0, 1], got {min_confidence}")
        self.settings = settings
        self.models = models
        self.min_confidence = float(min_confidence)
        self.thresholds = thresholds or ConfidenceThresholds()
        #: Autoware output: existence_probability without a confidence (< 0: the detector's)
        self.existence_fallback = float(existence_fallback)
        #: live inputs against the models' training data (``domain_profile``)
        self.domain = DomainCheck(getattr(models, "domain_profile", None), drift)
        #: output/quality as CDR bytes (the node, which only publishes it), not a message
        #: object (``process_bag`` reads its fields)
        self.serialized_quality = bool(serialized_quality)
        self.new_stream()
        self.transforms, self.transform_inputs = transforms, bool(transform_inputs)
        #: for whoever builds the buffer (process_bag: one per bag)
        self.transform_tolerance = float(transform_tolerance)
        from lidar_quality_msgs.msg import DetectionQuality, DetectionQualityArray
        from vision_msgs.msg import Detection3DArray
        self._Quality, self._QualityArray = DetectionQuality, DetectionQualityArray
        self._DetArray = Detection3DArray

    def new_stream(self) -> None:
        """Forget what one input stream taught: the intensity scale decided, the padding
        note, the drift window (``process_bag``: each bag of a batch is a new stream)."""
        self.intensity = IntensityScale(self.settings.intensity_scale)
        self._padding = PaddingNote()
        self.domain.reset()

    def process(self, cloud, detections, proposals, *, markers: bool = False) -> LmdOutputs:
        """One frame (``detections`` None in exact mode, ``proposals`` None in none mode).

        Re-scoring (``detection_cdr.rescaled_scores``): every hypothesis score of a
        detection is scaled so that its top one equals the meta confidence. Decoded
        (``DecodedDetections``) input gives serialized output bytes, every field copied;
        message input is re-scored in place (the node owns its input messages) and
        republished. Raises ``CloudFormatError`` for a bad cloud and ``NoTransformError``
        for inputs in another frame without a transform (the frame is dropped); bad boxes
        never raise.
        """
        moved, frame_notes = {}, []
        if self.transform_inputs:
            t = self.transforms
            moved, frame_notes = input_transforms(
                cloud.header.frame_id, {"input/detections": detections,
                                        "input/proposals": proposals},
                None if t is None else getattr(t, "lookup", t),
                fix=" (publish it on /tf_static or /tf, or set transform_inputs: false to "
                    "compute as if the frames were equal)")
        frame = frame_features(cloud, detections, proposals, self.settings, transforms=moved,
                               intensity=self.intensity)
        conf, iou = self.models.predict(frame.features)
        n = len(frame.detections)
        verdict = self.domain(frame_quantities(frame, self.models.feature_names))
        if verdict.passthrough:     # out of the models' domain: the detector's own score
            conf = np.where(frame.valid, frame.detections.scores, np.nan)
            iou = np.full(n, np.nan)
        kept, removed = replace(self.thresholds, floor=self.min_confidence).keep(
            conf, frame.detections.labels, frame.detections.boxes)
        header = frame.header
        dets = frame.detections
        src = frame.source
        fallback = None
        if isinstance(src, DecodedDetections):
            conf_src = np.full(len(src), np.nan)
            conf_src[frame.rows] = conf
            new = rescaled_scores(src.hyp_score, src.hyp_det, conf_src)
            det_msg = encode_detection_array(src, frame.rows[kept], new)
        elif isinstance(src, DecodedObjects):  # Autoware: bytes in, bytes out
            conf_src = np.full(len(src), np.nan)
            conf_src[frame.rows] = conf
            det_msg, fallback = encode_detected_objects(
                src, frame.rows[kept], conf_src,
                fallback=None if self.existence_fallback < 0 else self.existence_fallback)
        else:
            hyps = [r.hypothesis for m in frame.messages for r in m.results]
            owner = np.repeat(np.arange(n), [len(m.results) for m in frame.messages])
            new = rescaled_scores([h.score for h in hyps], owner, conf)
            for h, v in zip(hyps, new.tolist()):
                h.score = v
            det_msg = self._DetArray(header=header, detections=[
                m for m, k in zip(frame.messages, kept.tolist()) if k])
        quality = self.quality_message(header, dets, conf, iou, verdict)
        mk = self.markers(frame, conf, iou, kept) if markers else None
        issues = dict(frame.issues)
        if not frame.valid.all():
            bad = [f"#{i} {dets.ids[i]!r}: {dets.reasons[i]}"
                   for i in np.flatnonzero(~frame.valid).tolist()]
            issues["detections"] = (f"{len(bad)} invalid detection(s) kept with NaN confidence: "
                                    + ", ".join(bad[:5]) + (" ..." if len(bad) > 5 else ""))
        mismatch = (frame_id_mismatch(cloud, detections, proposals) if not self.transform_inputs
                    else "; ".join(frame_notes))
        if mismatch:
            issues["frame_id"] = mismatch
        if verdict.issue:
            issues["domain_drift"] = verdict.issue
        return LmdOutputs(frame, conf, iou, kept, det_msg, quality, mk, issues,
                          ([self.intensity.note] if self.intensity.note else [])
                          + self._padding(frame.n_padding, frame.points_in),
                          {"intensity_scale": self.intensity.decided, **verdict.values},
                          frozenset({"domain_drift"}) if verdict.error else frozenset(),
                          fallback=fallback, removed=removed)

    def quality_message(self, header, dets, conf, iou, verdict):
        """output/quality: one entry per scored detection (``serialized_quality``: its CDR
        bytes, ``detection_quality_cdr``, the same message)."""
        fields = verdict.message_fields(self._QualityArray)
        if self.serialized_quality:
            return encode_detection_quality_array(
                header, self.models.confidence_model_id, self.models.iou_model_id, dets.ids,
                dets.labels, np.column_stack([dets.scores, conf, iou]), **fields)
        Q = self._Quality
        return self._QualityArray(
            header=header, confidence_model_id=self.models.confidence_model_id,
            iou_model_id=self.models.iou_model_id,
            detections=[Q(detection_index=i, detection_id=dets.ids[i], class_id=dets.labels[i],
                          original_score=s, confidence=c, predicted_iou=u)
                        for i, (s, c, u) in enumerate(zip(dets.scores.tolist(), conf.tolist(),
                                                          iou.tolist()))],
            **fields)

    def markers(self, frame: LmdFrame, conf, iou, kept):
        """Boxes of the published detections coloured by confidence, labelled
        ``"<class> c=0.87 iou=0.62"``."""
        from lidar_quality_ros.markers import box_markers

        idx = np.flatnonzero(kept)
        labels = frame.detections.labels
        texts = [f"{labels[i]} c={conf[i]:.2f} iou={iou[i]:.2f}" for i in idx.tolist()]
        return box_markers(frame.boxes_header or frame.header, frame.detections.boxes[idx],
                           conf[idx], texts, ns="lmd")


def frame_quantities(frame: LmdFrame, feature_names) -> list:
    """What the drift monitor compares with the training profile (``meta_model``'s
    ``training_profile`` as ``lmd-train`` records it): every feature of the valid boxes,
    their detector scores and the frame's points, as ``DriftMonitor.add`` takes matrices.
    (Not the number of boxes: how many objects a frame holds is the scene's, and differs
    between the training sequences themselves.)"""
    v = frame.valid
    return [(tuple(feature_names) + ("detector score",),
             np.column_stack([frame.features[v], frame.detections.scores[v]])),
            (("points per frame",), np.array([[float(frame.n_points)]]))]


def frame_id_mismatch(cloud, detections, proposals) -> str | None:
    """A message when the inputs name different frames (None when they agree)."""
    ids = {"input/points": cloud.header.frame_id}
    if detections is not None:
        ids["input/detections"] = detections.header.frame_id
    if proposals is not None:
        ids["input/proposals"] = proposals.header.frame_id
    if len(set(ids.values())) <= 1:
        return None
    return ("frame_id mismatch (processed as if equal): "
            + ", ".join(f"{t} {f!r}" for t, f in ids.items()))
