"""``lms-train``: fit the LidarMetaSeg meta models (no rclpy).

    lms-train --data data/perception/meta_train --out models/lms

Builds the segment dataset (:mod:`lidar_quality_training.lms.dataset`: the node's own decoding and metrics,
cached as .npz), fits the meta classifier (target IoU_adj > 0: the segment is a true
positive; its probability is the node's ``confidence``) and the meta regressor (target
IoU_adj: ``predicted_iou``) on all metrics of :meth:`LmsSettings.metric_names`, and saves
them with :func:`lidar_quality_core.meta_model.save_pair` as ``lms_classifier.joblib`` /
``lms_regressor.joblib`` with manifests (training data, settings, grouped
cross-validation metrics) and a ``MODEL_CARD.md`` naming the data (bag or SemanticKITTI
paths; "simulated" only for the project's own data, ``meta_model.simulated_sources``).
XGBoost by default (paper III), seeded and single-threaded: the same data give the same
models. ``--cv-folds 0`` trains without cross validation (said in manifests and card);
cross validation needs at least two sub-sequences (groups of ``--block-frames``), else the
run ends with the reason and the fix (exit 2, no traceback), as for other bad data.

Feature sets (also used by ``lms-eval`` for the paper's baselines), by metric name:

* ``lms``: every metric (86 + 2n);
* ``no_features``: without the point-cloud *feature measures*, i.e. every metric whose
  heatmap is x, y, z, intensity or range: names matching :data:`FEATURE_MEASURE_PATTERN`
  ``^(mean|var)_(x|y|z|i|r)(_in|_bd|_rel|_rel_in)?$`` (5 x 10 = 50 metrics; the sizes,
  N_c and P_c stay, as in the paper's "LMS w/o features");
* ``entropy``: ``mean_E`` alone (the paper's "Entropy" baseline).

Feature tables (``lidar_quality_training.feature_table``): ``--features PATH`` (files,
directories, globs; repeatable) trains on Parquet tables instead of ``--data``, with the
settings they record (the image and ``--min-points`` options do not apply; the groups are
made with ``--block-frames``); ``--export-features DIR`` writes the dataset as
``DIR/lms_<ring source>.parquet`` (``--export-only``: and stops). ``--scheduler ADDRESS``
fits the XGBoost models, folds included, with ``xgboost.dask`` on a Dask cluster
(``lidar_quality_training.distributed_training``); the files are the same kind.
"""
from __future__ import annotations

import argparse
import re
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

from .. import feature_table
from ..distributed_training import (LocalTraining, add_scheduler_option, check_scheduler,
                                    training_backend)
from ..report import ModelCard, bullets, markdown_table
from .dataset import DEFAULT_BLOCK_FRAMES, RING_FROM, SegmentDataset, build_dataset

__all__ = ["FEATURE_MEASURE_PATTERN", "FEATURE_SETS", "feature_set", "cross_validate_pair",
           "fit_pair", "train", "main"]

FEATURE_MEASURE_PATTERN = re.compile(r"^(mean|var)_(x|y|z|i|r)(_in|_bd|_rel|_rel_in)?$")
FEATURE_SETS = ("lms", "no_features", "entropy")
PREFIX = "lms"


def feature_set(names: Sequence[str], which: str) -> list[str]:
    """The metric names of feature set ``which`` (see the module doc), in schema order."""
    names = list(names)
    if which == "lms":
        return names
    if which == "no_features":
        return [n for n in names if not FEATURE_MEASURE_PATTERN.match(n)]
    if which == "entropy":
        if "mean_E" not in names:
            raise KeyError("no metric mean_E")
        return ["mean_E"]
    raise ValueError(f"unknown feature set {which!r} (known: {', '.join(FEATURE_SETS)})")


def _cls_metrics(y, p) -> dict[str, float]:
    y = np.asarray(y, float)
    p = np.clip(np.asarray(p, float), 0.0, 1.0)
    # the paper's AUPRC ranks false positives (IoU_adj = 0) as the positive class
    return {"accuracy": qm.accuracy(y, p), "auroc": qm.auroc(y, p),
            "auprc_fp": qm.auprc(1.0 - y, 1.0 - p), "auprc_tp": qm.auprc(y, p),
            "ece": qm.ece(y, p), "mce": qm.mce(y, p)}


def _reg_metrics(y, p) -> dict[str, float]:
    p = np.clip(np.asarray(p, float), 0.0, 1.0)
    return {"r2": qm.r2(y, p), "mae": qm.mae(y, p)}


