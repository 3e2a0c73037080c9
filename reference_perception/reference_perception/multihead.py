"""The multi-head (MIMO-style) detector: one shared front end, K independently trained heads.

The front end (ground, multi-scale clusters, box fits, features: ``proposals``) runs once
per frame. Each head k has its own three models, trained on its own bootstrap sample of
the training candidates with its own seeds (the ensemble-like diversity LiDAR-MIMO gets
from independently fed heads):

* a classifier: class logits over ``PROB_NAMES`` (background + 4 thing classes; the logits
  are log-probabilities, so ``softmax(logits)`` gives the head's class distribution back);
* a box refinement (residuals in the candidate's frame, as the reference detector's);
* a variance regressor: the learned aleatoric estimate, a Poisson-deviance regression of
  the squared residuals of the box refinement on held-out sequences (two-fold cross
  fitting inside the head's sample), so it predicts E[residual^2] = the variance. The
  local variances are turned into variances of the box parameters x, y, z, l, w, h, yaw
  (centre variances rotated to the sensor frame).

Each head runs its own NMS (as in LiDAR-MIMO); the heads share the proposal set (the
candidates any head scores at least ``proposal_threshold``). Far, sparse objects have
features the training data covers thinly, so the heads disagree more there: measured by
``head_disagreement`` and printed by ``evaluate``.

CLI: ``python -m reference_perception.multihead train|evaluate [--heads K]``.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lidar_quality_core.iou import iou_bev_pairs

from .detector import (PROB_NAMES, TARGET_NAMES, DetectorConfig, _check_classes, _classifier,
                       _read_config, _reg_rows, _regressor, _score_label, _threads_one,
                       collect_training_data, decode_residuals, default_model_dir,
                       evaluate_outputs, gt_ignore_mask, proposal_targets, run_nms)
from .proposals import FEATURE_NAMES, Proposals, compute_proposals

__all__ = ["MAX_HEADS", "VARIANCE_NAMES", "HeadOutput", "MultiHeadOutput", "MultiHeadDetector",
           "train_multihead", "evaluate_multihead", "head_disagreement", "main"]

MAX_HEADS = 4
CONFIG_NAME = "multihead.json"
VARIANCE_NAMES = tuple(f"var_{t}" for t in TARGET_NAMES)
PARAM_NAMES = ("x", "y", "z", "l", "w", "h", "yaw")
_MIN_VAR = 1e-6


def head_files(k: int) -> dict[str, str]:
    return {"classifier": f"head{k}_classifier.ubj", "box_regressor": f"head{k}_box.ubj",
            "variance_regressor": f"head{k}_variance.ubj"}


def _variance_regressor(seed: int):
    # Poisson deviance with a log link: an unbiased estimate of E[r^2] from noisy r^2
    # (regressing log r^2 would be biased low by E[log chi2_1] ~ -1.27).
    return _regressor(seed, objective="count:poisson", n_estimators=30, max_depth=5,
                      learning_rate=0.3, max_delta_step=0.7, multi_strategy="multi_output_tree")


def _head_regressor(seed: int):
    # one tree per round for all 7 targets (vector leaves): a third of the size of one
    # tree per target at about the same held-out error
    return _regressor(seed, n_estimators=40, max_depth=6, learning_rate=0.2,
                      multi_strategy="multi_output_tree")


def train_multihead(out_dir=None, *, num_heads: int = 2, split: str = "reference_train",
                    sequences=None, frames=None, cfg: DetectorConfig = DetectorConfig(),
                    cache=None, seed: int = 0, log=print) -> dict:
    """Train ``num_heads`` heads on bootstrap samples of ``split``'s candidates; save them
    with ``multihead.json`` to ``out_dir``."""
    from lidar_quality_core.model_store import save_model

    if not 1 <= num_heads <= MAX_HEADS:
        raise ValueError(f"num_heads must be in 1..{MAX_HEADS}, got {num_heads}")
    out = Path(out_dir) if out_dir is not None else default_model_dir()
    out.mkdir(parents=True, exist_ok=True)
    data = collect_training_data(split, sequences=sequences, frames=frames, cfg=cfg.frontend,
                                 cache=cache, log=log)
    X, y, D, seq = data["X"], data["label"], data["deltas"], data["sequence"]
    _check_classes(y)
    n = len(y)
    reg_ok = np.zeros(n, bool)
    reg_ok[_reg_rows(data)] = True
    heads = []
    for k in range(num_heads):
        t0 = time.time()
        rng = np.random.default_rng([seed, k])
        boot = rng.integers(0, n, n)                       # bootstrap rows (with repeats)
        # smaller than the reference detector's models: K heads share a 3 MB budget
        clf = _classifier(seed=1000 * seed + k, colsample_bytree=0.7, subsample=0.9,
                          n_estimators=40, max_depth=6, learning_rate=0.2,
                          multi_strategy="multi_output_tree")
        clf.fit(X[boot], y[boot])
        fg = boot[reg_ok[boot]]
        # two-fold cross-fitting by sequence (by frame with a single sequence):
        # residuals on data the refinement did not see
        unit = seq[fg] if len(np.unique(seq[fg])) > 1 else data["frame"][fg]
        uu = np.unique(unit)
        if len(uu) < 2:
            raise ValueError("the variance regressor needs training data of >= 2 frames")
        fold = np.isin(unit, rng.permutation(uu)[: len(uu) // 2])
        oof = np.empty((len(fg), len(TARGET_NAMES)))
        for f in (False, True):
            tr, te = fg[fold != f], fold == f
            oof[te] = _head_regressor(1000 * seed + k).fit(X[tr], D[tr]).predict(X[fg[te]])
        r2 = (D[fg] - oof) ** 2
        var = _variance_regressor(1000 * seed + k)
        var.fit(X[fg], r2)
        box = _head_regressor(1000 * seed + k)
        box.fit(X[fg], D[fg])
        files = head_files(k)
        training = {"split": split, "sequences": sequences, "frames": frames, "head": k,
                    "bootstrap_seed": [seed, k], "n_candidates": int(n),
                    "n_foreground": int(len(fg)), "variance": "poisson regression of squared "
                    "2-fold out-of-sequence residuals of the box refinement"}
        save_model(clf, out / files["classifier"], feature_names=FEATURE_NAMES,
                   task="multiclass", class_names=PROB_NAMES, training_data=training)
        save_model(box, out / files["box_regressor"], feature_names=FEATURE_NAMES,
                   task="regression", target_names=TARGET_NAMES, training_data=training)
        save_model(var, out / files["variance_regressor"], feature_names=FEATURE_NAMES,
                   task="regression", target_names=VARIANCE_NAMES, training_data=training)
        rmse = np.sqrt(r2.mean(axis=0))
        log(f"head {k}: {len(fg)} foreground rows, out-of-fold residual rms "
            + ", ".join(f"{t}={v:.2f}" for t, v in zip(TARGET_NAMES, rmse))
            + f" ({time.time() - t0:.0f} s)")
        heads.append(files)
    info = {"split": split, "sequences": sequences, "frames": frames, "seed": seed}
    (out / CONFIG_NAME).write_text(json.dumps(
        {**cfg.to_dict(), "num_heads": num_heads, "heads": heads,
         "prob_names": list(PROB_NAMES), "training": info}, indent=2) + "\n")
    log(f"saved {num_heads} heads to {out}")
    return info


# ------------------------------------------------------------------ inference
@dataclass
class HeadOutput:
    """One head's view of the shared proposals (P) and its own NMS result."""

    logits: np.ndarray         # (P, 5) class logits (log-probabilities), PROB_NAMES order
    class_probs: np.ndarray    # (P, 5) softmax(logits)
    labels: np.ndarray         # (P,) our class ids (best foreground class)
    scores: np.ndarray         # (P,) probability of that class
    boxes: np.ndarray          # (P, 7) refined boxes x, y, z, l, w, h, yaw
    variances: np.ndarray      # (P, 7) predicted variance of x, y, z, l, w, h, yaw
    keep: np.ndarray           # (K,) proposal indices of this head's detections
    suppressed_by: np.ndarray  # (P,) suppressing survivor (proposal index), -1 otherwise

    @property
    def det_boxes(self) -> np.ndarray:
        return self.boxes[self.keep]

    @property
    def det_scores(self) -> np.ndarray:
        return self.scores[self.keep]

    @property
    def det_labels(self) -> np.ndarray:
        return self.labels[self.keep]


