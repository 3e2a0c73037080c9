"""Compiled passes (numba) of the LMS segment metrics
(:mod:`lidar_quality_core.lms.segment_metrics`): one pass over the points or pixels where
numpy needs several passes, temporaries or a sparse product per piece.

Each kernel reproduces the arithmetic of the numpy / scipy code it replaced operation for
operation (float32 where that code was float32, the same summation order), so that
results are bit-identical; the tests check them against numpy references:

* :func:`dispersion_block` (after :func:`transpose_block` for row-major probabilities;
  :func:`dispersion_rows` / :func:`dispersion_columns` run them over a whole cloud):
  argmax, top two probabilities and the entropy, summed in float32 in class order, with
  the logarithms taken in the same pass by :func:`~lidar_quality_core.float32_log.log_f32`
  (numpy's float32 ``log``, bit for bit, vectorized with the rest), then ``D`` and ``V``,
  and each point's sum and minimum of its probabilities (the node's probability checks).
* :func:`read_sources`: the point and the class each pixel of the filled image reads.
* :func:`region_sums`: the float64 sums of the measures, their squares and the
  probabilities per region (segment boundary / interior), and the pixel counts.
* :func:`segment_features`: the statistics of the kept segments from those sums.
* :func:`point_segments`: every projected point's segment.

Compiled once and cached next to this module (numba's ``cache=True``); a process loads
them at import.
"""
from __future__ import annotations

import numpy as np
from numba import njit, types

from lidar_quality_core.float32_log import log_f32
from lidar_quality_core.kernel_types import array_in as _in, array_out as _out

__all__ = ["transpose_block", "dispersion_block", "dispersion_rows", "dispersion_columns",
           "read_sources", "region_sums",
           "segment_features", "point_segments", "N_MEASURES", "N_STATS"]

#: measures summed by :func:`region_sums`: E, D, V, x, y, z, intensity, range
N_MEASURES = 8
#: statistics per measure: mean, mean_in, mean_bd, mean_rel, mean_rel_in, then var
N_STATS = 10

_F32, _F64, _I32, _I64, _BOOL = (types.float32, types.float64, types.int32, types.int64,
                                 types.boolean)


# probabilities read in place: any layout, aligned or not (a message's packed records)
_PROBS_VIEW = _in(_F32, 2, "A", aligned=False)


@njit(types.void(_PROBS_VIEW, _I64, _out(_F32, 2)), cache=True, nogil=True)
def transpose_block(probs, b0, out):
    """``out`` (n, m) = rows ``b0 .. b0 + m - 1`` of ``probs`` (N, n), transposed.

    Sixteen rows at a time, class by class: each class's 16 values go to one run of
    ``out`` (a 120k x 14 frame in 72-byte records: 1.03 -> 0.78 ms; one row at a time
    scattered every value to another row of ``out``)."""
    n, m = out.shape
    j = 0
    while j + 16 <= m:
        for c in range(n):
            for k in range(16):
                out[c, j + k] = probs[b0 + j + k, c]
        j += 16
    for jj in range(j, m):
        row = probs[b0 + jj]
        for c in range(n):
            out[c, jj] = row[c]


@njit(types.Tuple((_F32, _BOOL))(_in(_F32, 2), _I64, _I64, _I64, _BOOL, _F32,
                                  _F32, _out(_I32), _out(_F32), _out(_F32), _out(_F32),
                                  _out(_F32), _out(_F32)),
      cache=True, nogil=True, error_model="numpy")
