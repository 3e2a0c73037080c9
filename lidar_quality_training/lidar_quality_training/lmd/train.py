"""``lmd-train``: fit the LMD meta classifier (confidence, TP iff IoU_BEV >= 0.5) and meta
regressor (IoU_BEV) for every proposal mode and save them where the node looks for them.

    lmd-train --train data/perception/meta_train --test data/perception/meta_test --out models/lmd

Per mode (``exact``, ``threshold``, ``none``: all three are shipped so that the node runs
in every mode) the pair is fitted on all training rows and saved with
``meta_model.save_pair`` as ``lmd_<mode>_classifier.joblib`` / ``lmd_<mode>_regressor.joblib``
with manifests (feature schema = ``LmdSettings.feature_names()``; training data: sources
(bag paths or the KITTI directory), frames, boxes, settings; metrics: grouped cross
validation over the training sequences and, with held-out data, the held-out figures next
to the detector score's). ``--cv-folds 0`` trains without cross validation (said in the
manifests and the card); cross validation needs at least two sequences, so a single bag
trains with ``--cv-folds 0`` (otherwise: an error saying so). ``MODEL_CARD.md`` in the
output directory summarises data, features and metrics; it calls the data simulated only
when it is the project's (``meta_model.simulated_sources``). Seeds are fixed and
estimators run single-threaded by default, so one command reproduces the models. The
pickles are zlib-compressed (joblib level 3: XGBoost pairs ~0.23 MB instead of ~0.97 MB).
Bad data (no boxes, one class only, one sequence with cross validation) ends with a
message and exit code 2, no traceback.

Feature tables (``lidar_quality_training.feature_table``): ``--features PATH`` (files,
directories, globs; repeatable) trains on Parquet tables from ``process_bags`` or
``--export-features`` instead of bags / KITTI, one pair per mode found in them (or
``--modes``), with the settings the tables record; held-out data then comes from
``--test-features`` (or ``--test`` bags, read with the tables' settings), never from the
default ``meta_test``. ``--test-features`` also works beside bags (same settings
required). ``--export-features DIR`` writes the datasets the builders made as
``DIR/train/lmd_<mode>.parquet`` (and ``DIR/test/...``), ``--export-only`` stops there.
The manifests name the tables as the training data. ``--scheduler ADDRESS`` fits the
XGBoost models, cross-validation folds included, with ``xgboost.dask`` on a Dask cluster
(``lidar_quality_training.distributed_training``); the files are the same kind.
"""
from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np

from lidar_quality_core import meta_model
from lidar_quality_core import metrics as M
from lidar_quality_core.model_store import ModelStoreError

from .. import feature_table
from ..distributed_training import (LocalTraining, add_scheduler_option, check_scheduler,
                                    training_backend)
from ..report import ModelCard, bullets, code_block, fmt, markdown_table, round_floats
from .dataset import (TP_IOU, LmdDataset, Progress, add_source_args, load_from_args,
                      settings_for, settings_from_args)

__all__ = ["MODES", "fit_pair", "classification_metrics", "regression_metrics",
           "cv_metrics", "train", "main"]

MODES = ("exact", "threshold", "none")
DEFAULT_OUT = Path("models/lmd")


def fit_pair(ds: LmdDataset, kind: str = "xgboost", *, seed: int = 0, n_jobs: int = 1,
             columns=None, backend=None):
    """(classifier, regressor) of ``kind`` fitted on ``ds`` (all features, or ``columns``)
    by ``backend`` (``distributed_training``; default this machine)."""
    backend = backend or LocalTraining()
    X = ds.X if columns is None else ds.columns(columns)
    clf = backend.fit(kind, "classification", X, ds.tp.astype(float), seed=seed,
                      n_jobs=n_jobs)
    reg = backend.fit(kind, "regression", X, ds.iou, seed=seed, n_jobs=n_jobs)
    return clf, reg


