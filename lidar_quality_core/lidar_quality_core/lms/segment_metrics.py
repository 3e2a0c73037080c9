"""LidarMetaSeg (LMS) segment metrics (paper section II; no rclpy).

Shared by the node, training and evaluation. One call, :func:`compute_segments`, turns a
cloud with per-point softmax probabilities into the paper's segments, their metrics in the
order of :func:`metric_names`, and the point <-> segment maps;
:func:`lidar_quality_core.lms.targets.segment_targets` adds IoU and IoU_adj given per-point
ground truth; :func:`to_points` maps per-segment values (confidence, predicted IoU) back to
the points.

Every definition, and the choices the paper leaves open ("ours"):

Projection (II-A)
  :func:`lidar_quality_core.lms.projection.project` with the sensor's
  :class:`RangeImageConfig` (rows = channels, cols = 360 deg / angular resolution, beam
  elevations or a uniform vertical field of view) or the cloud's ``ring`` field; each
  pixel keeps its nearest point (smallest range, then lowest index). Points that are
  non-finite or outside the vertical field of view are not projected: they belong to no
  segment (id -1) and enter no metric.
Fill and delta (II-A)
  Every empty pixel takes the point of its nearest projected pixel (Euclidean in pixel
  units, azimuth periodic, rows not; ties: the same ring first, then left, then up; see
  :mod:`lidar_quality_core.lms.fill`); every image (probabilities, prediction,
  heatmaps, x, y, z, intensity, range, ground truth) is filled through that one map.
  delta = the pixel holds a projected point. An image without any projected point has no
  segment.
Heatmaps (eq. (5)-(8)), per point, read by every pixel the point fills
  E = -sum_c p_c log p_c / log n (0 log 0 = 0; E = 0 when n = 1), D = 1 - p_(1) + p_(2)
  (the two largest probabilities; p_(2) = 0 when n = 1), V = 1 - p_(1); x, y, z and
  range r = |xyz| in the cloud's frame; intensity as given (all 0 when the cloud has none:
  the schema does not change). Probabilities are used as given (no renormalisation);
  the predicted class is the argmax, the lowest class on ties.
Segments (II-B)
  8-connected components of equal predicted class on the filled image, columns periodic
  (a segment across the seam behind the car is one segment), rows not. Ids 0..n-1 follow
  each segment's first pixel in raster order (row 0 = top, column 0 = behind the car).
Interior and boundary
  A pixel is interior when all 8 neighbours exist and belong to its segment: pixels of the
  top and bottom rows are always boundary (ours; the paper's literal definition. MetaSeg's
  code ignores neighbours outside the image instead). Hence S_bd >= 1 and the relative
  sizes are always defined.
Metrics (eq. (12)-(17)), all over pixels of the filled image (only SP uses delta)
  For M in (E, D, V, x, y, z, i, r) and region in (segment, interior, boundary): the mean
  and the population variance mu(M^2) - mu(M)^2 (clipped at 0). Empty interior
  (S_in = 0): its means and variances are 0 (as MetaSeg's code leaves them). Relative
  metrics: mean_M_rel = mean_M * S/S_bd, var_M_rel = var_M * S/S_bd, mean_M_rel_in =
  mean_M_in * S_in/S_bd, var_M_rel_in = var_M_in * S_in/S_bd (the interior metric times
  the interior relative size, as in MetaSeg's code; the extracted eq. (15) reads as if it
  were the segment's metric). Sizes S, S_in, S_bd, S_rel = S/S_bd, S_rel_in = S_in/S_bd,
  SP = |k|_delta (projected pixels = points the image keeps). N_c: fraction of the
  segment's neighbourhood pixels k_nb (the set of pixels 8-adjacent to the segment and not
  in it, each counted once, seam included) predicted as class c. Eq. (16) as extracted
  sums over k_bd, whose pixels all have the segment's own class: that would be a size
  ratio, not a class ratio, so the sum is read over k_nb (ours). N of the segment's own
  class is then always 0 (same-class neighbours would be in the segment); all N_c = 0
  when k_nb is empty (one segment covers the image). P_c: mean probability of class c
  over the segment. Count 8 * 10 + 6 + 2n = 86 + 2n, order and names in
  :func:`metric_names`; all sums are accumulated in float64. The predicted class itself
  is not a metric (as in the paper's count): it is ``SegmentResult.segment_class``.
Exclusion
  Segments with SP < ``min_points`` (default 10, paper III-A) are not kept: the feature
  matrix and the targets have one row per kept segment (``SegmentResult.kept_ids``);
  their points still carry their segment id.
Targets (eq. (10), (11))
  IoU and IoU_adj of each segment: :mod:`lidar_quality_core.lms.targets`.
Points
  A projected point takes its pixel's segment when its own predicted class is the
  pixel's; a point that lost its pixel to a nearer point of another class takes the
  segment of the first 8-neighbour pixel of its class (order: left, right, up, down, then
  the diagonals), else none (-1). ``n_points`` counts the points of each segment.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.sparse import csc_matrix

from lidar_quality_core.lms.projection import Projection, RangeImageConfig, project
from lidar_quality_core.lms.fill import nearest_source
from lidar_quality_core.lms.segments import interior_mask, label_periodic, neighbour_class_counts

__all__ = [
    "MEASURES",
    "metric_names",
    "n_metrics",
    "SegmentResult",
    "compute_segments",
    "to_points",
    "dispersion",
]

#: Heatmaps in schema order: dispersion (entropy, probability margin, variation ratio),
#: then the point-cloud features x, y, z, intensity, range.
MEASURES = ("E", "D", "V", "x", "y", "z", "i", "r")
_STATS = ("mean", "mean_in", "mean_bd", "mean_rel", "mean_rel_in",
          "var", "var_in", "var_bd", "var_rel", "var_rel_in")
_SIZES = ("S", "S_in", "S_bd", "S_rel", "S_rel_in", "SP")
# neighbour order for points without a pixel of their class: 4-neighbours, then diagonals
_NB = ((0, -1), (0, 1), (-1, 0), (1, 0), (-1, -1), (-1, 1), (1, -1), (1, 1))
_BLOCK = 16384  # points per block of the probability sums (a cache-sized float64 copy)


def n_metrics(n_classes: int) -> int:
    """86 + 2 n."""
    return len(MEASURES) * len(_STATS) + len(_SIZES) + 2 * int(n_classes)


def metric_names(n_classes: int, class_names: Sequence[str] | None = None) -> tuple[str, ...]:
    """Ordered metric names (86 + 2n): for each M of :data:`MEASURES`
    ``mean_M, mean_M_in, mean_M_bd, mean_M_rel, mean_M_rel_in, var_M, ..., var_M_rel_in``;
    then ``S, S_in, S_bd, S_rel, S_rel_in, SP``; then ``N_<c>`` and ``P_<c>`` per class,
    ``<c>`` the class name if given, else its index."""
    n_classes = int(n_classes)
    if n_classes < 1:
        raise ValueError(f"need at least one class, got {n_classes}")
    if class_names is None:
        class_names = [str(c) for c in range(n_classes)]
    class_names = [str(c) for c in class_names]
    if len(class_names) != n_classes:
        raise ValueError(f"{len(class_names)} class names for {n_classes} classes")
    if len(set(class_names)) != n_classes:
        raise ValueError("class names must be unique")
    names = [s.replace("mean", f"mean_{m}", 1).replace("var", f"var_{m}", 1)
             for m in MEASURES for s in _STATS]
    names += list(_SIZES)
    names += [f"N_{c}" for c in class_names] + [f"P_{c}" for c in class_names]
    return tuple(names)


def _class_major(probs: np.ndarray, block: int = 4096) -> np.ndarray:
    """(n, N) float32 C-contiguous copy of (N, n) probabilities, copied in blocks of
    points (cache-sized pieces: faster than one strided copy)."""
    N, n = probs.shape
    out = np.empty((n, N), dtype=np.float32)
    for s in range(0, N, block):
        out[:, s:s + block] = probs[s:s + block].T
    return out


def dispersion(probs_cm: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per point from class-major probabilities (n, N) float32 C-contiguous, which it
    overwrites: ``(argmax, E, D, V)`` (see the module doc)."""
    n, N = probs_cm.shape
    E = np.zeros(N, dtype=np.float32)
    if n > 1 and N:
        # one class row at a time: the temporaries stay in cache
        clamp = not probs_cm.min() > 0          # 0 log 0 = 0: p * log(tiny) = 0
        tmp = np.empty(N, dtype=np.float32)
        for pc in probs_cm:
            if clamp:
                np.maximum(pc, np.float32(1e-37), out=tmp)
                np.log(tmp, out=tmp)
            else:
                np.log(pc, out=tmp)
            tmp *= pc
            E += tmp
        E *= np.float32(-1.0 / np.log(n))
    p1 = probs_cm.max(axis=0)
    if n > 1 and N:
        # argmax = the first class reaching p1 (as np.argmax): max of descending weights
        w = np.arange(n, 0, -1, dtype=np.uint8 if n < 256 else np.int32)[:, None]
        cls = (n - ((probs_cm == p1) * w).max(axis=0)).astype(np.int32)
        cls[cls >= n] = 0                                # NaN probabilities: class 0
        # p2: the largest value left once that one entry is removed (ties: p2 = p1)
        probs_cm.reshape(-1)[cls * N + np.arange(N)] = -np.inf
        p2 = probs_cm.max(axis=0)
    else:
        cls = np.zeros(N, dtype=np.int32)
        p2 = np.zeros(N, dtype=np.float32)
    V = np.float32(1.0) - p1
    D = V + p2
    return cls, E, D, V


