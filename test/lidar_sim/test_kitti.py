"""KITTI object files read back by an independent minimal reader; every conversion uses
the frame's own calibration (real KITTI frames round-trip through our writer and reader)."""

import numpy as np
import pytest
from lidar_sim import kitti
from realdata import require_realdata_kitti


def _read_calib(path):
    out = {}
    for line in filter(str.strip, path.read_text().splitlines()):
        key, vals = line.split(":", 1)
        out[key] = np.array([float(v) for v in vals.split()])
    return out


def _read_labels(path, calib):
    """KITTI label -> lidar boxes (x, y, z centre, l, w, h, yaw), types, truncated, occluded."""
    return _read_labels_of([line.split() for line in path.read_text().splitlines()], calib)


def _read_labels_of(rows, calib):
    tr = calib["Tr_velo_to_cam"].reshape(3, 4)
    r0 = calib["R0_rect"].reshape(3, 3)
    boxes, types, trunc, occ = [], [], [], []
    for r in rows:
        types.append(r[0])
        trunc.append(float(r[1]))
        occ.append(int(r[2]))
        h, w, l = map(float, r[8:11])
        loc = np.array(list(map(float, r[11:14])))
        ry = float(r[14])
        cam = np.linalg.solve(r0, loc)
        velo = np.linalg.solve(tr[:, :3], cam - tr[:, 3])
        yaw = (-ry - np.pi / 2 + np.pi) % (2 * np.pi) - np.pi
        boxes.append([velo[0], velo[1], velo[2] + h / 2, l, w, h, yaw])
    return np.array(boxes).reshape(-1, 7), types, trunc, occ


def test_roundtrip(tmp_path):
    rng = np.random.default_rng(0)
    boxes = np.array([[12.0, 1.5, -0.9, 4.2, 1.8, 1.6, 0.3],     # in front: labelled
                      [25.0, -4.0, -0.8, 0.6, 0.5, 1.7, -1.2],   # in front: labelled
                      [-10.0, 0.0, -0.9, 4.0, 1.8, 1.6, 0.0],    # behind: not labelled
                      [2.0, 15.0, -0.9, 4.0, 1.8, 1.6, 0.0]])    # beside: not in the image
    pts = np.concatenate([b[:3] + rng.uniform(-0.4, 0.4, (50, 3)) * [b[3] / 2, b[4] / 2, b[5] / 2] / 0.4
                          for b in boxes]).astype(np.float32)
    inten = rng.random(len(pts)).astype(np.float32)
    n = kitti.write_frame(tmp_path, "000007", pts, inten, boxes,
                          ["Car", "Pedestrian", "Car", "Car"], np.array([0.0, 0.5, 0.0, 0.9]),
                          calib=kitti.SIM_CALIB)
    kitti.write_image_sets(tmp_path, {"train": ["000007"], "val": []})
    assert n == 2
    scan = np.fromfile(tmp_path / "training" / "velodyne" / "000007.bin", dtype="<f4").reshape(-1, 4)
    np.testing.assert_array_equal(scan[:, :3], pts)
    np.testing.assert_array_equal(scan[:, 3], inten)
    calib = _read_calib(tmp_path / "training" / "calib" / "000007.txt")
    assert set(calib) == {"P0", "P1", "P2", "P3", "R0_rect", "Tr_velo_to_cam", "Tr_imu_to_velo"}
    read, types, trunc, occ = _read_labels(tmp_path / "training" / "label_2" / "000007.txt", calib)
    assert types == ["Car", "Pedestrian"] and occ == [0, 1]
    yaw_err = (read[:, 6] - boxes[:2, 6] + np.pi) % (2 * np.pi) - np.pi
    np.testing.assert_allclose(read[:, :6], boxes[:2, :6], atol=0.006)  # 2-decimal text
    np.testing.assert_allclose(yaw_err, 0, atol=0.006)
    assert all(0.0 <= t < 1.0 for t in trunc)
    # every labelled box contains points of the scan
    from lidar_quality_core.box_geometry import count_points_in_boxes
    assert (count_points_in_boxes(scan[:, :3], read) > 0).all()
    assert (tmp_path / "ImageSets" / "train.txt").read_text() == "000007\n"


def test_projection_of_a_point_ahead():
    # a point 20 m straight ahead, 0.08 m below the lidar, is on the camera axis
    rect = kitti.SIM_CALIB.velo_to_rect(np.array([[20.27, 0.0, -0.08]]))
    np.testing.assert_allclose(rect, [[0.0, 0.0, 20.0]], atol=1e-12)
    np.testing.assert_allclose(kitti.SIM_CALIB.rect_to_velo(rect), [[20.27, 0.0, -0.08]],
                               atol=1e-12)
    uv = kitti.SIM_CALIB.project(rect)
    assert abs(uv[0, 0] - (609.5593 * 20 + 44.85728) / (20 + 0.002745884)) < 1e-9


