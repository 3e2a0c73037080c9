"""``mimo-adapt``: adapt a LiDAR-MIMO meta model pair to the user's multi-head detector and
data from a few labelled frames (``lidar_quality_training.adapt``: shipped, recalibrated,
continued or fresh, chosen by cross validation over the frames, with 95 % intervals).

    mimo-adapt --data my_bags/ --out my_models/mimo
    mimo-adapt --data my_bags/ --use-points --out my_models/mimo --frames 20
    mimo-adapt --features tables/ --out my_models/mimo

Data: perception bags with ground truth, or feature tables (as ``mimo-train``). The base
pair is the shipped one of ``--use-points`` / ``--no-use-points`` (the node's
``use_points``, default off: the cluster statistics only) unless ``--base-classifier`` /
``--base-regressor`` name others; the merge settings of the data must be the base models'
(the node refuses a mismatch as well). Targets as ``mimo-train``: BEV IoU with the best
ground-truth box of the detection's class >= 0.5, and that IoU. Frames are the dataset's
frame rows, sequences its bags. The output pair (``mimo[_points]_classifier.joblib`` /
``_regressor.joblib`` with manifests, ``MODEL_CARD.md``) goes to the node by its
``classifier_path`` / ``regressor_path`` parameters. The detector-score signal of the
recalibration is the merged ``score`` feature. Exit 2 with a message on bad data.
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
from .dataset import MimoDataset, load_bags
from .train import PREFIXES, _data, add_data_arguments

__all__ = ["adapt_data", "first_frames", "main"]


def adapt_data(ds: MimoDataset, use_points: bool) -> A.AdaptData:
    """The merged detections of ``ds`` for ``adapt``, with the features of the
    ``use_points`` pair (frames = the dataset's frame rows, sequences = its bags)."""
    X, names = ds.features(use_points)
    return A.AdaptData(X, ds.tp, ds.m_iou_class, ds.m_frame, tuple(names), "score", "logit",
                       info={"use_points": bool(use_points)},
                       block=A.frame_blocks(ds.frame_group)[ds.m_frame],
                       sequence=ds.frame_group[ds.m_frame])


def first_frames(ds: MimoDataset, n: int | None) -> np.ndarray:
    """Frame rows to use: all, or ``n`` taken in turn from each sequence."""
    return A.take_in_turn(ds.frame_group, n)


def profile_extra(ds: MimoDataset, rows: np.ndarray):
    """The non-feature quantities of the domain profile (as ``mimo-train`` records them)."""
    return ({"detector score": ds.m_score[rows]},
            {"detector score": ds.frame_group[ds.m_frame[rows]]})


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="mimo-adapt", description=__doc__.split("\n\n")[0])
    add_data_arguments(ap, None)
    ap.add_argument("--features", action="append", default=None, metavar="PATH",
                    help="feature tables (Parquet; repeatable) instead of --data")
    ap.add_argument("--use-points", action=argparse.BooleanOptionalAction, default=None,
                    help="adapt the pair with the LMD point features (mimo_points_*) or "
                         "without (mimo_*; default: the node's use_points default)")
    A.add_adapt_arguments(ap)
    a = ap.parse_args(argv)
    command = "mimo-adapt " + " ".join(shlex.quote(x) for x in (sys.argv[1:] if argv is None
                                                                  else argv))
    from mimo_ros.pipeline import MimoSettings, default_model_paths

    use_points = MimoSettings().use_points if a.use_points is None else a.use_points
    try:
        cands = A.candidates_of(a)
        dc, dr = default_model_paths(use_points)
        cpath, rpath = a.base_classifier or dc, a.base_regressor or dr
        if a.features:
            if a.data is not None:
                raise ValueError("--features replaces --data: give one source of data")
            ds = feature_table.read_mimo(a.features, tool="mimo-adapt")
        elif a.data is None:
            raise ValueError("give the labelled data: --data bags or --features")
        else:
            ds = load_bags(a.data, cache_dir=a.cache or None, progress=not a.quiet,
                           topics=dict(a.topic))
        data = adapt_data(ds, use_points)
        models = meta_model.MetaModels(
            cpath, rpath, data.feature_names, method="mimo",
            settings={**(ds.info.get("settings") or {}), "use_points": use_points},
            warn=lambda t: print(f"mimo-adapt: {t}", file=sys.stderr))
        keep = first_frames(ds, a.frames)
        rows = np.flatnonzero(np.isin(ds.m_frame, keep))
        data = data.rows(rows)
        if not len(data):
            raise ValueError(f"no merged detection with ground truth in the {len(keep)} "
                             "frames")
        result = A.adapt(data, models.classifier.estimator, models.regressor.estimator,
                         strategies=cands, n_folds=a.folds, seed=a.seed)
        extra, groups = profile_extra(ds, rows)
        prefix = PREFIXES[bool(use_points)]
        files = A.save_adapted(result, a.out, prefix, data,
                               base_manifest=read_manifest(cpath), base_paths=[cpath, rpath],
                               sources=_data(ds)["sources"], command=command,
                               profile_extra=extra, profile_groups=groups,
                               title=f"LiDAR-MIMO meta models ({prefix}), adapted")
    except (ValueError, OSError, ModelStoreError, KeyError) as exc:
        print(f"mimo-adapt: {exc}", file=sys.stderr)
        return 2
    A.print_summary("mimo-adapt", result, [*files, a.out / "MODEL_CARD.md"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