# -- result ------------------------------------------------------------------------------


@dataclass
class SegmentResult:
    """Segments of one cloud (see the module doc).

    Images (rows, cols), filled: ``source`` (index of the point each pixel reads, -1 only
    when nothing was projected), ``pred`` (predicted class), ``segments`` (segment id),
    ``interior``. Per segment (n_segments,): ``segment_class``, ``size`` (S),
    ``size_projected`` (SP), ``n_points``, ``kept``. ``features`` (n_kept, n_metrics)
    float64 in :attr:`names` order, one row per :attr:`kept_ids`. Per point (N,):
    ``point_segment`` (-1: none), ``point_class`` (argmax), ``point_E/D/V`` heatmaps.
    """

    n_classes: int
    class_names: tuple[str, ...] | None
    projection: Projection
    source: np.ndarray
    pred: np.ndarray
    segments: np.ndarray
    interior: np.ndarray
    segment_class: np.ndarray
    size: np.ndarray
    size_projected: np.ndarray
    n_points: np.ndarray
    kept: np.ndarray
    features: np.ndarray
    point_segment: np.ndarray
    point_class: np.ndarray
    point_E: np.ndarray
    point_D: np.ndarray
    point_V: np.ndarray

    @property
    def names(self) -> tuple[str, ...]:
        return metric_names(self.n_classes, self.class_names)

    @property
    def n_segments(self) -> int:
        return len(self.segment_class)

    @property
    def kept_ids(self) -> np.ndarray:
        return np.flatnonzero(self.kept)

    @property
    def delta(self) -> np.ndarray:
        """(rows, cols) bool: the pixel holds a projected point."""
        return self.projection.index >= 0

    def image(self, per_point, fill=np.nan) -> np.ndarray:
        """Filled image (rows, cols, ...) of per-point values (what every metric reads)."""
        v = np.asarray(per_point)
        if len(v) != len(self.point_class):
            raise ValueError(f"{len(v)} values for {len(self.point_class)} points")
        src = self.source.reshape(-1)
        if len(src) and src[0] < 0:
            out = np.full(src.shape + v.shape[1:], fill,
                          dtype=np.result_type(v.dtype, np.asarray(fill).dtype))
        else:
            out = v[src]
        return out.reshape(self.source.shape + v.shape[1:])


