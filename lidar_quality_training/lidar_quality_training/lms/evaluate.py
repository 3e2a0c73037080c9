"""``lms-eval``: evaluate LidarMetaSeg like the paper (section III; no rclpy).

    lms-eval --train data/perception/meta_train --test data/perception/meta_test \\
             --models models/lms --out out/lms_eval --docs-figure docs/lms_quality.png

Writes into ``--out``: ``report.md``, ``summary.json`` and the figures.

* **Table I** (grouped 10-fold cross validation on ``--train``, folds of whole
  sub-sequences): ACC, AUROC, AUPRC (false positives, IoU_adj = 0, as the positive class,
  as in the paper) and R^2 of IoU_adj, mean and standard deviation over the folds, on the
  training and the validation folds, for LMS (every metric), "LMS w/o features" (without
  the point-cloud feature measures, :data:`lidar_quality_training.lms.train.FEATURE_MEASURE_PATTERN`) and
  "Entropy" (``mean_E`` alone), all with the same estimator (``--kind``, XGBoost), plus
  the naive baseline ACC (always the majority class).
* **Table II** (greedy forward selection, :func:`meta_model.greedy_selection`): from the
  empty set, add the metric whose model has the best grouped-CV validation score. The
  search estimator is ``--greedy-kind`` (default ``linear``: logistic / ridge regression
  on standardised metrics; the paper's heuristic is "inspired by forward-stepwise
  selection for linear regression") because the search fits (metrics x steps x folds)
  models, ~5000 for 15 steps and 3 folds, which XGBoost (3-4 s per fit on the full data)
  cannot do in reasonable time on two cores; for the same reason it runs on
  ``--greedy-rows`` random segments (folds still of whole sub-sequences). Every selected
  set is then re-scored with ``--kind`` (XGBoost) on all segments in the folds of
  Table I, so those rows compare with Table I's "all". The classification criterion is
  AUROC (threshold-free; the paper uses ACC, which is reported in the re-score).
* **Held-out** (``--test``, never seen in training): the shipped models of ``--models``
  (LMS, loaded and verified as the node loads them) against both baselines fitted on the
  whole ``--train`` set: ACC, AUROC, AUPRC, ECE, MCE, R^2, MAE; reliability diagrams
  (10 bins, ECE / MCE) for the CV out-of-fold and the held-out confidences; true vs
  predicted IoU_adj scatter; and the paper's figure 1 for one held-out scan: its range
  image coloured by ground truth, prediction, true IoU_adj and predicted IoU_adj (grey:
  segments with SP < 10, not rated), plus the points in bird's eye view.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from lidar_quality_core import meta_model
from lidar_quality_core.jsonable import jsonable
from lidar_quality_core import report_plots as rp
from lidar_quality_core.progress import Progress

from ..report import Section, markdown_table, update_card
from .dataset import SegmentDataset, discover_sources, load_frame
from .train import (FEATURE_SETS, PREFIX, add_data_arguments, cross_validate_pair,
                    data_summary, dataset_from_args, feature_set, fit_pair, settings_from_args,
                    task_metrics)

__all__ = ["SET_LABELS", "table1", "greedy", "heldout", "figure1", "write_report",
           "update_model_card", "main"]

SET_LABELS = {"lms": "LMS", "no_features": "LMS w/o features", "entropy": "Entropy"}


def table1(ds: SegmentDataset, *, kind: str = "xgboost", n_folds: int = 10, seed: int = 0,
           quiet: bool = False) -> dict:
    """Cross validation of every feature set: ``{set: cross_validate_pair(...)}`` plus
    ``naive_accuracy``."""
    out = {}
    for s in FEATURE_SETS:
        bar = Progress(f"CV {SET_LABELS[s]}", 2 * n_folds, not quiet)
        out[s] = cross_validate_pair(ds, feature_set(ds.names, s), kind=kind, n_folds=n_folds,
                                     seed=seed, progress=bar)
    p = float(ds.tp.mean())
    out["naive_accuracy"] = max(p, 1.0 - p)
    return out


def greedy(ds: SegmentDataset, *, kind: str = "linear", score_kind: str = "xgboost",
           steps: int = 15, search_folds: int = 3, search_rows: int | None = 20000,
           n_folds: int = 10, seed: int = 0, quiet: bool = False) -> dict:
    """Greedy selection for both tasks (see the module doc): the search runs ``kind``
    models in ``search_folds`` grouped folds on ``search_rows`` random rows (None: all);
    ``score_kind`` then re-scores the selected set of every size on all rows in the
    ``n_folds`` folds of Table I (validation ACC, AUROC, AUPRC, R^2)."""
    rows = np.arange(len(ds))
    if search_rows and search_rows < len(ds):
        rows = np.sort(np.random.default_rng(seed).choice(len(ds), search_rows, replace=False))
    sub = ds.subset(rows)
    folds = meta_model.group_folds(ds.group, n_folds, seed=seed)
    out = {}
    for task in ("classification", "regression"):
        y = ds.tp.astype(float) if task == "classification" else ds.iou_adj
        bar = Progress(f"greedy {task}", steps, not quiet)
        g = meta_model.greedy_selection(sub.X, y[rows], ds.names, sub.group, task=task,
                                        kind=kind, n_folds=search_folds, max_features=steps,
                                        min_gain=-np.inf, seed=seed, progress=bar)
        rescore = []
        if score_kind:
            bar = Progress(f"greedy {task}: {score_kind} re-score", len(g.selected), not quiet)
            for k in range(1, len(g.selected) + 1):
                X = ds.columns(g.selected[:k])
                vals = []
                for tr, va in folds:
                    est = meta_model.fit_estimator(score_kind, task, X[tr], y[tr], seed=seed)
                    vals.append(task_metrics(task, y[va], meta_model.predict(est, task, X[va])))
                rescore.append({m: float(np.nanmean([v[m] for v in vals])) for m in vals[0]})
                bar(k)
        out[task] = {"selected": g.selected, "scores": g.scores, "metric": g.metric,
                     "all_features_score": g.all_features_score, "kind": kind,
                     "search_rows": len(rows), "search_folds": search_folds,
                     "rescore_kind": score_kind, "rescore_folds": n_folds, "rescore": rescore}
    return out


def heldout(train_ds: SegmentDataset, test_ds: SegmentDataset, models_dir, *,
            kind: str = "xgboost", seed: int = 0) -> dict:
    """Metrics of the shipped LMS models and of both baselines (fitted on ``train_ds``)
    on ``test_ds``; predictions under ``"pred"``."""
    cpath = Path(models_dir) / f"{PREFIX}_classifier.joblib"
    rpath = Path(models_dir) / f"{PREFIX}_regressor.joblib"
    models = meta_model.MetaModels(cpath, rpath, test_ds.names,
                                   settings=test_ds.info["settings"], method="lms")
    y, t = test_ds.tp.astype(float), test_ds.iou_adj
    pred = {"lms": models.predict(test_ds.X)}
    for s in FEATURE_SETS[1:]:
        names = feature_set(train_ds.names, s)
        clf, reg = fit_pair(train_ds, names, kind=kind, seed=seed)
        X = test_ds.columns(names)
        pred[s] = (meta_model.predict(clf, "classification", X),
                   meta_model.predict(reg, "regression", X))
    out = {s: {"classification": task_metrics("classification", y, c),
               "regression": task_metrics("regression", t, r)} for s, (c, r) in pred.items()}
    p = float(y.mean())
    out["naive_accuracy"] = max(p, 1.0 - p)
    out["model_ids"] = {"classifier": models.confidence_model_id,
                        "regressor": models.iou_model_id}
    out["pred"] = pred
    # LMS by predicted class: where the meta models work and where they do not
    by = []
    conf, piou = pred["lms"]
    for c in np.unique(test_ds.segment_class):
        m = test_ds.segment_class == c
        if m.sum() < 20:
            continue
        cm = task_metrics("classification", y[m], conf[m])
        rm = task_metrics("regression", t[m], piou[m])
        by.append({"class": test_ds.class_names[c], "n": int(m.sum()),
                   "tp_rate": float(y[m].mean()), "auroc": cm["auroc"], "r2": rm["r2"],
                   "mae": rm["mae"]})
    out["by_class"] = by
    return out


# -- figure 1 --------------------------------------------------------------------------


def _class_colors(class_names) -> np.ndarray:
    """The simulator's (SemanticKITTI) colours for its classes, else tab20."""
    try:
        from lidar_sim.classes import CLASS_NAMES, colors_rgb
    except ImportError:
        CLASS_NAMES = None
    if CLASS_NAMES is not None and tuple(class_names) == tuple(CLASS_NAMES):
        return colors_rgb(normalized=True)
    import matplotlib

    cmap = matplotlib.colormaps["tab20"]
    return np.array([cmap(k % 20)[:3] for k in range(len(class_names))])


