"""``mimo-train``: the LiDAR-MIMO meta classifier (confidence) and regressor (predicted IoU).

    mimo-train --data data/perception/meta_train --out models/mimo --cache data/cache/mimo

Two pairs, both over the merged clusters of the perception bags (``dataset.py``, the node's
own features): ``mimo`` on the cluster statistics (``MimoSettings().feature_names()``) and
``mimo_points`` with the LMD own-box point features of the merged box as well
(``use_points=True``). Classifier target: BEV IoU with the best ground-truth box of the
detection's class >= 0.5; regressor target: that IoU. Estimator: ``meta_model`` kind
(XGBoost by default). Before the final fit on all data, grouped cross validation over the
sequences (``--cv-folds``, alias ``--folds``) gives the metrics written into the manifests
and ``MODEL_CARD.md`` (``mimo-eval --model-card`` adds the held-out evaluation to the
card). ``--cv-folds 0`` trains without it (said in manifests and card); it needs at least
two sequences (bags), so one bag trains with ``--cv-folds 0`` and otherwise ends with the
reason (exit 2, no traceback), as for other bad data. Each pair's manifest records the
merge settings with its own ``use_points``; the card names the bags and calls them
simulated only when they are the project's (``meta_model.simulated_sources``).

Feature tables (``lidar_quality_training.feature_table``): ``--features PATH`` (files,
directories, globs; repeatable) trains on Parquet tables instead of ``--data``, with the
settings they record: tables of mode ``points`` train both pairs, ``no_points`` tables
(``process_bags`` with ``use_points: false``) the ``mimo`` pair only. ``--export-features
DIR`` writes the dataset as ``DIR/mimo_points.parquet`` (``--export-only``: and stops).
``--scheduler ADDRESS`` fits the XGBoost models, folds included, with ``xgboost.dask`` on a
Dask cluster (``lidar_quality_training.distributed_training``); the files are the same kind.
"""
from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from lidar_quality_core import meta_model
from lidar_quality_core import metrics as qm
from lidar_quality_core.model_store import ModelStoreError
from lidar_quality_core.progress import Progress
from lidar_quality_ros.perception_bag import add_topic_option
from mimo_ros.pipeline import MimoSettings

from .. import feature_table
from ..distributed_training import (LocalTraining, add_scheduler_option, check_scheduler,
                                    training_backend)
from ..report import ModelCard, Section, code_block, markdown_table
from .dataset import TP_IOU, MimoDataset, load_bags

__all__ = ["PREFIXES", "train_pair", "train", "model_card", "heldout_section", "main",
           "CARD_BEGIN", "CARD_END"]

PREFIXES = {False: "mimo", True: "mimo_points"}
CARD_BEGIN, CARD_END = "<!-- mimo-eval:begin -->", "<!-- mimo-eval:end -->"


def _cv_summary(cv: meta_model.CVResult) -> dict:
    ms = cv.mean_std()
    return {"cv_folds": len(cv.folds), "cv_val": {k: list(v) for k, v in ms["val"].items()},
            "cv_train": {k: list(v) for k, v in ms["train"].items()}}


