"""Parquet feature tables: the rows a meta model trains on, one format for LMD, LMS and MIMO.

The dataset builders (``lmd/``, ``lms/``, ``mimo/`` ``dataset.py``) and ``process_bags``
write them; ``lmd-train`` / ``lms-train`` / ``mimo-train --features`` read them back into
the dataset objects the trainers take, so a table trains the same models as the bags it
came from. One row per scored item (LMD detection, LMS segment, MIMO merged detection).

Columns (names fixed: the ``process_bags`` writer uses the same):

* ``feat.<name>`` (float64), one per feature, in the model's feature order;
* ``group`` (str: the sequence / bag of grouped cross validation), ``source`` (str: bag
  path or KITTI file), ``frame_key`` (str: header stamp [ns] for bags, frame id for KITTI;
  LMS: see below), ``index`` (int32: position among its frame's scored items);
* targets, NaN where there is no ground truth: LMD and MIMO ``iou_any``, ``iou_class``
  (BEV IoU with the best ground-truth box of any class / of the item's class); LMS
  ``iou``, ``iou_adj``;
* LMD: ``score`` (detector score), ``label`` (class), ``det_id``, ``box_x, box_y, box_z,
  box_l, box_w, box_h, box_yaw``; MIMO: ``score``, ``label`` (class name), ``box_*``;
  LMS: ``segment_class`` (int), ``size`` (S), ``size_projected`` (SP).

Schema metadata: ``lq.method`` (``lmd`` | ``lms`` | ``mimo``), ``lq.mode`` (LMD proposal
mode; MIMO ``points`` | ``no_points``, whether the point features are in; LMS where the
image rows come from: ``points`` (ring field), ``segmentation`` (field of view) or
``none`` (SemanticKITTI)), ``lq.feature_names`` (JSON list), ``lq.settings`` (JSON: the
settings record the trainers write into the manifests), ``lq.version`` (``1``).
Optional ``lq.info`` (JSON, our writer's): what the rows do not hold, e.g. the frames
without a scored item, rows the builder left out, LMS's ignored label, and
``"frame_key": "frame_index"`` when LMS frame keys are frame positions (the LMS dataset
keeps no stamps). Without it, LMS numbers each sequence's frames by their sorted keys.

Reading (:func:`read_lmd`, :func:`read_lms`, :func:`read_mimo`) takes files, directory
trees of ``*.parquet`` (Hive partitions such as ``bag=NAME/part-0.parquet``: a column
missing from a file is taken from its ``NAME=VALUE`` folders) and globs; files are read in
sorted path order, rows in file order. Other columns (``bag``, ``stamp_ns``,
``confidence``, ...) are ignored. Rows without targets (NaN) and rows whose features are
all NaN (a box the node could not score) are left out and counted in the dataset's
``info`` (``rows_without_targets``, ``rows_invalid``). Refused, naming the file and what
is missing: a file without the metadata, of another method or version, without target or
key columns, with other feature names than its mode's, or tables of one mode with
different settings. Each file is one source in ``info["sources"]``; the frame table holds
the frames that have rows (counts of the others come from ``lq.info`` when present).
What a table does not carry stays empty in the datasets read from it (ground-truth
tables, LMD ``frame_points`` = -1, MIMO class distributions, variances and single-head
rows): enough to train, not for the evaluations (``*-eval`` read bags).

Other writers (``process_bags``) build the metadata with :func:`schema_metadata` and may
write with :func:`write_table` (atomic: temp file, then rename).
"""
from __future__ import annotations

import glob
import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence
from urllib.parse import unquote

import numpy as np

__all__ = ["VERSION", "METHODS", "FEATURE_PREFIX", "KEY_COLUMNS", "TARGETS", "ITEM_COLUMNS",
           "TableError", "schema_metadata", "table_of", "write_table", "write_dataset",
           "export_tables", "table_files",
           "read_lmd", "read_lms", "read_mimo"]

VERSION = "1"
METHODS = ("lmd", "lms", "mimo")
FEATURE_PREFIX = "feat."
KEY_COLUMNS = ("group", "source", "frame_key", "index")
TARGETS = {"lmd": ("iou_any", "iou_class"), "mimo": ("iou_any", "iou_class"),
           "lms": ("iou", "iou_adj")}