@dataclass
class MultiHeadOutput:
    """All heads' outputs of one frame over the shared proposals (P)."""

    heads: list[HeadOutput]
    fitted_boxes: np.ndarray   # (P, 7) shared box fits before refinement
    candidate: np.ndarray      # (P,) front-end candidate index
    cluster: np.ndarray        # (P,) front-end cluster index
    timings_ms: dict = field(default_factory=dict)

    @property
    def num_heads(self) -> int:
        return len(self.heads)

    # a sequence of its heads: ``for head in out``, ``out[k]``, ``len(out)``
    def __iter__(self):
        return iter(self.heads)

    def __getitem__(self, k: int) -> HeadOutput:
        return self.heads[k]

    def __len__(self) -> int:
        return len(self.heads)


def local_to_param_variance(boxes: np.ndarray, local_var: np.ndarray) -> np.ndarray:
    """Variances of (along, across, z, l, w, h, yaw) residuals -> of x, y, z, l, w, h, yaw
    (the centre's along / across variances rotated into the sensor frame)."""
    c2, s2 = np.cos(boxes[:, 6]) ** 2, np.sin(boxes[:, 6]) ** 2
    v = np.maximum(np.asarray(local_var, np.float64), _MIN_VAR)
    out = v.copy()
    out[:, 0] = c2 * v[:, 0] + s2 * v[:, 1]
    out[:, 1] = s2 * v[:, 0] + c2 * v[:, 1]
    return out