def train_pair(ds: MimoDataset, use_points: bool, out_dir, *, kind: str = "xgboost",
               folds: int = 6, seed: int = 0, progress=None, backend=None) -> dict:
    """Cross-validate and fit one classifier + regressor pair by ``backend``
    (``distributed_training``, default this machine); save it under ``out_dir``.
    Returns the metrics and paths."""
    backend = backend or LocalTraining()
    X, names = ds.features(use_points)
    y_cls, y_iou = ds.tp.astype(float), ds.m_iou_class
    groups = ds.group
    res = {"prefix": PREFIXES[use_points], "features": list(names), "n": int(len(X)),
           "positive_rate": float(y_cls.mean()) if len(X) else float("nan")}
    folds = meta_model.cv_fold_count(groups, folds, what="sequences (bags)")
    if folds:
        cv_c = meta_model.cross_validate(X, y_cls, groups, task="classification", kind=kind,
                                         n_folds=folds, seed=seed, progress=progress,
                                         fold_fitter=backend.fit_folds)
        cv_r = meta_model.cross_validate(X, y_iou, groups, task="regression", kind=kind,
                                         n_folds=folds, seed=seed, progress=progress,
                                         fold_fitter=backend.fit_folds)
        res["classifier_cv"], res["regressor_cv"] = _cv_summary(cv_c), _cv_summary(cv_r)
    clf = backend.fit(kind, "classification", X, y_cls, seed=seed)
    reg = backend.fit(kind, "regression", X, y_iou, seed=seed)
    training = {"sources": [s["path"] for s in ds.info.get("sources", [])],
                "groups": ds.groups, "frames": int(ds.n_frames), "rows": int(len(X)),
                "classifier_target": f"BEV IoU with the best GT box of the detection's class "
                                     f">= {TP_IOU}", "regressor_target": "that IoU",
                "kind": kind, "seed": seed, "cv_folds": folds,
                "merge_settings": {**(ds.info.get("settings") or {}), "use_points": use_points},
                "data": _data(ds)}
    if not folds:
        training["cross_validation"] = "skipped: --cv-folds 0"
    if backend.record():
        training["fitted_on"] = backend.record()
    profile = meta_model.training_profile(X, names, {"detector score": ds.m_score},
                                          groups=groups,
                                          extra_groups={"detector score": groups})
    cpath, rpath = meta_model.save_pair(out_dir, res["prefix"], clf, reg, names,
                                        training_data=training, domain_profile=profile,
                                        classifier_metrics=res.get("classifier_cv"),
                                        regressor_metrics=res.get("regressor_cv"))
    res["paths"] = [str(cpath), str(rpath)]
    return res


def _data(ds: MimoDataset) -> dict:
    """``{"sources": [{"kind": "perception_bag" | "feature_table", "path"}],
    "simulated"}``."""
    src = [{"kind": s.get("kind", "perception_bag"), "path": s["path"]}
           for s in ds.info.get("sources", [])]
    bags = [s["path"] for s in src if s["kind"] == "perception_bag"]
    return {"sources": src,
            "simulated": len(bags) == len(src) and meta_model.simulated_sources(bags)}


def _baseline(ds: MimoDataset) -> dict:
    """The merged score as a confidence / IoU predictor (no model): reference figures."""
    y = ds.tp.astype(float)
    return {"auroc": qm.auroc(y, ds.m_score), "ece": qm.ece(y, np.clip(ds.m_score, 0, 1)),
            "iou_r2": qm.r2(ds.m_iou_class, ds.m_score)}


def train(data: Sequence, out_dir, *, cache_dir=None, kind: str = "xgboost", folds: int = 6,
          seed: int = 0, quiet: bool = False, command: str = "",
          topics: dict | None = None, backend=None) -> dict:
    """Load the bags (``topics``: their topic names by key), train both pairs, write the
    model card. Returns the summary."""
    t0 = time.monotonic()
    ds = load_bags(data, cache_dir=cache_dir, progress=not quiet, topics=topics)
    return train_dataset(ds, out_dir, kind=kind, folds=folds, seed=seed, quiet=quiet,
                         command=command, backend=backend, t0=t0)


def train_dataset(ds: MimoDataset, out_dir, *, kind: str = "xgboost", folds: int = 6,
                  seed: int = 0, quiet: bool = False, command: str = "", backend=None,
                  t0: float | None = None) -> dict:
    """Train the pairs ``ds`` has the features of (both, or ``mimo`` only without the
    point features), write the model card. Returns the summary."""
    t0 = time.monotonic() if t0 is None else t0
    if len(ds) == 0:
        raise ValueError(f"no merged detections in the training data ({ds.n_frames} frames)")
    meta_model.cv_fold_count(ds.group, folds, what="sequences (bags)")  # before any fit
    if not folds and not quiet:
        sys.stderr.write("no cross validation (--cv-folds 0)\n")
    out = Path(out_dir)
    summary = {"data": ds.summary(), "baseline_merged_score": _baseline(ds), "pairs": [],
               "heads": (ds.info.get("settings") or {}).get("num_heads"),
               "sources": _data(ds)}
    with_points = len(ds.feature_names) > len(MimoSettings(use_points=False).feature_names())
    for use_points in (False, True)[:2 if with_points else 1]:
        bar = Progress(f"{PREFIXES[use_points]}: cross validation folds", None, not quiet)
        summary["pairs"].append(train_pair(ds, use_points, out, kind=kind, folds=folds,
                                           seed=seed, progress=bar, backend=backend))
    summary["seconds"] = time.monotonic() - t0
    (out / "MODEL_CARD.md").write_text(model_card(summary, command))
    return summary