def test_result_format_has_score_column():
    from lidar_sim.kitti import label_lines

    boxes = np.array([[12.0, 1.0, -0.9, 4.2, 1.8, 1.6, 0.1], [15.0, -2.0, -0.9, 0.6, 0.6, 1.7, 0.0]])
    plain = label_lines(boxes, ["Car", "Pedestrian"], np.zeros(2), calib=kitti.SIM_CALIB)
    scored = label_lines(boxes, ["Car", "Pedestrian"], np.zeros(2), scores=[0.875, 0.25],
                         calib=kitti.SIM_CALIB)
    assert [len(line.split()) for line in plain] == [15, 15]
    assert [line.split()[:8] for line in scored] == [line.split()[:8] for line in plain]
    # the 3D box: 2 decimals in labels (KITTI's), 4 in results
    box_plain = np.array([line.split()[8:15] for line in plain], dtype=float)
    box_scored = np.array([line.split()[8:15] for line in scored], dtype=float)
    np.testing.assert_allclose(box_plain, box_scored, atol=0.005 + 1e-9)
    assert all(len(v.split(".")[1]) == 4 for line in scored for v in line.split()[8:15])
    assert [float(line.split()[15]) for line in scored] == [0.875, 0.25]
    with pytest.raises(ValueError, match="2 boxes but 1 types"):
        label_lines(boxes, ["Car"], np.zeros(2), calib=kitti.SIM_CALIB)



# ------------------------------------------------------------------------- calibration
def _other_calib():
    """A calibration unlike the simulator's: camera turned 0.02 rad about the vertical and
    tilted 0.01 rad, a rectification of 0.01 rad, other intrinsics."""
    def rot(axis, a):
        c, s = np.cos(a), np.sin(a)
        i, j = [(1, 2), (0, 2), (0, 1)][axis]
        m = np.eye(3)
        m[i, i] = m[j, j] = c
        m[i, j], m[j, i] = -s, s
        return m
    tr = np.array(kitti.TR_VELO_TO_CAM)
    tr[:, :3] = rot(1, 0.02) @ rot(0, 0.01) @ tr[:, :3]
    tr[:, 3] += [-0.02, 0.03, 0.01]
    p2 = np.array([[718.3, 0.0, 600.4, 44.5], [0.0, 718.3, 181.5, -0.6], [0.0, 0.0, 1.0, 0.0026]])
    return kitti.Calibration(p2, rot(2, 0.01), tr, source="test calibration")


def test_calibration_file_round_trip_and_errors(tmp_path):
    text = kitti.SIM_CALIB.text()
    assert text == kitti.calib_text()  # the simulator's files are unchanged
    path = tmp_path / "000001.txt"
    path.write_text(_other_calib().text())
    back = kitti.Calibration.from_file(path)
    for name in ("p2", "r0_rect", "tr_velo_to_cam"):
        np.testing.assert_allclose(getattr(back, name), getattr(_other_calib(), name),
                                   rtol=1e-12, atol=1e-15)  # KITTI's 13 digits
    assert back.source == str(path) and back.image_size == (1242, 375)
    sim = kitti.Calibration.parse(text)
    assert [k for k, _ in sim.rows()] == ["P0", "P1", "P2", "P3", "R0_rect", "Tr_velo_to_cam",
                                          "Tr_imu_to_velo"]
    assert sim.text() == text
    with pytest.raises(ValueError, match="f.txt: no Tr_velo_to_cam"):
        kitti.Calibration.parse("P2: " + " 1" * 12 + "\nR0_rect:" + " 1" * 9, source="f.txt")
    with pytest.raises(ValueError, match="R0_rect has 8 values, expected 9"):
        kitti.Calibration.parse(text.replace("R0_rect: 1.000000000000e+00", "R0_rect:"))
    with pytest.raises(ValueError, match="P2 values are not numbers"):
        kitti.Calibration.parse(text.replace("P2: 7", "P2: x"))
    with pytest.raises(ValueError, match="R0_rect rotation is singular"):
        kitti.Calibration(kitti.P2, np.zeros((3, 3)), kitti.TR_VELO_TO_CAM)
    with pytest.raises(ValueError):  # shared: nobody can change the simulator's calibration
        kitti.SIM_CALIB.p2[0, 0] = 1.0


