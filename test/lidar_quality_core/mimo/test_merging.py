"""Tests for lidar_quality_core.mimo.merging (LiDAR-MIMO clustering and merging)."""
import math
import zlib
from types import SimpleNamespace

import numpy as np
import pytest

from lidar_quality_core.mimo.clustering import min_cluster_size
from lidar_quality_core.mimo.merging import HeadDetections, MergeConfig, merge_heads

CAR = np.array([10.0, 5.0, -1.0, 4.5, 1.9, 1.6, 0.3])
PED = np.array([10.5, 5.0, -1.0, 0.8, 0.7, 1.7, 0.0])  # inside the car's footprint
CAR_LOGITS = np.log([0.05, 0.8, 0.05, 0.05, 0.05])      # column 0 background, 1 car
PED_LOGITS = np.log([0.1, 0.05, 0.05, 0.75, 0.05])
VAR = np.array([0.04, 0.04, 0.01, 0.02, 0.01, 0.01, 0.003])


def head(boxes, logits, var=None):
    boxes = np.atleast_2d(np.asarray(boxes, float))
    logits = np.atleast_2d(np.asarray(logits, float))
    return HeadDetections(boxes, np.repeat(logits, len(boxes), 0) if len(logits) == 1 else logits,
                          None if var is None else np.tile(var, (len(boxes), 1)))


def h2(p):
    return -sum(x * math.log2(x) for x in p if x > 0)


def softmax(z):
    e = np.exp(z - np.max(z))
    return e / e.sum()


def test_config_validation():
    for bad in (dict(eps=0.0), dict(eps=1.0), dict(voting="majority"), dict(temperature=0.0),
                dict(score_type="scores"), dict(dbscan="hdbscan"), dict(min_cluster_size=0)):
        with pytest.raises(ValueError):
            MergeConfig(**bad)
    assert MergeConfig(min_cluster_size=3).min_samples(2) == 3
    assert MergeConfig().min_samples(4) == 3


# ------------------------------------------------------------------ issue's cases
@pytest.mark.parametrize("K", [2, 4])
def test_identical_heads(K):
    boxes = np.stack([CAR, CAR + [20, 0, 0, 0, 0, 0, 0]])
    logits = np.stack([CAR_LOGITS, PED_LOGITS])
    r = merge_heads([head(boxes, logits, VAR)] * K)
    assert len(r) == 2 and r.min_samples == min_cluster_size("consensus", K)
    np.testing.assert_allclose(r.boxes, boxes)
    np.testing.assert_array_equal(r.stats.epistemic_total_variance, 0.0)
    np.testing.assert_allclose(r.stats.mutual_information, 0.0, atol=1e-12)
    np.testing.assert_array_equal(r.stats.cluster_size, K)
    np.testing.assert_allclose(r.class_probs, [softmax(CAR_LOGITS), softmax(PED_LOGITS)])
    assert r.labels.tolist() == [1, 3]
    np.testing.assert_allclose(r.scores, [0.8, 0.75])
    np.testing.assert_allclose(r.stats.aleatoric_total_variance, VAR.sum())
    np.testing.assert_allclose(r.stats.predictive_variance, np.tile(VAR, (2, 1)))
    for c in range(2):
        hd, idx = r.members(c)
        assert sorted(hd.tolist()) == list(range(K)) and set(idx.tolist()) == {c}


def test_known_offset_gives_known_etv():
    d = np.array([0.2, -0.1, 0.05, 0.1, -0.06, 0.04, 0.02])
    r = merge_heads([head(CAR, CAR_LOGITS, VAR), head(CAR + d, CAR_LOGITS, VAR)])
    assert len(r) == 1 and r.stats.cluster_size[0] == 2
    np.testing.assert_allclose(r.stats.epistemic_variance[0], (d / 2) ** 2, atol=1e-15)
    assert r.stats.epistemic_total_variance[0] == pytest.approx(np.sum((d / 2) ** 2))
    np.testing.assert_allclose(r.boxes[0, :6], CAR[:6] + d[:6] / 2)
    # equal confidence: the top member is head 0's box, its yaw and yaw variance are used
    assert r.boxes[0, 6] == CAR[6] and r.top_member[0] == 0
    expected = (d / 2) ** 2 + VAR
    expected[6] = VAR[6]
    np.testing.assert_allclose(r.stats.predictive_variance[0], expected)


