"""lms_ros.pipeline: decoding (float32 / uint8 probabilities, one or two clouds, ring
layouts), probability checks, frame metrics and the node's frame work with real models."""
import numpy as np
import pytest
from lidar_quality_core import meta_model
from lidar_quality_core.pointcloud import (CloudFormatError, cloud_to_structured, create_cloud,
                                          read_fields)
from lms_ros.pipeline import (CLASS_NAMES, NO_LABEL, OUTPUT_FIELDS, RESULT_FIELDS, LmsProcessor,
                              LmsSettings, decode, default_model_paths, frame_metrics)
from lidar_quality_core.lms.segment_metrics import compute_segments, dispersion, to_points
from lms_scans import COLS, cloud, frame_cloud, scans, train_models
from lms_scans import frame_probs as noisy_probs
from lms_scans import settings as _settings
from std_msgs.msg import Header

N_CLASSES = len(CLASS_NAMES)


@pytest.fixture(scope="module")
def frames():
    return scans(3, 2)


# -- settings -------------------------------------------------------------------------------


def test_settings_schema_and_class_map():
    from lidar_sim.classes import CLASS_NAMES as SIM
    from reference_perception.messages import probability_field

    s = LmsSettings()
    assert s.class_names == SIM
    assert s.field_names() == tuple(probability_field(c) for c in SIM)
    assert len(s.metric_names()) == 86 + 2 * N_CLASSES
    assert "P_traffic-sign" in s.metric_names()
    cfg = s.range_config()
    assert cfg.shape == (64, 2048) and cfg.fov_up_deg == 3.0 and cfg.fov_down_deg == -25.0
    s.validate()
    c, r = default_model_paths()
    assert c.name == "lms_classifier.joblib" and r.name == "lms_regressor.joblib"
    assert c.parent.name == "lms"


@pytest.mark.parametrize("kw, word", [
    (dict(class_names=()), "class_names"),
    (dict(class_names=("a-b", "a_b")), "duplicate"),
    (dict(class_names=("road", "x")), "clash"),
    (dict(channels=0), "channels"),
    (dict(width=1.5), "width"),
    (dict(fov_up_deg=-30.0), "fov"),
    (dict(min_segment_points=0), "min_segment_points"),
    (dict(sum_tolerance=-0.1), "sum_tolerance"),
    (dict(ring_field=""), "ring_field"),
    (dict(width=100_000_000), "width must be <= 36000"),
    (dict(width=36001), "0.01 deg"),
    (dict(channels=1025), "channels must be <= 1024"),
    (dict(channels=1024, width=8192), r"1024 x 8192 = 8388608 pixels exceeds 4194304"),
    (dict(ring_field="intensity"), "ring_field 'intensity' names a coordinate / intensity"),
    (dict(ring_field="z"), "ring_field 'z'"),
])
def test_settings_validation(kw, word):
    with pytest.raises(ValueError, match=word):
        LmsSettings(**kw).validate()


def test_settings_bounds_accept_real_sensors():
    for kw in (dict(channels=128, width=2048), dict(channels=64, width=36000),
               dict(channels=1024, width=4096), dict(ring_field="intensity", use_ring=False)):
        LmsSettings(**kw).validate()


# -- decoding ---------------------------------------------------------------------------------


def test_decode_matches_compute_segments(frames):
    f = frames[0]
    p = noisy_probs(f, 1)
    s = _settings()
    inp = decode(frame_cloud(f, p), s)
    assert inp.n_renormalized == 0 and inp.n_invalid_points == 0 and not inp.quantized
    np.testing.assert_array_equal(inp.xyz, f.xyz.astype(np.float32))
    np.testing.assert_array_equal(inp.probs, p)
    np.testing.assert_array_equal(inp.ring, f.ring)
    res = frame_metrics(inp, s)
    ref = compute_segments(f.xyz, p, s.range_config(), ring=f.ring, intensity=f.intensity,
                           min_points=10, class_names=CLASS_NAMES)
    assert res.names == s.metric_names()
    np.testing.assert_array_equal(res.point_segment, ref.point_segment)
    np.testing.assert_allclose(res.features, ref.features, rtol=1e-12, atol=1e-12)
    assert 20 < len(res.kept_ids) < res.n_segments       # the scan has real segments


def test_uint8_equals_float32_on_representable_probabilities(frames):
    """Probabilities that are multiples of 1/255: the uint8 cloud decodes to exactly the
    float32 one, hence the same segments and metrics."""
    f = frames[0]
    q = np.rint(noisy_probs(f, 2) * 255)
    # make every row sum to exactly 255 (fix the largest entry)
    top = q.argmax(axis=1)
    q[np.arange(len(q)), top] += 255 - q.sum(axis=1)
    assert (q >= 0).all()
    s = _settings()
    a = decode(frame_cloud(f, (q / 255).astype(np.float32)), s)
    b = decode(frame_cloud(f, q.astype(np.uint8)), s)
    assert b.quantized and b.n_renormalized == 0
    np.testing.assert_array_equal(a.probs, b.probs)
    ra, rb = frame_metrics(a, s), frame_metrics(b, s)
    np.testing.assert_array_equal(ra.point_segment, rb.point_segment)
    np.testing.assert_array_equal(ra.features, rb.features)


def test_uint8_softmax_gives_the_same_segments_up_to_quantization(frames):
    f = frames[1]
    p = noisy_probs(f, 3)
    s = _settings()
    a, b = decode(frame_cloud(f, p), s), decode(frame_cloud(f, p, quantize=True), s)
    # rounding errors of 14 values stay inside the widened tolerance: nothing flagged
    assert b.n_renormalized == 0
    assert np.abs(b.probs - p).max() <= 0.5 / 255 + 1e-6
    ra, rb = frame_metrics(a, s), frame_metrics(b, s)
    srt = np.sort(p, axis=1)
    clear = srt[:, -1] - srt[:, -2] > 1.0 / 255          # argmax cannot flip there
    np.testing.assert_array_equal(ra.point_class[clear], rb.point_class[clear])
    assert (ra.point_class != rb.point_class).mean() < 0.005
    assert abs(ra.n_segments - rb.n_segments) <= 0.02 * ra.n_segments + 2
    # a segment of the float32 cloud keeps (almost) all its points in one uint8 segment
    both = (ra.point_segment >= 0) & (rb.point_segment >= 0)
    pairs = np.unique(np.stack([ra.point_segment[both], rb.point_segment[both]]), axis=1)
    assert pairs.shape[1] <= ra.n_segments * 1.05 + 2


