"""KITTI object files read back by an independent minimal reader."""
import numpy as np
from lidar_sim import kitti


def _read_calib(path):
    out = {}
    for line in path.read_text().splitlines():
        key, vals = line.split(":", 1)
        out[key] = np.array([float(v) for v in vals.split()])
    return out


def _read_labels(path, calib):
    """KITTI label -> lidar boxes (x, y, z centre, l, w, h, yaw), types, truncated, occluded."""
    tr = calib["Tr_velo_to_cam"].reshape(3, 4)
    r0 = calib["R0_rect"].reshape(3, 3)
    rows = [line.split() for line in path.read_text().splitlines()]
    boxes, types, trunc, occ = [], [], [], []
    for r in rows:
        types.append(r[0])
        trunc.append(float(r[1]))
        occ.append(int(r[2]))
        h, w, l = map(float, r[8:11])
        loc = np.array(list(map(float, r[11:14])))
        ry = float(r[14])
        cam = np.linalg.solve(r0, loc)
        velo = tr[:, :3].T @ (cam - tr[:, 3])
        boxes.append([velo[0], velo[1], velo[2] + h / 2, l, w, h, -ry - np.pi / 2])
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
                          ["Car", "Pedestrian", "Car", "Car"], np.array([0.0, 0.5, 0.0, 0.9]))
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
    rect = kitti.velo_to_rect(np.array([[20.27, 0.0, -0.08]]))
    np.testing.assert_allclose(rect, [[0.0, 0.0, 20.0]], atol=1e-12)
    uv = kitti.project(rect)
    assert abs(uv[0, 0] - (609.5593 * 20 + 44.85728) / (20 + 0.002745884)) < 1e-9


def test_result_format_has_score_column():
    from lidar_sim.kitti import label_lines

    boxes = np.array([[12.0, 1.0, -0.9, 4.2, 1.8, 1.6, 0.1], [15.0, -2.0, -0.9, 0.6, 0.6, 1.7, 0.0]])
    plain = label_lines(boxes, ["Car", "Pedestrian"], np.zeros(2))
    scored = label_lines(boxes, ["Car", "Pedestrian"], np.zeros(2), scores=[0.875, 0.25])
    assert [len(line.split()) for line in plain] == [15, 15]
    assert [line.split()[:15] for line in scored] == [line.split() for line in plain]
    assert [float(line.split()[15]) for line in scored] == [0.875, 0.25]