def test_box_of_one_head_dropped_by_consensus_kept_by_affirmative():
    lone = CAR + [30.0, 0, 0, 0, 0, 0, 0]
    heads = [head([CAR, lone], CAR_LOGITS), head([CAR], CAR_LOGITS)]
    r = merge_heads(heads)  # consensus, K = 2: min 2
    assert len(r) == 1 and r.stats.cluster_size.tolist() == [2]
    assert r.member_cluster.tolist() == [0, -1, 0]
    assert r.member_head.tolist() == [0, 0, 1] and r.member_index.tolist() == [0, 1, 0]
    a = merge_heads(heads, MergeConfig(voting="affirmative"))
    assert len(a) == 2 and sorted(a.stats.cluster_size.tolist()) == [1, 2]
    single = a.member_cluster[1]
    np.testing.assert_allclose(a.boxes[single], lone)
    assert a.stats.epistemic_total_variance[single] == 0.0
    u = merge_heads(heads + [head(np.zeros((0, 7)), np.zeros((0, 5)))],
                    MergeConfig(voting="unanimous"))
    assert len(u) == 0  # K = 3, the car is seen by two


def test_yaw_near_pi_is_not_averaged():
    a, b = CAR.copy(), CAR.copy()
    a[6], b[6] = math.pi - 0.01, -math.pi + 0.01
    strong = np.log([0.02, 0.9, 0.04, 0.02, 0.02])
    r = merge_heads([head(a, CAR_LOGITS), head(b, strong)])
    assert len(r) == 1
    assert r.boxes[0, 6] == b[6]  # head 1 is more confident
    assert abs(r.boxes[0, 6]) > 3.1
    assert r.stats.epistemic_variance[0, 6] == pytest.approx(1e-4)
    raw = merge_heads([head(a, CAR_LOGITS), head(b, strong)], MergeConfig(yaw_deviation="raw"))
    assert raw.stats.epistemic_variance[0, 6] == pytest.approx((math.pi - 0.01) ** 2)
    assert raw.boxes[0, 6] == b[6]


def test_hand_computed_entropies():
    # head 0 [bg 0.5, car 0.5], head 1 [bg 0, car 1]: as probabilities and as logits
    p0, p1 = np.array([0.5, 0.5]), np.array([0.0, 1.0])
    se, ae = h2([0.25, 0.75]), 0.5
    r = merge_heads([head(CAR, p0), head(CAR, p1)], MergeConfig(score_type="probabilities"))
    assert r.stats.shannon_entropy[0] == pytest.approx(se, abs=1e-9)      # 0.8113
    assert r.stats.aleatoric_entropy[0] == pytest.approx(ae, abs=1e-9)
    assert r.stats.mutual_information[0] == pytest.approx(se - ae, abs=1e-9)
    # the merged distribution is softmax of the mean logits (geometric mean): ~all car
    assert r.labels[0] == 1 and r.scores[0] > 0.999
    assert r.top_member[0] == 1
    # three heads, five classes, logits
    L = np.array([[0.0, 2.0, 0.5, -1.0, 0.0], [0.5, 1.0, 1.0, -0.5, 0.0],
                  [-1.0, 0.0, 2.5, 0.0, 0.0]])
    r = merge_heads([head(CAR, L[k]) for k in range(3)])
    P = np.array([softmax(z) for z in L])
    assert r.stats.shannon_entropy[0] == pytest.approx(h2(P.mean(axis=0)))
    assert r.stats.aleatoric_entropy[0] == pytest.approx(np.mean([h2(p) for p in P]))
    assert r.stats.mutual_information[0] == pytest.approx(
        h2(P.mean(axis=0)) - np.mean([h2(p) for p in P]))
    np.testing.assert_allclose(r.class_probs[0], softmax(L.mean(axis=0)))
    assert r.labels[0] == 2 and r.scores[0] == pytest.approx(softmax(L.mean(axis=0))[2])