def test_renormalization_is_counted_and_applied(frames):
    f = frames[0]
    p = noisy_probs(f, 4)
    scaled = p.copy()
    rows = np.arange(0, len(p), 7)
    scaled[rows] *= 1.5
    scaled[rows[::2]] *= 0.3                              # some sum to 0.45
    s = _settings()
    inp = decode(frame_cloud(f, scaled), s)
    assert inp.n_renormalized == len(rows)
    np.testing.assert_allclose(inp.probs.sum(axis=1), 1.0, atol=1e-5)
    np.testing.assert_allclose(inp.probs, p, atol=1e-6)
    # within the tolerance: left as is
    inp2 = decode(frame_cloud(f, p * 1.01), s)
    assert inp2.n_renormalized == 0
    np.testing.assert_array_equal(inp2.probs, (p * 1.01).astype(np.float32))
    assert decode(frame_cloud(f, p * 1.01), _settings(sum_tolerance=0.005)).n_renormalized \
        == len(p)


def test_bad_probabilities_and_nan_points(frames):
    f = frames[0]
    p = noisy_probs(f, 5)
    xyz = f.xyz.astype(np.float32).copy()
    p[10, 3] = np.nan
    p[11, 2] = -0.2
    p[12] = 0.0
    xyz[20] = np.nan
    xyz[21, 2] = np.inf
    s = _settings()
    inp = decode(cloud(xyz, p, intensity=f.intensity, ring=f.ring), s)
    assert inp.n_bad_probabilities == 3
    assert inp.n_invalid_points == 5
    assert not inp.valid[[10, 11, 12, 20, 21]].any() and inp.valid.sum() == len(xyz) - 5
    res = frame_metrics(inp, s)
    assert (res.point_segment[[10, 11, 12, 20, 21]] == -1).all()
    assert np.isfinite(res.features).all()
    # the other points are segmented as without the bad ones' pixels
    good = cloud(np.where(inp.valid[:, None], xyz, np.nan), np.where(inp.valid[:, None], p, 0.5),
                 intensity=f.intensity, ring=f.ring)
    ref = frame_metrics(decode(good, s), s)
    np.testing.assert_array_equal(res.features, ref.features)


def test_missing_probability_field_is_named(frames):
    f = frames[0]
    p = noisy_probs(f, 6)
    names = [c for c in CLASS_NAMES if c != "traffic-sign"]
    msg = cloud(f.xyz, np.delete(p, CLASS_NAMES.index("traffic-sign"), axis=1), names=names)
    with pytest.raises(CloudFormatError, match="traffic_sign") as e:
        decode(msg, _settings())
    assert "input/points" in str(e.value)
    with pytest.raises(CloudFormatError, match="'z'"):
        decode(create_cloud(None, {"x": f.xyz[:, 0], "y": f.xyz[:, 1]}), _settings())


@pytest.mark.parametrize("bad", [np.int16, "count2"])
def test_probability_field_types_are_checked(frames, bad):
    f = frames[0]
    p = noisy_probs(f, 6)
    msg = cloud(f.xyz, p)
    if bad == "count2":
        extra = {"car": np.stack([p[:, 10], p[:, 10]], axis=1)}
    else:
        extra = {"car": (p[:, 10] * 100).astype(bad)}
    names = [c for c in CLASS_NAMES if c != "car"]
    msg = cloud(f.xyz, np.delete(p, CLASS_NAMES.index("car"), axis=1), names=names,
                extra=extra)
    with pytest.raises(CloudFormatError, match="'car'"):
        decode(msg, _settings())


def test_two_clouds(frames):
    f = frames[0]
    p = noisy_probs(f, 7)
    s = _settings()
    one = decode(frame_cloud(f, p), s)
    points = cloud(f.xyz, intensity=f.intensity, ring=f.ring)
    probs = cloud(f.xyz, p, quantize=False)
    two = decode(points, s, probabilities_msg=probs)
    np.testing.assert_array_equal(one.probs, two.probs)
    np.testing.assert_array_equal(one.ring, two.ring)
    np.testing.assert_array_equal(frame_metrics(one, s).features, frame_metrics(two, s).features)
    # a probabilities cloud of bare fields (no xyz) and uint8 is fine too
    bare = create_cloud(None, {c.replace("-", "_"): np.rint(p[:, k] * 255).astype(np.uint8)
                               for k, c in enumerate(CLASS_NAMES)})
    assert decode(points, s, probabilities_msg=bare).quantized
    with pytest.raises(CloudFormatError, match=r"input/probabilities has \d+ points"):
        decode(points, s, probabilities_msg=cloud(f.xyz[:-1], p[:-1]))
    with pytest.raises(CloudFormatError, match="input/probabilities"):
        decode(points, s, probabilities_msg=points)          # no probability fields


def test_ring_flip_and_elevation_rows(frames):
    f = frames[0]
    p = noisy_probs(f, 8)
    # lidar_sim: ring 0 = top. A Velodyne-style cloud numbers the same beams bottom-up.
    velodyne_ring = 63 - f.ring.astype(np.int64)
    msg = cloud(f.xyz, p, intensity=f.intensity, ring=velodyne_ring)
    s = LmsSettings(width=COLS)                               # ring_zero_top=False
    inp = decode(msg, s)
    np.testing.assert_array_equal(inp.ring, f.ring)
    top = decode(frame_cloud(f, p), _settings())
    np.testing.assert_array_equal(frame_metrics(inp, s).features,
                                  frame_metrics(top, _settings()).features)
    assert inp.ring_issue is None
    # without ring (use_ring off): rows from elevation bins of the fov
    s2 = LmsSettings(width=COLS, use_ring=False, fov_up_deg=2.5, fov_down_deg=-25.5)
    inp2 = decode(msg, s2)
    assert inp2.ring is None and inp2.ring_issue is None
    el = np.degrees(np.arcsin(f.xyz[:, 2] / np.linalg.norm(f.xyz, axis=1)))
    want = np.floor((2.5 - el) / (28.0 / 64)).astype(int)
    row = frame_metrics(inp2, s2).projection.row
    np.testing.assert_array_equal(row, want)


