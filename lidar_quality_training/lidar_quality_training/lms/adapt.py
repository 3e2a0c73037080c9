"""``lms-adapt``: adapt the LidarMetaSeg meta models to the user's segmentation network and
data from a few labelled frames (``lidar_quality_training.adapt``: shipped, recalibrated,
continued or fresh, chosen by cross validation over the frames, with 95 % intervals).

    lms-adapt --data my_bags/ --out my_models/lms
    lms-adapt --data kitti/ --probabilities kitti_probs/ --out my_models/lms --frames 20
    lms-adapt --features tables/ --out my_models/lms

Data: perception bags with ground truth, SemanticKITTI-style roots with per-scan
probabilities, or feature tables (as ``lms-train``, with its data options). The base pair
is the shipped one (``lms_ros.pipeline.default_model_paths``) unless ``--base-classifier``
/ ``--base-regressor`` name others; the metrics are computed with the settings given here,
which must be the base models' (the node refuses a mismatch as well; another image
geometry only warns). Targets as ``lms-train``: the segment is a true positive (IoU_adj >
0) and IoU_adj. Frames are the (sequence, frame) pairs; the cross validation groups them
by sequence, else by ``--block-frames`` sub-sequences, else by frame. The output pair
(``lms_classifier.joblib`` / ``lms_regressor.joblib`` with manifests, ``MODEL_CARD.md``)
goes to the node by its ``classifier_path`` / ``regressor_path`` parameters. The user's own
signal in the recalibration is the mean entropy ``mean_E`` (no transform). Exit 2 with a
message on bad data.
"""
from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import numpy as np

from lidar_quality_core import meta_model
from lidar_quality_core.model_store import ModelStoreError, read_manifest

from .. import adapt as A
from .dataset import SegmentDataset
from .train import PREFIX, _data, add_data_arguments, dataset_from_args, dataset_from_tables

__all__ = ["adapt_data", "frame_keys", "first_frames", "main"]

SIGNAL = "mean_E"


def frame_keys(ds: SegmentDataset) -> np.ndarray:
    """(n,) ``<sequence name>/<frame index>`` of each row: the frame it belongs to."""
    seq = np.asarray(ds.sequences, dtype=str)[ds.sequence] if len(ds) else np.zeros(0, str)
    return np.char.add(np.char.add(seq, "/"), ds.frame.astype(str))


def adapt_data(ds: SegmentDataset) -> A.AdaptData:
    """The rows of ``ds`` for ``adapt``: targets as ``lms-train`` (IoU_adj > 0, IoU_adj),
    frames = (sequence, frame) pairs, blocks = the dataset's sub-sequence groups."""
    seq = np.asarray(ds.sequences, dtype=str)[ds.sequence] if len(ds) else np.zeros(0, str)
    return A.AdaptData(ds.X, ds.tp, ds.iou_adj, frame_keys(ds), tuple(ds.names), SIGNAL,
                       "identity", info={"block_frames": ds.info.get("block_frames")},
                       block=ds.group.astype(str), sequence=seq)


def first_frames(ds: SegmentDataset, n: int | None) -> np.ndarray:
    """Keys (``frame_keys``) of the frames to use: all, or ``n`` taken in turn from each
    sequence in frame order (so five frames of two sequences are not five of the first).
    Frames are those with at least one kept segment."""
    pairs = np.unique(np.stack([ds.sequence, ds.frame], axis=1), axis=0) if len(ds) else \
        np.zeros((0, 2), np.int64)
    pairs = pairs[A.take_in_turn(pairs[:, 0], n)]
    names = np.asarray(ds.sequences, dtype=str)
    return np.asarray([f"{names[s]}/{f}" for s, f in pairs.tolist()], dtype=str)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="lms-adapt", description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, nargs="+", default=None,
                    help="labelled perception bag(s), directories of bags or "
                         "SemanticKITTI-style roots")
    ap.add_argument("--features", action="append", default=None, metavar="PATH",
                    help="feature tables (Parquet; repeatable) instead of --data")
    A.add_adapt_arguments(ap)
    add_data_arguments(ap)
    a = ap.parse_args(argv)
    command = "lms-adapt " + " ".join(shlex.quote(x) for x in (sys.argv[1:] if argv is None
                                                                 else argv))
    from lms_ros.pipeline import default_model_paths

    try:
        cands = A.candidates_of(a)
        dc, dr = default_model_paths()
        cpath, rpath = a.base_classifier or dc, a.base_regressor or dr
        if a.features:
            ds = dataset_from_tables(a)
        elif a.data is None:
            raise ValueError("give the labelled data: --data bags / SemanticKITTI roots, or "
                             "--features")
        else:
            ds = dataset_from_args(a, a.data)
        models = meta_model.MetaModels(cpath, rpath, ds.names, settings=ds.info["settings"],
                                       method="lms",
                                       warn=lambda t: print(f"lms-adapt: {t}", file=sys.stderr))
        keep = first_frames(ds, a.frames)
        rows = np.flatnonzero(np.isin(frame_keys(ds), keep))
        data = adapt_data(ds).rows(rows)
        if not len(data):
            raise ValueError(f"no segment with ground truth in the {len(keep)} frames "
                             f"({ds.info.get('n_frames', 0)} read)")
        result = A.adapt(data, models.classifier.estimator, models.regressor.estimator,
                         strategies=cands, n_folds=a.folds, seed=a.seed)
        sources = _data(ds.info.get("sources") or [])["sources"]
        files = A.save_adapted(result, a.out, PREFIX, data,
                               base_manifest=read_manifest(cpath), base_paths=[cpath, rpath],
                               sources=sources, command=command,
                               title="LidarMetaSeg meta models, adapted")
    except (ValueError, OSError, ModelStoreError, KeyError) as exc:
        print(f"lms-adapt: {exc}", file=sys.stderr)
        return 2
    A.print_summary("lms-adapt", result, [*files, a.out / "MODEL_CARD.md"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
