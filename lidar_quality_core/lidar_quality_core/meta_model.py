"""Meta models shared by LMD, LMS and MIMO: estimators, grouped cross validation, greedy
forward selection, and the online classifier + regressor pair (numpy / sklearn / xgboost,
no rclpy).

* Estimator kinds (``KINDS``): ``xgboost`` (default of all three methods),
  ``gradient_boosting`` (scikit-learn's histogram gradient boosting), ``linear``
  (logistic / ridge regression), ``random_forest``, ``mlp``. Tree models take NaN features
  as they are (XGBoost and HistGradientBoosting learn a missing-value direction); the others
  impute the training median first and standardise.
* Cross validation is always over disjoint groups (sequences or sub-sequences, never random
  frames: consecutive frames are nearly identical). Classification metrics: accuracy,
  AUROC, AUPRC, ECE; regression: R^2 and MAE (``lidar_quality_core.metrics``).
* Greedy forward selection (LMD / LMS papers): start empty, add the feature whose model
  has the best mean validation AUROC (classification) or R^2 (regression) over the folds;
  stop at ``max_features`` or when the gain drops below ``min_gain`` (5e-4, the authors').
* ``MetaModels``: the classifier (confidence) and regressor (predicted IoU) of a node,
  loaded through ``model_store`` with the node's feature schema. Outputs are clipped to
  [0, 1]; a row whose features are all NaN (an invalid input the feature code flags) gets
  NaN, never a silent score.
* Training settings (``SETTING_RULES``): a feature schema does not say how the features
  were computed (LMD ``exact`` and ``threshold`` share one schema; a reordered class list
  keeps it). So ``MetaModels(..., settings=, method=)`` compares the settings the
  trainers record in the manifests (LMD / LMS ``training_data["settings"]``, MIMO
  ``training_data["merge_settings"]``) with the settings in use, before loading. What
  changes the meaning of a feature must be equal, or the model is refused with the
  setting, both values and the fix: LMD ``proposal_mode``, ``class_names`` (in order),
  ``class_score_features``; LMS ``class_names``, ``min_segment_points``; MIMO ``use_points``,
  ``class_names``, the merge's input convention (``score_type``, ``background_index``)
  and yaw ETV (``yaw_deviation``). What only shifts the feature distribution warns,
  naming both values: LMD thresholds of the mode in use; LMS image geometry
  (``channels``, ``width``, ``fov_up_deg``, ``fov_down_deg``), ``use_ring``,
  ``sum_tolerance``; MIMO ``num_heads``, ``eps``, ``voting``, ``min_cluster_size``,
  ``class_aware``, ``temperature``, ``yaw_variance``. Not compared: input conventions
  that the settings undo (LMS ``ring_field``, ``ring_zero_top``) and MIMO ``dbscan``
  (two implementations, same clusters). A manifest without recorded settings (an older
  model) loads with a warning that it cannot be checked.
"""
from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from . import metrics as M
from .model_store import (LoadedModel, ModelStoreError, ModelStoreWarning, SettingRule,
                          check_training_settings, load_model, read_manifest, save_model)
from .parameters import param

__all__ = ["KINDS", "TASKS", "make_estimator", "fit_estimator", "training_arrays", "predict",
           "group_folds", "FoldMetrics", "CVResult", "fit_folds", "cross_validate",
           "GreedyResult", "greedy_selection",
           "SETTINGS_SECTION", "SETTING_RULES", "settings_record", "check_settings",
           "MetaModels", "save_pair", "training_profile", "SIMULATED_DATA_DIR", "simulated_sources",
           "cv_folds_arg", "cv_fold_count"]

KINDS = ("xgboost", "gradient_boosting", "linear", "random_forest", "mlp")
TASKS = ("classification", "regression")


def _check(kind: str, task: str) -> None:
    if kind not in KINDS:
        raise ValueError(f"unknown meta model kind {kind!r} (known: {', '.join(KINDS)})")
    if task not in TASKS:
        raise ValueError(f"task must be one of {TASKS}, got {task!r}")