def test_ring_outside_the_channels_falls_back_to_elevation_rows(frames):
    """Rings beyond ``channels`` (e.g. a 128-beam ring numbering with channels 64): the
    frame takes the elevation rows, as with use_ring off, and says why (before: the
    out-of-range half of the points silently got no segment)."""
    f = frames[0]
    p = noisy_probs(f, 8)
    s = LmsSettings(width=COLS, fov_up_deg=2.5, fov_down_deg=-25.5)
    no_ring = LmsSettings(width=COLS, use_ring=False, fov_up_deg=2.5, fov_down_deg=-25.5)
    too_high = (63 - f.ring.astype(np.int64)) + 32
    inp = decode(cloud(f.xyz, p, ring=too_high), s)
    assert inp.ring is None
    assert "'ring' holds 32..95" in inp.ring_issue and "outside [0, channels=64)" in inp.ring_issue
    assert f"{np.count_nonzero(too_high > 63)} of {len(f.xyz)}" in inp.ring_issue
    want = frame_metrics(decode(cloud(f.xyz, p), no_ring), no_ring)
    got = frame_metrics(inp, s)
    np.testing.assert_array_equal(got.projection.row, want.projection.row)
    np.testing.assert_array_equal(got.point_segment, want.point_segment)
    assert (got.point_segment[too_high > 63] >= 0).mean() > 0.9
    # a sentinel ring on points without a return (NaN) is no reason to drop the ring
    xyz = f.xyz.astype(np.float32).copy()
    ring = 63 - f.ring.astype(np.int64)
    xyz[:10] = np.nan
    ring[:10] = 255
    inp = decode(cloud(xyz, p, ring=ring), s)
    assert inp.ring_issue is None
    np.testing.assert_array_equal(inp.ring[10:], f.ring[10:])


@pytest.mark.parametrize("kind", ["float", "count2", "negative"])
def test_ring_field_that_is_no_beam_index_falls_back(frames, kind):
    """``ring_field`` naming a float field (e.g. ``ring_field: range``), a multi-value
    field or one with negative values: elevation rows plus the reason; before, the float
    and count-2 cases dropped every frame with a CloudFormatError."""
    f = frames[0]
    p = noisy_probs(f, 8)
    rng = np.linalg.norm(f.xyz, axis=1).astype(np.float32)
    extra = {"float": {"range": rng},
             "count2": {"range": np.stack([f.ring, f.ring], axis=1).astype(np.uint16)},
             "negative": {"range": f.ring.astype(np.int16) - 1}}[kind]
    s = LmsSettings(width=COLS, ring_field="range", ring_zero_top=True)
    inp = decode(cloud(f.xyz, p, extra=extra), s)
    assert inp.ring is None
    assert "ring field 'range'" in inp.ring_issue and "use_ring: false" in inp.ring_issue
    want = {"float": "(float32) is not one integer", "count2": "(count 2) is not one",
            "negative": "holds -1..62"}[kind]
    assert want in inp.ring_issue
    no_ring = LmsSettings(width=COLS, use_ring=False)
    np.testing.assert_array_equal(frame_metrics(inp, s).projection.row,
                                  frame_metrics(decode(cloud(f.xyz, p), no_ring),
                                                no_ring).projection.row)


def test_organized_cloud_and_empty_cloud():
    s = _settings()
    h = Header(frame_id="l")
    rng = np.random.default_rng(0)
    xyz = rng.normal(0, 10, (4, 50, 3)).astype(np.float32)
    p = rng.dirichlet(np.ones(N_CLASSES), (4, 50)).astype(np.float32)
    arr = np.zeros((4, 50), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")]
                   + [(c.replace("-", "_"), "f4") for c in CLASS_NAMES])
    for k, n in enumerate("xyz"):
        arr[n] = xyz[..., k]
    for k, c in enumerate(CLASS_NAMES):
        arr[c.replace("-", "_")] = p[..., k]
    inp = decode(create_cloud(h, arr), s)
    assert inp.shape == (4, 50) and len(inp) == 200 and inp.intensity is None
    np.testing.assert_array_equal(inp.xyz, xyz.reshape(-1, 3))
    empty = decode(cloud(np.zeros((0, 3), np.float32), np.zeros((0, N_CLASSES), np.float32)), s)
    assert len(empty) == 0 and empty.n_invalid_points == 0
    res = frame_metrics(empty, s)
    assert res.n_segments == 0 and res.features.shape == (0, 86 + 2 * N_CLASSES)


# -- the node's frame work with real models ----------------------------------------------------


@pytest.fixture(scope="module")
def models(frames, tmp_path_factory):
    cpath, rpath = train_models(tmp_path_factory.mktemp("lms_models"), frames)
    return meta_model.MetaModels(cpath, rpath, _settings().metric_names())


