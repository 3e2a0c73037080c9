"""Annotation-error proposals (LMD paper, section IV g): false positives against the given
labels, ranked by the meta regressor's predicted IoU (or the meta confidence) descending
across the whole dataset. A confident detection that the labels call wrong is often right,
and the label wrong (missing, misplaced or mis-sized box).

* :func:`review` ranks the FPs (IoU_BEV < 0.5 with every given box, the dataset's target
  rule) by ``lmd_iou`` (predicted IoU), ``lmd_confidence``, the detector ``score`` and a
  seeded ``random`` order. :func:`export` writes the top k as CSV and JSON (frame, box,
  class, predicted IoU, confidence, ...), :func:`thumbnails` one BEV picture per proposal
  and a contact sheet.
* Known errors (simulation): :func:`inject_errors` corrupts the ground truth of a dataset
  with ``lidar_sim.annotation_errors`` (seeded per frame; only boxes with at least one
  cloud point, as annotators label what the sensor saw) and :func:`review` then scores
  each ranking by precision@k. Hit rules (a proposal is one FP against the corrupted
  labels):

  - ``caused`` (main figure): the FP is a true positive against the clean ground truth
    (IoU_BEV >= 0.5). Clean and corrupted labels differ only in corrupted objects, so the
    injected error is exactly what makes this detection an FP: reviewing it finds the error.
  - ``near`` (looser, for a reviewer who inspects the surroundings): the FP overlaps
    (IoU_BEV > 0.1) the clean box of an object whose annotation was corrupted. Counted kinds:
    ``missing``, ``shifted``, ``resized``, and ``wrong_class`` only with class-aware targets
    (with class-agnostic targets a class error cannot make a detection an FP).

  The random baseline is reported as its expectation (the hit rate among all FPs) and as one
  seeded draw.

``python -m lidar_quality_training.lmd.annotation_review`` runs the review with the shipped models
(``models/lmd``) on bags or a KITTI directory (``--inject-errors`` for the simulated case).
"""
from __future__ import annotations

import argparse
import csv
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from lidar_quality_core.detection_eval import match_frame
from lidar_quality_core.iou import iou_bev

from .dataset import TP_IOU, LmdDataset

__all__ = ["NEAR_IOU", "RANKINGS", "InjectedErrors", "inject_errors", "targets_against",
           "ReviewResult", "review", "precision_at_k", "export", "load_points",
           "frame_message", "draw_points", "draw_boxes", "thumbnails",
           "main"]

NEAR_IOU = 0.1
RANKINGS = ("lmd_iou", "lmd_confidence", "score", "random")
GEOMETRIC_ERRORS = ("missing", "shifted", "resized")


@dataclass
class InjectedErrors:
    """Corrupted ("given") ground truth of a dataset's frames plus what was done.

    ``corrupted`` marks the rows of the dataset's clean GT (``ds.gt_box``) whose annotation
    changed; ``kinds`` lists the error kinds per such row.
    """

    gt_offsets: np.ndarray
    gt_box: np.ndarray
    gt_label: np.ndarray
    records: list
    corrupted: np.ndarray            # (G,) bool over the clean GT rows
    kinds: dict = field(default_factory=dict)  # clean GT row -> [kind, ...]

    def counts(self) -> dict:
        out: dict[str, int] = {}
        for r in self.records:
            out[r["kind"]] = out.get(r["kind"], 0) + 1
        return out


