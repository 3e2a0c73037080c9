"""Vectorized ray casting against :class:`~lidar_sim.primitives.Primitives`.

``cast`` returns the nearest hit of every ray against the ground plane, oriented boxes,
closed vertical cylinders and axis-aligned ellipsoids (porous: a ray passes through an
ellipsoid with probability ``porosity``). Occlusion is simply the nearest hit.

Speed comes from culling, not from testing every ray against every primitive: rays are
sorted into thin elevation bands, azimuth-sorted within each band, and every primitive
covers a contiguous run of sorted rays per band (its azimuth interval seen from the
origin, split at the +-pi seam, or the full circle when its footprint contains the
origin) and only bands within its elevation interval. Exact intersections are then
computed for those (ray, primitive) pairs only. ``cull=False`` tests all pairs (the
reference the tests compare against); both paths give bit-identical results.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .primitives import Primitives

KIND_NONE, KIND_GROUND, KIND_BOX, KIND_CYLINDER, KIND_ELLIPSOID = 0, 1, 2, 3, 4

#: hits closer than this (metres) are ignored, so a ray leaving a surface does not hit it
T_EPS = 1e-6
# Culling intervals are widened by this (radians): culling may only ever be conservative.
_ANG_MARGIN = 1e-6
_CODE_SHIFT = 32  # winner code = kind << 32 | index, so ties resolve the same in any order


@dataclass
class Hits:
    """Nearest hit per ray (arrays of length R, in the order of the input rays).

    ``t`` range in metres along the unit ray (inf: no hit within max_range); ``kind``
    KIND_* (0 none); ``index`` primitive index within its kind (-1 none; 0 for ground);
    ``normal`` (R, 3) unit surface normal facing the ray origin (zeros: no hit);
    ``semantic`` / ``instance`` / ``reflectivity`` from the primitive or ground region
    (-1 / 0 / 0.0 for no hit).
    """

    t: np.ndarray
    kind: np.ndarray
    index: np.ndarray
    normal: np.ndarray
    semantic: np.ndarray
    instance: np.ndarray
    reflectivity: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        return self.kind > 0


# ---------------------------------------------------------------------------------------
# Per-primitive set-up (depends on the origin) and per-pair kernels. The same float
# operations run in the culled and brute-force paths, which keeps them bit-identical.
# ---------------------------------------------------------------------------------------

def _box_params(b: np.ndarray, o: np.ndarray) -> list[np.ndarray]:
    """Box frame set-up: cos, sin of yaw and the slab bounds relative to the origin."""
    c, s = np.cos(b[:, 6]), np.sin(b[:, 6])
    rx, ry, rz = o[..., 0] - b[:, 0], o[..., 1] - b[:, 1], o[..., 2] - b[:, 2]
    ox = c * rx + s * ry
    oy = c * ry - s * rx
    hx, hy, hz = 0.5 * b[:, 3], 0.5 * b[:, 4], 0.5 * b[:, 5]
    return [c, s, -hx - ox, hx - ox, -hy - oy, hy - oy, -hz - rz, hz - rz]


def _box_t(p, dx, dy, dz):
    c, s, lox, hix, loy, hiy, loz, hiz = p
    ix = 1.0 / (c * dx + s * dy)
    iy = 1.0 / (c * dy - s * dx)
    iz = 1.0 / dz
    # fmin/fmax ignore the NaN of 0 * inf (ray parallel to a slab, origin on its plane)
    a, b = lox * ix, hix * ix
    tn, tf = np.fmin(a, b), np.fmax(a, b)
    a, b = loy * iy, hiy * iy
    tn = np.fmax(tn, np.fmin(a, b))
    tf = np.fmin(tf, np.fmax(a, b))
    a, b = loz * iz, hiz * iz
    tn = np.fmax(tn, np.fmin(a, b))
    tf = np.fmin(tf, np.fmax(a, b))
    t = np.where(tn > T_EPS, tn, tf)  # origin inside: the exit face is the hit
    t[~((tn <= tf) & (tf > T_EPS))] = np.inf
    return t


def _cyl_params(cy: np.ndarray, o: np.ndarray) -> list[np.ndarray]:
    ox, oy = o[..., 0] - cy[:, 0], o[..., 1] - cy[:, 1]
    r2 = cy[:, 4] * cy[:, 4]
    return [ox, oy, ox * ox + oy * oy - r2, cy[:, 2] - o[..., 2], cy[:, 3] - o[..., 2], r2]


def _cyl_t(p, dx, dy, dz):
    """Closed cylinder: both side roots and both caps, nearest valid one."""
    ox, oy, cc, zlo, zhi, r2 = p
    a = dx * dx + dy * dy
    b = ox * dx + oy * dy
    disc = b * b - a * cc
    sq = np.sqrt(np.maximum(disc, 0.0))
    ia = 1.0 / a
    best = np.full(a.shape, np.inf)
    side_ok = (disc >= 0.0) & (a > 1e-18)
    for t in ((-b - sq) * ia, (-b + sq) * ia):
        z = t * dz
        ok = side_ok & (t > T_EPS) & (z >= zlo) & (z <= zhi)
        np.minimum(best, np.where(ok, t, np.inf), out=best)
    idz = 1.0 / dz
    for zc in (zhi, zlo):
        t = zc * idz
        px, py = ox + t * dx, oy + t * dy
        ok = (t > T_EPS) & (px * px + py * py <= r2)
        np.minimum(best, np.where(ok, t, np.inf), out=best)
    return best


def _ell_params(e: np.ndarray, o: np.ndarray) -> list[np.ndarray]:
    irx, iry, irz = 1.0 / e[:, 3], 1.0 / e[:, 4], 1.0 / e[:, 5]
    ox = (o[..., 0] - e[:, 0]) * irx
    oy = (o[..., 1] - e[:, 1]) * iry
    oz = (o[..., 2] - e[:, 2]) * irz
    return [ox, oy, oz, irx, iry, irz, ox * ox + oy * oy + oz * oz - 1.0]


def _ell_t(p, dx, dy, dz):
    """Scaled unit sphere: the ray in ellipsoid-normalised coordinates."""
    ox, oy, oz, irx, iry, irz, cc = p
    ux, uy, uz = dx * irx, dy * iry, dz * irz
    a = ux * ux + uy * uy + uz * uz
    b = ox * ux + oy * uy + oz * uz
    disc = b * b - a * cc
    sq = np.sqrt(np.maximum(disc, 0.0))
    ia = 1.0 / a
    t1 = (-b - sq) * ia
    t = np.where(t1 > T_EPS, t1, (-b + sq) * ia)
    t[~((disc >= 0.0) & (t > T_EPS))] = np.inf
    return t


def _mix64(x: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser (uint64 arrays wrap silently)."""
    x = x ^ (x >> np.uint64(30))
    x = x * np.uint64(0xBF58476D1CE4E5B9)
    x = x ^ (x >> np.uint64(27))
    x = x * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