BOX_COLUMNS = tuple(f"box_{c}" for c in ("x", "y", "z", "l", "w", "h", "yaw"))
#: Per method, the columns besides keys, targets and features (all required on reading).
ITEM_COLUMNS = {"lmd": ("score", "label", "det_id") + BOX_COLUMNS,
                "mimo": ("score", "label") + BOX_COLUMNS,
                "lms": ("segment_class", "size", "size_projected")}
_STRING = ("group", "source", "frame_key", "label", "det_id")
_INT = {"index": np.int32, "segment_class": np.int32, "size": np.int64,
        "size_projected": np.int64}


class TableError(ValueError):
    """A feature table that cannot be used as asked (the message says why and where)."""


# ------------------------------------------------------------------ writing
def schema_metadata(method: str, mode: str, feature_names, settings: dict,
                    info: dict | None = None) -> dict[bytes, bytes]:
    """The schema metadata of a table (module docstring; for other writers too):
    ``settings`` is the JSON-normal settings record, ``info`` the optional ``lq.info``."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    meta = {"lq.method": method, "lq.mode": mode,
            "lq.feature_names": json.dumps(list(feature_names)),
            "lq.settings": json.dumps(settings), "lq.version": VERSION}
    if info is not None:
        meta["lq.info"] = json.dumps(info)
    return {k.encode(): v.encode() for k, v in meta.items()}


def _table(columns: dict, X: np.ndarray, names, meta: dict[bytes, bytes]):
    import pyarrow as pa

    arrays, fields = [], []
    for name, values in columns.items():
        if name in _STRING:
            arr = pa.array(np.asarray(values, dtype=str).tolist(), pa.string())
        else:
            arr = pa.array(np.asarray(values, dtype=_INT.get(name, np.float64)))
        arrays.append(arr)
        fields.append(pa.field(name, arr.type))
    for j, n in enumerate(names):
        arrays.append(pa.array(np.ascontiguousarray(X[:, j], dtype=np.float64)))
        fields.append(pa.field(FEATURE_PREFIX + n, pa.float64()))
    return pa.Table.from_arrays(arrays, schema=pa.schema(fields, metadata=meta))


def _rank_in_frame(frame: np.ndarray) -> np.ndarray:
    """Position of each row among the rows of its frame (rows of a frame in order)."""
    frame = np.asarray(frame, np.int64)
    if not len(frame):
        return np.zeros(0, np.int32)
    order = np.argsort(frame, kind="stable")
    f = frame[order]
    start = np.r_[0, np.flatnonzero(np.diff(f)) + 1]
    run_start = np.repeat(start, np.diff(np.r_[start, len(f)]))
    rank = np.empty(len(f), np.int64)
    rank[order] = np.arange(len(f)) - run_start
    return rank.astype(np.int32)


def _box_columns(box: np.ndarray) -> dict:
    box = np.asarray(box, np.float64).reshape(-1, 7)
    return {c: box[:, j] for j, c in enumerate(BOX_COLUMNS)}


def lmd_table(ds):
    """The table of an ``LmdDataset`` (one proposal mode)."""
    cols = {"group": ds.frame_group[ds.frame], "source": ds.frame_source[ds.frame],
            "frame_key": ds.frame_key[ds.frame], "index": ds.det_index,
            "iou_any": ds.iou_any, "iou_class": ds.iou_class, "score": ds.score,
            "label": ds.label, "det_id": ds.det_id, **_box_columns(ds.box)}
    info = {k: ds.info[k] for k in ("dropped_invalid", "frames_without_gt") if k in ds.info}
    info.update(frames=int(ds.n_frames), gt_boxes=int(len(ds.gt_box)))
    return _table(cols, ds.X, ds.feature_names, schema_metadata(
        "lmd", ds.mode, ds.feature_names, ds.info.get("settings"), info))


def lms_table(ds):
    """The table of a ``SegmentDataset``; ``group`` is the sequence name (the CV groups,
    sub-sequences of ``block_frames`` frames, are made again on reading)."""
    seq = np.asarray(ds.sequence, np.int64)
    sources = list(ds.info.get("sources") or ds.sequences)
    key = seq * (int(ds.frame.max()) + 1 if len(ds.frame) else 1) + ds.frame
    cols = {"group": np.asarray(ds.sequences, dtype=str)[seq] if len(seq) else [],
            "source": np.asarray(sources, dtype=str)[seq] if len(seq) else [],
            "frame_key": np.asarray(ds.frame).astype(str), "index": _rank_in_frame(key),
            "iou": ds.iou, "iou_adj": ds.iou_adj, "segment_class": ds.segment_class,
            "size": ds.size, "size_projected": ds.size_projected}
    info = {k: ds.info[k] for k in ("n_frames", "n_excluded", "dropped_undefined",
                                    "ignore_label") if k in ds.info}
    info["frame_key"] = "frame_index"
    mode = ds.info.get("ring_from") or "points"
    return _table(cols, ds.X, ds.names,
                  schema_metadata("lms", mode, ds.names, ds.info.get("settings"), info))


def mimo_table(ds):
    """The table of a ``MimoDataset``'s merged detections: mode ``points`` with every
    feature of the dataset (both models' schemas), ``no_points`` without the point ones."""
    from mimo_ros.pipeline import MimoSettings

    full = MimoSettings(use_points=True).feature_names()
    mode = "points" if tuple(ds.feature_names) == tuple(full) else "no_points"
    names = np.asarray(ds.class_names, dtype=str)
    cols = {"group": ds.frame_group[ds.m_frame], "source": ds.frame_source[ds.m_frame],
            "frame_key": ds.frame_stamp[ds.m_frame].astype(str),
            "index": _rank_in_frame(ds.m_frame), "iou_any": ds.m_iou_any,
            "iou_class": ds.m_iou_class, "score": ds.m_score,
            "label": names[ds.m_label - 1] if len(ds) else [], **_box_columns(ds.m_box)}
    s = ds.summary()
    info = {k: ds.info[k] for k in ("dropped_single", "frames_without_gt",
                                    "frames_without_heads", "issues") if k in ds.info}
    info.update(frames=s["frames"], gt_boxes=s["gt_boxes"], gt_ignored=s["gt_ignored"],
                single=s["single"], single_tp=s["single_tp"])
    return _table(cols, ds.X, ds.feature_names, schema_metadata(
        "mimo", mode, ds.feature_names, ds.info.get("settings"), info))


def table_of(ds):
    """The feature table of a dataset object (``LmdDataset``, ``SegmentDataset``,
    ``MimoDataset``)."""
    kind = type(ds).__name__
    make = {"LmdDataset": lmd_table, "SegmentDataset": lms_table, "MimoDataset": mimo_table}
    if kind not in make:
        raise TypeError(f"no feature table for a {kind}")
    return make[kind](ds)


def write_table(table, path) -> Path:
    """Write ``table`` to ``path`` atomically (a temp file beside it, then a rename): a
    reader sees the old file or the complete new one."""
    import pyarrow.parquet as pq
    from lidar_quality_core.model_store import write_atomic

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # the temp name ends in .tmp, not .parquet: a directory read never picks it up
    write_atomic(path, lambda tmp: pq.write_table(table, tmp), digest=False)
    return path


def add_table_arguments(ap, *, instead_of: str, export_to: str, test: bool = False) -> None:
    """A trainer's ``--features`` (with ``test``: ``--test-features``), ``--export-features``
    (the dataset written to ``export_to``) and ``--export-only``; see
    :func:`check_table_arguments`."""
    g = ap.add_argument_group(f"feature tables (Parquet; instead of {instead_of})")
    g.add_argument("--features", action="append", default=None, metavar="PATH",
                   help="training feature tables: a file, a directory tree of *.parquet "
                        f"(Hive partitions too) or a glob; repeatable. Replaces {instead_of}; "
                        "the tables' settings are used")
    if test:
        g.add_argument("--test-features", action="append", default=None, metavar="PATH",
                       help="held-out feature tables (same forms; repeatable)")
    g.add_argument("--export-features", type=Path, default=None, metavar="DIR",
                   help=f"write the dataset as feature tables: {export_to}")
    g.add_argument("--export-only", action="store_true",
                   help="with --export-features: write the tables and stop (no training)")


def check_table_arguments(ap, args) -> None:
    """The argument parser's error for ``--export-only`` without ``--export-features``."""
    if args.export_only and args.export_features is None:
        ap.error("--export-only needs --export-features DIR")


def write_dataset(ds, path) -> Path:
    """``write_table(table_of(ds), path)``."""
    return write_table(table_of(ds), path)


def export_tables(datasets, out_dir) -> list[Path]:
    """One table per dataset, ``<out_dir>/<method>_<mode>.parquet``: ``datasets`` is a
    dataset or ``{name: dataset}`` (LMD's modes)."""
    items = datasets.values() if isinstance(datasets, dict) else [datasets]
    paths = []
    for ds in items:
        t = table_of(ds)
        meta = t.schema.metadata
        name = f"{meta[b'lq.method'].decode()}_{meta[b'lq.mode'].decode()}.parquet"
        paths.append(write_table(t, Path(out_dir) / name))
    return paths


# ------------------------------------------------------------------ reading
@dataclass
class _File:
    path: Path
    method: str
    mode: str
    feature_names: tuple
    settings: dict
    info: dict
    columns: set
    partition: dict = field(default_factory=dict)  # Hive folder values by column


def _is_glob(p: str) -> bool:
    return any(c in p for c in "*?[")


def _partition_values(path: Path, base: Path) -> dict:
    try:
        rel = path.parent.relative_to(base)
    except ValueError:
        return {}
    out = {}
    for part in rel.parts:
        m = re.fullmatch(r"([^=]+)=(.*)", part)
        if m:
            out[unquote(m.group(1))] = unquote(m.group(2))
    return out


def table_files(paths: Sequence) -> list[tuple[Path, Path]]:
    """``(file, base directory)`` of every ``*.parquet`` that ``paths`` name (files,
    directory trees, globs), sorted per path; hidden files and folders are skipped."""
    out = []
    for p in map(str, paths):
        if _is_glob(p):
            hits = sorted(Path(h) for h in glob.glob(p, recursive=True))
            files = [h for h in hits if h.is_file()]
            for d in (h for h in hits if h.is_dir()):
                files += [(f) for f, _ in table_files([d])]
            base = Path(re.split(r"[*?\[]", p)[0])
            base = base if base.is_dir() else base.parent
            found = [(f, base) for f in sorted(set(files))]
        elif Path(p).is_dir():
            root = Path(p)
            found = [(f, root) for f in sorted(root.rglob("*.parquet")) if f.is_file()
                     and not any(s.startswith((".", "_")) for s in f.relative_to(root).parts)]
        elif Path(p).is_file():
            found = [(Path(p), Path(p).parent)]
        else:
            raise TableError(f"{p}: no such file or directory")
        if not found:
            raise TableError(f"{p}: no *.parquet feature table there")
        out += found
    return out


def _open(path: Path, base: Path) -> _File:
    import pyarrow.parquet as pq

    try:
        schema = pq.read_schema(path)
    except Exception as exc:  # pyarrow's own error types: say which file, as a TableError
        raise TableError(f"{path}: not a readable Parquet file ({exc})") from None
    meta = {k.decode(): v.decode() for k, v in (schema.metadata or {}).items()}
    if "lq.method" not in meta:
        raise TableError(f"{path}: not a lidar_quality feature table (no lq.method in its "
                         "schema metadata)")
    if meta.get("lq.version") != VERSION:
        raise TableError(f"{path}: feature table version {meta.get('lq.version')!r}, this "
                         f"code reads version {VERSION}")
    missing = [k for k in ("lq.mode", "lq.feature_names", "lq.settings") if k not in meta]
    if missing:
        raise TableError(f"{path}: schema metadata without {', '.join(missing)}")
    try:
        names = tuple(json.loads(meta["lq.feature_names"]))
        settings = json.loads(meta["lq.settings"])
        info = json.loads(meta.get("lq.info") or "{}")
    except ValueError as exc:
        raise TableError(f"{path}: schema metadata is not valid JSON ({exc})") from None
    if not isinstance(settings, dict):
        raise TableError(f"{path}: lq.settings is not a settings record (a JSON object)")
    return _File(path, meta["lq.method"], meta["lq.mode"], names, settings,
                 info if isinstance(info, dict) else {}, set(schema.names),
                 _partition_values(path, base))


def _check_columns(f: _File, method: str) -> None:
    have = f.columns | set(f.partition)
    targets = [c for c in TARGETS[method] if c not in have]
    if targets:
        raise TableError(f"{f.path}: no target column{'s' if len(targets) > 1 else ''} "
                         f"{', '.join(targets)}: a table without ground truth cannot train "
                         "or test a model")
    need = list(KEY_COLUMNS) + list(ITEM_COLUMNS[method])
    need += [FEATURE_PREFIX + n for n in f.feature_names]
    missing = [c for c in need if c not in have]
    if missing:
        shown = ", ".join(missing[:8]) + (f" and {len(missing) - 8} more" if len(missing) > 8
                                          else "")
        raise TableError(f"{f.path}: missing column{'s' if len(missing) > 1 else ''} {shown}")


def _names_diff(expected, actual) -> str:
    expected, actual = list(expected), list(actual)
    miss = [n for n in expected if n not in actual]
    extra = [n for n in actual if n not in expected]
    parts = []
    if miss:
        parts.append(f"missing {miss[:6]}{' ...' if len(miss) > 6 else ''}")
    if extra:
        parts.append(f"extra {extra[:6]}{' ...' if len(extra) > 6 else ''}")
    if not parts:
        parts.append("same names in another order")
    return "; ".join(parts)


def _check_names(f: _File, expected, what: str) -> None:
    if tuple(f.feature_names) != tuple(expected):
        raise TableError(f"{f.path}: its feature names are not {what}'s "
                         f"({len(expected)} features): {_names_diff(expected, f.feature_names)}")


def _files_of(paths, method: str, tool: str) -> list[_File]:
    files = [_open(p, b) for p, b in table_files(paths)]
    for f in files:
        if f.method != method:
            raise TableError(f"{f.path}: a {f.method} feature table; {tool} trains on "
                             f"{method} tables")
    return files


def _same_settings(files: list[_File], what: str) -> dict:
    first = files[0]
    for f in files[1:]:
        if f.settings != first.settings:
            keys = sorted(k for k in set(f.settings) | set(first.settings)
                          if f.settings.get(k) != first.settings.get(k))
            raise TableError(f"{what}: {first.path} and {f.path} were made with different "
                             f"settings ({', '.join(keys)}: {first.settings.get(keys[0])!r} vs "
                             f"{f.settings.get(keys[0])!r}); train on tables of one setting")
    return first.settings


def _column(table, name: str, f: _File, n: int) -> np.ndarray:
    import pyarrow as pa

    if name in table.column_names:
        col = table.column(name)
    else:  # only in the Hive folder names
        col = pa.array([f.partition[name]] * n, pa.string())
    if col.null_count and (name in KEY_COLUMNS
                           or (name in ITEM_COLUMNS[f.method] and name != "score")):
        raise TableError(f"{f.path}: column {name} has {col.null_count} empty values")
    if name in _STRING:
        if not pa.types.is_string(col.type) and not pa.types.is_large_string(col.type):
            col = col.cast(pa.string())
        return np.asarray(col.to_pylist(), dtype=str).reshape(n)
    if name in _INT:
        try:
            return np.asarray(col.to_numpy(), dtype=np.float64).astype(_INT[name]).reshape(n)
        except (TypeError, ValueError):
            raise TableError(f"{f.path}: column {name} is {col.type}, not a number") from None
    if not (pa.types.is_floating(col.type) or pa.types.is_integer(col.type)):
        raise TableError(f"{f.path}: column {name} is {col.type}, not a number")
    # nulls (a writer without NaN) read as NaN: float conversion of the filled array
    return np.asarray(col.cast(pa.float64()).fill_null(np.nan).to_numpy(),
                      dtype=np.float64).reshape(n)


@dataclass
class _Rows:
    cols: dict
    X: np.ndarray
    sources: list
    info: dict
    without_targets: int
    invalid: int


def _read_rows(files: list[_File], method: str, names) -> _Rows:
    """Keys, targets, item columns and features of ``files`` (one mode), rows with targets
    and with a feature only."""
    import pyarrow.parquet as pq

    wanted = list(KEY_COLUMNS) + list(TARGETS[method]) + list(ITEM_COLUMNS[method])
    parts, Xs, sources = [], [], []
    without = invalid = 0
    for f in files:
        in_file = [c for c in wanted + [FEATURE_PREFIX + n for n in names] if c in f.columns]
        t = pq.read_table(f.path, columns=in_file)
        n = t.num_rows
        cols = {c: _column(t, c, f, n) for c in wanted}
        X = np.column_stack([_column(t, FEATURE_PREFIX + c, f, n) for c in names]) \
            if names else np.zeros((n, 0))
        has_targets = np.ones(n, bool)
        for c in TARGETS[method]:
            has_targets &= np.isfinite(cols[c])
        valid = ~np.isnan(X).all(axis=1) if X.shape[1] else np.ones(n, bool)
        keep = has_targets & valid
        without += int((~has_targets).sum())
        invalid += int((has_targets & ~valid).sum())
        parts.append({c: v[keep] for c, v in cols.items()})
        Xs.append(X[keep])
        sources.append({"kind": "feature_table", "path": str(f.path),
                        "rows": int(keep.sum())})
    cols = {c: np.concatenate([p[c] for p in parts]) for c in wanted}
    return _Rows(cols, np.concatenate(Xs).reshape(-1, len(names)), sources,
                 _merge_info([f.info for f in files]), without, invalid)


def _merge_info(infos: list[dict]) -> dict:
    """Counts summed over files (kept only where every file has them); other values kept
    where every file agrees."""
    out = {}
    for k in set().union(*infos) if infos else ():
        vals = [i.get(k) for i in infos]
        if any(k not in i for i in infos):
            continue
        if all(isinstance(v, int) and not isinstance(v, bool) for v in vals):
            out[k] = int(sum(vals))
        elif all(v == vals[0] for v in vals):
            out[k] = vals[0]
    return out


def _frames(rows: _Rows) -> tuple[np.ndarray, np.ndarray]:
    """(frame row of each row, first row of each frame): frames are distinct (source,
    frame_key) pairs in first-seen order."""
    c = rows.cols
    key = np.char.add(np.char.add(c["source"], "\x00"), c["frame_key"]) if len(c["source"]) \
        else np.zeros(0, dtype=str)
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order))
    return rank[inverse.reshape(-1)], first[order]


