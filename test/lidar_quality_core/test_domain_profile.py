"""Domain profile and drift score: JSON round trip, in-domain samples near 0 at every
sample size, shifts of location, scale and missing rate scored high, point masses
(discrete features), the rolling monitor's levels and its words."""
import json

import numpy as np
import pytest
from lidar_quality_core.domain_profile import (ERROR, OK, DomainProfile, DriftMonitor,
                                               QuantityProfile, explain, psi)


@pytest.fixture(scope="module")
def gamma():
    return QuantityProfile.of(np.random.default_rng(0).gamma(2.0, 1.0, 20_000))


def test_json_round_trip():
    rng = np.random.default_rng(1)
    p = DomainProfile.of({"a": rng.normal(size=500), "b": np.r_[rng.normal(size=50), [np.nan]]})
    back = DomainProfile.from_json(json.loads(json.dumps(p.to_json())))
    assert back == p
    assert back.quantities["b"].missing == pytest.approx(1 / 51)
    with pytest.raises(ValueError, match="version"):
        DomainProfile.from_json({"version": 9, "quantities": {}})


@pytest.mark.parametrize("n", [100, 1000, 10_000])
def test_in_domain_samples_score_near_zero(gamma, n):
    rng = np.random.default_rng(n)
    scores = np.array([psi(gamma, rng.gamma(2.0, 1.0, n)) for _ in range(200)])
    assert np.percentile(scores, 99) < 0.25       # the WARN reading, 1 % of windows
    assert np.median(scores) < 0.02


@pytest.mark.parametrize("shift", ["location", "scale", "missing"])
def test_shifts_score_high(gamma, shift):
    rng = np.random.default_rng(2)
    v = rng.gamma(2.0, 1.0, 500)
    v = {"location": v + 1.5, "scale": v * 40.0,
         "missing": np.where(rng.random(500) < 0.5, np.nan, v)}[shift]
    assert psi(gamma, v) > 0.5


def test_point_masses_of_a_discrete_feature():
    rng = np.random.default_rng(3)
    prof = QuantityProfile.of(rng.integers(0, 4, 20_000).astype(float))
    same = [psi(prof, rng.integers(0, 4, 200).astype(float)) for _ in range(100)]
    assert max(same) < 0.25
    assert psi(prof, rng.integers(2, 4, 200).astype(float)) > 0.5   # half the classes gone


def test_empty_sides_are_nan(gamma):
    assert np.isnan(psi(gamma, []))
    assert np.isnan(psi(QuantityProfile.of([np.nan]), [1.0, 2.0]))


def test_monitor_levels_and_words():
    rng = np.random.default_rng(4)
    prof = DomainProfile.of({"mean_intensity": rng.uniform(0, 1, 5000),
                             "score": rng.beta(5, 2, 20_000)})
    mon = DriftMonitor(prof, window=10, min_values=30)
    for _ in range(30):                                    # in domain: quiet
        r = mon.add({"mean_intensity": rng.uniform(0, 1, 8), "score": rng.beta(5, 2, 40)})
        assert r.level == OK, r
    levels = []
    for _ in range(10):                                    # intensity read as 0..255
        r = mon.add({"mean_intensity": rng.uniform(0, 255, 8), "score": rng.beta(5, 2, 40)})
        levels.append(r.level)
    assert levels[-1] == ERROR and levels.index(ERROR) <= 5
    assert r.drifted[0][0] == "mean_intensity"
    assert "intensity scale?" in r.text and "x)" in r.text


def test_monitor_needs_enough_values():
    prof = DomainProfile.of({"points": np.random.default_rng(5).normal(1e5, 1e3, 1000)})
    mon = DriftMonitor(prof, window=50, min_values=30)
    for k in range(29):                                     # one value a frame
        assert mon.add({"points": [5e4]}).score == 0.0     # not scored yet
    r = mon.add({"points": [5e4]})
    assert r.level == ERROR and "points" in r.text and "another sensor" in r.text
    assert r.scored == 1


def test_explain_reads_medians():
    prof = QuantityProfile.of(np.linspace(0, 2, 101))
    assert explain("detector score", prof, [10.0, 10.0]) == (
        "detector score median 10, training median 1 (10x): another detector?")
    with pytest.raises(ValueError):
        DriftMonitor(DomainProfile(), warn=0.6, error=0.5)


