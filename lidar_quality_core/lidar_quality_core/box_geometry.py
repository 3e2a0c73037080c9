"""Oriented 3D box geometry: corners, point-in-box membership, per-box reductions.

Boxes are float arrays (N, 7): ``x, y, z, l, w, h, yaw`` with ``(x, y, z)`` the box centre
(vision_msgs ``BoundingBox3D.center``), ``l`` along the heading axis, ``w`` along the local
y axis, ``yaw`` counter-clockwise about +z. Points are (M, 3) ``x, y, z``.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, types

from .kernel_types import array_in, array_out

__all__ = ["as_boxes", "bev_corners", "corners_3d", "points_in_boxes",
           "count_points_in_boxes", "segment_stats", "SegmentStats", "as_cloud",
           "inbox_point_stats"]

# Local (x, y) signs of the BEV corners, counter-clockwise: front-left, rear-left,
# rear-right, front-right.
_CORNER_SIGNS = np.array([[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [1.0, -1.0]])

# Grid limits for points_in_boxes: they bound memory whatever the box coordinates are.
_MAX_CELLS = 1 << 18          # cells in the dense cell table
_MAX_CELLS_PER_AXIS = 2048
_MAX_CELL_ENTRIES = 1 << 21   # (box, cell) incidences before the grid is coarsened
_BIG_BOX_CELLS = 96           # boxes wider than this many cells are tested brute force
_CELL_FACTOR = 0.25           # cell size relative to the median box BEV footprint


def as_boxes(boxes) -> np.ndarray:
    """``boxes`` as a C-contiguous float64 (N, 7) array (raises on a wrong shape)."""
    b = np.ascontiguousarray(boxes, dtype=np.float64)
    if b.ndim == 1 and b.size == 0:
        b = b.reshape(0, 7)
    if b.ndim != 2 or b.shape[1] != 7:
        raise ValueError(f"boxes must have shape (N, 7), got {b.shape}")
    return b


def _as_points(points) -> np.ndarray:
    p = np.asarray(points)
    if p.dtype.kind != "f":
        p = p.astype(np.float64)
    if p.ndim == 1 and p.size == 0:
        p = p.reshape(0, 3)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must have shape (M, 3), got {p.shape}")
    return p


def bev_corners(boxes) -> np.ndarray:
    """(N, 4, 2) BEV corners, counter-clockwise (front-left, rear-left, rear-right, front-right)."""
    b = as_boxes(boxes)
    c, s = np.cos(b[:, 6]), np.sin(b[:, 6])
    return _corners_cs(b, c, s)


def _corners_cs(b, c, s):
    """``bev_corners`` with precomputed cos / sin of the yaw."""
    hl, hw = 0.5 * b[:, 3], 0.5 * b[:, 4]
    ax, ay = c * hl, s * hl      # half heading axis
    bx, by = -s * hw, c * hw     # half lateral axis
    out = np.empty((len(b), 4, 2))
    for k, (sl, sw) in enumerate(_CORNER_SIGNS.tolist()):
        out[:, k, 0] = b[:, 0] + sl * ax + sw * bx
        out[:, k, 1] = b[:, 1] + sl * ay + sw * by
    return out


def corners_3d(boxes) -> np.ndarray:
    """(N, 8, 3) corners: 4 bottom then 4 top, each in ``bev_corners`` order."""
    b = as_boxes(boxes)
    xy = bev_corners(b)
    out = np.empty((len(b), 8, 3))
    out[:, :4, :2] = xy
    out[:, 4:, :2] = xy
    out[:, :4, 2] = (b[:, 2] - b[:, 5] / 2.0)[:, None]
    out[:, 4:, 2] = (b[:, 2] + b[:, 5] / 2.0)[:, None]
    return out


class _BoxTable(NamedTuple):
    """Per-box contiguous float64 columns used by the exact membership test."""

    cx: np.ndarray
    cy: np.ndarray
    cz: np.ndarray
    c: np.ndarray
    s: np.ndarray
    hl: np.ndarray
    hw: np.ndarray
    hh: np.ndarray
    ex: np.ndarray  # BEV axis-aligned half extents
    ey: np.ndarray


def _box_table(b: np.ndarray, margin: float):
    """(valid mask, gridable mask, BEV side, (10, N) columns in _BoxTable's order) with half
    sizes grown by ``margin``; side: twice the larger BEV half extent; gridable: valid, with
    a finite side and |centre| < 1e15 (``_inside_pairs``)."""
    with np.errstate(over="ignore", invalid="ignore"):
        c, s = np.cos(b[:, 6]), np.sin(b[:, 6])
    return _box_columns(b, c, s, float(margin))


@njit("Tuple((boolean[::1], boolean[::1], float64[::1], float64[:, ::1]))(float64[:, ::1], "
      "float64[::1], float64[::1], float64)", cache=True, nogil=True)
def _box_columns(b, c, s, margin):
    # One pass for what took some twenty numpy calls on a few hundred boxes (0.14 ms);
    # the same IEEE operations, so the same values.
    n = b.shape[0]
    valid = np.empty(n, np.bool_)
    gridable = np.empty(n, np.bool_)
    side = np.empty(n)
    cols = np.empty((10, n))
    for j in range(n):
        hl = b[j, 3] / 2.0 + margin
        hw = b[j, 4] / 2.0 + margin
        hh = b[j, 5] / 2.0 + margin
        ok = min(b[j, 3], b[j, 4], b[j, 5]) > 0.0 and min(hl, hw, hh) >= 0.0
        for k in range(7):
            ok = ok and np.isfinite(b[j, k])
        ok = ok and np.isfinite(hl) and np.isfinite(hw) and np.isfinite(hh)
        ac, as_ = abs(c[j]), abs(s[j])
        ex = ac * hl + as_ * hw
        ey = as_ * hl + ac * hw
        valid[j] = ok
        side[j] = 2.0 * (ex if ex >= ey or np.isnan(ex) else ey)
        # giant boxes (relative to a typical one) or absurd coordinates go brute force
        gridable[j] = (ok and np.isfinite(side[j]) and abs(b[j, 0]) < 1e15
                       and abs(b[j, 1]) < 1e15)
        cols[0, j], cols[1, j], cols[2, j] = b[j, 0], b[j, 1], b[j, 2]
        cols[3, j], cols[4, j] = c[j], s[j]
        cols[5, j], cols[6, j], cols[7, j] = hl, hw, hh
        cols[8, j], cols[9, j] = ex, ey
    return valid, gridable, side, cols


def _exact(px, py, pz, t: _BoxTable):
    """Inside mask for points paired element-wise with the boxes of table ``t``."""
    m = np.abs(pz - t.cz) <= t.hh
    dx = px - t.cx
    dy = py - t.cy
    lx = t.c * dx
    lx += t.s * dy
    np.abs(lx, out=lx)
    m &= lx <= t.hl
    ly = t.c * dy
    ly -= t.s * dx
    np.abs(ly, out=ly)
    m &= ly <= t.hw
    return m


def _inside_pairs(points, boxes, margin=0.0):
    """(point_idx, box_idx) int64 arrays of all inside pairs: the grid's pairs point-major,
    then those of boxes tested brute force, box by box; a box's points are ascending."""
    p = _as_points(points)
    b = as_boxes(boxes)
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    if len(p) == 0 or len(b) == 0 or not np.isfinite(margin):
        return empty
    valid, gridable, side, cols = _box_table(b, float(margin))
    if not valid.any():
        return empty
    out_pt, out_bx = [], []
    normal = np.zeros(0, np.int64)
    if gridable.any():
        # Grid only boxes of sane size and position; giant boxes (relative to a typical
        # one) or absurd coordinates go brute force below, so they cannot blow up the grid.
        sg = side[gridable]
        cs = _CELL_FACTOR * float(np.partition(sg, len(sg) // 2)[len(sg) // 2])  # ~median
        normal = np.flatnonzero(gridable & (side <= _BIG_BOX_CELLS * cs))
        if len(normal):
            _grid_pairs(p, cols, normal, cs, out_pt, out_bx)

    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    brute = valid.copy()  # a mask, not np.setdiff1d: its sort cost 0.36 ms a frame
    brute[normal] = False
    for j in np.flatnonzero(brute):
        # brute force, one box at a time (memory O(M)); only pathological inputs get here
        with np.errstate(invalid="ignore", over="ignore"):
            m = _exact(x, y, z, _BoxTable(*cols[:, j:j + 1]))
        out_pt.append(np.flatnonzero(m))
        out_bx.append(np.full(len(out_pt[-1]), j, dtype=np.int64))
    if not out_pt:
        return empty
    if len(out_pt) == 1:
        return out_pt[0], out_bx[0]
    return np.concatenate(out_pt), np.concatenate(out_bx)


def _grid_pairs(p, cols: np.ndarray, normal, cs, out_pt, out_bx):
    """Inside pairs of the ``normal`` boxes (``cols``: _box_table's columns) via a coarse BEV
    grid (appends to the lists)."""
    ftype = np.float32 if p.dtype == np.float32 else np.float64
    x0, y0, inv, nx, ny, cell_start, cell_cnt, cell_box, cell_rows = _cell_table(
        cols, np.ascontiguousarray(normal, dtype=np.int64), float(cs),
        float(np.finfo(ftype).eps), 1e-30 if ftype is np.float32 else 1e-200)
    if p.dtype != ftype:
        p = p.astype(ftype)
    pt, bx = _grid_kernel(p[:, 0], p[:, 1], p[:, 2], ftype(x0), ftype(y0), ftype(inv),
                          ftype(nx - 1), ftype(ny - 1), ny, cell_start, cell_cnt, cell_box,
                          cell_rows)
    out_pt.append(pt)
    out_bx.append(bx)


@njit("Tuple((int64[::1], int64[::1]))(int64[::1], int64[::1], int64)", cache=True, nogil=True)
def _group(keys, values, n):
    """``(offsets (n + 1,), values grouped by key)``: the values of key ``k`` are
    ``out[offsets[k]:offsets[k + 1]]``, in their input order (a stable counting sort)."""
    offsets = np.zeros(n + 1, np.int64)
    for k in keys:
        offsets[k + 1] += 1
    for k in range(n):
        offsets[k + 1] += offsets[k]
    fill = offsets[:n].copy()
    out = np.empty(len(values), np.int64)
    for i in range(len(values)):
        k = keys[i]
        out[fill[k]] = values[i]
        fill[k] += 1
    return offsets, out


@njit("Tuple((float64, float64, float64, int64, int64, int64[::1], int64[::1], int64[::1], "
      "float64[:, ::1]))(float64[:, ::1], int64[::1], float64, float64, float64)",
      cache=True, nogil=True)
def _cell_table(cols, normal, cs, eps, tiny):
    # The grid over the ``normal`` boxes (rows of ``cols``: _BoxTable's columns) and, per
    # cell, the boxes whose rotated rectangle may touch it: (x0, y0, 1 / cell size, nx, ny,
    # start, count, box, row) with the exact test's terms of each (cell, box) incidence in
    # one row (cx, cy, cz, cos, -sin, half l, w, h): a candidate reads one cache line.
    # One compiled pass for what were some forty numpy calls on a few hundred boxes.
    cx, cy, cz, c, s, hl, hw, hh, ex, ey = (cols[0], cols[1], cols[2], cols[3], cols[4],
                                            cols[5], cols[6], cols[7], cols[8], cols[9])
    n = len(normal)
    xmin, xmax, ymin, ymax = np.inf, -np.inf, np.inf, -np.inf
    for j in normal:
        xmin = min(xmin, cx[j] - ex[j])
        xmax = max(xmax, cx[j] + ex[j])
        ymin = min(ymin, cy[j] - ey[j])
        ymax = max(ymax, cy[j] + ey[j])
    wx, wy = xmax - xmin, ymax - ymin
    ax, ay = max(abs(xmin), abs(xmax)), max(abs(ymin), abs(ymax))
    # Slack covering the rounding of the point -> cell mapping (done in the points' dtype,
    # possibly float32, ``eps``) and of the exact test, so no inside pair is ever lost;
    # ``tiny``: 1 / cs must not overflow that dtype.
    cs = max(cs, wx / _MAX_CELLS_PER_AXIS, wy / _MAX_CELLS_PER_AXIS,
             np.sqrt(wx) * np.sqrt(wy) / np.sqrt(_MAX_CELLS), 1e-12 * max(ax, ay), tiny)
    tol = 8.0 * eps * (ax + ay + 4.0 * cs) + 1e-300
    ix0 = np.empty(n, np.int64)
    ix1 = np.empty(n, np.int64)
    iy0 = np.empty(n, np.int64)
    iy1 = np.empty(n, np.int64)
    while True:
        inv = 1.0 / cs
        # One empty margin cell on each side absorbs clamped far / NaN points.
        nx = int(np.ceil(wx * inv)) + 3
        ny = int(np.ceil(wy * inv)) + 3
        x0, y0 = xmin - cs, ymin - cs
        tot = 0
        for k in range(n):
            j = normal[k]
            ix0[k] = int(min(max(np.floor((cx[j] - ex[j] - tol - x0) * inv), 0.0), nx - 1.0))
            ix1[k] = int(min(max(np.floor((cx[j] + ex[j] + tol - x0) * inv), 0.0), nx - 1.0))
            iy0[k] = int(min(max(np.floor((cy[j] - ey[j] - tol - y0) * inv), 0.0), ny - 1.0))
            iy1[k] = int(min(max(np.floor((cy[j] + ey[j] + tol - y0) * inv), 0.0), ny - 1.0))
            tot += (ix1[k] - ix0[k] + 1) * (iy1[k] - iy0[k] + 1)
        if tot <= max(_MAX_CELL_ENTRIES, 16 * n):
            break
        cs *= 2.0  # many mid-size boxes: coarsen until the incidence table is bounded

    # The (box, cell) incidences of each box's axis-aligned rectangle, minus the cells the
    # rotated rectangle misses (separating axes = box axes, with slack), then grouped by
    # cell in box order.
    ent_cell = np.empty(tot, np.int64)
    ent_box = np.empty(tot, np.int64)
    m = 0
    for k in range(n):
        j = normal[k]
        ce, se = c[j], s[j]
        r = 0.5 * cs * (abs(ce) + abs(se)) + 2.0 * tol
        for gx in range(ix0[k], ix1[k] + 1):
            ccx = x0 + (gx + 0.5) * cs - cx[j]
            for gy in range(iy0[k], iy1[k] + 1):
                ccy = y0 + (gy + 0.5) * cs - cy[j]
                if (abs(ce * ccx + se * ccy) <= hl[j] + r
                        and abs(ce * ccy - se * ccx) <= hw[j] + r):
                    ent_cell[m] = gx * ny + gy
                    ent_box[m] = j
                    m += 1
    offsets, box = _group(ent_cell[:m], ent_box[:m], nx * ny)
    rows = np.empty((m, 8))
    for q in range(m):
        j = box[q]
        rows[q, 0], rows[q, 1], rows[q, 2], rows[q, 3] = cx[j], cy[j], cz[j], c[j]
        rows[q, 4], rows[q, 5], rows[q, 6], rows[q, 7] = -s[j], hl[j], hw[j], hh[j]
    return x0, y0, inv, nx, ny, offsets[:-1].copy(), offsets[1:] - offsets[:-1], box, rows


def _kernel_sig(f):
    # the points may be read-only views into a message (lmd_ros: no copy of the cloud)
    pts = array_in(f, 1, "A")
    return types.Tuple((array_out(types.int64), array_out(types.int64)))(
        pts, pts, pts, f, f, f, f, f, types.int64, array_out(types.int64),
        array_out(types.int64), array_out(types.int64), array_out(types.float64, 2))


@njit([_kernel_sig(types.float32), _kernel_sig(types.float64)], cache=True, nogil=True)
def _grid_kernel(px, py, pz, x0, y0, inv, hx, hy, ny, cell_start, cell_cnt, cell_box, rows):
    # Two passes: each point's cell (in the points' dtype, as the grid's slack assumes;
    # clamped to the margin cells ``hx``, ``hy`` without a branch, NaN to 0) and the
    # number of candidates, keeping a list of the points whose cell holds a box (a
    # fifth of a typical cloud); then the exact test of those against the incidences of
    # their cell (``rows``). Counting first sizes the outputs exactly: growing them as
    # candidates came (copies, and fresh pages each frame) cost more than the tests.
    # Pairs come out point-major. The local coordinates are rounded exactly as in _exact
    # (c dx + s dy, c dy - s dx): a point on a face gets the same verdict on both paths.
    # Each candidate is written and kept only if inside (no branch on the verdict: a third
    # of the candidates are inside, a branch the CPU cannot predict).
    n = px.shape[0]
    zero = hx - hx
    sel = np.empty(n, np.int64)
    sel_cell = np.empty(n, np.int64)
    total = 0
    k = 0
    for i in range(n):
        fx = (px[i] - x0) * inv
        fy = (py[i] - y0) * inv
        fx = fx if fx > zero else zero
        fx = fx if fx < hx else hx
        fy = fy if fy > zero else zero
        fy = fy if fy < hy else hy
        cell = int(fx) * ny + int(fy)
        m = cell_cnt[cell]
        sel[k] = i
        sel_cell[k] = cell
        total += m
        k += m > 0
    out_pt = np.empty(total, np.int64)
    out_bx = np.empty(total, np.int64)
    q0 = 0
    for j in range(k):
        i = sel[j]
        cell = sel_cell[j]
        x, y, z = np.float64(px[i]), np.float64(py[i]), np.float64(pz[i])
        s0 = cell_start[cell]
        for q in range(s0, s0 + cell_cnt[cell]):
            r = rows[q]
            dx = x - r[0]
            dy = y - r[1]
            inside = ((abs(dx * r[3] - dy * r[4]) <= r[5]) & (abs(dx * r[4] + dy * r[3]) <= r[6])
                      & (abs(z - r[2]) <= r[7]))
            out_pt[q0] = i
            out_bx[q0] = cell_box[q]
            q0 += inside
    return out_pt[:q0], out_bx[:q0]


def points_in_boxes(points, boxes, margin: float = 0.0):
    """CSR membership ``(offsets (N+1,), point_index int64)``: points of box ``b`` are
    ``point_index[offsets[b]:offsets[b+1]]`` (ascending).

    Inside means ``|local x| <= l/2 + margin``, same for ``w`` and ``h`` (boundary inclusive).
    A point may be in several boxes. NaN/inf points are never inside; boxes with a
    non-finite value or a non-positive size contain nothing.
    """
    n = len(as_boxes(boxes))
    pt, bx = _inside_pairs(points, boxes, margin)
    # Pairs come out point-major: grouped by box in a stable counting sort, the points of
    # each box stay ascending.
    return _group(np.ascontiguousarray(bx, np.int64), np.ascontiguousarray(pt, np.int64), n)


def count_points_in_boxes(points, boxes, margin: float = 0.0) -> np.ndarray:
    """(N,) int64 number of points inside each box (same rule as ``points_in_boxes``)."""
    n = len(as_boxes(boxes))
    _, bx = _inside_pairs(points, boxes, margin)
    return np.bincount(bx, minlength=n).astype(np.int64)


class SegmentStats(NamedTuple):
    count: np.ndarray  # (N,) int64
    min: np.ndarray    # (N,) float64, 0 for empty boxes
    max: np.ndarray
    mean: np.ndarray
    std: np.ndarray    # population std


def segment_stats(values, offsets, point_index) -> SegmentStats:
    """Per-box count / min / max / mean / std of per-point ``values`` over a CSR membership
    (sums in membership order)."""
    offsets = np.asarray(offsets, dtype=np.int64)
    idx = np.ascontiguousarray(np.asarray(point_index, dtype=np.int64)[offsets[0]:offsets[-1]])
    cnt = np.diff(offsets)
    box = np.repeat(np.arange(len(cnt), dtype=np.int64), cnt)
    return SegmentStats(*_pair_stats(_stat_values(values), idx, box, len(cnt), False))


def _stat_values(values) -> np.ndarray:
    v = np.asarray(values).reshape(-1)
    return v if v.dtype in (np.float32, np.float64) else v.astype(np.float64)


def _stats_sig(f):
    # the values may be a read-only, unaligned view into a message's records
    return types.Tuple((array_out(types.int64),) + (array_out(types.float64),) * 4)(
        array_in(f, 1, "A", aligned=False), array_in(types.int64), array_in(types.int64),
        types.int64, types.boolean)


@njit([_stats_sig(types.float32), _stats_sig(types.float64)], cache=True, nogil=True)
def _pair_stats(values, pt, box, n, finite_only):
    # Per box over (point, box) pairs in any order: count, min, max, mean and population
    # std (two passes: the mean, then the squared deviations), each box's sums in the
    # order its pairs come; a box without values gets zeros. ``finite_only``: pairs whose
    # value is NaN / inf are left out (else they propagate). The numpy chain it replaces
    # (a gather, four reduceat, a repeat; 0.4 ms on 500 boxes) summed pairwise: the last
    # bit of a mean can differ from it.
    cnt = np.zeros(n, np.int64)
    lo = np.full(n, np.inf)
    hi = np.full(n, -np.inf)
    total = np.zeros(n)
    vals = np.empty(len(pt))  # contiguous for the second pass
    for k in range(len(pt)):
        v = np.float64(values[pt[k]])
        vals[k] = v
        if np.isfinite(v) or not finite_only:
            b = box[k]
            lo[b] = v if v < lo[b] or np.isnan(v) else lo[b]  # NaN sticks, as in np.minimum
            hi[b] = v if v > hi[b] or np.isnan(v) else hi[b]
            total[b] += v
            cnt[b] += 1
    mean = np.zeros(n)
    for b in range(n):
        if cnt[b]:
            mean[b] = total[b] / cnt[b]
        else:
            lo[b] = hi[b] = 0.0
    dev = np.zeros(n)
    for k in range(len(pt)):
        v = vals[k]
        if np.isfinite(v) or not finite_only:
            d = v - mean[box[k]]
            dev[box[k]] += d * d
    std = np.zeros(n)
    for b in range(n):
        if cnt[b]:
            std[b] = np.sqrt(dev[b] / cnt[b])
    return cnt, lo, hi, mean, std


def _usable_count(points, intensity) -> int:
    """The points whose x, y, z and intensity are finite."""
    # Any NaN / inf makes the sum non-finite; an overflowing sum of finite values only
    # sends us to the exact check below.
    if np.isfinite(np.sum(points)) and np.isfinite(np.sum(intensity)):
        return len(points)
    ok = np.isfinite(intensity)
    for c in range(3):
        ok &= np.isfinite(points[:, c])
    return int(np.count_nonzero(ok))


def as_cloud(points, intensity) -> tuple[np.ndarray, np.ndarray]:
    """``(points (M, 3) float, intensity (M,))``; ``ValueError`` when the lengths differ."""
    pts = np.asarray(points)
    if pts.dtype.kind != "f":
        pts = pts.astype(np.float64)
    pts = pts.reshape(-1, 3)
    inten = np.asarray(intensity).reshape(-1)
    if len(inten) != len(pts):
        raise ValueError(f"intensity has {len(inten)} entries for {len(pts)} points")
    return pts, inten


def inbox_point_stats(points, intensity, boxes, n_usable: int | None = None
                      ) -> tuple[SegmentStats, int]:
    """Per box, the usable points inside it and their intensity statistics
    (:func:`segment_stats`: count, min, max, mean, std; 0 for an empty box), and the
    cloud's number of usable points (x, y, z and intensity finite). The in-box point
    quantities of LidarMetaDetect (P, Phi = P / usable, reflectance max / mean / std),
    shared with LiDAR-MIMO's point features of merged boxes. ``n_usable``: that number
    when the caller has counted it (``pointcloud.padding_counts`` over a cloud whose
    padding no box contains), not counted again."""
    pts, inten = as_cloud(points, intensity)
    if n_usable is None:
        n_usable = _usable_count(pts, inten)
    # Points without finite coordinates are inside no box; of the others, those without a
    # finite intensity are left out of the statistics (and the count).
    pt, box = _inside_pairs(pts, boxes)
    return SegmentStats(*_pair_stats(_stat_values(inten), pt, box, len(as_boxes(boxes)),
                                     True)), int(n_usable)