def dispersion_block(pcm, col0, m, b0, clamp, tiny, scale, cls, E, D, V, total, smallest):
    """Points ``b0 .. b0 + m - 1`` from their class-major probabilities
    ``pcm[:, col0:col0 + m]`` (n > 1 classes): writes ``cls`` (argmax),
    ``E`` = ``scale * sum_c p_c log p_c`` (summed in class order, ``log`` =
    :func:`~lidar_quality_core.float32_log.log_f32`, numpy's bits; with ``clamp``, a
    probability below ``tiny`` has the log of ``tiny``), ``V = 1 - p1``
    and ``D = V + p2``; a point with a NaN probability gets class 0 and a NaN ``p1``, as
    numpy's max and argmax-by-equality did; ``total`` and ``smallest``, each point's sum
    (in class order from +0.0) and minimum (NaN-propagating) of its probabilities: the
    bits of numpy's ``add`` / ``minimum`` reductions of the class-major array. Returns the
    smallest probability (valid when none is NaN) and whether some point has a NaN
    probability, found as a NaN entropy (with ``clamp`` no other term is NaN: each is
    finite or +inf).

    Class by class over the block, the running sums and top two of each point in small
    arrays: every loop is sequential and branch-free (vectorized); the top two's branches
    would mispredict on every other probability."""
    n = pcm.shape[0]
    log_tiny = log_f32(tiny)
    e = np.zeros(m, np.float32)
    tot = np.zeros(m, np.float32)
    p1 = np.full(m, -np.inf, np.float32)
    p2 = np.full(m, -np.inf, np.float32)
    lo = np.full(m, np.inf, np.float32)
    c1 = np.zeros(m, np.int32)
    for c in range(n):
        row = pcm[c, col0:col0 + m]
        ci = np.int32(c)
        for j in range(m):
            v = row[j]
            t = log_f32(v)
            t = log_tiny if clamp and v < tiny else t   # np.maximum(p, tiny); NaN stays
            e[j] += v * t
            tot[j] += v
            lo[j] = np.minimum(lo[j], v)
            a = p1[j]
            b = p2[j]
            gt = v > a                  # strict: the first class reaching the max wins
            p2[j] = a if gt else (v if v > b else b)
            p1[j] = v if gt else a
            k = c1[j]
            c1[j] = k + (ci - k) * np.int32(gt)
    cls_b, E_b, D_b, V_b = cls[b0:b0 + m], E[b0:b0 + m], D[b0:b0 + m], V[b0:b0 + m]
    one = np.float32(1.0)
    nan = np.float32(np.nan)
    any_nan = False
    for j in range(m):
        x = e[j]
        bad = x != x
        any_nan |= bad
        cls_b[j] = 0 if bad else c1[j]
        E_b[j] = x * scale
        vj = one - (nan if bad else p1[j])
        V_b[j] = vj
        D_b[j] = vj + p2[j]
    total[b0:b0 + m] = tot
    smallest[b0:b0 + m] = lo
    return lo.min(), any_nan


_BLOCKS_OUT = (_out(_I32), _out(_F32), _out(_F32), _out(_F32), _out(_F32), _out(_F32))


@njit(types.Tuple((_F32, _BOOL))(_PROBS_VIEW, _I64, _BOOL, _F32, _F32, _out(_F32),
                                 *_BLOCKS_OUT), cache=True, nogil=True)
def dispersion_rows(probs, step, clamp, tiny, scale, tbuf, cls, E, D, V, total, smallest):
    """:func:`dispersion_block` over all points of ``probs`` (N, n) whose classes lie
    together (row-major, or a message's records), ``step`` points at a time, each block
    transposed into ``tbuf`` (>= step * n) by :func:`transpose_block` first. The block
    loop is compiled too: from Python it cost two calls a block (26 on a 120k-point
    frame), each much dearer when the caches are cold, as in a node between frames.
    Returns the smallest probability and whether any is NaN (as :func:`dispersion_block`)."""
    N, n = probs.shape
    lo, nan = np.float32(np.inf), False
    for b0 in range(0, N, step):
        m = min(step, N - b0)
        src = tbuf[:m * n].reshape(n, m)
        transpose_block(probs, b0, src)
        b_lo, b_nan = dispersion_block(src, 0, m, b0, clamp, tiny, scale, cls, E, D, V,
                                       total, smallest)
        lo, nan = min(lo, b_lo), nan or b_nan
    return lo, nan