def make_estimator(kind: str, task: str, *, seed: int = 0, n_jobs: int = 1):
    """An unfitted estimator of ``kind`` for ``task``."""
    _check(kind, task)
    cls = task == "classification"
    if kind == "xgboost":
        import xgboost as xgb

        common = dict(n_estimators=300, max_depth=4, learning_rate=0.05, subsample=0.8,
                      colsample_bytree=0.8, min_child_weight=2.0, tree_method="hist",
                      n_jobs=n_jobs, random_state=seed)
        return (xgb.XGBClassifier(objective="binary:logistic", eval_metric="logloss", **common)
                if cls else xgb.XGBRegressor(objective="reg:squarederror", **common))
    if kind == "gradient_boosting":
        from sklearn.ensemble import HistGradientBoostingClassifier, HistGradientBoostingRegressor

        est = HistGradientBoostingClassifier if cls else HistGradientBoostingRegressor
        return est(max_iter=300, learning_rate=0.05, max_leaf_nodes=15, random_state=seed)
    from sklearn.impute import SimpleImputer
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    # keep_empty_features: a column that is all NaN in training (e.g. a class never seen)
    # must keep its place, or the fitted pipeline expects fewer columns than the schema.
    impute = SimpleImputer(strategy="median", keep_empty_features=True)
    if kind == "linear":
        from sklearn.linear_model import LogisticRegression, Ridge

        est = LogisticRegression(max_iter=2000, C=1.0) if cls else Ridge(alpha=1.0)
        return make_pipeline(impute, StandardScaler(), est)
    if kind == "random_forest":
        from sklearn.ensemble import RandomForestClassifier, RandomForestRegressor

        est = RandomForestClassifier if cls else RandomForestRegressor
        return make_pipeline(impute, est(n_estimators=200, min_samples_leaf=5, n_jobs=n_jobs,
                                         random_state=seed))
    from sklearn.neural_network import MLPClassifier, MLPRegressor

    est = MLPClassifier if cls else MLPRegressor
    return make_pipeline(impute, StandardScaler(),
                         est(hidden_layer_sizes=(64, 32), early_stopping=True, max_iter=500,
                             random_state=seed))


def training_arrays(X, y, task: str):
    """``(X, y)`` as the estimators take them: float64 ``(n, d)`` and finite ``(n,)``;
    classification ``y`` 0/1 as int64. ``ValueError`` naming what is wrong otherwise."""
    X = np.asarray(X, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64).reshape(-1)
    if X.ndim != 2 or X.shape[0] != y.shape[0]:
        raise ValueError(f"X must be (n, d) with n = len(y); got X {X.shape}, y {y.shape}")
    if not np.isfinite(y).all():
        raise ValueError("targets must be finite")
    if task == "classification":
        if not np.isin(y, (0.0, 1.0)).all():
            raise ValueError("classification targets must be 0/1")
        y = y.astype(np.int64)
    return X, y


def fit_estimator(kind: str, task: str, X, y, *, seed: int = 0, n_jobs: int = 1):
    """Fit a new ``kind`` estimator on ``(X, y)``; classification ``y`` is 0/1."""
    X, y = training_arrays(X, y, task)
    if task == "classification" and np.unique(y).size < 2:
        raise ValueError("classification needs both classes in the training data")
    est = make_estimator(kind, task, seed=seed, n_jobs=n_jobs)
    est.fit(X, y)
    return est


def predict(est, task: str, X) -> np.ndarray:
    """P(positive) for classification, the prediction for regression."""
    X = np.asarray(X, dtype=np.float64)
    if X.shape[0] == 0:
        return np.empty(0)
    if task == "classification":
        return np.asarray(est.predict_proba(X)[:, 1], dtype=np.float64)
    return np.asarray(est.predict(X), dtype=np.float64).reshape(-1)


def group_folds(groups, n_folds: int = 10, *, seed: int = 0):
    """``[(train_idx, val_idx), ...]`` with every group in exactly one validation fold.

    Groups are shuffled (seeded) and dealt round-robin; with fewer groups than
    ``n_folds`` there is one fold per group.
    """
    groups = np.asarray(groups)
    uniq = np.unique(groups)
    if uniq.size < 2:
        raise ValueError(f"cross validation needs at least 2 groups, got {uniq.size}")
    k = min(int(n_folds), uniq.size)
    if k < 2:
        raise ValueError(f"n_folds must be >= 2, got {n_folds}")
    order = np.random.default_rng(seed).permutation(uniq.size)
    fold_of_group = np.empty(uniq.size, dtype=np.int64)
    fold_of_group[order] = np.arange(uniq.size) % k
    fold = fold_of_group[np.searchsorted(uniq, groups)]
    return [(np.flatnonzero(fold != f), np.flatnonzero(fold == f)) for f in range(k)]


