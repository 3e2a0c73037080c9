"""Adaptation of a shipped meta model pair to the user's detector and data from a few
labelled frames (issue 18): the method-independent part of ``lmd-adapt``, ``lms-adapt``
and ``mimo-adapt``.

Candidates, per task (confidence classifier, IoU regressor), each fitted on the user's
rows, from the simplest:

* ``shipped``: the base model unchanged;
* ``score``: the user's own signal alone (the detector score, the mean entropy) through a
  regularised logistic / linear map: Platt scaling of the detector's score;
* ``recalibrate``: the base model's output and that signal through the same kind of map
  (``lidar_quality_core.recalibration``): three coefficients, usable from one frame;
* ``continue``: the base XGBoost model's trees plus ``CONTINUE_ROUNDS`` more, fitted to
  the user's rows (shallower, same learning rate);
* ``fresh``: a new model of the trainers' kind fitted on the user's rows only.

The choice is made by cross validation over the user's frames, grouped by sequence when
there are at least three, else by blocks of ``BLOCK_FRAMES`` consecutive frames when there
are at least three blocks (neighbouring frames see the same objects), else by frame; one
frame is split by rows, and the result says so. The score is the out-of-fold Brier score
(classifier) or squared error (regressor) on the rows every candidate predicted; the
simplest candidate within one standard error (paired, over the groups) of the best is
taken, because a few frames do not tell small differences apart; from fewer than
``MIN_FRAMES_FOR_TREES`` frames only the candidates with a few coefficients (``SIMPLE``)
can be chosen. Uncertainty: 95 %
intervals of every out-of-fold metric from a bootstrap over the groups, so a user with
three frames sees how little three frames say. The chosen candidates are then fitted on
all rows.
"""
from __future__ import annotations

import json
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from lidar_quality_core import meta_model
from lidar_quality_core import metrics as M
from .report import round_floats
from lidar_quality_core.recalibration import (RecalibratedClassifier, RecalibratedRegressor,
                                              logit)

__all__ = ["STRATEGIES", "CONTINUE_ROUNDS", "AdaptData", "AdaptResult", "fit_candidate",
           "adapt", "evaluate", "predict", "save_adapted", "subset_frames",
           "frame_blocks", "take_in_turn", "add_adapt_arguments", "candidates_of",
           "one_se_choice", "profile_of", "BLOCK_FRAMES", "SIMPLE", "MIN_FRAMES_FOR_TREES"]

STRATEGIES = ("shipped", "score", "recalibrate", "continue", "fresh")
BLOCK_FRAMES = 5
#: candidates with a few coefficients, the only ones chosen from fewer than
#: MIN_FRAMES_FOR_TREES frames (a frame or two cannot show that more trees generalise)
SIMPLE = ("shipped", "score", "recalibrate")
MIN_FRAMES_FOR_TREES = 5
TASKS = ("classification", "regression")
CONTINUE_ROUNDS = 60
N_FOLDS = 5
N_BOOT = 400
RECAL_C = 1.0  # inverse L2 strength of the logistic recalibration (standardised inputs)