def inject_errors(ds: LmdDataset, *, seed: int = 0, config=None,
                  min_points: int = 1) -> InjectedErrors:
    """Apply ``lidar_sim.annotation_errors`` box errors to ``ds``'s ground truth, frame by
    frame (generator seeded with ``[seed, frame]``), to boxes with >= ``min_points``
    points; class confusions as ``lidar-sim generate``'s (car <-> truck, pedestrian <->
    cyclist)."""
    from lidar_sim import classes
    from lidar_sim.annotation_errors import (AnnotationErrorConfig, apply_records,
                                             inject_box_errors)
    from lidar_sim.cli import CONFUSIONS

    cfg = config or AnnotationErrorConfig()
    names = list(classes.CLASS_NAMES)
    confusions = {classes.class_id(k): [classes.class_id(v) for v in vs]
                  for k, vs in CONFUSIONS.items()}
    offsets, boxes, labels, records = [0], [], [], []
    corrupted = np.zeros(len(ds.gt_box), dtype=bool)
    kinds: dict[int, list] = {}
    for k in range(ds.n_frames):
        a, b = int(ds.gt_offsets[k]), int(ds.gt_offsets[k + 1])
        gb, gl = ds.gt_box[a:b], ds.gt_label[a:b]
        vis = np.flatnonzero(ds.gt_points[a:b] >= min_points)
        cls = np.array([names.index(c) if c in names else -1 for c in gl[vis].tolist()])
        rng = np.random.default_rng([seed, k])
        recs = inject_box_errors(gb[vis], cls, vis, confusions, rng, cfg)
        nb, nc, ninst, _ = apply_records(recs, gb[vis], cls, vis)
        hidden = np.setdiff1d(np.arange(b - a), vis)
        boxes += [gb[hidden], nb]
        labels += [gl[hidden], np.array([names[c] if c >= 0 else gl[i]
                                         for c, i in zip(nc.tolist(), ninst.tolist())], dtype=str)]
        offsets.append(offsets[-1] + len(hidden) + len(nb))
        for r in recs:
            row = a + int(r["instance"])
            corrupted[row] = True
            kinds.setdefault(row, []).append(r["kind"])
            records.append({"frame": k, "group": str(ds.frame_group[k]),
                            "frame_key": str(ds.frame_key[k]), "gt_id": str(ds.gt_id[row]),
                            **{key: v for key, v in r.items() if key != "instance"}})
    return InjectedErrors(np.asarray(offsets, dtype=np.int64),
                          np.concatenate(boxes).reshape(-1, 7) if boxes else np.zeros((0, 7)),
                          np.concatenate(labels) if labels else np.zeros(0, dtype=str),
                          records, corrupted, kinds)


def targets_against(ds: LmdDataset, gt_offsets, gt_box, gt_label) -> np.ndarray:
    """(n,) IoU_BEV of every row with its best box of the given labels (class-aware when
    ``ds.class_aware``), the same rule as the dataset's own target."""
    out = np.zeros(len(ds))
    order = np.argsort(ds.frame, kind="stable")
    starts = np.searchsorted(ds.frame[order], np.arange(ds.n_frames + 1))
    for k in range(ds.n_frames):  # bounded: one match per frame
        rows = order[starts[k]:starts[k + 1]]
        if not len(rows):
            continue
        a, b = int(gt_offsets[k]), int(gt_offsets[k + 1])
        m = match_frame(ds.box[rows], ds.score[rows], ds.label[rows].tolist(), gt_box[a:b],
                        gt_label[a:b].tolist(), iou_threshold=TP_IOU)
        out[rows] = m.iou_same_class if ds.class_aware else m.iou_any
    return out


def _near_corrupted(ds: LmdDataset, rows: np.ndarray, errors: InjectedErrors) -> np.ndarray:
    """(len(rows),) bool: IoU_BEV > NEAR_IOU with the clean box of a corrupted object."""
    counted = set(GEOMETRIC_ERRORS) | ({"wrong_class"} if ds.class_aware else set())
    bad = np.array([any(k in counted for k in errors.kinds.get(j, ()))
                    for j in range(len(ds.gt_box))], dtype=bool)
    out = np.zeros(len(rows), dtype=bool)
    for k in np.unique(ds.frame[rows]).tolist():
        sel = np.flatnonzero(ds.frame[rows] == k)
        a, b = int(ds.gt_offsets[k]), int(ds.gt_offsets[k + 1])
        g = np.flatnonzero(bad[a:b]) + a
        if len(g):
            out[sel] = (iou_bev(ds.box[rows[sel]], ds.gt_box[g]) > NEAR_IOU).any(axis=1)
    return out


def precision_at_k(hits_ranked: np.ndarray, ks: Sequence[int]) -> dict:
    """{k: share of hits among the first k} (over all when fewer than k)."""
    h = np.asarray(hits_ranked, dtype=float)
    return {int(k): float(h[:k].mean()) if len(h) else float("nan") for k in ks}


@dataclass
class ReviewResult:
    """FP rows (dataset row indices) in each ranking's order, and, with injected errors,
    hit flags per FP row and precision@k per ranking and hit rule."""

    fp_rows: np.ndarray
    given_iou: np.ndarray                 # (n,) IoU_BEV with the given labels
    order: dict                           # ranking -> FP rows, best first
    hits: dict = field(default_factory=dict)       # rule -> (n,) bool over dataset rows
    precision: dict = field(default_factory=dict)  # ranking -> rule -> {k: value}
    expected_random: dict = field(default_factory=dict)  # rule -> hit rate among FPs


