"""Oriented box fitting of point clusters, vectorized over clusters.

Points come grouped by cluster (CSR ``offsets``). The yaw of a cluster's BEV rectangle is
found by one of three criteria:

* ``closeness`` (the L-shape fitting of Zhang et al., 2017): maximise the sum over points
  of ``1 / max(d, d0)``, ``d`` the distance to the nearest rectangle edge; it locks on to
  the visible sides of a car even when only an L or an I of it is seen;
* ``area``: the minimum-area rectangle, good for full outlines, poor for partial views;
* ``variance``: each point is assigned to its nearer edge, and the variance of the
  distances of the two edge sets is minimised (Zhang et al.'s second criterion);
* ``pca``: the principal axis of the BEV scatter (cheap, unstable for round shapes);
* ``sight``: aligned with the line of sight to the cluster (the usual guess for sparse
  far clusters, whose visible outline says little).

Several fits per cluster are several candidate boxes per object: where the fits agree
the object is well seen, where they scatter its shape is ambiguous.

The rectangle criteria search a coarse grid of angles over [0, pi/2), then refine around
the best one; they use at most ``max_points`` evenly spread points per cluster, so the cost
is bounded however dense a near object is. Extents come from all points. Boxes follow the
``l >= w`` convention with yaw in [-pi/2, pi/2): the fitter cannot know the heading. The
box reaches from the ground under the cluster to its highest point.
"""
from __future__ import annotations

import numpy as np

__all__ = ["METHODS", "subsample", "search_yaw", "pca_yaw", "rect_from_yaw", "fit_boxes",
           "wrap_half_pi"]

METHODS = ("closeness", "area", "variance", "pca", "sight")
_D0 = 0.02          # closeness floor (m): about the range noise
_MIN_SIZE = 0.1     # smallest box side (m): a one-line cluster still gets a valid box


def wrap_half_pi(a):
    """Angle(s) wrapped to [-pi/2, pi/2)."""
    return (np.asarray(a) + np.pi / 2) % np.pi - np.pi / 2


def subsample(offsets: np.ndarray, max_points: int):
    """Evenly spread ``<= max_points`` entries per group: ``(entry index, new offsets)``."""
    sizes = np.diff(offsets)
    k = np.minimum(sizes, max_points)
    new = np.zeros(len(k) + 1, np.int64)
    np.cumsum(k, out=new[1:])
    g = np.repeat(np.arange(len(k)), k)
    j = np.arange(new[-1]) - new[:-1][g]
    return offsets[:-1][g] + (j * sizes[g]) // np.maximum(k[g], 1), new


def _centred(xy: np.ndarray, offsets: np.ndarray):
    """Coordinates x, y (contiguous) minus their cluster mean (precision far from the
    sensor), and the means (C, 2)."""
    sizes = np.diff(offsets)
    st = offsets[:-1]
    x = np.ascontiguousarray(xy[:, 0], dtype=np.float64)
    y = np.ascontiguousarray(xy[:, 1], dtype=np.float64)
    mx = np.add.reduceat(x, st) / sizes
    my = np.add.reduceat(y, st) / sizes
    return x - np.repeat(mx, sizes), y - np.repeat(my, sizes), np.column_stack([mx, my])


def _criterion(x: np.ndarray, y: np.ndarray, offsets: np.ndarray, theta: np.ndarray,
               criterion: str):
    """(C, A) criterion value (higher is better) of angles ``theta``: (A,) shared by all
    clusters or (C, A) per cluster. Arrays are laid out (A, M): reductions run along
    contiguous rows."""
    sizes = np.diff(offsets)
    c, s = np.cos(theta), np.sin(theta)
    if theta.ndim == 2:                             # trig per cluster, then spread
        c, s = np.repeat(c.T, sizes, axis=1), np.repeat(s.T, sizes, axis=1)
    else:
        c, s = c[:, None], s[:, None]
    c1 = x * c + y * s                              # (A, M)
    c2 = y * c - x * s
    st = offsets[:-1]
    lo1, hi1 = np.minimum.reduceat(c1, st, axis=1), np.maximum.reduceat(c1, st, axis=1)
    lo2, hi2 = np.minimum.reduceat(c2, st, axis=1), np.maximum.reduceat(c2, st, axis=1)
    if criterion == "area":
        return (-(hi1 - lo1) * (hi2 - lo2)).T
    d1 = np.minimum(np.repeat(hi1, sizes, axis=1) - c1, c1 - np.repeat(lo1, sizes, axis=1))
    d2 = np.minimum(np.repeat(hi2, sizes, axis=1) - c2, c2 - np.repeat(lo2, sizes, axis=1))
    if criterion == "closeness":
        return np.add.reduceat(1.0 / np.maximum(np.minimum(d1, d2), _D0), st, axis=1).T
    # variance: each point belongs to its nearer edge; minimise the summed variances of
    # the distances of the two edge sets
    on1 = d1 <= d2
    out = np.zeros((c1.shape[0], len(st)))
    for on, d in ((on1, d1), (~on1, d2)):
        dm = np.where(on, d, 0.0)
        n = np.maximum(np.add.reduceat(on.astype(np.float64), st, axis=1), 1.0)
        m1 = np.add.reduceat(dm, st, axis=1) / n
        out -= np.add.reduceat(dm * dm, st, axis=1) / n - m1 * m1
    return out.T


