"""evaluation: recorded outputs joined with the perception bag's inputs and ground truth.
Real bags: a 4-frame simulated perception bag, its outputs written by process_bag (the
nodes' processors); then outputs that do not belong to their frame, and missing ones."""
import numpy as np
import pytest
from lidar_quality_core.boxes import detections_to_arrays
from lidar_quality_ros.bag_io import BagWriter, read_bag
from lidar_quality_ros.perception_bag import perception_frames
from lidar_quality_tools.evaluation import OUTPUT_TOPICS, MethodRows, evaluate
from lidar_quality_tools.process import node_parameters, node_settings, process_bag
from perception_bags import simulated_perception_bags
from rclpy.serialization import deserialize_message, serialize_message
from reference_perception.cli import Perception

N_FRAMES = 4
LMS_SEPARATE = {"lms": {"separate_probabilities": True}}


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    root = tmp_path_factory.mktemp("evaluation")
    return simulated_perception_bags(root, Perception(heads=2), n_sequences=1,
                                     n_frames=N_FRAMES, seed=5, columns=512) / "seq_00"


@pytest.fixture(scope="module")
def annotated(bag, tmp_path_factory):
    out = tmp_path_factory.mktemp("annotated") / "out"
    process_bag(bag, out, params=LMS_SEPARATE, progress=False)
    return out


def settings():
    return (node_settings("lms", node_parameters("lms", LMS_SEPARATE["lms"])),
            node_settings("mimo", node_parameters("mimo")))


def run(bag, outputs, **kw):
    lms, mimo = settings()
    return evaluate(bag, outputs, lms_settings=lms, mimo_settings=mimo, **kw)


def test_every_frame_joined_with_its_targets(bag, annotated):
    ev = run(bag, annotated, example_frame=1)
    assert ev.frames == N_FRAMES
    q = ev.quality()
    for m in ("lmd", "lms", "mimo"):
        r = ev.rows[m]
        assert (r.frames_in, r.frames_out, r.mismatched) == (N_FRAMES, N_FRAMES, 0), m
        tp, iou = r.column("tp"), r.column("iou")
        assert len(tp) > 0 and np.isfinite(r.column("confidence")).all()
        # the targets of each method's training data
        assert np.array_equal(tp.astype(bool), iou > 0 if m == "lms" else iou >= 0.5)
        assert set(q[m]) >= {"frames_in", "frames_out", "auroc", "auroc_baseline", "ece",
                             "ece_baseline", "r2", "n"}
        assert ev.example[m]["frame"] == 1
    # LMD: one row per valid input detection, with the recorded confidence
    n_valid = sum(int(detections_to_arrays(f.detections).valid.sum())
                  for f in perception_frames(bag, want=("detections",)))
    assert len(ev.rows["lmd"].column("confidence")) == n_valid
    recorded = [x.confidence for m in read_bag(annotated, {OUTPUT_TOPICS["lmd"]})
                for x in m.decode().detections]
    assert np.allclose(np.sort(ev.rows["lmd"].column("confidence")), np.sort(recorded))


def _rewrite(src, dst, edit):
    """Copy the outputs of ``src`` to ``dst``, each message through ``edit(topic, index,
    msg)`` (None: left out)."""
    seen = {}
    topics = set(OUTPUT_TOPICS.values())
    with BagWriter(dst) as w:
        for m in read_bag(src, topics):
            k = seen[m.topic] = seen.get(m.topic, -1) + 1
            msg = edit(m.topic, k, deserialize_message(m.raw, m.decode().__class__))
            if msg is not None:
                w.write(m.topic, m.msgtype, m.stamp_ns, serialize_message(msg))


