"""Reference point-cloud segmenter: a per-point MLP over hand-made geometric features.

It plays the segmentation network whose softmax probabilities LidarMetaSeg post-processes,
so it is a real learned model with real failure modes (ground classes told apart by
reflectivity and context, pole / trunk / sign, car / truck, pedestrian / cyclist, sparse
far points), not ground truth plus noise.

Features (``FEATURE_NAMES``, per point, float32) come from three sources. They do not depend
on the order of the points, and none is an absolute azimuth / x / y, so the model cannot
learn where the street lies around the car (only the BEV cell grid is tied to the axes):

* the point itself: range, z, height above ground (:func:`reference_perception.ground.
  estimate_ground`), intensity, elevation, ring row;
* its range-image neighbourhood (:mod:`lidar_quality_core.lms.projection`, periodic in
  azimuth): a surface normal from range-gated neighbour differences (verticality, incidence
  angle and a reflectivity estimate ``intensity / cos(incidence)``), range jumps to the
  neighbours, curvature, and 5 x 5 / 3 x 11 window statistics (height spread, range spread,
  filled fraction, height extent);
* bird's-eye-view cells of 0.5 m and 2 m: highest / lowest height above ground and point
  count of the cell (object height and extent: car vs truck, pole vs trunk under a crown).

Model: ``StandardScaler`` + ``MLPClassifier`` (ReLU) from scikit-learn, stored with
:mod:`lidar_quality_core.model_store` (task ``multiclass``, all ``NUM_CLASSES`` columns
including ``unlabeled``, which the simulator never emits, so its probability stays near 0).
:class:`ReferenceSegmenter` evaluates it with float32 numpy matmuls (scaler folded into the
first layer) for speed; other multiclass estimators fall back to ``LoadedModel``.

Invalid points (a non-finite coordinate or intensity) get the uniform distribution
``1 / NUM_CLASSES``: the model knows nothing about them, and their argmax (first maximum) is
``unlabeled``. Points outside the vertical field of view keep their own features with an
empty neighbourhood (the defaults of an isolated point) and are classified like any other.

Shipped model (``models/reference/segmenter.joblib``, 83 kB, hidden layers 64 + 32):
held-out mIoU 0.65 on ``reference_test``; per-class IoU and the confusion matrix are in
its manifest. ~100 ms per 118k-point frame on one core (``bench/bench_ref_segmenter.py``).

mIoU follows SemanticKITTI: ``unlabeled`` ground truth is ignored (those points are left
out of the confusion matrix) and the mean is over the classes present in the ground truth.
"""
from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from pathlib import Path
from typing import Any, Iterable

import numpy as np
from lidar_quality_core import metrics as qm
from lidar_quality_core.model_store import models_dir
from lidar_quality_core.lms.projection import RangeImageConfig, project, window_reduce
from lidar_sim.classes import CLASS_NAMES, NUM_CLASSES, UNLABELED

from .ground import estimate_ground

__all__ = [
    "FEATURE_NAMES",
    "DEFAULT_MODEL_PATH",
    "default_range_image_config",
    "segmenter_features",
    "ReferenceSegmenter",
    "train_segmenter",
    "evaluate_segmenter",
    "main",
]

DEFAULT_MODEL_PATH = models_dir() / "reference" / "segmenter.joblib"

FEATURE_NAMES: tuple[str, ...] = (
    "range", "z", "height", "intensity", "elevation_deg", "ring_frac",
    "normal_z", "cos_incidence", "reflectivity_est", "normal_ok",
    "dr_h_min", "dr_h_max", "dr_up", "dr_down", "curvature_h", "dz_up", "dz_down",
    "height_std_5x5", "range_std_5x5", "filled_5x5", "height_above_min_5x5",
    "height_below_max_5x5", "height_max_3x11", "height_min_3x11",
    "bev05_height_max", "bev05_height_min", "bev05_log_count",
    "bev2_height_max", "bev2_height_min", "bev2_log_count",
)

_DR_CLIP = 3.0        # m: range jumps beyond this (or a missing neighbour) read as "far"
_GATE_REL = 0.15      # neighbours within 15 % of the range (+ 0.3 m) are the same surface
_GATE_ABS = 0.3