def test_one_box_cluster_is_softmax_of_its_logits():
    """Issue 14 (1): one head, one box; the softmax used to run twice (0.518 for 0.844)."""
    z = np.array([[0.0, 2.0, -1.0]])
    given = z.copy()
    r = merge_heads([HeadDetections(CAR[None], z)], MergeConfig(voting="affirmative"))
    np.testing.assert_allclose(r.class_probs[0], softmax(z[0]), rtol=0, atol=1e-15)
    np.testing.assert_allclose(r.class_probs[0], [0.114, 0.844, 0.042], atol=5e-4)
    assert r.labels[0] == 1 and r.scores[0] == pytest.approx(0.8438, abs=1e-4)
    np.testing.assert_array_equal(z, given)


def _random_heads(rng, K, C, probabilities):
    """K heads over a few objects; some heads see nothing (stopped publishing)."""
    centres = rng.uniform(-30, 30, (int(rng.integers(1, 4)), 2))
    heads = []
    for _ in range(K):
        if rng.random() < 0.3:
            heads.append(HeadDetections(np.zeros((0, 7)), np.zeros((0, C))))
            continue
        m = int(rng.integers(1, len(centres) + 1))
        at = centres[rng.choice(len(centres), m, replace=False)] + rng.normal(0, 0.2, (m, 2))
        b = np.column_stack([at, np.zeros(m), np.full(m, 4.0), np.full(m, 2.0),
                             np.full(m, 1.5), rng.normal(0, 0.1, m)])
        s = rng.normal(0, 2, (m, C))
        if probabilities:  # not always normalized: softmax(log p) = p / sum(p)
            s = np.exp(s) / np.exp(s).sum(axis=1, keepdims=True) * rng.uniform(0.8, 1.2, (m, 1))
        heads.append(HeadDetections(b, s, rng.uniform(0.01, 0.1, (m, 7))))
    return heads


@pytest.mark.parametrize("setting", ["K=1", "affirmative", "min_cluster_size=1",
                                     "heads missing"])
@pytest.mark.parametrize("score_type", ["logits", "probabilities"])
def test_single_member_clusters_equal_softmax_of_their_logits(setting, score_type):
    """Every single-member cluster's class distribution is softmax(logits / T) of its one
    member (for probabilities: the normalized input), and no input array is written."""
    rng = np.random.default_rng(zlib.crc32(f"{setting} {score_type}".encode()))
    probs = score_type == "probabilities"
    singles = 0
    for _ in range(60):
        C, T = int(rng.integers(2, 6)), float(rng.choice([1.0, 0.5, 2.0]))
        K = 1 if setting == "K=1" else int(rng.integers(2, 5))
        cfg = MergeConfig(voting="consensus" if setting == "K=1" else "affirmative",
                          min_cluster_size=1 if setting == "min_cluster_size=1" else None,
                          temperature=T, score_type=score_type)
        heads = _random_heads(rng, K, C, probs)
        if setting == "heads missing":  # the node merges only the heads still publishing
            heads = heads[:int(rng.integers(1, K))]
        given = [(h.boxes.copy(), h.class_scores.copy(), h.variances) for h in heads]
        given = [(b, s, None if v is None else v.copy()) for b, s, v in given]
        r = merge_heads(heads, cfg)
        for h, (b, s, v) in zip(heads, given):
            np.testing.assert_array_equal(h.boxes, b)
            np.testing.assert_array_equal(h.class_scores, s)
            if v is not None:
                np.testing.assert_array_equal(h.variances, v)
        for c in np.flatnonzero(r.stats.cluster_size == 1):
            (k,), (i,) = r.members(c)
            s = heads[k].class_scores[i]
            want = s / s.sum() if probs and T == 1.0 else softmax(
                (np.log(s) if probs else s) / T)
            np.testing.assert_allclose(r.class_probs[c], want, rtol=1e-12, atol=1e-15)
            assert r.scores[c] == pytest.approx(want[r.labels[c]], rel=1e-12)
            singles += 1
    assert singles >= 20