def _table_info(rows: _Rows, settings: dict, top: Sequence[str]) -> dict:
    """The dataset's ``info``: sources, settings, the counts of rows left out, the
    builder's counts ``top`` that ``lq.info`` has, and all of ``lq.info`` under
    ``"table"`` (the summaries take frame and ground-truth counts from there)."""
    info = {k: rows.info[k] for k in top if k in rows.info}
    info.update(sources=rows.sources, settings=settings,
                rows_without_targets=rows.without_targets, rows_invalid=rows.invalid,
                table=dict(rows.info))
    return info


def _require_rows(rows: _Rows, what: str) -> None:
    if not len(rows.X):
        raise TableError(f"{what}: no row with targets and features in "
                         f"{', '.join(s['path'] for s in rows.sources)} "
                         f"({rows.without_targets} rows without targets, {rows.invalid} "
                         "invalid)")


def read_lmd(paths, *, modes=None, class_aware: bool = False,
             tool: str = "lmd-train") -> dict:
    """``{mode: LmdDataset}`` of the LMD tables ``paths`` (all modes found, or ``modes``:
    each must be there). Feature names must be the mode's under the tables' settings;
    the datasets' settings are the tables' (``lq.settings``)."""
    from lidar_quality_core.lmd import features

    from .lmd.dataset import LmdDataset

    files = _files_of(paths, "lmd", tool)
    by_mode: dict[str, list[_File]] = {}
    for f in files:
        by_mode.setdefault(f.mode, []).append(f)
    if modes is not None:
        absent = [m for m in modes if m not in by_mode]
        if absent:
            raise TableError(f"no LMD table of mode{'s' if len(absent) > 1 else ''} "
                             f"{', '.join(absent)} in {', '.join(map(str, paths))} (modes "
                             f"there: {', '.join(sorted(by_mode)) or 'none'})")
        by_mode = {m: by_mode[m] for m in modes}
    out = {}
    for mode, fs in by_mode.items():
        settings = _same_settings(fs, f"LMD mode {mode}")
        try:
            expected = features.feature_names(
                mode, settings.get("class_names") if settings.get("class_score_features")
                else None)
        except ValueError as exc:
            raise TableError(f"{fs[0].path}: {exc}") from None
        for f in fs:
            _check_names(f, expected, f"LMD mode {mode}")
            _check_columns(f, "lmd")
        rows = _read_rows(fs, "lmd", expected)
        _require_rows(rows, f"LMD mode {mode}")
        frame, first = _frames(rows)
        c = rows.cols
        info = _table_info(rows, settings, ("frames_without_gt",))
        # an invalid box (all-NaN features) is what the builder counts as dropped_invalid
        info["dropped_invalid"] = int(rows.info.get("dropped_invalid", 0)) + rows.invalid
        n = len(rows.X)
        out[mode] = LmdDataset(
            mode=mode, feature_names=tuple(expected), X=rows.X, iou_any=c["iou_any"],
            iou_class=c["iou_class"], score=c["score"], label=c["label"],
            box=np.column_stack([c[b] for b in BOX_COLUMNS]).reshape(n, 7),
            det_index=c["index"].astype(np.int64), det_id=c["det_id"], frame=frame,
            frame_group=c["group"][first], frame_source=c["source"][first],
            frame_key=c["frame_key"][first],
            frame_points=np.full(len(first), -1, np.int64),  # not in the table
            gt_offsets=np.zeros(len(first) + 1, np.int64), gt_box=np.zeros((0, 7)),
            gt_label=np.zeros(0, dtype=str), gt_id=np.zeros(0, dtype=str),
            gt_points=np.zeros(0, np.int64), class_aware=bool(class_aware), info=info)
    return out