def _pair_uniform(seed: int, ray: np.ndarray, prim: np.ndarray) -> np.ndarray:
    """Uniform [0, 1) per (ray, primitive) pair, independent of evaluation order, so the
    porosity draw is the same whichever path (or chunking) produced the pair."""
    x = _mix64(ray.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15) + np.uint64(seed))
    x = _mix64(x ^ (prim.astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F) + np.uint64(1)))
    return (x >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)


@dataclass
class _Kind:
    kind: int
    rows: np.ndarray  # primitive rows (n, k)
    params: list  # per-primitive set-up for the single origin (None: per-ray origins)
    setup: object
    kernel: object
    porosity: np.ndarray | None = None


def _kinds(prims: Primitives, o: np.ndarray | None) -> list[_Kind]:
    out = []
    for kind, rows, setup, kernel in (
            (KIND_BOX, prims.boxes, _box_params, _box_t),
            (KIND_CYLINDER, prims.cylinders, _cyl_params, _cyl_t),
            (KIND_ELLIPSOID, prims.ellipsoids, _ell_params, _ell_t)):
        rows = np.asarray(rows, dtype=np.float64)
        if len(rows) == 0:
            continue
        params = None if o is None else setup(rows, o)
        por = None
        if kind == KIND_ELLIPSOID:
            por = np.asarray(prims.ellipsoid_porosity, dtype=np.float64)
            if not np.any(por > 0):
                por = None
        out.append(_Kind(kind, rows, params, setup, kernel, por))
    return out