def default_range_image_config() -> RangeImageConfig:
    """The simulator's HDL-64 layout (64 beams, 2048 columns)."""
    from lidar_sim.sensor import hdl64

    s = hdl64()
    return RangeImageConfig.from_elevations(s.elevations_deg, s.columns)


_DEFAULT_CFG: RangeImageConfig | None = None


def _cfg_or_default(cfg: RangeImageConfig | None) -> RangeImageConfig:
    global _DEFAULT_CFG
    if cfg is not None:
        return cfg
    if _DEFAULT_CFG is None:
        _DEFAULT_CFG = default_range_image_config()
    return _DEFAULT_CFG


def _bev_stats(xy: np.ndarray, h: np.ndarray, cell: float) -> tuple[np.ndarray, ...]:
    """Per point: max / min height and log point count of its BEV cell (finite rows)."""
    ij = np.floor(xy / cell).astype(np.int64)
    ij -= ij.min(axis=0)
    nx, ny = int(ij[:, 0].max()) + 1, int(ij[:, 1].max()) + 1
    cid = ij[:, 0] * ny + ij[:, 1]
    n_cells = nx * ny
    if n_cells > 4 * len(cid) + 1_000_000:  # far outliers: compact ids instead of a grid
        uniq, cid = np.unique(cid, return_inverse=True)
        n_cells = len(uniq)
    hmax = np.full(n_cells, -np.inf, dtype=np.float32)
    hmin = np.full(n_cells, np.inf, dtype=np.float32)
    np.maximum.at(hmax, cid, h)
    np.minimum.at(hmin, cid, h)
    lc = np.log1p(np.bincount(cid, minlength=n_cells).astype(np.float32))
    return hmax[cid], hmin[cid], lc[cid]


# pixel-level features: computed on the range image of the points each pixel keeps, then
# read back by every point of the pixel; (name, value for a point outside the image)
_PIXEL_FEATURES = (
    ("normal_z", 0.5), ("cos_incidence", 0.5), ("normal_ok", 0.0),
    ("dr_h_min", _DR_CLIP), ("dr_h_max", _DR_CLIP), ("dr_up", _DR_CLIP),
    ("dr_down", _DR_CLIP), ("curvature_h", 0.0), ("dz_up", 0.0), ("dz_down", 0.0),
    ("height_std_5x5", 0.0), ("range_std_5x5", 0.0), ("filled_5x5", 0.0),
    ("height_above_min_5x5", 0.0), ("height_below_max_5x5", 0.0),
    ("height_max_3x11", np.nan), ("height_min_3x11", np.nan),
)