def test_writer_uses_the_calibration_it_is_given(tmp_path):
    calib = _other_calib()
    rng = np.random.default_rng(3)
    pts = rng.uniform([-5, -3, -2], [5, 3, 2], (20, 3))
    np.testing.assert_allclose(calib.rect_to_velo(calib.velo_to_rect(pts)), pts, atol=1e-12)
    boxes = np.column_stack([rng.uniform(8, 45, 12), rng.uniform(-6, 6, 12), rng.uniform(-1.2, -0.5, 12),
                             rng.uniform(0.5, 5, 12), rng.uniform(0.5, 2, 12), rng.uniform(1.4, 2, 12),
                             rng.uniform(-np.pi, np.pi, 12)])
    types = ["Car"] * 12
    assert kitti.in_image(boxes, calib=calib).all()
    n = kitti.write_results(tmp_path, "000003", boxes, types, np.full(12, 0.5), calib=calib)
    assert n == 12
    recorded = _read_calib(kitti.calib_path(tmp_path, "000003"))
    read, _, _, _ = _read_labels(tmp_path / "000003.txt", recorded)
    np.testing.assert_allclose(read[:, :6], boxes[:, :6], atol=2e-4)
    np.testing.assert_allclose((read[:, 6] - boxes[:, 6] + np.pi) % (2 * np.pi) - np.pi, 0,
                               atol=1e-4)
    # the same boxes placed with the simulator's calibration land elsewhere
    sim = {"R0_rect": kitti.R0_RECT.reshape(-1), "Tr_velo_to_cam": kitti.TR_VELO_TO_CAM.reshape(-1)}
    wrong, _, _, _ = _read_labels(tmp_path / "000003.txt", sim)
    assert np.hypot(*(wrong[:, :2] - boxes[:, :2]).T).max() > 0.3


# ------------------------------------------------------------------ real KITTI frames
@pytest.fixture(scope="module")
def real_kitti():
    return require_realdata_kitti() / "training"


def test_real_frames_round_trip(real_kitti, tmp_path):
    """Real labels -> lidar boxes with the frame's calib -> our result writer -> our reader:
    the same boxes, to 1 cm and 0.01 rad; the projected 2D boxes are the labelled ones."""
    from lidar_quality_core.box_geometry import count_points_in_boxes
    from lidar_quality_training.lmd import dataset as D

    fids = sorted(p.stem for p in (real_kitti / "label_2").glob("*.txt"))
    assert fids
    for fid in fids:
        label = real_kitti / "label_2" / f"{fid}.txt"
        raw = [line.split() for line in label.read_text().splitlines()
               if line.split() and line.split()[0] != "DontCare"]
        # the reference: an independent reading of the frame's labels with its calibration
        ref, types, _, _ = _read_labels_of(raw, _read_calib(real_kitti / "calib" / f"{fid}.txt"))
        scan = np.fromfile(real_kitti / "velodyne" / f"{fid}.bin", "<f4").reshape(-1, 4)
        assert (count_points_in_boxes(scan[:, :3], ref) >= 10).all(), fid  # placed on the objects
        calib = D.frame_calib(real_kitti, fid)
        ours, _, _ = D.read_kitti_objects(label, calib)
        np.testing.assert_allclose(ours, ref, atol=1e-6)

        scores = np.linspace(0.1, 0.9, len(ref))
        assert kitti.write_results(tmp_path, fid, ref, types, scores, calib=calib) == len(ref)
        back, _, sc = D.read_kitti_objects(tmp_path / f"{fid}.txt", D.frame_calib(tmp_path, fid),
                                           with_score=True)
        np.testing.assert_allclose(back[:, :6], ref[:, :6], atol=0.01)
        np.testing.assert_allclose((back[:, 6] - ref[:, 6] + np.pi) % (2 * np.pi) - np.pi, 0,
                                   atol=0.01)
        np.testing.assert_allclose(sc, scores, atol=1e-4)
        # 2D boxes and truncation come from the frame's P2: those of the labels (untruncated
        # objects; the sim P2 is 3-7 px off)
        out = np.array([line.split()[1:8] for line in
                        (tmp_path / f"{fid}.txt").read_text().splitlines()], dtype=float)
        lab = np.array([r[1:8] for r in raw], dtype=float)
        untruncated = lab[:, 0] == 0
        assert np.median(np.abs(out[untruncated, 3:7] - lab[untruncated, 3:7])) < 1.0, fid
        np.testing.assert_allclose(out[:, 0], lab[:, 0], atol=0.015)
        # the simulator's calibration in the writer (the old defect) misses by far more
        kitti.write_results(tmp_path / "sim", fid, ref, types, scores, calib=kitti.SIM_CALIB)
        wrong, _, _ = D.read_kitti_objects(tmp_path / "sim" / f"{fid}.txt", calib, with_score=True)
        assert np.abs(wrong[:, :3] - ref[:, :3]).max() > 0.1
