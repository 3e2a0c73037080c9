"""Nearest-neighbour fill of a sparse range image (LidarMetaSeg section II-A).

The paper fills every empty pixel with "a value of one of its nearest neighbours that
received a value from the projection" and keeps the delta mask of projected pixels. Here
the fill is expressed once, as an index: :func:`nearest_source` gives for every pixel the
flat index of its nearest projected pixel, so any image (class, probabilities, x, y, z,
ground truth) is filled consistently by one gather.

Conventions (those of :mod:`lidar_quality_core.lms.projection`):

* distance: Euclidean in pixel units (one row = one column), the column axis periodic
  (columns 0 and ``cols - 1`` are neighbours: the seam behind the car is not an edge),
  rows not periodic;
* ties, on the exact squared distance: the smaller row offset wins (the same ring first:
  lidar rings are farther apart than columns), then the left column (``c - dc``) over
  the right one, then the upper row over the lower one. A pixel farther than
  ``max_offset`` columns from its nearest projected pixel (only in nearly empty images)
  is resolved exactly by scipy's Euclidean distance transform on a periodically tiled
  image instead, whose ties are scipy's.

Cost: one vertical scan of the image, then a loop over column offsets that touches only
the still unresolved empty pixels (the loop ends at the largest nearest distance).
"""
from __future__ import annotations

import numpy as np

__all__ = ["nearest_source", "fill_image"]

_FAR = 1 << 20  # a vertical distance no image reaches (its square still fits in int64)


def _vertical_nearest(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel (int32): row of the nearest True pixel in its own column (upper on ties)
    and the vertical distance to it (``_FAR`` for a column without any)."""
    R, C = mask.shape
    rows = np.arange(R, dtype=np.int32)[:, None]
    # running max / min over rows, one row at a time (ufunc.accumulate over axis 0 is
    # several times slower on these shapes)
    up = np.where(mask, rows, np.int32(-_FAR))
    for r in range(1, R):
        np.maximum(up[r], up[r - 1], out=up[r])
    dn = np.where(mask, rows, np.int32(2 * _FAR))
    for r in range(R - 2, -1, -1):
        np.minimum(dn[r], dn[r + 1], out=dn[r])
    d_up = rows - up
    d_dn = dn - rows
    take_up = d_up <= d_dn
    g = np.minimum(np.where(take_up, d_up, d_dn), _FAR)
    return np.where(take_up, up, dn), g


def _edt_periodic(mask: np.ndarray) -> np.ndarray:
    """Flat index of the nearest True pixel per pixel by scipy's exact EDT on the image
    tiled three times along the columns (exact for a periodic axis: the nearest copy of
    any pixel is within half a width)."""
    from scipy.ndimage import distance_transform_edt

    R, C = mask.shape
    tiled = np.concatenate([mask, mask, mask], axis=1)
    ir, ic = distance_transform_edt(~tiled, return_distances=False, return_indices=True)
    return ir[:, C:2 * C].astype(np.int64) * C + ic[:, C:2 * C] % C


def nearest_source(mask, max_offset: int = 64) -> np.ndarray:
    """(rows, cols) int64: flat index (``row * cols + col``) of the nearest True pixel of
    ``mask`` for every pixel (a True pixel is its own source); all -1 if ``mask`` has no
    True pixel. See the module doc for distance and ties."""
    mask = np.asarray(mask, dtype=bool)
    if mask.ndim != 2:
        raise ValueError(f"mask must be 2-D, got shape {mask.shape}")
    R, C = mask.shape
    if not mask.any():
        return np.full((R, C), -1, dtype=np.int64)
    src = np.arange(R * C, dtype=np.int64)
    empty = np.flatnonzero(~mask.reshape(-1))
    if not len(empty):
        return src.reshape(R, C)
    src_row, g = _vertical_nearest(mask)
    g_flat = g.reshape(-1)
    srow_flat = src_row.reshape(-1)
    er, ec = np.divmod(empty, C)
    gv = g_flat[empty].astype(np.int64)
    best = gv * gv                        # squared distance of the same-column candidate
    best_src = srow_flat[empty].astype(np.int64) * C + ec
    active = np.arange(len(empty))
    dc = 1
    last = min(C // 2, max_offset)
    while len(active) and dc <= last:
        d2 = dc * dc
        active = active[best[active] >= d2]  # dc columns away is >= dc^2 away; ties count
        if not len(active):
            break
        r, c = er[active], ec[active]
        # a tie goes to the larger column offset (= the smaller row offset); right first,
        # so that left wins a tie between the two
        for cc in ((c + dc) % C, (c - dc) % C):
            pix = r * C + cc
            gg = g_flat[pix].astype(np.int64)
            cand = d2 + gg * gg
            better = cand <= best[active]
            if better.any():
                a = active[better]
                best[a] = cand[better]
                best_src[a] = srow_flat[pix[better]].astype(np.int64) * C + cc[better]
        dc += 1
    if dc > max_offset and dc <= C // 2 and len(active):
        left = active[best[active] >= dc * dc]
        if len(left):
            best_src[left] = _edt_periodic(mask).reshape(-1)[empty[left]]
    src[empty] = best_src
    return src.reshape(R, C)


def fill_image(image, mask, source=None, max_offset: int = 64) -> np.ndarray:
    """``image`` (rows, cols, ...) with every pixel outside ``mask`` replaced by the value
    of its nearest pixel inside (see :func:`nearest_source`; pass ``source`` to reuse it).
    The image is returned unchanged (a copy) when the mask has no True pixel."""
    image = np.asarray(image)
    if source is None:
        source = nearest_source(mask, max_offset)
    flat = image.reshape((-1,) + image.shape[2:])
    src = source.reshape(-1)
    if (src < 0).any():
        return image.copy()
    return flat[src].reshape(image.shape)