def _pixel_features(img: np.ndarray) -> dict[str, np.ndarray]:
    """Pixel features from ``img`` (5, R, C) = x, y, z, range, height (NaN: empty)."""
    K, R, C = img.shape
    # pad: rows with NaN (no neighbour above the top beam), columns periodically (seam)
    pad = np.empty((K, R + 2, C + 2), dtype=np.float32)
    pad[:, 0] = np.nan
    pad[:, -1] = np.nan
    pad[:, 1:-1, 1:-1] = img
    pad[:, 1:-1, 0] = img[:, :, -1]
    pad[:, 1:-1, -1] = img[:, :, 0]
    views = {"c": pad[:, 1:-1, 1:-1], "up": pad[:, :-2, 1:-1], "down": pad[:, 2:, 1:-1],
             "left": pad[:, 1:-1, :-2], "right": pad[:, 1:-1, 2:]}
    r0 = views["c"][3]
    gate = _GATE_REL * r0 + _GATE_ABS
    with np.errstate(invalid="ignore"):
        dr = {k: views[k][3] - r0 for k in ("up", "down", "left", "right")}
        same = {k: np.abs(v) < gate for k, v in dr.items()}  # NaN: False

    def tangent(a, b):
        pa = np.where(same[a], views[a][:3], views["c"][:3])
        pb = np.where(same[b], views[b][:3], views["c"][:3])
        return pa - pb

    th = tangent("right", "left")
    tv = tangent("down", "up")
    n = np.stack([th[1] * tv[2] - th[2] * tv[1], th[2] * tv[0] - th[0] * tv[2],
                  th[0] * tv[1] - th[1] * tv[0]])
    nn = np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    n_ok = nn > 1e-9
    inv = np.where(n_ok, 1.0 / np.where(n_ok, nn, 1.0), 0.0).astype(np.float32)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos_inc = np.abs(n[0] * views["c"][0] + n[1] * views["c"][1] + n[2] * views["c"][2]) \
            * inv / r0
    f = {"normal_z": np.where(n_ok, np.abs(n[2]) * inv, 0.5),
         "cos_incidence": np.where(n_ok, np.nan_to_num(cos_inc, nan=0.5), 0.5),
         "normal_ok": n_ok.astype(np.float32)}
    d = {k: np.clip(np.nan_to_num(v, nan=_DR_CLIP), -_DR_CLIP, _DR_CLIP) for k, v in dr.items()}
    f["dr_h_min"] = np.minimum(d["left"], d["right"])
    f["dr_h_max"] = np.maximum(d["left"], d["right"])
    f["dr_up"] = d["up"]
    f["dr_down"] = d["down"]
    f["curvature_h"] = np.where(same["left"] & same["right"],
                                np.clip(d["left"] + d["right"], -1.0, 1.0), 0.0)
    z0 = views["c"][2]
    f["dz_up"] = np.where(same["up"], views["up"][2] - z0, 0.0)
    f["dz_down"] = np.where(same["down"], z0 - views["down"][2], 0.0)

    h0, filled = img[4], np.isfinite(img[4])
    hz = np.where(filled, h0, 0.0)
    rz = np.where(filled, img[3], 0.0)
    cnt = window_reduce(filled.astype(np.float32), 5, "sum")
    with np.errstate(invalid="ignore", divide="ignore"):
        inv_cnt = 1.0 / cnt
        mh = window_reduce(hz, 5, "sum") * inv_cnt
        mr = window_reduce(rz, 5, "sum") * inv_cnt
        vh = window_reduce(hz * hz, 5, "sum") * inv_cnt - mh * mh
        vr = window_reduce(rz * rz, 5, "sum") * inv_cnt - mr * mr
    f["height_std_5x5"] = np.sqrt(np.maximum(np.nan_to_num(vh), 0.0))
    f["range_std_5x5"] = np.minimum(np.sqrt(np.maximum(np.nan_to_num(vr), 0.0)), 10.0)
    f["filled_5x5"] = cnt * (1.0 / 25.0)
    h_lo = np.where(filled, h0, np.inf)
    h_hi = np.where(filled, h0, -np.inf)
    f["height_above_min_5x5"] = np.where(filled, h0 - window_reduce(h_lo, 5, "min"), 0.0)
    f["height_below_max_5x5"] = np.where(filled, window_reduce(h_hi, 5, "max") - h0, 0.0)
    # a wide, flat window: the height extent of what is around the point in azimuth
    f["height_max_3x11"] = np.where(filled, window_reduce(h_hi, (3, 11), "max"), np.nan)
    f["height_min_3x11"] = np.where(filled, window_reduce(h_lo, (3, 11), "min"), np.nan)
    return f


def _finite_rows(xyz: np.ndarray, inten: np.ndarray) -> np.ndarray:
    # column by column: a reduction over axis 1 of width 3 is several times slower
    return np.isfinite(xyz[:, 0]) & np.isfinite(xyz[:, 1]) & np.isfinite(xyz[:, 2]) \
        & np.isfinite(inten)