def test_temperature():
    L = [np.array([0.0, 2.0, 0.5, -1.0, 0.0]), np.array([0.5, 1.0, 1.0, -0.5, 0.0])]
    T = 2.0
    r = merge_heads([head(CAR, L[0]), head(CAR, L[1])], MergeConfig(temperature=T))
    np.testing.assert_allclose(r.class_probs[0], softmax((L[0] + L[1]) / 2 / T))
    P = [softmax(z / T) for z in L]
    assert r.stats.shannon_entropy[0] == pytest.approx(h2(np.mean(P, axis=0)))


def test_probabilities_match_log_probability_logits():
    rng = np.random.default_rng(0)
    boxes = np.stack([CAR + [x, 0, 0, 0, 0, 0, 0] for x in (0, 10, 20)])
    P = [rng.dirichlet(np.ones(5), 3) for _ in range(2)]
    a = merge_heads([head(boxes, p) for p in P], MergeConfig(score_type="probabilities"))
    b = merge_heads([head(boxes, np.log(p)) for p in P])
    np.testing.assert_allclose(a.class_probs, b.class_probs)
    np.testing.assert_allclose(a.stats.shannon_entropy, b.stats.shannon_entropy)


def test_class_aware_separates_overlapping_classes():
    big_ped = CAR.copy()  # same footprint, but a pedestrian label
    heads = [head(CAR, CAR_LOGITS), head(big_ped, PED_LOGITS)]
    agnostic = merge_heads(heads, MergeConfig(voting="affirmative"))
    assert len(agnostic) == 1 and agnostic.stats.cluster_size[0] == 2
    assert agnostic.stats.mutual_information[0] > 0.1
    aware = merge_heads(heads, MergeConfig(voting="affirmative", class_aware=True))
    assert len(aware) == 2 and sorted(aware.labels.tolist()) == [1, 3]
    assert len(merge_heads(heads, MergeConfig(class_aware=True))) == 0  # consensus


def test_empty_heads():
    for heads in ([], [head(np.zeros((0, 7)), np.zeros((0, 5)))] * 2,
                  [HeadDetections(np.zeros((0, 7)), np.zeros(0))] * 3):
        r = merge_heads(heads)
        assert len(r) == 0 and r.boxes.shape == (0, 7)
        assert r.stats.predictive_variance.shape == (0, 7)
        assert r.member_cluster.shape == (0,)
    assert merge_heads([head(np.zeros((0, 7)), np.zeros((0, 5)))] * 2).class_probs.shape == (0, 5)


def test_a_head_with_zero_boxes():
    heads = [head([CAR, PED + [20, 0, 0, 0, 0, 0, 0]], np.stack([CAR_LOGITS, PED_LOGITS]), VAR),
             HeadDetections(np.zeros((0, 7)), np.zeros(0))]
    assert len(merge_heads(heads)) == 0          # K = 2 still needs 2 votes
    r = merge_heads(heads, MergeConfig(voting="affirmative"))
    assert len(r) == 2 and r.member_head.tolist() == [0, 0]
    np.testing.assert_array_equal(r.stats.epistemic_total_variance, 0.0)
    np.testing.assert_allclose(r.stats.aleatoric_total_variance, VAR.sum())