def classification_metrics(tp, conf) -> dict:
    """accuracy, AUROC, AUPRC, Brier, ECE, MCE (10 bins) of confidences ``conf``."""
    s = M.summary(np.asarray(tp, float), np.clip(conf, 0.0, 1.0))
    return {k: s[k] for k in ("accuracy", "auroc", "auprc", "brier", "ece", "mce")}


def regression_metrics(iou, pred) -> dict:
    """R^2 and MAE of predicted IoUs (clipped to [0, 1], as the node outputs them)."""
    p = np.clip(pred, 0.0, 1.0)
    return {"r2": M.r2(iou, p), "mae": M.mae(iou, p)}


def cv_metrics(ds: LmdDataset, kind: str, *, n_folds: int, seed: int = 0, n_jobs: int = 1,
               columns=None, progress=None, backend=None) -> dict:
    """Grouped (by sequence) cross validation: ``{"classification" | "regression":
    {metric: [mean, std]}}`` over the validation folds, plus the out-of-fold predictions;
    the fold models fitted by ``backend`` (default this machine)."""
    backend = backend or LocalTraining()
    X = ds.X if columns is None else ds.columns(columns)
    out = {}
    for task, y in (("classification", ds.tp.astype(float)), ("regression", ds.iou)):
        res = meta_model.cross_validate(X, y, ds.group, task=task, kind=kind, n_folds=n_folds,
                                        seed=seed, n_jobs=n_jobs, progress=progress,
                                        fold_fitter=backend.fit_folds)
        out[task] = {k: [float(v[0]), float(v[1])] for k, v in res.mean_std()["val"].items()}
        out[task + "_oof"] = res.oof
    return out




def _sources(ds: LmdDataset) -> list[str]:
    return [s.get("group") or s.get("path") for s in ds.info.get("sources", [])]


def _data(ds: LmdDataset) -> dict:
    """Where ``ds`` comes from: ``{"sources": [bag, KITTI or feature table source dicts],
    "simulated": bool}`` (the model card's data section)."""
    src = [dict(s) for s in ds.info.get("sources", [])]
    bags = [s["path"] for s in src if s.get("kind") == "perception_bag"]
    return {"sources": src,
            "simulated": len(bags) == len(src) and meta_model.simulated_sources(bags)}


def _check_trainable(ds: LmdDataset, mode: str) -> None:
    if not len(ds):
        raise ValueError(f"mode {mode}: no scored box with ground truth in the training data "
                         f"({ds.n_frames} frames, {ds.info.get('frames_without_gt', 0)} "
                         "skipped without ground truth)")