def _ranked(rows: np.ndarray, key: np.ndarray) -> np.ndarray:
    """``rows`` by ``key`` descending; ties (and NaN, last) keep row order."""
    v = np.where(np.isfinite(key[rows]), key[rows], -np.inf)
    return rows[np.argsort(-v, kind="stable")]


def review(ds: LmdDataset, confidence, predicted_iou, *, errors: InjectedErrors | None = None,
           ks: Sequence[int] = (50, 100), seed: int = 0) -> ReviewResult:
    """Rank the FPs of ``ds`` against its labels (or ``errors``' corrupted labels)."""
    confidence = np.asarray(confidence, dtype=float)
    predicted_iou = np.asarray(predicted_iou, dtype=float)
    if len(confidence) != len(ds) or len(predicted_iou) != len(ds):
        raise ValueError(f"need one confidence and predicted IoU per row ({len(ds)})")
    given = ds.iou if errors is None else targets_against(ds, errors.gt_offsets, errors.gt_box,
                                                          errors.gt_label)
    fp = np.flatnonzero(given < TP_IOU)
    rng = np.random.default_rng(seed)
    order = {"lmd_iou": _ranked(fp, predicted_iou), "lmd_confidence": _ranked(fp, confidence),
             "score": _ranked(fp, ds.score), "random": rng.permutation(fp)}
    res = ReviewResult(fp, given, order)
    if errors is not None:
        caused = np.zeros(len(ds), dtype=bool)
        caused[fp] = ds.iou[fp] >= TP_IOU
        near = np.zeros(len(ds), dtype=bool)
        near[fp] = _near_corrupted(ds, fp, errors)
        res.hits = {"caused": caused, "near": near}
        res.expected_random = {r: float(h[fp].mean()) if len(fp) else float("nan")
                               for r, h in res.hits.items()}
        res.precision = {name: {rule: precision_at_k(h[rows], ks) for rule, h in res.hits.items()}
                         for name, rows in order.items()}
    return res


def _rows_table(ds, rows, res: ReviewResult, confidence, predicted_iou) -> list[dict]:
    out = []
    for rank, i in enumerate(rows.tolist(), 1):
        k = int(ds.frame[i])
        rec = {"rank": rank, "row": i, "group": str(ds.frame_group[k]),
               "source": str(ds.frame_source[k]), "frame_key": str(ds.frame_key[k]),
               "detection_index": int(ds.det_index[i]), "detection_id": str(ds.det_id[i]),
               "class": str(ds.label[i]),
               **{n: float(v) for n, v in zip(("x", "y", "z", "l", "w", "h", "yaw"), ds.box[i])},
               "score": float(ds.score[i]), "predicted_iou": float(predicted_iou[i]),
               "confidence": float(confidence[i]), "iou_given_labels": float(res.given_iou[i])}
        for rule, h in res.hits.items():
            rec[f"hit_{rule}"] = bool(h[i])
        out.append(rec)
    return out