# ---------------------------------------------------------------------------------------
# Culling geometry: azimuth intervals and elevation bounds of each primitive
# ---------------------------------------------------------------------------------------

def _footprint(k: _Kind, o: np.ndarray):
    """(centre azimuth, lo, hi offsets from it, rho_min, rho_max, inside, zmin, zmax)."""
    r = k.rows
    if k.kind == KIND_BOX:
        c, s = np.cos(r[:, 6]), np.sin(r[:, 6])
        hx, hy = 0.5 * r[:, 3], 0.5 * r[:, 4]
        rx, ry = r[:, 0] - o[0], r[:, 1] - o[1]
        # origin in the box frame
        bx, by = -(c * rx + s * ry), -(c * ry - s * rx)
        ex, ey = np.maximum(np.abs(bx) - hx, 0.0), np.maximum(np.abs(by) - hy, 0.0)
        rho_min = np.hypot(ex, ey)
        rho_max = np.hypot(np.abs(bx) + hx, np.abs(by) + hy)
        phc = np.arctan2(ry, rx)
        lo = np.full(len(r), np.inf)
        hi = np.full(len(r), -np.inf)
        for sx in (-1.0, 1.0):
            for sy in (-1.0, 1.0):
                kx, ky = rx + c * sx * hx - s * sy * hy, ry + s * sx * hx + c * sy * hy
                d = np.mod(np.arctan2(ky, kx) - phc + np.pi, 2 * np.pi) - np.pi
                lo, hi = np.minimum(lo, d), np.maximum(hi, d)
        inside = (ex <= 1e-9) & (ey <= 1e-9)
        zmin, zmax = r[:, 2] - 0.5 * r[:, 5], r[:, 2] + 0.5 * r[:, 5]
    else:
        rad = r[:, 4] if k.kind == KIND_CYLINDER else np.maximum(r[:, 3], r[:, 4])
        rx, ry = r[:, 0] - o[0], r[:, 1] - o[1]
        d = np.hypot(rx, ry)
        phc = np.arctan2(ry, rx)
        inside = d <= rad * (1 + 1e-9) + 1e-9
        half = np.arcsin(np.minimum(rad / np.maximum(d, 1e-300), 1.0))
        lo, hi = -half, half
        rho_min, rho_max = np.maximum(d - rad, 0.0), d + rad
        if k.kind == KIND_CYLINDER:
            zmin, zmax = r[:, 2], r[:, 3]
        else:
            zmin, zmax = r[:, 2] - r[:, 5], r[:, 2] + r[:, 5]
    rho_min = np.where(inside, 0.0, rho_min)
    return phc, lo, hi, rho_min, rho_max, inside, zmin, zmax


