"""``mimo-eval``: the LiDAR-MIMO evaluation (paper IV.C / IV.D) on held-out perception bags.

    mimo-eval --data data/perception/meta_test --models models/mimo --out out/mimo_eval \\
        --docs docs --model-card models/mimo/MODEL_CARD.md

Compared: (1) ``single``: head 0 alone (its class distribution, box and predicted
variance); (2) ``merged``: the K heads clustered and merged (merged distribution, mean box,
predictive variance); (3) ``meta``: merged, score replaced by the meta confidence of
``models/mimo/mimo_*`` (and (4) ``meta_points`` with ``mimo_points_*`` when present). The
class distribution of (3) / (4) puts the confidence on the merged label and shares the
rest among the other columns (background included) in the merged proportions
(:func:`meta_distribution`); boxes and variances are the merged ones.

Protocol:

* Ground truth with fewer than 5 points or beyond 80 m is ignored (``dataset.gt_ignore``,
  the reference detector's rule): detections matching only such boxes are left out.
* TP / FP_ML / FP_BG (``detection_eval.match_frame`` + ``fp_partition``): class-aware
  greedy one-to-one matching by each method's own score at **BEV IoU >= 0.5 for every
  class** (the meta models' target, the project's detector evaluation); FP_BG: BEV IoU
  <= 0.1 with every ground-truth box. The paper matches in 3D at KITTI's per-class
  thresholds and averages its uncertainty metrics over IoU thresholds 0.5 .. 0.95; we also
  give mAP at KITTI's thresholds (car, truck 0.7; pedestrian, cyclist 0.5) in BEV and 3D.
* mAP: R40 (``detection_eval.average_precision``) over all frames, each method's score.
* Uncertainty metrics follow the paper's recal / eval split: the sequences are sorted,
  every other one (0, 2, ..) is the recalibration half, the others the evaluation half
  (a single sequence: its first / second half of frames). On the recalibration half, per
  class, F1-optimal score thresholds and a temperature (``calibration.Recalibration``, the
  authors' threshold / temperature / threshold sequence); on the evaluation half the
  temperatures are applied and detections below their class's threshold dropped, then:
  classification NLL and Brier score per partition (targets, as the authors' code: a TP
  its class, every FP, FP_ML included, the background: a detection that is not a TP should
  not have been output; this is also what the meta confidence P(TP) estimates), regression
  NLL and energy score for TP and FP_ML (against the matched / most overlapped ground-truth
  box), the marginal calibration
  error (all partitions) and the regression calibration error (TP), plus the ECE of the
  score as P(TP) (10 bins). The same metrics without recalibration are reported too.
* The reference detector has no heading (``box_fit``: l >= w, yaw modulo pi; it learns its
  boxes and variances against the ground-truth rectangle written in the parametrization
  nearest to each candidate, ``reference_perception.detector._canonical_gt``). The
  regression metrics therefore compare with that same equivalent rectangle (l / w swapped
  with yaw +- pi/2, or yaw + pi, whichever is nearest to the prediction); with the raw
  ground truth ~half of all TPs would be heading flips scored at ~1 / var_yaw.
  ``heading_aware=True`` (``--heading-aware``) uses the raw ground truth, for detectors that
  predict a heading.
* Meta model quality on all merged test detections: AUROC / AUPRC / ECE / Brier of the
  confidence against the meta target (BEV IoU >= 0.5 with a GT box of the class, ignored
  boxes included), R^2 / MAE of the predicted IoU; the merged score for comparison.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidar_quality_core import meta_model
from lidar_quality_core import metrics as qm
from lidar_quality_core import report_plots as rp
from lidar_quality_core.jsonable import jsonable
from lidar_quality_core.detection_eval import (KITTI_IOU_THRESHOLDS, Partition, fp_partition,
                                               match_frame, summarize)

from lidar_quality_core.mimo import scoring_rules as sr
from lidar_quality_core.mimo.calibration import Recalibration
from .dataset import TP_IOU, MimoDataset, load_bags
from ..report import fmt, markdown_table, update_card
from .train import PREFIXES, add_data_arguments, heldout_section

__all__ = ["METHODS", "KITTI_THRESHOLDS", "Detections", "meta_distribution",
           "method_detections", "annotate", "split_groups", "regression_gt", "uncertainty_metrics",
           "evaluate_method", "evaluate", "write_report", "qualitative_png", "main"]

METHODS = {"single": "single head (head 0)", "merged": "merged heads",
           "meta": "merged heads + meta model", "meta_points": "merged heads + meta (points)"}
KITTI_THRESHOLDS = {**KITTI_IOU_THRESHOLDS, "truck": 0.7}
QUALITY_LABELS = {"merged": "merged score (no model)", "meta": "meta model (cluster statistics)",
                  "meta_points": "meta model (+ point features)"}
PARTS = (("TP", Partition.TP), ("FP_ML", Partition.FP_ML), ("FP_BG", Partition.FP_BG))


@dataclass
class Detections:
    """One method's detections of a dataset's frames."""

    frame: np.ndarray   # (n,) frame row
    box: np.ndarray     # (n, 7)
    probs: np.ndarray   # (n, 1 + C) class distribution, column 0 background
    label: np.ndarray   # (n,) class column (1..C)
    score: np.ndarray   # (n,) ranking score (probability of the label)
    var: np.ndarray     # (n, 7) predicted variance of the box parameters
    iou: np.ndarray     # (n,) BEV IoU with the best GT box of its class (meta target)
    predicted_iou: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.score)


def meta_distribution(probs, label, conf) -> np.ndarray:
    """Class distributions with probability ``conf`` on column ``label`` and the remaining
    1 - conf shared among the other columns in proportion to ``probs`` (all of it to the
    background column 0 when they hold nothing)."""
    p = np.asarray(probs, np.float64)
    n = np.arange(len(p))
    conf = np.asarray(conf, np.float64)
    rest = 1.0 - p[n, label]
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(rest > 1e-12, (1.0 - conf) / rest, 0.0)
    out = p * scale[:, None]
    out[n, label] = conf
    empty = rest <= 1e-12
    out[empty, 0] = 1.0 - conf[empty]
    return out


def method_detections(ds: MimoDataset, models: dict) -> dict[str, Detections]:
    """``{method: Detections}``; ``models``: ``{use_points: MetaModels}``."""
    out = {"single": Detections(ds.s_frame, ds.s_box, ds.s_probs, ds.s_label, ds.s_score,
                                ds.s_var, ds.s_iou_class),
           "merged": Detections(ds.m_frame, ds.m_box, ds.m_probs, ds.m_label, ds.m_score,
                                ds.m_var, ds.m_iou_class)}
    for use_points, mm in models.items():
        X, _ = ds.features(use_points)
        conf, piou = mm.predict(X)
        conf = np.nan_to_num(conf, nan=0.0)
        name = "meta_points" if use_points else "meta"
        out[name] = Detections(ds.m_frame, ds.m_box, meta_distribution(ds.m_probs, ds.m_label,
                                                                       conf),
                               ds.m_label, conf, ds.m_var, ds.m_iou_class, piou)
    return out


@dataclass
class Annotation:
    """Per-detection evaluation labels of one method (``annotate``)."""

    matches: list          # FrameMatch per frame
    part: np.ndarray       # (n,) Partition code
    tp: np.ndarray         # (n,) bool
    target: np.ndarray     # (n,) class column of the scoring rules (0 = background)
    gt_row: np.ndarray     # (n,) GT row for the regression metrics (-1: none)


def _frame_order(frame: np.ndarray, n_frames: int):
    order = np.argsort(frame, kind="stable")
    return order, np.searchsorted(frame[order], np.arange(n_frames + 1))


def annotate(ds: MimoDataset, det: Detections, gt_ignore: np.ndarray, *, iou_threshold=TP_IOU,
             mode: str = "bev") -> Annotation:
    """Match every frame (``match_frame``) and label each detection (module docstring)."""
    names = np.asarray(ds.class_names, dtype=object)
    n = len(det)
    part = np.full(n, Partition.IGNORED, np.int8)
    target = np.zeros(n, np.intp)
    gt_row = np.full(n, -1, np.int64)
    order, bounds = _frame_order(det.frame, ds.n_frames)
    matches = []
    for k in range(ds.n_frames):
        rows = order[bounds[k]:bounds[k + 1]]
        gb, gl, _, _ = ds.gt_of(k)
        a = ds.gt_offsets[k]
        ign = gt_ignore[a:ds.gt_offsets[k + 1]]
        fm = match_frame(det.box[rows], det.score[rows], names[det.label[rows] - 1], gb,
                         list(gl), iou_threshold=iou_threshold, mode=mode, gt_ignore=ign)
        matches.append(fm)
        code = fp_partition(fm)
        part[rows] = code
        tp = code == Partition.TP
        ml = code == Partition.FP_ML
        target[rows[tp]] = det.label[rows[tp]]
        gt_row[rows[tp]] = a + fm.det_gt[tp]
        gt_row[rows[ml]] = a + fm.gt_any[ml]
    return Annotation(matches, part, part == Partition.TP, target, gt_row)


def split_groups(ds: MimoDataset) -> tuple[np.ndarray, np.ndarray]:
    """(recalibration frames, evaluation frames): alternate sorted sequences; a single
    sequence is split into its first and second half of frames."""
    groups = sorted(ds.groups)
    if len(groups) >= 2:
        return ds.frames_of_groups(groups[0::2]), ds.frames_of_groups(groups[1::2])
    k = ds.n_frames // 2
    return np.arange(k), np.arange(k, ds.n_frames)


def regression_gt(det_box: np.ndarray, gt_box: np.ndarray, heading_aware: bool = False):
    """Ground-truth boxes for the regression metrics of row-paired predictions (module
    docstring): the equivalent rectangle nearest to each prediction, or the raw boxes."""
    if heading_aware or not len(gt_box):
        return gt_box
    from reference_perception.detector import _canonical_gt

    return _canonical_gt(det_box, gt_box)


def uncertainty_metrics(ds: MimoDataset, det: Detections, ann: Annotation, rows: np.ndarray,
                        probs: np.ndarray, *, es_samples: int = 1000, seed: int = 0,
                        heading_aware: bool = False) -> dict:
    """Scoring rules and calibration errors of detections ``rows`` (not ignored) with
    class distributions ``probs`` (one per row)."""
    part, target = ann.part[rows], ann.target[rows]
    nll = sr.classification_nll(probs, target)
    brier = sr.brier_score(probs, target)
    out: dict = {"n": int(len(rows))}
    for name, code in PARTS:
        m = part == code
        out[f"count_{name}"] = int(m.sum())
        out[f"nll_cls_{name}"] = float(nll[m].mean()) if m.any() else float("nan")
        out[f"brier_{name}"] = float(brier[m].mean()) if m.any() else float("nan")
    for name, code in PARTS[:2]:
        m = part == code
        r = rows[m]
        if len(r):
            gt = regression_gt(det.box[r], ds.gt_box[ann.gt_row[r]], heading_aware)
            out[f"nll_reg_{name}"] = float(sr.regression_nll(det.box[r], det.var[r], gt).mean())
            out[f"energy_{name}"] = float(sr.energy_score(det.box[r], det.var[r], gt,
                                                          n_samples=es_samples,
                                                          seed=seed).mean())
        else:
            out[f"nll_reg_{name}"] = out[f"energy_{name}"] = float("nan")
    out["mce_cls"] = sr.marginal_calibration_error(probs, target)
    tp_rows = rows[part == Partition.TP]
    ce = sr.regression_calibration_error(det.box[tp_rows], det.var[tp_rows],
                                         regression_gt(det.box[tp_rows],
                                                       ds.gt_box[ann.gt_row[tp_rows]],
                                                       heading_aware))
    out["ce_reg"] = ce["mean"]
    out["ce_reg_per_parameter"] = ce["per_parameter"].tolist()
    score = probs[np.arange(len(rows)), det.label[rows]] if len(rows) else np.zeros(0)
    tp = (part == Partition.TP).astype(float)
    out["score_ece"] = qm.ece(tp, np.clip(score, 0, 1)) if len(rows) else float("nan")
    return out


def _n_gt(ds: MimoDataset, frames, gt_ignore) -> dict:
    rows = (np.concatenate([np.arange(ds.gt_offsets[k], ds.gt_offsets[k + 1]) for k in frames])
            if len(frames) else np.zeros(0, np.int64))
    rows = rows[~gt_ignore[rows]]
    lab = ds.gt_label[rows]
    return {c: int((lab == c).sum()) for c in ds.class_names}


def evaluate_method(ds: MimoDataset, det: Detections, gt_ignore, recal_frames, eval_frames, *,
                    es_samples: int = 1000, seed: int = 0, heading_aware: bool = False) -> dict:
    """mAP, partition counts, recalibration and uncertainty metrics of one method."""
    names = list(ds.class_names)
    ann = annotate(ds, det, gt_ignore)
    res: dict = {"n": int(len(det))}
    s = summarize(ann.matches, names)
    res["map_bev50"] = s["map"]
    res["ap_bev50"] = {c: s["per_class"][c]["ap"] for c in names}
    for mode in ("bev", "3d"):
        k = summarize(annotate(ds, det, gt_ignore, iou_threshold=KITTI_THRESHOLDS,
                               mode=mode).matches, names)
        res[f"map_kitti_{mode}"] = k["map"]
    res["counts"] = {name: int((ann.part == code).sum()) for name, code in PARTS}
    res["counts"]["ignored"] = int((ann.part == Partition.IGNORED).sum())

    in_recal = np.flatnonzero(np.isin(det.frame, recal_frames) & (ann.part != Partition.IGNORED))
    ev = np.flatnonzero(np.isin(det.frame, eval_frames) & (ann.part != Partition.IGNORED))
    rc = Recalibration.fit(names, det.label[in_recal], ann.tp[in_recal],
                           _n_gt(ds, recal_frames, gt_ignore), det.probs[in_recal],
                           ann.target[in_recal])
    res["recalibration"] = rc.as_dict()
    kw = dict(es_samples=es_samples, seed=seed, heading_aware=heading_aware)
    res["raw"] = uncertainty_metrics(ds, det, ann, ev, det.probs[ev], **kw)
    keep, cal = rc.apply(det.label[ev], det.probs[ev])
    res["recalibrated"] = uncertainty_metrics(ds, det, ann, ev[keep], cal, **kw)
    res["_annotation"] = ann
    res["_eval_rows"] = ev
    return res


def meta_quality(det: Detections, target_tp: np.ndarray) -> dict:
    """Confidence and predicted-IoU quality against the meta targets."""
    y = target_tp.astype(float)
    c = np.clip(det.score, 0, 1)
    out = {"auroc": qm.auroc(y, c), "auprc": qm.auprc(y, c), "ece": qm.ece(y, c),
           "brier": qm.brier(y, c)}
    pred = det.predicted_iou if det.predicted_iou is not None else det.score
    out["iou_r2"] = qm.r2(det.iou, pred)
    out["iou_mae"] = qm.mae(det.iou, pred)
    return out


def evaluate(ds: MimoDataset, models: dict, *, es_samples: int = 1000, seed: int = 0,
             heading_aware: bool = False, progress: bool = True) -> dict:
    """All methods on ``ds`` (see module docstring); returns the results (JSON-able keys
    plus ``_``-prefixed working arrays)."""
    gt_ignore = ds.gt_ignore()
    recal, ev = split_groups(ds)
    dets = method_detections(ds, models)
    res = {"data": ds.summary(), "recal_groups": sorted(set(ds.frame_group[recal].tolist())),
           "eval_groups": sorted(set(ds.frame_group[ev].tolist())),
           "recal_frames": int(len(recal)), "eval_frames": int(len(ev)),
           "heading_aware": bool(heading_aware), "methods": {}}
    for name, det in dets.items():
        t0 = time.monotonic()
        res["methods"][name] = evaluate_method(ds, det, gt_ignore, recal, ev,
                                               es_samples=es_samples, seed=seed,
                                               heading_aware=heading_aware)
        if progress:
            sys.stderr.write(f"mimo-eval: {METHODS[name]} done ({time.monotonic() - t0:.1f} s)\n")
    tp = ds.tp
    res["meta_quality"] = {name: meta_quality(dets[name], tp)
                           for name in ("merged", "meta", "meta_points") if name in dets}
    res["_detections"] = dets
    res["acceptance"] = acceptance(res)
    return res


def acceptance(res: dict) -> dict:
    """Issue 7: merged heads + meta model better calibrated than a single head (after the
    paper's recalibration): marginal calibration error and score ECE both lower."""
    m = res["methods"]
    if "meta" not in m:
        return {"checked": False}
    a, b = m["meta"]["recalibrated"], m["single"]["recalibrated"]
    out = {"checked": True, "mce_cls_meta": a["mce_cls"], "mce_cls_single": b["mce_cls"],
           "score_ece_meta": a["score_ece"], "score_ece_single": b["score_ece"]}
    out["better_calibrated"] = bool(a["mce_cls"] < b["mce_cls"] and a["score_ece"] < b["score_ece"])
    return out


# ------------------------------------------------------------------ figures
def qualitative_png(path, ds: MimoDataset, frame: int, models: dict, *, max_range: float = 45.0,
                    topics: dict | None = None):
    """The paper's figure 4 for one frame: BEV overview (points, ground truth, merged boxes
    coloured by meta confidence) and two zoomed true positives (near, far) with their head
    members, the merged box, its 95 % length / width interval and the statistics."""
    import matplotlib

    from lidar_quality_core.pointcloud import finite_mask, xyz_intensity
    from lidar_quality_core.report_plots import draw_bev_box
    from lidar_quality_ros.perception_bag import head_count, perception_frames

    from .dataset import settings_for
    from mimo_ros.pipeline import STAT_FEATURES, frame_features

    bag = ds.frame_source[frame]
    stamp = int(ds.frame_stamp[frame])
    k_heads = head_count(bag, topics)
    f = next(f for f in perception_frames(bag, want=("points", "gt_objects"), heads=k_heads,
                                          topics=topics) if f.stamp_ns == stamp)
    settings = settings_for(k_heads)
    fr = frame_features(f.heads, f.head_variances, settings, f.points)
    m = fr.merge
    mm = models.get(False)
    conf, piou = (mm.predict(fr.features[:, :len(STAT_FEATURES)]) if mm
                  else (m.scores, np.full(len(m), np.nan)))
    gb, gl, _, gpts = ds.gt_of(frame)
    ign = ds.gt_ignore()[ds.gt_offsets[frame]:ds.gt_offsets[frame + 1]]
    names = np.asarray(ds.class_names, dtype=object)
    fm = match_frame(m.boxes, conf, names[m.labels - 1], gb, list(gl), iou_threshold=TP_IOU,
                     gt_ignore=ign)
    xyz, _ = xyz_intensity(f.points)
    xyz = xyz[finite_mask(xyz)]
    near_pts = (np.abs(xyz[:, 0]) < max_range) & (np.abs(xyz[:, 1]) < max_range)
    rng = np.random.default_rng(0)
    show = np.flatnonzero(near_pts)
    show = show[rng.permutation(len(show))[:40000]]

    fig = rp.figure(13.0, 10.0)
    gs = fig.add_gridspec(2, 4, width_ratios=[1.3, 0.7, 1.3, 0.7], height_ratios=[1.15, 1])
    ax = fig.add_subplot(gs[0, :])
    ax.scatter(xyz[show, 0], xyz[show, 1], s=0.2, c="0.65", linewidths=0)
    for b, ig in zip(gb, ign):
        draw_bev_box(ax, b, color="tab:green", lw=0.9, ls=":" if ig else "-")
    cmap = matplotlib.colormaps["RdYlGn"]
    for i in range(len(m)):
        draw_bev_box(ax, m.boxes[i], color=cmap(float(np.clip(conf[i], 0, 1))), lw=1.6)
    sm = matplotlib.cm.ScalarMappable(cmap=cmap, norm=matplotlib.colors.Normalize(0, 1))
    fig.colorbar(sm, ax=ax, fraction=0.03, pad=0.01, shrink=0.6, label="meta confidence")
    # the scene's lateral extent (streets are long and narrow), within +-max_range
    y_lo, y_hi = (np.percentile(xyz[near_pts, 1], [0.5, 99.5]) if near_pts.any()
                  else (-max_range, max_range))
    ax.set_xlim(-max_range, max_range)
    ax.set_ylim(max(y_lo - 3, -max_range), min(y_hi + 3, max_range))
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"{Path(bag).parent.name}/{Path(bag).name}, stamp {stamp}: {len(m)} merged "
                 "detections\n(colour: meta confidence; ground truth green, dotted: ignored)",
                 fontsize=9)
    # the near and the far true positive with the most members
    dist = np.hypot(m.boxes[:, 0], m.boxes[:, 1])
    tps = np.flatnonzero(fm.tp & (dist < max_range))
    picks = []
    if len(tps):
        picks.append(int(tps[np.argmin(dist[tps])]))
        far = tps[dist[tps] > np.median(dist[tps])] if len(tps) > 1 else tps[:0]
        if len(far):
            picks.append(int(far[np.argmax(m.stats.epistemic_total_variance[far])]))
    head_colors = ["tab:orange", "tab:purple", "tab:brown", "tab:pink"]
    st = m.stats
    info = []
    for j, i in enumerate(picks):
        axz = fig.add_subplot(gs[1, 2 * j])
        b = m.boxes[i]
        heads, idx = m.members(i)
        for h, r in zip(heads.tolist(), idx.tolist()):
            hb = fr.arrays[h].boxes[r]
            draw_bev_box(axz, hb, color=head_colors[fr.heads_used[h] % 4], lw=1.0, ls="--",
                      label=f"head {fr.heads_used[h]}")
        var = st.predictive_variance[i]
        wide = b.copy()
        wide[3] += 2 * 1.96 * np.sqrt(max(var[3], 0))
        wide[4] += 2 * 1.96 * np.sqrt(max(var[4], 0))
        draw_bev_box(axz, wide, color="0.5", lw=2.5, alpha=0.6, label="95 % l, w")
        draw_bev_box(axz, b, color="tab:blue", lw=1.8, label="merged")
        if fm.det_gt[i] >= 0:
            draw_bev_box(axz, gb[fm.det_gt[i]], color="tab:green", lw=1.2, label="ground truth")
        sel = (np.abs(xyz[:, 0] - b[0]) < 4) & (np.abs(xyz[:, 1] - b[1]) < 4)
        axz.scatter(xyz[sel, 0], xyz[sel, 1], s=2, c="k", linewidths=0)
        half = 0.75 * max(b[3], b[4]) + 0.8
        axz.set_xlim(b[0] - half, b[0] + half)
        axz.set_ylim(b[1] - half, b[1] + half)
        axz.set_aspect("equal")
        axz.legend(fontsize=6, loc="upper right")
        axz.set_title(f"{'near' if j == 0 else 'far'} TP: {names[m.labels[i] - 1]} at "
                      f"{dist[i]:.1f} m", fontsize=9)
        axt = fig.add_subplot(gs[1, 2 * j + 1])
        axt.axis("off")
        text = (f"cluster size   {int(st.cluster_size[i])}\n"
                f"merged score   {m.scores[i]:.3f}\n"
                f"meta conf.     {conf[i]:.3f}\n"
                f"pred. IoU      {piou[i]:.3f}\n"
                f"true IoU       {fm.iou_matched[i]:.3f}\n"
                f"SE  {st.shannon_entropy[i]:.3f} bit\n"
                f"MI  {st.mutual_information[i]:.4f} bit\n"
                f"ETV {st.epistemic_total_variance[i]:.4f}\n"
                f"ATV {st.aleatoric_total_variance[i]:.4f}")
        axt.text(0.02, 0.98, text, va="top", ha="left", family="monospace", fontsize=9,
                 transform=axt.transAxes)
        ax.annotate(f"{'near' if j == 0 else 'far'}", (b[0], b[1]), color="tab:blue",
                    fontsize=8, xytext=(4, 4), textcoords="offset points")
        info.append({"detection": int(i), "distance": float(dist[i]),
                     "cluster_size": int(st.cluster_size[i]), "score": float(m.scores[i]),
                     "confidence": float(conf[i]), "se": float(st.shannon_entropy[i]),
                     "mi": float(st.mutual_information[i]),
                     "etv": float(st.epistemic_total_variance[i]),
                     "atv": float(st.aleatoric_total_variance[i])})
    rp.save(fig, path)
    return {"bag": str(bag), "stamp": stamp, "merged": int(len(m)), "shown": info}