def test_processor_outputs(frames, models):
    f = frames[1]
    s = _settings()
    p = noisy_probs(f, 9)
    xyz = f.xyz.astype(np.float32).copy()
    xyz[5] = np.nan
    msg = cloud(xyz, p, intensity=f.intensity, ring=f.ring, sec=42)
    out = LmsProcessor(s, models).process(msg, markers=True)
    res = out.result
    conf, iou = models.predict(res.features)
    np.testing.assert_array_equal(out.confidence[res.kept_ids], conf)
    np.testing.assert_array_equal(out.predicted_iou[res.kept_ids], iou)
    assert np.isnan(out.confidence[~res.kept]).all()
    # output/points: same points, same order, the per-point values of their segment
    pc = out.points
    assert pc.header == msg.header and pc.width == len(xyz) and pc.height == 1
    assert [fl.name for fl in pc.fields] == [nm for nm, _ in OUTPUT_FIELDS] == [
        "x", "y", "z", "label", "segment", "confidence", "predicted_iou"]
    np.testing.assert_array_equal(read_fields(pc, ["x", "y", "z"]), xyz)
    seg = read_fields(pc, ["segment"], dtype=np.int64)[:, 0]
    np.testing.assert_array_equal(seg, res.point_segment)
    assert seg[5] == -1
    lab = read_fields(pc, ["label"], dtype=np.int64)[:, 0]
    np.testing.assert_array_equal(lab, p.argmax(axis=1))
    pconf = read_fields(pc, ["confidence", "predicted_iou"])
    want = to_points(res, np.stack([conf, iou], axis=1).astype(np.float32))
    np.testing.assert_array_equal(pconf, want)
    in_kept = (seg >= 0) & np.isin(seg, res.kept_ids)
    assert np.isfinite(pconf[in_kept]).all() and np.isnan(pconf[~in_kept]).all()
    # published as the bytes of a PointCloud2 (what rclpy reads of them), not dense (a NaN)
    from lidar_quality_msgs.msg import SegmentQualityArray
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import PointCloud2
    rm = deserialize_message(out.points_cdr.tobytes(), PointCloud2)
    assert rm.header == msg.header and not rm.is_dense and not rm.is_bigendian
    assert (rm.height, rm.width, rm.point_step, rm.row_step) == (1, len(xyz), 26, 26 * len(xyz))
    assert [(fl.name, fl.offset, fl.datatype, fl.count) for fl in rm.fields] == [
        (fl.name, fl.offset, fl.datatype, fl.count) for fl in pc.fields]
    assert bytes(rm.data) == pc.data.tobytes()
    # output/segments: every segment in id order; published as bytes that are this message
    sq = out.segments
    got = deserialize_message(out.segments_cdr, SegmentQualityArray)
    floats = ("drift_score", "confidence", "predicted_iou")   # NaN != NaN: apart
    for a, b in ((got, sq), *zip(got.segments, sq.segments)):
        names = [k for k in a.get_fields_and_field_types() if k != "segments"]
        assert [getattr(a, k) for k in names if k not in floats] == \
            [getattr(b, k) for k in names if k not in floats]
        np.testing.assert_array_equal([getattr(a, k) for k in names if k in floats],
                                      [getattr(b, k) for k in names if k in floats])
    assert len(got.segments) == len(sq.segments)
    assert sq.header == msg.header and len(sq.segments) == res.n_segments
    assert sq.confidence_model_id == models.confidence_model_id
    # models without a training-data profile: no drift monitor, said in the message
    assert (sq.version, sq.drift_level) == (sq.MESSAGE_VERSION, sq.DRIFT_OFF)
    assert np.isnan(sq.drift_score) and sq.drift_window_frames == 0
    assert sq.drift_quantities == "" and not sq.passthrough
    for i in (0, int(res.kept_ids[0]), res.n_segments - 1):
        q = sq.segments[i]
        assert q.segment_id == i and q.class_index == res.segment_class[i]
        assert q.class_name == CLASS_NAMES[q.class_index]
        assert q.point_count == np.count_nonzero(seg == i)
        assert q.projected_point_count == res.size_projected[i]
        np.testing.assert_equal(q.confidence, out.confidence[i])
    # markers: one sphere per kept segment at its centroid
    m = out.markers.markers[-1]
    assert len(m.points) == len(res.kept_ids)
    k0 = int(res.kept_ids[0])
    c0 = xyz[seg == k0].astype(np.float64).mean(axis=0)
    np.testing.assert_allclose([m.points[0].x, m.points[0].y, m.points[0].z], c0, rtol=1e-6)
    assert out.issues == {}


def test_output_all_fields_repeats_the_input_cloud(frames, models):
    """output_all_fields: every input field as received (probabilities, ring, intensity),
    then the four results, equal to those of the default output; same height and width."""
    f = frames[1]
    p = noisy_probs(f, 9)
    msg = cloud(f.xyz, p, intensity=f.intensity, ring=f.ring, quantize=True, sec=42)
    s = _settings()
    lean = LmsProcessor(s, models).process(msg).points
    out = LmsProcessor(s, models, all_fields=True).process(msg)
    assert "replaced_fields" not in out.issues      # no input field is named like a result
    full = out.points
    results = ["label", "segment", "confidence", "predicted_iou"]
    assert [fl.name for fl in full.fields] == [fl.name for fl in msg.fields] + results
    assert (full.height, full.width) == (msg.height, msg.width)
    assert full.point_step > lean.point_step == 26
    src, got = cloud_to_structured(msg), cloud_to_structured(full)
    for fl in msg.fields:
        np.testing.assert_array_equal(got[fl.name], src[fl.name])
    for nm in results:
        np.testing.assert_array_equal(got[nm], cloud_to_structured(lean)[nm])


def test_output_all_fields_says_which_input_fields_the_results_replace(frames, models):
    """An input field named like a result (a driver's 'label') is replaced in output/points
    by the result: said as an issue (a throttled warning, /diagnostics WARN in the node)."""
    f = frames[1]
    p = noisy_probs(f, 9)
    msg = cloud(f.xyz, p, intensity=f.intensity, ring=f.ring, sec=42,
                extra={"label": np.full(len(f.xyz), 7, np.uint8)})
    s = _settings()
    out = LmsProcessor(s, models, all_fields=True).process(msg)
    assert "label" in out.issues["replaced_fields"]
    names = [fl.name for fl in out.points.fields]
    assert names.count("label") == 1 and names[-4:] == list(RESULT_FIELDS)
    np.testing.assert_array_equal(cloud_to_structured(out.points)["label"],
                                  out.result.point_class.astype(np.uint16))
    # the default output repeats no input field: nothing replaced, nothing said
    assert "replaced_fields" not in LmsProcessor(s, models).process(msg).issues