def cv_folds_arg(text: str) -> int:
    """``argparse`` type of the trainers' ``--cv-folds``: 0 (no cross validation) or >= 2."""
    import argparse

    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if n != 0 and n < 2:
        raise argparse.ArgumentTypeError(f"must be 0 (no cross validation) or >= 2, got {n}")
    return n


def cv_fold_count(groups, n_folds: int, *, what: str = "groups", hint: str = "") -> int:
    """The folds a grouped cross validation of ``n_folds`` runs on ``groups``: 0 for
    ``n_folds`` 0 (none), else ``min(n_folds, distinct groups)``. Fewer than 2 groups
    raise ``ValueError`` saying so and how to train anyway (``--cv-folds 0``, ``hint``)."""
    n_folds = int(n_folds)
    if n_folds == 0:
        return 0
    if n_folds < 2:
        raise ValueError(f"cross validation folds must be 0 (none) or >= 2, got {n_folds}")
    n = int(np.unique(np.asarray(groups)).size)
    if n < 2:
        raise ValueError(f"grouped cross validation needs at least 2 {what}, the training "
                         f"data has {n}: train on more{hint}, or pass --cv-folds 0 to "
                         "train without cross validation")
    return min(n_folds, n)


def _cls_metrics(y, p) -> dict[str, float]:
    return {"accuracy": M.accuracy(y, p), "auroc": M.auroc(y, p), "auprc": M.auprc(y, p),
            "ece": M.ece(y, p)}


def _reg_metrics(y, p) -> dict[str, float]:
    return {"r2": M.r2(y, p), "mae": M.mae(y, p)}


def metrics_for(task: str, y, p) -> dict[str, float]:
    """The metrics of ``task`` for targets ``y`` and predictions ``p`` (clipped to [0, 1])."""
    p = np.clip(np.asarray(p, dtype=np.float64), 0.0, 1.0)
    return _cls_metrics(y, p) if task == "classification" else _reg_metrics(y, p)


@dataclass
class FoldMetrics:
    train: dict[str, float]
    val: dict[str, float]


@dataclass
class CVResult:
    """Per-fold train / validation metrics and out-of-fold predictions."""

    task: str
    kind: str
    folds: list[FoldMetrics]
    oof: np.ndarray  # out-of-fold prediction of every sample

    def mean_std(self) -> dict[str, dict[str, tuple[float, float]]]:
        """``{"train" | "val": {metric: (mean, std)}}`` over the folds (NaN folds skipped)."""
        out = {}
        for part in ("train", "val"):
            keys = getattr(self.folds[0], part).keys()
            out[part] = {}
            for k in keys:
                v = np.array([getattr(f, part)[k] for f in self.folds], dtype=np.float64)
                v = v[np.isfinite(v)]
                out[part][k] = ((float(v.mean()), float(v.std())) if v.size
                                else (float("nan"), float("nan")))
        return out


def fit_folds(kind: str, task: str, X, y, folds, *, seed: int = 0, n_jobs: int = 1):
    """One ``kind`` model per fold of ``folds`` (``[(train_idx, val_idx), ...]``), fitted
    on the fold's training rows; a generator, each fitted when asked for."""
    for tr, _ in folds:
        yield fit_estimator(kind, task, X[tr], y[tr], seed=seed, n_jobs=n_jobs)


