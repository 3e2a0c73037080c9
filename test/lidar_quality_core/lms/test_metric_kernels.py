"""Compiled passes of the LMS segment metrics against plain numpy / scipy references (the
implementation they replaced), bit for bit, on random and awkward inputs: NaN, infinite,
zero, negative, tiny and tied probabilities, one class, many classes, either layout."""
import numpy as np
import pytest
from float32_logs import reference_log
from scipy.sparse import csc_matrix

from lidar_quality_core.lms import metric_kernels as mk
from lidar_quality_core.lms.segment_metrics import _BLOCK, _record_run, dispersion


# -- references --------------------------------------------------------------------------


def ref_dispersion(probs):
    """(argmax, E, D, V) from (N, n) float32 probabilities with numpy on a class-major copy
    (numpy's float32 log: see ``float32_logs.reference_log``)."""
    pcm = np.array(probs.T, dtype=np.float32, order="C")
    n, N = pcm.shape
    E = np.zeros(N, dtype=np.float32)
    with np.errstate(all="ignore"):
        if n > 1 and N:
            clamp = not pcm.min() > 0
            tmp = np.empty(N, dtype=np.float32)
            for pc in pcm:
                if clamp:
                    np.maximum(pc, np.float32(1e-37), out=tmp)
                    tmp[:] = reference_log(tmp)
                else:
                    tmp[:] = reference_log(pc)
                tmp *= pc
                E += tmp
            E *= np.float32(-1.0 / np.log(n))
        p1 = pcm.max(axis=0)
        if n > 1 and N:
            w = np.arange(n, 0, -1, dtype=np.int32)[:, None]
            cls = (n - ((pcm == p1) * w).max(axis=0)).astype(np.int32)
            cls[cls >= n] = 0
            pcm.reshape(-1)[cls * N + np.arange(N)] = -np.inf
            p2 = pcm.max(axis=0)
        else:
            cls = np.zeros(N, dtype=np.int32)
            p2 = np.zeros(N, dtype=np.float32)
        V = np.float32(1.0) - p1
        D = V + p2
    return cls, E, D, V


def ref_region_sums(index, source, seg, interior, n_seg, G, probs, block):
    """Sparse products over points, as segment_metrics computed them before."""
    N, n = probs.shape
    nb = 2 * n_seg
    rid = seg + n_seg * interior
    mask = index >= 0
    proj_pix = np.flatnonzero(mask)
    rid_pt = np.full(N, nb, dtype=np.int32)
    rid_pt[index[proj_pix]] = rid[proj_pix]
    fill_pix = np.flatnonzero(~mask)
    rid_fill = rid[fill_pix]
    src_fill = source[fill_pix]
    same = rid_fill == rid_pt[src_fill]
    weight = np.bincount(src_fill[same], minlength=N).astype(np.float64) + 1.0
    other = np.flatnonzero(~same)
    cols = np.arange(N + 1, dtype=np.int32)
    B = csc_matrix((weight, rid_pt, cols), shape=(nb + 1, N))
    s1, s2 = B @ G, B @ np.square(G)
    psum = np.zeros((nb + 1, n))
    for b0 in range(0, N, block):
        b1 = min(N, b0 + block)
        psum += csc_matrix((weight[b0:b1], rid_pt[b0:b1], cols[:b1 - b0 + 1]),
                           shape=(nb + 1, b1 - b0)) @ np.asarray(probs[b0:b1], np.float64)
    if len(other):
        nf = len(other)
        Bf = csc_matrix((np.ones(nf), rid_fill[other], np.arange(nf + 1)), shape=(nb + 1, nf))
        Gf = G[src_fill[other]]
        s1 += Bf @ Gf
        s2 += Bf @ (Gf * Gf)
        psum += Bf @ probs[src_fill[other]].astype(np.float64)
    sp = np.bincount(rid_pt, minlength=nb + 1)[:nb]
    cnt = sp + np.bincount(rid_fill, minlength=nb)
    return np.concatenate([s1[:nb], s2[:nb]], axis=1), psum[:nb], sp, cnt