def figure1(path, source, index: int, models_dir, settings, *, ignore_label=0,
            ring_from="points") -> dict:
    """The paper's figure 1 for frame ``index`` of ``source``: range image (front half)
    by ground truth, prediction, true and predicted IoU_adj (grey: not rated, SP < min),
    and the points in bird's eye view by true and predicted IoU_adj."""
    from matplotlib.colors import ListedColormap

    from lidar_quality_core.lms.segment_metrics import to_points

    inp, gt, res, iou, iou_adj = load_frame(source, index, settings, ignore_label=ignore_label,
                                            ring_from=ring_from)
    models = meta_model.MetaModels(Path(models_dir) / f"{PREFIX}_classifier.joblib",
                                   Path(models_dir) / f"{PREFIX}_regressor.joblib", res.names,
                                   settings=settings, method="lms")
    conf, piou = models.predict(res.features)
    R, C = res.source.shape
    cols = slice(C // 4, C - C // 4)                     # column C/2 looks forward (+x)
    colors = _class_colors(settings.class_names)
    cmap_cls = ListedColormap(colors)
    n = len(colors)

    # rows may run bottom-up (rings numbered from the lowest beam): show the sky on top
    z = res.image(np.asarray(inp.xyz)[:, 2].astype(np.float64))
    flip = bool(np.nanmean(z[: R // 4]) < np.nanmean(z[-(R // 4):])) if R >= 4 else False

    def crop(img):
        img = img[:, cols]
        return img[::-1] if flip else img

    def seg_image(vals):
        full = np.full(res.n_segments, np.nan)
        full[res.kept_ids] = vals
        return crop(np.where(res.segments >= 0, full[np.maximum(res.segments, 0)], np.nan))

    gt_img = crop(np.asarray(gt)[res.source])
    fig = rp.figure(13.0, 11.0)
    gs = fig.add_gridspec(6, 2, height_ratios=[1, 1, 1, 1, 0.1, 2.6])
    import matplotlib

    iou_cmap = matplotlib.colormaps["RdYlGn"].with_extremes(bad="0.6")
    panels = [(gt_img, cmap_cls, (-0.5, n - 0.5), "ground truth"),
              (crop(res.pred), cmap_cls, (-0.5, n - 0.5), "prediction (argmax)"),
              (seg_image(iou_adj), iou_cmap, (0, 1), "true IoU_adj per predicted segment"),
              (seg_image(piou), iou_cmap, (0, 1), "predicted IoU_adj (LidarMetaSeg)")]
    im = None
    for k, (img, cmap, (lo, hi), title) in enumerate(panels):
        ax = fig.add_subplot(gs[k, :])
        h = ax.imshow(img, cmap=cmap, vmin=lo, vmax=hi, interpolation="nearest",
                      aspect="auto")
        if k >= 2:
            im = h
        ax.set_title(title, fontsize=9, loc="left")
        ax.set_xticks([])
        ax.set_yticks([])
    ok = ~np.isnan(iou_adj)
    r2 = float(np.corrcoef(iou_adj[ok], piou[ok])[0, 1] ** 2) if ok.sum() > 2 else float("nan")
    true_pts = to_points(res, iou_adj)
    pred_pts = to_points(res, piou)
    xyz = np.asarray(inp.xyz)
    near = np.isfinite(xyz).all(axis=1) & (np.abs(xyz[:, 0]) < 40) & (np.abs(xyz[:, 1]) < 25)
    for k, (vals, title) in enumerate(((true_pts, "true IoU_adj"),
                                        (pred_pts, "predicted IoU_adj"))):
        ax = fig.add_subplot(gs[5, k])
        v = vals[near]
        rated = np.isfinite(v)
        ax.scatter(xyz[near][~rated, 0], xyz[near][~rated, 1], s=0.5, c="0.6", linewidths=0)
        ax.scatter(xyz[near][rated, 0], xyz[near][rated, 1], s=0.5, c=v[rated], cmap=iou_cmap,
                   vmin=0, vmax=1, linewidths=0)
        ax.set_aspect("equal")
        ax.set_xlim(-40, 40)
        ax.set_ylim(-25, 25)
        ax.set_title(f"bird's eye view (|x| < 40 m): {title}", fontsize=9)
        ax.set_xlabel("x [m]")
    if im is not None:
        fig.colorbar(im, ax=fig.axes[-2:], fraction=0.02, pad=0.01, label="IoU_adj")
    fig.suptitle(f"LidarMetaSeg on held-out {source.name}, frame {index}: range image "
                 f"(front 180°), {len(res.kept_ids)} rated segments, "
                 f"corr² true/pred {r2:.2f}", fontsize=10)
    fig.savefig(Path(path), dpi=90)
    return {"source": source.name, "frame": int(index), "n_segments": int(res.n_segments),
            "n_rated": int(len(res.kept_ids)), "corr2": r2}


# -- report ----------------------------------------------------------------------------


def _heldout_table(h: dict, auprc: str = "AUPRC") -> str:
    """Held-out ACC ... MAE of each feature set and the naive baseline."""
    rows = []
    for s in FEATURE_SETS:
        c, r = h[s]["classification"], h[s]["regression"]
        rows.append([SET_LABELS[s], _p(c["accuracy"]), _p(c["auroc"]), _p(c["auprc_fp"]),
                     c["ece"], c["mce"], _p(r["r2"]), r["mae"]])
    rows.append(["naive baseline", _p(h["naive_accuracy"])] + [""] * 6)
    return markdown_table(["", "ACC", "AUROC", auprc, "ECE", "MCE", "R²", "MAE"], rows)


def update_model_card(path: Path, res: dict) -> None:
    """Put the held-out table of ``res`` into the model card at ``path`` (section
    "Held-out evaluation", replaced if present, else before "Limits")."""
    h, te = res["heldout"], res["test_data"]
    sec = Section("Held-out evaluation", [
        f"`{res['command']}`: {te['n_segments']} segments of {te['n_frames']} frames of "
        f"{te['n_sequences']} sequences never used in training (true-positive rate "
        f"{_p(te['true_positive_rate'])}). Baselines fitted on the same training data.",
        _heldout_table(h, "AUPRC (false positives)")])
    o = res.get("heldout_other_rows")
    if o:
        c, r = o["classification"], o["regression"]
        how = ("the vertical field of view (segmentation cloud alone, no ring field)"
               if o["ring_from"] == "segmentation" else "the ring field")
        sec.add(f"With image rows from {how} instead: ACC {_p(c['accuracy'])}, "
                f"AUROC {_p(c['auroc'])}, R² {_p(r['r2'])}.")
    update_card(path, sec, before="Limits")


def _pct(ms) -> str:
    return "–" if ms is None or not np.isfinite(ms[0]) else f"{100 * ms[0]:.2f}% (±{100 * ms[1]:.2f}%)"


def _p(x) -> str:
    return "–" if x is None or not np.isfinite(x) else f"{100 * x:.2f}%"


def write_report(out: Path, res: dict) -> Path:
    """report.md from the summary ``res`` (see :func:`main`)."""
    L = ["# LidarMetaSeg evaluation", "",
         f"Command: `{res['command']}`", ""]
    tr, te = res["train_data"], res.get("test_data")
    L.append(f"Training data (meta_train): {tr['n_segments']} segments from {tr['n_frames']} "
             f"frames of {tr['n_sequences']} sequences; true-positive rate "
             f"{_p(tr['true_positive_rate'])}; folds over {tr['n_groups']} sub-sequences of "
             f"{tr['block_frames']} frames.")
    if te:
        L.append(f"Held-out data: {te['n_segments']} segments from {te['n_frames']} frames of "
                 f"{te['n_sequences']} sequences; true-positive rate "
                 f"{_p(te['true_positive_rate'])}.")
    L += ["", "Feature sets: **LMS** = all "
          f"{res['n_metrics']} metrics; **LMS w/o features** = without the {res['n_point_feature_metrics']} "
          "point-cloud feature-measure metrics (names matching "
          f"`{res['feature_measure_pattern']}`: mean / variance, interior / boundary / relative "
          "of the x, y, z, intensity and range heatmaps); **Entropy** = `mean_E` alone. "
          "Targets: IoU_adj > 0 (classification), IoU_adj (regression). AUPRC ranks false "
          "positives (IoU_adj = 0) as the positive class, as the paper.", ""]
    t1 = res["table1"]
    L += [f"## Table I: grouped {res['folds']}-fold cross validation on the training data "
          f"({res['kind']})", ""]
    rows = []
    for lab, task, key in (("ACC", "classification", "accuracy"),
                           ("AUROC", "classification", "auroc"),
                           ("AUPRC", "classification", "auprc_fp"), ("R²", "regression", "r2")):
        rows += [[lab, SET_LABELS[s], _pct(t1[s][task]["train"][key]),
                  _pct(t1[s][task]["val"][key])] for s in FEATURE_SETS]
        if key == "accuracy":
            rows.append(["ACC", "naive baseline", _p(t1["naive_accuracy"]), ""])
    L.append(markdown_table(["", "", "training", "validation"], rows).rstrip())
    if "heldout" in res:
        h = res["heldout"]
        L += ["", "## Held-out sequences (trained on all training data; LMS = the shipped "
              "models)", "", _heldout_table(h).rstrip()]
        o = res.get("heldout_other_rows")
        if o:
            c, r = o["classification"], o["regression"]
            how = ("the segmentation cloud alone (no ring: rows from the vertical field of "
                   "view, as the output of segmenter_node)" if o["ring_from"] == "segmentation"
                   else "the ring field of the points cloud")
            L += ["", f"The same LMS models with image rows from {how}, {o['n_segments']} "
                  f"held-out segments: ACC {_p(c['accuracy'])}, AUROC {_p(c['auroc'])}, "
                  f"AUPRC {_p(c['auprc_fp'])}, ECE {c['ece']:.3f}, R² {_p(r['r2'])}."]
        acc = res.get("acceptance", {})
        if acc:
            L += ["", f"Acceptance (held-out AUROC and R² of LMS above both baselines): "
                  f"**{'met' if acc['passed'] else 'NOT met'}** (AUROC {acc['auroc']:.4f} vs "
                  f"{acc['auroc_baselines']}, R² {acc['r2']:.4f} vs {acc['r2_baselines']})."]
        if h.get("by_class"):
            L += ["", "LMS held-out by predicted class:", "",
                  markdown_table(["class", "segments", "TP rate", "AUROC", "R²", "MAE"],
                                 [[b["class"], b["n"], _p(b["tp_rate"]), _p(b["auroc"]),
                                   _p(b["r2"]), b["mae"]] for b in h["by_class"]]).rstrip()]
    if "greedy" in res:
        g = res["greedy"]
        g0 = g["classification"]
        L += ["", "## Table II: greedy metric selection", "",
              f"Search: `{g0['kind']}` models (see the module doc of "
              f"`lidar_quality_training.lms.evaluate` for why) on {g0['search_rows']} random training "
              f"segments, {g0['search_folds']} "
              "grouped folds; criterion validation AUROC (classification) and R² "
              f"(regression); 'all' = every metric. Re-score: `{g0['rescore_kind']}` on all "
              f"segments in the {g0['rescore_folds']} folds of Table I (its 'all' = Table I's "
              "LMS validation mean).", ""]
        for task, crit in (("classification", "AUROC"), ("regression", "R²")):
            d = g[task]
            k = len(d["selected"])
            rows = [["added", *(f"`{n}`" for n in d["selected"]), "all"],
                    [f"{crit} ({d['kind']})", *map(_p, d["scores"]),
                     _p(d["all_features_score"])]]
            if d["rescore"]:
                key = "auroc" if task == "classification" else "r2"
                allv = res["table1"]["lms"][task]["val"][key][0]
                rows.append([f"{crit} ({d['rescore_kind']})",
                             *(_p(v[key]) for v in d["rescore"]), _p(allv)])
                if task == "classification":
                    alla = res["table1"]["lms"][task]["val"]["accuracy"][0]
                    rows.append([f"ACC ({d['rescore_kind']})",
                                 *(_p(v["accuracy"]) for v in d["rescore"]), _p(alla)])
            L.append(markdown_table([task, *map(str, range(1, k + 1)), "all"], rows))
    L += ["## Figures", ""]
    for name, cap in res["figures"].items():
        L += [f"![{cap}]({name})", "", f"*{cap}*", ""]
    path = out / "report.md"
    path.write_text("\n".join(L) + "\n")
    return path


def other_rows(a, settings) -> dict:
    """Held-out LMS metrics when the image rows come the other way (``--ring-from``
    swapped: the segmentation cloud alone, rows from the vertical field of view, as behind
    ``segmenter_node``; or the ring field): how much the shipped models depend on it."""
    from .dataset import build_dataset

    alt = "segmentation" if a.ring_from == "points" else "points"
    ds = build_dataset(a.test, settings, probabilities_root=a.probabilities,
                       ignore_label=None if a.ignore_label < 0 else a.ignore_label,
                       ring_from=alt, block_frames=a.block_frames,
                       cache_dir=Path(a.cache) if a.cache else None, quiet=a.quiet,
                       topics=dict(a.topic))
    models = meta_model.MetaModels(a.models / f"{PREFIX}_classifier.joblib",
                                   a.models / f"{PREFIX}_regressor.joblib", ds.names,
                                   settings=settings, method="lms")
    conf, piou = models.predict(ds.X)
    return {"ring_from": alt, "n_segments": len(ds),
            "classification": task_metrics("classification", ds.tp.astype(float), conf),
            "regression": task_metrics("regression", ds.iou_adj, piou)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="lms-eval", description=__doc__.split("\n\n")[0])
    ap.add_argument("--train", type=Path, nargs="+",
                    default=[Path("data/perception/meta_train")],
                    help="training data (cross validation, baselines)")
    ap.add_argument("--test", type=Path, nargs="*", default=[Path("data/perception/meta_test")],
                    help="held-out data (none: CV only)")
    ap.add_argument("--models", type=Path, default=Path("models/lms"),
                    help="directory of lms_classifier/regressor.joblib (held-out LMS)")
    ap.add_argument("--out", type=Path, default=Path("out/lms_eval"))
    ap.add_argument("--kind", choices=meta_model.KINDS, default="xgboost")
    ap.add_argument("--folds", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--greedy-steps", type=int, default=15, help="0: no Table II")
    ap.add_argument("--greedy-kind", choices=meta_model.KINDS, default="linear")
    ap.add_argument("--greedy-folds", type=int, default=3,
                    help="grouped folds of the greedy search")
    ap.add_argument("--greedy-rows", type=int, default=20000,
                    help="random segments the greedy search runs on (0: all)")
    ap.add_argument("--figure-frame", type=int, default=20,
                    help="frame of the first held-out sequence shown in figure1.png")
    ap.add_argument("--model-card", action="store_true",
                    help="write the held-out table into <models>/MODEL_CARD.md")
    ap.add_argument("--docs-figure", type=Path, default=None,
                    help="also copy figure1.png there (e.g. docs/lms_quality.png)")
    add_data_arguments(ap)
    a = ap.parse_args(argv)
    t_start = time.monotonic()
    out = a.out
    out.mkdir(parents=True, exist_ok=True)
    import shlex

    res: dict = {"command": "lms-eval " + " ".join(
        shlex.quote(x) for x in (sys.argv[1:] if argv is None else argv)),
        "kind": a.kind, "folds": a.folds, "figures": {}}
    settings = settings_from_args(a)
    train_ds = dataset_from_args(a, a.train)
    from .train import FEATURE_MEASURE_PATTERN

    res["train_data"] = data_summary(train_ds)
    res["n_metrics"] = len(train_ds.names)
    res["n_point_feature_metrics"] = len(train_ds.names) - len(
        feature_set(train_ds.names, "no_features"))
    res["feature_measure_pattern"] = FEATURE_MEASURE_PATTERN.pattern
    res["feature_sets"] = {s: feature_set(train_ds.names, s) for s in FEATURE_SETS}

    t1 = table1(train_ds, kind=a.kind, n_folds=a.folds, seed=a.seed, quiet=a.quiet)
    y_tr = train_ds.tp.astype(float)
    rp.reliability_png(out / "reliability_cv.png",
                       {SET_LABELS[s]: (y_tr, np.clip(t1[s]["oof"]["classification"], 0, 1))
                        for s in FEATURE_SETS},
                       title="Meta classification, CV validation folds (training data)")
    rp.scatter_png(out / "scatter_cv.png", train_ds.iou_adj,
                   np.clip(t1["lms"]["oof"]["regression"], 0, 1), xlabel="true IoU_adj",
                   ylabel="predicted IoU_adj", title="LMS, CV validation folds")
    res["figures"]["reliability_cv.png"] = ("Reliability diagrams of the meta classifiers, "
                                            "out-of-fold predictions on the training data")
    res["figures"]["scatter_cv.png"] = "True vs predicted IoU_adj (LMS, out-of-fold)"
    res["table1"] = {s: {task: {k: t1[s][task][k] for k in ("train", "val")}
                         for task in ("classification", "regression")} for s in FEATURE_SETS}
    res["table1"]["naive_accuracy"] = t1["naive_accuracy"]

    if a.test:
        test_ds = dataset_from_args(a, a.test)
        res["test_data"] = data_summary(test_ds)
        h = heldout(train_ds, test_ds, a.models, kind=a.kind, seed=a.seed)
        pred = h.pop("pred")
        res["heldout"] = h
        y_te = test_ds.tp.astype(float)
        rp.reliability_png(out / "reliability_heldout.png",
                           {SET_LABELS[s]: (y_te, np.clip(pred[s][0], 0, 1)) for s in FEATURE_SETS},
                           title="Meta classification, held-out sequences")
        rp.scatter_png(out / "scatter_heldout.png", test_ds.iou_adj, pred["lms"][1],
                       xlabel="true IoU_adj", ylabel="predicted IoU_adj",
                       title="LMS, held-out")
        res["figures"]["reliability_heldout.png"] = ("Reliability diagrams, held-out "
                                                     "sequences (LMS = shipped model)")
        res["figures"]["scatter_heldout.png"] = "True vs predicted IoU_adj, held-out (LMS)"
        lms = h["lms"]
        base = {s: h[s] for s in FEATURE_SETS[1:]}
        res["acceptance"] = {
            "auroc": lms["classification"]["auroc"], "r2": lms["regression"]["r2"],
            "auroc_baselines": {s: round(b["classification"]["auroc"], 4) for s, b in base.items()},
            "r2_baselines": {s: round(b["regression"]["r2"], 4) for s, b in base.items()},
            "passed": bool(all(lms["classification"]["auroc"] > b["classification"]["auroc"]
                               and lms["regression"]["r2"] > b["regression"]["r2"]
                               for b in base.values()))}
        if any(s.kind == "bag" for p in a.test
               for s in discover_sources(p, a.probabilities, dict(a.topic))):
            res["heldout_other_rows"] = other_rows(a, settings)
        src = discover_sources(a.test[0], a.probabilities, dict(a.topic))[0]
        res["figure1"] = figure1(out / "figure1.png", src, a.figure_frame, a.models, settings,
                                 ignore_label=None if a.ignore_label < 0 else a.ignore_label,
                                 ring_from=a.ring_from)
        res["figures"]["figure1.png"] = ("Paper figure 1 on a held-out scan: range image by "
                                         "ground truth, prediction, true and predicted IoU_adj "
                                         "(grey: SP < 10, not rated); bird's eye view below")
        if a.docs_figure:
            a.docs_figure.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(out / "figure1.png", a.docs_figure)
        if a.model_card:
            update_model_card(a.models / "MODEL_CARD.md", res)

    if a.greedy_steps > 0:
        g = greedy(train_ds, kind=a.greedy_kind, score_kind=a.kind, steps=a.greedy_steps,
                   search_folds=a.greedy_folds, search_rows=a.greedy_rows or None,
                   n_folds=a.folds, seed=a.seed, quiet=a.quiet)
        res["greedy"] = g
        for task, key in (("classification", "AUROC"), ("regression", "R²")):
            d = g[task]
            rp.curve_png(out / f"greedy_{task}.png", d["selected"], d["scores"],
                         ylabel=f"validation {key} ({d['kind']})",
                         title=f"Greedy selection, meta {task}")
            res["figures"][f"greedy_{task}.png"] = f"Greedy selection ({task})"
    res["seconds"] = round(time.monotonic() - t_start, 1)
    write_report(out, res)
    (out / "summary.json").write_text(json.dumps(jsonable(res), indent=2) + "\n")
    if not a.quiet:
        sys.stderr.write(f"wrote {out / 'report.md'}, {out / 'summary.json'}\n")
    if "acceptance" in res and not a.quiet:
        acc = res["acceptance"]
        print(f"held-out LMS: AUROC {acc['auroc']:.4f} (baselines {acc['auroc_baselines']}), "
              f"R2 {acc['r2']:.4f} (baselines {acc['r2_baselines']}); acceptance "
              f"{'met' if acc['passed'] else 'NOT met'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
