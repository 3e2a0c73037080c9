"""lidar_quality_tools.fuzz: every category makes what it says, companions stay valid, the
stream is seeded; plus the short in-suite runs of scripts/fuzz_nodes.py (a few hundred
malformed messages per node) and scripts/soak.py (15 s of the three nodes)."""
import json
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from lidar_quality_core.boxes import detections_to_arrays
from lidar_quality_core.pointcloud import CloudFormatError, cloud_to_structured
from lidar_quality_tools import fuzz
from lidar_quality_tools.fuzz import DETECTIONS, POINTS, VARIANCES, FrameTemplate, Fuzzer, InputSpec

ROOT = Path(__file__).resolve().parents[2]
PROBS = ("unlabeled", "road", "building", "car", "traffic_sign")
INPUTS = [InputSpec("input/points", POINTS),
          InputSpec("input/seg", POINTS, prob_fields=PROBS),
          InputSpec("input/seg_u8", POINTS, prob_fields=PROBS, prob_dtype="uint8"),
          InputSpec("input/detections", DETECTIONS),
          InputSpec("input/proposals", DETECTIONS, source="proposals"),
          InputSpec("input/head_1", DETECTIONS, source="head1"),
          InputSpec("input/head_1/variance", VARIANCES, of="input/head_1")]
CLASSES = ("car", "truck", "pedestrian", "cyclist")


@pytest.fixture(scope="module")
def template():
    return FrameTemplate(INPUTS, n_points=500, n_objects=5, n_proposals=20, seed=3,
                         classes=CLASSES)


def fingerprint(msg):
    """Hashable content of a message (clouds by their bytes; repr shows NaN as nan)."""
    if isinstance(msg, bytes):
        return msg
    if hasattr(msg, "point_step"):
        return (repr(msg.header), msg.height, msg.width, msg.point_step, msg.row_step,
                msg.is_bigendian, tuple(layout(msg)), bytes(msg.data))
    return repr(msg)


def stamp_ns(msg):
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def decodes(msg) -> bool:
    try:
        cloud_to_structured(msg)
        return True
    except CloudFormatError:
        return False


def layout(msg):
    return [(f.name, f.offset, f.datatype, f.count) for f in msg.fields]


def float_columns(msg, spec):
    arr = cloud_to_structured(msg)
    names = (["x", "y", "z", "intensity"] if spec.xyz else []) + list(spec.prob_fields)
    return np.stack([arr[n].astype(np.float64) for n in names
                     if arr.dtype[n].kind == "f"], axis=1)


def probabilities(msg, spec):
    arr = cloud_to_structured(msg)
    p = np.stack([arr[n].astype(np.float64) for n in spec.prob_fields], axis=1)
    return p / 255.0 if spec.prob_dtype == "uint8" else p