def test_spread_between_sequences_is_not_drift():
    """A quantity that differs by scene (e.g. where the objects are): one training
    sequence's values already differ from the mix, so a window of one new scene is not a
    shift; a shift well beyond that still is."""
    rng = np.random.default_rng(6)
    centres = rng.uniform(-20, 20, 12)
    values = np.concatenate([rng.normal(c, 2.0, 300) for c in centres])
    groups = np.repeat(np.arange(12), 300)
    prof = DomainProfile.of({"mean_y": values}, {"mean_y": groups})
    assert prof.quantities["mean_y"].spread > 0.5
    assert DomainProfile.of({"mean_y": values}).quantities["mean_y"].spread == 0.0
    mon = DriftMonitor(prof, window=5)
    for _ in range(5):                                    # a new scene of the same kind
        r = mon.add({"mean_y": rng.normal(rng.uniform(-15, 15), 2.0, 40)})
    assert r.level == OK, r
    for _ in range(5):                                    # far outside every scene
        r = mon.add({"mean_y": rng.normal(80.0, 2.0, 40)})
    assert r.level == ERROR
    back = DomainProfile.from_json(json.loads(json.dumps(prof.to_json())))
    assert back == prof
    with pytest.raises(ValueError, match="group labels"):
        DomainProfile.of({"a": [1.0, 2.0]}, {"a": [0]})


def test_monitor_scores_are_psi_of_the_window():
    """The monitor keeps bin counts per frame (cheap per frame); its scores are psi of the
    window's values minus the spread, quantity by quantity, NaN and ties included."""
    from lidar_quality_core.domain_profile import fine_counts, psi_counts

    rng = np.random.default_rng(7)
    train = {"a": rng.normal(size=3000), "b": rng.integers(0, 3, 3000).astype(float),
             "c": np.r_[rng.gamma(2.0, 1.0, 2900), np.full(100, np.nan)]}
    prof = DomainProfile.of(train, {k: np.repeat(np.arange(6), 500) for k in train})
    mon = DriftMonitor(prof, window=4, min_frames=1, min_values=1, top=3, warn=0.0)
    frames = [{"a": rng.normal(0.5, 1.0, 25), "b": rng.integers(0, 2, 25).astype(float),
               "c": np.r_[rng.gamma(2.0, 2.0, 20), [np.nan] * 5]} for _ in range(7)]
    for k, f in enumerate(frames):
        r = mon.add(f)
        window = frames[max(0, k - 3):k + 1]
        for name, score in r.drifted:
            q = prof.quantities[name]
            v = np.concatenate([w[name] for w in window])
            assert score == pytest.approx(psi(q, v) - q.spread, abs=1e-4)
            assert psi_counts(q, fine_counts(q, v)) == psi(q, v)


def test_domain_check_verdict_as_the_quality_messages_carry_it():
    """The verdict's state for the quality messages: off without a profile, warming up until
    a quantity is scored (fewer than min_frames frames, or fewer than 30 values of each
    quantity after them), then the level; the window's score (NaN before), its frames and
    the drifted quantities; passthrough only at ERROR with drift_action passthrough."""
    from lidar_quality_core.domain_profile import DomainCheck, DriftParameters
    from lidar_quality_msgs.msg import (ClusterUncertaintyArray, DetectionQualityArray,
                                        SegmentQualityArray)

    off = DomainCheck(None)({"points": [1.0]})
    assert (off.state, off.frames, off.quantities, off.passthrough) == ("off", 0, (), False)
    for cls in (DetectionQualityArray, SegmentQualityArray, ClusterUncertaintyArray):
        f = off.message_fields(cls)
        assert f.pop("drift_level") == cls.DRIFT_OFF and np.isnan(f.pop("drift_score"))
        assert f == {"version": cls.MESSAGE_VERSION, "drift_window_frames": 0,
                     "drift_quantities": "", "passthrough": False}
        cls(**off.message_fields(cls))     # the message takes them as they are

    rng = np.random.default_rng(8)
    prof = DomainProfile.of({"points per frame": rng.normal(1e5, 1e3, 2000)})
    for action in ("flag", "passthrough"):
        check = DomainCheck(prof, DriftParameters(drift_window=50, drift_action=action))
        # one value a frame: past min_frames (10) still unscored until 30 values are in
        states = [check({"points per frame": [rng.normal(1e5, 1e3)]}) for _ in range(30)]
        assert [v.state for v in states[:29]] == ["warming up"] * 29
        assert all(np.isnan(v.score) and not v.passthrough for v in states[:29])
        # /diagnostics says the same: no score (not a 0) while the window fills
        assert all(v.values["drift.level"] == "warming up" and "drift.score" not in v.values
                   for v in states[:29])
        assert [v.frames for v in states] == list(range(1, 31))
        assert states[-1].state == "OK"
        assert states[-1].score == pytest.approx(states[-1].values["drift.score"], abs=5e-4)
        for _ in range(20):                  # another sensor: half the points
            v = check({"points per frame": [rng.normal(5e4, 1e3)]})
        assert v.state == "ERROR" and v.error and v.quantities == ("points per frame",)
        assert v.passthrough == (action == "passthrough")
        f = v.message_fields(DetectionQualityArray)
        assert f["drift_level"] == DetectionQualityArray.DRIFT_ERROR
        assert f["drift_score"] == float(np.float32(v.score))   # as the message carries it
        assert f["drift_quantities"] == v.values["drift.quantities"] == "points per frame"
        assert f["passthrough"] == v.passthrough and f["drift_window_frames"] == 50
    # ordered by severity: >= DRIFT_WARN is an alarm, 0 is a message that does not say
    c = DetectionQualityArray
    assert (c.DRIFT_UNKNOWN, c.DRIFT_OFF, c.DRIFT_WARMING_UP, c.DRIFT_OK, c.DRIFT_WARN,
            c.DRIFT_ERROR) == (0, 1, 2, 3, 4, 5)