def test_processor_bad_probabilities_and_issues(frames, models):
    f = frames[0]
    s = _settings()
    p = noisy_probs(f, 10)
    p[:100] *= 2.0
    p[200] = np.nan
    out = LmsProcessor(s, models).process(frame_cloud(f, p))
    assert set(out.issues) == {"probabilities", "bad_probabilities"}
    assert "100 of" in out.issues["probabilities"]
    lab = read_fields(out.points, ["label"], dtype=np.int64)[:, 0]
    assert lab[200] == NO_LABEL and (lab[:100] == p[:100].argmax(axis=1)).all()
    conf = read_fields(out.points, ["confidence"])[:, 0]
    assert np.isnan(conf[200])


def test_processor_reports_an_unused_ring_field(frames, models):
    f = frames[0]
    p = noisy_probs(f, 10)
    out = LmsProcessor(_settings(channels=32), models).process(frame_cloud(f, p))
    assert set(out.issues) == {"ring"}
    assert "outside [0, channels=32)" in out.issues["ring"]
    assert out.result.n_segments > 0


@pytest.mark.parametrize("dtype", [np.int16, np.int32, np.uint16])
def test_integer_coordinates_are_refused(frames, dtype):
    """x, y, z in mm as INT16 / INT32 (as some drivers publish them) were read as metres:
    a cloud 1000x too large, without a word."""
    f = frames[0]
    p = noisy_probs(f, 6)
    mm = np.rint(f.xyz * 1000).clip(-32768, 32767).astype(dtype)
    cols = {"x": mm[:, 0], "y": mm[:, 1], "z": mm[:, 2]}
    msg = cloud(np.zeros((len(mm), 3)), p, extra=cols)
    name = {np.int16: "INT16", np.int32: "INT32", np.uint16: "UINT16"}[dtype]
    with pytest.raises(CloudFormatError, match=f"input/points field 'x' is {name}: x, y, z "
                                               "must be FLOAT32 / FLOAT64 metres"):
        decode(msg, _settings())


def test_processor_refuses_other_class_map(models):
    with pytest.raises(ValueError, match="another class map"):
        LmsProcessor(_settings(class_names=CLASS_NAMES[:-1]), models)


def test_processor_empty_cloud(models):
    out = LmsProcessor(_settings(), models).process(
        cloud(np.zeros((0, 3), np.float32), np.zeros((0, N_CLASSES), np.float32)))
    assert out.points.width == 0 and len(out.segments.segments) == 0
    assert set(out.issues) == {"intensity"}          # the cloud has no intensity field


# -- sensors: ring field names, beam rows, presets, points without a pixel (issue 16) ----


def _elevation(xyz):
    xyz = np.asarray(xyz, np.float64)
    return np.degrees(np.arcsin(xyz[:, 2] / np.linalg.norm(xyz, axis=1)))


def test_ring_field_auto_finds_channel_and_lists_are_tried_in_order(frames):
    f = frames[0]
    p = noisy_probs(f, 8)
    # nebula's layout: `channel`, 0 = lowest beam
    msg = cloud(f.xyz, p, intensity=f.intensity, extra={"channel": (63 - f.ring).astype(np.uint16)})
    inp = decode(msg, LmsSettings(width=COLS))                 # ring_field: auto
    assert inp.ring_field == "channel"
    np.testing.assert_array_equal(inp.ring, f.ring)
    inp = decode(msg, LmsSettings(width=COLS, ring_field="laser_id, channel"))
    assert inp.ring_field == "channel"
    # `ring_field: ring` as before: the channel field is not read
    inp = decode(msg, LmsSettings(width=COLS, ring_field="ring"))
    assert inp.ring is None and inp.ring_field is None and inp.ring_issue is None


def test_beam_rows_elevation_reads_any_beam_numbering(frames):
    f = frames[0]
    p = noisy_probs(f, 8)
    perm = np.random.default_rng(0).permutation(64)      # laser ids in firing order
    msg = cloud(f.xyz, p, intensity=f.intensity, extra={"laser_id": perm[f.ring].astype(np.uint16)})
    s = LmsSettings(width=COLS, beam_rows="elevation")
    inp = decode(msg, s)
    assert inp.ring_field == "laser_id"
    np.testing.assert_array_equal(inp.ring, f.ring)       # rows go down the beams again
    ref = frame_metrics(decode(frame_cloud(f, p), _settings()), _settings())
    np.testing.assert_array_equal(frame_metrics(inp, s).features, ref.features)
    # index mode takes the ids as rows: scrambled
    assert (decode(msg, LmsSettings(width=COLS, ring_zero_top=True)).ring != f.ring).mean() > 0.9


def test_sensor_presets_resolve_the_geometry(tmp_path):
    from lidar_quality_core.parameters import from_parameters

    s = LmsSettings(sensor="VLP-16").resolved()
    assert (s.channels, s.width) == (16, 1800)
    assert s.beam_elevations_deg == tuple(float(v) for v in range(15, -16, -2))
    assert (s.fov_up_deg, s.fov_down_deg) == (16.0, -16.0)
    assert s.range_config().shape == (16, 1800) and s.rows_by_elevation()
    assert LmsSettings().resolved() == LmsSettings()       # no preset: the parameters
    assert not LmsSettings().rows_by_elevation()
    with pytest.raises(ValueError, match=r"sensor 'VLP-17' is not a preset .*VLP-16"):
        LmsSettings(sensor="VLP-17").validate()
    # a table as a parameter (any order): one row per beam
    t = from_parameters(LmsSettings, {"beam_elevations_deg": "1, -1, 3", "width": 900})
    assert t.beam_elevations_deg == (1.0, -1.0, 3.0)
    r = t.resolved()
    assert (r.channels, r.width, r.fov_up_deg, r.fov_down_deg) == (3, 900, 4.0, -2.0)
    with pytest.raises(ValueError, match="same elevation"):
        LmsSettings(beam_elevations_deg=(1.0, 1.0)).validate()
    # your own presets file
    own = tmp_path / "mine.yaml"
    own.write_text("Mine:\n  elevations_deg: [2, 0, -2, -4]\n  azimuth_resolution_deg: 0.4\n")
    m = LmsSettings(sensor="Mine", sensors_file=str(own))
    m.validate()
    assert m.resolved().range_config().shape == (4, 900)


