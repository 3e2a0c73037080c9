"""Hand-built LMS range images and a brute-force implementation of the paper's segment
definitions (pixel sets, breadth-first search), shared by the LMS core tests."""
import math
from collections import deque

import numpy as np

from lidar_quality_core.lms.projection import RangeImageConfig, project
from lidar_quality_core.lms.segment_metrics import MEASURES

NB8 = [(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc]


def pixel_points(cfg, rows, cols, rng_m=10.0):
    """Points at the centres of pixels (rows, cols) of a uniform config."""
    R, C = cfg.shape
    up, down = cfg.fov_up_deg, cfg.fov_down_deg
    rows, cols = np.asarray(rows, float), np.asarray(cols, float)
    el = np.radians(up - (rows + 0.5) * (up - down) / R)
    az = np.pi * (1.0 - 2.0 * (cols + 0.5) / C)
    r = np.broadcast_to(np.asarray(rng_m, float), rows.shape)
    return np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az),
                     r * np.sin(el)], axis=1)


def image_cloud(cfg, classes, rng_m=10.0, sharp=0.9):
    """One point per pixel of ``classes`` (rows, cols; -1 = no point), probability
    ``sharp`` on its class and the rest spread evenly; returns xyz, probs, n."""
    rows, cols = np.nonzero(classes >= 0)
    cls = classes[rows, cols]
    n = int(classes.max()) + 1
    xyz = pixel_points(cfg, rows, cols, rng_m)
    probs = np.full((len(cls), n), (1 - sharp) / max(n - 1, 1))
    probs[np.arange(len(cls)), cls] = sharp if n > 1 else 1.0
    return xyz, probs, n


# -- brute force -------------------------------------------------------------------------


def brute_fill(mask):
    R, C = mask.shape
    qr, qc = np.nonzero(mask)
    out = np.empty((R, C), dtype=np.int64)
    for r in range(R):
        for c in range(C):
            d_right, d_left = (qc - c) % C, (c - qc) % C
            dc = np.minimum(d_left, d_right)
            d2 = dc * dc + (qr - r) ** 2
            best = min(zip(d2, np.abs(qr - r), (d_left > d_right).astype(int), qr, qc))
            out[r, c] = best[3] * C + best[4]
    return out


def neighbours(r, c, R, C):
    return {(r + dr, (c + dc) % C) for dr, dc in NB8 if 0 <= r + dr < R}


def components(img):
    R, C = img.shape
    seen, comps = set(), []
    for r in range(R):
        for c in range(C):
            if (r, c) in seen or img[r, c] < 0:
                continue
            comp, todo = {(r, c)}, deque([(r, c)])
            seen.add((r, c))
            while todo:
                p = todo.popleft()
                for q in neighbours(*p, R, C):
                    if q not in seen and img[q] == img[r, c]:
                        seen.add(q)
                        comp.add(q)
                        todo.append(q)
            comps.append(comp)
    return comps


def brute(xyz, probs, cfg, ring=None, intensity=None, min_points=10):
    """The paper's definitions, literally, per segment: {frozenset(pixels): features}."""
    proj = project(xyz, cfg, ring)
    R, C = cfg.shape
    mask = proj.index >= 0
    src = proj.index.reshape(-1)[brute_fill(mask).reshape(-1)].reshape(R, C)
    n = probs.shape[1]
    inten = np.zeros(len(xyz)) if intensity is None else intensity
    heat = {m: np.zeros((R, C)) for m in MEASURES}
    Y = np.zeros((R, C), int)
    for r in range(R):
        for c in range(C):
            j = src[r, c]
            p = [float(v) for v in probs[j]]
            top = sorted(p, reverse=True)
            Y[r, c] = int(np.argmax(probs[j]))
            heat["E"][r, c] = (-sum(v * math.log(v) for v in p if v > 0) / math.log(n)
                               if n > 1 else 0.0)
            heat["V"][r, c] = 1 - top[0]
            heat["D"][r, c] = 1 - top[0] + (top[1] if n > 1 else 0.0)
            x, y, z = (float(v) for v in xyz[j])
            heat["x"][r, c], heat["y"][r, c], heat["z"][r, c] = x, y, z
            heat["i"][r, c] = inten[j]
            heat["r"][r, c] = math.sqrt(x * x + y * y + z * z)
    out = {}
    for k in components(Y):
        inner = {p for p in k if all(0 <= p[0] + dr < R for dr in (-1, 1))
                 and neighbours(*p, R, C) <= k}
        bd = k - inner
        S, S_in, S_bd = len(k), len(inner), len(bd)
        SP = sum(bool(mask[p]) for p in k)
        if SP < min_points:
            continue
        row = []
        for m in MEASURES:
            mu, va = {}, {}
            for name, reg in (("", k), ("_in", inner), ("_bd", bd)):
                vals = np.array([heat[m][p] for p in reg])
                mu[name] = vals.mean() if len(vals) else 0.0
                va[name] = (vals ** 2).mean() - vals.mean() ** 2 if len(vals) else 0.0
            row += [mu[""], mu["_in"], mu["_bd"], mu[""] * S / S_bd, mu["_in"] * S_in / S_bd,
                    va[""], va["_in"], va["_bd"], va[""] * S / S_bd, va["_in"] * S_in / S_bd]
        row += [S, S_in, S_bd, S / S_bd, S_in / S_bd, SP]
        knb = set().union(*(neighbours(*p, R, C) for p in k)) - k
        row += [sum(Y[p] == c for p in knb) / len(knb) if knb else 0.0 for c in range(n)]
        row += [np.mean([probs[src[p], c] for p in k]) for c in range(n)]
        out[frozenset(k)] = np.array(row, dtype=float)
    return out, src, Y, mask


