"""Spherical projection of a lidar cloud to a range image, and range-image neighbourhoods.

The project's single projection module (numpy; :func:`project`'s per-point and per-pixel
work in numba kernels, the azimuth by a vectorized atan2 checked against libm's near
column edges): the reference segmenter's local geometry features and
LidarMetaSeg's image representation (paper eq. (1)-(3)) both use it.

Conventions (ROS sensor frame: x forward, y left, z up):

* **Rows**: row 0 is the TOP of the image (highest elevation), as lidar rings in
  ``lidar_sim`` (ring 0 = top beam), Ouster and SemanticKITTI range images. With a
  ``ring`` field the row is the ring; otherwise the row is the beam whose elevation bin
  holds the point's elevation ``asin(z / r)``. Bins are the midpoints between adjacent beam
  elevations (non-uniform beams, e.g. HDL-64) or ``rows`` equal bins from ``fov_up`` down
  to ``fov_down`` (uniform, paper eq. (2)); the outermost bins reach half a beam spacing
  beyond the outermost beams.
* **Columns**: ``col = floor((1 - atan2(y, x) / pi) / 2 * cols) mod cols`` (RangeNet++ /
  SemanticKITTI, paper eq. (2)): column 0 starts at azimuth +pi (straight back), columns
  advance clockwise seen from above, the middle column looks forward (+x), and the last
  column ends just right of straight back. The image wraps around in azimuth: columns 0
  and ``cols - 1`` are neighbours (the seam behind the car is not an edge), and every
  neighbourhood helper here treats the column axis as periodic. Rows are not periodic:
  outside the image a neighbour is missing.
* **Pixels**: each pixel keeps the *nearest* point projected to it (smallest range; ties:
  the lowest point index). ``Projection.index`` holds its index, -1 for an empty pixel.
* **Invalid points**: non-finite points (NaN / inf coordinates) and points outside the
  vertical field of view (or with ``ring >= rows``) are not projected: ``row = col = -1``,
  ``valid = False``; ``out_of_fov`` flags the finite ones among them. Nothing raises.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from numba import njit, types

from lidar_quality_core.kernel_types import array_in as _in, array_out as _out

__all__ = [
    "RangeImageConfig",
    "Projection",
    "project",
    "shift",
    "window_reduce",
    "window_stats",
    "WindowStats",
]


@dataclass(frozen=True)
class RangeImageConfig:
    """Image size and vertical beam layout.

    Give either ``elevations_deg`` (one per row, strictly decreasing: row 0 = top beam) or
    ``fov_up_deg`` / ``fov_down_deg`` (uniform rows, ``fov_down_deg`` negative below the
    horizon). ``cols`` = 360 deg / horizontal resolution (paper eq. (3)).
    """

    rows: int
    cols: int
    elevations_deg: tuple[float, ...] | None = None
    fov_up_deg: float | None = None
    fov_down_deg: float | None = None
    _edges: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        rows, cols = int(self.rows), int(self.cols)
        if rows < 1 or cols < 1:
            raise ValueError(f"rows and cols must be >= 1, got {self.rows} x {self.cols}")
        object.__setattr__(self, "rows", rows)
        object.__setattr__(self, "cols", cols)
        uniform = self.fov_up_deg is not None or self.fov_down_deg is not None
        if (self.elevations_deg is None) == (not uniform) or (
                uniform and (self.fov_up_deg is None or self.fov_down_deg is None)):
            raise ValueError("give either elevations_deg or both fov_up_deg and fov_down_deg")
        if self.elevations_deg is not None:
            e = np.asarray(self.elevations_deg, dtype=np.float64).ravel()
            if len(e) != rows or not np.all(np.isfinite(e)) or np.any(np.diff(e) >= 0):
                raise ValueError("elevations_deg needs `rows` finite, strictly decreasing "
                                 "values (row 0 = top beam)")
            object.__setattr__(self, "elevations_deg", tuple(float(v) for v in e))
            if rows == 1:
                edges = np.array([e[0] + 0.5, e[0] - 0.5])  # a single beam: +-0.5 deg
            else:
                mid = 0.5 * (e[1:] + e[:-1])
                edges = np.r_[e[0] + (e[0] - mid[0]), mid, e[-1] - (mid[-1] - e[-1])]
        else:
            up, down = float(self.fov_up_deg), float(self.fov_down_deg)
            if not (np.isfinite(up) and np.isfinite(down) and up > down):
                raise ValueError(f"need fov_up_deg > fov_down_deg, got {up}, {down}")
            object.__setattr__(self, "fov_up_deg", up)
            object.__setattr__(self, "fov_down_deg", down)
            edges = np.linspace(up, down, rows + 1)
        edges.flags.writeable = False
        object.__setattr__(self, "_edges", edges)

    @classmethod
    def from_elevations(cls, elevations_deg: Sequence[float], cols: int = 2048
                        ) -> "RangeImageConfig":
        """One row per beam elevation (degrees, decreasing: row 0 = top beam)."""
        e = tuple(float(v) for v in np.asarray(elevations_deg, dtype=np.float64).ravel())
        return cls(rows=len(e), cols=cols, elevations_deg=e)

    @classmethod
    def uniform(cls, rows: int, cols: int, fov_up_deg: float, fov_down_deg: float
                ) -> "RangeImageConfig":
        """``rows`` equal elevation bins from ``fov_up_deg`` down to ``fov_down_deg``."""
        return cls(rows=rows, cols=cols, fov_up_deg=fov_up_deg, fov_down_deg=fov_down_deg)

    @property
    def row_edges_deg(self) -> np.ndarray:
        """(rows + 1,) decreasing elevation bin edges: row r covers [edges[r+1], edges[r])."""
        return self._edges

    @property
    def shape(self) -> tuple[int, int]:
        return (self.rows, self.cols)


def _fill_dtype(dtype, fill) -> np.dtype:
    """``dtype`` if it can hold ``fill`` (float arrays keep their precision), else a wider one."""
    dtype = np.dtype(dtype)
    if np.issubdtype(dtype, np.floating) or np.can_cast(np.asarray(fill), dtype, "same_kind") \
            and np.asarray(fill, dtype=dtype) == fill:
        return dtype
    return np.result_type(dtype, np.asarray(fill).dtype)


@dataclass
class Projection:
    """Where each point of a cloud lands in the range image (see the module doc).

    Per point (N,): ``row`` / ``col`` (int32, -1 if not projected), ``pixel``
    (``row * cols + col``, -1 if not projected), ``range`` (float32 Euclidean range, NaN
    for non-finite points), ``valid`` (projected), ``out_of_fov`` (finite but outside the
    vertical field of view). Per pixel: ``index`` (rows, cols) int32, the index of the
    nearest point projected there, -1 if empty.
    """

    cfg: RangeImageConfig
    row: np.ndarray
    col: np.ndarray
    pixel: np.ndarray
    range: np.ndarray
    valid: np.ndarray
    out_of_fov: np.ndarray
    index: np.ndarray

    def __len__(self) -> int:
        return len(self.row)

    @property
    def mask(self) -> np.ndarray:
        """(rows, cols) bool: the pixel holds a projected point (the paper's delta)."""
        return self.index >= 0

    @property
    def winner(self) -> np.ndarray:
        """(N,) bool: the point is the one its pixel keeps."""
        w = np.zeros(len(self.row), dtype=bool)
        idx = self.index[self.index >= 0]
        w[idx] = True
        return w

    def gather(self, values, fill=np.nan) -> np.ndarray:
        """Image ``(rows, cols, ...)`` of per-point ``values`` (N, ...) at the points each
        pixel keeps; ``fill`` in empty pixels."""
        values = np.asarray(values)
        if len(values) != len(self.row):
            raise ValueError(f"values has {len(values)} rows, the projection {len(self.row)}")
        dtype = _fill_dtype(values.dtype, fill)
        flat_idx = self.index.reshape(-1)
        out = np.full((flat_idx.size,) + values.shape[1:], fill, dtype=dtype)
        m = flat_idx >= 0
        out[m] = values[flat_idx[m]]
        return out.reshape(self.cfg.shape + values.shape[1:])

    def at_points(self, image, fill=np.nan) -> np.ndarray:
        """Per-point values ``(N, ...)`` read from each point's pixel of ``image``
        (rows, cols, ...); ``fill`` for points that are not projected."""
        return self.neighbour_values(image, 0, 0, fill)

    def neighbour_pixels(self, drow: int, dcol: int) -> np.ndarray:
        """(N,) flat index of the pixel at offset (drow, dcol) from each point's pixel
        (columns wrap around, rows do not); -1 outside the image or for unprojected
        points."""
        R, C = self.cfg.shape
        if drow == 0 and dcol == 0:
            return self.pixel
        r = self.row.astype(np.int64) + drow
        ok = self.valid & (r >= 0) & (r < R)
        return np.where(ok, r * C + (self.col.astype(np.int64) + dcol) % C, -1)

    def neighbour_values(self, image, drow: int, dcol: int, fill=np.nan) -> np.ndarray:
        """Per point (N, ...): the value of ``image`` (rows, cols, ...) at offset
        (drow, dcol) from the point's pixel (see :meth:`neighbour_pixels`); ``fill`` where
        there is no such pixel. Empty pixels give whatever ``image`` holds there."""
        image = np.asarray(image)
        if image.shape[:2] != self.cfg.shape:
            raise ValueError(f"image shape {image.shape[:2]} != {self.cfg.shape}")
        dtype = _fill_dtype(image.dtype, fill)
        # one fill element after the last pixel: index -1 reads it
        flat = np.concatenate([image.reshape((-1,) + image.shape[2:]).astype(dtype, copy=False),
                               np.full((1,) + image.shape[2:], fill, dtype=dtype)])
        return np.take(flat, self.neighbour_pixels(drow, dcol), axis=0)


# Compiled passes with vectorized approximations of asin and atan2, redone with libm's
# near a bin edge, so that rows and columns are libm's on every machine (numpy's float64
# arcsin / arctan2 call libm point by point without AVX-512 and run their own SIMD loops
# with it, a last bit away from libm for about 8 % of inputs): two before, for the
# elevations and the column coordinates, and one after, for everything per point and per
# pixel without temporaries. Coordinates are read as contiguous float32 or float64
# columns (the node's xyz is a transposed view: its columns already are; contiguous, the
# sine pass vectorizes, 4x faster than strided) and widened to float64 per point.


_COORDS = (types.float32, types.float64)
_LUT_MAX = 1 << 14  # most cells of the elevation lookup table
_DEG = 180.0 / math.pi  # np.degrees' factor


# atan(t) = t * sum_k (-1)^k t^(2k) / (2k + 1), k = 0..12, for |t| <= tan(pi/8): the first
# term left out is below 0.4143**27 / 27 < 2e-12 rad
(_A0, _A1, _A2, _A3, _A4, _A5, _A6, _A7, _A8, _A9, _A10, _A11,
 _A12) = ((-1.0) ** k / (2 * k + 1) for k in range(13))
_TAN_PI_8 = math.tan(math.pi / 8)
# a column coordinate (columns) or elevation (degrees) this close to an edge is computed
# again with libm's atan2 / asin (the approximations are within 1e-11 rad: 1e-8 columns
# for 2048 columns, 1e-9 degrees)
_EDGE_MARGIN = 1e-6


@njit(inline="always")
def _atan_ratio(a, b):
    """atan(a / b) for 0 <= a <= b (within 2e-12 rad; NaN for 0 / 0 and inf / inf),
    branch-free, one division."""
    big = a > _TAN_PI_8 * b
    u = (a - b if big else a) / (a + b if big else b)   # atan(a / b) = pi/4 + atan(u)
    v = u * u
    p = ((((((((((((_A12 * v + _A11) * v + _A10) * v + _A9) * v + _A8) * v + _A7) * v + _A6)
               * v + _A5) * v + _A4) * v + _A3) * v + _A2) * v + _A1) * v + _A0)
    return (math.pi / 4 if big else 0.0) + u * p


@njit([(_in(t), _in(t), types.float64, types.float64, _out(types.float64)) for t in _COORDS],
      cache=True, nogil=True, error_model="numpy")
def _column_coordinates(x, y, scale, offset, out):
    """``atan2(y, x) * scale + offset`` per point, with an approximate atan2 (within 1e-11
    rad; vectorized, where numpy's float64 arctan2 calls libm point by point: 35 ns a
    point on this project's machine); :func:`_place` redoes it exactly near a column
    edge and for anything but finite points off the origin (NaN here)."""
    for i in range(x.shape[0]):
        xi, yi = np.float64(x[i]), np.float64(y[i])
        ax, ay = abs(xi), abs(yi)
        steep = ay > ax
        a = _atan_ratio(ax if steep else ay, ay if steep else ax)
        a = math.pi / 2 - a if steep else a
        a = math.pi - a if xi < 0.0 else a
        a = -a if yi < 0.0 else a
        out[i] = a * scale + offset


@njit(inline="always")
def _elevation_sine(xi, yi, zi):
    """``clip(z / r, -1, 1)`` (``z`` itself where ``r`` is not positive)."""
    r = math.sqrt(xi * xi + yi * yi + zi * zi)
    s = zi / (r if r > 0.0 else 1.0)
    return min(max(s, -1.0), 1.0)


@njit([(_in(t), _in(t), _in(t), _out(types.float64)) for t in _COORDS],
      cache=True, nogil=True, error_model="numpy")
def _elevations(x, y, z, out):
    """``asin(clip(z / r, -1, 1))`` per point with an approximate asin (within 1e-11 rad:
    atan of sine over cosine, vectorized, where numpy's float64 arcsin calls libm point by
    point); :func:`_place` redoes it exactly near a row edge."""
    for i in range(x.shape[0]):
        s = _elevation_sine(np.float64(x[i]), np.float64(y[i]), np.float64(z[i]))
        a = abs(s)
        c = math.sqrt((1.0 - a) * (1.0 + a))
        steep = a > c
        e = _atan_ratio(c if steep else a, a if steep else c)
        e = math.pi / 2 - e if steep else e
        out[i] = -e if s < 0.0 else e


@njit(inline="always")
def _edges_above(e, edges, lut, lut_scale):
    """The number of row edges >= ``e`` (degrees): the table's guess, then exact
    comparisons (a binary search mispredicts its branches too often)."""
    t = (edges[0] - e) * lut_scale
    cnt = lut[np.int64(min(max(t, 0.0), len(lut) - 1.0))]
    cnt += edges[cnt] >= e
    while edges[cnt] >= e:
        cnt += 1
    while cnt > 0 and edges[cnt - 1] < e:
        cnt -= 1
    return cnt


@njit([(_in(t), _in(t), _in(t), _in(types.int64), _in(types.float64),
        _in(types.float64), _in(types.int64), types.float64, _in(types.float64),
        types.int64, types.int64, types.float64, types.float64, _out(types.int32),
        _out(types.int32), _out(types.int64), _out(types.float32), _out(types.boolean),
        _out(types.boolean), _out(types.int32))
       for t in _COORDS], cache=True, nogil=True)
def _place(x, y, z, ring, el, edges, lut, lut_scale, az, R, C, scale, offset,
           row, col, pixel, rng32, valid, out_of_fov, index):
    """Row, column, pixel, range and flags per point, and the nearest point per pixel.

    Rows from ``ring`` if it has one entry per point, else from the elevations ``el``
    (radians from :func:`_elevations`, recomputed with ``math.asin`` within
    ``_EDGE_MARGIN`` degrees of an edge; to degrees as ``np.degrees`` does) binned by
    ``edges`` (the row edges, then -inf) with the table ``lut`` / ``lut_scale`` of
    :func:`_row_lookup`. ``az`` is ``atan2(y, x) * scale + offset`` from
    :func:`_column_coordinates` (its floor is the column; recomputed with ``math.atan2``
    within ``_EDGE_MARGIN`` of an edge, so that every column is libm's). Points are
    visited in index order and a pixel changes hands only to a strictly nearer point, so
    a tie keeps the lowest index.
    """
    for p in range(index.size):
        index[p] = -1
    use_ring = len(ring) == len(x)
    for i in range(len(x)):
        xi, yi, zi = np.float64(x[i]), np.float64(y[i]), np.float64(z[i])
        r = math.sqrt(xi * xi + yi * yi + zi * zi)
        finite = math.isfinite(r)
        rng32[i] = np.float32(r) if finite else np.float32(np.nan)
        rw = -1
        if finite:
            if use_ring:
                if 0 <= ring[i] < R:
                    rw = ring[i]
            else:
                # row + 1 = the number of edges >= the elevation
                e = el[i] * _DEG
                cnt = _edges_above(e, edges, lut, lut_scale)
                if not (e - edges[cnt] > _EDGE_MARGIN
                        and (cnt == 0 or edges[cnt - 1] - e > _EDGE_MARGIN)):
                    e = math.asin(_elevation_sine(xi, yi, zi)) * _DEG     # libm's, exact
                    cnt = _edges_above(e, edges, lut, lut_scale)
                if 0 < cnt <= R:
                    rw = cnt - 1
        if rw < 0:
            row[i] = -1
            col[i] = -1
            pixel[i] = -1
            valid[i] = False
            out_of_fov[i] = finite
            continue
        u = az[i]
        f = math.floor(u)
        if not (_EDGE_MARGIN < u - f < 1.0 - _EDGE_MARGIN):     # near an edge, or NaN
            u = math.atan2(yi, xi) * scale
            u += offset
            f = math.floor(u)
        c = np.int64(f)
        if c >= C or c < 0:  # az = -pi lands on C -> 0; no division in the common case
            c %= C
        pv = rw * C + c
        row[i] = rw
        col[i] = c
        pixel[i] = pv
        valid[i] = True
        out_of_fov[i] = False
        j = index[pv]
        if j < 0:
            index[pv] = i
        else:
            xj, yj, zj = np.float64(x[j]), np.float64(y[j]), np.float64(z[j])
            if r < math.sqrt(xj * xj + yj * yj + zj * zj):
                index[pv] = i


@functools.lru_cache(maxsize=16)
def _row_lookup(cfg: RangeImageConfig) -> tuple[np.ndarray, np.ndarray, float]:
    """(edges followed by -inf, table, scale) for :func:`_place`: cell ``k`` of the table,
    elevations ``k / scale`` to ``(k + 1) / scale`` degrees below the top edge, holds the
    number of edges >= its upper end. Cells are about an eighth of the narrowest row (up
    to ``_LUT_MAX`` cells), so an elevation is at most one edge past its cell's count
    (mostly none): the kernel then compares exactly, the table only saves comparisons."""
    e = cfg.row_edges_deg
    span = float(e[0] - e[-1])
    cells = int(min(8.0 * span / float(np.min(e[:-1] - e[1:])), _LUT_MAX))  # >= 8
    scale = cells / span
    if not math.isfinite(scale):  # a subnormal span: one cell, the comparisons do it all
        cells, scale = 1, 0.0
    upper = e[0] - np.arange(cells) / scale if scale else e[:1]
    lut = np.searchsorted(-e, -upper, side="right").astype(np.int64)
    edges = np.r_[e, -np.inf]
    lut.flags.writeable = edges.flags.writeable = False
    return edges, lut, scale


def project(xyz, cfg: RangeImageConfig, ring=None) -> Projection:
    """Project ``xyz`` (N, 3) to the range image of ``cfg``.

    ``ring`` (N,) optional: the row of each point (ring 0 = top beam); rings outside
    ``[0, rows)`` are flagged out of the field of view. Without it, rows come from the
    points' elevations (see the module doc).
    """
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        if xyz.size == 0:
            xyz = xyz.reshape(0, 3)
        else:
            raise ValueError(f"xyz must have shape (N, 3), got {xyz.shape}")
    if xyz.dtype not in (np.dtype(np.float32), np.dtype(np.float64)):
        xyz = xyz.astype(np.float64)
    n = len(xyz)
    R, C = cfg.rows, cfg.cols
    x, y, z = (np.ascontiguousarray(xyz[:, k]) for k in range(3))
    edges, lut, lut_scale = _row_lookup(cfg)
    if ring is not None:
        ring = np.asarray(ring).reshape(-1)
        if len(ring) != n:
            raise ValueError(f"ring has {len(ring)} entries, xyz {n}")
        if ring.dtype.kind in "biu":
            # out-of-range values stay out of range (uint64 above 2^63 turns negative)
            ring = ring.astype(np.int64)
        else:
            with np.errstate(invalid="ignore"):
                ring = np.where((ring >= 0) & (ring < R), ring, -1).astype(np.int64)
        el = np.zeros(0)
    else:
        ring = np.zeros(0, dtype=np.int64)
        el = np.empty(n)
        _elevations(x, y, z, el)
    az = np.empty(n)
    scale, offset = -0.5 * C / np.pi, 0.5 * C
    _column_coordinates(x, y, scale, offset, az)
    row = np.empty(n, dtype=np.int32)
    col = np.empty(n, dtype=np.int32)
    pixel = np.empty(n, dtype=np.int64)
    rng = np.empty(n, dtype=np.float32)
    valid = np.empty(n, dtype=bool)
    out_of_fov = np.empty(n, dtype=bool)
    index = np.empty(R * C, dtype=np.int32)
    _place(x, y, z, ring, el, edges, lut, lut_scale, az, R, C, scale, offset,
           row, col, pixel, rng, valid, out_of_fov, index)
    return Projection(cfg=cfg, row=row, col=col, pixel=pixel, range=rng, valid=valid,
                      out_of_fov=out_of_fov, index=index.reshape(R, C))


# -- neighbourhoods -------------------------------------------------------------------


def shift(image, drow: int, dcol: int, fill=np.nan) -> np.ndarray:
    """``out[r, c] = image[r + drow, (c + dcol) mod cols]``; ``fill`` where ``r + drow``
    leaves the image (rows do not wrap, columns do). Trailing axes are carried along."""
    image = np.asarray(image)
    R = image.shape[0]
    rolled = np.roll(image, -dcol, axis=1) if dcol else image
    if drow == 0:
        return rolled.copy() if rolled is image else rolled
    out = np.empty_like(rolled, dtype=_fill_dtype(rolled.dtype, fill))
    if abs(drow) >= R:
        out[...] = fill
        return out
    if drow > 0:
        out[:R - drow] = rolled[drow:]
        out[R - drow:] = fill
    else:
        out[-drow:] = rolled[:R + drow]
        out[:-drow] = fill
    return out


def _size(size) -> tuple[int, int]:
    h, w = (size, size) if np.isscalar(size) else tuple(size)
    h, w = int(h), int(w)
    if h < 1 or w < 1 or h % 2 == 0 or w % 2 == 0:
        raise ValueError(f"window size must be odd and >= 1, got {size}")
    return h, w


def window_reduce(image, size, op: str = "sum", fill=None) -> np.ndarray:
    """Sum / min / max of ``image`` (rows, cols) over a centred ``size`` window
    (int or (height, width), odd), periodic in columns.

    Rows outside the image contribute ``fill`` (default: the neutral element, 0 / +inf /
    -inf). Separable: cost grows with height + width, not their product.
    """
    reducers = {"sum": (np.add, 0.0), "min": (np.minimum, np.inf), "max": (np.maximum, -np.inf)}
    if op not in reducers:
        raise ValueError(f"op must be one of {sorted(reducers)}, got {op!r}")
    ufunc, neutral = reducers[op]
    fill = neutral if fill is None else fill
    h, w = _size(size)
    image = np.asarray(image)
    if not np.issubdtype(image.dtype, np.floating):
        image = image.astype(np.float64)
    R, C = image.shape[:2]
    hw = w // 2
    if hw:
        # pad periodically, then accumulate shifted slices (no per-offset roll copy)
        padded = image.take(np.arange(-hw, C + hw) % C, axis=1)
        acc = padded[:, 0:C].copy()
        for d in range(1, w):
            ufunc(acc, padded[:, d:d + C], out=acc)
    else:
        acc = image.copy()
    hh = h // 2
    if hh:
        pad = np.full((hh,) + acc.shape[1:], fill, dtype=acc.dtype)
        padded = np.concatenate([pad, acc, pad], axis=0)
        out = padded[0:R].copy()
        for d in range(1, h):
            ufunc(out, padded[d:d + R], out=out)
        return out
    return acc


@dataclass
class WindowStats:
    """Per-pixel statistics over the non-missing pixels of a window (NaN if none)."""

    count: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    min: np.ndarray
    max: np.ndarray


def window_stats(image, size, valid=None) -> WindowStats:
    """Count, mean, population std, min and max of ``image`` (rows, cols) over a centred
    ``size`` window, periodic in columns, ignoring NaN pixels and pixels where ``valid``
    (rows, cols) is False. Statistics of windows without any pixel are NaN."""
    image = np.asarray(image)
    img = image.astype(np.float64) if not np.issubdtype(image.dtype, np.floating) else image
    ok = np.isfinite(img)
    if valid is not None:
        ok &= np.asarray(valid, dtype=bool)
    zero = np.where(ok, img, 0.0)
    cnt = window_reduce(ok.astype(img.dtype), size, "sum")
    s1 = window_reduce(zero, size, "sum")
    s2 = window_reduce(zero * zero, size, "sum")
    mn = window_reduce(np.where(ok, img, np.inf), size, "min")
    mx = window_reduce(np.where(ok, img, -np.inf), size, "max")
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = s1 / cnt
        var = np.maximum(s2 / cnt - mean * mean, 0.0)
    empty = cnt == 0
    std = np.sqrt(var)
    for a in (mean, std, mn, mx):
        a[empty] = np.nan
    return WindowStats(count=cnt, mean=mean, std=std, min=mn, max=mx)