@njit(types.Tuple((_F32, _BOOL))(_in(_F32, 2), _I64, _BOOL, _F32, _F32, *_BLOCKS_OUT),
      cache=True, nogil=True)
def dispersion_columns(pcm, step, clamp, tiny, scale, cls, E, D, V, total, smallest):
    """:func:`dispersion_rows` for class-major probabilities ``pcm`` (n, N), read in
    place."""
    N = pcm.shape[1]
    lo, nan = np.float32(np.inf), False
    for b0 in range(0, N, step):
        m = min(step, N - b0)
        b_lo, b_nan = dispersion_block(pcm, b0, m, b0, clamp, tiny, scale, cls, E, D, V,
                                       total, smallest)
        lo, nan = min(lo, b_lo), nan or b_nan
    return lo, nan


@njit([types.void(_in(_I32), _in(_I32), _in(t), _out(_I32), _out(_I32)) for t in (_I32, _I64)],
      cache=True, nogil=True)
def read_sources(index, point_class, near, source, pred):
    """Per pixel: ``source`` = ``index[near]`` (the point it reads) and ``pred`` = that
    point's class."""
    for p in range(near.shape[0]):
        i = index[near[p]]
        source[p] = i
        pred[p] = point_class[i]


# measures in float32 (as the node's) or float64 (exact for anything else), any stride;
# probabilities writable row-major (its class loop vectorizes; typed writable so that it
# is the one such an array picks) or any layout (the node's class-major view); ``rows``:
# the same probabilities as one flat float32 run (a message's records, see region_sums)
_SUMS_SIGS = [types.void(_in(_I32), _in(_I32), _in(_I32), _in(_BOOL), _I64, _in(_F32),
                         _in(_F32), _in(_F32), *[_in(f, 1, "A")] * 5, p, _in(_F32), _I64,
                         _I64, _out(_F64, 2), _out(_F64, 2), _out(_I64), _out(_I64))
              for f in (_F32, _F64) for p in (_PROBS_VIEW, _out(_F32, 2))]


@njit(inline="always")
def _add(acc, r, w, g0, g1, g2, g3, g4, g5, g6, g7):
    # acc[r] += w * (g, g * g) per measure, as the sparse products of G and G**2 added
    acc[r, 0] += w * g0
    acc[r, 1] += w * g1
    acc[r, 2] += w * g2
    acc[r, 3] += w * g3
    acc[r, 4] += w * g4
    acc[r, 5] += w * g5
    acc[r, 6] += w * g6
    acc[r, 7] += w * g7
    acc[r, 8] += w * (g0 * g0)
    acc[r, 9] += w * (g1 * g1)
    acc[r, 10] += w * (g2 * g2)
    acc[r, 11] += w * (g3 * g3)
    acc[r, 12] += w * (g4 * g4)
    acc[r, 13] += w * (g5 * g5)
    acc[r, 14] += w * (g6 * g6)
    acc[r, 15] += w * (g7 * g7)