class MultiHeadDetector:
    """K heads on a shared front end, loaded from ``model_dir`` (``multihead.json``)."""

    def __init__(self, model_dir=None, num_heads: int | None = None, **overrides):
        from lidar_quality_core.model_store import load_model

        self.model_dir = Path(model_dir) if model_dir is not None else default_model_dir()
        raw = _read_config(self.model_dir, CONFIG_NAME)
        raw.update(overrides)
        self.config = DetectorConfig.from_dict(raw)
        avail = raw["heads"]
        k = len(avail) if num_heads is None else int(num_heads)
        if not 1 <= k <= len(avail):
            raise ValueError(f"{self.model_dir}: {len(avail)} trained heads, asked for {k}")
        self.heads = []
        for files in avail[:k]:
            clf = load_model(self.model_dir / files["classifier"], expected_features=FEATURE_NAMES,
                             expected_task="multiclass")
            if tuple(clf.class_names) != PROB_NAMES:
                raise ValueError(f"{clf.path}: classes {clf.class_names} are not {PROB_NAMES}")
            box = load_model(self.model_dir / files["box_regressor"],
                             expected_features=FEATURE_NAMES, expected_task="regression")
            var = load_model(self.model_dir / files["variance_regressor"],
                             expected_features=FEATURE_NAMES, expected_task="regression")
            for m in (clf, box, var):
                _threads_one(m)
            self.heads.append((clf, box, var))

    @property
    def num_heads(self) -> int:
        return len(self.heads)

    def proposals(self, xyz, intensity, ring=None) -> Proposals:
        return compute_proposals(xyz, intensity, ring, self.config.frontend)

    def detect(self, xyz, intensity, ring=None) -> MultiHeadOutput:
        return self.detect_proposals(self.proposals(xyz, intensity, ring))

    def detect_proposals(self, props: Proposals) -> MultiHeadOutput:
        """Run every head on a front-end result (computed once for all heads)."""
        t0 = time.perf_counter()
        cfg = self.config
        probs = [clf.predict_proba(props.features) for clf, _, _ in self.heads]
        best = np.max([_score_label(p)[1] for p in probs], axis=0) if len(props) else np.zeros(0)
        sel = np.flatnonzero(best >= cfg.proposal_threshold)
        F = props.features[sel]
        fitted = props.boxes[sel]
        heads = []
        t_nms = 0.0
        for (_, box, var), p in zip(self.heads, probs):
            p = p[sel]
            labels, scores = _score_label(p)
            boxes = decode_residuals(fitted, box.predict_value(F))
            variances = local_to_param_variance(boxes, var.predict_value(F))
            t1 = time.perf_counter()
            keep, sup = run_nms(boxes, scores, cfg)
            t_nms += time.perf_counter() - t1
            heads.append(HeadOutput(logits=np.log(np.clip(p, 1e-7, 1.0)), class_probs=p,
                                    labels=labels, scores=scores, boxes=boxes,
                                    variances=variances, keep=keep, suppressed_by=sup))
        total = (time.perf_counter() - t0) * 1e3
        timings = dict(props.timings_ms, models=total - t_nms * 1e3, nms=t_nms * 1e3)
        return MultiHeadOutput(heads=heads, fitted_boxes=fitted, candidate=sel,
                               cluster=props.cluster[sel], timings_ms=timings)