def task_metrics(task: str, y, p) -> dict[str, float]:
    """Metrics of ``task``: accuracy, AUROC, AUPRC (false positives / true positives as
    the positive class), ECE, MCE; or R^2, MAE. Predictions clipped to [0, 1]."""
    return _cls_metrics(y, p) if task == "classification" else _reg_metrics(y, p)


def _mean_std(rows: list[dict[str, float]]) -> dict[str, list[float]]:
    out = {}
    for k in rows[0]:
        v = np.array([r[k] for r in rows], float)
        v = v[np.isfinite(v)]
        out[k] = [float(v.mean()), float(v.std())] if v.size else [float("nan")] * 2
    return out


def cross_validate_pair(ds: SegmentDataset, names: Sequence[str] | None = None, *,
                        kind: str = "xgboost", n_folds: int = 10, seed: int = 0,
                        n_jobs: int = 1, progress=None, backend=None) -> dict:
    """Grouped ``n_folds`` cross validation (folds of whole sub-sequences,
    :func:`meta_model.group_folds`) of the classifier and the regressor on the columns
    ``names``, the fold models fitted by ``backend`` (default this machine). Returns
    ``{"classification" | "regression": {"train" | "val": {metric: [mean, std]},
    "folds": [...]}, "oof": {task: out-of-fold predictions}, "fold": fold of each row}``."""
    backend = backend or LocalTraining()
    X = ds.X if names is None else ds.columns(names)
    y = {"classification": ds.tp.astype(float), "regression": ds.iou_adj}
    folds = meta_model.group_folds(ds.group, n_folds, seed=seed)
    fold_of = np.empty(len(ds), np.int32)
    out = {"oof": {}, "fold": fold_of}
    for f, (_, va) in enumerate(folds):
        fold_of[va] = f
    done = 0
    for task in ("classification", "regression"):
        oof = np.full(len(ds), np.nan)
        per = []
        models = backend.fit_folds(kind, task, X, y[task], folds, seed=seed, n_jobs=n_jobs)
        for (tr, va), est in zip(folds, models):
            p_tr = meta_model.predict(est, task, X[tr])
            oof[va] = meta_model.predict(est, task, X[va])
            per.append({"train": task_metrics(task, y[task][tr], p_tr),
                        "val": task_metrics(task, y[task][va], oof[va])})
            done += 1
            if progress is not None:
                progress(done, 2 * len(folds))
        out[task] = {"train": _mean_std([p["train"] for p in per]),
                     "val": _mean_std([p["val"] for p in per]), "folds": per}
        out["oof"][task] = oof
    return out


def fit_pair(ds: SegmentDataset, names: Sequence[str] | None = None, *,
             kind: str = "xgboost", seed: int = 0, n_jobs: int = 1, backend=None):
    """(classifier, regressor) fitted on all rows, columns ``names`` (default: all), by
    ``backend`` (default this machine)."""
    backend = backend or LocalTraining()
    X = ds.X if names is None else ds.columns(names)
    clf = backend.fit(kind, "classification", X, ds.tp.astype(float), seed=seed,
                      n_jobs=n_jobs)
    reg = backend.fit(kind, "regression", X, ds.iou_adj, seed=seed, n_jobs=n_jobs)
    return clf, reg


def data_summary(ds: SegmentDataset) -> dict:
    """What a model was trained on (for manifests and reports)."""
    return {"sequences": list(ds.sequences), "n_sequences": len(ds.sequences),
            "n_frames": int(ds.info.get("n_frames", ds.n_frames)), "n_segments": len(ds),
            "n_groups": int(len(np.unique(ds.group))),
            "block_frames": ds.info.get("block_frames"),
            "true_positive_rate": float(ds.tp.mean()) if len(ds) else float("nan"),
            "mean_iou_adj": float(ds.iou_adj.mean()) if len(ds) else float("nan"),
            "excluded_small_segments": ds.info.get("n_excluded"),
            "dropped_undefined_iou": ds.info.get("dropped_undefined"),
            "ignore_label": ds.info.get("ignore_label"), "ring_from": ds.info.get("ring_from"),
            "settings": ds.info.get("settings"), "sources": ds.info.get("sources"),
            "data": _data(ds.info.get("sources") or [])}


def _source_kind(path) -> str:
    if str(path).endswith(".parquet"):
        return "feature_table"
    return "perception_bag" if (Path(path) / "metadata.yaml").is_file() else "semantickitti"


