"""Bird's-eye-view picture of a simulated frame (a PNG for eyeballing the world).

    python -m lidar_sim.render --seed 7000 --frame 0 --out docs/sim_bev.png
    python -m lidar_sim.render --seed 7000 --scene suburban --out /tmp/suburban.png

``--seed`` is a sequence seed (split ``demo``'s first sequence is 7000); the frame is the
one ``lidar_sim.frames.sequence_frames(seed, frames, scene=scene)`` yields, i.e. with the
default scene type the one the datasets hold. matplotlib is imported only when rendering
(Agg canvas, no display needed).
"""
from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import numpy as np

from . import classes as C
from .scene import SCENE_TYPES

BOX_COLOR = (0.1, 0.1, 0.1)
#: share of white mixed into the ground classes' colours: the ground holds half the
#: points and in full colour drowns the objects on it
GROUND_FADE = 0.6
GROUND_CLASSES = (C.ROAD, C.SIDEWALK, C.TERRAIN)


def render_bev(frame, path, *, extent: float = 60.0, y_extent: float | None = None,
               boxes=None, box_color=BOX_COLOR, size_px: int = 1000, point_size: float = 0.5,
               name: str | None = None) -> Path:
    """Write a BEV PNG of ``frame`` (a :class:`~lidar_sim.simulate.SimFrame`) to ``path``.

    The view spans +-``extent`` m in x and +-``y_extent`` (default ``extent``) in y;
    ``size_px`` is the image width, the height follows the view's aspect. Points are
    coloured by semantic class and drawn low to high, so objects stay on top of the ground
    under them. ``boxes``: (N, 7) boxes to draw instead of the frame's ground truth (e.g.
    detections). Each box is an oriented rectangle with a tick from its centre to its front
    edge. The legend lists the classes present; the title starts with ``name`` (default
    "sequence S frame I") and gives the point and object counts. Returns the path written.
    """
    # the Agg canvas directly, not pyplot: no global backend switch, no display needed
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    from lidar_quality_core.box_geometry import bev_corners

    path = Path(path)
    y_extent = extent if y_extent is None else y_extent
    xyz = np.asarray(frame.xyz, dtype=np.float64)
    sem = np.asarray(frame.semantic, dtype=np.int64)
    keep = ((np.abs(xyz[:, 0]) <= extent) & (np.abs(xyz[:, 1]) <= y_extent)
            & (sem >= 0) & (sem < C.NUM_CLASSES))
    xyz, sem = xyz[keep], sem[keep]
    palette = C.colors_rgb(normalized=True)
    palette[list(GROUND_CLASSES)] += GROUND_FADE * (1.0 - palette[list(GROUND_CLASSES)])

    dpi = 100
    fig = Figure(figsize=(size_px / dpi, size_px / dpi * y_extent / extent), dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.set_facecolor("white")
    thing = C.is_thing(sem)
    for sel, size in ((~thing, point_size), (thing, 2.0 * point_size)):  # things on top
        i = np.flatnonzero(sel)
        i = i[np.argsort(xyz[i, 2], kind="stable")]
        # linewidths=0: an edge would blur every marker into its neighbours' colours
        ax.scatter(xyz[i, 0], xyz[i, 1], s=size, c=palette[sem[i]], marker="s",
                   linewidths=0, rasterized=True, zorder=2)

    gt = boxes is None
    b = np.asarray(frame.gt_boxes if gt else boxes, dtype=np.float64).reshape(-1, 7)
    if len(b):
        corners = bev_corners(b)                                  # (N, 4, 2)
        front = 0.5 * (corners[:, 0] + corners[:, 3])             # front-edge midpoints
        ring = np.concatenate([corners, corners[:, :1], np.full((len(b), 1, 2), np.nan)],
                              axis=1)                             # closed, NaN-separated
        tick = np.stack([b[:, :2], front, np.full((len(b), 2), np.nan)], axis=1)
        # under the points: an object's side faces project onto its box's edges
        ax.plot(*np.concatenate([ring, tick], axis=1).reshape(-1, 2).T, color=box_color,
                lw=0.7, zorder=1)
    ax.plot([0], [0], marker="^", ms=6, color="black", zorder=3)  # the sensor
    ax.set_xlim(-extent, extent)
    ax.set_ylim(-y_extent, y_extent)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, forward)")
    ax.set_ylabel("y (m, left)")
    ax.grid(True, lw=0.3, alpha=0.4)

    present, counts = np.unique(sem, return_counts=True)
    handles = [Patch(color=palette[c], label=f"{C.CLASS_NAMES[c]} ({n:,})")
               for c, n in zip(present.tolist(), counts.tolist())]
    handles.append(Patch(facecolor="none", edgecolor=box_color,
                         label="GT boxes" if gt else "boxes"))
    ax.legend(handles=handles, loc="upper right", fontsize=7, framealpha=0.85,
              title="class (points)", title_fontsize=7)
    name = name or f"sequence {frame.sequence} frame {frame.index}"
    if gt:
        seen = int((np.asarray(frame.gt_num_points) > 0).sum())
        what = f"{len(b)} objects ({seen} with points)"
    else:
        what = f"{len(b)} boxes"
    ax.set_title(f"{name}: {len(frame.xyz):,} points, {what}", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi, format="png")
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Render a simulated frame as a BEV PNG.")
    ap.add_argument("--seed", type=int, default=7000,
                    help="sequence seed (split seed * 1000 + sequence; demo: 7000)")
    ap.add_argument("--frame", type=int, default=0, help="frame index in the sequence")
    ap.add_argument("--frames", type=int, default=100,
                    help="sequence length the drive is planned over (demo split: 100)")
    ap.add_argument("--scene", choices=list(SCENE_TYPES), default="street",
                    help="scene type (lidar_sim.scene.SCENE_TYPES; the datasets: street)")
    ap.add_argument("--out", type=Path, default=Path("sim_bev.png"))
    ap.add_argument("--extent", type=float, default=60.0, help="half length of the view in x (m)")
    ap.add_argument("--y-extent", type=float, default=None,
                    help="half width of the view in y (m, default --extent)")
    ap.add_argument("--size", type=int, default=1000, help="image width (px)")
    args = ap.parse_args(argv)
    if not 0 <= args.frame < args.frames:
        ap.error("--frame must be in [0, --frames)")
    from .frames import sequence_frames

    # the noise generator advances frame by frame: simulate up to the one asked for
    f = next(itertools.islice(sequence_frames(args.seed, args.frames, scene=args.scene),
                              args.frame, None))
    name = f"seed {args.seed} frame {args.frame}"
    out = render_bev(f, args.out, extent=args.extent, y_extent=args.y_extent,
                     size_px=args.size,
                     name=name if args.scene == "street" else f"{args.scene} {name}")
    print(f"wrote {out} ({out.stat().st_size / 1024:.0f} kB): {len(f.xyz)} points, "
          f"{len(f.gt_boxes)} objects")
    return 0


if __name__ == "__main__":
    sys.exit(main())