def test_check_rebuilds_its_words_on_change_and_every_words_every_frames():
    """DomainCheck's warning words: rebuilt (as DriftMonitor.add words them) on the first
    drifted frame, whenever the level or the drifted quantities change, and every
    WORDS_EVERY frames; in between the last words stand. Score, level and quantities
    are every frame's, as a monitor's that words every frame."""
    from lidar_quality_core.domain_profile import WARN, DomainCheck, DriftParameters

    rng = np.random.default_rng(11)
    train = {"a": rng.normal(size=3000), "b": rng.normal(size=3000)}
    prof = DomainProfile.of(train, {k: np.repeat(np.arange(6), 500) for k in train})
    params = DriftParameters(drift_window=20)
    check, every_frame = DomainCheck(prof, params), DriftMonitor(prof, window=20)
    words, rebuilt_at, last, stale = None, [], None, 0
    for k in range(60):
        # "a" drifts further every frame (its median moves); "b" joins from frame 30
        frame = {"a": rng.normal(0.1 * k, 1.0, 40), "b": rng.normal(3.0 * (k >= 30), 1.0, 40)}
        v = check(frame)
        r = every_frame.add(frame)
        assert (v.state, v.quantities) == (("warming up" if not r.scored else
                                             ("OK", "WARN", "ERROR")[r.level]),
                                            tuple(q for q, _ in r.drifted))
        if r.level < WARN:
            assert v.issue is None
            last = None
            continue
        of = (r.level, tuple(q for q, _ in r.drifted))
        text = v.issue.split("frames): ", 1)[1]
        if of != last or k - rebuilt_at[-1] >= DomainCheck.WORDS_EVERY:
            assert text == r.text          # rebuilt: this frame's words
            rebuilt_at.append(k)
            words = text
        else:
            assert text == words           # unchanged since the last rebuild
            stale += text != r.text        # while the frame's own words moved on
        last = of
    assert len(rebuilt_at) >= 4 and any(b - a == DomainCheck.WORDS_EVERY
                                        for a, b in zip(rebuilt_at, rebuilt_at[1:]))
    assert stale > 0


@pytest.mark.parametrize("branchless", [True, False])
def test_monitor_counts_are_fine_counts(branchless):
    """A frame's bin counts, compared against every edge at once (finite, ascending edges)
    or up to the first edge above the value (any other row), are ``fine_counts``: values
    on an edge, in point masses, NaN and inf included."""
    from lidar_quality_core.domain_profile import fine_counts

    rng = np.random.default_rng(11)
    train = {"a": rng.normal(size=3000), "b": rng.integers(0, 3, 3000).astype(float)}
    prof = DomainProfile.of(train, {k: np.repeat(np.arange(6), 500) for k in train})
    mon = DriftMonitor(prof, window=3, min_frames=1, min_values=1)
    assert mon._sorted_edges.all()
    if not branchless:
        mon._sorted_edges[:] = False
    edges_a = np.asarray(prof.quantities["a"].quantiles[1:-1])
    X = np.column_stack([np.r_[rng.normal(size=60), edges_a, [np.nan, np.inf, -np.inf]],
                         np.r_[rng.integers(-1, 4, 60 + len(edges_a)), [np.nan] * 3]])
    mon.add((("a", "b"), X))
    for j, name in enumerate(("a", "b")):
        np.testing.assert_array_equal(mon._counts[-1][mon._index[name]],
                                      fine_counts(prof.quantities[name], X[:, j]))