def test_every_shipped_preset_is_a_valid_image():
    from lms_ros.pipeline import sensor_presets

    presets = sensor_presets()
    for name in ("VLP-16", "VLP-32C", "HDL-32E", "HDL-64E", "VLS-128", "Pandar40P", "Pandar64",
                 "PandarXT32", "PandarQT128", "OT128", "AT128", "OS1-64", "OS1-128", "OS2-64",
                 "OS2-128"):
        p = presets[name]
        s = LmsSettings(sensor=name)
        s.validate()
        assert s.resolved().channels == p.channels and p.description
    # published beam counts and widths at 10 Hz
    assert {n: (presets[n].channels, presets[n].width) for n in
            ("VLP-16", "HDL-64E", "VLS-128", "PandarXT32", "PandarQT128", "OS1-128")} == {
        "VLP-16": (16, 1800), "HDL-64E": (64, 2048), "VLS-128": (128, 1800),
        "PandarXT32": (32, 2000), "PandarQT128": (128, 900), "OS1-128": (128, 2048)}


def test_padding_points_are_excluded_and_counted(frames, models):
    f = frames[1]
    s = _settings()
    p = noisy_probs(f, 9)
    xyz = f.xyz.astype(np.float32).copy()
    pad = np.arange(0, len(xyz), 50)
    xyz[pad] = 0.0
    xyz[7] = np.nan
    out = LmsProcessor(s, models).process(cloud(xyz, p, intensity=f.intensity, ring=f.ring))
    c = out.counts
    assert c["points.padding"] == len(pad) and c["points.invalid"] == len(pad) + 1
    seg = read_fields(out.points, ["segment"], dtype=np.int64)[:, 0]
    assert (seg[pad] == -1).all() and seg[7] == -1
    # padding takes no pixel: the image equals that of the cloud without those points
    keep = np.setdiff1d(np.arange(len(xyz)), np.r_[pad, 7])
    ref = frame_metrics(decode(cloud(xyz[keep], p[keep], intensity=f.intensity[keep],
                                     ring=f.ring[keep]), s), s)
    np.testing.assert_array_equal(out.result.features, ref.features)
    # a defined label: the point's own predicted class (its probabilities are usable)
    lab = read_fields(out.points, ["label"], dtype=np.int64)[:, 0]
    np.testing.assert_array_equal(lab[pad], p[pad].argmax(axis=1))
    assert c["points.no_segment"] == c["points.invalid"] + c["points.unprojected"] + \
        c["points.occluded"] == int((seg < 0).sum())
    assert "unprojected" not in out.issues
    # padding is said once (a log line), never warned: it is right to leave it out
    assert any(f"{len(pad)} of {len(xyz)}" in n and "points.padding" in n for n in out.notes)


@pytest.mark.parametrize("share, level", [(0.10, "warn"), (0.40, "error")])
def test_points_without_a_pixel_are_counted_and_warned(frames, models, share, level):
    f = frames[1]
    p = noisy_probs(f, 9)
    el = _elevation(f.xyz)
    down = float(np.quantile(el, share))
    s = _settings(use_ring=False, fov_up_deg=3.0, fov_down_deg=down)
    out = LmsProcessor(s, models).process(frame_cloud(f, p))
    a = out.accounting
    assert abs(a["unprojected"] - int((el <= down).sum())) <= 2
    assert out.values["points.unprojected_ratio"] == pytest.approx(share, abs=0.01)
    assert out.values["points.no_pixel_ratio"] == pytest.approx(
        a["unprojected_ratio"] + a["occluded_ratio"])
    assert out.counts["points.unprojected"] == a["unprojected"]
    assert "unprojected" in out.issues and f"{a['unprojected']} outside" in out.issues["unprojected"]
    assert ("unprojected" in out.errors) == (level == "error")
    # the frame goes out whole; points without a pixel: segment -1, own class, NaN confidence
    assert out.points.width == len(f.xyz)
    below = el < down - 1e-6
    seg = read_fields(out.points, ["segment"], dtype=np.int64)[:, 0]
    lab = read_fields(out.points, ["label"], dtype=np.int64)[:, 0]
    conf = read_fields(out.points, ["confidence"])[:, 0]
    assert (seg[below] == -1).all() and np.isnan(conf[below]).all()
    np.testing.assert_array_equal(lab[below], p[below].argmax(axis=1))


@pytest.fixture(scope="module")
def recorded_models(frames, tmp_path_factory):
    """Models whose manifests record their training settings (as lms-train writes them)."""
    from lms_data import train_node_models

    c, r = train_node_models(tmp_path_factory.mktemp("lms_recorded"), frames, _settings())
    return meta_model.MetaModels(c, r, _settings().metric_names())


def test_model_geometry_mismatch_warns(models, recorded_models):
    from lms_ros.pipeline import geometry_mismatch

    s = _settings(sensor="VLP-16")
    assert geometry_mismatch(models, s) is None          # nothing recorded: nothing to say
    assert geometry_mismatch(recorded_models, _settings()) is None
    assert geometry_mismatch(recorded_models, s) == (
        "trained 64 x 256, fov 3 .. -25 deg; running 16 x 1800, fov 16 .. -16 deg")
    warnings = []
    m = meta_model.MetaModels(recorded_models.classifier.path, recorded_models.regressor.path,
                              s.metric_names(), settings=s.resolved(), method="lms",
                              warn=warnings.append)
    assert m.confidence_model_id == recorded_models.confidence_model_id
    assert any("channels: model trained with 64, node set to 16" in w for w in warnings), warnings
    out = LmsProcessor(s, m).process(cloud(np.array([[5, 0, 0]] * 20, np.float32),
                                           np.full((20, N_CLASSES), 1 / N_CLASSES)))
    assert out.points.width == 20


