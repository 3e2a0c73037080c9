"""The detector's front end: cloud -> candidate boxes with per-candidate features.

Ground estimation, multi-scale clustering of the points above it, and several box fits
per cluster (``box_fit.METHODS``; the line-of-sight fit only for sparse clusters). Every
(cluster, fit) pair is a candidate ("proposal"); its feature vector (``FEATURE_NAMES``)
describes the cluster's points and the fitted box, and is what the learned classifier and
box refinement see. Computed once per frame and shared by the reference detector and all
heads of the multi-head detector.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np

from .box_fit import METHODS, fit_boxes
from .clustering import ClusterConfig, Clusters, candidate_mask, cluster_points
from .ground import Ground, GroundConfig, estimate_ground

__all__ = ["FEATURE_NAMES", "FrontEndConfig", "Proposals", "compute_proposals"]

FEATURE_NAMES: tuple[str, ...] = (
    "n_points", "range", "density",
    "height_min", "height_max", "height_mean", "height_std",
    "frac_h_0_05", "frac_h_05_10", "frac_h_10_16", "frac_h_16_up",
    "intensity_mean", "intensity_std", "intensity_max",
    "elevation_span", "pca_ratio", "n_scales", "cell_size",
    "length", "width", "height", "area", "aspect", "edge_dist", "fit_method", "view_angle",
)
_HEIGHT_BINS = (0.5, 1.0, 1.6)


@dataclass(frozen=True)
class FrontEndConfig:
    ground: GroundConfig = field(default_factory=GroundConfig)
    cluster: ClusterConfig = field(default_factory=ClusterConfig)
    methods: tuple[str, ...] = METHODS
    n_angles: int = 12          # coarse yaw grid over [0, pi/2) of the rectangle criteria
    max_fit_points: int = 32    # points per cluster the yaw search looks at
    sight_max_points: int = 60  # the line-of-sight fit only for sparser clusters: a dense
    #                             cluster's outline says more than the viewing direction

    def to_dict(self) -> dict:
        return {"ground": asdict(self.ground), "cluster": self.cluster.to_dict(),
                "methods": list(self.methods), "n_angles": self.n_angles,
                "max_fit_points": self.max_fit_points, "sight_max_points": self.sight_max_points}

    @classmethod
    def from_dict(cls, d: dict) -> "FrontEndConfig":
        return cls(ground=GroundConfig(**d.get("ground", {})),
                   cluster=ClusterConfig.from_dict(d.get("cluster", {})),
                   methods=tuple(d.get("methods", METHODS)),
                   n_angles=int(d.get("n_angles", 12)),
                   max_fit_points=int(d.get("max_fit_points", 32)),
                   sight_max_points=int(d.get("sight_max_points", 60)))


@dataclass
class Proposals:
    """Candidates of one frame. ``boxes`` (P, 7) as fitted (centre, l >= w, yaw in
    [-pi/2, pi/2)); ``features`` (P, F) float32 in ``FEATURE_NAMES`` order; ``cluster``
    (P,) index into ``clusters``; ``method`` (P,) index into ``box_fit.METHODS``."""

    boxes: np.ndarray
    features: np.ndarray
    cluster: np.ndarray
    method: np.ndarray
    clusters: Clusters
    ground: Ground
    timings_ms: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.boxes)


def _cluster_features(xyz, height, intensity, cl: Clusters, cell_sizes) -> np.ndarray:
    """(C, 15) cluster-level features (FEATURE_NAMES[:18] minus the 3 box-dependent)."""
    pi = cl.point_index
    st = cl.offsets[:-1]
    n = cl.sizes.astype(np.float64)
    px, py, pz = (xyz[:, k].take(pi).astype(np.float64) for k in range(3))
    h = height[pi].astype(np.float64)
    it = intensity[pi].astype(np.float64)
    g = cl.owner

    def mean_std(v):
        m = np.add.reduceat(v, st) / n
        return m, np.sqrt(np.maximum(np.add.reduceat(v * v, st) / n - m * m, 0.0))

    h_mean, h_std = mean_std(h)
    i_mean, i_std = mean_std(it)
    bins = np.searchsorted(np.asarray(_HEIGHT_BINS), h, side="right")
    nb = len(_HEIGHT_BINS) + 1
    frac = np.bincount(g * nb + bins, minlength=len(n) * nb).reshape(len(n), nb) / n[:, None]
    rxy = np.hypot(px, py)
    el = np.degrees(np.arctan2(pz, rxy))
    el_span = np.maximum.reduceat(el, st) - np.minimum.reduceat(el, st)
    # BEV scatter eigenvalue ratio: ~0 for a wall / line, ~1 for a blob
    mx, my = np.add.reduceat(px, st) / n, np.add.reduceat(py, st) / n
    sz = cl.sizes
    dx, dy = px - np.repeat(mx, sz), py - np.repeat(my, sz)
    sxx = np.add.reduceat(dx * dx, st) / n
    syy = np.add.reduceat(dy * dy, st) / n
    sxy = np.add.reduceat(dx * dy, st) / n
    tr, det = sxx + syy, sxx * syy - sxy * sxy
    disc = np.sqrt(np.maximum(tr * tr / 4 - det, 0.0))
    l1, l2 = tr / 2 + disc, np.maximum(tr / 2 - disc, 0.0)
    pca_ratio = np.sqrt(l2 / np.maximum(l1, 1e-9))
    rng = np.hypot(mx, my)
    return np.column_stack([
        n, rng, n * rng * rng / 1000.0,
        np.minimum.reduceat(h, st), np.maximum.reduceat(h, st), h_mean, h_std, frac,
        i_mean, i_std, np.maximum.reduceat(it, st),
        el_span, pca_ratio, cl.n_scales.astype(np.float64),
        np.asarray(cell_sizes, np.float64)[cl.scale],
    ])


def compute_proposals(xyz, intensity, ring=None, cfg: FrontEndConfig = FrontEndConfig(),
                      ground: Ground | None = None) -> Proposals:
    """Candidates of one cloud ``xyz`` (N, 3) sensor frame, ``intensity`` (N,) in [0, 1].

    ``ring`` is accepted for interface compatibility; the features use the elevation span
    instead, so clouds without ring numbers work the same. ``ground``: a precomputed
    ground estimate of this cloud (else estimated here).
    """
    del ring
    t0 = time.perf_counter()
    xyz = np.asarray(xyz, np.float32)
    intensity = np.asarray(intensity, np.float32).reshape(-1)
    if ground is None:
        ground = estimate_ground(xyz, cfg.ground)
    t1 = time.perf_counter()
    mask = candidate_mask(xyz, ground.height, ground.is_ground, cfg.cluster)
    cl = cluster_points(xyz, mask, cfg.cluster)
    t2 = time.perf_counter()
    F = len(FEATURE_NAMES)
    if not len(cl):
        return Proposals(np.zeros((0, 7)), np.zeros((0, F), np.float32), np.zeros(0, np.int64),
                         np.zeros(0, np.int64), cl, ground,
                         {"ground": (t1 - t0) * 1e3, "cluster": (t2 - t1) * 1e3})
    pts = xyz[cl.point_index]
    gz = pts[:, 2] - ground.height[cl.point_index]
    boxes, cluster, method, edge = fit_boxes(pts, gz, cl.offsets, cfg.methods,
                                             n_angles=cfg.n_angles, max_points=cfg.max_fit_points)
    if "sight" in cfg.methods:
        ok = (method != METHODS.index("sight")) | (cl.sizes[cluster] < cfg.sight_max_points)
        boxes, cluster, method, edge = boxes[ok], cluster[ok], method[ok], edge[ok]
    t3 = time.perf_counter()
    cf = _cluster_features(xyz, ground.height, intensity, cl, cfg.cluster.cell_sizes)
    l, w, h = boxes[:, 3], boxes[:, 4], boxes[:, 5]
    az = np.arctan2(boxes[:, 1], boxes[:, 0])
    view = np.abs(np.sin(boxes[:, 6] - az))   # 0: seen end-on, 1: seen broadside
    feats = np.column_stack([cf[cluster], l, w, h, l * w, w / l, edge,
                             method.astype(np.float64), view]).astype(np.float32)
    t4 = time.perf_counter()
    return Proposals(boxes, feats, cluster, method, cl, ground,
                     {"ground": (t1 - t0) * 1e3, "cluster": (t2 - t1) * 1e3,
                      "box_fit": (t3 - t2) * 1e3, "features": (t4 - t3) * 1e3})