def segmenter_features(xyz, intensity, ring=None, cfg: RangeImageConfig | None = None,
                       *, height: np.ndarray | None = None) -> np.ndarray:
    """(N, len(FEATURE_NAMES)) float32 features (see the module doc).

    ``ring`` (optional) gives each point's range-image row, else rows come from elevations
    against ``cfg`` (default: HDL-64). ``height`` (optional): precomputed height above
    ground. Range-image features describe the pixel's point (the nearest one): points that
    share a pixel share them. Rows of invalid points (non-finite xyz or intensity) are 0.
    """
    cfg = _cfg_or_default(cfg)
    xyz = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
    inten = np.asarray(intensity, dtype=np.float32).reshape(-1)
    n = len(xyz)
    if len(inten) != n:
        raise ValueError(f"intensity has {len(inten)} entries, xyz {n}")
    ok = _finite_rows(xyz, inten)
    if n == 0:
        return np.zeros((0, len(FEATURE_NAMES)), dtype=np.float32)
    if not ok.all():
        out = np.zeros((n, len(FEATURE_NAMES)), dtype=np.float32)
        if ok.any():
            out[ok] = segmenter_features(
                xyz[ok], inten[ok], None if ring is None else np.asarray(ring)[ok], cfg,
                height=None if height is None else np.asarray(height)[ok])
        return out

    proj = project(xyz, cfg, ring)
    hag = (estimate_ground(xyz).height if height is None else
           np.asarray(height, dtype=np.float32).reshape(-1))
    rng = proj.range
    R, C = cfg.shape
    # per-point channels, plus a NaN column that empty pixels read
    ch = np.empty((5, n + 1), dtype=np.float32)
    ch[:3, :n] = xyz.T
    ch[3, :n] = rng
    ch[4, :n] = hag
    ch[:, n] = np.nan
    img = np.take(ch, proj.index.reshape(-1), axis=1).reshape(5, R, C)
    pf = _pixel_features(img)
    # per point: one gather of all pixel features; points outside the image read the
    # defaults in the extra last column
    pimg = np.empty((len(_PIXEL_FEATURES), R * C + 1), dtype=np.float32)
    for k, (name, default) in enumerate(_PIXEL_FEATURES):
        pimg[k, :-1] = pf[name].reshape(-1)
        pimg[k, -1] = default
    pix = np.where(proj.valid, proj.pixel, R * C)
    per_point = np.take(pimg, pix, axis=1)

    out_t = np.empty((len(FEATURE_NAMES), n), dtype=np.float32)
    col = {name: j for j, name in enumerate(FEATURE_NAMES)}
    for k, (name, _) in enumerate(_PIXEL_FEATURES):
        out_t[col[name]] = per_point[k]
    for name in ("height_max_3x11", "height_min_3x11"):
        v = out_t[col[name]]
        np.copyto(v, hag, where=~np.isfinite(v))
    out_t[col["range"]] = rng
    out_t[col["z"]] = xyz[:, 2]
    out_t[col["height"]] = hag
    out_t[col["intensity"]] = inten
    with np.errstate(invalid="ignore", divide="ignore"):
        out_t[col["elevation_deg"]] = np.degrees(
            np.arcsin(np.clip(xyz[:, 2] / np.maximum(rng, 1e-6), -1.0, 1.0)))
    out_t[col["ring_frac"]] = np.where(proj.valid, proj.row / max(R - 1, 1), -1.0)
    out_t[col["reflectivity_est"]] = np.minimum(
        inten / np.maximum(out_t[col["cos_incidence"]], 0.1), 2.0)
    for cell, tag in ((0.5, "bev05"), (2.0, "bev2")):
        hmax, hmin, lc = _bev_stats(xyz[:, :2], hag, cell)
        out_t[col[f"{tag}_height_max"]] = hmax
        out_t[col[f"{tag}_height_min"]] = hmin
        out_t[col[f"{tag}_log_count"]] = lc
    return out_t.T


# -- model ----------------------------------------------------------------------------


def _softmax_columns(z: np.ndarray) -> np.ndarray:
    """In-place softmax over axis 0 of logits laid out (classes, n)."""
    z -= z.max(axis=0)
    np.exp(z, out=z)
    z /= z.sum(axis=0)
    return z