def train(train_sets: dict, test_sets: dict | None, out: Path, *, kind: str = "xgboost",
          seed: int = 0, n_jobs: int = 1, cv_folds: int = 4, command: str = "",
          progress: bool = True, backend=None) -> dict:
    """Fit, evaluate and save one pair per mode of ``train_sets``; returns the metrics.
    ``backend`` fits the models (``distributed_training``; default this machine)."""
    backend = backend or LocalTraining()
    out = Path(out)
    results = {}
    n_folds = {}
    for mode, ds in train_sets.items():  # every mode's problem before any fit
        _check_trainable(ds, mode)
        n_folds[mode] = meta_model.cv_fold_count(ds.group, cv_folds, what="sequences (groups)")
    for mode, ds in train_sets.items():
        folds = n_folds[mode]
        t0 = time.monotonic()
        if progress:
            sys.stderr.write(f"mode {mode}: {len(ds)} boxes, {ds.X.shape[1]} features\n")
        cmet, rmet = {}, {}
        if folds:
            bar = Progress(f"  grouped CV ({kind})", 2 * folds, progress)
            cv = cv_metrics(ds, kind, n_folds=folds, seed=seed, n_jobs=n_jobs,
                            progress=lambda *_: bar.update(), backend=backend)
            bar.close()
            cmet["cv"], rmet["cv"] = cv["classification"], cv["regression"]
        elif progress:
            sys.stderr.write("  no cross validation (--cv-folds 0)\n")
        clf, reg = fit_pair(ds, kind, seed=seed, n_jobs=n_jobs, backend=backend)
        held = None
        if test_sets is not None and mode in test_sets and len(test_sets[mode]):
            te = test_sets[mode]
            conf = meta_model.predict(clf, "classification", te.X)
            pred = meta_model.predict(reg, "regression", te.X)
            cmet["held_out"] = classification_metrics(te.tp, conf)
            cmet["held_out_detector_score"] = classification_metrics(te.tp, te.score)
            rmet["held_out"] = regression_metrics(te.iou, pred)
            held = {"sources": _sources(te), **te.summary(), "data": _data(te)}
        target = ("IoU_BEV with the best ground-truth box of the same class" if ds.class_aware
                  else "IoU_BEV with the best ground-truth box of any class")
        training = {"sources": _sources(ds), **ds.summary(),
                    "target": target, "tp_rule": f"IoU_BEV >= {TP_IOU}",
                    "settings": ds.info.get("settings"), "kind": kind, "seed": seed,
                    "cv_folds": folds, "command": command, "held_out": held,
                    "data": _data(ds)}
        if not folds:
            training["cross_validation"] = "skipped: --cv-folds 0"
        if backend.record():
            training["fitted_on"] = backend.record()
        known = ds.frame_points >= 0                     # -1: unknown (feature tables)
        profile = meta_model.training_profile(ds.X, ds.feature_names, {
            "detector score": ds.score, "points per frame": ds.frame_points[known]},
            groups=ds.group, extra_groups={"detector score": ds.group,
                                           "points per frame": ds.frame_group[known]})
        cpath, rpath = meta_model.save_pair(out, f"lmd_{mode}", clf, reg, ds.feature_names,
                                            training_data=round_floats(training),
                                            classifier_metrics=round_floats(cmet),
                                            regressor_metrics=round_floats(rmet), compress=3,
                                            domain_profile=round_floats(profile))
        results[mode] = {"training": training, "classifier": cmet, "regressor": rmet,
                         "n_features": len(ds.feature_names),
                         "files": [str(cpath), str(rpath)],
                         "bytes": cpath.stat().st_size + rpath.stat().st_size,
                         "seconds": time.monotonic() - t0}
        if progress:
            h = cmet.get("held_out", {})
            sys.stderr.write(f"  saved {cpath.name}, {rpath.name} "
                             f"({results[mode]['bytes'] / 1e3:.0f} kB); held-out AUROC "
                             f"{h.get('auroc', float('nan')):.4f}, ECE "
                             f"{h.get('ece', float('nan')):.4f}, R^2 "
                             f"{rmet.get('held_out', {}).get('r2', float('nan')):.4f}\n")
    return results


def _source_items(data: dict | None, label: str) -> list[str]:
    """Card bullets naming where ``label`` data came from (``_data``)."""
    if not data:
        return []
    out = []
    bags = [s["path"] for s in data["sources"] if s.get("kind") == "perception_bag"]
    if bags:
        out.append(f"{label} perception bags: {', '.join(f'`{b}`' for b in bags)}.")
    tables = [s["path"] for s in data["sources"] if s.get("kind") == "feature_table"]
    if tables:
        out.append(f"{label} feature tables (Parquet): {', '.join(f'`{t}`' for t in tables)}.")
    for s in data["sources"]:
        if s.get("kind") == "kitti":
            props = s.get("proposals")
            out.append(f"{label} KITTI object directory `{s['path']}` (split "
                       f"`{s.get('split')}`), detector results `{s.get('results')}`"
                       + (f", proposals `{props}`" if props else ", no proposals") + ".")
    return out