def test_organized_ouster_cloud_with_padding(models):
    """An OS1-64-style organized cloud (64 x 256, ring 0 = top, no-return pixels written
    as (0, 0, 0)) with the OS1-64 preset: layout kept, the padding counted and without a
    segment, every other point in the image."""
    rng = np.random.default_rng(4)
    H, W = 64, 256
    el = np.radians(np.linspace(22.5, -22.5, H))[:, None]
    az = np.radians(np.linspace(180, -180, W, endpoint=False))[None, :]
    r = rng.uniform(3, 30, (H, W))
    grid = np.zeros((H, W), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "f4"),
                                   ("ring", "u2")] + [(nm.replace("-", "_"), "f4")
                                                      for nm in CLASS_NAMES])
    grid["x"], grid["y"] = r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az)
    grid["z"] = np.broadcast_to(r * np.sin(el), (H, W))
    grid["ring"] = np.arange(H)[:, None]
    p = rng.dirichlet(np.ones(N_CLASSES) * 0.3, H * W).astype(np.float32).reshape(H, W, -1)
    for k, nm in enumerate(CLASS_NAMES):
        grid[nm.replace("-", "_")] = p[..., k]
    pad = rng.random((H, W)) < 0.3
    for k in ("x", "y", "z"):
        grid[k][pad] = 0.0
    msg = create_cloud(Header(frame_id="os_sensor"), grid)
    out = LmsProcessor(LmsSettings(class_names=CLASS_NAMES, sensor="OS1-64", width=COLS),
                       models).process(msg)
    assert (out.points.height, out.points.width) == (H, W)
    c = out.counts
    assert c["points.padding"] == c["points.invalid"] == int(pad.sum())
    assert c["points.unprojected"] == 0 and out.values["points.no_pixel_ratio"] < 0.05
    seg = read_fields(out.points, ["segment"], dtype=np.int64)[:, 0].reshape(H, W)
    assert (seg[pad] == -1).all() and (seg[~pad] >= 0).mean() > 0.95
    # rows from the beams' elevations: ring r is row r
    np.testing.assert_array_equal(out.result.projection.row.reshape(H, W)[~pad],
                                  np.broadcast_to(np.arange(H)[:, None], (H, W))[~pad])


