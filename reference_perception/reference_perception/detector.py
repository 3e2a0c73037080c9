"""The reference 3D detector: clusters -> fitted boxes -> learned classes, scores and box
refinement -> rotated NMS.

Front end (``proposals``): ground removal, BEV clustering at several cell sizes, four or
five box fits per cluster; every (cluster, fit) is a candidate. Two learned models
(XGBoost, on the candidates' ``FEATURE_NAMES``, run with one thread):

* a classifier giving the class distribution over ``PROB_NAMES`` (column 0 background);
  the score of a candidate is its best foreground probability, its label that class;
* a box refinement regressing the ground-truth box residual in the candidate's frame
  (``TARGET_NAMES``: centre offset along / across the box, dz, size differences, yaw).

Training labels are deliberately looser than the evaluation (documented choice): a
candidate is an object of class c if it mostly consists of that object's points (purity
and coverage >= 0.5) or its fitted box overlaps the object's box with BEV IoU >= 0.3;
evaluation asks for BEV IoU >= 0.5 of the refined box. Sparse, occluded and partially
seen objects are therefore scored like well-localised ones, and the score is
over-confident as a TP probability, as the objectness of real detectors is.

Outputs per frame (``DetectorOutput``): the pre-NMS proposals (candidates scoring at least
``proposal_threshold``) with refined boxes, class distribution, label and score, and the
post-NMS result of a class-agnostic rotated BEV NMS: ``keep`` (proposal index of each
detection, by descending score) and ``suppressed_by`` (per proposal the proposal index of
the survivor that suppressed it, -1 for survivors and for proposals below the detection
score threshold). Several fits and scales per object give each detection a pre-image of
several proposals (``DetectorOutput.preimage``), as LidarMetaDetect needs.

CLI: ``python -m reference_perception.detector train|evaluate``.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lidar_quality_core.iou import iou_bev
from lidar_quality_core.nms import rotated_nms

from .box_fit import wrap_half_pi
from .proposals import FEATURE_NAMES, FrontEndConfig, Proposals, compute_proposals

__all__ = ["FG_CLASS_IDS", "PROB_NAMES", "TARGET_NAMES", "DetectorConfig", "DetectorOutput",
           "ReferenceDetector", "encode_residuals", "decode_residuals", "proposal_targets",
           "collect_training_data", "train_detector", "evaluate_detector", "default_model_dir",
           "main"]


def _things():
    from lidar_sim.classes import THING_CLASS_IDS, class_name
    ids = np.asarray(THING_CLASS_IDS, np.int64)
    return ids, ("background",) + tuple(class_name(int(c)) for c in ids)


# our class ids of probability columns 1.. and the column names:
# ("background", "car", "truck", "pedestrian", "cyclist")
FG_CLASS_IDS, PROB_NAMES = _things()
TARGET_NAMES: tuple[str, ...] = ("dx_along", "dy_across", "dz", "dl", "dw", "dh", "dyaw")
_MIN_SIZE = 0.1
CONFIG_NAME = "detector.json"
CLASSIFIER_NAME = "detector_classifier.ubj"
REGRESSOR_NAME = "detector_box.ubj"

# Training label rule (see module docstring): looser than the evaluation's IoU >= 0.5.
LABEL_MIN_PURITY = 0.5
LABEL_MIN_COVERAGE = 0.5
LABEL_MIN_IOU = 0.3


def default_model_dir() -> Path:
    """The shipped reference models: ``models_dir() / "reference"``."""
    from lidar_quality_core.model_store import models_dir

    return models_dir() / "reference"


@dataclass(frozen=True)
class DetectorConfig:
    """Post-processing parameters (stored in the JSON next to the models)."""

    frontend: FrontEndConfig = field(default_factory=FrontEndConfig)
    proposal_threshold: float = 0.05   # candidates below are not proposals
    score_threshold: float = 0.1       # NMS input threshold (detections)
    nms_iou: float = 0.1               # BEV IoU above which a lower-scored box is suppressed
    max_detections: int = 200

    def to_dict(self) -> dict:
        return {"frontend": self.frontend.to_dict(), "proposal_threshold": self.proposal_threshold,
                "score_threshold": self.score_threshold, "nms_iou": self.nms_iou,
                "max_detections": self.max_detections}

    @classmethod
    def from_dict(cls, d: dict) -> "DetectorConfig":
        return cls(frontend=FrontEndConfig.from_dict(d.get("frontend", {})),
                   **{k: type(getattr(cls(), k))(d[k]) for k in
                      ("proposal_threshold", "score_threshold", "nms_iou", "max_detections")
                      if k in d})


# ------------------------------------------------------------------ box residuals
def _canonical_gt(boxes: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """GT boxes rewritten as the equivalent rectangle (l/w swapped, yaw +-pi/2 or pi)
    whose yaw is nearest to the candidate's (the fit has no heading)."""
    g = np.array(gt, np.float64, copy=True)
    d = wrap_half_pi(g[:, 6] - boxes[:, 6])
    swap = np.abs(d) > np.pi / 4
    g[swap, 3], g[swap, 4] = gt[swap, 4], gt[swap, 3]
    d = np.where(swap, wrap_half_pi(d + np.pi / 2), d)
    g[:, 6] = boxes[:, 6] + d
    return g