def _frame_numbers(rows: _Rows, sequence: np.ndarray) -> np.ndarray:
    """Each row's frame number in its sequence: the key itself when the tables say keys
    are frame positions, else the rank of the key among the sequence's sorted keys."""
    keys = rows.cols["frame_key"]
    if rows.info.get("frame_key") == "frame_index":
        return keys.astype(np.int64)
    numeric = all(k.lstrip("-").isdigit() for k in np.unique(keys))
    frame = np.empty(len(keys), np.int64)
    for s in np.unique(sequence):
        rows_s = np.flatnonzero(sequence == s)
        k = keys[rows_s]
        uniq = np.unique(k.astype(np.int64) if numeric else k)
        frame[rows_s] = np.searchsorted(uniq, k.astype(np.int64) if numeric else k)
    return frame


def read_lms(paths, *, block_frames: int | None = None, tool: str = "lms-train"):
    """The ``SegmentDataset`` of the LMS tables ``paths`` (one mode, one setting);
    cross-validation groups are sub-sequences of ``block_frames`` frames of each
    ``group`` (sequence)."""
    from lidar_quality_core.lms.segment_metrics import metric_names

    from .lms.dataset import DEFAULT_BLOCK_FRAMES, SegmentDataset, subsequence_groups

    files = _files_of(paths, "lms", tool)
    modes = sorted({f.mode for f in files})
    if len(modes) > 1:
        raise TableError(f"LMS tables of different image sources ({', '.join(modes)}: "
                         "lq.mode) cannot train one model; pass the tables of one")
    settings = _same_settings(files, "LMS")
    classes = settings.get("class_names")
    if not classes:
        raise TableError(f"{files[0].path}: lq.settings has no class_names")
    expected = metric_names(len(classes), classes)
    for f in files:
        _check_names(f, expected, f"LMS with {len(classes)} classes")
        _check_columns(f, "lms")
    rows = _read_rows(files, "lms", expected)
    _require_rows(rows, "LMS")
    c = rows.cols
    names_seen = list(dict.fromkeys(c["group"].tolist()))
    pos = {n: k for k, n in enumerate(names_seen)}
    sequence = np.array([pos[g] for g in c["group"].tolist()], np.int32)
    frame = _frame_numbers(rows, sequence).astype(np.int32)
    block = int(block_frames or DEFAULT_BLOCK_FRAMES)
    src_of = dict(zip(c["group"].tolist(), c["source"].tolist()))
    info = _table_info(rows, settings, ("n_frames", "n_excluded", "dropped_undefined",
                                        "ignore_label"))
    # LMS datasets list their sources as paths (lms.train.data_summary)
    info.update(block_frames=block, ring_from=modes[0],
                sources=[s["path"] for s in rows.sources],
                table_sources=[src_of[n] for n in names_seen])
    if "n_frames" not in info:
        info["n_frames"] = int(len(np.unique(np.stack([sequence, frame]), axis=1).T))
    return SegmentDataset(
        X=rows.X, names=tuple(expected), iou=c["iou"], iou_adj=c["iou_adj"],
        segment_class=c["segment_class"], size=c["size"], size_projected=c["size_projected"],
        sequence=sequence, frame=frame, group=subsequence_groups(sequence, frame, block),
        sequences=tuple(names_seen), class_names=tuple(classes), info=info)


