"""Figures of the evaluation reports (LMD, LMS, MIMO, demo).

matplotlib is imported only here and only when drawing (Agg canvas, no display needed).
Every function writes one PNG and returns its path. The tables and model cards are
``lidar_quality_training.report``'s.
"""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from .metrics import reliability_diagram

__all__ = ["figure", "save", "reliability_png", "scatter_png", "curve_png", "histogram_png",
           "draw_bev_box", "bev_boxes_png", "bev_values_png"]


def figure(width: float = 5.0, height: float = 4.0):
    """A new matplotlib Figure on an Agg canvas (thread-safe, no pyplot state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=100)
    FigureCanvasAgg(fig)
    return fig


def save(fig, path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path)
    return path


def reliability_png(path, curves: Mapping[str, tuple[Sequence, Sequence]], *, n_bins: int = 10,
                    title: str = "Reliability diagram") -> Path:
    """One panel per named ``(y_true 0/1, probability)`` pair: bin accuracy against bin
    confidence, bar width = bin, with ECE / MCE in the panel title."""
    n = max(len(curves), 1)
    fig = figure(3.6 * n, 3.8)
    for k, (name, (y, p)) in enumerate(curves.items()):
        ax = fig.add_subplot(1, n, k + 1)
        rd = reliability_diagram(np.asarray(y, float), np.clip(np.asarray(p, float), 0, 1), n_bins)
        centers = 0.5 * (rd.edges[:-1] + rd.edges[1:])
        has = rd.counts > 0
        ax.bar(centers[has], rd.accuracy[has], width=1.0 / n_bins, edgecolor="k",
               color="#4c72b0", alpha=0.8, label="accuracy")
        ax.bar(centers[has], (rd.mean_confidence - rd.accuracy)[has], bottom=rd.accuracy[has],
               width=1.0 / n_bins, color="#dd8452", alpha=0.5, label="gap")
        ax.plot([0, 1], [0, 1], "k--", lw=1)
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
        ax.set_xlabel("confidence")
        if k == 0:
            ax.set_ylabel("fraction of true positives")
            ax.legend(loc="upper left", fontsize=8)
        ax.set_title(f"{name}\nECE {rd.ece:.3f}  MCE {rd.mce:.3f}", fontsize=9)
    fig.suptitle(title, fontsize=10)
    return save(fig, path)


def scatter_png(path, true, pred, *, xlabel: str = "true IoU", ylabel: str = "predicted IoU",
                title: str = "", max_points: int = 20000, seed: int = 0) -> Path:
    """True vs predicted scatter with the diagonal and R^2 in the title."""
    from .metrics import r2

    t, p = np.asarray(true, float), np.asarray(pred, float)
    ok = np.isfinite(t) & np.isfinite(p)
    t, p = t[ok], p[ok]
    score = r2(t, p) if t.size > 1 else float("nan")
    if t.size > max_points:
        keep = np.random.default_rng(seed).choice(t.size, max_points, replace=False)
        t, p = t[keep], p[keep]
    fig = figure(4.2, 4.0)
    ax = fig.add_subplot(1, 1, 1)
    ax.scatter(t, p, s=3, alpha=0.3, color="#4c72b0", linewidths=0)
    lo, hi = min(0.0, *(t.min(initial=0), p.min(initial=0))), max(1.0, t.max(initial=1), p.max(initial=1))
    ax.plot([lo, hi], [lo, hi], "k--", lw=1)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(f"{title}  R² = {score:.3f}".strip(), fontsize=10)
    return save(fig, path)


def curve_png(path, labels: Sequence[str], values: Sequence[float], *, ylabel: str,
              title: str = "") -> Path:
    """A curve over named steps (e.g. greedy selection: score after adding each feature)."""
    fig = figure(max(4.0, 0.45 * len(labels) + 2), 3.8)
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(np.arange(len(values)), values, "o-", color="#4c72b0")
    ax.set_xticks(np.arange(len(labels)))
    ax.set_xticklabels(labels, rotation=60, ha="right", fontsize=7)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    return save(fig, path)


def histogram_png(path, samples: Mapping[str, Sequence[float]], *, xlabel: str, bins: int = 50,
                  title: str = "") -> Path:
    """Overlaid histograms of named samples (e.g. latencies per node)."""
    fig = figure(5.0, 3.6)
    ax = fig.add_subplot(1, 1, 1)
    for name, v in samples.items():
        v = np.asarray(v, float)
        v = v[np.isfinite(v)]
        if v.size:
            ax.hist(v, bins=bins, alpha=0.5, label=f"{name} (n={v.size})")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("count")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8)
    return save(fig, path)


def draw_bev_box(ax, box, **kw) -> None:
    """Outline of one (7,) box ``x, y, z, l, w, h, yaw`` in the x-y plane."""
    from .box_geometry import bev_corners

    c = bev_corners(np.asarray(box, np.float64).reshape(1, 7))[0]
    c = np.vstack([c, c[:1]])
    ax.plot(c[:, 0], c[:, 1], **kw)


def _bev_axes(ax, xy, max_range: float) -> None:
    xy = np.asarray(xy, float).reshape(-1, 2)
    near = np.abs(xy).max(axis=1) <= max_range if len(xy) else np.zeros(0, bool)
    ax.scatter(xy[near, 0], xy[near, 1], s=0.2, color="0.6", linewidths=0)
    ax.set_xlim(-max_range, max_range)
    ax.set_ylim(-max_range, max_range)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def bev_boxes_png(path, xy, boxes, values, *, gt_boxes=(), title: str = "",
                  label: str = "confidence", max_range: float = 50.0) -> Path:
    """Bird's-eye view of one frame: the points (grey), ground-truth boxes (dashed black)
    and boxes coloured by ``values`` in [0, 1] (e.g. the meta confidence)."""
    import matplotlib
    from matplotlib import cm, colors

    fig = figure(6.4, 5.6)
    ax = fig.add_subplot(1, 1, 1)
    _bev_axes(ax, xy, max_range)
    for b in np.asarray(gt_boxes, float).reshape(-1, 7):
        draw_bev_box(ax, b, color="k", lw=0.8, ls="--")
    cmap, norm = matplotlib.colormaps["RdYlGn"], colors.Normalize(0.0, 1.0)
    for b, v in zip(np.asarray(boxes, float).reshape(-1, 7), np.asarray(values, float)):
        draw_bev_box(ax, b, color=cmap(norm(v)) if np.isfinite(v) else "m", lw=1.4)
    fig.colorbar(cm.ScalarMappable(norm=norm, cmap=cmap), ax=ax, label=label)
    ax.set_title(title, fontsize=10)
    return save(fig, path)


def bev_values_png(path, xy, panels: Mapping[str, Sequence[float]], *, label: str = "",
                   max_range: float = 50.0, title: str = "") -> Path:
    """Bird's-eye view of one frame's points, one panel per named per-point value in
    [0, 1] (NaN: grey), e.g. predicted against true segment IoU."""
    import matplotlib
    from matplotlib import cm, colors

    xy = np.asarray(xy, float).reshape(-1, 2)
    fig = figure(5.6 * max(len(panels), 1), 5.4)
    cmap, norm = matplotlib.colormaps["RdYlGn"], colors.Normalize(0.0, 1.0)
    for k, (name, v) in enumerate(panels.items()):
        ax = fig.add_subplot(1, len(panels), k + 1)
        _bev_axes(ax, xy, max_range)
        v = np.asarray(v, float).reshape(-1)
        ok = np.isfinite(v) & (np.abs(xy).max(axis=1) <= max_range)
        ax.scatter(xy[ok, 0], xy[ok, 1], c=v[ok], s=0.4, cmap=cmap, norm=norm, linewidths=0)
        ax.set_title(name, fontsize=10)
    fig.colorbar(cm.ScalarMappable(norm=norm, cmap=cmap), ax=fig.axes[-1], label=label)
    if title:
        fig.suptitle(title, fontsize=10)
    return save(fig, path)