def _view_frame(b: np.ndarray):
    """cos, sin of the yaw and the signs making the candidate's local axes point away
    from the sensor: the unseen far side of an object then always lies at positive
    local coordinates, which is what lets a regressor extend an L or I shape."""
    c, s = np.cos(b[:, 6]), np.sin(b[:, 6])
    su = np.where(c * b[:, 0] + s * b[:, 1] >= 0, 1.0, -1.0)
    sv = np.where(c * b[:, 1] - s * b[:, 0] >= 0, 1.0, -1.0)
    return c, s, su, sv


def encode_residuals(boxes: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """(n, 7) residuals ``TARGET_NAMES`` of row-paired GT boxes in the candidates' frames.

    Centre offsets along / across the candidate, its axes oriented away from the sensor;
    size differences (m; not log ratios: a one-line fit has a near-zero width); yaw
    difference in the same (possibly mirrored) frame.
    """
    b = np.asarray(boxes, np.float64)
    g = _canonical_gt(b, np.asarray(gt, np.float64))
    c, s, su, sv = _view_frame(b)
    dx, dy = g[:, 0] - b[:, 0], g[:, 1] - b[:, 1]
    return np.column_stack([su * (c * dx + s * dy), sv * (c * dy - s * dx), g[:, 2] - b[:, 2],
                            g[:, 3] - b[:, 3], g[:, 4] - b[:, 4], g[:, 5] - b[:, 5],
                            su * sv * (g[:, 6] - b[:, 6])])


def decode_residuals(boxes: np.ndarray, deltas: np.ndarray) -> np.ndarray:
    """Inverse of ``encode_residuals``: refined boxes (yaw wrapped to [-pi/2, pi/2))."""
    b = np.asarray(boxes, np.float64)
    d = np.asarray(deltas, np.float64)
    c, s, su, sv = _view_frame(b)
    du, dv = su * d[:, 0], sv * d[:, 1]
    out = np.empty_like(b)
    out[:, 0] = b[:, 0] + c * du - s * dv
    out[:, 1] = b[:, 1] + s * du + c * dv
    out[:, 2] = b[:, 2] + d[:, 2]
    out[:, 3:6] = np.maximum(b[:, 3:6] + d[:, 3:6], _MIN_SIZE)
    out[:, 6] = wrap_half_pi(b[:, 6] + su * sv * d[:, 6])
    return out


# ------------------------------------------------------------------ training labels
@dataclass
class ProposalTargets:
    label: np.ndarray      # (P,) probability column: 0 background, 1.. PROB_NAMES
    gt_index: np.ndarray   # (P,) matched GT row, -1 for background
    purity: np.ndarray     # (P,) share of the cluster's points on its majority object
    coverage: np.ndarray   # (P,) share of that object's points inside the cluster
    iou: np.ndarray        # (P,) best BEV IoU of the fitted box with any GT box
    deltas: np.ndarray     # (P, 7) residuals to gt_index's box (NaN for background)


def proposal_targets(props: Proposals, frame) -> ProposalTargets:
    """Training targets of a frame's candidates from its ground truth (``SimFrame``)."""
    P = len(props)
    cl = props.clusters
    n_gt = len(frame.gt_boxes)
    col_of = {int(c): k + 1 for k, c in enumerate(FG_CLASS_IDS)}
    gt_col = np.array([col_of.get(int(c), 0) for c in frame.gt_class], np.int64)
    # majority object of each cluster, from the points' instance ids
    inst = np.asarray(frame.instance, np.int64)[cl.point_index]
    row_of = {int(k): i for i, k in enumerate(frame.gt_instance)}
    lut = np.full(int(max(inst.max(initial=0), max(row_of, default=0))) + 2, -1, np.int64)
    for k, i in row_of.items():
        lut[k] = i
    gt_row = lut[np.clip(inst, 0, len(lut) - 1)]
    owner = cl.owner
    C = len(cl)
    purity_c = np.zeros(C)
    cover_c = np.zeros(C)
    maj_c = np.full(C, -1, np.int64)
    has = gt_row >= 0
    if has.any() and n_gt:
        key = owner[has] * n_gt + gt_row[has]
        u, cnt = np.unique(key, return_counts=True)
        uc, ug = u // n_gt, u % n_gt
        order = np.lexsort((-cnt, uc))               # per cluster, largest count first
        first = order[np.r_[True, uc[order][1:] != uc[order][:-1]]]
        c_ids, g_ids, counts = uc[first], ug[first], cnt[first]
        maj_c[c_ids] = g_ids
        purity_c[c_ids] = counts / cl.sizes[c_ids]
        cover_c[c_ids] = counts / np.maximum(np.asarray(frame.gt_num_points)[g_ids], 1)
    maj = maj_c[props.cluster]
    purity, coverage = purity_c[props.cluster], cover_c[props.cluster]
    if n_gt and P:
        ious = iou_bev(props.boxes, frame.gt_boxes)
        best = ious.argmax(axis=1)
        iou = ious[np.arange(P), best]
    else:
        best, iou = np.zeros(P, np.int64), np.zeros(P)
    by_points = (maj >= 0) & (purity >= LABEL_MIN_PURITY) & (coverage >= LABEL_MIN_COVERAGE)
    gt_index = np.where(by_points, maj, np.where(iou >= LABEL_MIN_IOU, best, -1))
    label = np.where(gt_index >= 0, gt_col[np.maximum(gt_index, 0)] if n_gt else 0, 0)
    gt_index = np.where(label > 0, gt_index, -1)
    deltas = np.full((P, 7), np.nan)
    fg = gt_index >= 0
    if fg.any():
        deltas[fg] = encode_residuals(props.boxes[fg], frame.gt_boxes[gt_index[fg]])
    return ProposalTargets(label, gt_index, purity, coverage, iou, deltas)


def _cache_key(split: str, sequences, frames, cfg: FrontEndConfig) -> str:
    from lidar_sim.frames import simulator_version
    src = "".join((Path(__file__).parent / n).read_text() for n in
                  ("proposals.py", "clustering.py", "box_fit.py", "ground.py"))
    h = hashlib.sha256(json.dumps([split, sequences, frames, cfg.to_dict(),
                                   simulator_version(), LABEL_MIN_PURITY, LABEL_MIN_COVERAGE,
                                   LABEL_MIN_IOU]).encode() + src.encode())
    return h.hexdigest()[:16]


def collect_training_data(split: str = "reference_train", *, sequences=None, frames=None,
                          cfg: FrontEndConfig = FrontEndConfig(), cache: str | Path | None = None,
                          log=print) -> dict:
    """Candidates, features and targets of every frame of ``split``.

    Returns arrays ``X`` (n, F) float32, ``label``, ``deltas`` (n, 7), ``sequence``,
    ``frame``, ``range``, ``iou``, ``purity``, ``coverage`` (one row per candidate).
    ``cache``: an ``.npz`` path reused when its key (split, front end, simulator and
    front-end source hashes) matches.
    """
    from lidar_sim.frames import split_frames

    key = _cache_key(split, sequences, frames, cfg)
    if cache is not None and Path(cache).is_file():
        with np.load(cache) as z:
            if str(z["key"]) == key:
                log(f"training data: cache {cache} ({len(z['label'])} candidates)")
                return {k: z[k] for k in z.files if k != "key"}
    parts: dict[str, list] = {k: [] for k in ("X", "label", "deltas", "sequence", "frame",
                                              "range", "iou", "purity", "coverage", "boxes",
                                              "gt_boxes")}
    t0 = time.time()
    n_frames = 0
    for f in split_frames(split, sequences=sequences, frames=frames):
        p = compute_proposals(f.xyz, f.intensity, f.ring, cfg)
        t = proposal_targets(p, f)
        n = len(p)
        parts["X"].append(p.features)
        parts["label"].append(t.label)
        parts["deltas"].append(t.deltas.astype(np.float32))
        parts["sequence"].append(np.full(n, f.sequence, np.int32))
        parts["frame"].append(np.full(n, f.index, np.int32))
        parts["range"].append(np.hypot(p.boxes[:, 0], p.boxes[:, 1]).astype(np.float32))
        parts["iou"].append(t.iou.astype(np.float32))
        parts["purity"].append(t.purity.astype(np.float32))
        parts["coverage"].append(t.coverage.astype(np.float32))
        parts["boxes"].append(p.boxes.astype(np.float32))
        gtb = np.full((n, 7), np.nan, np.float32)
        fg = t.gt_index >= 0
        gtb[fg] = f.gt_boxes[t.gt_index[fg]]
        parts["gt_boxes"].append(gtb)
        n_frames += 1
        if n_frames % 30 == 0:
            log(f"  {split}: {n_frames} frames, {sum(map(len, parts['label']))} candidates, "
                f"{time.time() - t0:.0f} s")
    data = {k: np.concatenate(v) for k, v in parts.items()}
    lab = data["label"]
    log(f"training data: {n_frames} frames, {len(lab)} candidates, per class "
        + ", ".join(f"{n}={int((lab == i).sum())}" for i, n in enumerate(PROB_NAMES)))
    if cache is not None:
        Path(cache).parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(str(cache) + ".tmp.npz")
        np.savez(tmp, key=key, **data)
        tmp.replace(cache)
    return data


# ------------------------------------------------------------------ models
def _classifier(seed: int = 0, **kw):
    import xgboost as xgb
    params = dict(n_estimators=80, max_depth=5, learning_rate=0.15, subsample=0.8,
                  colsample_bytree=0.8, min_child_weight=5.0, tree_method="hist",
                  objective="multi:softprob", n_jobs=2, random_state=seed)
    params.update(kw)
    return xgb.XGBClassifier(**params)


def _regressor(seed: int = 0, **kw):
    import xgboost as xgb
    params = dict(n_estimators=60, max_depth=5, learning_rate=0.15, subsample=0.8,
                  colsample_bytree=0.8, min_child_weight=10.0, tree_method="hist",
                  objective="reg:squarederror", n_jobs=2, random_state=seed)
    params.update(kw)
    return xgb.XGBRegressor(**params)


def _reg_rows(data: dict, idx=None) -> np.ndarray:
    """Rows usable for box refinement: foreground with finite residuals."""
    ok = (data["label"] > 0) & np.isfinite(data["deltas"]).all(axis=1)
    # residuals of wildly wrong matches (a fragment matched by IoU only) teach nothing
    ok &= np.hypot(data["deltas"][:, 0], data["deltas"][:, 1]) < 6.0
    rows = np.flatnonzero(ok)
    return rows if idx is None else np.intersect1d(rows, idx)


def _check_classes(y: np.ndarray) -> None:
    missing = [PROB_NAMES[c] for c in range(len(PROB_NAMES)) if not np.any(y == c)]
    if missing:
        raise ValueError(f"training data has no candidate of class(es) {missing}: use more "
                         "sequences / frames")


def train_detector(out_dir: str | Path | None = None, *, split: str = "reference_train",
                   sequences=None, frames=None, cfg: DetectorConfig = DetectorConfig(),
                   cache: str | Path | None = None, log=print) -> dict:
    """Fit the classifier and box refinement on ``split`` and save them to ``out_dir``."""
    from lidar_quality_core.model_store import save_model

    out = Path(out_dir) if out_dir is not None else default_model_dir()
    out.mkdir(parents=True, exist_ok=True)
    data = collect_training_data(split, sequences=sequences, frames=frames, cfg=cfg.frontend,
                                 cache=cache, log=log)
    X, y = data["X"], data["label"]
    _check_classes(y)
    t0 = time.time()
    clf = _classifier()
    clf.fit(X, y)
    log(f"classifier: {len(y)} candidates, {time.time() - t0:.0f} s")
    rows = _reg_rows(data)
    t0 = time.time()
    reg = _regressor()
    reg.fit(X[rows], data["deltas"][rows])
    log(f"box refinement: {len(rows)} foreground candidates, {time.time() - t0:.0f} s")
    training = {"split": split, "sequences": sequences, "frames": frames,
                "n_candidates": int(len(y)), "n_foreground": int((y > 0).sum()),
                "label_rule": {"min_purity": LABEL_MIN_PURITY, "min_coverage": LABEL_MIN_COVERAGE,
                               "min_bev_iou": LABEL_MIN_IOU}}
    save_model(clf, out / CLASSIFIER_NAME, feature_names=FEATURE_NAMES, task="multiclass",
               class_names=PROB_NAMES, training_data=training)
    save_model(reg, out / REGRESSOR_NAME, feature_names=FEATURE_NAMES, task="regression",
               target_names=TARGET_NAMES, training_data=training)
    (out / CONFIG_NAME).write_text(json.dumps(
        {**cfg.to_dict(), "classifier": CLASSIFIER_NAME, "box_regressor": REGRESSOR_NAME,
         "prob_names": list(PROB_NAMES), "class_ids": FG_CLASS_IDS.tolist(),
         "training": training}, indent=2) + "\n")
    log(f"saved to {out}")
    return training


# ------------------------------------------------------------------ inference
@dataclass
class DetectorOutput:
    """One frame's proposals (P) and post-NMS detections (indices into the proposals)."""

    boxes: np.ndarray          # (P, 7) refined boxes x, y, z, l, w, h, yaw
    class_probs: np.ndarray    # (P, 1 + 4): background, car, truck, pedestrian, cyclist
    labels: np.ndarray         # (P,) our class ids (best foreground class)
    scores: np.ndarray         # (P,) probability of that class
    keep: np.ndarray           # (K,) proposal index of each detection, descending score
    suppressed_by: np.ndarray  # (P,) suppressing survivor's proposal index, -1 otherwise
    fitted_boxes: np.ndarray   # (P, 7) the box fits before refinement
    candidate: np.ndarray      # (P,) index of the front-end candidate
    cluster: np.ndarray        # (P,) front-end cluster of the candidate
    timings_ms: dict = field(default_factory=dict)

    @property
    def det_boxes(self) -> np.ndarray:
        return self.boxes[self.keep]

    @property
    def det_scores(self) -> np.ndarray:
        return self.scores[self.keep]

    @property
    def det_labels(self) -> np.ndarray:
        return self.labels[self.keep]

    def preimage(self, proposal: int) -> np.ndarray:
        """Proposal indices a survivor stands for: itself and what it suppressed."""
        return np.r_[proposal, np.flatnonzero(self.suppressed_by == proposal)].astype(np.int64)


def _score_label(probs: np.ndarray):
    fg = probs[:, 1:]
    k = np.argmax(fg, axis=1) if len(fg) else np.zeros(0, np.int64)
    return FG_CLASS_IDS[k], fg[np.arange(len(fg)), k]


def run_nms(boxes, scores, cfg: DetectorConfig):
    """Class-agnostic rotated BEV NMS: ``(keep, suppressed_by)`` with -1 for survivors."""
    res = rotated_nms(boxes, scores, cfg.nms_iou, score_threshold=cfg.score_threshold,
                      max_output=cfg.max_detections)
    sup = res.suppressed_by.copy()
    sup[res.keep] = -1
    return res.keep, sup


def _threads_one(model) -> None:
    """One thread per model: the per-frame batches are small, and the budget is one core."""
    est = model.estimator
    if hasattr(est, "set_params"):
        est.set_params(n_jobs=1)


def _read_config(model_dir: Path, name: str) -> dict:
    path = model_dir / name
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no trained model configuration (train with "
                                f"python -m reference_perception.{name.split('.')[0]} train)")
    return json.loads(path.read_text())


class ReferenceDetector:
    """Load the trained models of ``model_dir`` and detect objects in clouds."""

    def __init__(self, model_dir: str | Path | None = None, **overrides):
        from lidar_quality_core.model_store import load_model

        self.model_dir = Path(model_dir) if model_dir is not None else default_model_dir()
        raw = _read_config(self.model_dir, CONFIG_NAME)
        raw.update(overrides)
        self.config = DetectorConfig.from_dict(raw)
        self.classifier = load_model(self.model_dir / raw["classifier"],
                                     expected_features=FEATURE_NAMES, expected_task="multiclass")
        self.regressor = load_model(self.model_dir / raw["box_regressor"],
                                    expected_features=FEATURE_NAMES, expected_task="regression")
        if tuple(self.classifier.class_names) != PROB_NAMES:
            raise ValueError(f"{self.classifier.path}: classes {self.classifier.class_names} "
                             f"are not {PROB_NAMES}")
        for m in (self.classifier, self.regressor):
            _threads_one(m)

    def proposals(self, xyz, intensity, ring=None) -> Proposals:
        """The front end alone (shared with the multi-head detector)."""
        return compute_proposals(xyz, intensity, ring, self.config.frontend)

    def detect(self, xyz, intensity, ring=None) -> DetectorOutput:
        """Detect objects in one cloud (sensor frame, z up)."""
        return self.detect_proposals(self.proposals(xyz, intensity, ring))

    def detect_proposals(self, props: Proposals) -> DetectorOutput:
        """Score, refine and suppress the candidates of a front-end result."""
        t0 = time.perf_counter()
        cfg = self.config
        probs = self.classifier.predict_proba(props.features)
        labels, scores = _score_label(probs)
        sel = np.flatnonzero(scores >= cfg.proposal_threshold)
        deltas = self.regressor.predict_value(props.features[sel])
        boxes = decode_residuals(props.boxes[sel], deltas)
        t1 = time.perf_counter()
        keep, sup = run_nms(boxes, scores[sel], cfg)
        t2 = time.perf_counter()
        timings = dict(props.timings_ms, models=(t1 - t0) * 1e3, nms=(t2 - t1) * 1e3)
        return DetectorOutput(boxes=boxes, class_probs=probs[sel], labels=labels[sel],
                              scores=scores[sel], keep=keep, suppressed_by=sup,
                              fitted_boxes=props.boxes[sel], candidate=sel,
                              cluster=props.cluster[sel], timings_ms=timings)


# ------------------------------------------------------------------ evaluation
EVAL_MIN_POINTS = 5        # GT boxes with fewer lidar points are ignored (nuScenes / Waymo style)


def gt_ignore_mask(frame, max_range: float, min_points: int = EVAL_MIN_POINTS) -> np.ndarray:
    """GT boxes left out of the evaluation: too few points or beyond the clustering range."""
    r = np.hypot(frame.gt_boxes[:, 0], frame.gt_boxes[:, 1])
    return (np.asarray(frame.gt_num_points) < min_points) | (r > max_range)


def class_names_of(ids) -> list[str]:
    from lidar_sim.classes import class_name
    return [class_name(int(c)) for c in ids]


def evaluate_outputs(records, *, iou: float = 0.5, log=print) -> dict:
    """AP (BEV and 3D, R40), score ECE and counts from ``(output boxes, scores, labels,
    frame, ignore)`` records; prints a report. Returns the numbers."""
    from lidar_quality_core.detection_eval import evaluate
    from lidar_quality_core.metrics import ece

    names = list(PROB_NAMES[1:])
    res = {}
    for mode in ("bev", "3d"):
        frames = [dict(det_boxes=b, det_scores=s, det_labels=class_names_of(l),
                       gt_boxes=f.gt_boxes, gt_labels=class_names_of(f.gt_class), gt_ignore=ign)
                  for b, s, l, f, ign in records]
        res[mode] = evaluate(frames, names, iou, mode=mode)
    matches = res["bev"]["matches"]
    sc = np.concatenate([m.scores[~m.ignored] for m in matches]) if matches else np.zeros(0)
    tp = np.concatenate([m.tp[~m.ignored] for m in matches]) if matches else np.zeros(0, bool)
    out = {"ece": ece(tp, np.clip(sc, 0, 1)) if len(sc) else float("nan"),
           "n_det": int(len(sc)), "n_tp": int(tp.sum()),
           "mean_score": float(sc.mean()) if len(sc) else float("nan"),
           "precision": float(tp.mean()) if len(sc) else float("nan")}
    log(f"{'class':12s} {'n_gt':>6s} {'n_det':>6s} {'n_tp':>6s} {'AP_bev@%.1f' % iou:>11s} "
        f"{'AP_3d@%.1f' % iou:>10s}")
    for c in names:
        b, t = res["bev"]["per_class"][c], res["3d"]["per_class"][c]
        out[f"ap_bev_{c}"], out[f"ap_3d_{c}"] = b["ap"], t["ap"]
        log(f"{c:12s} {b['n_gt']:6d} {b['n_det']:6d} {b['n_tp']:6d} {b['ap']:11.3f} "
            f"{t['ap']:10.3f}")
    out["map_bev"], out["map_3d"] = res["bev"]["map"], res["3d"]["map"]
    log(f"{'mAP':12s} {'':6s} {'':6s} {'':6s} {out['map_bev']:11.3f} {out['map_3d']:10.3f}")
    log(f"score as P(TP, BEV IoU >= {iou} same class): ECE {out['ece']:.3f}, mean score "
        f"{out['mean_score']:.3f} vs precision {out['precision']:.3f} over {out['n_det']} "
        f"detections")
    return out


def evaluate_detector(model_dir=None, *, split: str = "reference_test", sequences=None,
                      frames=None, max_frames: int | None = None, log=print) -> dict:
    """Run the detector on ``split`` and print AP per class, score ECE, counts, timing."""
    from lidar_sim.frames import split_frames

    det = ReferenceDetector(model_dir)
    records, n_props, n_pre, times = [], [], [], []
    for i, f in enumerate(split_frames(split, sequences=sequences, frames=frames)):
        if max_frames is not None and i >= max_frames:
            break
        t0 = time.perf_counter()
        o = det.detect(f.xyz, f.intensity, f.ring)
        times.append((time.perf_counter() - t0) * 1e3)
        records.append((o.det_boxes, o.det_scores, o.det_labels, f,
                        gt_ignore_mask(f, det.config.frontend.cluster.max_range)))
        n_props.append(len(o.scores))
        n_pre.extend(len(o.preimage(k)) for k in o.keep)
    log(f"{split}: {len(records)} frames, GT ignored if < {EVAL_MIN_POINTS} points or beyond "
        f"{det.config.frontend.cluster.max_range:.0f} m")
    res = evaluate_outputs(records, log=log)
    pre = np.asarray(n_pre)
    res.update(proposals_per_frame=float(np.mean(n_props)),
               detections_per_frame=float(len(pre) / max(len(records), 1)),
               preimage_median=float(np.median(pre)) if len(pre) else float("nan"),
               ms_median=float(np.median(times)))
    log(f"proposals / frame {res['proposals_per_frame']:.0f}, detections / frame "
        f"{res['detections_per_frame']:.1f}, proposals per detection (NMS pre-image incl. "
        f"itself): median {res['preimage_median']:.0f}, mean {pre.mean():.1f}, "
        f"p90 {np.percentile(pre, 90):.0f}" if len(pre) else "no detections")
    log(f"time per frame (this machine, shared cores): median {res['ms_median']:.0f} ms")
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m reference_perception.detector",
                                 description="Train or evaluate the reference detector.")
    sub = ap.add_subparsers(dest="cmd", required=True)
    tr = sub.add_parser("train", help="fit on reference_train, save to the model dir")
    tr.add_argument("--out", default=None, help="model directory (default models/reference)")
    tr.add_argument("--split", default="reference_train")
    tr.add_argument("--sequences", type=int, nargs="*", default=None)
    tr.add_argument("--cache", default=None, help="npz cache of the training candidates")
    ev = sub.add_parser("evaluate", help="AP, ECE and counts on reference_test")
    ev.add_argument("--models", default=None, help="model directory (default models/reference)")
    ev.add_argument("--split", default="reference_test")
    ev.add_argument("--sequences", type=int, nargs="*", default=None)
    ev.add_argument("--max-frames", type=int, default=None)
    args = ap.parse_args(argv)
    def log(*a):
        print(*a, flush=True)
    if args.cmd == "train":
        train_detector(args.out, split=args.split, sequences=args.sequences, cache=args.cache,
                       log=log)
    else:
        evaluate_detector(args.models, split=args.split, sequences=args.sequences,
                          max_frames=args.max_frames, log=log)
    return 0


if __name__ == "__main__":
    sys.exit(main())
