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

Cost: one compiled kernel (numba), two sweeps over the rows: down, then up, finishing
each row with a search per empty pixel over column offsets that stops as soon as no
farther column can tie (a few columns in a dense scan).
"""
from __future__ import annotations

import numpy as np
from numba import njit, types

from lidar_quality_core.kernel_types import array_in, array_out

__all__ = ["nearest_source", "fill_image"]

_FAR = 1 << 20  # a vertical distance no image reaches (its square still fits in int64)
_MASK = array_in(types.boolean, 2)
_ROW = array_out(types.int64)


@njit(types.void(types.int64, array_in(types.boolean), _ROW, _ROW, _ROW, _ROW), cache=True,
      nogil=True)
def _finish_row(r, filled, out_row, below, src_row, dist):
    """Row ``r`` of the sweep up (see :func:`_nearest`). Its own function: inlined into
    the sweep's loop this loop is not vectorized (3x slower)."""
    C = len(filled)
    for c in range(C):
        b = r if filled[c] else below[c]
        below[c] = b
        up = out_row[c]
        d_up = r - up
        d_dn = b - r
        take_up = d_up <= d_dn
        src_row[c] = up if take_up else b
        dist[c] = min(d_up if take_up else d_dn, _FAR)
        out_row[c] = r * C + c


@njit(types.int64(_MASK, types.int64, array_out(types.int64, 2)), cache=True, nogil=True)
def _nearest(mask, max_offset, out):
    """:func:`nearest_source` into ``out``, except that empty pixels not resolved within
    ``max_offset`` columns get -1 (left to the EDT); returns how many.

    A sweep down the rows leaves in ``out`` the nearest True row at or above each pixel.
    A sweep up then finishes one row at a time in row buffers: the nearest True row in the
    pixel's column (upper on ties) and its distance, then per empty pixel the search over
    column offsets ``dc = 1, 2, ...`` right and left while ``dc^2`` can still tie the best
    squared distance, up to ``min(cols // 2, max_offset)``.
    """
    R, C = mask.shape
    for c in range(C):
        out[0, c] = 0 if mask[0, c] else -_FAR
    for r in range(1, R):
        for c in range(C):
            out[r, c] = r if mask[r, c] else out[r - 1, c]
    below = np.full(C, 2 * _FAR, dtype=np.int64)  # nearest True row at or below
    src_row = np.empty(C, dtype=np.int64)
    dist = np.empty(C, dtype=np.int64)            # _FAR: none in the column
    empty = np.empty(C, dtype=np.int64)
    last = min(C // 2, max_offset)
    n_far = 0
    for r in range(R - 1, -1, -1):
        _finish_row(r, mask[r], out[r], below, src_row, dist)
        # the row's empty pixels, without a branch on the mask (it mispredicts at random)
        n_empty = 0
        for c in range(C):
            empty[n_empty] = c
            n_empty += not mask[r, c]
        for k in range(n_empty):
            c = empty[k]
            best = dist[c] * dist[c]
            src = src_row[c] * C + c
            dc = 1
            while dc <= last:
                d2 = dc * dc
                if best < d2:
                    break
                # a tie goes to the larger column offset (= the smaller row offset); right
                # first, so that left wins a tie between the two
                cc = c + dc if c + dc < C else c + dc - C
                if d2 + dist[cc] * dist[cc] <= best:
                    best = d2 + dist[cc] * dist[cc]
                    src = src_row[cc] * C + cc
                cc = c - dc if c >= dc else c - dc + C
                if d2 + dist[cc] * dist[cc] <= best:
                    best = d2 + dist[cc] * dist[cc]
                    src = src_row[cc] * C + cc
                dc += 1
            if dc > max_offset and dc <= C // 2 and best >= dc * dc:
                out[r, c] = -1
                n_far += 1
            else:
                out[r, c] = src
    return n_far


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
    mask = np.ascontiguousarray(mask)
    out = np.empty((R, C), dtype=np.int64)
    # any offset >= cols // 2 searches every column, any offset <= 0 none
    if _nearest(mask, max(0, min(int(max_offset), C)), out):
        far = out == -1
        out[far] = _edt_periodic(mask)[far]
    return out


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