def check_case(case, prev_stamp, t: FrameTemplate) -> None:
    """The case's malformed message is malformed the way its category says."""
    frame = dict(case.messages)
    assert set(frame) == {s.topic for s in t.inputs}, "a frame holds every input"
    cat = case.category
    ref = t.messages.get(case.topic)
    msg = frame.get(case.topic)
    spec = t.spec(case.topic) if case.topic != "*" else None
    if cat == "truncated_buffer":
        assert len(msg.data) < msg.height * msg.row_step and not decodes(msg)
    elif cat == "oversized_buffer":
        assert len(msg.data) > msg.height * msg.row_step and not decodes(msg)
    elif cat == "wrong_point_step":
        assert msg.point_step != ref.point_step and not decodes(msg)
    elif cat == "wrong_row_step":
        assert msg.row_step != msg.width * msg.point_step
    elif cat == "wrong_dimensions":
        assert (msg.height, msg.width) != (ref.height, ref.width) and not decodes(msg)
    elif cat == "missing_fields":
        missing = {f.name for f in ref.fields} - {f.name for f in msg.fields}
        assert missing & {f.name for f in ref.fields[:4]}
    elif cat == "wrong_datatypes":
        assert msg.is_bigendian != ref.is_bigendian or \
            [f.datatype for f in msg.fields] != [f.datatype for f in ref.fields]
    elif cat == "wrong_field_layout":
        assert layout(msg) != layout(ref)
    elif cat == "nan_inf_coordinates" and spec.kind == POINTS:
        assert not np.isfinite(float_columns(msg, spec)).all()
    elif cat == "huge_coordinates" and spec.kind == POINTS:
        assert (np.abs(float_columns(msg, spec)) >= 1e15).any()
    elif cat == "empty" and spec.kind == POINTS:
        assert msg.width * msg.height == 0 and len(msg.data) == 0
    elif cat == "invalid_probabilities":
        p = probabilities(msg, spec)
        assert ((p < 0) | (p > 1)).any() or (np.abs(p.sum(axis=1) - 1) > 0.05).any()
    elif cat == "huge_cloud":
        for s in t.inputs:
            if s.kind == POINTS:
                c = frame[s.topic]
                assert c.width * c.height == fuzz.HUGE_CLOUD_POINTS and decodes(c)
    elif cat == "nonpositive_box_sizes":
        assert any("size <= 0" in r for r in detections_to_arrays(msg).reasons)
    elif cat == "non_unit_quaternions":
        q = np.array([[d.bbox.center.orientation.x, d.bbox.center.orientation.y,
                       d.bbox.center.orientation.z, d.bbox.center.orientation.w]
                      for d in msg.detections])
        assert (np.abs(np.linalg.norm(q, axis=1) - 1) > 1e-3).any()
    elif cat == "nan_scores":
        s = np.array([r.hypothesis.score for d in msg.detections for r in d.results])
        assert (~np.isfinite(s) | (s < 0) | (s > 1)).any()
    elif cat == "unknown_classes":
        assert any(not d.results or any(r.hypothesis.class_id not in CLASSES for r in d.results)
                   for d in msg.detections)
    elif cat == "nan_inf_coordinates" and spec.kind == DETECTIONS:
        assert any("non-finite" in r for r in detections_to_arrays(msg).reasons)
    elif cat == "huge_coordinates" and spec.kind == DETECTIONS:
        a = detections_to_arrays(msg)
        assert (np.abs(a.boxes[:, :6]) >= 1e15).any() or any(
            max(abs(d.bbox.center.orientation.x), abs(d.bbox.center.orientation.w)) >= 1e15
            for d in msg.detections)
    elif cat == "empty" and spec.kind == DETECTIONS:
        assert len(msg.detections) == 0
    elif cat == "bad_ids":
        assert [d.id for d in msg.detections] != [d.id for d in ref.detections]
    elif cat == "thousands_of_boxes":
        assert len(msg.detections) >= 1000 and detections_to_arrays(msg).valid.all()
    elif cat == "variance_count_mismatch":
        assert len(msg.variances) != len(frame[spec.of].detections)
    elif cat == "invalid_variances":
        v = np.array([[x.x, x.y, x.z, x.length, x.width, x.height, x.yaw] for x in msg.variances])
        assert (~np.isfinite(v) | (v < 0) | (v > 1e6)).any()
    elif cat == "bad_indices":
        ids = [d.id for d in frame[spec.of].detections]
        assert ([v.detection_index for v in msg.variances] != list(range(len(msg.variances)))
                or [v.detection_id for v in msg.variances] != ids)
    elif cat == "empty" and spec.kind == VARIANCES:
        assert len(msg.variances) == 0
    elif cat == "mismatched_frame_ids":
        assert msg.header.frame_id != t.frame_id
        assert all(m.header.frame_id == t.frame_id for tp, m in frame.items() if tp != case.topic)
    elif cat in ("stamp_future", "stamp_past", "invalid_stamp"):
        hit = list(frame.values()) if case.topic == "*" else [msg]
        for m in hit:
            if cat == "stamp_future":
                assert stamp_ns(m) >= case.stamp_ns + 60 * 10**9
            elif cat == "stamp_past":
                assert stamp_ns(m) <= case.stamp_ns - 60 * 10**9
            else:
                assert m.header.stamp.nanosec >= 10**9
    elif cat == "time_backwards":
        assert case.topic == "*" and case.stamp_ns < prev_stamp
        assert all(stamp_ns(m) == case.stamp_ns for m in frame.values())
    elif cat == "corrupt_cdr":
        valid = fuzz.restamp_bytes(t.serialized(case.topic), case.stamp_ns)
        assert isinstance(msg, bytes) and msg != valid
        assert all(not isinstance(m, bytes) for tp, m in frame.items() if tp != case.topic)
    elif cat == "unmatched_stamp":
        assert 0 < abs(stamp_ns(msg) - case.stamp_ns) < 50_000_000
    else:
        raise AssertionError(f"no check for {cat} on {case.topic}")
    if cat not in fuzz.COMMON_CATEGORIES and cat != "huge_cloud":
        # the other inputs are the template's messages, restamped, unmodified
        for tp, m in frame.items():
            if tp != case.topic:
                assert stamp_ns(m) == case.stamp_ns and m.header.frame_id == t.frame_id
                assert payload(m) is payload(t.messages[tp])