# ------------------------------------------------------------------ disagreement
def proposal_disagreement(out: MultiHeadOutput) -> dict[str, np.ndarray]:
    """Per proposal, how much the heads disagree: ``score_std`` (std over heads of the
    foreground probability 1 - p_background), ``box_1_iou`` (mean over head pairs of
    1 - BEV IoU of their refined boxes), ``centre_spread`` (rms distance of the heads'
    box centres to their mean, m)."""
    fg = np.stack([1.0 - h.class_probs[:, 0] for h in out.heads])
    boxes = np.stack([h.boxes for h in out.heads])
    K = len(out.heads)
    pair = [1.0 - iou_bev_pairs(boxes[a], boxes[b]) for a in range(K) for b in range(a + 1, K)]
    centre = boxes[:, :, :2]
    spread = np.sqrt(((centre - centre.mean(axis=0)) ** 2).sum(axis=2).mean(axis=0))
    return {"score_std": fg.std(axis=0),
            "box_1_iou": np.mean(pair, axis=0) if pair else np.zeros(boxes.shape[1]),
            "centre_spread": spread}


def head_disagreement(out: MultiHeadOutput, props: Proposals, frame) -> dict[str, np.ndarray]:
    """Disagreement of the proposals that belong to a ground-truth object (training label
    rule of ``proposal_targets``), with that object's BEV range: arrays ``range`` plus the
    measures of ``proposal_disagreement``."""
    t = proposal_targets(props, frame)
    gi = t.gt_index[out.candidate]
    on = gi >= 0
    d = proposal_disagreement(out)
    gt = np.asarray(frame.gt_boxes, np.float64).reshape(-1, 7)
    res = {k: v[on] for k, v in d.items()}
    res["range"] = np.hypot(gt[gi[on], 0], gt[gi[on], 1])
    return res


RANGE_BINS = (0.0, 15.0, 30.0, 45.0, 60.0, 80.0)
NEAR, FAR = 20.0, 40.0


def summarize_disagreement(parts: list[dict], log=print) -> dict:
    """Mean disagreement per range bin and near (< 20 m) vs far (> 40 m)."""
    cat = {k: np.concatenate([p[k] for p in parts]) if parts else np.zeros(0) for k in
           ("range", "score_std", "box_1_iou", "centre_spread")}
    r = cat["range"]
    keys = ("score_std", "box_1_iou", "centre_spread")
    log(f"{'range (m)':12s} {'n':>6s} " + " ".join(f"{k:>13s}" for k in keys))
    for lo, hi in zip(RANGE_BINS[:-1], RANGE_BINS[1:]):
        m = (r >= lo) & (r < hi)
        if m.any():
            log(f"{f'{lo:.0f}-{hi:.0f}':12s} {int(m.sum()):6d} "
                + " ".join(f"{cat[k][m].mean():13.4f}" for k in keys))
    out = {}
    for name, m in (("near", r < NEAR), ("far", r > FAR)):
        out[name] = {k: float(cat[k][m].mean()) if m.any() else float("nan") for k in keys}
        out[name]["n"] = int(m.sum())
    log(f"near (< {NEAR:.0f} m) vs far (> {FAR:.0f} m): "
        + ", ".join(f"{k} {out['near'][k]:.4f} vs {out['far'][k]:.4f}" for k in keys))
    return out