def _data(paths) -> dict:
    """``{"sources": [{"kind": "perception_bag" | "semantickitti" | "feature_table",
    "path"}], "simulated"}`` of the dataset's source paths (the model card's data
    section)."""
    src = [{"kind": _source_kind(p), "path": str(p)} for p in paths]
    return {"sources": src, "simulated": all(s["kind"] == "perception_bag" for s in src)
            and meta_model.simulated_sources([s["path"] for s in src])}


def _source_items(data: dict | None) -> list[str]:
    if not data:
        return []
    out = []
    for kind, label in (("perception_bag", "Perception bags"),
                        ("semantickitti", "SemanticKITTI-style sequences"),
                        ("feature_table", "Feature tables (Parquet)")):
        paths = [s["path"] for s in data["sources"] if s["kind"] == kind]
        if paths:
            out.append(f"{label}: {', '.join(f'`{p}`' for p in paths)}.")
    return out


def _model_card(path: Path, data: dict, cv: dict | None, kind: str, command: str,
                sizes: dict[str, int], n_features: int, fitted_on: dict | None = None) -> None:
    card = ModelCard(
        "LidarMetaSeg meta models (`lms_classifier.joblib`, `lms_regressor.joblib`)",
        ["Used by `lms_node` (via `lms_ros.pipeline.default_model_paths`): per predicted "
         "segment of a segmentation cloud, the classifier gives `confidence` = P(IoU_adj > 0) "
         "(the segment is not a false positive) and the regressor `predicted_iou` = "
         "estimated IoU_adj, both from the segment's "
         f"{n_features} LidarMetaSeg metrics (`LmsSettings.metric_names()`, order fixed "
         "by the manifests)."])
    made = card.section("How they were made", bullets([
        f"Command: `{command}`",
        f"Estimator: `{kind}` (`lidar_quality_core.meta_model.make_estimator`, seed 0, "
        + (f"fitted with xgboost.dask on {fitted_on['workers']} Dask workers (`--scheduler "
           f"{fitted_on['scheduler']}`)." if fitted_on else "one thread; deterministic)."),
        f"Data: {data['n_sequences']} sequences, {data['n_frames']} frames, "
        f"{data['n_segments']} segments with SP >= "
        f"{(data.get('settings') or {}).get('min_segment_points', '?')} points "
        f"({data['excluded_small_segments']} smaller ones excluded, "
        f"{data['dropped_undefined_iou']} with undefined IoU dropped); "
        f"true-positive rate {data['true_positive_rate']:.3f}, mean IoU_adj "
        f"{data['mean_iou_adj']:.3f}.",
        f"Sequences: {', '.join(data['sequences'])}.",
        *_source_items(data.get("data")),
        f"Ground-truth label {data['ignore_label']} ignored in the targets; clouds "
        f"decoded as the node does (rows from: {data['ring_from']}).",
        "Files: " + ", ".join(f"`{k}` {v / 1024:.0f} kB" for k, v in sizes.items())]))
    if cv is None:
        made.add("No cross validation (`--cv-folds 0`).")
    else:
        c, r = cv["classification"], cv["regression"]
        rows = [[lab, tuple(c["train"][k]), tuple(c["val"][k])]
                for k, lab in (("accuracy", "ACC"), ("auroc", "AUROC"),
                               ("auprc_fp", "AUPRC (false positives)"), ("ece", "ECE"))]
        rows += [[f"{lab} (IoU_adj)", tuple(r["train"][k]), tuple(r["val"][k])]
                 for k, lab in (("r2", "R²"), ("mae", "MAE"))]
        card.section(f"Grouped {len(c['folds'])}-fold cross validation (sub-sequences of "
                     f"{data['block_frames']} frames, {data['n_groups']} groups)",
                     markdown_table(["", "training", "validation"], rows),
                     "Held-out results and the baselines: `lms-eval` (report.md).")
    trained_on = ("simulated HDL-64 scans segmented by the reference segmenter"
                  if (data.get("data") or {}).get("simulated") else
                  "the data named above, segmented by the network that wrote its "
                  "probabilities")
    card.section(
        "Limits",
        f"Trained on {trained_on}: the metrics depend on that segmenter's probability "
        "calibration and on the sensor layout (image size, rows from rings). Retrain for "
        "another segmentation network or sensor; the node refuses a model trained for "
        "another class list or min_segment_points and warns for another image geometry "
        "(manifest `training_data.settings`).")
    card.write(path)