@dataclass
class AdaptData:
    """The user's labelled rows: features, targets, frame of each row and the column that
    carries the user's own signal (``signal``: the detector score for LMD / MIMO with
    ``transform="logit"``, ``mean_E`` for LMS with ``"identity"``)."""

    X: np.ndarray
    tp: np.ndarray
    iou: np.ndarray
    frame: np.ndarray
    feature_names: tuple
    signal: str
    transform: str = "logit"
    info: dict = field(default_factory=dict)
    block: np.ndarray | None = None     # (n,) block of consecutive frames (optional)
    sequence: np.ndarray | None = None  # (n,) sequence (bag, drive) of each row (optional)

    def __post_init__(self):
        self.X = np.asarray(self.X, np.float64)
        self.tp = np.asarray(self.tp, bool).reshape(-1)
        self.iou = np.asarray(self.iou, np.float64).reshape(-1)
        self.frame = np.asarray(self.frame).astype(str).reshape(-1)
        n = len(self.tp)
        if self.X.shape != (n, len(self.feature_names)) or len(self.iou) != n or \
                len(self.frame) != n:
            raise ValueError(f"rows disagree: X {self.X.shape}, tp {n}, iou {len(self.iou)}, "
                             f"frame {len(self.frame)}, {len(self.feature_names)} features")
        self.block = self.frame if self.block is None else \
            np.asarray(self.block).astype(str).reshape(-1)
        self.sequence = self.block if self.sequence is None else \
            np.asarray(self.sequence).astype(str).reshape(-1)
        if len(self.block) != n or len(self.sequence) != n:
            raise ValueError(f"block / sequence have {len(self.block)} / {len(self.sequence)} "
                             f"rows, expected {n}")
        if self.signal not in self.feature_names:
            raise ValueError(f"signal column {self.signal!r} is not a feature")

    def __len__(self) -> int:
        return len(self.tp)

    @property
    def column(self) -> int:
        return list(self.feature_names).index(self.signal)

    @property
    def frames(self) -> list[str]:
        return list(dict.fromkeys(self.frame.tolist()))

    def rows(self, idx) -> "AdaptData":
        return AdaptData(self.X[idx], self.tp[idx], self.iou[idx], self.frame[idx],
                         self.feature_names, self.signal, self.transform, self.info,
                         self.block[idx], self.sequence[idx])

    def baseline(self) -> np.ndarray | None:
        """The signal as a confidence (a detector score), None for another kind."""
        return self.X[:, self.column] if self.transform == "logit" else None