@njit(_SUMS_SIGS, cache=True, nogil=True)
def region_sums(index, source, seg, interior, n_seg, E, D, V, x, y, z, inten, rng, probs,
                rows, row_step, block, sums, psum, sp, cnt):
    """Per region ``r`` (``seg`` on the boundary, ``n_seg + seg`` in the interior; the
    caller's arrays have ``2 n_seg`` zeroed rows): ``sums[r]`` = the float64 sums over the
    region's pixels of the 8 measures (E, D, V, x, y, z, intensity, range, per point), then
    of their squares; ``psum[r]`` of the probabilities ``probs`` (N, n, any layout), or,
    when ``rows`` is not empty, of ``rows[i * row_step + c]`` (point i, class c; ``probs``
    then gives n only): a message's records read as one float32 run, whose class loop
    vectorizes where the strided view's does not (the e2e bench's 120k-point frame, 14
    classes in 72-byte records: 2.7-2.9 -> 2.2-2.4 ms, as fast as a contiguous copy);
    ``sp[r]`` its projected pixels, ``cnt[r]`` all its pixels. Images flat:
    ``index`` (the point each pixel keeps, -1: none), ``source`` (the point each pixel
    reads).

    Summed over points as the sparse products did: a point kept by a pixel counts with
    weight 1 + the filled pixels of its region that read it, in point order (the
    probabilities by blocks of ``block`` points, each block summed from 0 then added);
    then the other filled pixels, in pixel order, summed from 0 and added."""
    P = index.shape[0]
    N = E.shape[0]
    n = probs.shape[1]
    flat = rows.shape[0] > 0
    nb = 2 * n_seg
    rid_pt = np.full(N, nb, np.int32)            # nb: kept by no pixel (summed nowhere)
    for p in range(P):
        i = index[p]
        if i >= 0:
            r = seg[p] + (n_seg if interior[p] else 0)
            rid_pt[i] = r
            sp[r] += 1
    weight = np.ones(N)
    other = np.empty(P, np.int64)
    n_other = 0
    for p in range(P):
        if index[p] < 0:
            r = seg[p] + (n_seg if interior[p] else 0)
            cnt[r] += 1
            s = source[p]
            if rid_pt[s] == r:
                weight[s] += 1.0
            else:
                other[n_other] = p
                n_other += 1
    for r in range(nb):
        cnt[r] += sp[r]

    # point by point, its class values inner: the n sums of a region are independent
    # chains (class by class, consecutive points of one region would chain every add)
    loc = np.zeros((nb, n))
    mark = np.full(nb, -1, np.int64)
    touched = np.empty(nb, np.int64)
    for b0 in range(0, N, block):
        b1 = min(N, b0 + block)
        nt = 0
        for i in range(b0, b1):
            r = rid_pt[i]
            if r == nb:
                continue
            w = weight[i]
            _add(sums, r, w, np.float64(E[i]), np.float64(D[i]), np.float64(V[i]),
                 np.float64(x[i]), np.float64(y[i]), np.float64(z[i]),
                 np.float64(inten[i]), np.float64(rng[i]))
            if mark[r] != b0:
                mark[r] = b0
                touched[nt] = r
                nt += 1
            if flat:
                pr = rows[i * row_step:i * row_step + n]
                for c in range(n):
                    loc[r, c] += w * np.float64(pr[c])
            else:
                for c in range(n):
                    loc[r, c] += w * np.float64(probs[i, c])
        for t in range(nt):
            r = touched[t]
            for c in range(n):
                psum[r, c] += loc[r, c]
                loc[r, c] = 0.0

    fsum = np.zeros((nb, 2 * N_MEASURES))
    for k in range(n_other):
        p = other[k]
        r = seg[p] + (n_seg if interior[p] else 0)
        j = source[p]
        _add(fsum, r, 1.0, np.float64(E[j]), np.float64(D[j]), np.float64(V[j]),
             np.float64(x[j]), np.float64(y[j]), np.float64(z[j]),
             np.float64(inten[j]), np.float64(rng[j]))
        if flat:
            pr = rows[j * row_step:j * row_step + n]
            for c in range(n):
                loc[r, c] += np.float64(pr[c])
        else:
            for c in range(n):
                loc[r, c] += np.float64(probs[j, c])
    for r in range(nb):
        for m in range(2 * N_MEASURES):
            sums[r, m] += fsum[r, m]
        for c in range(n):
            psum[r, c] += loc[r, c]


@njit(types.void(_in(_F64, 2), _in(_F64, 2), _in(_I64), _in(_I64), _in(_I64), _out(_F64, 2)),
      cache=True, nogil=True)