def _pick_frame(ds: MimoDataset, eval_frames: np.ndarray) -> int:
    """The evaluation frame in the middle of the first evaluation sequence."""
    if not len(eval_frames):
        return 0
    g = ds.frame_group[eval_frames[0]]
    fr = eval_frames[ds.frame_group[eval_frames] == g]
    return int(fr[len(fr) // 2])


# ------------------------------------------------------------------ report
def _f(x, d=3):
    return fmt(x, d)


def comparison_rows(res: dict, which: str = "recalibrated") -> list:
    rows = []
    for name, r in res["methods"].items():
        u = r[which]
        rows.append([METHODS[name], *(u[f"nll_cls_{p}"] for p, _ in PARTS),
                     *(u[f"brier_{p}"] for p, _ in PARTS), u["nll_reg_TP"], u["nll_reg_FP_ML"],
                     u["energy_TP"], u["energy_FP_ML"], u["mce_cls"], u["ce_reg"],
                     u["score_ece"]])
    return rows


COMPARISON_HEADER = ["method", "NLL cls TP", "NLL cls FP_ML", "NLL cls FP_BG", "Brier TP",
                     "Brier FP_ML", "Brier FP_BG", "NLL reg TP", "NLL reg FP_ML", "ES TP",
                     "ES FP_ML", "MCE cls", "CE reg", "score ECE"]


def write_report(out: Path, res: dict, figures: dict) -> Path:
    m = res["methods"]
    d = res["data"]
    lines = ["# LiDAR-MIMO evaluation (held-out sequences)", "",
             f"Data: {d['groups']} sequences, {d['frames']} frames, {d['gt_boxes']} ground-truth "
             f"boxes ({d['gt_ignored']} ignored: < 5 points or > 80 m); {d['merged']} merged and "
             f"{d['single']} single-head detections. Recalibration half: "
             f"{', '.join(res['recal_groups'])} ({res['recal_frames']} frames); evaluation half: "
             f"{', '.join(res['eval_groups'])} ({res['eval_frames']} frames).", "",
             "Partitions: class-aware one-to-one matching at BEV IoU >= 0.5 (all classes); "
             "FP_BG: BEV IoU <= 0.1 with every ground-truth box. KITTI columns: car / truck "
             "0.7, pedestrian / cyclist 0.5. mAP: R40, all frames.", "",
             "## Detection quality and partitions", "",
             markdown_table(["method", "mAP BEV@0.5", "mAP KITTI BEV", "mAP KITTI 3D", "TP",
                             "FP_ML", "FP_BG", "ignored"],
                            [[METHODS[k], 100 * r["map_bev50"], 100 * r["map_kitti_bev"],
                              100 * r["map_kitti_3d"], r["counts"]["TP"],
                              r["counts"]["FP_ML"], r["counts"]["FP_BG"],
                              r["counts"]["ignored"]] for k, r in m.items()]).rstrip(), "",
             "mAP in %. The meta model changes only the ranking score of the merged "
             "detections, so its partitions equal the merged ones up to duplicates.", "",
             "## Uncertainty (evaluation half, after per-class F1 thresholds and temperature "
             "scaling fitted on the recalibration half)", "",
             markdown_table(COMPARISON_HEADER, comparison_rows(res)).rstrip(), "",
             "Lower is better everywhere. NLL cls / Brier: K + 1 classes (target: a TP its "
             "class, FP_ML and FP_BG the background, as the authors' code); NLL reg: Gaussian "
             "x, y, z, l, w, h (+ 0.01 variance) + von Mises yaw against the ground-truth "
             "rectangle in the parametrization nearest to the prediction (the reference "
             "detector has no heading); ES: energy score (1000 samples); MCE "
             "cls: marginal calibration error (Kumar et al., 15 equal-mass bins, debiased); CE "
             "reg: Kuleshov calibration error of the TPs (levels j/15); score ECE: the score as "
             "P(TP), 10 bins.", "",
             "Detections kept after the thresholds: " + ", ".join(
                 f"{METHODS[k]} {r['recalibrated']['n']} of {r['raw']['n']}" for k, r in m.items())
             + ".", "",
             "### Without recalibration (all detections of the evaluation half, raw "
             "distributions)", "",
             markdown_table(COMPARISON_HEADER, comparison_rows(res, "raw")).rstrip(), "",
             "### Fitted recalibration (recalibration half)", "",
             "Per class: the F1-optimal threshold on the temperature-scaled score / the "
             "temperature T.", "",
             markdown_table(["method"] + [f"{c} thr / T" for c in
                                          res["methods"]["single"]["ap_bev50"]],
                            [[METHODS[k]] + [f"{r['recalibration']['thresholds'][c]:.3f} / "
                                             f"{r['recalibration']['temperatures'][c]:.2f}"
                                             for c in r["ap_bev50"]]
                             for k, r in m.items()]).rstrip(), ""]
    q = res["meta_quality"]
    label = QUALITY_LABELS
    lines += ["## Meta model vs merged score (all merged test detections)", "",
              "Target: BEV IoU >= 0.5 with a ground-truth box of the detection's class "
              "(ignored boxes included); IoU: the predicted IoU (merged score for the first "
              "row).", "",
              markdown_table(["confidence", "AUROC", "AUPRC", "ECE", "Brier", "IoU R²",
                              "IoU MAE"],
                             [[label[k], v["auroc"], v["auprc"], v["ece"], v["brier"],
                               v["iou_r2"], v["iou_mae"]] for k, v in q.items()]).rstrip(),
              ""]
    a = res["acceptance"]
    if a.get("checked"):
        lines += ["## Acceptance (issue 7)", "",
                  f"Merged heads + meta model vs single head after recalibration: marginal "
                  f"calibration error {a['mce_cls_meta']:.4f} vs {a['mce_cls_single']:.4f}, "
                  f"score ECE {a['score_ece_meta']:.4f} vs {a['score_ece_single']:.4f}: "
                  f"**{'better' if a['better_calibrated'] else 'NOT better'} calibrated**.",
                  ""]
    lines += ["## Figures", ""]
    for k, v in figures.items():
        lines.append(f"![{k}]({Path(v).name})")
        lines.append("")
    path = out / "report.md"
    path.write_text("\n".join(lines))
    return path


def update_model_card(card: Path, res: dict, command: str) -> None:
    """Replace the held-out section of ``MODEL_CARD.md`` (added if the card has none)."""
    q = res["meta_quality"]
    m = res["methods"]
    update_card(card, heldout_section(
        f"Held-out sequences {', '.join(sorted(res['recal_groups'] + res['eval_groups']))} "
        f"(`{command}`):",
        markdown_table(["confidence", "AUROC", "ECE", "IoU R²", "IoU MAE"],
                       [[QUALITY_LABELS[k], v["auroc"], v["ece"], v["iou_r2"],
                         v["iou_mae"]] for k, v in q.items()]),
        markdown_table(["method", "mAP BEV@0.5 [%]", "MCE cls", "CE reg", "score ECE"],
                       [[METHODS[k], 100 * r["map_bev50"], r["recalibrated"]["mce_cls"],
                         r["recalibrated"]["ce_reg"], r["recalibrated"]["score_ece"]]
                        for k, r in m.items()]),
        "(calibration metrics after the paper's recalibration; full report: "
        "`report.md` of mimo-eval)"))


def run(data, models_dir, out, *, cache_dir=None, docs=None, model_card=None,
        es_samples: int = 1000, seed: int = 0, heading_aware: bool = False, quiet: bool = False,
        command: str = "", topics: dict | None = None) -> dict:
    t0 = time.monotonic()
    from mimo_ros.pipeline import MimoSettings

    ds = load_bags(data, cache_dir=cache_dir, progress=not quiet, topics=topics)
    models = {}
    for use_points in (False, True):
        prefix = PREFIXES[use_points]
        c = Path(models_dir) / f"{prefix}_classifier.joblib"
        r = Path(models_dir) / f"{prefix}_regressor.joblib"
        if c.exists() or r.exists() or not use_points:
            models[use_points] = meta_model.MetaModels(
                c, r, MimoSettings(use_points=use_points).feature_names(), method="mimo",
                settings={**ds.info["settings"], "use_points": use_points})
    res = evaluate(ds, models, es_samples=es_samples, seed=seed, heading_aware=heading_aware,
                   progress=not quiet)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    figures = {}
    dets = res["_detections"]
    curves = {}
    for name, r in res["methods"].items():
        ev = r["_eval_rows"]
        curves[METHODS[name]] = (r["_annotation"].tp[ev].astype(float),
                                 np.clip(dets[name].score[ev], 0, 1))
    figures["reliability"] = rp.reliability_png(out / "mimo_reliability.png", curves,
                                                title="score as P(TP), evaluation half, raw")
    if "meta" in dets:
        figures["iou"] = rp.scatter_png(out / "mimo_iou_scatter.png", dets["meta"].iou,
                                        dets["meta"].predicted_iou, title="MIMO meta regressor")
    _, ev_frames = split_groups(ds)
    frame = _pick_frame(ds, ev_frames)
    figures["qualitative"] = out / "mimo_qualitative.png"
    res["qualitative"] = qualitative_png(figures["qualitative"], ds, frame, models,
                                         topics=topics)
    res["seconds"] = time.monotonic() - t0
    (out / "summary.json").write_text(json.dumps(jsonable(res, drop_private=True), indent=1, sort_keys=True))
    write_report(out, res, figures)
    if docs:
        Path(docs).mkdir(parents=True, exist_ok=True)
        for k in ("qualitative", "reliability"):
            shutil.copyfile(figures[k], Path(docs) / Path(figures[k]).name)
    if model_card:
        update_model_card(Path(model_card), res, command)
    return res


def main(argv=None) -> int:
    import shlex

    p = argparse.ArgumentParser(prog="mimo-eval", description=__doc__.split("\n\n")[0])
    add_data_arguments(p, "data/perception/meta_test")
    p.add_argument("--models", default="models/mimo", help="directory of mimo_*.joblib")
    p.add_argument("--out", default="out/mimo_eval", help="report directory")
    p.add_argument("--docs", default="", help="also copy the figures here (e.g. docs)")
    p.add_argument("--model-card", default="", help="MODEL_CARD.md to add the results to")
    p.add_argument("--es-samples", type=int, default=1000, help="energy score samples")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--heading-aware", action="store_true",
                   help="regression metrics against the raw ground truth (detectors with a "
                        "heading); default: the equivalent rectangle nearest to the prediction")
    a = p.parse_args(argv)
    command = "mimo-eval " + " ".join(shlex.quote(x) for x in (argv if argv is not None
                                                              else sys.argv[1:]))
    res = run(a.data, a.models, a.out, cache_dir=a.cache or None, docs=a.docs or None,
              model_card=a.model_card or None, es_samples=a.es_samples, seed=a.seed,
              heading_aware=a.heading_aware, quiet=a.quiet, command=command,
              topics=dict(a.topic))
    print(markdown_table(["method", "mAP BEV@0.5 [%]", "TP", "FP_ML", "FP_BG"],
                            [[METHODS[k], 100 * r["map_bev50"], r["counts"]["TP"],
                              r["counts"]["FP_ML"], r["counts"]["FP_BG"]]
                             for k, r in res["methods"].items()]))
    print(markdown_table(COMPARISON_HEADER, comparison_rows(res)))
    a_ = res["acceptance"]
    if a_.get("checked"):
        print(f"merged + meta vs single head: MCE {a_['mce_cls_meta']:.4f} vs "
              f"{a_['mce_cls_single']:.4f}, score ECE {a_['score_ece_meta']:.4f} vs "
              f"{a_['score_ece_single']:.4f} -> "
              f"{'better calibrated' if a_['better_calibrated'] else 'NOT better calibrated'}")
    print(f"wrote {Path(a.out) / 'report.md'}, summary.json, figures ({res['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