def test_invalid_members_are_noise_and_unknown_variances_nan():
    bad = CAR.copy()
    bad[0] = np.nan
    nan_scores = CAR_LOGITS.copy()
    nan_scores[2] = np.nan
    h0 = HeadDetections(np.stack([CAR, bad, CAR]), np.stack([CAR_LOGITS, CAR_LOGITS, nan_scores]))
    r = merge_heads([h0, head(CAR, CAR_LOGITS)])
    assert r.member_cluster.tolist() == [0, -1, -1, 0]
    assert np.isnan(r.stats.aleatoric_total_variance[0])
    assert np.isnan(r.stats.predictive_variance[0]).all()
    assert r.stats.epistemic_total_variance[0] == 0.0
    # a -inf logit is invalid, a probability 0 is not
    minus_inf = CAR_LOGITS.copy()
    minus_inf[4] = -np.inf
    r = merge_heads([head(CAR, minus_inf), head(CAR, CAR_LOGITS)])
    assert r.member_cluster.tolist() == [-1, -1]
    p = np.exp(CAR_LOGITS)
    p[4] = 0.0
    cfg = MergeConfig(score_type="probabilities")
    assert merge_heads([head(CAR, p), head(CAR, p)], cfg).member_cluster.tolist() == [0, 0]
    # finite entries whose sum overflows: invalid too (no infinite mean box)
    huge = CAR.copy()
    huge[:2] = 1e308
    r = merge_heads([head(huge, CAR_LOGITS), head(CAR, CAR_LOGITS), head(CAR, CAR_LOGITS)],
                    MergeConfig(voting="affirmative"))
    assert r.member_cluster.tolist() == [-1, 0, 0]


def test_no_background_column():
    L = np.array([0.1, 2.0, 0.3])
    r = merge_heads([head(CAR, L)] * 2, MergeConfig(background_index=None))
    assert r.labels[0] == 1
    r = merge_heads([head(CAR, [3.0, 2.0, 0.3])] * 2, MergeConfig(background_index=None))
    assert r.labels[0] == 0
    with pytest.raises(ValueError, match="background_index"):
        merge_heads([head(CAR, L)], MergeConfig(background_index=5))


def test_shape_errors():
    with pytest.raises(ValueError, match="class scores"):
        merge_heads([HeadDetections(np.stack([CAR, CAR]), CAR_LOGITS[None])])
    with pytest.raises(ValueError, match="class columns"):
        merge_heads([head(CAR, CAR_LOGITS), head(CAR, CAR_LOGITS[:3])])
    with pytest.raises(ValueError, match="variances"):
        merge_heads([HeadDetections(CAR[None], CAR_LOGITS[None], np.zeros((1, 6)))])


def test_from_head_output():
    ho = SimpleNamespace(boxes=np.stack([CAR, PED, CAR]), logits=np.stack([CAR_LOGITS] * 3),
                         variances=np.tile(VAR, (3, 1)), keep=np.array([2, 0]))
    h = HeadDetections.from_head_output(ho)
    assert h.boxes.shape == (2, 7) and h.variances.shape == (2, 7)
    np.testing.assert_array_equal(h.class_scores, ho.logits[[2, 0]])


def test_one_head_boxes_can_share_a_cluster():
    near = CAR + [0.3, 0, 0, 0, 0, 0, 0]  # IoU ~0.87: a head whose NMS kept both
    r = merge_heads([head([CAR, near], CAR_LOGITS), head(CAR, CAR_LOGITS)])
    assert len(r) == 1 and r.stats.cluster_size[0] == 3


@pytest.mark.parametrize("voting", ["affirmative", "consensus", "unanimous"])
def test_head_fraction_counts_distinct_heads(voting):
    # against its definition: distinct (cluster, head) pairs among the members / K
    rng = np.random.default_rng(11)
    base = np.column_stack([rng.uniform(0, 40, (30, 2)), np.zeros(30), rng.uniform(0.5, 5, (30, 2)),
                            np.ones(30), rng.uniform(-3, 3, 30)])
    heads = [head(base[rng.random(30) < 0.8] + rng.normal(0, 0.2, 7) * [1, 1, 0, 0, 0, 0, 0.1],
                  rng.normal(0, 1, 5)) for _ in range(4)]
    heads[1] = head(np.vstack([heads[1].boxes, heads[1].boxes[:5] + 0.1]), rng.normal(0, 1, 5))
    r = merge_heads(heads, MergeConfig(voting=voting))
    want = np.array([len(set(r.members(c)[0].tolist())) for c in range(len(r))]) / 4
    np.testing.assert_array_equal(r.head_fraction(), want)
    np.testing.assert_array_equal(r.head_fraction(5), want * 4 / 5)
    assert (r.stats.cluster_size > 4 * want).any()  # a cluster with one head twice
    with pytest.raises(ValueError, match="heads outside"):
        r.head_fraction(2)


