"""Tests for lidar_quality_core.mimo.outputs (the output messages' numbers in one pass)."""
import numpy as np
import pytest

from lidar_quality_core.mimo.merging import HeadDetections, MergeConfig, merge_heads
from lidar_quality_core.mimo.outputs import output_tables


def _merge(seed):
    rng = np.random.default_rng(seed)
    base = np.column_stack([rng.uniform(0, 40, (30, 2)), np.zeros(30), rng.uniform(0.5, 5, (30, 2)),
                            np.ones(30), rng.uniform(-3, 3, 30)])
    heads = []
    for k in range(3):
        b = base + rng.normal(0, 0.2, base.shape) * [1, 1, 0, 0, 0, 0, 0.1]
        var = rng.uniform(0.01, 0.2, (30, 7))
        var[rng.random((30, 7)) < 0.2] = np.nan   # unknown predicted variances
        heads.append(HeadDetections(b, rng.normal(0, 1, (30, 5)), None if k == 2 else var))
    return merge_heads(heads, MergeConfig(voting="affirmative"))


def _numpy_chain(m, conf, iou, rows, scale):
    # what output_messages computed before (mimo_ros.pipeline, 856570b)
    fg = m.class_probs[:, 1:]
    if scale:
        with np.errstate(invalid="ignore", divide="ignore"):
            s = np.where(np.isfinite(conf) & (m.scores > 0), conf / m.scores, 1.0)
        fg = fg * s[:, None]
    st = m.stats
    pred = st.predictive_variance
    cov = np.zeros((len(m), 6))
    xyzyaw = [0, 1, 2, 6]
    cov[:, [0, 1, 2, 5]] = np.where(np.isnan(pred[:, xyzyaw]), st.epistemic_variance[:, xyzyaw],
                                    pred[:, xyzyaw])
    figures = np.column_stack([st.shannon_entropy, st.aleatoric_entropy, st.mutual_information,
                               st.epistemic_total_variance, st.aleatoric_total_variance, conf, iou])
    return fg[rows], cov[rows], figures


def _bits(a):
    return np.ascontiguousarray(a).view(np.uint64)


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("scale", [True, False])
def test_output_tables_equal_the_numpy_chain_to_the_bit(seed, scale):
    m = _merge(seed)
    rng = np.random.default_rng(seed + 10)
    n = len(m)
    assert n > 10 and np.isnan(m.stats.predictive_variance).any()
    conf, iou = rng.random(n), rng.random(n)
    conf[::5] = np.nan                  # no confidence: unscaled
    m.scores[1::7] = 0.0                # p(label) 0: unscaled
    m.scores[2::9] = -0.0
    for rows in (np.arange(n), np.flatnonzero(rng.random(n) < 0.5), np.zeros(0, np.int64)):
        got = output_tables(m, conf, iou, rows, scale=scale)
        want = _numpy_chain(m, conf, iou, rows, scale)
        for g, w in zip(got, want):
            assert g.shape == w.shape
            np.testing.assert_array_equal(_bits(g), _bits(w))


def test_output_tables_take_other_dtypes_and_layouts_converted():
    # the merge's own arrays go to the kernel as they are; others (float32 scores, a
    # strided view, int32 rows, lists) are converted first, with the same result
    m = _merge(1)
    n = len(m)
    rng = np.random.default_rng(3)
    conf, iou = rng.random(n), rng.random(n).astype(np.float32).astype(np.float64)
    rows = np.flatnonzero(rng.random(n) < 0.6)
    want = output_tables(m, conf, iou, rows, scale=True)
    wide = np.repeat(conf, 2)[::2]                      # strided, the same values
    for c, i, r in ((wide, iou.astype(np.float32), rows.astype(np.int32)),
                    (conf.tolist(), iou, rows.tolist())):
        got = output_tables(m, c, i, r, scale=True)
        for g, w in zip(got, want):
            np.testing.assert_array_equal(_bits(g), _bits(w))


def test_output_tables_refuse_rows_outside_the_merge():
    m = _merge(0)
    with pytest.raises(IndexError, match="outside"):
        output_tables(m, np.ones(len(m)), np.ones(len(m)), np.array([len(m)]), scale=True)
