"""Multi-scale clustering of the non-ground points: connected components of a BEV
occupancy grid at several cell sizes.

Fine cells split sparse (far, dark, occluded) objects into fragments; coarse cells merge
neighbours (a pedestrian next to a pole, cars parked bumper to bumper). Running several
scales gives the detector several overlapping candidate point sets per object, which is
what makes its pre-NMS proposal sets informative. A cluster found identically at several
scales is kept once, with the number of scales that produced it (a stability cue).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
from scipy import ndimage

__all__ = ["ClusterConfig", "Clusters", "candidate_mask", "cluster_points", "group_reduce"]

_EIGHT = np.ones((3, 3), dtype=bool)


@dataclass(frozen=True)
class ClusterConfig:
    cell_sizes: tuple[float, ...] = (0.15, 0.25, 0.4, 0.7)  # BEV cells (m), finest first
    min_height: float = 0.2     # above ground: lower points are ground / curbs
    max_height: float = 3.8     # above ground: tree crowns and facades above are dropped
    max_range: float = 80.0     # BEV range of the points clustered (m)
    min_points: int = 4         # smaller components are noise
    max_extent: float = 13.0    # largest axis-aligned BEV side (m): walls, hedges are dropped

    def to_dict(self) -> dict:
        d = asdict(self)
        d["cell_sizes"] = list(self.cell_sizes)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "ClusterConfig":
        d = dict(d)
        if "cell_sizes" in d:
            d["cell_sizes"] = tuple(float(c) for c in d["cell_sizes"])
        return cls(**d)


@dataclass
class Clusters:
    """Clusters as CSR over point indices of the cloud.

    Points of cluster ``c`` are ``point_index[offsets[c]:offsets[c+1]]`` (ascending).
    ``scale``: index into ``cell_sizes`` of the finest scale producing the cluster;
    ``n_scales``: how many scales produced exactly this point set.
    """

    point_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    offsets: np.ndarray = field(default_factory=lambda: np.zeros(1, np.int64))
    scale: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    n_scales: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def __len__(self) -> int:
        return len(self.offsets) - 1

    @property
    def sizes(self) -> np.ndarray:
        return np.diff(self.offsets)

    @property
    def owner(self) -> np.ndarray:
        """(M,) cluster index of each entry of ``point_index``."""
        return np.repeat(np.arange(len(self)), self.sizes)

    def members(self, c: int) -> np.ndarray:
        return self.point_index[self.offsets[c]:self.offsets[c + 1]]


def candidate_mask(xyz: np.ndarray, height: np.ndarray, is_ground: np.ndarray,
                   cfg: ClusterConfig = ClusterConfig()) -> np.ndarray:
    """Points that take part in clustering: finite, off the ground, in the height band
    and BEV range."""
    with np.errstate(invalid="ignore"):
        r2 = xyz[:, 0].astype(np.float64) ** 2 + xyz[:, 1].astype(np.float64) ** 2
        return (~is_ground & (height >= cfg.min_height) & (height <= cfg.max_height)
                & (r2 <= cfg.max_range ** 2))


def group_reduce(ufunc, values: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """``ufunc.reduceat`` over non-empty CSR groups (all groups must be non-empty)."""
    if len(offsets) <= 1:
        return np.zeros((0,) + values.shape[1:], values.dtype)
    return ufunc.reduceat(values, offsets[:-1], axis=0)


def _label_scale(x: np.ndarray, y: np.ndarray, cell: float) -> np.ndarray:
    """Per point component label (0-based) of the 8-connected occupied cells; ``x``, ``y``
    are non-negative offsets from the points' lower corner."""
    inv = 1.0 / cell
    ix = (x * inv).astype(np.int32)
    iy = (y * inv).astype(np.int32)
    ny = int(iy.max()) + 1
    flat = ix * ny + iy
    grid = np.zeros((int(ix.max()) + 1) * ny, dtype=bool)
    grid[flat] = True
    lab, _ = ndimage.label(grid.reshape(-1, ny), structure=_EIGHT)
    return lab.ravel().take(flat) - 1


def cluster_points(xyz: np.ndarray, mask: np.ndarray,
                   cfg: ClusterConfig = ClusterConfig()) -> Clusters:
    """Cluster the ``mask`` points of ``xyz`` (N, 3) at every scale of ``cfg``."""
    idx = np.flatnonzero(mask)
    if len(idx) < cfg.min_points:
        return Clusters()
    # contiguous 1-D columns: numpy's axis reductions over (n, 2) arrays are slow
    x = xyz[idx, 0].astype(np.float64)
    y = xyz[idx, 1].astype(np.float64)
    x -= x.min()
    y -= y.min()
    parts_idx, parts_sizes, parts_scale = [], [], []
    for s, cell in enumerate(cfg.cell_sizes):
        lab = _label_scale(x, y, float(cell))
        # points ascending within a cluster; 16-bit keys get numpy's radix sort
        key = lab.astype(np.uint16) if lab.max(initial=0) < 1 << 16 else lab
        order = np.argsort(key, kind="stable")
        sl = lab[order]
        starts = np.flatnonzero(np.r_[True, sl[1:] != sl[:-1]])
        sizes = np.diff(np.r_[starts, len(sl)])
        px, py = x[order], y[order]
        ext = np.maximum(np.maximum.reduceat(px, starts) - np.minimum.reduceat(px, starts),
                         np.maximum.reduceat(py, starts) - np.minimum.reduceat(py, starts))
        ok = (sizes >= cfg.min_points) & (ext <= cfg.max_extent)
        keep_pt = np.repeat(ok, sizes)
        parts_idx.append(idx[order[keep_pt]])
        parts_sizes.append(sizes[ok])
        parts_scale.append(np.full(int(ok.sum()), s, np.int64))
    point_index = np.concatenate(parts_idx)
    sizes = np.concatenate(parts_sizes)
    scale = np.concatenate(parts_scale)
    if not len(sizes):
        return Clusters()
    offsets = np.zeros(len(sizes) + 1, np.int64)
    np.cumsum(sizes, out=offsets[1:])

    # Identical point sets across scales share size, first, last and index sum; within a
    # scale the components are disjoint (distinct first index), and unequal sets of
    # different scales agreeing on all four is vanishingly unlikely.
    first = point_index[offsets[:-1]]
    last = point_index[offsets[1:] - 1]
    total = np.add.reduceat(point_index, offsets[:-1])
    key = np.stack([sizes, first, last, total], axis=1)
    _, uniq, inv, counts = np.unique(key, axis=0, return_index=True, return_inverse=True,
                                     return_counts=True)
    uniq_sorted = np.sort(uniq)                      # keep the finest scale's copy, in order
    n_scales = counts[inv.reshape(-1)][uniq_sorted]
    keep_pt = np.zeros(len(sizes), bool)
    keep_pt[uniq_sorted] = True
    point_index = point_index[np.repeat(keep_pt, sizes)]
    sizes = sizes[uniq_sorted]
    offsets = np.zeros(len(sizes) + 1, np.int64)
    np.cumsum(sizes, out=offsets[1:])
    return Clusters(point_index=point_index, offsets=offsets, scale=scale[uniq_sorted],
                    n_scales=n_scales.astype(np.int64))