def _intervals(k: _Kind, o: np.ndarray, ground_z: float, max_range: float):
    """Azimuth/elevation intervals per primitive: (prim, a0, a1, e0, e1), a in [-pi, pi]."""
    phc, lo, hi, rho_min, rho_max, inside, zmin, zmax = _footprint(k, o)
    oz = o[2]
    if np.isfinite(ground_z) and oz > ground_z:
        zmin = np.maximum(zmin, ground_z)  # below the ground: always occluded by it
    keep = (zmin <= zmax) & (rho_min <= max_range)
    dz_hi, dz_lo = zmax - oz, zmin - oz
    e1 = np.arctan2(dz_hi, np.where(dz_hi >= 0, rho_min, rho_max)) + _ANG_MARGIN
    e0 = np.arctan2(dz_lo, np.where(dz_lo <= 0, rho_min, rho_max)) - _ANG_MARGIN
    a0 = np.where(inside, -np.pi, phc + lo - _ANG_MARGIN)
    a1 = np.where(inside, np.pi, phc + hi + _ANG_MARGIN)
    full = inside | (a1 - a0 >= 2 * np.pi)
    a0, a1 = np.where(full, -np.pi, a0), np.where(full, np.pi, a1)
    idx = np.flatnonzero(keep)
    a0, a1, e0, e1 = a0[idx], a1[idx], e0[idx], e1[idx]
    # split at the seam: the part beyond +-pi wraps to the other end
    lw, hw = a0 < -np.pi, a1 > np.pi
    parts = [(idx, np.maximum(a0, -np.pi), np.minimum(a1, np.pi), e0, e1),
             (idx[lw], a0[lw] + 2 * np.pi, np.full(lw.sum(), np.pi), e0[lw], e1[lw]),
             (idx[hw], np.full(hw.sum(), -np.pi), a1[hw] - 2 * np.pi, e0[hw], e1[hw])]
    return [np.concatenate(x) for x in zip(*parts)]


# ---------------------------------------------------------------------------------------
# The caster
# ---------------------------------------------------------------------------------------

def _ground_t(dz, oz, ground_z):
    t = np.full(dz.shape, np.inf)
    if ground_z is None or not np.isfinite(ground_z):
        return t
    down = dz < 0
    with np.errstate(divide="ignore", invalid="ignore"):
        tg = (ground_z - oz) / dz
    ok = down & (tg > T_EPS)
    t[ok] = tg[ok]
    return t


class _Reducer:
    """Running nearest-hit per ray plus the candidate pairs that might win."""

    def __init__(self, best: np.ndarray):
        self.best = best
        self.rays, self.ts, self.codes = [], [], []

    def add(self, ray: np.ndarray, t: np.ndarray, code: np.ndarray):
        # <=, not <: every pair tied with the final minimum must stay a candidate
        m = t <= self.best[ray]
        ray, t, code = ray[m], t[m], code[m]
        np.minimum.at(self.best, ray, t)
        self.rays.append(ray)
        self.ts.append(t)
        self.codes.append(code)

    def winners(self, code: np.ndarray) -> np.ndarray:
        """Largest winning code per ray; ``code`` holds the ground's (or 0) initially,
        which any primitive code exceeds (kind > KIND_GROUND)."""
        if self.rays:
            ray, t, c = (np.concatenate(x) for x in (self.rays, self.ts, self.codes))
            w = t == self.best[ray]
            ray, c = ray[w], c[w]
            np.maximum.at(code, ray, c)
        return code


def _porous(k: _Kind, t, ray_orig, prim, seed):
    if k.porosity is None:
        return t
    h = np.flatnonzero(np.isfinite(t))
    thru = _pair_uniform(seed, ray_orig[h], prim[h]) < k.porosity[prim[h]]
    t[h[thru]] = np.inf
    return t