def test_monitor_reads_a_matrix_as_its_columns():
    """``add((names, X))`` (lms_node's metrics) scores and words as ``add`` of the columns,
    a column the profile does not know left out."""
    rng = np.random.default_rng(3)
    train = {"a": rng.normal(size=3000), "b": rng.gamma(2.0, 1.0, 3000)}
    prof = DomainProfile.of(train, {k: np.repeat(np.arange(6), 500) for k in train})
    by_dict, by_matrix = (DriftMonitor(prof, window=3, min_frames=1, min_values=1, warn=0.0)
                          for _ in range(2))
    for _ in range(5):
        X = np.column_stack([rng.normal(1.0, 1.0, 40), rng.uniform(size=40),
                             rng.gamma(2.0, 3.0, 40)])
        X[rng.uniform(size=X.shape) < 0.1] = np.nan
        names = ("a", "unknown", "b")
        r1 = by_dict.add(dict(zip(names, X.T)))
        r2 = by_matrix.add((names, X))
        assert (r1.score, r1.level, r1.drifted, r1.text, r1.frames, r1.scored) == (
            r2.score, r2.level, r2.drifted, r2.text, r2.frames, r2.scored)
        assert r2.scored == 2


def test_monitor_reads_groups_of_matrices_as_their_columns():
    """``add([(names, X), (names, X)])`` (lmd_node: the boxes' features and one value per
    frame) scores and words as ``add`` of the columns."""
    rng = np.random.default_rng(4)
    train = {"a": rng.normal(size=3000), "b": rng.gamma(2.0, 1.0, 3000),
             "points": rng.normal(1e5, 1e4, 3000)}
    prof = DomainProfile.of(train, {k: np.repeat(np.arange(6), 500) for k in train})
    by_dict, by_groups = (DriftMonitor(prof, window=4, min_frames=1, min_values=1, warn=0.0)
                          for _ in range(2))
    for k in range(8):
        X = np.column_stack([rng.normal(1.0, 1.0, 30), rng.gamma(2.0, 3.0, 30)])
        X[rng.uniform(size=X.shape) < 0.1] = np.nan
        points = 5e4 * (1 + k)
        r1 = by_dict.add({"a": X[:, 0], "b": X[:, 1], "points": [points]})
        r2 = by_groups.add([(("a", "b"), X), (("points", "unknown"), [[points, 1.0]])])
        assert (r1.score, r1.level, r1.drifted, r1.text, r1.frames, r1.scored) == (
            r2.score, r2.level, r2.drifted, r2.text, r2.frames, r2.scored)
        assert r2.scored == 3



@pytest.mark.parametrize("seed", range(4))
def test_window_scores_are_psi_counts_of_each_row(seed):
    """The compiled window scoring against psi_counts, row by row: every bin count from 2
    to N_FINE (n_bins 8 puts linspace on .5 and rounds half to even), empty profiles,
    too few values, missing values."""
    from lidar_quality_core.domain_profile import (N_FINE, VALUES_PER_BIN, _fine_mass,
                                                   _window_scores, psi_counts)

    rng = np.random.default_rng(seed)
    quantities = {f"q{k}": rng.gamma(1.0 + k % 5, 1.0, 500 + 100 * k) for k in range(24)}
    quantities["q3"][:50] = np.nan
    prof = DomainProfile.of(quantities, {k: np.repeat(np.arange(5), len(v) // 5 + 1)[:len(v)]
                                         for k, v in quantities.items()})
    qs = list(prof.quantities.values())
    mass = np.array([_fine_mass(q) for q in qs])
    train_n = np.array([q.count for q in qs], float)
    spread = np.array([q.spread for q in qs], float)
    empty = train_n == 0
    empty[5] = True
    n_values = [VALUES_PER_BIN * b + int(rng.integers(0, VALUES_PER_BIN))
                for b in range(2, N_FINE + 1)] + [3, 200, 1000, 7]
    total = np.zeros((len(qs), N_FINE + 1))
    for r, n in enumerate(n_values[:len(qs)]):
        total[r] = rng.multinomial(n, np.r_[np.full(N_FINE, 0.9 / N_FINE), 0.1])
    out = np.full(len(qs), np.nan)
    _window_scores(total, mass, train_n, spread, empty, 10.0, out)
    for r, q in enumerate(qs):
        n = total[r].sum()
        if n < 10 or empty[r]:
            assert np.isnan(out[r])
        else:
            assert out[r] == pytest.approx(psi_counts(q, total[r], mass[r]) - q.spread,
                                           rel=1e-12, abs=1e-14), r


def test_ranking_is_numpys_stable_argsort_of_the_finite_scores():
    from lidar_quality_core.domain_profile import _ranked

    rng = np.random.default_rng(3)
    for _ in range(300):
        n = int(rng.integers(0, 12))
        s = rng.choice([0.0, -0.0, 0.3, 0.3, 1.5, np.nan, np.inf, -np.inf], n) if rng.random() < 0.5 \
            else rng.normal(size=n)
        scored = np.flatnonzero(np.isfinite(s))
        for k in (1, 3, 20):
            want = scored[np.argsort(-s[scored], kind="stable")[:k]]
            got, n_scored = _ranked(np.ascontiguousarray(s, np.float64), k)
            np.testing.assert_array_equal(got, want)
            assert n_scored == len(scored)
