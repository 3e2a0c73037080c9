"""LidarMetaSeg segments on the range image (paper section II-B; numpy / scipy only).

A segment is an 8-connected component of equal predicted class on the filled image, columns
periodic (the seam behind the car joins), rows not; a pixel is interior when all 8
neighbours exist and belong to its segment. The full set of definitions is in
:mod:`lidar_quality_core.lms.segment_metrics`.
"""
from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

__all__ = ["label_periodic", "interior_mask", "neighbour_class_counts"]


def label_periodic(classes, return_values: bool = False):
    """8-connected components of equal value of an int image (rows, cols), columns
    periodic, rows not. Pixels < 0 are background (label -1). Returns ``(labels int32,
    n)``, ids 0..n-1 ordered by each component's first pixel in raster order, and with
    ``return_values`` also the value of each component.

    Runs of equal value along each row are the nodes; two runs of adjacent rows are
    joined where they overlap (checked only where one of them starts) or touch
    diagonally (checked only at run ends); the runs at both ends of a row are joined
    across the seam. Components of that graph (scipy.sparse.csgraph), mapped back to
    pixels.
    """
    Y = np.asarray(classes)
    if Y.ndim != 2:
        raise ValueError(f"classes must be 2-D, got shape {Y.shape}")
    R, C = Y.shape
    if Y.size == 0:
        out = (np.full((R, C), -1, dtype=np.int32), 0)
        return out + (np.zeros(0, Y.dtype),) if return_values else out
    start = np.empty((R, C), dtype=bool)
    start[:, 0] = True
    np.not_equal(Y[:, 1:], Y[:, :-1], out=start[:, 1:])
    run = np.cumsum(start.reshape(-1), dtype=np.int32)
    run -= 1
    n_runs = int(run[-1]) + 1
    rows = np.arange(R)
    pa = [rows[Y[:, -1] == Y[:, 0]] * C + (C - 1)]                 # across the seam
    pb = [pa[0] - (C - 1)]
    if R > 1:
        top, bot = Y[:-1], Y[1:]
        f = np.flatnonzero((start[:-1] | start[1:]) & (top == bot))  # overlap (vertical)
        pa.append(f)
        pb.append(f + C)
        # down-right from the last pixel of a top run, down-left from its first pixel;
        # columns wrap around
        end = np.empty((R - 1, C), dtype=bool)
        end[:, :-1] = start[:-1, 1:]
        end[:, -1] = True
        for at, dc in ((end, 1), (start[:-1], -1)):
            f = np.flatnonzero(at & (top == np.roll(bot, -dc, axis=1)))
            r, c = np.divmod(f, C)
            pa.append(f)
            pb.append((r + 1) * C + (c + dc) % C)
    ea, eb = run[np.concatenate(pa)], run[np.concatenate(pb)]
    g = coo_matrix((np.ones(len(ea), dtype=np.int8), (ea, eb)), shape=(n_runs, n_runs))
    n, comp = connected_components(g, directed=False)   # labels in order of first run
    comp = comp.astype(np.int32)
    run_value = Y.reshape(-1)[np.flatnonzero(start)]
    value = np.empty(n, dtype=Y.dtype)
    value[comp] = run_value
    if run_value.min() < 0:
        # background runs are components too: drop them and compact the ids
        is_fg = value >= 0
        new_id = np.cumsum(is_fg, dtype=np.int32) - 1
        new_id[~is_fg] = -1
        comp = new_id[comp]
        value = value[is_fg]
        n = int(is_fg.sum())
    labels = comp[run].reshape(R, C)
    return (labels, int(n), value) if return_values else (labels, int(n))


def interior_mask(classes) -> np.ndarray:
    """(rows, cols) bool: all 8 neighbours exist and have the pixel's value (columns
    periodic; the top and bottom rows are never interior)."""
    Y = np.asarray(classes)
    R, C = Y.shape
    out = np.zeros((R, C), dtype=bool)
    if R < 3:
        return out
    right = Y == np.roll(Y, -1, axis=1)
    h3 = right & np.roll(right, 1, axis=1)          # equal to both horizontal neighbours
    out[1:-1] = (h3[1:-1] & h3[:-2] & h3[2:]
                 & (Y[1:-1] == Y[:-2]) & (Y[1:-1] == Y[2:]))
    return out


def neighbour_class_counts(segments, Y, px, n_seg, n):
    """(n_seg, n) counts of each segment's neighbourhood pixels per class, each pixel
    once: every pixel of ``px`` (flat indices; the non-interior pixels, the only ones
    with a neighbour in another segment) adds its class to every distinct other segment
    among its 8 neighbours (columns periodic, rows outside the image ignored)."""
    R, C = segments.shape
    W = C + 2
    pad = np.full((R + 2, W), -1, dtype=np.int32)
    pad[1:-1, 1:-1] = segments
    pad[1:-1, 0] = segments[:, -1]
    pad[1:-1, -1] = segments[:, 0]
    flat = pad.reshape(-1)
    r, c = np.divmod(px, C)
    base = (r + 1) * W + (c + 1)
    own = segments.reshape(-1)[px]
    cls = Y.reshape(-1)[px].astype(np.int64)
    dummy = n_seg * n                      # bin of the entries that do not count
    keys = np.empty((8, len(px)), dtype=np.int64)
    seen = []
    for j, o in enumerate((-W - 1, -W, -W + 1, -1, 1, W - 1, W, W + 1)):
        v = flat[base + o]
        keep = v != own
        keep &= v >= 0
        for u in seen:                     # a segment met twice around a pixel counts once
            keep &= v != u
        seen.append(v)
        np.multiply(v, n, out=keys[j])
        keys[j] += cls
        np.copyto(keys[j], dummy, where=~keep)
    return np.bincount(keys.reshape(-1), minlength=dummy + 1)[:dummy].reshape(n_seg, n)
