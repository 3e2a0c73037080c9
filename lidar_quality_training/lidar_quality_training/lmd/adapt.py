"""``lmd-adapt``: adapt the LMD meta models of one proposal mode to the user's detector and
data from a few labelled frames (``lidar_quality_training.adapt``: shipped, recalibrated,
continued or fresh, chosen by cross validation over the frames, with 95 % intervals).

    lmd-adapt --train my_bags/ --mode none --out my_models/lmd
    lmd-adapt --kitti-root kitti --kitti-results results/ --mode none --out my_models/lmd
    lmd-adapt --features tables/ --mode threshold --out my_models/lmd --frames 20

Data: perception bags with ground truth, a KITTI directory with result files, or feature
tables (as ``lmd-train``). The base pair is the shipped one of ``--mode`` unless
``--base-classifier`` / ``--base-regressor`` name others; the features are computed with
the settings given here, which must be the base models' (the node refuses a mismatch as
well). The output pair (``lmd_<mode>_classifier.joblib`` / ``_regressor.joblib`` with
manifests, ``MODEL_CARD.md``) goes to the node by its ``classifier_path`` /
``regressor_path`` parameters. The detector-score signal of the recalibration is the
``score`` feature. Exit 2 with a message on bad data.
"""
from __future__ import annotations

import argparse
import shlex
import sys

import numpy as np

from lidar_quality_core import meta_model
from lidar_quality_core.model_store import ModelStoreError, read_manifest

from .. import adapt as A
from .. import feature_table
from .train import dataset_settings
from .dataset import LmdDataset, add_source_args, load_from_args, settings_from_args

__all__ = ["adapt_data", "first_frames", "main"]


def adapt_data(ds: LmdDataset) -> A.AdaptData:
    """The rows of ``ds`` for ``adapt`` (frames = the dataset's frame rows)."""
    return A.AdaptData(ds.X, ds.tp, ds.iou, ds.frame, tuple(ds.feature_names), "score",
                       "logit", info={"mode": ds.mode},
                       block=A.frame_blocks(ds.frame_group)[ds.frame], sequence=ds.group)


def first_frames(ds: LmdDataset, n: int | None) -> np.ndarray:
    """Frame rows to use: all, or ``n`` taken in turn from each sequence."""
    return A.take_in_turn(ds.frame_group, n)


def profile_extra(ds: LmdDataset, keep_frames: np.ndarray, rows: np.ndarray):
    """The non-feature quantities of the domain profile (as ``lmd-train`` records them)."""
    pts = ds.frame_points[keep_frames]
    known = pts >= 0
    return ({"detector score": ds.score[rows], "points per frame": pts[known]},
            {"detector score": ds.group[rows],
             "points per frame": ds.frame_group[keep_frames][known]})


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="lmd-adapt", description=__doc__.split("\n\n")[0])
    add_source_args(ap, test=False)
    ap.add_argument("--features", nargs="+", default=None,
                    help="feature tables (Parquet) instead of bags / KITTI")
    ap.add_argument("--mode", choices=("exact", "threshold", "none"), default="threshold",
                    help="proposal mode of the models adapted (the node's proposal_mode)")
    A.add_adapt_arguments(ap, "the shipped one of --mode")
    a = ap.parse_args(argv)
    command = "lmd-adapt " + " ".join(shlex.quote(x) for x in (sys.argv[1:] if argv is None
                                                                 else argv))
    from lmd_ros.pipeline import default_model_paths

    try:
        cands = A.candidates_of(a)
        dc, dr = default_model_paths(a.mode)
        cpath, rpath = a.base_classifier or dc, a.base_regressor or dr
        if a.features:
            if a.train is not None or a.kitti_root is not None:
                raise ValueError("--features replaces --train / --kitti-root")
            ds = feature_table.read_lmd(a.features, modes=[a.mode], class_aware=a.class_aware,
                                        tool="lmd-adapt")[a.mode]
        else:
            if a.train is None and a.kitti_root is None:
                raise ValueError("give the labelled data: --train bags, --kitti-root or "
                                 "--features")
            ds = load_from_args(a, settings_from_args(a, [a.mode]), "train")[a.mode]
        settings = dataset_settings(ds)
        models = meta_model.MetaModels(cpath, rpath, settings.feature_names(),
                                       settings=settings, method="lmd",
                                       warn=lambda t: print(f"lmd-adapt: {t}", file=sys.stderr))
        keep = first_frames(ds, a.frames)
        rows = np.flatnonzero(np.isin(ds.frame, keep))
        data = adapt_data(ds).rows(rows)
        if not len(data):
            raise ValueError(f"no scored box with ground truth in the {len(keep)} frames")
        result = A.adapt(data, models.classifier.estimator, models.regressor.estimator,
                         strategies=cands, n_folds=a.folds, seed=a.seed)
        extra, groups = profile_extra(ds, keep, rows)
        sources = [dict(s) for s in ds.info.get("sources", [])]
        files = A.save_adapted(result, a.out, f"lmd_{a.mode}", data,
                               base_manifest=read_manifest(cpath), base_paths=[cpath, rpath],
                               sources=sources, command=command, profile_extra=extra,
                               profile_groups=groups,
                               title=f"LMD meta models ({a.mode}), adapted")
    except (ValueError, OSError, ModelStoreError, KeyError) as exc:
        print(f"lmd-adapt: {exc}", file=sys.stderr)
        return 2
    A.print_summary("lmd-adapt", result, [*files, a.out / "MODEL_CARD.md"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