def train(ds: SegmentDataset, out, *, kind: str = "xgboost", n_folds: int = 10,
          seed: int = 0, n_jobs: int = 1, command: str = "", quiet: bool = False,
          backend=None) -> dict:
    """Cross-validate (``n_folds`` >= 2; 0: none), fit on all rows and save the pair +
    model card into ``out``; ``backend`` fits the models (``distributed_training``,
    default this machine). Returns a summary (data, CV means and stds, file sizes).
    Raises ``ValueError`` for data it cannot train on (no segment, one CV group)."""
    backend = backend or LocalTraining()
    out = Path(out)
    if not len(ds):
        raise ValueError(f"no segment in the training data ({ds.info.get('n_frames', 0)} "
                         f"frames, {ds.info.get('n_excluded', 0)} segments below "
                         "min_segment_points)")
    n_folds = meta_model.cv_fold_count(ds.group, n_folds,
                                       what=f"sub-sequences of {ds.info.get('block_frames')} "
                                            "frames (groups)",
                                       hint=" or a smaller --block-frames")
    data = data_summary(ds)
    cv = None
    if not n_folds and not quiet:
        sys.stderr.write("no cross validation (--cv-folds 0)\n")
    if n_folds:
        bar = Progress("cross validation", 2 * n_folds, not quiet)
        cv = cross_validate_pair(ds, kind=kind, n_folds=n_folds, seed=seed, n_jobs=n_jobs,
                                 progress=bar, backend=backend)
    t0 = time.monotonic()
    clf, reg = fit_pair(ds, kind=kind, seed=seed, n_jobs=n_jobs, backend=backend)
    fit_s = time.monotonic() - t0

    def task_cv(task):
        if cv is None:
            return {}
        return {"cv_folds": n_folds, "cv_groups": "sub-sequences",
                "cv_train": cv[task]["train"], "cv_val": cv[task]["val"]}

    training_data = {**data, "kind": kind, "seed": seed, "command": command,
                     "cv_folds": n_folds}
    if not n_folds:
        training_data["cross_validation"] = "skipped: --cv-folds 0"
    if backend.record():
        training_data["fitted_on"] = backend.record()
    cpath, rpath = meta_model.save_pair(out, PREFIX, clf, reg, ds.names,
                                        training_data=training_data,
                                        domain_profile=meta_model.training_profile(
                                            ds.X, ds.names, groups=ds.sequence),
                                        classifier_metrics=task_cv("classification"),
                                        regressor_metrics=task_cv("regression"))
    sizes = {p.name: p.stat().st_size for p in (cpath, rpath)}
    _model_card(out / "MODEL_CARD.md", data, cv, kind, command, sizes, len(ds.names),
                backend.record())
    summary = {"data": data, "kind": kind, "fit_seconds": round(fit_s, 1), "files": sizes,
               "cv": None if cv is None else {t: {"train": cv[t]["train"], "val": cv[t]["val"]}
                                               for t in ("classification", "regression")}}
    if not quiet:
        kbs = ", ".join(f"{v / 1024:.0f} kB" for v in sizes.values())
        sys.stderr.write(f"wrote {cpath}, {rpath} ({kbs})\n")
    return summary


def add_data_arguments(ap: argparse.ArgumentParser) -> None:
    """Dataset options shared by ``lms-train`` and ``lms-eval``."""
    ap.add_argument("--probabilities", type=Path, default=None,
                    help="SemanticKITTI-style data: root holding sequences/NN/probabilities "
                         "(default: the data root itself)")
    ap.add_argument("--cache", default="data/cache/lms",
                    help="directory of the per-sequence .npz cache ('' : no cache)")
    ap.add_argument("--min-points", type=int, default=None,
                    help="exclude segments with fewer projected points (SP; default: the "
                         "node's min_segment_points, 10)")
    ap.add_argument("--channels", type=int, default=None,
                    help="image rows (default: the node's, 64); must match the node's parameter")
    ap.add_argument("--width", type=int, default=None,
                    help="image columns = 360 deg / resolution (default: the node's, 2048)")
    ap.add_argument("--fov-up", type=float, default=None,
                    help="upper vertical field of view [deg] for clouds without a ring field")
    ap.add_argument("--fov-down", type=float, default=None,
                    help="lower vertical field of view [deg] for clouds without a ring field")
    ap.add_argument("--intensity-scale", choices=("auto", "unit", "byte"), default=None,
                    help="the clouds' intensity scale, brought to [0, 1] for the intensity "
                         "metrics (default: the node's, auto)")
    ap.add_argument("--ignore-label", type=int, default=0,
                    help="ground-truth class ignored in the targets (-1: none; default 0 = "
                         "unlabeled)")
    ap.add_argument("--ring-from", choices=RING_FROM, default="points",
                    help="bags: rows from /lidar/points' ring field (two-cloud input) or the "
                         "segmentation cloud alone (vertical field of view)")
    ap.add_argument("--block-frames", type=int, default=DEFAULT_BLOCK_FRAMES,
                    help="sub-sequence length for the grouped folds")
    add_topic_option(ap)
    ap.add_argument("--quiet", action="store_true")