def payload(msg):
    """The bulk of a message (shared, not copied, by restamped frames)."""
    for name in ("data", "detections", "variances"):
        if hasattr(msg, name):
            return getattr(msg, name)
    raise AssertionError(type(msg))


def test_template_frame_is_valid(template):
    frame = template.frame(5 * 10**9)
    for spec in template.inputs:
        m = frame[spec.topic]
        assert stamp_ns(m) == 5 * 10**9 and m.header.frame_id == "lidar_top"
        if spec.kind == POINTS:
            assert m.width == 500 and np.isfinite(float_columns(m, spec)).all()
            if spec.prob_fields:
                p = probabilities(m, spec)
                tol = 0.05 if spec.prob_dtype == "uint8" else 1e-4
                assert np.allclose(p.sum(axis=1), 1.0, atol=tol)
        elif spec.kind == DETECTIONS:
            a = detections_to_arrays(m)
            assert len(a) and a.valid.all() and set(a.labels) <= set(CLASSES)
        else:
            ids = [d.id for d in frame[spec.of].detections]
            assert [v.detection_id for v in m.variances] == ids
    dets = detections_to_arrays(frame["input/detections"])
    assert dets.ids == [f"d{i}" for i in range(5)]
    assert len(frame["input/proposals"].detections) == 20


def test_every_category_makes_what_it_says(template):
    before = {t: fingerprint(m) for t, m in template.messages.items()}
    fz = Fuzzer(template, seed=11, huge_clouds=0, box_floods=0, start_ns=10**15)
    slots = fz.slots()
    cats = {c for c, _ in slots}
    assert cats == set(fuzz.CATEGORIES) - set(fuzz.HEAVY_CATEGORIES)
    # five cases per (category, topic) slot, in stream order (time_backwards needs it)
    prev = fz._clock_ns
    i = 0
    for rep in range(5):
        for cat, topic in slots:
            topic = topic if topic != "?" else fz.topics[(i + rep) % len(fz.topics)]
            case = fz.make_case(i, cat, topic)
            check_case(case, prev, template)
            prev = case.stamp_ns
            i += 1
    # the heavy ones, once each
    case = fz.make_case(i, "thousands_of_boxes", "input/proposals")
    check_case(case, prev, template)
    assert {s.topic for s in template.inputs} == {t for t, _ in case.messages}
    after = {t: fingerprint(m) for t, m in template.messages.items()}
    assert after == before, "cases must not modify the template"