def cross_validate(X, y, groups, *, task: str, kind: str = "xgboost", n_folds: int = 10,
                   seed: int = 0, n_jobs: int = 1,
                   progress: Callable[[int, int], None] | None = None,
                   fold_fitter: Callable | None = None) -> CVResult:
    """Grouped ``n_folds`` cross validation of a ``kind`` model on ``(X, y)``.

    ``fold_fitter``: fits the fold models, with the signature of :func:`fit_folds` (the
    default, on this machine); ``lidar_quality_training.distributed_training`` passes one
    that fits them on a Dask cluster. Predictions and metrics are computed here."""
    _check(kind, task)
    X, y = training_arrays(X, y, task)
    folds = group_folds(groups, n_folds, seed=seed)
    for f, (tr, _) in enumerate(folds):  # before any fit
        if task == "classification" and np.unique(y[tr]).size < 2:
            raise ValueError(f"fold {f}: training part holds one class only")
    oof = np.full(y.shape[0], np.nan)
    result = []
    models = (fold_fitter or fit_folds)(kind, task, X, y, folds, seed=seed, n_jobs=n_jobs)
    for f, ((tr, va), est) in enumerate(zip(folds, models)):
        p_tr, p_va = predict(est, task, X[tr]), predict(est, task, X[va])
        oof[va] = p_va
        result.append(FoldMetrics(metrics_for(task, y[tr], p_tr), metrics_for(task, y[va], p_va)))
        if progress is not None:
            progress(f + 1, len(folds))
    return CVResult(task, kind, result, oof)


@dataclass
class GreedyResult:
    """Features in the order they were chosen and the validation score after each step."""

    selected: list[str]
    scores: list[float]
    metric: str
    all_features_score: float = float("nan")
    trace: list[dict[str, float]] = field(default_factory=list)


def _val_score(X, y, folds, task, kind, seed, n_jobs) -> float:
    vals = []
    for tr, va in folds:
        est = fit_estimator(kind, task, X[tr], y[tr], seed=seed, n_jobs=n_jobs)
        p = np.clip(predict(est, task, X[va]), 0.0, 1.0)
        vals.append(M.auroc(y[va], p) if task == "classification" else M.r2(y[va], p))
    v = np.asarray(vals)
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else float("nan")


def greedy_selection(X, y, names: Sequence[str], groups, *, task: str, kind: str = "linear",
                     n_folds: int = 3, max_features: int = 10, min_gain: float = 5e-4,
                     seed: int = 0, n_jobs: int = 1,
                     progress: Callable[[int, int], None] | None = None) -> GreedyResult:
    """Greedy forward feature selection by grouped cross-validated AUROC / R^2."""
    _check(kind, task)
    X, y = training_arrays(X, y, task)
    names = list(names)
    if len(names) != X.shape[1]:
        raise ValueError(f"{len(names)} names for {X.shape[1]} columns")
    folds = group_folds(groups, n_folds, seed=seed)
    chosen: list[int] = []
    scores: list[float] = []
    trace: list[dict[str, float]] = []
    best_prev = -np.inf
    steps = min(max_features, X.shape[1])
    for step in range(steps):
        cand = [j for j in range(X.shape[1]) if j not in chosen]
        s = {names[j]: _val_score(X[:, chosen + [j]], y, folds, task, kind, seed, n_jobs)
             for j in cand}
        trace.append(s)
        j_best = max(cand, key=lambda j: -np.inf if not np.isfinite(s[names[j]]) else s[names[j]])
        gain = s[names[j_best]] - best_prev
        if scores and not gain >= min_gain:
            break
        chosen.append(j_best)
        scores.append(s[names[j_best]])
        best_prev = s[names[j_best]]
        if progress is not None:
            progress(step + 1, steps)
    full = _val_score(X, y, folds, task, kind, seed, n_jobs)
    return GreedyResult([names[j] for j in chosen], scores,
                        "auroc" if task == "classification" else "r2", full, trace)


# ------------------------------------------------------------------ training settings
#: Where each method's trainer records its settings in ``training_data``.
SETTINGS_SECTION = {"lmd": "settings", "lms": "settings", "mimo": "merge_settings"}


def _lmd_rules() -> tuple[SettingRule, ...]:
    def threshold(key, mode, option):
        return SettingRule(key, exact=False, when=("proposal_mode", (mode,)),
                           fix=f"set {key} to {{model}}, or retrain with lmd-train "
                               f"{option} {{current}}")

    return (
        SettingRule("proposal_mode",
                    fix="set proposal_mode to {model}, or use models trained for {current} "
                        "(lmd-train --modes; the shipped lmd_<mode>_* pair is chosen by "
                        "proposal_mode when classifier_path and regressor_path are empty)"),
        SettingRule("class_names",
                    fix="set class_names to {model}: the class feature is the position in "
                        "this list"),
        SettingRule("class_score_features",
                    fix="use models trained with class_score_features {current}"),
        threshold("iou_threshold", "threshold", "--iou-threshold"),
        threshold("proposal_score_threshold", "threshold", "--proposal-score-threshold"),
        threshold("nms_iou_threshold", "exact", "--nms-iou-threshold"),
        threshold("nms_score_threshold", "exact", "--nms-score-threshold"),
    )


