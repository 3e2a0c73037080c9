"""Verified saving and loading of the meta models (classifiers / regressors).

Layout: the model file plus a manifest beside it named ``<model file name>.manifest.json``
(e.g. ``lmd_classifier.joblib`` + ``lmd_classifier.joblib.manifest.json``). Manifest
fields (``MANIFEST_VERSION`` 1):

``manifest_version``, ``model_file`` (basename), ``sha256`` (hex of the model file),
``format`` (``joblib`` | ``xgboost-json`` | ``xgboost-ubj``), ``task``
(``classification`` | ``regression``), ``feature_names`` (ordered), ``n_features``,
``model_id``, ``library_versions`` (python, numpy, scikit-learn, xgboost, joblib at
save time; ``null`` if absent), ``training_data`` (free dict), ``metrics`` (dict),
``created`` (ISO 8601 UTC), ``positive_class`` (classification: the label whose
probability is the confidence), and for native XGBoost ``xgboost``:
``{"estimator": "XGBClassifier" | "XGBRegressor" | "Booster", "objective": ...}``.

Task ``classification`` is binary: the confidence is P(positive class). Native XGBoost
classifiers must use ``binary:logistic`` (the probability is the model output). Task
``multiclass`` (e.g. the reference perception's class distributions) stores ``classes``
(the labels, in probability-column order) and optionally ``class_names``; native XGBoost
must use ``multi:softprob``. A ``regression`` model with several outputs names them in
``target_names`` and predicts an ``(n, T)`` array.

Loading checks, in this order and before anything is deserialised: manifest present and
well formed, model file present and named as in the manifest, format known, SHA-256
equal, feature schema equal to ``expected_features``, task equal to ``expected_task``.
The model bytes are read once and both hashed and deserialised from memory, so the file
cannot change between check and load. Library version differences only warn
(:class:`ModelStoreWarning`).

Training settings: a trainer records the settings that define the features (proposal
mode, class list, image geometry, ...) in ``training_data`` (e.g.
``training_data["settings"]``). :func:`check_training_settings` compares them with the
settings a user runs, by a list of :class:`SettingRule` (which setting must be equal and
which only warns, and the fix); ``meta_model.MetaModels`` holds the rules of the three
methods and runs them before loading.

Security: the hash proves integrity against the manifest, not authenticity (whoever can
write both files can forge them). ``joblib`` files are pickles, i.e. code: load only
trusted ones. The native XGBoost formats never touch pickle.

Saving writes each file to a temp file in the target directory and renames it (model
first, then manifest), so a reader sees either the old pair, a transient hash mismatch
(refused), or the new pair; never a half-written file.
"""
from __future__ import annotations

import copy
import hashlib
import math
import io
import json
import os
import platform
import tempfile
import warnings
from dataclasses import dataclass
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np

__all__ = [
    "MANIFEST_SUFFIX",
    "MANIFEST_VERSION",
    "FORMATS",
    "TASKS",
    "ModelStoreError",
    "ModelStoreWarning",
    "SettingRule",
    "check_training_settings",
    "LoadedModel",
    "manifest_path_for",
    "sha256_file",
    "write_atomic",
    "save_model",
    "load_model",
    "read_manifest",
    "models_dir",
]

MANIFEST_SUFFIX = ".manifest.json"
MANIFEST_VERSION = 1
FORMATS = ("joblib", "xgboost-json", "xgboost-ubj")
TASKS = ("classification", "regression", "multiclass")
_NATIVE_EXT = {"xgboost-json": ".json", "xgboost-ubj": ".ubj"}
_XGB_ESTIMATORS = ("XGBClassifier", "XGBRegressor", "Booster")
_LIBS = {  # manifest key -> candidate distribution names
    "numpy": ("numpy",),
    "scikit-learn": ("scikit-learn",),
    "xgboost": ("xgboost", "xgboost-cpu"),
    "joblib": ("joblib",),
}
_REQUIRED = {
    "model_file": str,
    "sha256": str,
    "format": str,
    "task": str,
    "feature_names": list,
    "model_id": str,
}