def evaluate_multihead(model_dir=None, *, num_heads: int | None = None,
                       split: str = "reference_test", sequences=None, frames=None,
                       max_frames: int | None = None, log=print) -> dict:
    """Per-head AP / ECE, far-vs-near head disagreement and timing on ``split``."""
    from lidar_sim.frames import split_frames

    det = MultiHeadDetector(model_dir, num_heads)
    max_range = det.config.frontend.cluster.max_range
    records = [[] for _ in range(det.num_heads)]
    parts, times, n_props = [], [], []
    for i, f in enumerate(split_frames(split, sequences=sequences, frames=frames)):
        if max_frames is not None and i >= max_frames:
            break
        t0 = time.perf_counter()
        props = det.proposals(f.xyz, f.intensity, f.ring)
        o = det.detect_proposals(props)
        times.append((time.perf_counter() - t0) * 1e3)
        ign = gt_ignore_mask(f, max_range)
        for k, h in enumerate(o.heads):
            records[k].append((h.det_boxes, h.det_scores, h.det_labels, f, ign))
        parts.append(head_disagreement(o, props, f))
        n_props.append(len(o.candidate))
    log(f"{split}: {len(times)} frames, {det.num_heads} heads, GT ignored if < 5 points or "
        f"beyond {max_range:.0f} m; proposals / frame {np.mean(n_props):.0f}")
    res = {"heads": []}
    for k in range(det.num_heads):
        log(f"--- head {k}")
        res["heads"].append(evaluate_outputs(records[k], log=log))
    log("--- head disagreement on proposals of ground-truth objects, by object range")
    res["disagreement"] = summarize_disagreement(parts, log=log)
    res["ms_median"] = float(np.median(times))
    log(f"time per frame, front end + {det.num_heads} heads (this machine, shared cores): "
        f"median {res['ms_median']:.0f} ms")
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m reference_perception.multihead",
                                 description="Train or evaluate the multi-head detector.")
    sub = ap.add_subparsers(dest="cmd", required=True)
    tr = sub.add_parser("train", help="fit K heads on reference_train, save to the model dir")
    tr.add_argument("--out", default=None, help="model directory (default models/reference)")
    tr.add_argument("--heads", type=int, default=2, help=f"number of heads, 1..{MAX_HEADS}")
    tr.add_argument("--split", default="reference_train")
    tr.add_argument("--sequences", type=int, nargs="*", default=None)
    tr.add_argument("--seed", type=int, default=0)
    tr.add_argument("--cache", default=None, help="npz cache of the training candidates")
    ev = sub.add_parser("evaluate", help="per-head AP, ECE, disagreement on reference_test")
    ev.add_argument("--models", default=None, help="model directory (default models/reference)")
    ev.add_argument("--heads", type=int, default=None, help="use the first K heads")
    ev.add_argument("--split", default="reference_test")
    ev.add_argument("--sequences", type=int, nargs="*", default=None)
    ev.add_argument("--max-frames", type=int, default=None)
    args = ap.parse_args(argv)
    def log(*a):
        print(*a, flush=True)
    if args.cmd == "train":
        train_multihead(args.out, num_heads=args.heads, split=args.split,
                        sequences=args.sequences, cache=args.cache, seed=args.seed, log=log)
    else:
        evaluate_multihead(args.models, num_heads=args.heads, split=args.split,
                           sequences=args.sequences, max_frames=args.max_frames, log=log)
    return 0


if __name__ == "__main__":
    sys.exit(main())
