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

from lidar_quality_core.lms import metric_kernels as _k
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
# points per block of the probability sums (float64: float32 ones drift by ~1e-4 on large
# segments); each block is summed from 0, then added: the order of the blockwise sparse
# products this replaced, kept so that results stay bit-identical
_BLOCK = 16384
# probabilities per block of the dispersion pass (the running sums and top two of a block
# of points, and a row-major block transposed, stay in cache)
_DISPERSION_BLOCK = 1 << 17
# 0 log 0 = 0: the entropy reads max(p, tiny) when some probability is not positive
_TINY = np.float32(1e-37)


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


def _class_major(probs: np.ndarray) -> bool:
    return probs.flags.f_contiguous and not probs.flags.c_contiguous


def _readable(probs: np.ndarray) -> np.ndarray:
    """``probs`` (N, n) float32 as the kernels read it without a copy: class-major (the
    transposed view of an (n, N) array) or each point's classes contiguous (row-major, or
    rows of a message's records); anything else copied row-major."""
    if _class_major(probs) or probs.strides[1] == probs.itemsize or probs.shape[1] == 1:
        return probs
    return np.ascontiguousarray(probs)


def dispersion(probs: np.ndarray, sums: tuple[np.ndarray, np.ndarray] | None = None
               ) -> tuple[np.ndarray, ...]:
    """Per point from probabilities (N, n) float32, any layout (not modified; see
    :func:`_readable`): ``(argmax, E, D, V)`` (see the module doc;
    a NaN probability makes the point's argmax 0 and E, D, V NaN). ``sums``: (N,) float32
    ``(total, smallest)`` filled in the same pass with each point's sum and minimum of its
    probabilities, the bits of numpy's reductions over the classes (``probs.T.sum(0)``
    from +0.0 in class order, NaN-propagating ``min``)."""
    probs = np.asarray(probs).astype(np.float32, copy=False)
    N, n = probs.shape
    cls = np.zeros(N, dtype=np.int32)
    E = np.zeros(N, dtype=np.float32)
    p_sum, p_min = sums if sums is not None else (np.empty(N, np.float32),
                                                  np.empty(N, np.float32))
    if n == 1 or N == 0:                                 # no second class: p2 = 0, E = 0
        if n == 1:
            np.add(np.float32(0.0), probs[:, 0], out=p_sum)
            p_min[:] = probs[:, 0]
        V = np.float32(1.0) - probs[:, 0] if n == 1 else np.zeros(N, dtype=np.float32)
        return cls, E, V + np.float32(0.0), V
    D = np.empty(N, dtype=np.float32)
    V = np.empty(N, dtype=np.float32)
    scale = np.float32(-1.0 / np.log(n))
    probs = _readable(probs)
    class_major = _class_major(probs)
    pcm = probs.T if class_major else None
    step = max(1, _DISPERSION_BLOCK // n)
    tbuf = None if class_major else np.empty(step * n, dtype=np.float32)

    def run(clamp: bool):
        if class_major:
            return _k.dispersion_columns(pcm, step, clamp, _TINY, scale, cls, E, D, V,
                                         p_sum, p_min)
        return _k.dispersion_rows(probs, step, clamp, _TINY, scale, tbuf, cls, E, D, V,
                                  p_sum, p_min)

    # 0 log 0 = 0: the logs read max(p, tiny) when some p is <= 0 or NaN, which is known
    # after the pass: assumed, and the entropy redone in the rare case of tiny positive
    # probabilities without any such p
    smallest, nan = run(True)
    if not nan and 0 < smallest < _TINY:
        run(False)
    return cls, E, D, V


_NO_RUN = np.zeros(0, np.float32)
_NO_RUN.flags.writeable = False


def _record_run(probs: np.ndarray) -> tuple[np.ndarray, int]:
    """``(run, step)`` for ``metric_kernels.region_sums``: float32 probabilities (N, n)
    whose classes lie together, rows a multiple of 4 bytes apart (a message's records, a
    row-major array) as one read-only flat view from the first probability to the last,
    point i's at ``run[i * step:i * step + n]``; else an empty run (the kernel reads
    ``probs`` itself)."""
    N, n = probs.shape
    s0, s1 = probs.strides
    if not (N and n and probs.dtype == np.float32 and probs.flags.aligned
            and s1 == 4 and s0 > 0 and s0 % 4 == 0):
        return _NO_RUN, 0
    run = np.lib.stride_tricks.as_strided(probs, shape=((N - 1) * (s0 // 4) + n,),
                                          strides=(4,), writeable=False)
    return run, s0 // 4


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


def _i32(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.int32)


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
                     min_points: int = 10, class_names: Sequence[str] | None = None,
                     point_dispersion: tuple | None = None) -> SegmentResult:
    """Segments, metrics and point maps of one cloud (see the module doc).

    ``xyz`` (N, 3); ``probs`` (N, n) softmax probabilities in [0, 1], float32, read in
    place when class-major (the transposed view of an (n, N) array) or with each point's
    classes contiguous (row-major, or a view into a message's records), never copied in
    float64 (quantized inputs are the caller's to scale); ``ring`` (N,) optional rows
    (ring 0 = top beam); ``intensity`` (N,) optional; ``min_points``: smallest SP of a
    kept segment; ``class_names`` only name the N_c / P_c metrics; ``point_dispersion``:
    :func:`dispersion` of these ``probs`` when the caller has it (the node's decode takes
    it with its probability checks, in one pass over the probabilities).
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
    probs = _readable(probs)
    if point_dispersion is None:
        point_dispersion = dispersion(probs)
    elif any(len(a) != N for a in point_dispersion):
        raise ValueError(f"point_dispersion must hold 4 arrays of {N} values")
    point_class, E, D, V = point_dispersion
    R, C = cfg.shape
    idx = _i32(proj.index).reshape(-1)
    mask = idx >= 0
    if not mask.any():
        return _empty_result(n, names_arg, proj, N, point_class, E, D, V)

    # fill: every pixel reads the point of its nearest projected pixel
    near = nearest_source(mask.reshape(R, C)).reshape(-1)
    if near.dtype != np.int64:                      # the kernel reads int64 or int32
        near = _i32(near)
    source = np.empty(R * C, np.int32)
    Yf = np.empty(R * C, np.int32)
    _k.read_sources(idx, point_class, near, source, Yf)
    Y = Yf.reshape(R, C)
    segments, n_seg, segment_class = label_periodic(Y, return_values=True)
    interior = interior_mask(Y)
    seg = segments.reshape(-1)
    inn = interior.reshape(-1)

    # Sums over the pixels of the filled image, done over points: every kept point at its
    # own pixel, weighted by 1 + the filled pixels that read it and fall in the same region
    # (nine in ten), plus the other filled pixels read one by one (metric_kernels). Regions
    # (rows): (segment, boundary) -> seg, (segment, interior) -> n_seg + seg; in float64.
    nb = 2 * n_seg
    M = len(MEASURES)
    inten = np.zeros(N, np.float32) if intensity is None else intensity
    cols5 = (xyz[:, 0], xyz[:, 1], xyz[:, 2], inten, proj.range)
    if any(c.dtype != np.float32 for c in cols5):   # the kernel's other variant: float64
        cols5 = tuple(np.asarray(c, np.float64) for c in cols5)
    sums = np.zeros((nb, 2 * M))
    psum = np.zeros((nb, n))
    SP_rid = np.zeros(nb, np.int64)                              # projected pixels
    cnt = np.zeros(nb, np.int64)                                 # all pixels
    rows, row_step = _record_run(probs)
    _k.region_sums(idx, source, _i32(seg), np.ascontiguousarray(inn, bool),
                   n_seg, E, D, V, *cols5, probs, rows, row_step, _BLOCK, sums, psum, SP_rid,
                   cnt)
    SP = SP_rid[:n_seg] + SP_rid[n_seg:]
    S_bd, S_in = cnt[:n_seg], cnt[n_seg:]
    S = S_bd + S_in
    kept = SP >= min_points
    kid = np.flatnonzero(kept)
    k = len(kid)

    # statistics, sizes and P_c per kept segment (metric_kernels.segment_features)
    features = np.empty((k, n_metrics(n)))
    _k.segment_features(sums, psum, cnt, SP_rid, kid, features)
    # neighbourhood class ratios N_c
    nbc = neighbour_class_counts(segments, Y, np.flatnonzero(~inn), n_seg, n)[kid]
    tot = nbc.sum(axis=1, keepdims=True)
    o = M * len(_STATS) + len(_SIZES)
    features[:, o:o + n] = np.divide(nbc, tot, out=np.zeros(nbc.shape), where=tot > 0)

    # points -> segments (see the module doc)
    point_segment = np.full(N, -1, dtype=np.int32)
    n_points = SP.copy()
    _k.point_segments(idx, np.ascontiguousarray(proj.valid, bool), _i32(proj.pixel),
                      _i32(proj.row), _i32(proj.col), _i32(seg), Yf, point_class, C,
                      point_segment, n_points)

    return SegmentResult(
        n_classes=n, class_names=names_arg, projection=proj,
        source=source.reshape(R, C), pred=Y, segments=segments,
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