class ModelStoreError(Exception):
    """A model or manifest is missing, corrupt, or does not fit what the caller expects."""


class ModelStoreWarning(UserWarning):
    """Non-fatal model store issue (e.g. library versions differ from save time)."""


def models_dir() -> Path:
    """Directory of the shipped models: ``$LQ_MODELS_DIR`` if set, else the repository's
    ``models/`` (found from this file, which a symlink install keeps in the checkout)."""
    env = os.environ.get("LQ_MODELS_DIR")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2] / "models"


def manifest_path_for(model_path: str | os.PathLike) -> Path:
    """Manifest path of a model file: ``<model file>.manifest.json``."""
    p = Path(model_path)
    return p.with_name(p.name + MANIFEST_SUFFIX)


def sha256_file(path: str | os.PathLike) -> str:
    """Hex SHA-256 of a file."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _short(h: str) -> str:
    return h[:12] + "…" if len(h) > 12 else h


def _library_versions() -> dict[str, str | None]:
    out: dict[str, str | None] = {"python": platform.python_version()}
    for key, dists in _LIBS.items():
        out[key] = None
        for dist in dists:
            try:
                out[key] = metadata.version(dist)
                break
            except metadata.PackageNotFoundError:
                continue
    return out


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def _check_feature_names(feature_names: Iterable[str]) -> list[str]:
    names = list(feature_names)
    if not names or not all(isinstance(n, str) and n for n in names):
        raise ModelStoreError("feature_names must be a non-empty list of non-empty strings")
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ModelStoreError(f"duplicate feature names: {dup}")
    return names


def _schema_diff(expected: Sequence[str], actual: Sequence[str]) -> str | None:
    """Human-readable difference of two ordered feature lists, or None if equal."""
    expected, actual = list(expected), list(actual)
    if expected == actual:
        return None
    parts = []
    missing = [n for n in expected if n not in actual]
    extra = [n for n in actual if n not in expected]
    if missing:
        parts.append(f"missing from model: {missing}")
    if extra:
        parts.append(f"extra in model: {extra}")
    common_e = [n for n in expected if n in actual]
    common_a = [n for n in actual if n in expected]
    if common_e != common_a:
        moved = [
            f"{n!r} expected at {expected.index(n)}, model has it at {actual.index(n)}"
            for n, m in zip(common_e, common_a)
            if n != m
        ]
        parts.append("reordered: " + "; ".join(moved))
    if not parts:  # same names, differing only in duplicates
        parts.append(f"expected {expected}, model has {actual}")
    return ", ".join(parts)


def _is_xgb(model: Any) -> bool:
    try:
        import xgboost
    except ImportError:
        return False
    return isinstance(model, (xgboost.XGBModel, xgboost.Booster))


def _xgb_objective(booster: Any) -> str:
    return json.loads(booster.save_config())["learner"]["objective"]["name"]


# -- saving ----------------------------------------------------------------------------


def write_atomic(target: Path, write: Any, suffix: str = "", *, digest: bool = True
                 ) -> str | None:
    """Write via ``write(tmp_path)`` (a file beside ``target``, named ``.<name>.*.tmp``
    plus ``suffix``), synced, then renamed onto ``target``: a reader sees the old file or
    the complete new one. Returns the SHA-256 of what was written (``digest``), else
    None."""
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp" + suffix,
                               dir=target.parent)
    os.close(fd)
    try:
        write(tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        # mkstemp creates 0600; the node may run as another user than the trainer.
        os.chmod(tmp, 0o644)
        sha = sha256_file(tmp) if digest else None
        os.replace(tmp, target)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return sha


def save_model(
    model: Any,
    path: str | os.PathLike,
    *,
    feature_names: Sequence[str],
    task: str,
    training_data: Mapping[str, Any] | None = None,
    metrics: Mapping[str, Any] | None = None,
    model_id: str | None = None,
    format: str | None = None,
    class_names: Sequence[str] | None = None,
    target_names: Sequence[str] | None = None,
    compress: int = 0,
) -> dict[str, Any]:
    """Write ``model`` to ``path`` and its manifest beside it; returns the manifest.

    ``format`` defaults to ``xgboost-json`` / ``xgboost-ubj`` for XGBoost models saved
    to ``*.json`` / ``*.ubj`` and to ``joblib`` otherwise. ``model_id`` defaults to
    ``<file stem>-<first 12 hex of sha256>``. ``class_names`` (multiclass) label the
    probability columns; ``target_names`` (regression) name the outputs of a multi-output
    regressor. ``compress`` (0-9, ``joblib`` only): zlib level of the pickle (loading
    detects it; XGBoost pickles shrink about 4x).
    """
    path = Path(path)
    if task not in TASKS:
        raise ModelStoreError(f"{path.name}: task must be one of {TASKS}, got {task!r}")
    names = _check_feature_names(feature_names)
    if format is None:
        native = {v: k for k, v in _NATIVE_EXT.items()}.get(path.suffix.lower())
        format = native if native and _is_xgb(model) else "joblib"
    if format not in FORMATS:
        raise ModelStoreError(f"{path.name}: unknown format {format!r} (known: {FORMATS})")
    if not path.parent.is_dir():
        raise ModelStoreError(f"{path}: directory {path.parent} does not exist")

    manifest: dict[str, Any] = {"manifest_version": MANIFEST_VERSION}
    n_in = getattr(model, "n_features_in_", None)
    if n_in is not None and int(n_in) != len(names):
        raise ModelStoreError(
            f"{path.name}: model was fitted on {n_in} features, feature_names has {len(names)}"
        )

    if format == "joblib":
        import joblib

        if task == "classification":
            manifest["positive_class"] = _positive_class(model, path)
        elif task == "multiclass":
            manifest["classes"] = _multiclass_labels(model, path)
        elif not hasattr(model, "predict"):
            raise ModelStoreError(f"{path.name}: regression model has no predict()")
        def writer(tmp):
            return joblib.dump(model, tmp, compress=compress)
        suffix = ""
    else:
        ext = _NATIVE_EXT[format]
        if path.suffix.lower() != ext:
            raise ModelStoreError(f"{path.name}: format {format!r} needs a '{ext}' file name")
        if not _is_xgb(model):
            raise ModelStoreError(
                f"{path.name}: format {format!r} needs an xgboost model, got {type(model).__name__}"
            )
        manifest["xgboost"] = _xgb_info(model, task, names, path)
        if task == "classification":
            manifest["positive_class"] = 1
        elif task == "multiclass":
            manifest["classes"] = list(range(manifest["xgboost"]["num_class"]))
        writer = model.save_model
        suffix = ext  # xgboost picks the format from the extension

    if class_names is not None:
        if task != "multiclass" or len(class_names) != len(manifest["classes"]):
            raise ModelStoreError(f"{path.name}: class_names need a multiclass model with "
                                  f"{len(manifest.get('classes', []))} classes")
        manifest["class_names"] = [str(c) for c in class_names]
    if target_names is not None:
        if task != "regression":
            raise ModelStoreError(f"{path.name}: target_names need a regression model")
        manifest["target_names"] = [str(t) for t in target_names]

    digest = write_atomic(path, writer, suffix)
    manifest.update(
        model_file=path.name,
        sha256=digest,
        format=format,
        task=task,
        feature_names=names,
        n_features=len(names),
        model_id=model_id if model_id is not None else f"{path.stem}-{digest[:12]}",
        library_versions=_library_versions(),
        training_data=dict(training_data or {}),
        metrics=dict(metrics or {}),
        created=datetime.now(timezone.utc).isoformat(timespec="seconds"),
    )
    text = json.dumps(manifest, indent=2, sort_keys=True, default=_json_default) + "\n"

    def write_manifest(tmp: str) -> None:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)

    write_atomic(manifest_path_for(path), write_manifest)
    return json.loads(text)


def _positive_class(model: Any, path: Path) -> Any:
    if not hasattr(model, "predict_proba"):
        raise ModelStoreError(f"{path.name}: classification model has no predict_proba()")
    classes = getattr(model, "classes_", None)
    if classes is None or len(classes) != 2:
        raise ModelStoreError(
            f"{path.name}: only binary classifiers are supported (classes_={classes!r})"
        )
    # sklearn sorts classes_, so the positive label (1 / True) is the second one.
    return _json_default(classes[1]) if isinstance(classes[1], np.generic) else classes[1]


def _multiclass_labels(model: Any, path: Path) -> list:
    if not hasattr(model, "predict_proba"):
        raise ModelStoreError(f"{path.name}: multiclass model has no predict_proba()")
    classes = getattr(model, "classes_", None)
    if classes is None or len(classes) < 2:
        raise ModelStoreError(f"{path.name}: multiclass model needs classes_ (got {classes!r})")
    return [_json_default(c) if isinstance(c, np.generic) else c for c in classes]


def _xgb_info(model: Any, task: str, names: list[str], path: Path) -> dict[str, Any]:
    import xgboost

    if isinstance(model, xgboost.XGBClassifier):
        estimator = "XGBClassifier"
    elif isinstance(model, xgboost.XGBRegressor):
        estimator = "XGBRegressor"
    elif isinstance(model, xgboost.Booster):
        estimator = "Booster"
    else:
        raise ModelStoreError(f"{path.name}: unsupported xgboost model {type(model).__name__}")
    booster = model if estimator == "Booster" else model.get_booster()
    objective = _xgb_objective(booster)
    if task == "classification":
        if estimator == "XGBRegressor":
            raise ModelStoreError(f"{path.name}: XGBRegressor saved with task classification")
        if objective != "binary:logistic":
            raise ModelStoreError(
                f"{path.name}: native xgboost classifiers must use objective "
                f"binary:logistic (got {objective!r})"
            )
    elif task == "multiclass":
        if estimator == "XGBRegressor":
            raise ModelStoreError(f"{path.name}: XGBRegressor saved with task multiclass")
        if objective != "multi:softprob":
            raise ModelStoreError(f"{path.name}: native xgboost multiclass models must use "
                                  f"objective multi:softprob (got {objective!r})")
    elif estimator == "XGBClassifier":
        raise ModelStoreError(f"{path.name}: XGBClassifier saved with task regression")
    if booster.num_features() != len(names):
        raise ModelStoreError(
            f"{path.name}: booster has {booster.num_features()} features, "
            f"feature_names has {len(names)}"
        )
    if booster.feature_names is not None and list(booster.feature_names) != names:
        raise ModelStoreError(
            f"{path.name}: booster feature names differ from feature_names: "
            f"{_schema_diff(names, booster.feature_names)}"
        )
    info = {"estimator": estimator, "objective": objective}
    if task == "multiclass":
        info["num_class"] = _xgb_num_class(booster)
    return info


def _xgb_num_class(booster: Any) -> int:
    cfg = json.loads(booster.save_config())
    return int(cfg["learner"]["learner_model_param"]["num_class"])


# -- training settings -----------------------------------------------------------------


@dataclass(frozen=True)
class SettingRule:
    """How one training setting is compared with the setting in use.

    ``key``: dotted path into the recorded settings (``"merge.eps"``) and into the
    current ones. ``exact``: a difference refuses the model; otherwise it only warns.
    ``fix``: what resolves a difference (``{model}`` / ``{current}`` are replaced by the
    two values). ``when``: ``(key, values)``, the rule applies only while the current
    setting ``key`` is one of ``values`` (e.g. a threshold of one proposal mode).
    ``model_value``: takes the model's value from the whole manifest instead of the
    recorded settings (for a setting the feature schema already fixes).
    """

    key: str
    exact: bool = True
    fix: str = ""
    when: tuple[str, tuple] | None = None
    model_value: Callable[[Mapping[str, Any]], Any] | None = None


_MISSING = object()


def _lookup(d: Any, key: str) -> Any:
    for part in key.split("."):
        if not isinstance(d, Mapping) or part not in d:
            return _MISSING
        d = d[part]
    return d


def _plain(v: Any) -> Any:
    """JSON-normal form (tuples -> lists, numpy scalars -> Python) for comparing."""
    return json.loads(json.dumps(v, default=_json_default))


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, bool) or isinstance(b, bool):
        return a is b
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a == b


def _show(v: Any) -> str:
    return json.dumps(v) if not isinstance(v, str) else repr(v)


def check_training_settings(
    manifest: Mapping[str, Any],
    current: Mapping[str, Any],
    rules: Sequence[SettingRule],
    *,
    section: str = "settings",
    name: str | None = None,
) -> list[str]:
    """Compare the training settings recorded in ``manifest["training_data"][section]``
    with ``current`` by ``rules``.

    Raises :class:`ModelStoreError` naming every ``exact`` setting that differs (model
    value, current value, fix). Returns warnings (no raise): the settings that differ
    but need not match, and settings the manifest does not record (an older model: they
    cannot be checked).
    """
    name = name or str(manifest.get("model_file", "model"))
    recorded = (manifest.get("training_data") or {}).get(section)
    current = _plain(dict(current))
    errors: list[str] = []
    warns: list[str] = []
    unrecorded: list[str] = []
    for rule in rules:
        if rule.when is not None:
            wkey, values = rule.when
            if _lookup(current, wkey) not in values:
                continue
        if rule.model_value is not None:
            model = rule.model_value(manifest)
        elif isinstance(recorded, Mapping):
            model = _lookup(recorded, rule.key)
        else:
            model = _MISSING
        if model is _MISSING:
            unrecorded.append(rule.key)
            continue
        cur = _lookup(current, rule.key)
        model = _plain(model)
        if cur is _MISSING or _same(model, cur):
            continue
        fix = rule.fix.format(model=_show(model), current=_show(cur))
        # the last part names the parameter (merge.voting -> the node's "voting")
        text = (f"{rule.key.rsplit('.', 1)[-1]}: model trained with {_show(model)}, "
                f"node set to {_show(cur)}")
        if rule.exact:
            errors.append(text + (f" (fix: {fix})" if fix else ""))
        else:
            warns.append(f"{name}: {text}; its confidence and IoU are calibrated for "
                         f"{_show(model)}" + (f" ({fix})" if fix else ""))
    if errors:
        raise ModelStoreError(f"{name}: trained with other settings than the node's: "
                              + "; ".join(errors))
    if unrecorded:
        what = ("records no training settings (an older model)"
                if not isinstance(recorded, Mapping) else "does not record them")
        warns.append(f"{name}: cannot check {', '.join(unrecorded)} against the settings "
                     f"in use: the manifest {what}; a mismatch would go unnoticed "
                     "(retrain to record them)")
    return warns


# -- loading ---------------------------------------------------------------------------


def read_manifest(model_path: str | os.PathLike) -> dict[str, Any]:
    """Read and validate the manifest of ``model_path`` (no hash check, no model load)."""
    model_path = Path(model_path)
    mpath = manifest_path_for(model_path)
    if not mpath.is_file():
        raise ModelStoreError(f"{model_path}: missing manifest {mpath.name}")
    try:
        manifest = json.loads(mpath.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ModelStoreError(f"{mpath}: unreadable manifest: {e}") from e
    if not isinstance(manifest, dict):
        raise ModelStoreError(f"{mpath}: manifest is not a JSON object")
    version = manifest.get("manifest_version", MANIFEST_VERSION)
    if version != MANIFEST_VERSION:
        raise ModelStoreError(f"{mpath}: unsupported manifest_version {version!r}")
    for key, typ in _REQUIRED.items():
        if not isinstance(manifest.get(key), typ):
            raise ModelStoreError(f"{mpath}: field {key!r} missing or not a {typ.__name__}")
    mf = manifest["model_file"]
    if mf != model_path.name:
        raise ModelStoreError(
            f"{mpath}: describes model_file {mf!r}, not {model_path.name!r}"
        )
    if manifest["format"] not in FORMATS:
        raise ModelStoreError(
            f"{model_path}: unknown format {manifest['format']!r} (known: {FORMATS})"
        )
    if manifest["task"] not in TASKS:
        raise ModelStoreError(f"{model_path}: unknown task {manifest['task']!r}")
    try:
        _check_feature_names(manifest["feature_names"])
    except ModelStoreError as e:
        raise ModelStoreError(f"{mpath}: {e}") from None
    return manifest


def load_model(
    path: str | os.PathLike,
    *,
    expected_features: Sequence[str] | None = None,
    expected_task: str | None = None,
) -> LoadedModel:
    """Verify and load the model at ``path`` (the model file, not the manifest)."""
    path = Path(path)
    if path.name.endswith(MANIFEST_SUFFIX):
        raise ModelStoreError(f"{path}: pass the model file, not its manifest")
    manifest = read_manifest(path)
    if not path.is_file():
        raise ModelStoreError(
            f"{path}: missing model file (manifest {manifest_path_for(path).name} exists)"
        )
    data = path.read_bytes()
    actual = hashlib.sha256(data).hexdigest()
    if actual != manifest["sha256"].lower():
        raise ModelStoreError(
            f"{path}: SHA-256 mismatch: manifest {_short(manifest['sha256'])}, "
            f"file {_short(actual)}"
        )
    names = manifest["feature_names"]
    if expected_features is not None:
        diff = _schema_diff(list(expected_features), names)
        if diff:
            raise ModelStoreError(f"{path}: feature schema mismatch: {diff}")
    task = manifest["task"]
    if expected_task is not None and expected_task != task:
        raise ModelStoreError(
            f"{path}: task mismatch: expected {expected_task!r}, model is {task!r}"
        )
    _warn_versions(path, manifest)

    fmt = manifest["format"]
    if fmt == "joblib":
        import joblib

        try:
            estimator = joblib.load(io.BytesIO(data))
        except Exception as e:
            raise ModelStoreError(f"{path}: joblib load failed: {e}") from e
        _check_loaded_joblib(path, estimator, manifest)
    else:
        estimator = _load_xgb_native(path, data, manifest)
    return LoadedModel(path, manifest, estimator)


def _warn_versions(path: Path, manifest: Mapping[str, Any]) -> None:
    saved = manifest.get("library_versions") or {}
    now = _library_versions()
    keys = ["xgboost"] if manifest["format"] != "joblib" else ["python", *_LIBS]
    diffs = []
    for k in keys:
        a, b = saved.get(k), now.get(k)
        if k == "python" and a and b:
            # Pickles depend on the minor version only.
            a, b = ".".join(a.split(".")[:2]), ".".join(b.split(".")[:2])
        if a is not None and a != b:
            diffs.append(f"{k} {a} (saved) vs {b} (now)")
    if diffs:
        warnings.warn(f"{path.name}: library versions differ: " + "; ".join(diffs),
                      ModelStoreWarning, stacklevel=3)


def _check_loaded_joblib(path: Path, est: Any, manifest: Mapping[str, Any]) -> None:
    n = len(manifest["feature_names"])
    n_in = getattr(est, "n_features_in_", None)
    if n_in is not None and int(n_in) != n:
        raise ModelStoreError(f"{path}: model expects {n_in} features, manifest lists {n}")
    if manifest["task"] == "multiclass":
        classes = manifest.get("classes")
        got = _multiclass_labels(est, path) if hasattr(est, "predict_proba") else None
        if got is None or got != classes:
            raise ModelStoreError(f"{path}: classes_ {got} differ from the manifest's {classes}")
    elif manifest["task"] == "classification":
        if not hasattr(est, "predict_proba"):
            raise ModelStoreError(f"{path}: classification model has no predict_proba()")
        classes = list(getattr(est, "classes_", []))
        if len(classes) != 2 or classes[1] != manifest.get("positive_class", 1):
            raise ModelStoreError(
                f"{path}: classes_ {classes} do not match positive_class "
                f"{manifest.get('positive_class')!r} of a binary classifier"
            )
    elif not hasattr(est, "predict"):
        raise ModelStoreError(f"{path}: regression model has no predict()")


def _load_xgb_native(path: Path, data: bytes, manifest: Mapping[str, Any]) -> Any:
    import xgboost

    info = manifest.get("xgboost")
    if not isinstance(info, dict) or info.get("estimator") not in _XGB_ESTIMATORS:
        raise ModelStoreError(
            f"{path}: manifest 'xgboost.estimator' must be one of {_XGB_ESTIMATORS}"
        )
    kind = info["estimator"]
    expected = {"classification": ("XGBClassifier", "Booster"),
                "multiclass": ("XGBClassifier", "Booster"),
                "regression": ("XGBRegressor", "Booster")}[manifest["task"]]
    if kind not in expected:
        raise ModelStoreError(f"{path}: {kind} cannot serve task {manifest['task']!r}")
    est = {"XGBClassifier": xgboost.XGBClassifier, "XGBRegressor": xgboost.XGBRegressor,
           "Booster": xgboost.Booster}[kind]()
    try:
        est.load_model(bytearray(data))
    except Exception as e:
        raise ModelStoreError(f"{path}: xgboost load failed: {e}") from e
    booster = est if kind == "Booster" else est.get_booster()
    objective = _xgb_objective(booster)
    if objective != info.get("objective"):
        raise ModelStoreError(
            f"{path}: objective {objective!r} differs from manifest {info.get('objective')!r}"
        )
    if manifest["task"] == "classification" and objective != "binary:logistic":
        raise ModelStoreError(f"{path}: classification needs binary:logistic, got {objective!r}")
    if manifest["task"] == "multiclass":
        if objective != "multi:softprob":
            raise ModelStoreError(f"{path}: multiclass needs multi:softprob, got {objective!r}")
        if _xgb_num_class(booster) != len(manifest.get("classes") or []):
            raise ModelStoreError(f"{path}: booster has {_xgb_num_class(booster)} classes, "
                                  f"manifest lists {manifest.get('classes')}")
    n = len(manifest["feature_names"])
    if booster.num_features() != n:
        raise ModelStoreError(
            f"{path}: booster has {booster.num_features()} features, manifest lists {n}"
        )
    return est


class LoadedModel:
    """A verified model with a uniform prediction interface.

    Attributes: ``path``, ``manifest`` (a copy), ``model_id``, ``feature_names`` (tuple),
    ``n_features``, ``task``, ``format``, ``sha256``, ``estimator`` (the raw model),
    ``classes`` / ``class_names`` (multiclass), ``target_names`` (regression; None for a
    single output).
    Prediction is thread-safe as far as the underlying library's predict is.
    """

    def __init__(self, path: Path, manifest: Mapping[str, Any], estimator: Any) -> None:
        self.path = Path(path)
        self.manifest = copy.deepcopy(dict(manifest))
        self.model_id: str = manifest["model_id"]
        self.feature_names: tuple[str, ...] = tuple(manifest["feature_names"])
        self.n_features = len(self.feature_names)
        self.task: str = manifest["task"]
        self.format: str = manifest["format"]
        self.sha256: str = manifest["sha256"]
        self.estimator = estimator
        self._kind = (manifest.get("xgboost") or {}).get("estimator")
        self.classes = tuple(manifest.get("classes") or ())
        self.class_names = tuple(manifest.get("class_names") or map(str, self.classes))
        tn = manifest.get("target_names")
        self.target_names = tuple(tn) if tn else None
        #: the compiled walk of an xgboost model's trees (``tree_ensemble``), used for
        #: batches up to ``tree_ensemble.MAX_ROWS``; None: every batch goes to the library
        #: (``compiled_note`` says why)
        self.compiled, self.compiled_note = self._pack()

    def _pack(self):
        est = self.estimator
        kind = type(est).__name__
        if (not type(est).__module__.startswith("xgboost.") or kind not in _XGB_ESTIMATORS
                or self.task not in ("classification", "regression")):
            return None, "not an xgboost classifier or regressor"
        from .tree_ensemble import MAX_ROWS, pack

        self._compiled_max_rows = MAX_ROWS
        booster = est if kind == "Booster" else est.get_booster()
        missing = getattr(est, "missing", float("nan"))
        try:
            packed, why = pack(booster, float("nan") if missing is None else missing)
        except (KeyError, ValueError, TypeError, IndexError) as e:  # a model JSON we do not know
            packed, why = None, f"unreadable tree dump ({e})"
        if packed is not None and packed.n_features != self.n_features:
            packed, why = None, f"{packed.n_features} features, manifest {self.n_features}"
        return packed, why

    def __repr__(self) -> str:
        return (f"LoadedModel({self.path.name!r}, id={self.model_id!r}, task={self.task}, "
                f"format={self.format}, n_features={self.n_features})")

    def _check_X(self, X: Any) -> np.ndarray:
        X = np.asarray(X, dtype=np.float64)
        if X.ndim == 1 and X.size == 0:
            X = X.reshape(0, self.n_features)
        if X.ndim != 2:
            raise ModelStoreError(
                f"{self.path.name}: X must be 2-D (n, {self.n_features}), got shape {X.shape}"
            )
        if X.shape[1] != self.n_features:
            raise ModelStoreError(
                f"{self.path.name}: X has {X.shape[1]} columns, model expects "
                f"{self.n_features} ({', '.join(self.feature_names)})"
            )
        return X

    def _raw(self, X: np.ndarray) -> np.ndarray:
        if self.compiled is not None and len(X) <= self._compiled_max_rows:
            return self.compiled.predict(X)
        if self._kind == "Booster":
            import xgboost

            # save_model guaranteed booster names (if any) equal feature_names.
            dm = xgboost.DMatrix(X, feature_names=self.estimator.feature_names)
            return self.estimator.predict(dm)
        if self.task == "classification":
            return self.estimator.predict_proba(X)[:, 1]
        if self.task == "multiclass":
            return self.estimator.predict_proba(X)
        return self.estimator.predict(X)

    def predict_confidence(self, X: Any) -> np.ndarray:
        """Probability of the positive class, shape ``(n,)``; classification only."""
        if self.task != "classification":
            raise ModelStoreError(f"{self.path.name}: predict_confidence on a {self.task} model")
        X = self._check_X(X)
        if X.shape[0] == 0:
            return np.empty(0, dtype=np.float64)
        return np.asarray(self._raw(X), dtype=np.float64).reshape(-1)

    def predict_value(self, X: Any) -> np.ndarray:
        """Regression output, shape ``(n,)``; regression only."""
        if self.task != "regression":
            raise ModelStoreError(f"{self.path.name}: predict_value on a {self.task} model")
        X = self._check_X(X)
        n_out = len(self.target_names) if self.target_names else 1
        if X.shape[0] == 0:
            return np.empty((0, n_out) if self.target_names else 0, dtype=np.float64)
        out = np.asarray(self._raw(X), dtype=np.float64)
        return out.reshape(len(X), n_out) if self.target_names else out.reshape(-1)

    def predict_proba(self, X: Any) -> np.ndarray:
        """Class probabilities, shape ``(n, len(classes))``; multiclass only."""
        if self.task != "multiclass":
            raise ModelStoreError(f"{self.path.name}: predict_proba on a {self.task} model")
        X = self._check_X(X)
        if X.shape[0] == 0:
            return np.empty((0, len(self.classes)), dtype=np.float64)
        return np.asarray(self._raw(X), dtype=np.float64).reshape(len(X), len(self.classes))

    def predict(self, X: Any) -> np.ndarray:
        """``predict_confidence``, ``predict_proba`` or ``predict_value`` by ``task``."""
        if self.task == "multiclass":
            return self.predict_proba(X)
        if self.task == "classification":
            return self.predict_confidence(X)
        return self.predict_value(X)
