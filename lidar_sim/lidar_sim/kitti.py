"""KITTI 3D object dataset files, in the real formats.

``velodyne/NNNNNN.bin`` float32 x, y, z, reflectance; ``label_2/NNNNNN.txt`` one object
per line (type truncated occluded alpha x1 y1 x2 y2 h w l x y z rotation_y, boxes in
the rectified camera frame with the location at the bottom centre); ``calib/NNNNNN.txt``
P0..P3, R0_rect, Tr_velo_to_cam, Tr_imu_to_velo; ``ImageSets/<split>.txt``. There is no
camera in the simulation: the calibration is a fixed KITTI-like one and only objects
whose box projects into the (virtual) 1242 x 375 image are labelled, as in KITTI.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

IMAGE_WIDTH, IMAGE_HEIGHT = 1242, 375
#: Camera 2 intrinsics of KITTI's 2011_09_26 drive (the usual reference calibration).
P2 = np.array([[721.5377, 0.0, 609.5593, 44.85728],
               [0.0, 721.5377, 172.854, 0.2163791],
               [0.0, 0.0, 1.0, 0.002745884]])
P0 = np.array([[721.5377, 0.0, 609.5593, 0.0], [0.0, 721.5377, 172.854, 0.0], [0.0, 0.0, 1.0, 0.0]])
P1 = P0 - np.array([[0, 0, 0, 387.5744], [0, 0, 0, 0], [0, 0, 0, 0]])
P3 = np.array([[721.5377, 0.0, 609.5593, -339.5242],
               [0.0, 721.5377, 172.854, 2.199936],
               [0.0, 0.0, 1.0, 0.002729905]])
R0_RECT = np.eye(3)
#: Lidar (x forward, y left, z up) -> camera (x right, y down, z forward), camera 0.27 m
#: in front of and 0.08 m below the lidar.
TR_VELO_TO_CAM = np.array([[0.0, -1.0, 0.0, 0.0],
                           [0.0, 0.0, -1.0, -0.08],
                           [1.0, 0.0, 0.0, -0.27]])
TR_IMU_TO_VELO = np.array([[1.0, 0.0, 0.0, -0.81], [0.0, 1.0, 0.0, 0.32], [0.0, 0.0, 1.0, -0.8]])


def velo_to_rect(xyz: np.ndarray) -> np.ndarray:
    """Lidar points (N, 3) -> rectified camera coordinates (N, 3)."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    return (R0_RECT @ (TR_VELO_TO_CAM[:, :3] @ xyz.T + TR_VELO_TO_CAM[:, 3:])).T


def project(rect: np.ndarray) -> np.ndarray:
    """Rectified camera points (N, 3) -> image pixels (N, 2) with camera 2."""
    h = np.hstack([rect, np.ones((len(rect), 1))]) @ P2.T
    return h[:, :2] / h[:, 2:3]


def occlusion_level(occluded_fraction: np.ndarray) -> np.ndarray:
    """KITTI's integer occlusion state: 0 fully visible, 1 partly, 2 largely occluded."""
    f = np.asarray(occluded_fraction, dtype=np.float64)
    return np.where(f < 0.2, 0, np.where(f < 0.6, 1, 2)).astype(int)