def ref_features(sums, psum, cnt, sp, kid, M=8):
    """Statistics, sizes and P_c of the kept segments (N_c columns left at 0)."""
    n_seg = len(cnt) // 2
    nb = 2 * n_seg
    n = psum.shape[1]
    k = len(kid)
    S_bd, S_in = cnt[:n_seg], cnt[n_seg:]
    S = S_bd + S_in
    SP = sp[:n_seg] + sp[n_seg:]
    s_reg = np.stack([sums[:n_seg] + sums[n_seg:nb], sums[n_seg:nb], sums[:n_seg]], axis=1)[kid]
    S3 = np.stack([S[kid], S_in[kid], S_bd[kid]], axis=1).astype(np.float64)
    has = (S3 > 0)[:, :, None]
    den = np.where(has, S3[:, :, None], 1.0)
    with np.errstate(all="ignore"):
        mean = np.where(has, s_reg[:, :, :M] / den, 0.0)
        var = np.where(has, np.maximum(s_reg[:, :, M:] / den - mean * mean, 0.0), 0.0)
        S_rel = S3[:, 0] / S3[:, 2]
        S_rel_in = S3[:, 1] / S3[:, 2]
        stats = np.empty((k, M, 10))
        stats[:, :, 0:3] = mean.transpose(0, 2, 1)
        stats[:, :, 3] = mean[:, 0] * S_rel[:, None]
        stats[:, :, 4] = mean[:, 1] * S_rel_in[:, None]
        stats[:, :, 5:8] = var.transpose(0, 2, 1)
        stats[:, :, 8] = var[:, 0] * S_rel[:, None]
        stats[:, :, 9] = var[:, 1] * S_rel_in[:, None]
        Pc = (psum[:n_seg] + psum[n_seg:nb])[kid] / S3[:, :1]
    return np.concatenate([stats.reshape(k, M * 10), S3, S_rel[:, None], S_rel_in[:, None],
                           SP[kid, None].astype(np.float64), np.zeros((k, n)), Pc], axis=1)


_NB = ((0, -1), (0, 1), (-1, 0), (1, 0), (-1, -1), (-1, 1), (1, -1), (1, 1))


def ref_point_segments(index, valid, pixel, row, col, seg, pred, point_class, C, sp_seg):
    R = len(index) // C
    N = len(valid)
    proj_pix = np.flatnonzero(index >= 0)
    win = index[proj_pix]
    point_segment = np.full(N, -1, dtype=np.int32)
    point_segment[win] = seg[proj_pix]
    n_points = sp_seg.copy()
    other = valid.copy()
    other[win] = False
    other = np.flatnonzero(other)
    pix = pixel[other]
    ps = seg[pix].astype(np.int32)
    wrong = np.flatnonzero(pred[pix] != point_class[other])
    pr, pcol = row[other[wrong]].astype(np.int64), col[other[wrong]].astype(np.int64)
    want = point_class[other[wrong]]
    found = np.full(len(wrong), -1, dtype=np.int32)
    for dr, dc in _NB:
        rr = pr + dr
        ok = np.flatnonzero((found < 0) & (rr >= 0) & (rr < R))
        q = rr[ok] * C + (pcol[ok] + dc) % C
        hit = pred[q] == want[ok]
        found[ok[hit]] = seg[q[hit]]
    ps[wrong] = found
    point_segment[other] = ps
    n_points += np.bincount(ps[ps >= 0], minlength=len(n_points))
    return point_segment, n_points


# -- inputs ------------------------------------------------------------------------------


def softmax(rng, N, n, spread=3.0):
    logits = rng.normal(0.0, spread, (N, n))
    p = np.exp(logits - logits.max(axis=1, keepdims=True))
    return (p / p.sum(axis=1, keepdims=True)).astype(np.float32)