def test_outputs_of_other_frames_are_mismatched_and_missing_ones_counted(
        bag, annotated, tmp_path):
    def edit(topic, k, msg):
        if topic == OUTPUT_TOPICS["lmd"] and k == 0:
            msg.detections = msg.detections[::-1]             # other order
        if topic == OUTPUT_TOPICS["lms"] and k == 1:
            msg.segments = msg.segments[:-1]                   # a segment missing
        if topic == OUTPUT_TOPICS["mimo"] and k == 2:
            msg.clusters[0].detection_id = "0:someone_else"
        if topic == OUTPUT_TOPICS["lmd"] and k == 3:
            return None                                        # no output at all
        return msg

    bad = tmp_path / "bad"
    _rewrite(annotated, bad, edit)
    ev = run(bag, bad)
    lmd, lms, mimo = (ev.rows[m] for m in ("lmd", "lms", "mimo"))
    assert (lmd.frames_out, lmd.mismatched) == (N_FRAMES - 1, 1)
    assert (lms.frames_out, lms.mismatched) == (N_FRAMES, 1)
    assert (mimo.frames_out, mimo.mismatched) == (N_FRAMES, 1)
    assert "LMD quality" in lmd.mismatch_reasons[0]
    good = run(bag, annotated)
    for m in ("lmd", "lms", "mimo"):  # the frames left out are not in the rows
        assert len(ev.rows[m].column("tp")) < len(good.rows[m].column("tp"))


def test_pictures_from_a_frame_every_method_answered(bag, annotated, tmp_path):
    """The plotted frame is the one nearest the middle (frame 2 of 4) that every method
    answered with a matching output; none such: no example, said by ``example_frame``."""
    def edit(topic, k, msg):
        if topic == OUTPUT_TOPICS["lmd"] and k == 2:
            return None                                    # LMD dropped the middle frame
        if topic == OUTPUT_TOPICS["mimo"] and k == 1:
            msg.clusters[0].detection_id = "0:someone_else"  # MIMO's frame 1 mismatched
        return msg

    holes = tmp_path / "holes"
    _rewrite(annotated, holes, edit)
    ev = run(bag, holes)
    assert ev.example_target == N_FRAMES // 2 == 2
    assert ev.example_frame == 3 and ev.answered_by_all == N_FRAMES - 2
    assert {m: ex["frame"] for m, ex in ev.example.items()} == dict.fromkeys(
        ("lmd", "lms", "mimo"), 3)
    assert run(bag, holes, example_frame=0).example_frame == 0

    def disjoint(topic, k, msg):   # LMD answered frames 0, 1; LMS frames 2, 3
        if (topic == OUTPUT_TOPICS["lmd"] and k >= 2) or (topic == OUTPUT_TOPICS["lms"]
                                                          and k < 2):
            return None
        return msg

    none = tmp_path / "none"
    _rewrite(annotated, none, disjoint)
    ev = run(bag, none)
    assert ev.example_frame is None and ev.example == {} and ev.answered_by_all == 0
    assert ev.rows["lmd"].frames_out == ev.rows["lms"].frames_out == 2


def test_quality_figures():
    r = MethodRows("lmd")
    rng = np.random.default_rng(0)
    iou = rng.uniform(0, 1, 400)
    tp = iou >= 0.5
    r.add(tp=tp, iou=iou, confidence=tp * 0.8 + 0.1, predicted_iou=iou,
          baseline=rng.uniform(0, 1, 400))
    q = r.quality()
    assert q["auroc"] == pytest.approx(1.0) and 0.4 < q["auroc_baseline"] < 0.6
    assert q["r2"] == pytest.approx(1.0) and q["n"] == 400
    assert q["ece"] == pytest.approx(abs(0.9 - 1) * tp.mean() + 0.1 * (1 - tp.mean()))
    one_class = MethodRows("mimo")
    one_class.add(tp=np.ones(3), iou=np.ones(3), confidence=np.ones(3),
                  predicted_iou=np.ones(3), baseline=np.ones(3))
    assert one_class.quality()["auroc"] is None  # undefined with one outcome only
    assert MethodRows("lms").quality()["n"] == 0


def test_cli_scores_an_annotated_bag(bag, annotated, capsys):
    import json

    from lidar_quality_tools.evaluation import main

    assert main(["--bag", str(bag), "--outputs", str(annotated),
                 "--param", "lms.separate_probabilities=true"]) == 0
    q = json.loads(capsys.readouterr().out)
    assert {m: q[m]["frames_out"] for m in q} == dict.fromkeys(("lmd", "lms", "mimo"), N_FRAMES)
    with pytest.raises(SystemExit):
        main(["--bag", str(bag), "--param", "lmd_bad"])