def settings_from_args(a):
    """The node's default :class:`LmsSettings` with the image options given on the
    command line (``--min-points``, ``--channels``, ``--width``, ``--fov-up/-down``)."""
    import dataclasses

    from lms_ros.pipeline import LmsSettings

    given = {"min_segment_points": a.min_points, "channels": a.channels, "width": a.width,
             "fov_up_deg": a.fov_up, "fov_down_deg": a.fov_down,
             "intensity_scale": a.intensity_scale}
    s = dataclasses.replace(LmsSettings(), **{k: v for k, v in given.items() if v is not None})
    s.validate()
    return s


def dataset_from_args(a, paths) -> SegmentDataset:
    return build_dataset(paths, settings_from_args(a), probabilities_root=a.probabilities,
                         ignore_label=None if a.ignore_label < 0 else a.ignore_label,
                         ring_from=a.ring_from, block_frames=a.block_frames,
                         cache_dir=Path(a.cache) if a.cache else None, quiet=a.quiet,
                         topics=dict(a.topic))


def dataset_from_tables(a) -> SegmentDataset:
    """The dataset of ``--features`` (``a.features``), groups of ``--block-frames``."""
    if a.data is not None:
        raise ValueError("--features replaces --data: give one source of training data")
    ds = feature_table.read_lms(a.features, block_frames=a.block_frames)
    left = ds.info["rows_without_targets"], ds.info["rows_invalid"]
    if any(left) and not a.quiet:
        sys.stderr.write(f"feature tables: {left[0]} rows without targets and {left[1]} "
                         "invalid rows left out\n")
    return ds


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="lms-train", description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, nargs="+", default=None,
                    help="perception bag(s), directories of bags or SemanticKITTI-style roots "
                         "(default: data/perception/meta_train)")
    feature_table.add_table_arguments(ap, instead_of="--data",
                                      export_to="DIR/lms_<ring source>.parquet")
    ap.add_argument("--out", type=Path, default=Path("models/lms"))
    ap.add_argument("--kind", choices=meta_model.KINDS, default="xgboost")
    ap.add_argument("--cv-folds", "--folds", dest="folds", type=meta_model.cv_folds_arg,
                    default=10, help="grouped CV folds over sub-sequences (0: no CV)")
    ap.add_argument("--seed", type=int, default=0)
    add_scheduler_option(ap)
    add_data_arguments(ap)
    a = ap.parse_args(argv)
    feature_table.check_table_arguments(ap, a)
    command = "lms-train " + " ".join(shlex.quote(x) for x in (sys.argv[1:] if argv is None
                                                                 else argv))
    try:
        check_scheduler(a.scheduler, a.kind)  # before reading any data
        if a.features:
            ds = dataset_from_tables(a)
        else:
            ds = dataset_from_args(a, a.data or [Path("data/perception/meta_train")])
        if a.export_features is not None:
            for p in feature_table.export_tables(ds, a.export_features):
                print(f"wrote {p}")
            if a.export_only:
                return 0
        if not a.quiet:
            sys.stderr.write(f"{len(ds)} segments from {ds.info['n_frames']} frames of "
                             f"{len(ds.sequences)} sequences, {len(np.unique(ds.group))} "
                             "groups\n")
        with training_backend(a.scheduler, a.kind) as backend:
            summary = train(ds, a.out, kind=a.kind, n_folds=a.folds, seed=a.seed,
                            command=command, quiet=a.quiet, backend=backend)
    except (ValueError, OSError, ModelStoreError) as exc:  # bad data: say why, no traceback
        print(f"lms-train: {exc}", file=sys.stderr)
        return 2
    if summary["cv"] and not a.quiet:
        c, r = summary["cv"]["classification"]["val"], summary["cv"]["regression"]["val"]
        print(f"CV validation: ACC {c['accuracy'][0]:.3f}  AUROC {c['auroc'][0]:.3f}  "
              f"AUPRC(fp) {c['auprc_fp'][0]:.3f}  R2 {r['r2'][0]:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