def _origin_item(tr: dict) -> str:
    data = tr.get("data") or {}
    if data.get("simulated"):
        return ("Detections, proposals and ground truth: simulated lidar sequences "
                "(`lidar_sim`) run through the reference perception (`reference_perception`), "
                "stored as perception bags (`make meta-data`).")
    if any(s.get("kind") == "feature_table" for s in data.get("sources", [])):
        return ("Features and targets: the feature tables named above (`process_bags` or "
                "`lmd-train --export-features`), computed by the node's own code from "
                "their bags or KITTI data.")
    if any(s.get("kind") == "kitti" for s in data.get("sources", [])):
        return ("Ground truth: the KITTI directory's `label_2` (camera boxes converted with "
                "each frame's `calib`); detections and proposals: the result files named above.")
    return ("Detections, proposals and ground truth: the perception bags named above "
            "(`/perception/detections`, `/perception/proposals`, `/lidar/gt_objects`).")


def _all_modes(results: dict, data_of) -> dict | None:
    """The ``_data`` dicts of every mode's training record (``data_of``) in one: bags
    are the same for all modes, feature tables are one per mode."""
    found = [d for r in results.values() if (d := data_of(r["training"]))]
    if not found:
        return None
    sources = {json.dumps(s, sort_keys=True): s for d in found for s in d["sources"]}
    return {"sources": list(sources.values()),
            "simulated": all(d.get("simulated") for d in found)}


def model_card(results: dict, command: str) -> str:
    """MODEL_CARD.md text of a ``train`` run."""
    any_mode = next(iter(results.values()))
    tr = any_mode["training"]
    held = tr.get("held_out")
    s = tr.get("settings") or {}
    card = ModelCard("LMD meta models (LidarMetaDetect)", [
        "Meta classifier (confidence that a detection is a true positive, IoU_BEV >= 0.5 with "
        "a ground-truth box) and meta regressor (predicted IoU_BEV) of `lmd_node`, one pair per "
        "proposal mode (`lmd_<mode>_classifier.joblib`, `lmd_<mode>_regressor.joblib`, each with "
        "a manifest: feature schema, SHA-256, training data, metrics)."])
    card.section(
        "Reproduce", code_block(command),
        "(`lmd-train` is `python -m lidar_quality_training.lmd.train`; in the repository: "
        "`make lmd-models`.)",
        f"Estimator: `{tr['kind']}` (lidar_quality_core.meta_model), seed {tr['seed']}, "
        + (f"fitted with xgboost.dask on {tr['fitted_on']['workers']} Dask workers "
           f"(`--scheduler {tr['fitted_on']['scheduler']}`)." if tr.get("fitted_on")
           else "single-threaded."))
    data = [f"Training: {tr['frames']} frames, {tr['boxes']} boxes ({tr['tp']} TP, rate "
            f"{fmt(tr['tp_rate'], 3)}) from {tr['groups']} sequences: "
            f"{', '.join(map(str, tr['sources']))}.",
            *_source_items(_all_modes(results, lambda t: t.get("data")), "Training")]
    if held:
        data += [f"Held out: {held['frames']} frames, {held['boxes']} boxes ({held['tp']} "
                 f"TP, rate {fmt(held['tp_rate'], 3)}) from {held['groups']} sequences: "
                 f"{', '.join(map(str, held['sources']))}.",
                 *_source_items(_all_modes(results, lambda t: (t.get("held_out") or {})
                                           .get("data")), "Held-out")]
    data += [_origin_item(tr),
             f"Target: {tr['target']} (class-agnostic, as the authors' code); TP iff "
             f"{tr['tp_rule']}."]
    card.section("Data", bullets(data))
    card.section(
        "Features",
        "`lidar_quality_core.lmd.features` (the paper's set): 17 own-box quantities (x, y, z, l, w, h, "
        "theta, score, class, volume, surface, size ratio, points in box, fraction of the cloud's "
        "points, reflectance max / mean / std); for `exact` and `threshold` also min / max / "
        "mean / std over the proposal set of the 16 non-class quantities, of IoU_3D and IoU_BEV "
        "to the proposals, and the number of proposals (90 in all). `none`: the 17 own-box "
        "features. Settings the models were trained with (manifest `training_data.settings`; "
        "the node refuses another mode or class list and warns about other thresholds): "
        f"proposal-set BEV IoU > {s.get('iou_threshold')}, proposal score > "
        f"{s.get('proposal_score_threshold')} (threshold mode); NMS IoU "
        f"{s.get('nms_iou_threshold')}, NMS score >= {s.get('nms_score_threshold')} "
        f"(exact mode); classes {', '.join(s.get('class_names', []))}.",
        "IoU statistics are ours, not the authors': min / max / mean / std of IoU_3D and "
        "IoU_BEV over the proposal set without the box itself. The authors keep the box's "
        "match with itself in each list as a 0, which makes min always 0 and pulls mean and "
        "std towards 0 by an amount set by the count (already the feature n_proposals); ours "
        "describe the other proposals only. Following the authors would change every box "
        "with another proposal and need the models retrained. A proposal is the box itself "
        "only with its geometry and its score; the features do not depend on the order of "
        "the proposals (`lidar_quality_core.lmd.features`).")
    rows = []
    for mode, r in results.items():
        c, g = r["classifier"], r["regressor"]
        h, hs, hr = c.get("held_out", {}), c.get("held_out_detector_score", {}), g.get(
            "held_out", {})
        rows.append([mode, r["n_features"],
                     tuple(c["cv"]["auroc"]) if "cv" in c else None,
                     tuple(g["cv"]["r2"]) if "cv" in g else None,
                     h.get("accuracy"), h.get("auroc"), h.get("auprc"), h.get("ece"),
                     h.get("mce"), hr.get("r2"), hr.get("mae"), hs.get("auroc"), hs.get("ece"),
                     f"{r['bytes'] / 1e3:.0f}"])
    card.section(
        "Metrics",
        (f"Grouped {tr['cv_folds']}-fold cross validation over the training sequences "
         "(mean ± std over folds)" if tr["cv_folds"] else
         "No cross validation (`--cv-folds 0`): the CV columns are empty")
        + (" and held-out sequences." if held else "; no held-out data.")
        + " ECE / MCE: 10 equal-width bins.",
        markdown_table(["mode", "features", "CV AUROC", "CV R²", "held-out accuracy",
                        "held-out AUROC", "held-out AUPRC", "held-out ECE", "held-out MCE",
                        "held-out R²", "held-out MAE", "detector score AUROC",
                        "detector score ECE", "size kB"], rows, digits=4),
        "The full evaluation (score and box-feature baselines, other estimators, "
        "reliability diagrams, feature selection, annotation-error proposals) is "
        "`lmd-eval`'s report.")
    return card.render()


