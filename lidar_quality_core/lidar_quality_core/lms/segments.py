"""LidarMetaSeg segments on the range image (paper section II-B; numpy / numba).

A segment is an 8-connected component of equal predicted class on the filled image, columns
periodic (the seam behind the car joins), rows not; a pixel is interior when all 8
neighbours exist and belong to its segment. The full set of definitions is in
:mod:`lidar_quality_core.lms.segment_metrics`.

The work of each function is done by compiled loops over the pixels (numba, for C-contiguous
int32 or int64 images; other integer or bool images are converted to int64 first, other
dtypes are refused). They are compiled once and cached next to this module (numba's
``cache=True``; where that directory is not writable, numba's user cache); a process loads
them at import.
"""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["label_periodic", "interior_mask", "neighbour_class_counts"]


@njit("int32(int32[::1], int32)", cache=True, nogil=True)
def _find(parent, x):
    while parent[x] != x:
        parent[x] = parent[parent[x]]           # path halving
        x = parent[x]
    return x


@njit("int32(int32[::1], int32, int32)", cache=True, nogil=True)
def _union(parent, a, b):
    # the smaller root wins: a root is then the first label of its component, hence the
    # component's first pixel in raster order (labels are made in raster order)
    a = _find(parent, a)
    b = _find(parent, b)
    if a < b:
        parent[b] = a
        return a
    parent[a] = b
    return b


@njit(["int64(int32[:, ::1], boolean, int32[:, ::1], int32[::1])",
       "int64(int64[:, ::1], boolean, int32[:, ::1], int32[::1])"], cache=True, nogil=True)
def _label(Y, bg, lab, first):
    # Writes the ids into lab (-1: background, pixels < 0 when bg) and the flat index of
    # each component's first pixel into first[:n]; returns n.
    R, C = Y.shape
    parent = np.empty(R * C, np.int32)
    n_lab = np.int32(0)
    for r in range(R):
        for c in range(C):
            v = Y[r, c]
            if bg and v < 0:
                lab[r, c] = -1
                continue
            cl = c - 1 if c > 0 else C - 1
            cr = c + 1 if c < C - 1 else 0
            lb = np.int32(-1)
            # Earlier neighbours only: left, then the three above (wrapping). Some need no
            # check: an equal left pixel was already joined with the equal pixels up-left
            # and up of this one (its own up and up-right), an equal pixel above with its
            # equal row neighbours (both diagonals).
            if c > 0 and Y[r, c - 1] == v:
                lb = lab[r, c - 1]
                if r > 0 and Y[r - 1, c] != v and Y[r - 1, cr] == v:
                    lb = _union(parent, lb, lab[r - 1, cr])
            elif r > 0:
                if Y[r - 1, c] == v:
                    lb = lab[r - 1, c]
                else:
                    if Y[r - 1, cl] == v:
                        lb = lab[r - 1, cl]
                    if Y[r - 1, cr] == v:
                        lb = (lab[r - 1, cr] if lb < 0
                              else _union(parent, lb, lab[r - 1, cr]))
            if lb < 0:
                parent[n_lab] = n_lab
                first[n_lab] = r * C + c
                lb = n_lab
                n_lab += 1
            lab[r, c] = lb
        # the seam within the row (the diagonals across it wrap above)
        if Y[r, C - 1] == Y[r, 0] and lab[r, 0] >= 0:
            _union(parent, lab[r, C - 1], lab[r, 0])
    # roots in label order get the ids 0..n-1; a parent is always a smaller label, so its
    # id is known when a label is reached
    n = 0
    for i in range(n_lab):
        p = parent[i]
        if p == i:
            parent[i] = n
            first[n] = first[i]
            n += 1
        else:
            parent[i] = parent[p]
    for r in range(R):
        for c in range(C):
            if lab[r, c] >= 0:
                lab[r, c] = parent[lab[r, c]]
    return n


def _kernel_image(Y):
    """``(image, signed)``: Y as a C-contiguous int32 / int64 image for the kernels;
    ``signed`` False where negative values cannot occur."""
    if Y.dtype == np.int32 or Y.dtype == np.int64:
        return np.ascontiguousarray(Y), True
    if Y.dtype == np.uint64:
        # equality survives the reinterpretation; the sign test must not run
        return np.ascontiguousarray(Y).view(np.int64), False
    if Y.dtype == np.bool_ or np.issubdtype(Y.dtype, np.integer):
        return np.ascontiguousarray(Y, dtype=np.int64), Y.dtype.kind == "i"
    raise TypeError(f"classes must be an integer image, got dtype {Y.dtype}")


def label_periodic(classes, return_values: bool = False):
    """8-connected components of equal value of an int image (rows, cols), columns
    periodic, rows not. Pixels < 0 are background (label -1). Returns ``(labels int32,
    n)``, ids 0..n-1 ordered by each component's first pixel in raster order, and with
    ``return_values`` also the value of each component (the image's dtype).

    One raster pass of union-find over the pixels: a pixel joins its equal earlier
    neighbours (left, and the three above, wrapping), skipping those already joined
    through another; the seam is joined at the end of each row. Roots are then numbered
    in raster order and the labels rewritten.
    """
    Y = np.asarray(classes)
    if Y.ndim != 2:
        raise ValueError(f"classes must be 2-D, got shape {Y.shape}")
    R, C = Y.shape
    if Y.size == 0:
        out = (np.full((R, C), -1, dtype=np.int32), 0)
        return out + (np.zeros(0, Y.dtype),) if return_values else out
    Yk, signed = _kernel_image(Y)
    labels = np.empty((R, C), dtype=np.int32)
    first = np.empty(R * C, dtype=np.int32)
    n = int(_label(Yk, signed, labels, first))
    if return_values:
        return labels, n, Y.reshape(-1)[first[:n]]
    return labels, n