def frame_blocks(frame_group, block_frames: int = BLOCK_FRAMES) -> np.ndarray:
    """(f,) block of each frame: ``<group>/<position in its group // block_frames>``
    (frames listed in recording order)."""
    g = np.asarray(frame_group).astype(str)
    pos = np.zeros(len(g), np.int64)
    seen: dict[str, int] = {}
    for k, name in enumerate(g.tolist()):
        pos[k] = seen.get(name, 0)
        seen[name] = pos[k] + 1
    return np.char.add(np.char.add(g, "/"), (pos // block_frames).astype(str))


def take_in_turn(sequence_of_frame, n: int | None) -> np.ndarray:
    """Sorted indices of ``n`` frames taken in turn from each sequence, in order within
    one (so five frames of two bags are not five of the first); all for None."""
    seq = np.asarray(sequence_of_frame)
    idx = np.arange(len(seq))
    if n is None or n >= len(idx):
        return idx
    by_seq = [idx[seq == s] for s in dict.fromkeys(seq.tolist())]
    order = [b[k] for k in range(max(len(b) for b in by_seq)) for b in by_seq if k < len(b)]
    return np.sort(np.asarray(order[:max(n, 0)], np.int64))


def subset_frames(data: AdaptData, frames: Sequence[str]) -> AdaptData:
    """The rows of ``frames``."""
    return data.rows(np.flatnonzero(np.isin(data.frame, np.asarray(frames, str))))


# --------------------------------------------------------------------------- candidates
def _is_xgb(est) -> bool:
    return type(est).__module__.startswith("xgboost")


def _standardise(Z):
    mu, sd = Z.mean(axis=0), Z.std(axis=0)
    return mu, np.where(sd > 1e-9, sd, 1.0)


def _recalibrate(task: str, base, data: AdaptData, *, signal_only: bool = False):
    Est = RecalibratedClassifier if task == "classification" else RecalibratedRegressor
    raw = data.X[:, data.column]
    sig = logit(raw) if data.transform == "logit" else raw
    fill = float(np.nanmean(sig)) if np.isfinite(sig).any() else 0.0
    proto = Est(base, [1.0, 0.0], 0.0, column=data.column, transform=data.transform,
                fill=fill)
    Z = proto.inputs(data.X, Est.base_output(base, data.X))
    mu, sd = _standardise(Z)
    Zs = (Z - mu) / sd
    if signal_only:  # the base output gets weight 0: Platt scaling of the signal
        Zs = Zs[:, 1:]
    if task == "classification":
        from sklearn.linear_model import LogisticRegression

        m = LogisticRegression(C=RECAL_C, max_iter=1000).fit(Zs, data.tp.astype(int))
        w, b = m.coef_.reshape(-1), float(m.intercept_[0])
    else:
        from sklearn.linear_model import Ridge

        m = Ridge(alpha=1.0).fit(Zs, data.iou)
        w, b = np.asarray(m.coef_).reshape(-1), float(m.intercept_)
    if signal_only:
        w = np.concatenate([[0.0], w])
    # back to unstandardised inputs: w·(z - mu)/sd + b
    coef = w / sd
    return Est(base, coef, b - float(coef @ mu), column=data.column, transform=data.transform,
               fill=fill)


def _continue(task: str, base, data: AdaptData, seed: int):
    import xgboost as xgb

    params = {k: v for k, v in base.get_params().items() if v is not None}
    params.update(n_estimators=CONTINUE_ROUNDS, max_depth=3, random_state=seed, n_jobs=1)
    est = (xgb.XGBClassifier if task == "classification" else xgb.XGBRegressor)(**params)
    y = data.tp.astype(int) if task == "classification" else data.iou
    est.fit(data.X, y, xgb_model=base.get_booster())
    return est


def _both_classes(data: AdaptData) -> bool:
    return 0 < int(data.tp.sum()) < len(data)


def fit_candidate(name: str, task: str, base, data: AdaptData, *, kind: str = "xgboost",
                  seed: int = 0):
    """The ``name`` candidate for ``task`` fitted on ``data`` (``base``: the shipped
    estimator), or None when it cannot be fitted there (one class only; ``continue`` on a
    base that is not XGBoost)."""
    if name == "shipped":
        return base
    if task == "classification" and not _both_classes(data):
        return None
    if name in ("recalibrate", "score"):
        return _recalibrate(task, base, data, signal_only=name == "score")
    if name == "continue":
        return _continue(task, base, data, seed) if _is_xgb(base) else None
    if name == "fresh":
        y = data.tp.astype(float) if task == "classification" else data.iou
        return meta_model.fit_estimator(kind, task, data.X, y, seed=seed)
    raise ValueError(f"unknown candidate {name!r} (known: {', '.join(STRATEGIES)})")


def predict(est, task: str, X) -> np.ndarray:
    return np.clip(meta_model.predict(est, task, X), 0.0, 1.0)


# --------------------------------------------------------------------------- metrics
def evaluate(tp, iou, conf=None, pred=None) -> dict:
    """AUROC, ECE, Brier of ``conf`` and R², MAE of ``pred`` (either may be None)."""
    out = {}
    tp = np.asarray(tp, float)
    if conf is not None:
        both = 0 < tp.sum() < len(tp)
        out.update(auroc=M.auroc(tp, conf) if both else float("nan"),
                   ece=M.ece(tp, conf) if len(tp) else float("nan"),
                   brier=float(np.mean((conf - tp) ** 2)) if len(tp) else float("nan"))
    if pred is not None:
        out.update(r2=M.r2(iou, pred) if len(iou) > 1 else float("nan"),
                   mae=M.mae(iou, pred) if len(iou) else float("nan"))
    return out


def _bootstrap(units: np.ndarray, tp, iou, conf, pred, n_boot: int, seed: int) -> dict:
    """95 % percentile intervals of ``evaluate``'s metrics, resampling ``units``."""
    uniq, inv = np.unique(units, return_inverse=True)
    members = [np.flatnonzero(inv == u) for u in range(len(uniq))]
    rng = np.random.default_rng(seed)
    draws: dict[str, list] = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for _ in range(n_boot):
            pick = np.concatenate([members[u] for u in rng.integers(0, len(uniq), len(uniq))])
            m = evaluate(tp[pick], iou[pick], None if conf is None else conf[pick],
                         None if pred is None else pred[pick])
            for k, v in m.items():
                draws.setdefault(k, []).append(v)
    out = {}
    for k, v in draws.items():
        v = np.asarray(v, float)
        v = v[np.isfinite(v)]
        out[k] = [float(np.quantile(v, 0.025)), float(np.quantile(v, 0.975))] \
            if len(v) >= 10 else [float("nan"), float("nan")]
    return out


# --------------------------------------------------------------------------- adaptation
@dataclass
class AdaptResult:
    """What ``adapt`` chose, why, and the fitted pair."""

    classifier: object
    regressor: object
    chosen: dict              # {"classification": name, "regression": name}
    cv: dict                  # {name: {"metrics": {...}, "ci95": {...}}} (+ "detector score")
    scheme: str               # how the rows were split
    n_frames: int
    n_rows: int
    n_tp: int
    notes: list

    def record(self) -> dict:
        """JSON-ready summary (manifests, model card)."""
        return {"chosen": self.chosen, "cross_validation": self.cv, "scheme": self.scheme,
                "frames": self.n_frames, "rows": self.n_rows, "tp": self.n_tp,
                "notes": self.notes, "candidates": list(STRATEGIES),
                "continue_rounds": CONTINUE_ROUNDS}


def _folds(data: AdaptData, n_folds: int, seed: int) -> tuple[list, str, np.ndarray]:
    frames = data.frames
    seqs, blocks = np.unique(data.sequence), np.unique(data.block)
    if len(seqs) >= 3 and len(seqs) < len(frames):
        folds = meta_model.group_folds(data.sequence, n_folds, seed=seed)
        return folds, (f"{len(folds)}-fold cross validation grouped by sequence "
                       f"({len(frames)} frames of {len(seqs)} sequences)"), data.sequence
    if len(blocks) >= 3 and len(blocks) < len(frames):
        folds = meta_model.group_folds(data.block, n_folds, seed=seed)
        return folds, (f"{len(folds)}-fold cross validation grouped by blocks of consecutive "
                       f"frames ({len(frames)} frames in {len(blocks)} blocks)"), data.block
    if len(frames) >= 2:
        folds = meta_model.group_folds(data.frame, n_folds, seed=seed)
        return folds, (f"{len(folds)}-fold cross validation grouped by frame "
                       f"({len(frames)} frames)"), data.frame
    rows = np.arange(len(data)).astype(str)
    if len(data) < 2:
        return [], "no cross validation: a single row", rows
    folds = meta_model.group_folds(rows, n_folds, seed=seed)
    return folds, (f"one frame: {len(folds)}-fold cross validation over its "
                   f"{len(data)} rows (rows of one frame are not independent: optimistic)"), rows


def one_se_choice(losses: dict, units, order: Sequence[str]) -> str:
    """The simplest (first in ``order``) candidate whose mean loss is within one standard
    error of the best one's; the error is of the per-unit mean differences (paired)."""
    uniq, inv = np.unique(np.asarray(units), return_inverse=True)
    per = {s: np.bincount(inv, weights=v, minlength=len(uniq)) / np.bincount(
        inv, minlength=len(uniq)) for s, v in losses.items()}
    mean = {s: float(np.mean(v)) for s, v in per.items()}
    best = min(mean, key=lambda s: (mean[s], list(order).index(s)))
    for s in order:
        if s not in per:
            continue
        d = per[s] - per[best]
        se = float(np.std(d, ddof=1) / np.sqrt(len(d))) if len(d) > 1 else 0.0
        if mean[s] - mean[best] <= se:
            return s
    return best


def adapt(data: AdaptData, base_classifier, base_regressor, *, kind: str = "xgboost",
          strategies: Sequence[str] = STRATEGIES, n_folds: int = N_FOLDS, seed: int = 0,
          n_boot: int = N_BOOT, force: dict | None = None) -> AdaptResult:
    """Choose and fit the adapted pair (module docstring). ``force``: ``{task: name}`` to
    take a candidate regardless of the cross validation."""
    if not len(data):
        raise ValueError("no labelled rows to adapt on")
    for s in strategies:
        if s not in STRATEGIES:
            raise ValueError(f"unknown candidate {s!r} (known: {', '.join(STRATEGIES)})")
    bases = {"classification": base_classifier, "regression": base_regressor}
    folds, scheme, units = _folds(data, n_folds, seed)
    notes = []
    eligible = tuple(strategies)
    if len(data.frames) < MIN_FRAMES_FOR_TREES:
        eligible = tuple(s for s in strategies if s in SIMPLE) or ("shipped",)
        notes.append(f"{len(data.frames)} frame(s): only {', '.join(eligible)} can be chosen "
                     f"(tree candidates need {MIN_FRAMES_FOR_TREES} frames or more)")
    oof = {task: {s: np.full(len(data), np.nan) for s in strategies} for task in TASKS}
    for tr, va in folds:
        part = data.rows(tr)
        for task in TASKS:
            for s in strategies:
                est = fit_candidate(s, task, bases[task], part, kind=kind, seed=seed)
                if est is not None:
                    oof[task][s][va] = predict(est, task, data.X[va])
    cv, chosen = {}, {}
    for task in TASKS:
        y = data.tp.astype(float) if task == "classification" else data.iou
        ok = np.all([np.isfinite(oof[task][s]) for s in eligible], axis=0) if folds else \
            np.zeros(len(data), bool)
        usable = [s for s in strategies if np.isfinite(oof[task][s]).any()]
        if force and force.get(task):
            chosen[task] = force[task]
        elif ok.any():
            chosen[task] = one_se_choice({s: (p[ok] - y[ok]) ** 2 for s, p in oof[task].items()
                                          if s in eligible}, units[ok], eligible)
        else:
            chosen[task] = "shipped"
            notes.append(f"{task}: too few rows to compare candidates; the shipped model "
                         "is kept")
        for s in strategies:
            p = oof[task][s]
            if not np.isfinite(p).any():
                continue
            m = p if task == "classification" else None
            r = p if task == "regression" else None
            fin = np.isfinite(p)
            entry = cv.setdefault(s, {"metrics": {}, "ci95": {}, "rows": {}})
            entry["metrics"].update(evaluate(data.tp[fin], data.iou[fin],
                                             None if m is None else m[fin],
                                             None if r is None else r[fin]))
            entry["ci95"].update(_bootstrap(units[fin], data.tp[fin], data.iou[fin],
                                            None if m is None else m[fin],
                                            None if r is None else r[fin], n_boot, seed))
            entry["rows"][task] = int(fin.sum())
        missing = [s for s in strategies if s not in usable and s != "shipped"]
        if missing and folds:
            notes.append(f"{task}: {', '.join(missing)} could not be fitted in some folds "
                         "(one class only, or a base that is not XGBoost)")
    base_conf = data.baseline()
    if base_conf is not None:
        cv["detector score"] = {"metrics": evaluate(data.tp, data.iou, base_conf),
                                "ci95": _bootstrap(units, data.tp, data.iou, base_conf, None,
                                                   n_boot, seed),
                                "rows": {"classification": len(data)}}
    final = {}
    for task in TASKS:
        est = fit_candidate(chosen[task], task, bases[task], data, kind=kind, seed=seed)
        if est is None:
            notes.append(f"{task}: {chosen[task]} cannot be fitted on all rows (one class "
                         "only?); the shipped model is kept")
            chosen[task], est = "shipped", bases[task]
        final[task] = est
    if not _both_classes(data):
        notes.append(f"the labelled rows hold one class only ({int(data.tp.sum())} TP of "
                     f"{len(data)}): the confidence model cannot be adapted from them")
    return AdaptResult(final["classification"], final["regression"], chosen, cv, scheme,
                       len(data.frames), len(data), int(data.tp.sum()), notes)


# --------------------------------------------------------------------------- saving


def profile_of(data: AdaptData, extra: dict | None = None,
               extra_groups: dict | None = None, base: dict | None = None) -> dict:
    """The domain profile (JSON) of the user's rows: every feature plus ``extra``
    quantities (``extra_groups``: their sequences), quantiles from the user's rows. A few
    labelled frames cover a few scenes, too few to measure how much one scene differs
    from the next; so each quantity's ``spread`` is the larger of the user's (between
    sequences) and the ``base`` profile's (the base model's training scenes), and the
    monitor of an adapted model allows for at least the scene-to-scene variation of the
    base's training data."""
    from lidar_quality_core.domain_profile import DomainProfile, QuantityProfile

    own = DomainProfile.from_json(meta_model.training_profile(
        data.X, data.feature_names, extra, groups=data.sequence, extra_groups=extra_groups))
    if base:
        prior = DomainProfile.from_json(base).quantities
        own = DomainProfile({k: QuantityProfile(q.quantiles, q.count, q.missing, max(
            q.spread, prior[k].spread if k in prior else 0.0))
            for k, q in own.quantities.items()})
    return own.to_json()


def save_adapted(result: AdaptResult, out, prefix: str, data: AdaptData, *,
                 base_manifest: dict, base_paths: Sequence, sources: list, command: str,
                 profile_extra: dict | None = None, profile_groups: dict | None = None,
                 title: str) -> tuple[Path, Path]:
    """Save the adapted pair as ``OUT/<prefix>_{classifier,regressor}.joblib`` with
    manifests (the base's training settings, so the node checks them as before; the
    adaptation record; a domain profile of the user's rows) and ``OUT/MODEL_CARD.md``."""
    base_td = base_manifest.get("training_data") or {}
    training = {"settings": base_td.get("settings"), "sources": sources,
                "frames": result.n_frames, "boxes": result.n_rows, "tp": result.n_tp,
                "kind": "adapted", "command": command,
                "adapted_from": {"files": [str(p) for p in base_paths],
                                 "model_id": base_manifest.get("model_id"),
                                 "sources": base_td.get("sources")},
                "adaptation": round_floats(result.record())}
    for k in ("target", "tp_rule", "use_points", "class_aware", "merge_settings"):
        if k in base_td:
            training[k] = base_td[k]
    profile = profile_of(data, profile_extra, profile_groups, base_td.get("domain_profile"))
    metrics = {"cross_validation": round_floats(result.cv)}
    cpath, rpath = meta_model.save_pair(out, prefix, result.classifier, result.regressor,
                                        data.feature_names, training_data=training,
                                        classifier_metrics=metrics, regressor_metrics=metrics,
                                        compress=3, domain_profile=round_floats(profile))
    (Path(out) / "MODEL_CARD.md").write_text(model_card(result, title=title, sources=sources,
                                                        base_paths=base_paths,
                                                        command=command, files=(cpath, rpath)))
    return cpath, rpath


def _fmt(v, ci=None) -> str:
    if v is None or not np.isfinite(v):
        return "-"
    if ci and all(c is not None and np.isfinite(c) for c in ci):
        return f"{v:.3f} [{ci[0]:.3f}, {ci[1]:.3f}]"
    return f"{v:.3f}"


def cv_table(result: AdaptResult) -> list[str]:
    """Markdown rows: every candidate's out-of-fold metrics with 95 % intervals."""
    lines = ["| candidate | AUROC | ECE | Brier | R² | MAE |", "|---|---|---|---|---|---|"]
    for name, e in result.cv.items():
        m, c = e["metrics"], e["ci95"]
        mark = [t[:3] for t, s in result.chosen.items() if s == name]
        label = name + (f" (chosen: {', '.join('confidence' if t == 'cla' else 'IoU' for t in mark)})"
                        if mark else "")
        lines.append(f"| {label} | " + " | ".join(_fmt(m.get(k), c.get(k)) for k in
                                                  ("auroc", "ece", "brier", "r2", "mae")) + " |")
    return lines


def model_card(result: AdaptResult, *, title: str, sources: list, base_paths, command: str,
               files) -> str:
    lines = [f"# {title}", "",
             "Adapted from " + ", ".join(f"`{p}`" for p in base_paths) + " on the user's "
             "labelled data (`lidar_quality_training.adapt`).", "",
             "## Data", ""]
    for s in sources:
        lines.append(f"- {s.get('kind', 'data')}: `{s.get('path')}`")
    lines += [f"- {result.n_frames} frames, {result.n_rows} rows ({result.n_tp} TP).", "",
              "## Reproduce", "", "```", command, "```", "",
              "## Choice", "",
              f"Confidence: **{result.chosen['classification']}**; predicted IoU: "
              f"**{result.chosen['regression']}** ({result.scheme}; the simplest candidate "
              "within one standard error of the lowest out-of-fold Brier score / squared "
              "error). 95 % intervals: bootstrap over the cross-validation groups.", ""]
    lines += cv_table(result)
    if result.notes:
        lines += ["", "## Notes", ""] + [f"- {n}" for n in result.notes]
    if result.n_frames < 20:
        lines += ["", f"With {result.n_frames} frame(s) these estimates are uncertain (see the "
                  "intervals); label more frames of your data for a firmer choice."]
    lines += ["", "Files: " + ", ".join(f"`{Path(f).name}`" for f in files) + " (manifests "
              "beside them: schema, SHA-256, this record, a domain profile of the data above)."]
    return "\n".join(lines) + "\n"


def add_adapt_arguments(ap, shipped: str = "the shipped one") -> None:
    """The options every ``*-adapt`` command has: base pair, output, frames, candidates,
    folds, seed (``shipped``: which base pair the defaults are, in words)."""
    ap.add_argument("--base-classifier", type=Path, default=None,
                    help=f"meta classifier to adapt (default: {shipped})")
    ap.add_argument("--base-regressor", type=Path, default=None,
                    help=f"meta regressor to adapt (default: {shipped})")
    ap.add_argument("--out", type=Path, required=True, help="output model directory")
    ap.add_argument("--frames", type=int, default=None,
                    help="use only this many labelled frames (taken in turn from each sequence)")
    ap.add_argument("--candidates", default=",".join(STRATEGIES),
                    help=f"comma-separated subset of {', '.join(STRATEGIES)}")
    ap.add_argument("--folds", type=int, default=N_FOLDS, help="cross-validation folds")
    ap.add_argument("--seed", type=int, default=0)


def candidates_of(args) -> tuple[str, ...]:
    """``--candidates`` as a tuple of names."""
    return tuple(c.strip() for c in args.candidates.split(",") if c.strip())


def print_summary(prog: str, result: AdaptResult, files) -> None:
    print(f"{prog}: {result.n_frames} frames, {result.n_rows} rows ({result.n_tp} TP); "
          f"{result.scheme}")
    for line in cv_table(result):
        print("  " + line)
    print(f"{prog}: chosen: confidence {result.chosen['classification']}, IoU "
          f"{result.chosen['regression']}")
    for n in result.notes:
        print(f"{prog}: note: {n}", file=sys.stderr)
    for f in files:
        print(f"{prog}: wrote {f}")


def dumps(result: AdaptResult) -> str:
    return json.dumps(round_floats(result.record()), indent=1)