def awkward_probs(rng, N, n):
    """Softmax rows with NaN, +-inf, zeros, -0.0, negative values, ties and tiny values."""
    p = softmax(rng, N, n)
    k = rng.permutation(N)
    m = max(1, N // 20)
    p[k[:m], rng.integers(0, n, m)] = np.nan
    p[k[m:2 * m], 0] = np.nan
    p[k[2 * m:3 * m], rng.integers(0, n, m)] = np.inf
    p[k[3 * m:4 * m], rng.integers(0, n, m)] = -np.inf
    p[k[4 * m:5 * m]] = 0.0
    p[k[5 * m:6 * m], rng.integers(0, n, m)] = -0.0
    p[k[6 * m:7 * m], rng.integers(0, n, m)] = -0.25
    p[k[7 * m:8 * m], -1] = p[k[7 * m:8 * m]].max(axis=1)                 # ties for p1
    p[k[8 * m:9 * m]] = np.float32(1 / n)                                  # all tied
    p[k[9 * m:10 * m], rng.integers(0, n, m)] = np.float32(1e-39)          # subnormal
    p[k[10 * m:11 * m]] = np.round(p[k[10 * m:11 * m]] * 255) / np.float32(255)
    return p


def class_major(p):
    return np.ascontiguousarray(p.T).T


def assert_dispersion_exact(p):
    want = ref_dispersion(p)
    for probs in (p, class_major(p)):
        before = probs.copy()
        got = dispersion(probs)
        for g, w in zip(got, want):
            assert g.dtype == w.dtype and g.shape == w.shape
            np.testing.assert_array_equal(g, w)
        np.testing.assert_array_equal(probs, before)           # the input is not modified


# -- dispersion --------------------------------------------------------------------------


@pytest.mark.parametrize("n", [2, 3, 20, 33, 300])
def test_dispersion_matches_numpy_on_softmax(n):
    rng = np.random.default_rng(n)
    assert_dispersion_exact(softmax(rng, 3001, n))
    assert_dispersion_exact(softmax(rng, 5, n, spread=60.0))   # exact zeros: clamped logs


@pytest.mark.parametrize("n", [2, 5, 20])
def test_dispersion_matches_numpy_on_awkward_values(n):
    rng = np.random.default_rng(100 + n)
    assert_dispersion_exact(awkward_probs(rng, 4000, n))
    q = np.round(softmax(rng, 2000, n) * 255) / np.float32(255)           # quantized: ties
    assert_dispersion_exact(q.astype(np.float32))
    assert_dispersion_exact(np.full((50, n), np.nan, np.float32))
    assert_dispersion_exact(np.full((50, n), -np.inf, np.float32))
    assert_dispersion_exact(np.zeros((50, n), np.float32))


def test_dispersion_clamps_only_when_a_probability_is_not_positive():
    # tiny positive probabilities: their own logs, unless some p <= 0 or NaN exists
    rng = np.random.default_rng(7)
    p = softmax(rng, 1000, 20)
    p[:40] = (10.0 ** rng.uniform(-44, -37.5, (40, 20))).astype(np.float32)
    assert_dispersion_exact(p)
    E_free = dispersion(p)[1]
    for bad in (0.0, np.nan, -1e-30):
        q = p.copy()
        q[500, 3] = bad
        assert_dispersion_exact(q)
        assert not np.array_equal(dispersion(q)[1][:40], E_free[:40])


def test_dispersion_one_class_and_no_point():
    rng = np.random.default_rng(3)
    p = rng.random((100, 1)).astype(np.float32)
    p[::7] = np.nan
    assert_dispersion_exact(p)
    for n in (1, 2, 20):
        assert_dispersion_exact(np.zeros((0, n), np.float32))


def test_dispersion_blocks_do_not_matter(monkeypatch):
    from lidar_quality_core.lms import segment_metrics

    rng = np.random.default_rng(5)
    p = awkward_probs(rng, 1000, 7)
    for block in (7, 50, 7 * 333):
        monkeypatch.setattr(segment_metrics, "_DISPERSION_BLOCK", block)
        assert_dispersion_exact(p)


@pytest.mark.parametrize("m", [1, 15, 16, 17, 50, 177])
def test_transpose_block(m):
    # whole tiles of 16 rows, a remainder, and rows read from a message's records
    rng = np.random.default_rng(m)
    p = rng.random((400, 7)).astype(np.float32)
    records = np.zeros((400, 9), np.float32)
    records[:, 2:] = p
    unaligned = np.zeros((400, 9 * 4 + 2), np.uint8)
    unaligned[:, 2:2 + 7 * 4] = p.view(np.uint8).reshape(400, 28)
    strided = np.ndarray((400, 7), np.float32, unaligned, offset=2, strides=(38, 4))
    assert not strided.flags.aligned
    for src in (p, records[:, 2:], strided):
        out = np.full((7, m), np.nan, np.float32)
        mk.transpose_block(src, 123, out)
        np.testing.assert_array_equal(out, p[123:123 + m].T)


# -- sums over regions -------------------------------------------------------------------


def random_image(rng, R, C, N, n_seg, fill_ratio=0.3):
    """index (a point per projected pixel, some points kept by none), source (a projected
    pixel's point for every pixel), segment ids and interior flags, flat."""
    P = R * C
    projected = rng.random(P) > fill_ratio
    projected[rng.integers(0, P)] = True
    proj_pix = np.flatnonzero(projected)
    assert len(proj_pix) <= N
    index = np.full(P, -1, np.int32)
    index[proj_pix] = rng.permutation(N)[:len(proj_pix)]
    source = index.copy()
    empty = np.flatnonzero(~projected)
    # mostly a projected neighbour along the row (same region as often as not), else any
    near = np.clip(empty + rng.integers(-2, 3, len(empty)), 0, P - 1)
    near = np.where(projected[near], near, proj_pix[rng.integers(0, len(proj_pix), len(empty))])
    source[empty] = index[near]
    seg = rng.integers(0, n_seg, P).astype(np.int32)
    seg.reshape(R, C)[:, 1::2] = seg.reshape(R, C)[:, ::2][:, :C // 2]    # runs of a segment
    interior = rng.random(P) < 0.4
    return index, source, seg, interior


def measures(rng, N, dtype):
    cols = [rng.normal(0, 1, N), rng.random(N), rng.random(N), rng.normal(0, 30, N),
            rng.normal(0, 30, N), rng.normal(0, 2, N), rng.random(N) * 255,
            10.0 ** rng.uniform(-3, 2, N)]
    cols = [c.astype(dtype) for c in cols]
    cols[3][rng.integers(0, N, 5)] = np.nan
    cols[6][rng.integers(0, N, 5)] = -0.0
    cols[7][rng.integers(0, N, 3)] = np.inf
    return cols


def run_region_sums(index, source, seg, interior, n_seg, cols, probs, block, run=False):
    """The kernel on ``probs`` as they are, or (``run``) read as a flat run of records
    (segment_metrics._record_run: the node's message view)."""
    nb = 2 * n_seg
    sums = np.zeros((nb, 16))
    psum = np.zeros((nb, probs.shape[1]))
    sp = np.zeros(nb, np.int64)
    cnt = np.zeros(nb, np.int64)
    rows, step = _record_run(probs) if run else (np.zeros(0, np.float32), 0)
    assert len(rows) or not run
    with np.errstate(all="ignore"):
        mk.region_sums(index, source, seg, interior, n_seg, *cols, probs, rows, step, block,
                       sums, psum, sp, cnt)
    return sums, psum, sp, cnt


def in_records(probs, before=4, after=3):
    """``probs`` (N, n) as the read-only view of a message's records: float32 fields
    before and after them, other values there."""
    N, n = probs.shape
    rec = np.full((N, before + n + after), np.float32(-7.5))
    rec[:, before:before + n] = probs
    view = rec[:, before:before + n]
    view.flags.writeable = False
    return view


@pytest.mark.parametrize("seed", range(6))
def test_region_sums_match_the_sparse_products(seed):
    rng = np.random.default_rng(seed)
    R, C = (4, 9) if seed < 3 else (16, 64)
    N = R * C + 40 if seed % 3 else R * C
    n = (1, 3, 20)[seed % 3]
    n_seg = (1, 5, 40)[seed % 3]
    index, source, seg, interior = random_image(rng, R, C, N, n_seg, fill_ratio=0.1 + 0.1 * seed)
    probs = awkward_probs(rng, N, n) if seed % 2 else softmax(rng, N, n)
    probs[rng.random(probs.shape) < 0.3] *= np.float32(1e-6)           # wide magnitudes
    for dtype in (np.float32, np.float64):
        cols = measures(rng, N, dtype)
        E, D, V = (c.astype(np.float32) for c in cols[:3])
        G = np.stack([E, D, V] + cols[3:], axis=1).astype(np.float64)
        for block in (_BLOCK, 7, 1):
            with np.errstate(all="ignore"):
                want = ref_region_sums(index, source, seg, interior, n_seg, G, probs, block)
            for p, run in ((probs, False), (class_major(probs), False),
                           (in_records(probs), False), (in_records(probs), True),
                           (probs, True)):
                got = run_region_sums(index, source, seg, interior, n_seg,
                                      [E, D, V] + cols[3:], p, block, run)
                for g, w in zip(got, want):
                    np.testing.assert_array_equal(g, w)


def test_region_sums_keep_the_order_of_the_blocks():
    # many terms of all magnitudes per region: float64 sums that depend on their order, so
    # that the blocks of the probability sums are seen
    rng = np.random.default_rng(11)
    R, C, N, n_seg, n = 32, 64, 2048, 2, 8
    index, source, seg, interior = random_image(rng, R, C, N, n_seg, fill_ratio=0.2)
    probs = (10.0 ** rng.uniform(-12, 0, (N, n))).astype(np.float32)
    cols = measures(rng, N, np.float32)
    G = np.stack(cols, axis=1).astype(np.float64)
    psums = []
    for block in (_BLOCK, 100):
        want = ref_region_sums(index, source, seg, interior, n_seg, G, probs, block)
        for p, run in ((probs, False), (class_major(probs), False), (in_records(probs), True)):
            got = run_region_sums(index, source, seg, interior, n_seg, cols, p, block, run)
            for g, w in zip(got, want):
                np.testing.assert_array_equal(g, w)
        psums.append(want[1])
    assert not np.array_equal(psums[0], psums[1])


def test_region_sums_strided_measures_and_sparse_images():
    # xyz columns of a row-major (N, 3) array; more filled pixels than points
    rng = np.random.default_rng(9)
    R, C, N, n_seg = 8, 32, 25, 3
    index, source, seg, interior = random_image(rng, R, C, N, n_seg, fill_ratio=0.96)
    xyz = rng.normal(0, 10, (N, 3)).astype(np.float32)
    E, D, V, inten, rng_m = (rng.random(N).astype(np.float32) for _ in range(5))
    probs = softmax(rng, N, 4)
    G = np.stack([E, D, V, xyz[:, 0], xyz[:, 1], xyz[:, 2], inten, rng_m], axis=1)
    want = ref_region_sums(index, source, seg, interior, n_seg, G.astype(np.float64), probs,
                           _BLOCK)
    got = run_region_sums(index, source, seg, interior, n_seg,
                          [E, D, V, xyz[:, 0], xyz[:, 1], xyz[:, 2], inten, rng_m], probs,
                          _BLOCK)
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)


@pytest.mark.parametrize("seed", range(4))
def test_segment_features_match_numpy(seed):
    rng = np.random.default_rng(seed)
    n_seg, n = 30, (1, 4, 20, 2)[seed]
    nb = 2 * n_seg
    sums = rng.normal(0, 10, (nb, 16))
    sums[:, 8:] = np.abs(sums[:, 8:]) * 0.01                  # variances below 0: clipped
    sums[rng.integers(0, nb, 4), rng.integers(0, 16, 4)] = np.nan
    sums[rng.integers(0, nb, 2), rng.integers(0, 16, 2)] = np.inf
    psum = np.abs(rng.normal(0, 5, (nb, n)))
    sp = rng.integers(0, 20, nb)
    cnt = sp + rng.integers(0, 30, nb)
    cnt[:n_seg] = np.maximum(cnt[:n_seg], 1)                  # S_bd >= 1
    cnt[n_seg + rng.integers(0, n_seg, 8)] = 0                # empty interiors
    sp[n_seg:] = np.minimum(sp[n_seg:], cnt[n_seg:])
    for kid in (np.arange(n_seg), np.flatnonzero(rng.random(n_seg) < 0.5), np.zeros(0, int)):
        kid = kid.astype(np.int64)
        got = np.full((len(kid), 86 + 2 * n), -7.0)
        mk.segment_features(sums, psum, cnt, sp, kid, got)
        want = ref_features(sums, psum, cnt, sp, kid)
        got[:, 86:86 + n] = 0.0                               # N_c: the caller's
        np.testing.assert_array_equal(got, want)


# -- pixels and points -------------------------------------------------------------------


def test_read_sources():
    rng = np.random.default_rng(2)
    index = rng.integers(-1, 50, 200).astype(np.int32)
    index[index < 0] = 3
    point_class = rng.integers(0, 5, 50).astype(np.int32)
    for dtype in (np.int32, np.int64):
        near = rng.integers(0, 200, 200).astype(dtype)
        source = np.empty(200, np.int32)
        pred = np.empty(200, np.int32)
        mk.read_sources(index, point_class, near, source, pred)
        np.testing.assert_array_equal(source, index[near])
        np.testing.assert_array_equal(pred, point_class[index[near]])


@pytest.mark.parametrize("seed", range(8))
def test_point_segments_match_numpy(seed):
    rng = np.random.default_rng(seed)
    R, C = (3 + seed, 5 + 3 * seed)
    P = R * C
    N = P + 30 * (seed + 1)
    n_cls = 1 + seed % 4
    row = rng.integers(0, R, N).astype(np.int32)
    col = rng.integers(0, C, N).astype(np.int32)
    valid = rng.random(N) < 0.9
    row[~valid] = col[~valid] = -1
    pixel = np.where(valid, row * C + col, -1).astype(np.int32)
    index = np.full(P, -1, np.int32)
    for j in rng.permutation(np.flatnonzero(valid)):          # one point keeps each pixel
        index[pixel[j]] = j
    pred = rng.integers(0, n_cls, P).astype(np.int32)
    seg = rng.integers(0, 2 * P, P).astype(np.int32)
    n_seg = int(seg.max()) + 1
    point_class = rng.integers(0, n_cls, N).astype(np.int32)
    sp_seg = np.bincount(seg[index >= 0], minlength=n_seg).astype(np.int64)
    want = ref_point_segments(index, valid, pixel, row, col, seg, pred, point_class, C, sp_seg)
    ps = np.full(N, -1, np.int32)
    n_points = sp_seg.copy()
    mk.point_segments(index, valid, pixel, row, col, seg, pred, point_class, C, ps, n_points)
    np.testing.assert_array_equal(ps, want[0])
    np.testing.assert_array_equal(n_points, want[1])


@pytest.mark.parametrize("n", [1, 2, 20])
def test_dispersion_sums_are_numpys_reductions(n):
    rng = np.random.default_rng(n)
    p = awkward_probs(rng, 3000, n)
    p[:10] = -0.0                                      # numpy sums from +0.0
    rec = np.zeros((3000, n + 3), np.float32)          # a view with strided rows
    rec[:, 2:2 + n] = p
    pcm = np.ascontiguousarray(p.T)
    for probs in (rec[:, 2:2 + n], pcm.T, p):
        total, smallest = np.empty(3000, np.float32), np.empty(3000, np.float32)
        got = dispersion(probs, sums=(total, smallest))
        with np.errstate(all="ignore"):
            assert total.tobytes() == np.add.reduce(pcm, axis=0).tobytes()
            assert smallest.tobytes() == np.minimum.reduce(pcm, axis=0).tobytes()
        for g, w in zip(got, dispersion(p)):
            assert g.tobytes() == w.tobytes()
    dispersion(p[:0], sums=(total[:0], smallest[:0]))