class ReferenceSegmenter:
    """Per-point class probabilities of a cloud (see the module doc)."""

    def __init__(self, loaded, cfg: RangeImageConfig | None = None):
        self.model = loaded
        self.cfg = _cfg_or_default(cfg)
        classes = [int(c) for c in loaded.classes]
        if classes != list(range(NUM_CLASSES)):
            raise ValueError(f"{loaded.path.name}: model classes {classes} are not "
                             f"0..{NUM_CLASSES - 1}")
        self._layers = _mlp_layers(loaded.estimator)

    @classmethod
    def load(cls, path: str | Path = DEFAULT_MODEL_PATH, cfg: RangeImageConfig | None = None
             ) -> "ReferenceSegmenter":
        from lidar_quality_core.model_store import load_model

        return cls(load_model(path, expected_features=list(FEATURE_NAMES),
                              expected_task="multiclass"), cfg)

    @property
    def model_id(self) -> str:
        return self.model.model_id

    def predict_features(self, X: np.ndarray) -> np.ndarray:
        """(n, NUM_CLASSES) float32 probabilities of feature rows ``X``."""
        X = np.asarray(X, dtype=np.float32)
        if self._layers is None:
            return self.model.predict_proba(X).astype(np.float32)
        # activations laid out (units, n): the bias, ReLU and softmax passes then run along
        # contiguous rows, ~30 % faster than (n, units) at this width
        h = X.T
        last = len(self._layers) - 1
        for i, (WT, b) in enumerate(self._layers):
            h = WT @ h
            h += b
            if i < last:
                np.maximum(h, 0.0, out=h)
        return np.ascontiguousarray(_softmax_columns(h).T)

    def predict_proba(self, xyz, intensity, ring=None) -> np.ndarray:
        """(N, NUM_CLASSES) float32 probabilities, rows summing to 1; invalid points
        (non-finite xyz / intensity) get the uniform distribution."""
        xyz = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
        inten = np.asarray(intensity, dtype=np.float32).reshape(-1)
        n = len(xyz)
        if len(inten) != n:
            raise ValueError(f"intensity has {len(inten)} entries, xyz {n}")
        ok = _finite_rows(xyz, inten)
        if ok.all():
            return self.predict_features(segmenter_features(xyz, inten, ring, self.cfg))
        out = np.full((n, NUM_CLASSES), 1.0 / NUM_CLASSES, dtype=np.float32)
        if not ok.any():
            return out
        r = None if ring is None else np.asarray(ring)[ok]
        out[ok] = self.predict_features(segmenter_features(xyz[ok], inten[ok], r, self.cfg))
        return out

    def predict(self, xyz, intensity, ring=None) -> np.ndarray:
        """(N,) int32 argmax class ids."""
        return self.predict_proba(xyz, intensity, ring).argmax(axis=1).astype(np.int32)


def _mlp_layers(est) -> list[tuple[np.ndarray, np.ndarray]] | None:
    """float32 (W^T, b) of a StandardScaler + ReLU MLPClassifier pipeline, the scaler folded
    into the first layer; None for anything else (evaluated through its predict_proba)."""
    try:
        from sklearn.neural_network import MLPClassifier
        from sklearn.pipeline import Pipeline
        from sklearn.preprocessing import StandardScaler
    except ImportError:  # pragma: no cover
        return None
    if not isinstance(est, Pipeline) or len(est.steps) != 2:
        return None
    scaler, mlp = est.steps[0][1], est.steps[1][1]
    if not (isinstance(scaler, StandardScaler) and isinstance(mlp, MLPClassifier)
            and mlp.activation == "relu" and mlp.out_activation_ == "softmax"):
        return None
    mean = np.zeros(scaler.n_features_in_) if scaler.mean_ is None else scaler.mean_
    scale = np.ones(scaler.n_features_in_) if scaler.scale_ is None else scaler.scale_
    W0 = mlp.coefs_[0] / scale[:, None]
    b0 = mlp.intercepts_[0] - mean / scale @ mlp.coefs_[0]
    layers = [(W0, b0)] + list(zip(mlp.coefs_[1:], mlp.intercepts_[1:]))
    # (out, in) weights and (out, 1) biases for the (units, n) layout of predict_features
    return [(np.ascontiguousarray(W.T, np.float32), np.asarray(b, np.float32)[:, None])
            for W, b in layers]


# -- training and evaluation ------------------------------------------------------------


def _frame_sample(frame, rng: np.random.Generator, per_class: int,
                  cfg: RangeImageConfig) -> tuple[np.ndarray, np.ndarray]:
    """Features and labels of a class-balanced-ish sample of one frame's points: up to
    ``per_class`` random points of every class present."""
    X = segmenter_features(frame.xyz, frame.intensity, frame.ring, cfg)
    y = np.asarray(frame.semantic, dtype=np.int64)
    idx = []
    for c in np.unique(y):
        members = np.flatnonzero(y == c)
        idx.append(members if len(members) <= per_class else
                   rng.choice(members, per_class, replace=False))
    idx = np.sort(np.concatenate(idx))
    return X[idx], y[idx]