def _fmt_ms(d: dict | None, key: str) -> str:
    if not d or key not in d.get("cv_val", {}):
        return "–"
    m, s = d["cv_val"][key]
    return f"{m:.3f} ± {s:.3f}"


def model_card(summary: dict, command: str = "") -> str:
    """``MODEL_CARD.md`` of the trained pairs (the held-out section is mimo-eval's)."""
    from mimo_ros.pipeline import POINT_FEATURES, STAT_FEATURES

    d = summary["data"]
    base = summary["baseline_merged_score"]
    rows = []
    for p in summary["pairs"]:
        c, r = p.get("classifier_cv"), p.get("regressor_cv")
        rows.append([p["prefix"], len(p["features"]), _fmt_ms(c, "auroc"), _fmt_ms(c, "ece"),
                     _fmt_ms(c, "auprc"), _fmt_ms(r, "r2"), _fmt_ms(r, "mae")])
    folds = next((p["classifier_cv"]["cv_folds"] for p in summary["pairs"]
                  if "classifier_cv" in p), 0)
    src = summary.get("sources") or {"sources": [], "simulated": False}
    bags = ", ".join(f"`{s['path']}`" for s in src["sources"])
    if src["simulated"]:
        data_line = (f"Simulated perception bags (`lidar_sim` scenes, reference perception with "
                     f"{summary.get('heads')} heads; `make meta-data`): {bags}.")
        trained_on = "simulated scans and the reference multi-head detector"
    elif any(s["kind"] == "feature_table" for s in src["sources"]):
        data_line = (f"Feature tables (Parquet) of perception bags with {summary.get('heads')} "
                     f"detector heads: {bags}.")
        trained_on = "the bags of the feature tables named above (their heads and scenes)"
    else:
        data_line = f"Perception bags with {summary.get('heads')} detector heads: {bags}."
        trained_on = "the perception bags named above (their detector heads and scenes)"
    card = ModelCard("LiDAR-MIMO meta models (`models/mimo`)", [
        "Meta classifier (confidence = P(the merged detection is a true positive)) and meta "
        "regressor (predicted BEV IoU with the best ground-truth box of its class) of "
        "`mimo_node`, over the merged clusters of the reference multi-head detector "
        "(`mimo_ros.pipeline`: consensus DBSCAN on 1 - BEV IoU, mean merge, SE / AE / MI, "
        "ETV / ATV and per-parameter variances, merged score, class, range).",
        markdown_table(["files", "features", "used when"], [
            ["`mimo_classifier.joblib`, `mimo_regressor.joblib` (+ `.manifest.json`)",
             f"the {len(STAT_FEATURES)} cluster statistics", "default (`use_points: false`)"],
            ["`mimo_points_classifier.joblib`, `mimo_points_regressor.joblib` (+ manifests)",
             f"the same + {len(POINT_FEATURES)} LMD own-box point features of the merged box",
             "`use_points: true`"]])])
    card.section(
        "Training data", data_line,
        f"{d['groups']} sequences, {d['frames']} frames, "
        f"{d['merged']} merged detections of which {d['merged_tp']} are TPs "
        f"(BEV IoU >= {TP_IOU} with a ground-truth box of their class), {d['gt_boxes']} "
        "ground-truth boxes. Sources and settings are in the manifests (`training_data`).")
    card.section(
        "Models",
        "XGBoost (`lidar_quality_core.meta_model`, kind `xgboost`: 300 trees, depth 4, "
        "learning rate 0.05), fitted on all training sequences. Missing values (e.g. point "
        "features without a cloud) go the learnt default way.",
        (f"Grouped cross validation over the sequences ({folds} folds, mean ± std of the "
         "validation folds):" if folds else
         "No cross validation (`--cv-folds 0`): the table is empty."),
        markdown_table(["pair", "features", "AUROC", "ECE", "AUPRC", "IoU R²", "IoU MAE"],
                       rows),
        f"For reference, the merged score itself on the training data: AUROC "
        f"{base['auroc']:.3f}, ECE {base['ece']:.3f}, as IoU predictor R² {base['iou_r2']:.3f}.")
    card.section(
        "Limits",
        f"Trained on {trained_on} only: another detector, sensor or scene distribution needs "
        "retraining (`mimo-train` on its own perception bags). The confidence is calibrated "
        "for the merge settings in the manifests (`training_data.merge_settings`); the node "
        "refuses another class list or `use_points` and warns about other merge settings, "
        "which change the clusters.")
    card.section("Reproduce", code_block(
        command or "mimo-train --data data/perception/meta_train --out models/mimo"))
    card.sections.append(heldout_section(
        "Not evaluated yet: run `mimo-eval ... --model-card models/mimo/MODEL_CARD.md`."))
    return card.render()