def dataset_settings(ds: LmdDataset):
    """The ``LmdSettings`` a table's dataset was made with (to read bags alike)."""
    rec = dict(ds.info.get("settings") or {})
    rec.pop("proposal_mode", None)
    try:
        return settings_for(ds.mode, **rec)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"the tables' settings of mode {ds.mode} are not usable: {exc}") \
            from None


def _same_settings(train_sets: dict, test_sets: dict) -> dict:
    """``test_sets`` of the training modes; a mode whose held-out data was made with other
    settings than its training data is refused, naming the settings."""
    out = {}
    for mode, te in test_sets.items():
        if mode not in train_sets:
            continue
        a, b = train_sets[mode].info.get("settings") or {}, te.info.get("settings") or {}
        diff = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
        if diff:
            pairs = ", ".join(f"{k} {b.get(k)!r} vs {a.get(k)!r}" for k in diff)
            raise ValueError(f"mode {mode}: the held-out data was made with other settings "
                             f"than the training data ({pairs})")
        out[mode] = te
    return out


def load_data(args) -> tuple[dict, dict | None]:
    """``({mode: training dataset}, {mode: held-out dataset} or None)`` of the arguments:
    bags, KITTI or feature tables."""
    if args.features:
        if args.train is not None or args.kitti_root is not None:
            raise ValueError("--features replaces --train / --kitti-root: give one source "
                             "of training data")
        train_sets = feature_table.read_lmd(args.features, modes=args.modes,
                                            class_aware=args.class_aware)
        test_sets = None
        if args.test:  # bags, read with the settings the tables were made with
            test_sets = load_from_args(args, [dataset_settings(d) for d in train_sets.values()],
                                       "test")
    else:
        train_sets = load_from_args(args, settings_from_args(args, args.modes or MODES),
                                    "train")
        test_sets = None if args.test_features else load_from_args(
            args, settings_from_args(args, args.modes or MODES), "test")
    if args.test_features:
        if args.test:
            raise ValueError("--test-features replaces --test: give one source of held-out "
                             "data")
        test_sets = feature_table.read_lmd(args.test_features, class_aware=args.class_aware)
    return train_sets, (None if test_sets is None else _same_settings(train_sets, test_sets))