@njit(["void(int32[:, ::1], boolean[:, ::1])", "void(int64[:, ::1], boolean[:, ::1])"],
      cache=True, nogil=True)
def _interior(Y, out):
    R, C = Y.shape
    out[0, :] = False
    out[R - 1, :] = False
    for r in range(1, R - 1):
        a, b, d = Y[r - 1], Y[r], Y[r + 1]
        # the columns away from the seam without branches, so that the loop vectorises
        for c in range(1, C - 1):
            v = b[c]
            out[r, c] = ((a[c - 1] == v) & (a[c] == v) & (a[c + 1] == v) & (b[c - 1] == v)
                         & (b[c + 1] == v) & (d[c - 1] == v) & (d[c] == v) & (d[c + 1] == v))
        for c in (0, C - 1):
            cl = c - 1 if c > 0 else C - 1
            cr = c + 1 if c < C - 1 else 0
            v = b[c]
            out[r, c] = ((a[cl] == v) & (a[c] == v) & (a[cr] == v) & (b[cl] == v)
                         & (b[cr] == v) & (d[cl] == v) & (d[c] == v) & (d[cr] == v))


def interior_mask(classes) -> np.ndarray:
    """(rows, cols) bool: all 8 neighbours exist and have the pixel's value (columns
    periodic; the top and bottom rows are never interior)."""
    Y = np.asarray(classes)
    R, C = Y.shape
    if R < 3 or C == 0:
        return np.zeros((R, C), dtype=bool)
    out = np.empty((R, C), dtype=bool)
    _interior(_kernel_image(Y)[0], out)
    return out


@njit(["int64(int32[:, ::1], int32[:, ::1], int64[::1], int64, int64[::1])",
       "int64(int32[:, ::1], int64[:, ::1], int64[::1], int64, int64[::1])"],
      cache=True, nogil=True)
def _neighbour_counts(seg, Y, px, n, counts):
    # counts: flat (n_seg * n); returns 0, 1 for a pixel index out of range, 2 for a
    # negative bin (segment * n + class < 0, which np.bincount refused)
    R, C = seg.shape
    size = counts.shape[0]
    nb = np.empty(8, np.int32)
    r = 0
    row0 = 0
    for p in px:
        # the row is carried over while px stays in it (a division costs more than a
        # pixel's other work)
        if p < row0 or p >= row0 + C:
            if p < 0 or p >= R * C:
                return 1
            r = p // C
            row0 = r * C
        c = p - row0
        own = seg[r, c]
        cls = np.int64(Y[r, c])
        cl = c - 1 if c > 0 else C - 1
        cr = c + 1 if c < C - 1 else 0
        # rows outside the image read as background: they never count
        if r > 0:
            nb[0], nb[1], nb[2] = seg[r - 1, cl], seg[r - 1, c], seg[r - 1, cr]
        else:
            nb[0], nb[1], nb[2] = -1, -1, -1
        nb[3], nb[4] = seg[r, cl], seg[r, cr]
        if r < R - 1:
            nb[5], nb[6], nb[7] = seg[r + 1, cl], seg[r + 1, c], seg[r + 1, cr]
        else:
            nb[5], nb[6], nb[7] = -1, -1, -1
        for j in range(8):
            v = nb[j]
            if v < 0 or v == own:
                continue
            # a segment met twice around a pixel counts once (at its first place)
            dup = False
            for i in range(j):
                if nb[i] == v:
                    dup = True
            if dup:
                continue
            k = v * n + cls
            if k < 0:
                return 2
            # a class outside 0..n-1 lands in a neighbouring bin or beyond the last one,
            # as in the flat bincount this replaces
            if k < size:
                counts[k] += 1
    return 0


def neighbour_class_counts(segments, Y, px, n_seg, n):
    """(n_seg, n) counts of each segment's neighbourhood pixels per class, each pixel
    once: every pixel of ``px`` (flat indices; the non-interior pixels, the only ones
    with a neighbour in another segment) adds its class to every distinct other segment
    among its 8 neighbours (columns periodic, rows outside the image ignored)."""
    seg = np.ascontiguousarray(segments, dtype=np.int32)
    Yk = _kernel_image(np.asarray(Y))[0]
    if seg.ndim != 2 or Yk.shape != seg.shape:
        raise ValueError(f"segments {seg.shape} and classes {Yk.shape} must be the same "
                         "2-D shape")
    n_seg, n = int(n_seg), int(n)
    counts = np.zeros(n_seg * n, dtype=np.int64)
    px = np.ascontiguousarray(px, dtype=np.int64).reshape(-1)
    err = _neighbour_counts(seg, Yk, px, n, counts)
    if err == 1:
        raise IndexError(f"pixel index out of range for an image of shape {seg.shape}")
    if err == 2:
        raise ValueError("a negative class at a pixel next to segment 0 has no bin")
    return counts.reshape(n_seg, n)