def test_huge_cloud_covers_every_cloud_of_the_frame():
    t = FrameTemplate([InputSpec("input/points", POINTS),
                       InputSpec("input/probabilities", POINTS, prob_fields=("road", "car"),
                                 xyz=False)], n_points=300, n_objects=2, n_proposals=4)
    case = Fuzzer(t, seed=1).make_case(0, "huge_cloud", "input/points")
    check_case(case, 0, t)
    assert case.topic == "*" and case.malformed == 2


def test_stream_is_seeded(template):
    def stream(seed):
        return [(c.category, c.topic, c.variant, c.stamp_ns, c.malformed,
                 [(tp, fingerprint(m)) for tp, m in c.messages])
                for c in Fuzzer(template, seed=seed, huge_clouds=0, box_floods=0).cases(40)]
    a, b = stream(5), stream(5)
    assert a == b
    assert stream(6) != a


def test_schedule_shares_and_heavy_quota(template):
    fz = Fuzzer(template, seed=2, huge_clouds=3, box_floods=4)
    plan = fz.schedule(2000)
    assert len(plan) == 2000
    counts = Counter(plan)
    assert counts[("huge_cloud", "input/points")] + counts[("huge_cloud", "input/seg")] \
        + counts[("huge_cloud", "input/seg_u8")] == 3
    assert sum(n for (c, _), n in counts.items() if c == "thousands_of_boxes") == 4
    assert plan[0][0] not in fuzz.HEAVY_CATEGORIES
    ordinary = [n for (c, t), n in counts.items() if c not in fuzz.HEAVY_CATEGORIES
                and c not in fuzz.COMMON_CATEGORIES]
    assert max(ordinary) - min(ordinary) <= 1  # round robin over the slots
    common = Counter(c for c, _ in plan if c in fuzz.COMMON_CATEGORIES)
    assert set(common) == set(fuzz.COMMON_CATEGORIES)
    assert max(common.values()) - min(common.values()) <= 1
    assert all(t != "?" for _, t in plan)


def test_next_stamp_follows_the_stream(template):
    fz = Fuzzer(template, seed=4, huge_clouds=0, box_floods=0, start_ns=10**15)  # no clamping at 0
    stamps = [c.stamp_ns for c in fz.cases(300)]
    nxt = fz.next_stamp_ns()
    # newer than every frame since the last backwards jump over the reset threshold
    last_reset = max((i for i in range(1, len(stamps)) if stamps[i] < stamps[i - 1] - 10**9),
                     default=0)
    assert nxt > max(stamps[last_reset:])
    assert nxt - max(stamps[last_reset:]) == fz.period_ns


def test_serialized_bytes_restamp(template):
    from rclpy.serialization import deserialize_message
    for topic, msg in template.messages.items():
        data = fuzz.restamp_bytes(template.serialized(topic), 1234 * 10**9 + 5)
        assert fuzz.stamp_of_bytes(data) == 1234 * 10**9 + 5
        back = deserialize_message(data, type(msg))
        assert stamp_ns(back) == 1234 * 10**9 + 5
        assert fingerprint(fuzz.restamp(back, 0)) == fingerprint(fuzz.restamp(msg, 0))


def test_input_spec_from_topic_names():
    assert fuzz.input_spec("/x/input/head_3", "vision_msgs/msg/Detection3DArray").source == "head3"
    assert fuzz.input_spec("input/proposals", "Detection3DArray").source == "proposals"
    assert fuzz.input_spec("input/detections", "Detection3DArray").source == "detections"
    v = fuzz.input_spec("input/head_0/variance", "lidar_quality_msgs/msg/BoxVarianceArray")
    assert v.kind == VARIANCES and v.of == "input/head_0"
    p = fuzz.input_spec("input/points", "sensor_msgs/msg/PointCloud2", ("road",))
    assert p.xyz and p.prob_fields == ("road",)
    p = fuzz.input_spec("input/points", "PointCloud2", ("road",), separate_probabilities=True)
    assert p.xyz and p.prob_fields == ()
    q = fuzz.input_spec("input/probabilities", "PointCloud2", ("road",), True)
    assert not q.xyz and q.prob_fields == ("road",)
    with pytest.raises(ValueError):
        fuzz.input_spec("input/image", "sensor_msgs/msg/Image")