def label_lines(boxes: np.ndarray, types: list[str], occluded_fraction: np.ndarray,
                scores=None) -> list[str]:
    """KITTI label lines for the lidar boxes (N, 7: centre x, y, z, l, w, h, yaw) whose
    projection meets the image; truncation = share of the projected box outside it.
    With ``scores`` the lines are in KITTI's result format (a 16th column, the score)."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    occ = occlusion_level(occluded_fraction)
    lines = []
    for i, img in enumerate(_image_boxes(boxes)):
        if img is None:
            continue
        x1, y1, x2, y2, cx1, cy1, cx2, cy2 = img
        truncated = 1.0 - (cx2 - cx1) * (cy2 - cy1) / ((x2 - x1) * (y2 - y1))
        x, y, z, length, width, height, yaw = boxes[i]
        bottom = velo_to_rect(np.array([[x, y, z - height / 2]]))[0]
        rotation_y = _wrap(-yaw - np.pi / 2)
        alpha = _wrap(rotation_y - np.arctan2(bottom[0], bottom[2]))
        lines.append(f"{types[i]} {truncated:.2f} {occ[i]} {alpha:.2f} "
                     f"{cx1:.2f} {cy1:.2f} {cx2:.2f} {cy2:.2f} "
                     f"{height:.2f} {width:.2f} {length:.2f} "
                     f"{bottom[0]:.2f} {bottom[1]:.2f} {bottom[2]:.2f} {rotation_y:.2f}"
                     + (f" {float(scores[i]):.4f}" if scores is not None else ""))
    return lines


def _image_boxes(boxes: np.ndarray) -> list:
    """Per box: its projected 2D box and the part inside the image
    ``(x1, y1, x2, y2, cx1, cy1, cx2, cy2)``, or None when KITTI would not label it."""
    from lidar_quality_core.box_geometry import corners_3d

    out = []
    for corners in corners_3d(np.asarray(boxes, dtype=np.float64).reshape(-1, 7)):
        rect = velo_to_rect(corners)
        if (rect[:, 2] <= 0.1).any():
            out.append(None)  # behind or beside the camera: KITTI labels only what the image sees
            continue
        uv = project(rect)
        x1, y1 = uv.min(axis=0)
        x2, y2 = uv.max(axis=0)
        cx1, cy1 = max(x1, 0.0), max(y1, 0.0)
        cx2, cy2 = min(x2, IMAGE_WIDTH - 1.0), min(y2, IMAGE_HEIGHT - 1.0)
        out.append((x1, y1, x2, y2, cx1, cy1, cx2, cy2) if cx1 < cx2 and cy1 < cy2 else None)
    return out


def in_image(boxes: np.ndarray) -> np.ndarray:
    """Which lidar boxes KITTI labels: those whose projection meets the camera image."""
    return np.array([b is not None for b in _image_boxes(boxes)], dtype=bool)


def _wrap(a: float) -> float:
    return float((a + np.pi) % (2 * np.pi) - np.pi)


OBJECT_CALIB = (("P0", P0), ("P1", P1), ("P2", P2), ("P3", P3), ("R0_rect", R0_RECT),
                ("Tr_velo_to_cam", TR_VELO_TO_CAM), ("Tr_imu_to_velo", TR_IMU_TO_VELO))


def calib_text(rows=OBJECT_CALIB) -> str:
    """KITTI calibration file text: one ``key: row-major values`` line per matrix."""
    return "".join(f"{k}: {' '.join(f'{v:.12e}' for v in m.reshape(-1))}\n" for k, m in rows)


def write_velodyne(path: Path, xyz: np.ndarray, intensity: np.ndarray) -> None:
    """``.bin`` scan: float32 x, y, z, reflectance per point, little endian."""
    scan = np.empty((len(xyz), 4), dtype="<f4")
    scan[:, :3] = xyz
    scan[:, 3] = intensity
    path.write_bytes(scan.tobytes())


def write_frame(root: Path, frame_id: str, xyz, intensity, boxes, types, occluded_fraction,
                split: str = "training") -> int:
    """Write one frame's scan, labels and calibration; returns the number of labels."""
    base = Path(root) / split
    for sub in ("velodyne", "label_2", "calib"):
        (base / sub).mkdir(parents=True, exist_ok=True)
    write_velodyne(base / "velodyne" / f"{frame_id}.bin", xyz, intensity)
    lines = label_lines(boxes, types, occluded_fraction)
    (base / "label_2" / f"{frame_id}.txt").write_text("".join(line + "\n" for line in lines))
    (base / "calib" / f"{frame_id}.txt").write_text(calib_text())
    return len(lines)


def write_image_sets(root: Path, splits: dict[str, list[str]]) -> None:
    """``ImageSets/<name>.txt`` with one frame id per line (e.g. train, val, test)."""
    (Path(root) / "ImageSets").mkdir(parents=True, exist_ok=True)
    for name, ids in splits.items():
        (Path(root) / "ImageSets" / f"{name}.txt").write_text("".join(f"{i}\n" for i in ids))
