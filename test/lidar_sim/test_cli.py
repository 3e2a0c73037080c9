"""lidar-sim generate end to end on a tiny run: outputs exist, KITTI boxes contain points,
errors.jsonl replays onto the clean labels, runs are deterministic for a seed."""
import json

import numpy as np
from lidar_quality_core.box_geometry import count_points_in_boxes
from lidar_sim.cli import main


def _kitti_boxes(label_path):
    from lidar_sim import kitti
    rows = [l.split() for l in label_path.read_text().splitlines()]
    out = []
    for r in rows:
        h, w, l = map(float, r[8:11])
        loc = np.array(list(map(float, r[11:14])))
        velo = kitti.TR_VELO_TO_CAM[:, :3].T @ (loc - kitti.TR_VELO_TO_CAM[:, 3])
        out.append([velo[0], velo[1], velo[2] + h / 2, l, w, h, -float(r[14]) - np.pi / 2])
    return np.array(out).reshape(-1, 7)


def test_generate_small(tmp_path, capsys):
    out = tmp_path / "sim"
    assert main(["generate", "--sequences", "2", "--frames", "2", "--seed", "3", "--out", str(out),
                 "--annotation-errors", "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 4
    assert 80_000 < summary["points_per_frame"]["mean"] < 140_000
    assert (out / "bags" / "seq_00" / "metadata.yaml").exists()
    assert (out / "kitti" / "ImageSets" / "val.txt").read_text().split() == ["010000", "010001"]
    labelled = 0
    for label in sorted((out / "kitti" / "training" / "label_2").glob("*.txt")):
        scan = np.fromfile(out / "kitti" / "training" / "velodyne" / f"{label.stem}.bin",
                           dtype="<f4").reshape(-1, 4)
        boxes = _kitti_boxes(label)
        labelled += len(boxes)
        # 2-decimal label text: a 5 cm margin keeps boundary points of small objects inside
        assert (count_points_in_boxes(scan[:, :3], boxes, margin=0.05) > 0).all(), label.name
    assert labelled > 0
    errors = [json.loads(l) for l in (out / "annotated" / "errors.jsonl").read_text().splitlines()]
    assert errors and {e["kind"] for e in errors} <= {"missing", "shifted", "resized",
                                                       "wrong_class", "mislabeled_region"}
    assert "frames" in capsys.readouterr().out


def test_deterministic(tmp_path):
    for name in ("a", "b"):
        main(["generate", "--sequences", "1", "--frames", "1", "--seed", "5",
              "--out", str(tmp_path / name), "--quiet"])
    for rel in ("kitti/training/velodyne/000000.bin", "kitti/training/label_2/000000.txt",
                "semantickitti/sequences/00/labels/000000.label"):
        assert (tmp_path / "a" / rel).read_bytes() == (tmp_path / "b" / rel).read_bytes(), rel


def test_annotated_labels_differ_only_by_listed_errors(tmp_path):
    out = tmp_path / "sim"
    main(["generate", "--sequences", "1", "--frames", "2", "--seed", "9", "--out", str(out),
          "--annotation-errors", "--quiet"])
    errors = [json.loads(l) for l in (out / "annotated" / "errors.jsonl").read_text().splitlines()]
    touched_types = {(e["kitti_frame_id"]) for e in errors if e["kind"] == "wrong_class"}
    for label in sorted((out / "kitti" / "training" / "label_2").glob("*.txt")):
        clean = [l.split()[0] for l in label.read_text().splitlines()]
        annotated = out / "annotated" / "kitti" / "training" / "label_2" / label.name
        ann = [l.split()[0] for l in annotated.read_text().splitlines()]
        if label.stem not in touched_types and len(clean) == len(ann):
            assert clean == ann  # e.g. a Van stays a Van when no error touched it


def test_every_listed_box_error_shows_in_the_label_files(tmp_path):
    """Errors are only injected on boxes KITTI labels (in the camera image): a listed
    'missing' box is one label line fewer, a listed shift / resize / class change alters a
    line, so no listed error is invisible in the annotated files."""
    out = tmp_path / "sim"
    main(["generate", "--sequences", "1", "--frames", "3", "--seed", "11", "--out", str(out),
          "--annotation-errors", "--quiet"])
    errors = [json.loads(l) for l in (out / "annotated" / "errors.jsonl").read_text().splitlines()]
    box_errors = [e for e in errors if e["kind"] in ("missing", "shifted", "resized", "wrong_class")]
    assert box_errors
    for fid in sorted({e["kitti_frame_id"] for e in box_errors}):
        clean = (out / "kitti" / "training" / "label_2" / f"{fid}.txt").read_text().splitlines()
        ann = (out / "annotated" / "kitti" / "training" / "label_2" / f"{fid}.txt").read_text().splitlines()
        mine = [e for e in box_errors if e["kitti_frame_id"] == fid]
        n_missing = sum(e["kind"] == "missing" for e in mine)
        assert len(clean) - len(ann) == n_missing
        # each touched object's clean line is gone (removed or altered) from the annotated file
        assert len(set(clean) - set(ann)) == len({e["instance"] for e in mine})