def test_intensity_scale_auto_reads_both_scales_alike(frames, models):
    """The same scan with 0..255 intensity: auto reads it as [0, 1] (same metrics and
    confidences); read as given ('unit'), the intensity metrics are 255x off."""
    from dataclasses import replace

    f = frames[1]
    s = _settings()
    p = noisy_probs(f, 9)
    xyz = f.xyz.astype(np.float32)
    assert 0.0 <= f.intensity.min() and f.intensity.max() <= 1.0
    inten255 = (np.asarray(f.intensity, np.float32) * 255).astype(np.float32)
    ref = LmsProcessor(s, models).process(cloud(xyz, p, intensity=f.intensity, ring=f.ring))
    proc = LmsProcessor(s, models, all_fields=True)
    out = proc.process(cloud(xyz, p, intensity=inten255, ring=f.ring))
    np.testing.assert_allclose(out.result.features, ref.result.features, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(out.confidence, ref.confidence, atol=1e-5)
    assert out.values["intensity_scale"] == "byte" and "0..255" in out.notes[0]
    assert ref.values["intensity_scale"] == "unit"
    # the output cloud (all fields) keeps the input's own intensity
    np.testing.assert_array_equal(read_fields(out.points, ["intensity"])[:, 0], inten255)
    raw = LmsProcessor(replace(s, intensity_scale="unit"), models).process(
        cloud(xyz, p, intensity=inten255, ring=f.ring))
    col = list(raw.result.names).index("mean_i")
    assert np.nanmax(np.abs(raw.result.features[:, col] - ref.result.features[:, col])) > 1.0


# -- domain drift -------------------------------------------------------------------------
def test_drift_check_flags_a_less_certain_segmenter(tmp_path):
    """Models recording the profile of their training metrics: frames of the same
    segmenter are quiet, a segmenter with three times the logit noise is out of the domain
    (ERROR, metrics named); passthrough leaves its segments unscored (NaN)."""
    from lidar_quality_core.domain_profile import DriftParameters
    from lms_ros.pipeline import decode, frame_metrics
    from lms_scans import noisy_probs as probs_of

    s = _settings()
    names = s.metric_names()
    train = [f for seed in (21, 23, 24, 25, 26) for f in scans(seed, 2)]   # five scenes
    rows = [frame_metrics(decode(frame_cloud(f, probs_of(f.xyz, f.ring, f.semantic, k)), s),
                          s).features for k, f in enumerate(train)]
    X = np.vstack(rows)
    scene = np.repeat(np.arange(len(rows)) // 2, [len(r) for r in rows])
    y = (np.arange(len(X)) % 2).astype(float)
    c, r = meta_model.save_pair(
        tmp_path, "lms", meta_model.fit_estimator("linear", "classification", X, y),
        meta_model.fit_estimator("linear", "regression", X, y), names,
        domain_profile=meta_model.training_profile(X, names, groups=scene))
    models = meta_model.MetaModels(c, r, names)
    live = scans(22, 4)
    # thresholds above the default: a profile of ten frames knows the scenes' spread poorly
    drift = dict(drift_window=2, drift_warn=0.5, drift_error=1.0)
    proc = LmsProcessor(s, models, drift=DriftParameters(**drift))
    for k, f in enumerate(live[:2]):
        out = proc.process(frame_cloud(f, probs_of(f.xyz, f.ring, f.semantic, 50 + k)))
        assert out.values["drift.level"] == ("warming up", "OK")[k], out.values
        q = sent(out.segments)        # output/segments says so too
        assert q.version == q.MESSAGE_VERSION and not q.passthrough
        assert q.drift_window_frames == k + 1
        if k == 0:                    # scoring starts with a full window (2 frames here)
            assert q.drift_level == q.DRIFT_WARMING_UP and np.isnan(q.drift_score)
        else:
            assert q.drift_level == q.DRIFT_OK and q.drift_quantities == ""
            assert q.drift_score == pytest.approx(out.values["drift.score"], abs=5e-4)
    for k, f in enumerate(live[2:]):
        out = proc.process(frame_cloud(f, probs_of(f.xyz, f.ring, f.semantic, 60 + k,
                                                   noise=3.6)))
    assert out.values["drift.level"] == "ERROR" and "domain_drift" in out.errors, out.values
    assert out.issues["domain_drift"].startswith("inputs unlike the models' training data")
    assert np.isfinite(out.confidence[out.result.kept_ids]).all()     # flag: annotated
    q = sent(out.segments)
    assert q.drift_level == q.DRIFT_ERROR and q.drift_score >= 1.0 and not q.passthrough
    assert q.drift_score == pytest.approx(out.values["drift.score"], abs=5e-4)
    assert q.drift_quantities == out.values["drift.quantities"] != ""

    passthrough = LmsProcessor(s, models, drift=DriftParameters(**drift,
                                                                drift_action="passthrough"))
    for k, f in enumerate(live[2:]):
        out = passthrough.process(frame_cloud(f, probs_of(f.xyz, f.ring, f.semantic, 60 + k,
                                                          noise=3.6)))
    assert out.values["drift.level"] == "ERROR"
    assert np.isnan(out.confidence).all() and np.isnan(out.predicted_iou).all()
    assert len(out.segments.segments) == out.result.n_segments       # every segment still out
    q = sent(out.segments)
    assert q.drift_level == q.DRIFT_ERROR and q.passthrough
    assert all(np.isnan(x.confidence) and np.isnan(x.predicted_iou) for x in q.segments)


def sent(msg):
    """``msg`` as a subscriber gets it: through rclpy's serialization."""
    from rclpy.serialization import deserialize_message, serialize_message

    return deserialize_message(serialize_message(msg), type(msg))


def test_probability_sums_taken_during_the_gather_are_numpys():
    """decode's per-point sum and minimum come from the gather, block by block: the same
    bits as numpy's reductions over the whole class-major array (NaN, inf, -0.0, uint8)."""
    from lms_ros.pipeline import _probabilities

    rng = np.random.default_rng(7)
    N, names = 10_000, ["p_a", "p_b", "p_c", "p_d"]
    dt = np.dtype([("x", "<f4"), ("p_a", "<f4"), ("p_b", "u1"), ("p_c", "<f8"), ("p_d", "<f4")])
    arr = np.zeros(N, dt)
    arr["p_a"] = rng.random(N) * np.float32(1e-20)
    arr["p_b"] = rng.integers(0, 256, N)
    arr["p_c"] = rng.normal(size=N)
    arr["p_d"] = rng.random(N)
    arr["p_a"][:50], arr["p_c"][50:100], arr["p_d"][100:150] = np.nan, np.inf, -0.0
    arr["p_a"][150:200] = -0.0
    probs, quantized, total, smallest, disp = _probabilities(arr, names, "input/points")
    assert quantized and not np.shares_memory(probs, arr) and disp is None   # gathered
    pcm = np.ascontiguousarray(probs.T)
    with np.errstate(invalid="ignore"):
        assert total.tobytes() == pcm.sum(axis=0).tobytes()
        assert smallest.tobytes() == pcm.min(axis=0).tobytes()


def test_float32_probability_fields_in_a_run_are_read_in_place(frames):
    """Float32 fields one after the other: decode reads them in the message (a read-only
    view, no copy), with the sums and minima of numpy's reductions (NaN, inf, -0.0); a
    frame with points to renormalize or drop works on a copy, the message untouched."""
    from lms_ros.pipeline import _probabilities

    f = frames[0]
    p = noisy_probs(f, 6)
    p[:20, 0], p[20:40, 1], p[40:60, 2] = np.nan, np.inf, -0.0
    p[60:80] *= np.float32(1.5)                                  # to renormalize
    msg = cloud(f.xyz, p, intensity=f.intensity)                 # no ring: aligned run
    arr = cloud_to_structured(msg)
    names = _settings().field_names()
    ro = arr.copy()
    ro.flags.writeable = False
    probs, quantized, total, smallest, disp = _probabilities(ro, names, "input/points")
    assert not quantized and np.shares_memory(probs, ro) and not probs.flags.writeable
    np.testing.assert_array_equal(probs, p)
    for got, want in zip(disp, dispersion(np.ascontiguousarray(p))):  # taken in the pass
        assert got.tobytes() == want.tobytes()
    pcm = np.ascontiguousarray(p.T)
    with np.errstate(invalid="ignore"):
        assert total.tobytes() == pcm.sum(axis=0).tobytes()
        assert smallest.tobytes() == pcm.min(axis=0).tobytes()

    before = bytes(msg.data)
    inp = decode(msg, _settings(use_ring=False))
    assert inp.n_bad_probabilities == 40 and inp.n_renormalized >= 20
    assert inp.dispersion is None                                # of the corrected copy
    assert bytes(msg.data) == before and not np.shares_memory(inp.probs, arr)
    np.testing.assert_array_equal(inp.probs[:40], 0.0)
    np.testing.assert_allclose(inp.probs[60:80].sum(axis=1), 1.0, rtol=1e-5)
    clean = cloud(f.xyz[80:], p[80:], intensity=f.intensity[80:])
    inp = decode(clean, _settings(use_ring=False))
    assert inp.n_bad_probabilities == 0 and inp.n_renormalized == 0
    assert np.shares_memory(inp.probs, inp.cloud)                # the message's own bytes
    np.testing.assert_array_equal(inp.probs, p[80:])
    s = _settings(use_ring=False)
    with_pass = frame_metrics(inp, s)
    inp.dispersion = None
    assert with_pass.features.tobytes() == frame_metrics(inp, s).features.tobytes()