def brute_targets(res, gt, ignore_label=None):
    R, C = res.segments.shape
    n = res.n_classes
    src = res.source
    G = np.asarray(gt)[src]
    d = res.delta & (G != (-99 if ignore_label is None else ignore_label))
    pred = components(res.pred)
    gts = components(np.where(G == (-99 if ignore_label is None else ignore_label), n, G))
    out = {}
    for k in pred:
        c = res.pred[next(iter(k))]
        Kp = set().union(*[g for g in gts if G[next(iter(g))] == c and g & k] or [set()])
        Q = set().union(*[q for q in pred if res.pred[next(iter(q))] == c and q & Kp]
                        or [set()])

        def size(s):
            return sum(bool(d[p]) for p in s)

        inter = size(k & Kp)
        u, ua = size(k | Kp), size(k | (Kp - Q))
        out[frozenset(k)] = (inter / u if u else np.nan, inter / ua if ua else np.nan)
    return out


def pixel_sets(res):
    seg = res.segments
    return {s: frozenset(zip(*np.nonzero(seg == s))) for s in range(res.n_segments)}


def random_scene(seed, R=6, C=12, n=4):
    rng = np.random.default_rng(seed)
    cfg = RangeImageConfig.uniform(R, C, 10.0, -20.0)
    # blocky class image so that segments are bigger than a pixel
    base = rng.integers(0, n, (R // 2 + 1, C // 3 + 1))
    cls_img = np.kron(base, np.ones((2, 3), int))[:R, :C]
    flip = rng.random((R, C)) < 0.15
    cls_img[flip] = rng.integers(0, n, flip.sum())
    occupied = rng.random((R, C)) < 0.75
    rows, cols = np.nonzero(occupied)
    extra = rng.random(len(rows)) < 0.2            # a second point in some pixels
    rows = np.r_[rows, rows[extra]]
    cols = np.r_[cols, cols[extra]]
    xyz = pixel_points(cfg, rows + rng.uniform(-0.3, 0.3, len(rows)),
                       cols + rng.uniform(-0.3, 0.3, len(rows)),
                       rng.uniform(2.0, 50.0, len(rows)))
    logits = rng.normal(0, 1, (len(rows), n))
    logits[np.arange(len(rows)), cls_img[rows, cols]] += 2.5
    # the second points are often of another class (shadowed by the nearer one)
    k = int(extra.sum())
    if k:
        logits[-k:] = rng.normal(0, 3, (k, n))
    probs = np.exp(logits)
    probs /= probs.sum(axis=1, keepdims=True)
    # out of the field of view, NaN: never projected
    xyz = np.r_[xyz, pixel_points(cfg, [-3.0, R + 2.0], [1.0, 2.0]), [[np.nan, 0, 0]]]
    probs = np.r_[probs, np.full((3, n), 1.0 / n)]
    inten = rng.uniform(0, 1, len(xyz))
    gt = np.r_[cls_img[rows, cols], [0, 0, 0]]
    swap = rng.random(len(gt)) < 0.1
    gt[swap] = rng.integers(0, n, swap.sum())
    return cfg, xyz, probs.astype(np.float32), inten, gt


# -- schema ------------------------------------------------------------------------------
