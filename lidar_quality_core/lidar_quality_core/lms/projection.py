"""Spherical projection of a lidar cloud to a range image, and range-image neighbourhoods.

The project's single projection module (numpy only): the reference segmenter's local
geometry features and LidarMetaSeg's image representation (paper eq. (1)-(3)) both use it.

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

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

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
    n = len(xyz)
    R, C = cfg.rows, cfg.cols
    x, y, z = (xyz[:, k].astype(np.float64) for k in range(3))
    with np.errstate(invalid="ignore", over="ignore"):
        rng = np.sqrt(x * x + y * y + z * z)
    finite = np.isfinite(rng)

    row = np.full(n, -1, dtype=np.int32)
    if ring is not None:
        ring = np.asarray(ring).reshape(-1)
        if len(ring) != n:
            raise ValueError(f"ring has {len(ring)} entries, xyz {n}")
        r_ok = finite & (ring >= 0) & (ring < R)
        row[r_ok] = ring[r_ok]
    else:
        with np.errstate(invalid="ignore", divide="ignore"):
            el = np.degrees(np.arcsin(np.clip(z / np.where(rng > 0, rng, 1.0), -1.0, 1.0)))
        # ascending copy of the decreasing edges: row r covers [e[r+1], e[r])
        neg = -cfg.row_edges_deg
        r_idx = np.searchsorted(neg, -el[finite], side="right") - 1
        r_idx[(r_idx < 0) | (r_idx >= R)] = -1
        row[finite] = r_idx
    valid = row >= 0
    out_of_fov = finite & ~valid

    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.arctan2(y, x)
        u *= -0.5 * C / np.pi
        u += 0.5 * C
    col = np.full(n, -1, dtype=np.int32)
    # az = -pi lands on C -> 0
    col[valid] = np.floor(u[valid]).astype(np.int32) % np.int32(C)
    vidx = np.flatnonzero(valid)
    pixel = np.full(n, -1, dtype=np.int64)
    vpix = row[vidx].astype(np.int64) * C + col[vidx]
    pixel[vidx] = vpix

    # Write every point to its pixel and read back: a point that does not find itself
    # lost its pixel to another one, so only those pixels need the nearest-point rule.
    index = np.full(R * C, -1, dtype=np.int32)
    index[vpix] = vidx
    lost = index[vpix] != vidx
    if lost.any():
        contested = np.zeros(R * C, dtype=bool)
        contested[vpix[lost]] = True
        shared = contested[vpix]
        sub, p = vidx[shared], vpix[shared]
        # per contested pixel the smallest range, then the lowest index among the points at
        # it: two unbuffered minima, linear in the points (two stable sorts cost 5x more
        # when most pixels are contested, as in a dense 250k-point scan)
        r_sub = rng[sub]
        best = np.full(R * C, np.inf)
        np.minimum.at(best, p, r_sub)
        win = r_sub == best[p]
        lowest = np.full(R * C, np.iinfo(np.int64).max)
        np.minimum.at(lowest, p[win], sub[win])
        index[contested] = lowest[contested]
    return Projection(cfg=cfg, row=row, col=col, pixel=pixel,
                      range=np.where(finite, rng, np.nan).astype(np.float32),
                      valid=valid, out_of_fov=out_of_fov, index=index.reshape(R, C))


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