def _empty_result(n, names_arg, proj, N, point_class, E, D, V) -> SegmentResult:
    R, C = proj.cfg.shape
    z = np.zeros(0, dtype=np.int64)
    return SegmentResult(
        n_classes=n, class_names=names_arg, projection=proj,
        source=np.full((R, C), -1, np.int32), pred=np.full((R, C), -1, np.int32),
        segments=np.full((R, C), -1, np.int32), interior=np.zeros((R, C), bool),
        segment_class=z.astype(np.int32), size=z, size_projected=z, n_points=z,
        kept=np.zeros(0, bool), features=np.zeros((0, n_metrics(n))),
        point_segment=np.full(N, -1, np.int32), point_class=point_class,
        point_E=E, point_D=D, point_V=V)


def compute_segments(xyz, probs, cfg: RangeImageConfig, ring=None, intensity=None,
                     min_points: int = 10, class_names: Sequence[str] | None = None
                     ) -> SegmentResult:
    """Segments, metrics and point maps of one cloud (see the module doc).

    ``xyz`` (N, 3); ``probs`` (N, n) softmax probabilities in [0, 1], float32 row-major
    or the transposed view of a class-major (n, N) array, neither copied as a whole in
    float64 (quantized inputs are the caller's to scale); ``ring`` (N,) optional rows
    (ring 0 = top beam); ``intensity`` (N,) optional; ``min_points``: smallest SP of a
    kept segment; ``class_names`` only name the N_c / P_c metrics.
    """
    xyz = np.asarray(xyz)
    if xyz.size == 0:
        xyz = xyz.reshape(0, 3)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"xyz must have shape (N, 3), got {xyz.shape}")
    N = len(xyz)
    probs = np.asarray(probs)
    if probs.ndim != 2 or probs.shape[0] != N or probs.shape[1] < 1:
        raise ValueError(f"probs must have shape ({N}, n_classes >= 1), got {probs.shape}")
    n = probs.shape[1]
    names_arg = None if class_names is None else tuple(str(c) for c in class_names)
    metric_names(n, names_arg)  # validates the class names
    if intensity is not None:
        intensity = np.asarray(intensity).reshape(-1)
        if len(intensity) != N:
            raise ValueError(f"intensity has {len(intensity)} entries, xyz {N}")

    proj = project(xyz, cfg, ring)
    probs = probs.astype(np.float32, copy=False)
    # top two, argmax and entropy want class rows (a copy: dispersion overwrites it), P_c
    # wants point rows; a class-major input (transposed view) is used as it is
    if probs.flags.f_contiguous and not probs.flags.c_contiguous:
        probs_cm = np.array(probs.T)
    else:
        probs = np.ascontiguousarray(probs)
        probs_cm = _class_major(probs)
    point_class, E, D, V = dispersion(probs_cm)
    del probs_cm
    R, C = cfg.shape
    idx = proj.index.reshape(-1)
    mask = idx >= 0
    if not mask.any():
        return _empty_result(n, names_arg, proj, N, point_class, E, D, V)

    # fill: every pixel reads the point of its nearest projected pixel
    near = nearest_source(mask.reshape(R, C)).reshape(-1)
    source = idx[near]
    Yf = point_class[source]
    Y = Yf.reshape(R, C)
    segments, n_seg, segment_class = label_periodic(Y, return_values=True)
    interior = interior_mask(Y)
    seg = segments.reshape(-1)
    inn = interior.reshape(-1)

    # Sums over the pixels of the filled image, done over points: every winner point at
    # its own pixel, weighted by 1 + the filled pixels that read it and fall in the same
    # row (nine in ten), plus the other filled pixels read one by one. Rows:
    # (segment, boundary) -> seg, (segment, interior) -> n_seg + seg, and nb for the
    # points no pixel keeps. Sparse products (row x point) @ (point x value), in float64.
    nb = 2 * n_seg
    rid = seg + n_seg * inn
    proj_pix = np.flatnonzero(mask)
    win = idx[proj_pix]
    rid_pt = np.full(N, nb, dtype=np.int32)
    rid_pt[win] = rid[proj_pix]
    fill_pix = np.flatnonzero(~mask)
    rid_fill = rid[fill_pix]
    src_fill = source[fill_pix]
    same = rid_fill == rid_pt[src_fill]
    weight = np.bincount(src_fill[same], minlength=N).astype(np.float64)
    weight += 1.0
    other_fill = np.flatnonzero(~same)
    inten = np.zeros(N, np.float32) if intensity is None else intensity
    M = len(MEASURES)
    G = np.stack([E, D, V, xyz[:, 0], xyz[:, 1], xyz[:, 2], inten, proj.range],
                 axis=1).astype(np.float64)
    G2 = np.square(G)
    cols = np.arange(N + 1, dtype=np.int32)
    B = csc_matrix((weight, rid_pt, cols), shape=(nb + 1, N))
    s1, s2 = B @ G, B @ G2
    # probabilities: float64 sums too (float32 ones drift by ~1e-4 on large segments),
    # converted block by block so that no float64 copy of them all is made
    psum = np.zeros((nb + 1, n))
    for b0 in range(0, N, _BLOCK):
        b1 = min(N, b0 + _BLOCK)
        psum += csc_matrix((weight[b0:b1], rid_pt[b0:b1], cols[:b1 - b0 + 1]),
                           shape=(nb + 1, b1 - b0)) @ np.asarray(probs[b0:b1], np.float64,
                                                                 order="C")
    if len(other_fill):
        nf = len(other_fill)
        # its own column pointer: nf exceeds N in sparse clouds (more filled pixels than
        # points), where cols[:nf + 1] would be too short (found by fuzzing)
        Bf = csc_matrix((np.ones(nf), rid_fill[other_fill], np.arange(nf + 1, dtype=np.int64)),
                        shape=(nb + 1, nf))
        sf = src_fill[other_fill]
        Gf = G[sf]
        s1 += Bf @ Gf
        s2 += Bf @ (Gf * Gf)
        psum += Bf @ probs[sf].astype(np.float64)
    SP_rid = np.bincount(rid_pt, minlength=nb + 1)[:nb]       # projected pixels per row
    cnt = SP_rid + np.bincount(rid_fill, minlength=nb)
    SP = SP_rid[:n_seg] + SP_rid[n_seg:]
    S_bd, S_in = cnt[:n_seg], cnt[n_seg:]
    S = S_bd + S_in
    kept = SP >= min_points
    kid = np.flatnonzero(kept)
    k = len(kid)

    # regions: segment = boundary + interior rows, interior, boundary
    sums = np.concatenate([s1[:, :M], s2[:, :M]], axis=1)
    s_reg = np.stack([sums[:n_seg] + sums[n_seg:nb], sums[n_seg:nb], sums[:n_seg]],
                     axis=1)[kid]                                  # (k, 3, 2M)
    S3 = np.stack([S[kid], S_in[kid], S_bd[kid]], axis=1).astype(np.float64)
    has = (S3 > 0)[:, :, None]
    den = np.where(has, S3[:, :, None], 1.0)
    mean = np.where(has, s_reg[:, :, :M] / den, 0.0)               # (k, 3, M)
    var = np.where(has, np.maximum(s_reg[:, :, M:] / den - mean * mean, 0.0), 0.0)
    S_rel = S3[:, 0] / S3[:, 2]
    S_rel_in = S3[:, 1] / S3[:, 2]
    stats = np.empty((k, M, len(_STATS)))
    stats[:, :, 0:3] = mean.transpose(0, 2, 1)
    stats[:, :, 3] = mean[:, 0] * S_rel[:, None]
    stats[:, :, 4] = mean[:, 1] * S_rel_in[:, None]
    stats[:, :, 5:8] = var.transpose(0, 2, 1)
    stats[:, :, 8] = var[:, 0] * S_rel[:, None]
    stats[:, :, 9] = var[:, 1] * S_rel_in[:, None]

    # neighbourhood class ratios N_c
    nbc = neighbour_class_counts(segments, Y, np.flatnonzero(~inn), n_seg, n)[kid]
    tot = nbc.sum(axis=1, keepdims=True)
    Nc = np.divide(nbc, tot, out=np.zeros(nbc.shape), where=tot > 0)
    # mean class probabilities P_c
    Pc = (psum[:n_seg] + psum[n_seg:nb])[kid] / S3[:, :1]

    features = np.concatenate(
        [stats.reshape(k, M * len(_STATS)), S3, S_rel[:, None], S_rel_in[:, None],
         SP[kid, None].astype(np.float64), Nc, Pc], axis=1)

    # points -> segments: a winner is in its pixel's segment; other projected points
    # (their pixel kept a nearer point) too if of the pixel's class, else in the segment
    # of the first neighbour pixel of their class
    point_segment = np.full(N, -1, dtype=np.int32)
    point_segment[win] = seg[proj_pix]
    n_points = SP.copy()
    if np.count_nonzero(proj.valid) > len(win):
        other = proj.valid.copy()
        other[win] = False
        other = np.flatnonzero(other)
        pix = proj.pixel[other]
        ps = seg[pix].astype(np.int32)
        wrong = np.flatnonzero(Yf[pix] != point_class[other])
        if len(wrong):
            pr = proj.row[other[wrong]].astype(np.int64)
            pcol = proj.col[other[wrong]].astype(np.int64)
            want = point_class[other[wrong]]
            found = np.full(len(wrong), -1, dtype=np.int32)
            for dr, dc in _NB:
                rr = pr + dr
                ok = np.flatnonzero((found < 0) & (rr >= 0) & (rr < R))
                q = rr[ok] * C + (pcol[ok] + dc) % C
                hit = Yf[q] == want[ok]
                found[ok[hit]] = seg[q[hit]]
            ps[wrong] = found
        point_segment[other] = ps
        n_points += np.bincount(ps[ps >= 0], minlength=n_seg)

    return SegmentResult(
        n_classes=n, class_names=names_arg, projection=proj,
        source=source.reshape(R, C).astype(np.int32), pred=Y, segments=segments,
        interior=interior, segment_class=segment_class.astype(np.int32), size=S,
        size_projected=SP, n_points=n_points, kept=kept, features=features,
        point_segment=point_segment, point_class=point_class,
        point_E=E, point_D=D, point_V=V)


def to_points(result: SegmentResult, per_segment, fill=np.nan) -> np.ndarray:
    """Per-point array (N, ...) of per-segment values: ``per_segment`` has one row per
    segment (n_segments) or per kept segment (n_kept, the rows of ``features``); points
    without a segment, or of a segment without a value, get ``fill``."""
    vals = np.asarray(per_segment)
    ns, nk = result.n_segments, len(result.kept_ids)
    if len(vals) == ns:
        full = vals
        has = np.ones(ns, dtype=bool)
    elif len(vals) == nk:
        full = np.zeros((ns,) + vals.shape[1:], dtype=vals.dtype)
        full[result.kept_ids] = vals
        has = result.kept
    else:
        raise ValueError(f"{len(vals)} values, expected {ns} (segments) or {nk} (kept)")
    out = np.full((len(result.point_segment),) + vals.shape[1:], fill,
                  dtype=np.result_type(vals, fill))
    ps = result.point_segment
    ok = ps >= 0
    ok[ok] = has[ps[ok]]
    out[ok] = full[ps[ok]]
    return out