def _lms_rules() -> tuple[SettingRule, ...]:
    # Another image geometry (a sensor preset on models trained for our simulated HDL-64)
    # keeps the feature schema: it warns (lms_node also shows it in /diagnostics,
    # model.geometry) instead of refusing, since the user's sensor is what it is (issue 16).
    def geometry(key, option):
        return SettingRule(key, exact=False,
                           fix=f"set {key} to {{model}} if that is your sensor's image, "
                               f"or retrain for it (lms-train {option} {{current}})")

    return (
        SettingRule("class_names",
                    fix="set class_names to {model}, the models' class order (class c "
                        "reads the probability field of class_names[c])"),
        geometry("channels", "--channels"), geometry("width", "--width"),
        geometry("fov_up_deg", "--fov-up"), geometry("fov_down_deg", "--fov-down"),
        SettingRule("min_segment_points",
                    fix="set min_segment_points to {model}, or retrain with lms-train "
                        "--min-points {current}"),
        SettingRule("use_ring", exact=False,
                    fix="image rows from the ring field (true) or from the vertical field "
                        "of view (false); set use_ring to {model} to match the training"),
        SettingRule("sum_tolerance", exact=False, fix="set sum_tolerance to {model}"),
    )


#: The LMD own-box point features that ``use_points`` adds to the MIMO schema.
_MIMO_POINT_FEATURES = ("points", "points_frac", "refl_max", "refl_mean", "refl_std")


def _mimo_uses_points(manifest: Mapping[str, Any]) -> bool:
    # From the schema, not the record: mimo-train before issue 14 wrote the dataset's
    # use_points (always true) into the manifests of both pairs.
    return set(_MIMO_POINT_FEATURES) <= set(manifest.get("feature_names") or ())


def _mimo_rules() -> tuple[SettingRule, ...]:
    def merge(key, exact=False, fix=None):
        return SettingRule(f"merge.{key}", exact=exact, fix=fix or f"set {key} to {{model}}")

    retrain = "the model comes from other merge code: retrain it with mimo-train"
    return (
        SettingRule("use_points", model_value=_mimo_uses_points,
                    fix="set use_points to {model}, or use the pair with the feature "
                        "schema of use_points {current} (the shipped mimo_* / mimo_points_* "
                        "pair is chosen by use_points when classifier_path and "
                        "regressor_path are empty)"),
        SettingRule("class_names",
                    fix="set class_names to {model}: the class feature is the position in "
                        "this list"),
        merge("score_type", True, retrain), merge("background_index", True, retrain),
        merge("yaw_deviation", True, retrain),
        SettingRule("num_heads", exact=False,
                    fix="set num_heads to {model}, or retrain on bags with this number of "
                        "heads (mimo-train)"),
        merge("eps"), merge("voting"),
        merge("min_cluster_size", fix="set min_cluster_size to {model} (null: 0, from the "
                                      "voting rule)"),
        merge("class_aware"), merge("temperature"), merge("yaw_variance", fix=retrain),
    )


#: Per method: how its recorded training settings are compared with the settings in use
#: (module docstring).
SETTING_RULES: dict[str, tuple[SettingRule, ...]] = {
    "lmd": _lmd_rules(), "lms": _lms_rules(), "mimo": _mimo_rules()}


def _settings_dict(settings) -> dict:
    if dataclasses.is_dataclass(settings) and not isinstance(settings, type):
        return dataclasses.asdict(settings)
    if isinstance(settings, Mapping):
        return dict(settings)
    raise TypeError(f"settings must be a dataclass or a mapping, got {type(settings).__name__}")


def settings_record(settings, method: str) -> dict:
    """``{section: settings}``: how a trainer of ``method`` records its settings in
    ``training_data`` (JSON-normal), for :func:`check_settings` to find them."""
    if method not in SETTINGS_SECTION:
        raise ValueError(f"method must be one of {sorted(SETTINGS_SECTION)}, got {method!r}")
    import json

    return {SETTINGS_SECTION[method]: json.loads(json.dumps(_settings_dict(settings),
                                                            default=str))}