def test_sklearn_option_gives_the_same_merge():
    rng = np.random.default_rng(5)
    base = np.column_stack([rng.uniform(0, 40, (30, 2)), np.zeros(30), rng.uniform(0.5, 5, (30, 2)),
                            np.ones(30), rng.uniform(-3, 3, 30)])
    heads = [head(base + rng.normal(0, 0.2, base.shape) * [1, 1, 0, 0, 0, 0, 0.1],
                  rng.normal(0, 1, (30, 5))) for _ in range(3)]
    for voting in ("affirmative", "consensus", "unanimous"):
        a = merge_heads(heads, MergeConfig(voting=voting))
        b = merge_heads(heads, MergeConfig(voting=voting, dbscan="sklearn"))
        np.testing.assert_array_equal(a.member_cluster, b.member_cluster)
        np.testing.assert_allclose(a.boxes, b.boxes)


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("temperature", [1.0, 1.7])
def test_merged_clusters_equal_their_numpy_definition(seed, temperature):
    # the merge runs as one compiled pass: per cluster the members ordered by confidence
    # (ties: lowest pooled row, as np.lexsort), mean box with the top member's yaw and
    # softmax(mean logits / T), checked against numpy on random frames of three heads
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-40, 40, (25, 2))
    heads = []
    for _ in range(3):
        n = rng.integers(15, 25)
        pick = rng.choice(len(centres), n, replace=False)
        b = np.column_stack([centres[pick] + rng.normal(0, 0.2, (n, 2)), rng.normal(-1, 0.1, n),
                             rng.uniform(3.5, 4.5, n), rng.uniform(1.6, 2.0, n),
                             rng.uniform(1.4, 1.7, n), rng.uniform(-np.pi, np.pi, n)])
        logits = rng.normal(0, 2, (n, 5))
        logits[rng.random(n) < 0.2] = logits[0]   # equal confidences: ties
        heads.append(HeadDetections(b, logits, rng.uniform(0, 0.1, (n, 7))))
    r = merge_heads(heads, MergeConfig(temperature=temperature))
    boxes = np.concatenate([h.boxes for h in heads])
    logits = np.concatenate([h.class_scores for h in heads])
    z = logits / temperature
    probs = np.exp(z - z.max(axis=1, keepdims=True))
    probs /= probs.sum(axis=1, keepdims=True)
    conf = probs[:, 1:].max(axis=1)
    lab = r.member_cluster
    assert len(r) > 5 and (lab >= 0).sum() > len(r)
    keep = np.flatnonzero(lab >= 0)
    order = keep[np.lexsort((-conf[keep], lab[keep]))]
    g = lab[order]
    starts = np.flatnonzero(np.r_[True, g[1:] != g[:-1]])
    counts = np.diff(starts, append=len(order))
    want = np.add.reduceat(boxes[order], starts, axis=0) / counts[:, None]
    want[:, 6] = boxes[order[starts], 6]
    mz = np.add.reduceat(logits[order], starts, axis=0) / counts[:, None] / temperature
    cp = np.exp(mz - mz.max(axis=1, keepdims=True))
    cp /= cp.sum(axis=1, keepdims=True)
    np.testing.assert_array_equal(r.top_member, order[starts])
    np.testing.assert_allclose(r.boxes, want, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(r.class_probs, cp, rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(r.labels, 1 + np.argmax(cp[:, 1:], axis=1))
    np.testing.assert_allclose(r.scores, cp[np.arange(len(r)), r.labels], rtol=1e-12)
    np.testing.assert_array_equal(r.stats.cluster_size, counts)