def segment_features(sums, psum, cnt, sp, kid, features):
    """Rows of the kept segments ``kid`` in ``features`` (k, 86 + 2n) from the region sums
    of :func:`region_sums` (rows ``s`` boundary, ``n_seg + s`` interior): for each measure
    the 10 statistics, then S, S_in, S_bd, S_rel, S_rel_in, SP, (N_c: left to the
    caller), P_c; the arithmetic of the numpy expressions it replaces, in float64 (a mean
    or variance of an empty region is 0; a variance below 0 is 0, NaN stays NaN)."""
    n_seg = sums.shape[0] // 2
    n = psum.shape[1]
    size0 = N_MEASURES * N_STATS
    for q in range(kid.shape[0]):
        s = kid[q]
        b, i = s, n_seg + s
        S3 = (np.float64(cnt[b] + cnt[i]), np.float64(cnt[i]), np.float64(cnt[b]))
        S_rel = S3[0] / S3[2]
        S_rel_in = S3[1] / S3[2]
        f = features[q]
        for m in range(N_MEASURES):
            o = m * N_STATS
            for g in range(3):              # segment, interior, boundary
                if g == 0:
                    s1 = sums[b, m] + sums[i, m]
                    s2 = sums[b, N_MEASURES + m] + sums[i, N_MEASURES + m]
                elif g == 1:
                    s1, s2 = sums[i, m], sums[i, N_MEASURES + m]
                else:
                    s1, s2 = sums[b, m], sums[b, N_MEASURES + m]
                mean = 0.0
                var = 0.0
                if S3[g] > 0:
                    mean = s1 / S3[g]
                    var = np.maximum(s2 / S3[g] - mean * mean, 0.0)
                f[o + g] = mean
                f[o + 5 + g] = var
            f[o + 3] = f[o] * S_rel
            f[o + 4] = f[o + 1] * S_rel_in
            f[o + 8] = f[o + 5] * S_rel
            f[o + 9] = f[o + 6] * S_rel_in
        f[size0] = S3[0]
        f[size0 + 1] = S3[1]
        f[size0 + 2] = S3[2]
        f[size0 + 3] = S_rel
        f[size0 + 4] = S_rel_in
        f[size0 + 5] = np.float64(sp[b] + sp[i])
        o = size0 + 6 + n
        for c in range(n):
            f[o + c] = (psum[b, c] + psum[i, c]) / S3[0]


# neighbour order for points without a pixel of their class: 4-neighbours, then diagonals
_DR = np.array([0, 0, -1, 1, -1, -1, 1, 1], np.int64)
_DC = np.array([-1, 1, 0, 0, -1, 1, -1, 1], np.int64)


@njit(types.void(_in(_I32), _in(_BOOL), _in(_I32), _in(_I32), _in(_I32), _in(_I32), _in(_I32),
                 _in(_I32), _I64, _out(_I32), _out(_I64)), cache=True, nogil=True)
def point_segments(index, valid, pixel, row, col, seg, pred, point_class, cols,
                   point_segment, n_points):
    """``point_segment`` (N; the caller fills it with -1) as the module doc of
    :mod:`lidar_quality_core.lms.segment_metrics` defines it: a point kept by its pixel
    takes the pixel's segment; another projected point too if of the pixel's class
    ``pred``, else the segment of the first neighbour pixel of its class (left, right, up,
    down, then the diagonals; rows bounded, columns periodic), else none (-1). Adds these
    other points to ``n_points`` (which the caller starts at the kept points: SP)."""
    P = index.shape[0]
    R = P // cols
    for p in range(P):
        i = index[p]
        if i >= 0:
            point_segment[i] = seg[p]   # >= 0: every pixel is in a segment
    # kept points are now those with a segment: no look-up of index[pixel[j]], which for
    # points in scan order would jump a row of the image from one point to the next
    for j in range(valid.shape[0]):
        if not valid[j] or point_segment[j] >= 0:
            continue
        p = pixel[j]
        want = point_class[j]
        s = -1
        if pred[p] == want:
            s = seg[p]
        else:
            for k in range(8):
                rr = row[j] + _DR[k]
                if 0 <= rr < R:
                    q = rr * cols + (col[j] + _DC[k]) % cols
                    if pred[q] == want:
                        s = seg[q]
                        break
        point_segment[j] = s
        if s >= 0:
            n_points[s] += 1