def check_settings(manifest: Mapping[str, Any], settings, method: str, *,
                   name: str | None = None) -> list[str]:
    """Compare a model's recorded training settings with ``settings`` (the pipeline's
    settings dataclass or a mapping) by the rules of ``method`` (``lmd``, ``lms``,
    ``mimo``). Raises ``ModelStoreError`` on a setting that must match; returns the
    warnings (settings that differ but need not match, or that were not recorded)."""
    if method not in SETTING_RULES:
        raise ValueError(f"method must be one of {sorted(SETTING_RULES)}, got {method!r}")
    return check_training_settings(manifest, _settings_dict(settings), SETTING_RULES[method],
                                   section=SETTINGS_SECTION[method], name=name)


class MetaModels:
    """Meta classifier (confidence) and meta regressor (predicted IoU) of one node.

    Both are loaded and verified through the model store against ``feature_names``;
    any problem raises ``ModelStoreError`` naming the file and the reason. With
    ``settings`` and ``method``, the training settings recorded in both manifests are
    checked first (:func:`check_settings`): a mismatch that changes the features refuses
    the models; the other findings are in ``warnings`` and go to ``warn`` (default: a
    ``ModelStoreWarning``), once for the pair when both models say the same.
    """

    def __init__(self, classifier_path, regressor_path, feature_names: Sequence[str], *,
                 settings=None, method: str | None = None,
                 warn: Callable[[str], Any] | None = None):
        self.feature_names = tuple(feature_names)
        self.warnings: list[str] = []
        if settings is not None or method is not None:
            if settings is None or method is None:
                raise ValueError("settings and method go together")
            self.warnings = _pair_warnings(
                [(Path(p).name, check_settings(read_manifest(p), settings, method,
                                               name=Path(p).name))
                 for p in (classifier_path, regressor_path)])
            for text in self.warnings:
                if warn is not None:
                    warn(text)
                else:
                    warnings.warn(text, ModelStoreWarning, stacklevel=2)
        self.classifier: LoadedModel = load_model(classifier_path,
                                                  expected_features=self.feature_names,
                                                  expected_task="classification")
        self.regressor: LoadedModel = load_model(regressor_path,
                                                 expected_features=self.feature_names,
                                                 expected_task="regression")
        if self.regressor.target_names:
            raise ModelStoreError(f"{regressor_path}: expected a single-output regressor, "
                                  f"got outputs {self.regressor.target_names}")
        #: both models' compiled walks (``tree_ensemble``), taken together for a frame's
        #: rows (``predict_pair``); None: each model predicts on its own
        self._pair = None
        both = (self.classifier.compiled, self.regressor.compiled)
        if None not in both:  # then model_store has imported tree_ensemble (numba)
            from .tree_ensemble import MAX_ROWS, predict_pair

            self._pair, self._pair_rows, self._predict_pair = both, MAX_ROWS, predict_pair

    @property
    def confidence_model_id(self) -> str:
        return self.classifier.model_id

    @property
    def iou_model_id(self) -> str:
        return self.regressor.model_id

    @property
    def domain_profile(self):
        """The training data's ``DomainProfile`` from the classifier's manifest (None for
        models trained before profiles were recorded)."""
        from .domain_profile import DomainProfile

        d = (self.classifier.manifest.get("training_data") or {}).get("domain_profile")
        return DomainProfile.from_json(d) if d else None

    def predict(self, X) -> tuple[np.ndarray, np.ndarray]:
        """``(confidence, predicted_iou)``, both in [0, 1]; NaN for all-NaN rows."""
        X = np.asarray(X, dtype=np.float64)
        if X.ndim != 2 or X.shape[1] != len(self.feature_names):
            raise ValueError(f"features must be (n, {len(self.feature_names)}), got {X.shape}")
        if self._pair is not None and 0 < len(X) <= self._pair_rows:
            conf, iou = self._predict_pair(*self._pair, X)
            return np.clip(conf, 0.0, 1.0, out=conf), np.clip(iou, 0.0, 1.0, out=iou)
        conf = np.full(X.shape[0], np.nan)
        iou = np.full(X.shape[0], np.nan)
        ok = ~np.isnan(X).all(axis=1) if X.shape[1] else np.ones(X.shape[0], bool)
        # +-inf would reach the trees as a valid split value; treat it as missing.
        Xo = np.where(np.isinf(X[ok]), np.nan, X[ok])
        if Xo.shape[0]:
            conf[ok] = np.clip(self.classifier.predict_confidence(Xo), 0.0, 1.0)
            iou[ok] = np.clip(self.regressor.predict_value(Xo), 0.0, 1.0)
        return conf, iou


