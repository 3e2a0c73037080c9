"""Fleet review: rank LMD's results over every bag of a ``process_bags`` run.

    fleet_review OUT [--k 100] [--thumbnails 12] [--node lmd]

Reads ``OUT/results/<node>`` (all bags' Parquet tables at once, ``pyarrow.dataset``) and
writes ``OUT/review/``:

* ``annotation_errors.csv``: annotation-error candidates, the LMD paper's review
  (section IV g, as ``lidar_quality_training.lmd.annotation_review``): detections that
  the bag's labels call false positives (``iou_any`` < 0.5) ranked by predicted IoU,
  highest first: a confident, well-localized detection without a label is often a
  missing or misplaced label. Needs bags with ground truth (else the list is empty and
  the report says why).
* ``low_confidence.csv``: the published detections (``kept``) the meta model trusts
  least, lowest confidence first: weak detections to look at first.
* ``thumbnails/<list>_NNN.png`` and ``sheet_<list>.png``: a bird's-eye view of the top
  ``--thumbnails`` of each list (cloud around the box from its bag, the detection red,
  the frame's other detections grey, its labels purple where the bag has them).
* ``report.md`` with both lists' heads and the counts.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

__all__ = ["load_results", "rank", "review", "main"]

LISTS = ("annotation_errors", "low_confidence")
TABLE_COLUMNS = ("rank", "bag", "frame_key", "index", "det_id", "label", "score",
                 "confidence", "predicted_iou", "iou_any", "box_x", "box_y", "box_l",
                 "box_w", "box_yaw", "source")


def load_results(out, node: str = "lmd"):
    """Every bag's result rows of ``node`` in ``out`` (a ``process_bags`` output, or the
    ``--results`` folder of ``process_bag``) as a pandas DataFrame (``bag`` from the
    partition folders)."""
    import pyarrow.dataset as ds

    root = Path(out) / "results" / node
    if not root.is_dir() and (Path(out) / node).is_dir():   # process_bag --results DIR
        root = Path(out) / node
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no result tables of {node} (run process_bags with "
                                f"{node} in --nodes)")
    table = ds.dataset(root, format="parquet", partitioning="hive").to_table()
    df = table.to_pandas()
    df["bag"] = df["bag"].astype(str)
    return df


def rank(df, k: int) -> dict:
    """``{"annotation_errors": rows, "low_confidence": rows}``, top ``k`` each, ranked."""
    from lidar_quality_core.conventions import TP_IOU

    valid = df["valid"] if "valid" in df else np.ones(len(df), bool)
    fp = df[valid & df["iou_any"].notna() & (df["iou_any"] < TP_IOU)
            & df["predicted_iou"].notna()]
    # ties keep the bags' order (stable sort): the same list in every run
    errors = fp.sort_values("predicted_iou", ascending=False, kind="stable").head(k)
    kept = df[valid & df["kept"] & df["confidence"].notna()]
    weak = kept.sort_values("confidence", ascending=True, kind="stable").head(k)
    out = {}
    for name, rows in (("annotation_errors", errors), ("low_confidence", weak)):
        rows = rows.copy()
        rows.insert(0, "rank", np.arange(1, len(rows) + 1))
        out[name] = rows
    return out


def _gt_boxes(source: str, key: str) -> np.ndarray:
    """The labels of the frame with header stamp ``key`` in the bag (none: (0, 7))."""
    from lidar_quality_core.boxes import detections_to_arrays
    from lidar_quality_ros.bag_io import bag_topics
    from lidar_quality_ros.perception_bag import topic_of
    from lidar_quality_training.lmd.annotation_review import frame_message

    topic = topic_of("gt_objects")
    msg = frame_message(source, topic, int(key)) if topic in bag_topics(source) else None
    if msg is None:
        return np.zeros((0, 7))
    a = detections_to_arrays(msg)
    return a.boxes[a.valid]


BOX = ["box_x", "box_y", "box_z", "box_l", "box_w", "box_h", "box_yaw"]


def _panel(ax, row, xyz, others, labels, radius: float) -> None:
    from lidar_quality_training.lmd.annotation_review import draw_boxes, draw_points

    cx, cy = row["box_x"], row["box_y"]
    draw_points(ax, xyz, cx, cy, radius)
    draw_boxes(ax, others, color="#999999", lw=0.8)
    draw_boxes(ax, labels, color="#7b2cbf", lw=1.2)
    draw_boxes(ax, row[BOX].to_numpy(float), color="#e63946", lw=1.4)
    ax.set_xlim(cx - radius, cx + radius)
    ax.set_ylim(cy - radius, cy + radius)
    ax.set_aspect("equal")
    ax.tick_params(labelsize=6)
    ax.set_title(f"#{row['rank']} {row['label']} pIoU {row['predicted_iou']:.2f} "
                 f"c {row['confidence']:.2f}\n{row['bag']} {row['frame_key']}", fontsize=7)


def thumbnails(df, rows, name: str, out_dir: Path, *, radius: float = 10.0,
               columns: int = 4) -> list[Path]:
    """One BEV picture per row of ``rows`` and a contact sheet; returns the paths."""
    from lidar_quality_core.report_plots import figure, save
    from lidar_quality_training.lmd.annotation_review import load_points

    cache: dict = {}
    panels = []
    for _, row in rows.iterrows():
        key = (row["source"], row["frame_key"])
        if key not in cache:
            frame = df[(df["source"] == row["source"]) & (df["frame_key"] == row["frame_key"])]
            cache[key] = (load_points(*key), frame, _gt_boxes(*key))
        xyz, frame, labels = cache[key]
        others = frame[frame["index"] != row["index"]][BOX].to_numpy(float)
        panels.append((row, xyz, others, labels))
    paths = []
    for row, xyz, others, labels in panels:
        fig = figure(3.2, 3.4)
        _panel(fig.add_subplot(1, 1, 1), row, xyz, others, labels, radius)
        paths.append(save(fig, out_dir / "thumbnails" / f"{name}_{row['rank']:03d}.png"))
    if panels:
        ncol = min(columns, len(panels))
        nrow = -(-len(panels) // ncol)
        fig = figure(3.0 * ncol, 3.2 * nrow)
        for n, panel in enumerate(panels):
            _panel(fig.add_subplot(nrow, ncol, n + 1), *panel, radius)
        fig.suptitle(f"{name.replace('_', ' ')}: detection red, other detections grey, "
                     "labels purple", fontsize=8)
        paths.append(save(fig, out_dir / f"sheet_{name}.png"))
    return paths


def _markdown(rows, n: int = 20) -> str:
    cols = [c for c in TABLE_COLUMNS if c in rows and c != "source"]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for _, r in rows.head(n).iterrows():
        lines.append("| " + " | ".join(f"{r[c]:.3f}" if isinstance(r[c], float) else str(r[c])
                                       for c in cols) + " |")
    return "\n".join(lines)


def review(out, *, k: int = 100, n_thumbnails: int = 12, node: str = "lmd") -> dict:
    """Rank, write the lists, thumbnails and ``report.md`` under ``out/review``; returns
    ``{list: DataFrame}``."""
    out = Path(out)
    df = load_results(out, node)
    lists = rank(df, k)
    rdir = out / "review"
    rdir.mkdir(parents=True, exist_ok=True)
    with_gt = int(df["iou_any"].notna().sum())
    text = [f"# Fleet review of {out}", "",
            f"{len(df)} detections of {df['bag'].nunique()} bag(s), "
            f"{df.groupby(['bag', 'frame_key']).ngroups} frames; {with_gt} with ground truth.",
            ""]
    for name, rows in lists.items():
        cols = [c for c in TABLE_COLUMNS if c in rows]
        rows[cols].to_csv(rdir / f"{name}.csv", index=False)
        pics = thumbnails(df, rows.head(n_thumbnails), name, rdir) if n_thumbnails else []
        text += [f"## {name.replace('_', ' ').capitalize()}", ""]
        if name == "annotation_errors" and not with_gt:
            text += ["No bag has ground truth (`/lidar/gt_objects`): no candidates.", ""]
            continue
        text += [f"Top {len(rows)} (`{name}.csv`)" + (f", sheet `sheet_{name}.png`" if pics
                                                      else "") + ":", "", _markdown(rows), ""]
    (rdir / "report.md").write_text("\n".join(text) + "\n")
    return lists


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="fleet_review", description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path, help="a process_bags output folder")
    ap.add_argument("--k", type=int, default=100, help="length of each list (default 100)")
    ap.add_argument("--thumbnails", type=int, default=12, help="pictures per list")
    ap.add_argument("--node", default="lmd", choices=("lmd", "mimo"),
                    help="whose detections (default lmd)")
    a = ap.parse_args(argv)
    try:
        lists = review(a.out, k=a.k, n_thumbnails=a.thumbnails, node=a.node)
    except FileNotFoundError as exc:
        print(f"fleet_review: {exc}", file=sys.stderr)
        return 2
    for name, rows in lists.items():
        print(f"{name}: {len(rows)} rows -> {a.out / 'review' / (name + '.csv')}")
    print(f"report: {a.out / 'review' / 'report.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