def cast(prims: Primitives, origin, dirs, max_range: float = np.inf, rng=None, *,
         cull: bool = True, chunk_pairs: int = 1 << 15) -> Hits:
    """Nearest hit of each ray ``origin + t * dir`` (t > 0, t <= max_range).

    ``origin``: (3,) for all rays, or (R, 3) per ray (per-ray origins that differ are
    cast brute force, O(rays x primitives): meant for small ray sets). ``dirs`` (R, 3),
    normalised here, so ``t`` is metric (zero or non-finite directions never hit).
    ``prims.ground_z`` None or +-inf: no ground. ``rng`` (Generator, int seed, or None =
    seed 0) decides the porous-ellipsoid pass-throughs, once per (ray, ellipsoid) pair.
    ``cull=False`` disables culling (reference path for tests); ``chunk_pairs`` bounds
    the pairs intersected at once (small chunks stay in cache: faster, not just leaner).
    """
    d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    n = np.sqrt(np.einsum("ij,ij->i", d, d))
    bad = ~(np.isfinite(n) & (n > 0))
    if bad.any():  # zero / non-finite directions: cast straight up, reported as misses
        d, n = d.copy(), n.copy()
        d[bad], n[bad] = (0.0, 0.0, 1.0), 1.0
    d = d / n[:, None]
    R = len(d)
    o = np.asarray(origin, dtype=np.float64)
    if o.ndim == 2 and len(o) and np.all(o == o[0]):
        o = o[0]
    single = o.ndim == 1
    if isinstance(rng, np.random.Generator):
        seed = int(rng.integers(0, 2**63 - 1))
    else:
        seed = 0 if rng is None else int(rng) % (1 << 63)
    gz = prims.ground_z
    gz = np.inf if gz is None else float(gz)
    max_range = float(max_range)

    oz = o[2] if single else o[:, 2]
    tg = _ground_t(d[:, 2], oz, gz)
    ground = tg <= max_range
    kinds = _kinds(prims, o if single else None)

    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if single and cull and kinds and R:
            best, code, order = _cast_culled(kinds, o, d, tg, ground, max_range, gz, seed,
                                             chunk_pairs)
        else:
            best, code, order = _cast_brute(kinds, o, d, tg, ground, max_range, seed,
                                            chunk_pairs)
    if order is not None:  # back from sorted to input order
        b2, c2 = np.empty_like(best), np.empty_like(code)
        b2[order], c2[order] = best, code
        best, code = b2, c2
    if bad.any():
        code[bad] = 0
    return _finish(prims, o, d, best, code)