def heldout_section(*blocks: str) -> Section:
    """The card's "Held-out evaluation" section (``mimo-eval --model-card`` replaces it),
    its text between the mimo-eval markers."""
    body = "\n\n".join(b.strip("\n") for b in blocks)
    return Section("Held-out evaluation", [f"{CARD_BEGIN}\n{body}\n{CARD_END}"])


def add_data_arguments(p: argparse.ArgumentParser, default_data: str | None) -> None:
    p.add_argument("--data", nargs="+", default=None if default_data is None else [default_data],
                   help="perception bags or directories of bags (one sequence per bag)"
                        + (f" (default: {default_data})" if default_data else ""))
    p.add_argument("--cache", default="data/cache/mimo",
                   help="dataset cache directory ('' = no cache)")
    add_topic_option(p)
    p.add_argument("--quiet", action="store_true", help="no progress output")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="mimo-train", description=__doc__.split("\n\n")[0])
    add_data_arguments(p, None)
    feature_table.add_table_arguments(p, instead_of="--data",
                                      export_to="DIR/mimo_points.parquet")
    p.add_argument("--out", default="models/mimo", help="model directory")
    p.add_argument("--kind", default="xgboost", choices=meta_model.KINDS)
    p.add_argument("--cv-folds", "--folds", dest="folds", type=meta_model.cv_folds_arg,
                   default=6, help="grouped CV folds over the sequences (0: no CV)")
    p.add_argument("--seed", type=int, default=0)
    add_scheduler_option(p)
    a = p.parse_args(argv)
    feature_table.check_table_arguments(p, a)
    command = "mimo-train " + " ".join(shlex.quote(x) for x in (argv if argv is not None
                                                               else sys.argv[1:]))
    try:
        check_scheduler(a.scheduler, a.kind)  # before reading any data
        t0 = time.monotonic()
        if a.features:
            if a.data is not None:
                raise ValueError("--features replaces --data: give one source of training "
                                 "data")
            ds = feature_table.read_mimo(a.features)
            left = ds.info["rows_without_targets"], ds.info["rows_invalid"]
            if any(left) and not a.quiet:
                sys.stderr.write(f"feature tables: {left[0]} rows without targets and "
                                 f"{left[1]} invalid rows left out\n")
        else:
            ds = load_bags(a.data or ["data/perception/meta_train"], cache_dir=a.cache or None,
                           progress=not a.quiet, topics=dict(a.topic))
        if a.export_features is not None:
            for path in feature_table.export_tables(ds, a.export_features):
                print(f"wrote {path}")
            if a.export_only:
                return 0
        with training_backend(a.scheduler, a.kind) as backend:
            s = train_dataset(ds, a.out, kind=a.kind, folds=a.folds, seed=a.seed,
                              quiet=a.quiet, command=command, backend=backend, t0=t0)
    except (ValueError, OSError, ModelStoreError) as exc:  # bad data: say why, no traceback
        print(f"mimo-train: {exc}", file=sys.stderr)
        return 2
    d = s["data"]
    print(f"mimo-train: {d['groups']} sequences, {d['frames']} frames, {d['merged']} merged "
          f"detections ({d['merged_tp']} TP) in {s['seconds']:.0f} s")
    for pr in s["pairs"]:
        c, r = pr.get("classifier_cv"), pr.get("regressor_cv")
        print(f"  {pr['prefix']:12s} AUROC {_fmt_ms(c, 'auroc')}  ECE {_fmt_ms(c, 'ece')}  "
              f"IoU R² {_fmt_ms(r, 'r2')}  -> {', '.join(pr['paths'])}")
    print(f"  wrote {Path(a.out) / 'MODEL_CARD.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