def _print_table_counts(label: str, sets: dict | None) -> None:
    for mode, ds in (sets or {}).items():
        left = ds.info.get("rows_without_targets", 0), ds.info.get("rows_invalid", 0)
        if "rows_without_targets" in ds.info and any(left):
            sys.stderr.write(f"{label} tables, mode {mode}: {left[0]} rows without targets "
                             f"and {left[1]} invalid rows left out\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="lmd-train", description=__doc__.split("\n\n")[0])
    add_source_args(ap)
    feature_table.add_table_arguments(
        ap, instead_of="--train / --kitti-root", test=True,
        export_to="DIR/train/lmd_<mode>.parquet, DIR/test/lmd_<mode>.parquet")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help="model directory")
    ap.add_argument("--modes", nargs="+", choices=MODES, default=None,
                    help="proposal modes to train (default: all three; with --features: "
                         "every mode in the tables)")
    ap.add_argument("--kind", choices=meta_model.KINDS, default="xgboost")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=1, help="estimator threads")
    ap.add_argument("--cv-folds", type=meta_model.cv_folds_arg, default=4,
                    help="grouped CV folds (by sequence; needs >= 2 sequences); 0: no CV")
    add_scheduler_option(ap)
    ap.add_argument("--no-model-card", action="store_true")
    args = ap.parse_args(argv)
    feature_table.check_table_arguments(ap, args)
    command = "lmd-train " + " ".join(shlex.quote(a) for a in
                                      (sys.argv[1:] if argv is None else list(argv)))
    try:
        check_scheduler(args.scheduler, args.kind)  # before reading any data
        train_sets, test_sets = load_data(args)
        if not args.quiet:
            _print_table_counts("training", train_sets)
            _print_table_counts("held-out", test_sets)
        if args.export_features is not None:
            for part, sets in (("train", train_sets), ("test", test_sets)):
                for p in feature_table.export_tables(sets or {}, args.export_features / part):
                    print(f"wrote {p}")
            if args.export_only:
                return 0
        with training_backend(args.scheduler, args.kind) as backend:
            results = train(train_sets, test_sets, args.out, kind=args.kind, seed=args.seed,
                            n_jobs=args.jobs, cv_folds=args.cv_folds, command=command,
                            progress=not args.quiet, backend=backend)
    except (ValueError, OSError, ModelStoreError) as exc:  # bad data: say why, no traceback
        print(f"lmd-train: {exc}", file=sys.stderr)
        return 2
    if not args.no_model_card:
        (Path(args.out) / "MODEL_CARD.md").write_text(model_card(results, command))
    for mode, r in results.items():
        h = r["classifier"].get("held_out", {})
        print(f"{mode}: {r['training']['boxes']} training boxes -> {', '.join(r['files'])} "
              f"({r['bytes'] / 1e3:.0f} kB)"
              + (f"; held-out AUROC {h['auroc']:.4f} (score "
                 f"{r['classifier']['held_out_detector_score']['auroc']:.4f}), ECE "
                 f"{h['ece']:.4f} (score {r['classifier']['held_out_detector_score']['ece']:.4f}), "
                 f"R^2 {r['regressor']['held_out']['r2']:.4f}" if h else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