def test_input_spec_validation():
    with pytest.raises(ValueError):
        InputSpec("x", "lidar")
    with pytest.raises(ValueError):
        InputSpec("x", VARIANCES)
    with pytest.raises(ValueError):
        InputSpec("x", POINTS, xyz=False)
    with pytest.raises(ValueError):
        FrameTemplate([InputSpec("a", POINTS), InputSpec("a", POINTS)])


# -- short in-suite runs of the two scripts (the full ones: make fuzz, make soak) -------
def _run(args, timeout):
    proc = subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout)
    return proc, proc.stdout + proc.stderr


def test_fuzz_nodes_short(tmp_path):
    """A few hundred malformed messages per node: each stays up, processes the valid frame
    after them as before them, keeps its output invariants, raises nothing unhandled."""
    out = tmp_path / "report.json"
    proc, text = _run(["scripts/fuzz_nodes.py", "--cases", "150", "--huge-clouds", "1",
                       "--box-floods", "1", "--nodes", "lmd,lms,mimo", "--seed", "1",
                       "--out", str(out)], timeout=400)
    report = json.loads(out.read_text())
    for name, r in report["nodes"].items():
        why = r.get("start_errors") or r.get("error")
        assert r.get("started"), f"{name}: {why}\n{text[-3000:]}"
        assert "error" not in r, f"{name}: {r['error']}\n{r.get('traceback')}"
        assert r["malformed_messages"] >= 150
        assert r["n_executor_errors"] == 0, r["executor_errors"]
        assert r["alive"], name
        valid = r["valid_frames_after"][0]
        assert valid["processed"] and valid["correct"], (name, valid)
        inv = r["invariants"]
        assert inv["checked"] > 0 and inv["violations"] == 0, inv
        cats = r["categories"]
        assert {"huge_cloud", "invalid_stamp", "time_backwards", "missing_fields"} <= set(cats)
        errors = {c: v["outcomes"].get("dropped.processing_error", 0) for c, v in cats.items()}
        assert not any(errors.values()), (name, errors, {c: v["examples"] for c, v in cats.items()})
        assert r["valid_cdr_refused"] == 0, (name, {c: v["refused"] for c, v in cats.items()
                                                   if v.get("refused")})
        assert r["passed"], name
    assert proc.returncode == 0, text[-3000:]
    assert "malformed messages" in proc.stdout


def test_soak_short(tmp_path):
    """15 s of the three nodes at once at 10 Hz with 120k-point frames: every node process
    is sampled, its outputs are the frames sent (no duplicates, no strangers), it exits
    cleanly. Drops and latency are not asserted (a loaded machine may drop a frame)."""
    out = tmp_path / "soak.json"
    proc, text = _run(["scripts/soak.py", "--duration", "15", "--nodes", "lmd,lms,mimo",
                       "--frames", "1", "--out", str(out)], timeout=300)
    assert out.exists(), text[-3000:]
    r = json.loads(out.read_text())
    assert set(r["nodes"]) == {"lmd", "lms", "mimo"}
    for name, e in r["nodes"].items():
        assert e["exit_code"] == 0, (name, text[-3000:])
        assert e["published"] == 150 and 0 < e["received"] <= e["published"], name
        assert e["dropped"] == e["published"] - e["received"]
        assert e["unexpected_outputs"] == 0 and e["duplicates"] == 0, name
        assert e["diag_frames_out"] >= e["received"], name
        m = e["memory"]
        assert m["samples"] >= 10 and m["rss_warm_mb"] > 10 and np.isfinite(m["growth_pct"])
        assert e["latency_ms_p50"] > 0 and e["cpu_pct"] > 0
    assert r["achieved_rate_hz"] > 0 and r["frame_bytes"]["lms"] > r["frame_bytes"]["mimo"]
    assert ("PASS" in proc.stdout) == r["passed"]