def export(ds: LmdDataset, res: ReviewResult, confidence, predicted_iou, out_dir, *,
           k: int = 100, ranking: str = "lmd_iou") -> tuple[Path, Path]:
    """``proposals_<ranking>.csv`` / ``.json``: the top ``k`` FPs of ``ranking``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    table = _rows_table(ds, res.order[ranking][:k], res, confidence, predicted_iou)
    cpath, jpath = out / f"proposals_{ranking}.csv", out / f"proposals_{ranking}.json"
    fields = list(table[0]) if table else ["rank"]
    with open(cpath, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        w.writerows(table)
    jpath.write_text(json.dumps({"ranking": ranking, "fp_total": int(len(res.fp_rows)),
                                 "proposals": table}, indent=1) + "\n")
    return cpath, jpath


# ---------------------------------------------------------------------------- thumbnails
def load_points(source: str, key: str, points_topic: str = "/lidar/points") -> np.ndarray:
    """(M, 3) finite points of a dataset frame: a KITTI ``.bin`` file, or the cloud with
    header stamp ``key`` in the bag ``source``."""
    from lidar_quality_core.pointcloud import finite_mask, xyz_intensity

    if source.endswith(".bin"):
        xyz = np.fromfile(source, dtype="<f4").reshape(-1, 4)[:, :3]
        return xyz[finite_mask(xyz)]
    msg = frame_message(source, points_topic, int(key))
    if msg is None:
        raise KeyError(f"{source}: no {points_topic} message with stamp {key}")
    xyz, _ = xyz_intensity(msg)
    return xyz[finite_mask(xyz)]


def frame_message(bag: str, topic: str, stamp: int):
    """The decoded ``topic`` message of ``bag`` with header stamp ``stamp`` [ns], or None."""
    from lidar_quality_ros.bag_io import read_bag

    # Recorders log a message shortly after its stamp: seek near it, then the whole bag.
    for start in (max(stamp - 2_000_000_000, 0), None):
        for m in read_bag(bag, topics={topic}, start_ns=start):
            msg = m.decode()
            if msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec == stamp:
                return msg
    return None


def draw_points(ax, xyz, cx: float, cy: float, radius: float) -> None:
    """The cloud's points within ``radius`` of (cx, cy), grey by height, ground pale (objects
    stand out without a ground model)."""
    near = (np.abs(xyz[:, 0] - cx) < radius) & (np.abs(xyz[:, 1] - cy) < radius)
    p = xyz[near]
    if len(p):
        lo, hi = np.percentile(p[:, 2], [5, 99])
        ax.scatter(p[:, 0], p[:, 1], s=0.8, c=p[:, 2], cmap="Greys", vmin=lo - 0.3 * (hi - lo),
                   vmax=hi, linewidths=0)


def draw_boxes(ax, boxes, **kw):
    """BEV outlines of (n, 7) boxes."""
    from lidar_quality_core.box_geometry import bev_corners

    for c in bev_corners(np.asarray(boxes, dtype=float).reshape(-1, 7)):
        ring = np.vstack([c, c[:1]])
        ax.plot(ring[:, 0], ring[:, 1], **kw)


def _panel(ax, ds, i, xyz, given_boxes, clean_bad, rec, radius):
    cx, cy = ds.box[i, 0], ds.box[i, 1]
    draw_points(ax, xyz, cx, cy, radius)
    draw_boxes(ax, given_boxes, color="#7b2cbf", lw=1.2)
    draw_boxes(ax, ds.box[i], color="#e63946", lw=1.4)
    if clean_bad is not None and len(clean_bad):
        draw_boxes(ax, clean_bad, color="#2a9d8f", lw=1.4, ls="--")
    ax.set_xlim(cx - radius, cx + radius)
    ax.set_ylim(cy - radius, cy + radius)
    ax.set_aspect("equal")
    ax.tick_params(labelsize=6)
    hit = "".join(f" {r}" for r in ("caused", "near") if rec.get(f"hit_{r}"))
    ax.set_title(f"#{rec['rank']} {rec['class']} pIoU {rec['predicted_iou']:.2f} "
                 f"c {rec['confidence']:.2f}{hit}\n{rec['group']} {rec['frame_key']}",
                 fontsize=7)


def thumbnails(ds: LmdDataset, res: ReviewResult, confidence, predicted_iou, out_dir, *,
               k: int = 12, ranking: str = "lmd_iou", errors: InjectedErrors | None = None,
               radius: float = 10.0, sheet_columns: int = 4,
               points: Callable[[str, str], np.ndarray] = load_points) -> list[Path]:
    """One BEV PNG per top-``k`` proposal of ``ranking`` (proposal red, given labels purple,
    clean boxes of corrupted objects dashed green) and ``sheet_<ranking>.png`` with all of
    them; returns the paths (sheet last)."""
    from lidar_quality_core.report_plots import figure, save

    out = Path(out_dir) / "thumbnails"
    rows = res.order[ranking][:k]
    table = _rows_table(ds, rows, res, confidence, predicted_iou)
    cache: dict[int, np.ndarray] = {}
    panels = []
    for i, rec in zip(rows.tolist(), table):
        f = int(ds.frame[i])
        if f not in cache:
            cache[f] = points(str(ds.frame_source[f]), str(ds.frame_key[f]))
        if errors is not None:
            a, b = int(errors.gt_offsets[f]), int(errors.gt_offsets[f + 1])
            given = errors.gt_box[a:b]
            ca, cb = int(ds.gt_offsets[f]), int(ds.gt_offsets[f + 1])
            clean_bad = ds.gt_box[ca:cb][errors.corrupted[ca:cb]]
        else:
            given, clean_bad = ds.gt_of(f)[0], None
        panels.append((i, cache[f], given, clean_bad, rec))
    paths = []
    for i, xyz, given, clean_bad, rec in panels:
        fig = figure(3.2, 3.4)
        _panel(fig.add_subplot(1, 1, 1), ds, i, xyz, given, clean_bad, rec, radius)
        paths.append(save(fig, out / f"{ranking}_{rec['rank']:03d}.png"))
    if panels:
        ncol = min(sheet_columns, len(panels))
        nrow = -(-len(panels) // ncol)
        fig = figure(3.0 * ncol, 3.2 * nrow)
        for n, (i, xyz, given, clean_bad, rec) in enumerate(panels):
            _panel(fig.add_subplot(nrow, ncol, n + 1), ds, i, xyz, given, clean_bad, rec, radius)
        fig.suptitle(f"Top {len(panels)} annotation-error proposals ({ranking}): proposal red, "
                     "labels purple, clean box of a corrupted label dashed green", fontsize=8)
        paths.append(save(fig, Path(out_dir) / f"sheet_{ranking}.png"))
    return paths


def summary(res: ReviewResult, errors: InjectedErrors | None) -> dict:
    """JSON-ready figures of a review."""
    out = {"fp_total": int(len(res.fp_rows)), "hit_rules": {
        "caused": "FP against the given labels, TP (IoU_BEV >= 0.5) against the clean ones",
        "near": f"FP overlapping (IoU_BEV > {NEAR_IOU}) the clean box of a corrupted object"}}
    if errors is not None:
        out["errors_injected"] = errors.counts()
        out["corrupted_objects"] = int(errors.corrupted.sum())
        out["hits_among_fps"] = {r: int(h[res.fp_rows].sum()) for r, h in res.hits.items()}
        out["expected_random_precision"] = res.expected_random
        out["precision_at_k"] = {n: {r: {str(k): v for k, v in p.items()} for r, p in d.items()}
                                 for n, d in res.precision.items()}
    return out


def main(argv=None) -> int:
    from lidar_quality_core.meta_model import MetaModels

    from .dataset import add_source_args, load_from_args, settings_from_args
    from lmd_ros.pipeline import MODES, default_model_paths

    ap = argparse.ArgumentParser(prog="python -m lidar_quality_training.lmd.annotation_review",
                                 description=__doc__.split("\n\n")[0])
    add_source_args(ap, train=False)
    ap.add_argument("--mode", choices=MODES, default="threshold")
    ap.add_argument("--models", type=Path, default=None,
                    help="directory with lmd_<mode>_*.joblib (default: the shipped models)")
    ap.add_argument("--out", type=Path, default=Path("out/lmd/annotation_review"))
    ap.add_argument("--k", type=int, nargs="+", default=[50, 100], help="precision@k / export")
    ap.add_argument("--thumbnails", type=int, default=12, help="BEV pictures of the top n")
    ap.add_argument("--inject-errors", action="store_true",
                    help="corrupt the ground truth (simulation) and report precision@k")
    ap.add_argument("--seed", type=int, default=0, help="error injection / random ranking")
    args = ap.parse_args(argv)
    settings = settings_from_args(args, [args.mode])[0]
    data = load_from_args(args, [settings], "test")
    if data is None:
        raise SystemExit("no data: give --test bags or a KITTI directory with --kitti-test-frames")
    ds = data[args.mode]
    cpath, rpath = default_model_paths(args.mode)
    if args.models is not None:
        cpath, rpath = args.models / cpath.name, args.models / rpath.name
    conf, pred = MetaModels(cpath, rpath, settings.feature_names(), settings=settings,
                            method="lmd").predict(ds.X)
    errors = inject_errors(ds, seed=args.seed) if args.inject_errors else None
    res = review(ds, conf, pred, errors=errors, ks=args.k, seed=args.seed)
    export(ds, res, conf, pred, args.out, k=max(args.k))
    export(ds, res, conf, pred, args.out, k=max(args.k), ranking="score")
    if args.thumbnails:
        # the cloud under the user's topic name (--topic points=...), as the dataset read it
        points_topic = dict(getattr(args, "topic", None) or ()).get("points", "/lidar/points")
        thumbnails(ds, res, conf, pred, args.out, k=args.thumbnails, errors=errors,
                   points=lambda src, key: load_points(src, key, points_topic))
    s = summary(res, errors)
    (args.out / "summary.json").write_text(json.dumps(s, indent=2) + "\n")
    print(f"{s['fp_total']} false positives against the "
          f"{'corrupted' if errors else 'given'} labels -> {args.out}")
    for name, d in s.get("precision_at_k", {}).items():
        print(f"  {name:15s} " + "  ".join(f"{r} P@{k} {v:.2f}" for r, p in d.items()
                                           for k, v in p.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