def _cast_brute(kinds, o, d, tg, ground, max_range, seed, chunk_pairs):
    R = len(d)
    best = np.where(ground, tg, max_range)
    red = _Reducer(best)
    rays_all = np.arange(R)
    for k in kinds:
        n = len(k.rows)
        step = max(1, chunk_pairs // max(n, 1))
        for r0 in range(0, R, step):
            rr = rays_all[r0:r0 + step]
            # primitive-major pairs: (prim, ray)
            prim = np.repeat(np.arange(n), len(rr))
            ray = np.tile(rr, n)
            if k.params is not None:
                p = [np.repeat(x, len(rr)) for x in k.params]
            else:
                p = k.setup(k.rows[prim], o[ray])
            t = k.kernel(p, d[ray, 0], d[ray, 1], d[ray, 2])
            t = _porous(k, t, ray, prim, seed)
            red.add(ray, t, (np.int64(k.kind) << _CODE_SHIFT) | prim)
    code = np.where(ground & (tg == best), np.int64(KIND_GROUND) << _CODE_SHIFT, 0)
    return best, red.winners(code), None


def _cast_culled(kinds, o, d, tg, ground, max_range, gz, seed, chunk_pairs):
    R = len(d)
    el = np.arcsin(np.clip(d[:, 2], -1.0, 1.0))
    az = np.arctan2(d[:, 1], d[:, 0])
    el_min = el.min()
    span = el.max() - el_min
    # Bands ~ one channel of a spinning lidar; never finer than 0.086 deg (1.5 mrad).
    bw = max(span / max(1, min(R // 512, 2048)), 1.5e-3)
    band = np.minimum(((el - el_min) / bw).astype(np.int64), 1 << 20)
    key = band * 8.0 + (az + np.pi)
    order = np.argsort(key, kind="stable")  # cheap on the scan's already ordered rays
    key_s = key[order]
    band_s = band[order]
    starts = np.flatnonzero(np.r_[True, band_s[1:] != band_s[:-1]])
    band_id = band_s[starts]
    el_s = el[order]
    band_lo = np.minimum.reduceat(el_s, starts)
    band_hi = np.maximum.reduceat(el_s, starts)
    dx, dy, dz = (np.ascontiguousarray(d[order, i]) for i in range(3))
    tg_s, ground_s = tg[order], ground[order]
    best = np.where(ground_s, tg_s, max_range)
    red = _Reducer(best)

    for k in kinds:
        prim, a0, a1, e0, e1 = _intervals(k, o, gz, max_range)
        # bands overlapping [e0, e1]: band elevation ranges are disjoint and increasing
        i0 = np.searchsorted(band_hi, e0, "left")
        i1 = np.searchsorted(band_lo, e1, "right")
        nb = np.maximum(i1 - i0, 0)
        tot = int(nb.sum())
        if tot == 0:
            continue
        iv = np.repeat(np.arange(len(prim)), nb)
        bi = np.repeat(i0 - (np.cumsum(nb) - nb), nb) + np.arange(tot)
        base = band_id[bi] * 8.0 + np.pi
        lo = np.searchsorted(key_s, base + a0[iv], "left")
        hi = np.searchsorted(key_s, base + a1[iv], "right")
        # keys may spill into the neighbouring band when a0/a1 are at +-pi: clamp
        s_lo, s_hi = starts[bi], np.r_[starts[1:], R][bi]
        lo, hi = np.maximum(lo, s_lo), np.minimum(hi, s_hi)
        m = hi > lo
        seg_p, lo, ln = prim[iv[m]], lo[m], (hi - lo)[m]
        if len(ln) == 0:
            continue
        cum = np.cumsum(ln)
        # chunks of whole segments, about chunk_pairs pairs each
        cuts = np.searchsorted(cum, np.arange(chunk_pairs, cum[-1], chunk_pairs), "left") + 1
        bounds = np.r_[0, np.unique(np.minimum(cuts, len(ln))), len(ln)]
        for s0, s1 in zip(bounds[:-1], bounds[1:]):
            if s1 <= s0:
                continue
            sl = ln[s0:s1]
            P = int(sl.sum())
            ray = np.repeat(lo[s0:s1] - (np.cumsum(sl) - sl), sl) + np.arange(P)
            sp = seg_p[s0:s1]
            pp = [np.repeat(x[sp], sl) for x in k.params]
            t = k.kernel(pp, dx[ray], dy[ray], dz[ray])
            pr = np.repeat(sp, sl)
            t = _porous(k, t, order[ray] if k.porosity is not None else ray, pr, seed)
            red.add(ray, t, (np.int64(k.kind) << _CODE_SHIFT) | pr)
    code = np.where(ground_s & (tg_s == best), np.int64(KIND_GROUND) << _CODE_SHIFT, 0)
    return best, red.winners(code), order


def _surface_normals(kd: int, rw: np.ndarray, qx, qy, qz):
    """Outward unit normal at hit points (x, y, z) on primitives ``rw`` of kind ``kd``."""
    qx, qy = qx - rw[:, 0], qy - rw[:, 1]
    if kd == KIND_BOX:  # rows carry cos, sin of yaw in columns 7, 8
        cy, sy = rw[:, 7], rw[:, 8]
        qz = qz - rw[:, 2]
        lx, ly = cy * qx + sy * qy, cy * qy - sy * qx
        # the face is the axis on which the point is relatively farthest out
        fx, fy, fz = np.abs(lx) / rw[:, 3], np.abs(ly) / rw[:, 4], np.abs(qz) / rw[:, 5]
        ax = np.where(fx >= fy, np.where(fx >= fz, 0, 2), np.where(fy >= fz, 1, 2))
        ux = np.where(ax == 0, np.where(lx < 0, -1.0, 1.0), 0.0)
        uy = np.where(ax == 1, np.where(ly < 0, -1.0, 1.0), 0.0)
        return (cy * ux - sy * uy, sy * ux + cy * uy,
                np.where(ax == 2, np.where(qz < 0, -1.0, 1.0), 0.0))
    if kd == KIND_CYLINDER:
        rho = np.hypot(qx, qy)
        ds = np.abs(rho - rw[:, 4])
        dt, db = np.abs(qz - rw[:, 3]), np.abs(qz - rw[:, 2])
        side = (ds <= dt) & (ds <= db) & (rho > 0)
        irho = np.where(side, 1.0 / np.where(rho > 0, rho, 1.0), 0.0)
        return qx * irho, qy * irho, np.where(side, 0.0, np.where(dt <= db, 1.0, -1.0))
    a = qx / rw[:, 3] ** 2
    b = qy / rw[:, 4] ** 2
    c = (qz - rw[:, 2]) / rw[:, 5] ** 2
    inv = 1.0 / np.sqrt(a * a + b * b + c * c)
    return a * inv, b * inv, c * inv


_FINISH_BLOCK = 1 << 14  # rays per block: keeps temporaries cache-sized (much faster)


def _finish(prims: Primitives, o, d, best, code) -> Hits:
    R = len(d)
    kind = (code >> _CODE_SHIFT).astype(np.int8)
    index = (code & ((1 << _CODE_SHIFT) - 1)).astype(np.int32)
    hit = kind > 0
    t = np.where(hit, best, np.inf)
    index[~hit] = -1
    normal = np.empty((R, 3))
    sem = np.full(R, -1, np.int32)
    inst = np.zeros(R, np.int32)
    refl = np.zeros(R)
    reg = np.asarray(prims.ground_regions, np.float64).reshape(-1, 4)
    gcls, grefl = np.asarray(prims.ground_class), np.asarray(prims.ground_reflectivity)
    table = [(KIND_BOX, prims.boxes, prims.box_class, prims.box_instance,
              prims.box_reflectivity),
             (KIND_CYLINDER, prims.cylinders, prims.cylinder_class, prims.cylinder_instance,
              prims.cylinder_reflectivity),
             (KIND_ELLIPSOID, prims.ellipsoids, prims.ellipsoid_class,
              prims.ellipsoid_instance, prims.ellipsoid_reflectivity)]
    table = [(kd, np.asarray(r, np.float64), np.asarray(c), np.asarray(i), np.asarray(f))
             for kd, r, c, i, f in table]
    bx = table[0][1]
    table[0] = (KIND_BOX, np.c_[bx, np.cos(bx[:, 6]), np.sin(bx[:, 6])]) + table[0][2:]

    for b0 in range(0, R, _FINISH_BLOCK):
        blk = slice(b0, min(R, b0 + _FINISH_BLOCK))
        kb, tb, db = kind[blk], t[blk], d[blk]
        ob = o if o.ndim == 1 else o[blk]
        nb = np.zeros(db.shape)
        sb, ib, rb = sem[blk], inst[blk], refl[blk]  # views: written in place

        dsel = None

        def hit_points(sel):
            nonlocal dsel
            dsel = np.take(db, sel, axis=0)  # np.take: much faster than fancy row indexing
            osel = ob if ob.ndim == 1 else np.take(ob, sel, axis=0)
            return list((osel + tb[sel, None] * dsel).T)

        sel = np.flatnonzero(kb == KIND_GROUND)
        if len(sel):
            nb[sel, 2] = 1.0
            cls = np.full(len(sel), prims.default_ground_class, np.int32)
            rf = np.full(len(sel), prims.default_ground_reflectivity, np.float64)
            gx, gy, _ = hit_points(sel)
            todo = np.ones(len(sel), bool)
            for g in range(len(reg)):  # first matching region wins
                m = (todo & (gx >= reg[g, 0]) & (gx <= reg[g, 1])
                     & (gy >= reg[g, 2]) & (gy <= reg[g, 3]))
                cls[m], rf[m] = gcls[g], grefl[g]
                todo &= ~m
            sb[sel], rb[sel] = cls, rf

        for kd, rows, c_, i_, r_ in table:
            sel = np.flatnonzero(kb == kd)
            if not len(sel):
                continue
            j = index[blk][sel]
            a, b, c = _surface_normals(kd, np.take(rows, j, axis=0), *hit_points(sel))
            # normals face the origin: flip those pointing along the ray
            f = np.where(a * dsel[:, 0] + b * dsel[:, 1] + c * dsel[:, 2] > 0, -1.0, 1.0)
            nb[sel] = np.stack([a * f, b * f, c * f], axis=1)
            sb[sel], ib[sel], rb[sel] = c_[j], i_[j], r_[j]
        normal[blk] = nb
    return Hits(t=t, kind=kind, index=index, normal=normal, semantic=sem, instance=inst,
                reflectivity=refl)