def read_mimo(paths, *, tool: str = "mimo-train"):
    """The ``MimoDataset`` of the MIMO tables ``paths`` (merged detections only: no
    single-head baseline, no ground-truth table). Mode ``points`` tables train both
    pairs, ``no_points`` tables the ``mimo`` pair only."""
    from mimo_ros.pipeline import MimoSettings

    from .mimo.dataset import MimoDataset

    files = _files_of(paths, "mimo", tool)
    modes = sorted({f.mode for f in files})
    unknown = [m for m in modes if m not in ("points", "no_points")]
    if unknown:
        raise TableError(f"unknown MIMO table mode {unknown[0]!r} (points or no_points)")
    if len(modes) > 1:
        raise TableError("MIMO tables with and without the point features (lq.mode points "
                         "and no_points) cannot be mixed; pass the tables of one")
    settings = _same_settings(files, "MIMO")
    expected = MimoSettings(use_points=modes[0] == "points").feature_names()
    for f in files:
        _check_names(f, expected, f"MIMO mode {modes[0]}")
        _check_columns(f, "mimo")
    classes = tuple(settings.get("class_names") or ())
    if not classes:
        raise TableError(f"{files[0].path}: lq.settings has no class_names")
    rows = _read_rows(files, "mimo", expected)
    _require_rows(rows, "MIMO")
    c = rows.cols
    pos = {n: k + 1 for k, n in enumerate(classes)}
    unknown = sorted(set(c["label"].tolist()) - set(pos))
    if unknown:
        raise TableError(f"MIMO labels {unknown} are not in the tables' class_names "
                         f"{list(classes)}")
    frame, first = _frames(rows)
    n, C1 = len(rows.X), 1 + len(classes)
    stamps = c["frame_key"][first]
    info = _table_info(rows, settings, ("dropped_single", "frames_without_gt",
                                        "frames_without_heads", "issues"))
    e7 = np.zeros((0, 7))
    return MimoDataset(
        classes, tuple(expected), X=rows.X,
        m_box=np.column_stack([c[b] for b in BOX_COLUMNS]).reshape(n, 7),
        m_probs=np.full((n, C1), np.nan),  # not in the table
        m_label=np.array([pos[x] for x in c["label"].tolist()], np.int64).reshape(n),
        m_score=c["score"], m_var=np.full((n, 7), np.nan), m_iou_class=c["iou_class"],
        m_iou_any=c["iou_any"], m_frame=frame,
        s_box=e7, s_probs=np.zeros((0, C1)), s_label=np.zeros(0, np.int64),
        s_score=np.zeros(0), s_var=e7, s_iou_class=np.zeros(0), s_iou_any=np.zeros(0),
        s_frame=np.zeros(0, np.int64),
        frame_group=c["group"][first], frame_source=c["source"][first],
        frame_stamp=np.array([int(k) if k.lstrip("-").isdigit() else -1 for k in stamps],
                             np.int64).reshape(len(first)),
        frame_heads=np.full(len(first), -1, np.int64),  # not in the table
        gt_offsets=np.zeros(len(first) + 1, np.int64), gt_box=e7,
        gt_label=np.zeros(0, dtype=str), gt_id=np.zeros(0, dtype=str),
        gt_points=np.zeros(0, np.int64), info=info)