def search_yaw(xy: np.ndarray, offsets: np.ndarray, criterion: str = "closeness", *,
               n_angles: int = 12, n_refine: int = 5, max_points: int = 32) -> np.ndarray:
    """(C,) yaw in [0, pi/2) of the best rectangle under ``criterion``."""
    if len(offsets) <= 1:
        return np.zeros(0)
    sel, so = subsample(offsets, max_points)
    x, y, _ = _centred(np.asarray(xy)[sel], so)
    n = len(so) - 1
    step = 0.5 * np.pi / n_angles
    grid = np.arange(n_angles) * step
    best = grid[np.argmax(_criterion(x, y, so, grid, criterion), axis=1)]
    if n_refine > 1:
        fine = best[:, None] + np.linspace(-0.5, 0.5, n_refine)[None, :] * step
        best = fine[np.arange(n), np.argmax(_criterion(x, y, so, fine, criterion), axis=1)]
    return np.mod(best, 0.5 * np.pi)


def pca_yaw(xy: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(C,) direction of the principal BEV axis."""
    if len(offsets) <= 1:
        return np.zeros(0)
    x, y, _ = _centred(xy, offsets)
    st = offsets[:-1]
    sxx = np.add.reduceat(x * x, st)
    syy = np.add.reduceat(y * y, st)
    sxy = np.add.reduceat(x * y, st)
    return 0.5 * np.arctan2(2.0 * sxy, sxx - syy)


def rect_from_yaw(xy: np.ndarray, offsets: np.ndarray, yaw: np.ndarray, centred=None):
    """BEV rectangles of the clusters at ``yaw``: ``(cx, cy, l, w, yaw, edge_dist)``.

    ``l >= w`` (yaw turned by pi/2 where needed), yaw in [-pi/2, pi/2); ``edge_dist`` is
    the mean distance of the points to the nearest rectangle edge (fit quality).
    ``centred``: ``_centred(xy, offsets)`` if already computed.
    """
    x, y, mean = centred if centred is not None else _centred(xy, offsets)
    sizes = np.diff(offsets)
    c, s = np.cos(yaw), np.sin(yaw)
    cg, sg = np.repeat(c, sizes), np.repeat(s, sizes)
    c1 = x * cg + y * sg
    c2 = y * cg - x * sg
    st = offsets[:-1]
    lo1, hi1 = np.minimum.reduceat(c1, st), np.maximum.reduceat(c1, st)
    lo2, hi2 = np.minimum.reduceat(c2, st), np.maximum.reduceat(c2, st)
    d = np.minimum(np.minimum(np.repeat(hi1, sizes) - c1, c1 - np.repeat(lo1, sizes)),
                   np.minimum(np.repeat(hi2, sizes) - c2, c2 - np.repeat(lo2, sizes)))
    edge = np.add.reduceat(d, st) / sizes
    m1, m2 = 0.5 * (lo1 + hi1), 0.5 * (lo2 + hi2)
    cx = mean[:, 0] + m1 * c - m2 * s
    cy = mean[:, 1] + m1 * s + m2 * c
    a, b = np.maximum(hi1 - lo1, _MIN_SIZE), np.maximum(hi2 - lo2, _MIN_SIZE)
    swap = b > a
    l, w = np.where(swap, b, a), np.where(swap, a, b)
    yaw = wrap_half_pi(np.where(swap, yaw + 0.5 * np.pi, yaw))
    return cx, cy, l, w, yaw, edge


def fit_boxes(xyz: np.ndarray, ground_z: np.ndarray, offsets: np.ndarray,
              methods=METHODS, *, n_angles: int = 12, max_points: int = 32):
    """Boxes of every cluster under every method.

    ``xyz`` (M, 3) and ``ground_z`` (M,) (ground height under each point) grouped by
    cluster. Returns ``(boxes (C * H, 7), cluster (C * H,), method (C * H,),
    edge_dist (C * H,))``, cluster-major (the H = len(methods) boxes of a cluster adjacent).
    """
    n = len(offsets) - 1
    H = len(methods)
    if n <= 0:
        return np.zeros((0, 7)), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    xyz = np.asarray(xyz, np.float64)
    st = offsets[:-1]
    sizes = np.diff(offsets)
    bottom = np.add.reduceat(np.asarray(ground_z, np.float64), st) / sizes
    top = np.maximum.reduceat(np.ascontiguousarray(xyz[:, 2]), st)
    h = np.maximum(top - bottom, _MIN_SIZE)
    xy = xyz[:, :2]
    centred = _centred(xy, offsets)
    boxes = np.empty((n, H, 7))
    edge = np.empty((n, H))
    for k, m in enumerate(methods):
        if m == "pca":
            yaw = pca_yaw(xy, offsets)
        elif m == "sight":
            yaw = np.arctan2(centred[2][:, 1], centred[2][:, 0])
        elif m in ("closeness", "area", "variance"):
            yaw = search_yaw(xy, offsets, m, n_angles=n_angles, max_points=max_points)
        else:
            raise ValueError(f"unknown box fit method {m!r} (known: {METHODS})")
        cx, cy, l, w, yw, e = rect_from_yaw(xy, offsets, yaw, centred)
        boxes[:, k] = np.stack([cx, cy, bottom + 0.5 * h, l, w, h, yw], axis=1)
        edge[:, k] = e
    method = np.tile(np.array([METHODS.index(m) for m in methods], np.int64), n)
    return (boxes.reshape(-1, 7), np.repeat(np.arange(n), H), method, edge.reshape(-1))