def _collect(split: str, sequences, frames, per_class: int, seed: int, cfg,
             verbose: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sampled features and labels of a split's frames, and the class counts of all their
    points."""
    from lidar_sim.frames import split_frames

    rng = np.random.default_rng(seed)
    Xs, ys = [], []
    full = np.zeros(NUM_CLASSES, dtype=np.int64)
    t0 = time.perf_counter()
    for i, fr in enumerate(split_frames(split, sequences=sequences, frames=frames)):
        X, y = _frame_sample(fr, rng, per_class, cfg)
        full += np.bincount(fr.semantic, minlength=NUM_CLASSES)[:NUM_CLASSES]
        Xs.append(X)
        ys.append(y)
        if verbose and (i + 1) % 30 == 0:
            print(f"  {split}: {i + 1} frames, {sum(map(len, ys))} rows, "
                  f"{time.perf_counter() - t0:.0f} s", flush=True)
    return np.concatenate(Xs), np.concatenate(ys), full


def train_segmenter(out_path: str | Path | None = DEFAULT_MODEL_PATH, *,
                    train_split: str = "reference_train", test_split: str | None =
                    "reference_test", sequences: Iterable[int] | None = None,
                    frames: int | None = None, val_sequences: Iterable[int] | None = None,
                    per_class: int = 600, hidden: tuple[int, ...] = (64, 32),
                    epochs: int = 15, batch_size: int = 1024, learning_rate: float = 1e-3,
                    alpha: float = 1e-4, prior_power: float = 0.5, seed: int = 0,
                    test_sequences: Iterable[int] | None = None,
                    test_frames: int | None = None, threads: int = 1,
                    verbose: bool = True) -> dict:
    """Train the segmenter on ``train_split`` and save it to ``out_path`` (None: don't).

    Rows: up to ``per_class`` points per class and frame. Sample weights
    ``(N_c / n_c) ** prior_power`` give the classes back part of their true frequency
    (0: balanced, 1: the data's prior; RangeNet-style inverse-sqrt weighting ~ 0.5).
    ``val_sequences`` of the train split (default: its last sequence) are held out to pick
    the best epoch by validation loss; the rate drops to 30 % for the last 30 % of epochs.
    Returns ``{"model": Pipeline, "metrics": ..., "manifest": ...}``
    with the held-out evaluation on ``test_split`` in the metrics. ``threads``: BLAS
    threads (threaded BLAS spins badly on a busy shared machine; 1 is the safe default).
    """
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=threads):
        return _train(out_path, train_split=train_split, test_split=test_split,
                      sequences=sequences, frames=frames, val_sequences=val_sequences,
                      per_class=per_class, hidden=hidden, epochs=epochs,
                      batch_size=batch_size, learning_rate=learning_rate, alpha=alpha,
                      prior_power=prior_power, seed=seed, test_sequences=test_sequences,
                      test_frames=test_frames, verbose=verbose)


def _train(out_path, *, train_split, test_split, sequences, frames, val_sequences, per_class,
           hidden, epochs, batch_size, learning_rate, alpha, prior_power, seed,
           test_sequences, test_frames, verbose) -> dict:
    from sklearn.neural_network import MLPClassifier
    from sklearn.pipeline import Pipeline
    from sklearn.preprocessing import StandardScaler

    from lidar_sim.splits import split as get_split

    cfg = _cfg_or_default(None)
    t_start = time.perf_counter()
    sp = get_split(train_split)
    all_seq = list(range(sp.sequences)) if sequences is None else list(sequences)
    if val_sequences is None:
        val_sequences = all_seq[-1:] if len(all_seq) > 2 else []
    val_sequences = list(val_sequences)
    train_seq = [s for s in all_seq if s not in val_sequences]
    say = print if verbose else (lambda *a, **k: None)
    say(f"segmenter: training on {train_split} sequences {train_seq}, validation "
        f"{val_sequences}, {per_class} points / class / frame")
    X, y, full = _collect(train_split, train_seq, frames, per_class, seed, cfg, verbose)
    Xv, yv, _ = (_collect(train_split, val_sequences, frames, per_class, seed + 1, cfg, False)
                 if val_sequences else (None, None, None))
    t_feat = time.perf_counter() - t_start
    counts = np.bincount(y, minlength=NUM_CLASSES)
    say(f"  {len(y)} training rows in {t_feat:.0f} s; per class: "
        + ", ".join(f"{CLASS_NAMES[c]} {counts[c]}" for c in range(NUM_CLASSES) if counts[c]))

    sw = _prior_weights(y, full, prior_power)
    scaler = StandardScaler().fit(X)
    Xs = scaler.transform(X).astype(np.float32)
    mlp = MLPClassifier(hidden_layer_sizes=tuple(hidden), activation="relu", solver="adam",
                        alpha=alpha, batch_size=batch_size, learning_rate_init=learning_rate,
                        random_state=seed, shuffle=True)
    classes = np.arange(NUM_CLASSES)
    best = (np.inf, None, -1)
    Xvs = scaler.transform(Xv).astype(np.float32) if Xv is not None else None
    swv = _prior_weights(yv, full, prior_power) if yv is not None else None
    for ep in range(epochs):
        t0 = time.perf_counter()
        if ep == int(0.7 * epochs) and hasattr(mlp, "_optimizer"):
            # a lower rate for the last epochs: partial_fit keeps its Adam optimizer, which
            # reads the rate from itself, not from the estimator's parameters
            mlp._optimizer.learning_rate_init = learning_rate * 0.3
        mlp.partial_fit(Xs, y, sample_weight=sw, classes=classes)
        msg = f"  epoch {ep + 1:2d}/{epochs}: train loss {mlp.loss_:.4f}"
        if Xvs is not None:
            pv = np.clip(mlp.predict_proba(Xvs), 1e-7, 1)
            vloss = float(np.average(-np.log(pv[np.arange(len(yv)), yv]), weights=swv))
            vacc = float(np.average(pv.argmax(1) == yv, weights=swv))
            msg += f", val loss {vloss:.4f}, val acc {vacc:.3f}"
            if vloss < best[0]:
                best = (vloss, copy.deepcopy(mlp), ep + 1)
        say(msg + f" ({time.perf_counter() - t0:.1f} s)", flush=True)
    if best[1] is not None:
        mlp = best[1]
        say(f"  best epoch {best[2]} (val loss {best[0]:.4f})")
    model = Pipeline([("scale", scaler), ("mlp", mlp)])
    t_train = time.perf_counter() - t_start

    metrics: dict[str, Any] = {
        "train_seconds": round(t_train, 1),
        "miou_convention": "SemanticKITTI: unlabeled ground truth ignored, mean over the "
                           "classes present in the ground truth, all points of all frames",
    }
    result: dict[str, Any] = {"model": model}
    if test_split:
        seg = ReferenceSegmenter(_InMemoryModel(model))
        ev = evaluate_segmenter(seg, test_split, sequences=test_sequences, frames=test_frames,
                                verbose=verbose)
        metrics.update({f"{test_split}_{k}": v for k, v in ev.items()
                        if k in ("miou", "accuracy", "per_class_iou", "n_points", "n_frames",
                                 "ms_per_frame")})
        metrics[f"{test_split}_confusion"] = ev["confusion"]
        result["evaluation"] = ev
    result["metrics"] = metrics
    if out_path is not None:
        from lidar_quality_core.model_store import save_model

        out_path = Path(out_path)
        out_path.parent.mkdir(parents=True, exist_ok=True)
        training_data = {
            "split": train_split, "sequences": train_seq, "val_sequences": val_sequences,
            "frames_per_sequence": frames, "rows": int(len(y)),
            "rows_per_class": {CLASS_NAMES[c]: int(counts[c]) for c in range(NUM_CLASSES)},
            "per_class_per_frame": per_class, "prior_power": prior_power,
            "hidden": list(hidden), "epochs": epochs, "best_epoch": best[2],
            "batch_size": batch_size, "learning_rate": learning_rate, "alpha": alpha,
            "seed": seed, "range_image": {"rows": cfg.rows, "cols": cfg.cols},
        }
        result["manifest"] = save_model(model, out_path, feature_names=list(FEATURE_NAMES),
                                        task="multiclass", class_names=list(CLASS_NAMES),
                                        training_data=training_data, metrics=metrics)
        say(f"saved {out_path} ({out_path.stat().st_size / 1e3:.0f} kB)")
    return result


def _prior_weights(y: np.ndarray, full: np.ndarray, power: float) -> np.ndarray:
    """Sample weights ``(N_c / n_c) ** power`` (N_c: points of class c in the frames, n_c:
    sampled rows), normalised to mean 1: power 0 trains on the balanced sample, 1 on the
    data's class prior."""
    n = np.bincount(y, minlength=NUM_CLASSES).astype(np.float64)
    w = np.ones(NUM_CLASSES)
    present = n > 0
    w[present] = (full[present] / n[present]) ** power
    w = w[y]
    return w / w.mean()


class _InMemoryModel:
    """The LoadedModel surface ReferenceSegmenter needs, for a model not yet saved."""

    def __init__(self, estimator):
        self.estimator = estimator
        self.classes = tuple(int(c) for c in estimator.classes_)
        self.path = Path("<in memory>")
        self.model_id = "in-memory"

    def predict_proba(self, X):
        return self.estimator.predict_proba(X)


def evaluate_segmenter(model, split: str = "reference_test", *, sequences=None,
                       frames: int | None = None, verbose: bool = False) -> dict:
    """Confusion matrix, per-class IoU, mIoU and accuracy of ``model`` (a
    ReferenceSegmenter or a model path) over all points of ``split``'s frames.

    ``unlabeled`` ground truth is ignored; mIoU averages the classes present in the
    ground truth (see :func:`lidar_quality_core.metrics.mean_iou`).
    """
    from lidar_sim.frames import split_frames

    seg = model if isinstance(model, ReferenceSegmenter) else ReferenceSegmenter.load(model)
    cm = np.zeros((NUM_CLASSES, NUM_CLASSES), dtype=np.int64)
    n_frames, t_pred = 0, 0.0
    for fr in split_frames(split, sequences=sequences, frames=frames):
        t0 = time.perf_counter()
        pred = seg.predict(fr.xyz, fr.intensity, fr.ring)
        t_pred += time.perf_counter() - t0
        cm += qm.confusion_matrix(fr.semantic, pred, NUM_CLASSES, ignore=UNLABELED)
        n_frames += 1
    iou = qm.per_class_iou(cm)
    present = cm.sum(axis=1) > 0
    out = {
        "split": split,
        "n_frames": n_frames,
        "n_points": int(cm.sum()),
        "miou": qm.mean_iou(cm, ignore=UNLABELED),
        "accuracy": float(np.trace(cm) / max(cm.sum(), 1)),
        "per_class_iou": {CLASS_NAMES[c]: (round(float(iou[c]), 4) if present[c] else None)
                          for c in range(NUM_CLASSES) if c != UNLABELED},
        "confusion": cm.tolist(),
        "ms_per_frame": round(1e3 * t_pred / max(n_frames, 1), 1),
    }
    if verbose:
        print(f"  {split}: {n_frames} frames, {out['n_points']} points, mIoU "
              f"{out['miou']:.3f}, accuracy {out['accuracy']:.3f}, "
              f"{out['ms_per_frame']} ms / frame")
        for name, v in out["per_class_iou"].items():
            print(f"    {name:13s} IoU {'-' if v is None else f'{v:.3f}'}")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m reference_perception.segmenter",
                                 description="Train / evaluate the reference segmenter.")
    sub = ap.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train", help="train on reference_train, evaluate, save")
    t.add_argument("--out", default=str(DEFAULT_MODEL_PATH))
    t.add_argument("--per-class", type=int, default=600)
    t.add_argument("--hidden", default="64,32", help="hidden layer sizes, comma separated")
    t.add_argument("--epochs", type=int, default=15)
    t.add_argument("--prior-power", type=float, default=0.5)
    t.add_argument("--sequences", default=None, help="train sequences, e.g. 0,1,2")
    t.add_argument("--frames", type=int, default=None)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--threads", type=int, default=1, help="BLAS threads for training")
    t.add_argument("--no-test", action="store_true", help="skip the held-out evaluation")
    e = sub.add_parser("evaluate", help="evaluate a saved model on a split")
    e.add_argument("--model", default=str(DEFAULT_MODEL_PATH))
    e.add_argument("--split", default="reference_test")
    e.add_argument("--sequences", default=None)
    e.add_argument("--frames", type=int, default=None)
    e.add_argument("--json", default=None, help="also write the results to this file")
    args = ap.parse_args(argv)
    seqs = None if args.sequences is None else [int(s) for s in args.sequences.split(",")]
    if args.cmd == "train":
        train_segmenter(args.out, per_class=args.per_class,
                        hidden=tuple(int(h) for h in args.hidden.split(",")),
                        epochs=args.epochs, prior_power=args.prior_power, sequences=seqs,
                        frames=args.frames, seed=args.seed, threads=args.threads,
                        test_split=None if args.no_test else "reference_test")
        return 0
    ev = evaluate_segmenter(args.model, args.split, sequences=seqs, frames=args.frames,
                            verbose=True)
    if args.json:
        Path(args.json).write_text(json.dumps(ev, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
