"""Ground estimation: a height map of the ground under the cloud, and each point's height
above it.

The ground height of a BEV cell is its lowest return, cleaned by a grey opening (a minimum
then a maximum filter over ``window`` metres): cells whose lowest return is an object (a car
roof, the underside of a crown) and narrower than the window are replaced by their
surroundings, while slopes and curbs wider than the window are kept. Cells without returns
take the value of the nearest cell with returns. Used by the detector (ground removal) and
the segmenter (height above ground feature).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage


@dataclass(frozen=True)
class GroundConfig:
    cell: float = 1.0            # BEV cell size (m)
    extent: float = 80.0         # half-width of the grid around the sensor (m)
    window: float = 7.0          # opening window (m): wider than a car, narrower than a hill
    ground_tolerance: float = 0.25  # points this close above the ground are ground (m)


@dataclass
class Ground:
    """Per-point height above ground and ground mask, plus the height map."""

    height: np.ndarray        # (N,) z - ground height below the point (NaN: non-finite point)
    is_ground: np.ndarray     # (N,) bool
    height_map: np.ndarray    # (n, n) ground z per cell
    origin: float             # x / y of the map's lower cell corner
    cell: float


def estimate_ground(xyz: np.ndarray, cfg: GroundConfig = GroundConfig()) -> Ground:
    """Estimate the ground under ``xyz`` (N, 3) in the sensor frame (z up)."""
    xyz = np.asarray(xyz, dtype=np.float32)
    n_cells = int(np.ceil(2 * cfg.extent / cfg.cell))
    origin = -n_cells * cfg.cell / 2
    finite = np.isfinite(xyz).all(axis=1)
    ij = np.floor((xyz[:, :2] - origin) / cfg.cell)
    ij = np.clip(np.nan_to_num(ij, nan=0.0), 0, n_cells - 1).astype(np.int64)
    flat = ij[:, 0] * n_cells + ij[:, 1]

    low = np.full(n_cells * n_cells, np.inf, dtype=np.float32)
    _min_by_group(low, flat[finite], xyz[finite, 2])
    low = low.reshape(n_cells, n_cells)
    empty = ~np.isfinite(low)
    if empty.all():
        hmap = np.zeros_like(low)
    else:
        k = max(1, int(round(cfg.window / cfg.cell)) | 1)
        # empty cells must not win the minimum nor spread in the maximum
        eroded = ndimage.minimum_filter(np.where(empty, np.inf, low), size=k, mode="nearest")
        eroded = np.where(np.isfinite(eroded), eroded, np.nan)
        hmap = ndimage.maximum_filter(np.where(np.isnan(eroded), -np.inf, eroded), size=k,
                                      mode="nearest")
        hmap = np.minimum(hmap, np.where(empty, np.inf, low))  # never above a cell's lowest return
        missing = ~np.isfinite(hmap)
        if missing.any():
            idx = ndimage.distance_transform_edt(missing, return_distances=False, return_indices=True)
            hmap = hmap[idx[0], idx[1]]
    height = np.where(finite, xyz[:, 2] - hmap[ij[:, 0], ij[:, 1]], np.nan).astype(np.float32)
    return Ground(height=height, is_ground=finite & (height < cfg.ground_tolerance),
                  height_map=hmap.astype(np.float32), origin=origin, cell=cfg.cell)


def _min_by_group(out: np.ndarray, group: np.ndarray, values: np.ndarray) -> None:
    """``out[g] = min(out[g], values of group g)``, via one sort (ufunc.at is slow)."""
    if not len(group):
        return
    order = np.argsort(group, kind="stable")
    g = group[order]
    starts = np.flatnonzero(np.r_[True, g[1:] != g[:-1]])
    out[g[starts]] = np.minimum(out[g[starts]], np.minimum.reduceat(values[order], starts))
