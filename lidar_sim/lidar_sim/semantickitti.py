"""SemanticKITTI dataset files, in the real formats.

``sequences/NN/velodyne/NNNNNN.bin`` (float32 x, y, z, remission), ``labels/NNNNNN.label``
(uint32 per point: SemanticKITTI class id in the lower 16 bits, instance id in the upper
16), ``poses.txt`` (KITTI odometry: 3 x 4 camera-0 poses relative to the first frame,
row-major), ``calib.txt`` (P0..P3, Tr) and ``times.txt`` (seconds).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .kitti import P0, P1, P2, P3, TR_VELO_TO_CAM, calib_text, write_velodyne


def encode_labels(semantic_kitti_id: np.ndarray, instance: np.ndarray) -> np.ndarray:
    """uint32 labels: class in the lower 16 bits, instance in the upper 16."""
    sem = np.asarray(semantic_kitti_id).astype(np.uint32)
    inst = np.asarray(instance).astype(np.uint32)
    if (sem > 0xFFFF).any() or (inst > 0xFFFF).any():
        raise ValueError("SemanticKITTI class and instance ids must fit in 16 bits")
    return (inst << 16) | sem


def decode_labels(raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`encode_labels`: (class ids, instance ids) as uint16."""
    raw = np.asarray(raw, dtype=np.uint32)
    return (raw & 0xFFFF).astype(np.uint16), (raw >> 16).astype(np.uint16)


def sequence_dir(root: Path, sequence: int) -> Path:
    return Path(root) / "sequences" / f"{sequence:02d}"


def write_scan(root: Path, sequence: int, index: int, xyz, intensity, semantic_kitti_id,
               instance) -> None:
    """One scan and its labels (point order shared by both files)."""
    seq = sequence_dir(root, sequence)
    (seq / "velodyne").mkdir(parents=True, exist_ok=True)
    (seq / "labels").mkdir(parents=True, exist_ok=True)
    write_velodyne(seq / "velodyne" / f"{index:06d}.bin", xyz, intensity)
    labels = encode_labels(semantic_kitti_id, instance).astype("<u4")
    (seq / "labels" / f"{index:06d}.label").write_bytes(labels.tobytes())


def _tr4() -> np.ndarray:
    tr = np.eye(4)
    tr[:3] = TR_VELO_TO_CAM
    return tr


def write_sequence_meta(root: Path, sequence: int, world_from_lidar: np.ndarray,
                        stamps_s: np.ndarray) -> None:
    """poses.txt (camera-0 poses relative to the first frame), calib.txt, times.txt."""
    seq = sequence_dir(root, sequence)
    seq.mkdir(parents=True, exist_ok=True)
    poses = np.asarray(world_from_lidar, dtype=np.float64).reshape(-1, 4, 4)
    tr = _tr4()
    first_inv = np.linalg.inv(poses[0]) if len(poses) else np.eye(4)
    cam = tr @ first_inv @ poses @ np.linalg.inv(tr)  # KITTI odometry: camera-0 frames
    (seq / "poses.txt").write_text(
        "".join(" ".join(f"{v:.9e}" for v in p[:3].reshape(-1)) + "\n" for p in cam))
    (seq / "calib.txt").write_text(
        calib_text((("P0", P0), ("P1", P1), ("P2", P2), ("P3", P3), ("Tr", TR_VELO_TO_CAM))))
    (seq / "times.txt").write_text("".join(f"{t:.6e}\n" for t in np.asarray(stamps_s)))


def lidar_poses_from_files(seq: Path) -> np.ndarray:
    """Read poses.txt + calib.txt back as lidar poses relative to the first lidar frame."""
    calib = {}
    for line in (seq / "calib.txt").read_text().splitlines():
        key, vals = line.split(":", 1)
        calib[key] = np.array([float(v) for v in vals.split()])
    tr = np.eye(4)
    tr[:3] = calib["Tr"].reshape(3, 4)
    rows = np.loadtxt(seq / "poses.txt", ndmin=2).reshape(-1, 3, 4)
    cam = np.tile(np.eye(4), (len(rows), 1, 1))
    cam[:, :3] = rows
    return np.linalg.inv(tr) @ cam @ tr