# ------------------------------------------------------------------ training data
#: Where ``make meta-data`` writes the simulated perception bags of a split:
#: ``<split>/seq_NN``, and ``<split>/.done`` once the whole split is written.
SIMULATED_DATA_DIR = Path(__file__).resolve().parents[2] / "data" / "perception"


def simulated_sources(paths: Sequence) -> bool:
    """True iff there are ``paths`` and each is a bag of a split that ``make meta-data``
    simulated (``lidar_sim`` scenes through the reference perception): directly under
    ``SIMULATED_DATA_DIR/<split>/`` with the split's ``.done`` marker. Model cards call
    their data simulated only then."""
    root = SIMULATED_DATA_DIR.resolve()
    for p in paths:
        try:
            rel = Path(p).resolve().relative_to(root)
        except ValueError:
            return False
        if len(rel.parts) != 2 or not (root / rel.parts[0] / ".done").is_file():
            return False
    return len(paths) > 0


def _pair_warnings(found: list[tuple[str, list[str]]]) -> list[str]:
    """One warning per finding: ``"<c>, <r>: ..."`` when both models report it."""
    by_text: dict[str, list[str]] = {}
    for name, texts in found:
        for t in texts:
            by_text.setdefault(t[len(name) + 2:], []).append(name)
    return [f"{', '.join(names)}: {text}" for text, names in by_text.items()]


def save_pair(out_dir, prefix: str, classifier, regressor, feature_names: Sequence[str], *,
              training_data: dict[str, Any] | None = None,
              classifier_metrics: dict[str, Any] | None = None,
              regressor_metrics: dict[str, Any] | None = None,
              compress: int = 0, domain_profile: dict | None = None) -> tuple[Path, Path]:
    """Save ``<prefix>_classifier.joblib`` and ``<prefix>_regressor.joblib`` with manifests
    (``compress``: joblib zlib level, see ``model_store.save_model``); ``domain_profile``
    (``training_profile``) goes into both manifests' ``training_data``."""
    if domain_profile is not None:
        training_data = {**(training_data or {}), "domain_profile": domain_profile}
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cpath, rpath = out / f"{prefix}_classifier.joblib", out / f"{prefix}_regressor.joblib"
    save_model(classifier, cpath, feature_names=list(feature_names), task="classification",
               training_data=training_data, metrics=classifier_metrics, compress=compress)
    save_model(regressor, rpath, feature_names=list(feature_names), task="regression",
               training_data=training_data, metrics=regressor_metrics, compress=compress)
    return cpath, rpath


def training_profile(X, feature_names: Sequence[str], extra: dict | None = None, *,
                     groups=None, extra_groups: dict | None = None) -> dict:
    """The domain profile (``domain_profile.DomainProfile``, JSON) of a training set: every
    feature column by name, plus ``extra`` quantities (``{name: values}``, e.g. the
    detector's scores, points per frame). ``groups`` (the sequence of each row of ``X``)
    and ``extra_groups`` (``{name: the sequence of each value}``) give each quantity's
    spread between sequences."""
    from .domain_profile import DomainProfile

    X = np.asarray(X, np.float64)
    cols = {n: X[:, j] for j, n in enumerate(feature_names)}
    cols.update(extra or {})
    by = {n: groups for n in feature_names} if groups is not None else {}
    by.update(extra_groups or {})
    return DomainProfile.of(cols, by).to_json()


def model_path_param(role: str, target: str, shipped: str):
    """The ``classifier_path`` / ``regressor_path`` parameter field of a node's parameters
    (``lidar_quality_core.parameters``): ``role`` classifier | regressor, ``target`` what it
    predicts, ``shipped`` the model used when the parameter is empty."""
    return param("", f"Meta {role} ({target}; model store file with manifest); empty: the "
                     f"shipped {shipped}.")
