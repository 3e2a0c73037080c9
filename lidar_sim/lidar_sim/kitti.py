"""KITTI 3D object dataset files, in the real formats.

``velodyne/NNNNNN.bin`` float32 x, y, z, reflectance; ``label_2/NNNNNN.txt`` one object
per line (type truncated occluded alpha x1 y1 x2 y2 h w l x y z rotation_y, boxes in
the rectified camera frame with the location at the bottom centre); ``calib/NNNNNN.txt``
P0..P3, R0_rect, Tr_velo_to_cam, Tr_imu_to_velo; ``ImageSets/<split>.txt``.

Every conversion between the lidar frame and the camera frame takes the frame's
:class:`Calibration` explicitly: a dataset's own ``calib/<id>.txt``
(:meth:`Calibration.from_file`, each KITTI frame has its own), or, only for data without
one (the simulation has no camera), :data:`SIM_CALIB`, a fixed KITTI-like calibration.
Writers record the calibration they used in a ``calib/<id>.txt`` beside what they wrote,
so readers never guess. Only objects whose box projects into the 1242 x 375 image are
written, as in KITTI.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from lidar_quality_core.conventions import wrap_angle

IMAGE_WIDTH, IMAGE_HEIGHT = 1242, 375
# The simulator's fixed calibration (use it through SIM_CALIB).
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

_SHAPES = {"P2": (3, 4), "R0_rect": (3, 3), "Tr_velo_to_cam": (3, 4)}
_FILE_ORDER = ("P0", "P1", "P2", "P3", "R0_rect", "Tr_velo_to_cam", "Tr_imu_to_velo")


def _frozen(a, shape, name: str, source: str) -> np.ndarray:
    m = np.array(a, dtype=np.float64)
    if m.size != shape[0] * shape[1]:
        raise ValueError(f"{source}: {name} has {m.size} values, expected "
                         f"{shape[0] * shape[1]} ({shape[0]} x {shape[1]})")
    m = m.reshape(shape)
    if not np.isfinite(m).all():
        raise ValueError(f"{source}: {name} has non-finite values")
    m.setflags(write=False)
    return m


@dataclass(frozen=True, eq=False)
class Calibration:
    """One frame's KITTI object calibration (the part that places boxes).

    ``p2``: camera 2 projection (3, 4); ``r0_rect`` (3, 3); ``tr_velo_to_cam`` (3, 4);
    ``extra``: the file's other matrices (P0, P1, P3, Tr_imu_to_velo, ...), kept so that
    :meth:`text` writes the file back whole. ``image_size`` (width, height) is not in the
    file: KITTI's 1242 x 375 unless given. ``source`` names it in messages.
    """

    p2: np.ndarray
    r0_rect: np.ndarray
    tr_velo_to_cam: np.ndarray
    extra: tuple = ()
    image_size: tuple = (IMAGE_WIDTH, IMAGE_HEIGHT)
    source: str = "calibration"

    def __post_init__(self):
        for name, attr in (("P2", "p2"), ("R0_rect", "r0_rect"), ("Tr_velo_to_cam", "tr_velo_to_cam")):
            object.__setattr__(self, attr, _frozen(getattr(self, attr), _SHAPES[name], name,
                                                   self.source))
        for name, m in (("R0_rect", self.r0_rect), ("Tr_velo_to_cam", self.tr_velo_to_cam[:, :3])):
            if abs(np.linalg.det(m)) < 1e-6:
                raise ValueError(f"{self.source}: {name} rotation is singular")
        extra = tuple((str(k), np.array(v, dtype=np.float64)) for k, v in self.extra)
        for _, m in extra:
            m.setflags(write=False)
        object.__setattr__(self, "extra", extra)
        w, h = self.image_size
        object.__setattr__(self, "image_size", (int(w), int(h)))

    @classmethod
    def parse(cls, text: str, source: str = "calibration text", **kw) -> Calibration:
        """A calibration from KITTI's ``key: row-major values`` lines."""
        vals = {}
        for n, line in enumerate(text.splitlines(), 1):
            if not line.strip():
                continue
            key, sep, rest = line.partition(":")
            if not sep:
                raise ValueError(f"{source}:{n}: expected 'key: values', got {line[:60]!r}")
            try:
                vals[key.strip()] = np.array(rest.split(), dtype=np.float64)
            except ValueError:
                raise ValueError(f"{source}:{n}: {key.strip()} values are not numbers") from None
        missing = [k for k in _SHAPES if k not in vals]
        if missing:
            raise ValueError(f"{source}: no {', '.join(missing)} (has {', '.join(vals) or 'nothing'})")
        return cls(vals["P2"], vals["R0_rect"], vals["Tr_velo_to_cam"],
                   extra=tuple((k, v) for k, v in vals.items() if k not in _SHAPES),
                   source=source, **kw)

    @classmethod
    def from_file(cls, path, **kw) -> Calibration:
        """A KITTI object calibration file (``calib/<id>.txt``)."""
        return cls.parse(Path(path).read_text(), source=str(path), **kw)

    def rows(self) -> tuple:
        """(key, matrix) of every matrix, in KITTI's file order."""
        known = {"P2": self.p2, "R0_rect": self.r0_rect, "Tr_velo_to_cam": self.tr_velo_to_cam}
        known.update((k, v) for k, v in self.extra if k not in known)
        return (tuple((k, known[k]) for k in _FILE_ORDER if k in known)
                + tuple((k, v) for k, v in known.items() if k not in _FILE_ORDER))

    def text(self) -> str:
        """The calibration file's text."""
        return calib_text(self.rows())

    def velo_to_rect(self, xyz) -> np.ndarray:
        """Lidar points (N, 3) -> rectified camera coordinates (N, 3)."""
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        tr = self.tr_velo_to_cam
        return (self.r0_rect @ (tr[:, :3] @ xyz.T + tr[:, 3:])).T

    def rect_to_velo(self, rect) -> np.ndarray:
        """Rectified camera points (N, 3) -> lidar coordinates (N, 3)."""
        rect = np.asarray(rect, dtype=np.float64).reshape(-1, 3)
        tr = self.tr_velo_to_cam
        return np.linalg.solve(tr[:, :3], np.linalg.solve(self.r0_rect, rect.T) - tr[:, 3:]).T

    def project(self, rect) -> np.ndarray:
        """Rectified camera points (N, 3) -> camera 2 image pixels (N, 2)."""
        rect = np.asarray(rect, dtype=np.float64).reshape(-1, 3)
        h = np.hstack([rect, np.ones((len(rect), 1))]) @ self.p2.T
        return h[:, :2] / h[:, 2:3]


def calib_path(directory, frame_id: str) -> Path:
    """Where a frame's calibration lives: ``<directory>/calib/<frame_id>.txt``."""
    return Path(directory) / "calib" / f"{frame_id}.txt"


def camera_boxes(boxes, calib: Calibration) -> np.ndarray:
    """Lidar boxes (N, 7: centre x, y, z, l, w, h, yaw) -> KITTI camera boxes (N, 7: h, w,
    l, bottom centre x, y, z in the rectified camera frame, rotation_y)."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    bottom = calib.velo_to_rect(np.column_stack([b[:, :2], b[:, 2] - b[:, 5] / 2]))
    # yaw about lidar z <-> rotation_y about camera y (the usual KITTI convention)
    ry = wrap_angle(-b[:, 6] - np.pi / 2)
    return np.column_stack([b[:, 5], b[:, 4], b[:, 3], bottom, ry])


def lidar_boxes(hwl_xyz_ry, calib: Calibration) -> np.ndarray:
    """Inverse of :func:`camera_boxes`."""
    a = np.asarray(hwl_xyz_ry, dtype=np.float64).reshape(-1, 7)
    h, w, l = a[:, 0], a[:, 1], a[:, 2]
    v = calib.rect_to_velo(a[:, 3:6])
    yaw = wrap_angle(-a[:, 6] - np.pi / 2)
    return np.column_stack([v[:, 0], v[:, 1], v[:, 2] + h / 2, l, w, h, yaw])


def occlusion_level(occluded_fraction: np.ndarray) -> np.ndarray:
    """KITTI's integer occlusion state: 0 fully visible, 1 partly, 2 largely occluded."""
    f = np.asarray(occluded_fraction, dtype=np.float64)
    return np.where(f < 0.2, 0, np.where(f < 0.6, 1, 2)).astype(int)


def label_lines(boxes: np.ndarray, types: list[str], occluded_fraction: np.ndarray,
                scores=None, *, calib: Calibration) -> list[str]:
    """KITTI label lines for the lidar boxes (N, 7: centre x, y, z, l, w, h, yaw) whose
    projection meets ``calib``'s image; truncation = share of the projected box outside it.
    With ``scores`` the lines are in KITTI's result format (a 16th column, the score) and
    the 3D box has 4 decimals (labels: 2, as KITTI's), so results round-trip to 1e-4."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    if len(types) != len(boxes) or (scores is not None and len(scores) != len(boxes)):
        raise ValueError(f"{len(boxes)} boxes but {len(types)} types"
                         + ("" if scores is None else f" and {len(scores)} scores"))
    occ = occlusion_level(occluded_fraction)
    cam = camera_boxes(boxes, calib)
    d = 2 if scores is None else 4
    lines = []
    for i, img in enumerate(_image_boxes(boxes, calib)):
        if img is None:
            continue
        x1, y1, x2, y2, cx1, cy1, cx2, cy2 = img
        truncated = 1.0 - (cx2 - cx1) * (cy2 - cy1) / ((x2 - x1) * (y2 - y1))
        h, w, length, x, y, z, rotation_y = cam[i]
        alpha = _wrap(rotation_y - np.arctan2(x, z))
        lines.append(f"{types[i]} {truncated:.2f} {occ[i]} {alpha:.2f} "
                     f"{cx1:.2f} {cy1:.2f} {cx2:.2f} {cy2:.2f} "
                     f"{h:.{d}f} {w:.{d}f} {length:.{d}f} "
                     f"{x:.{d}f} {y:.{d}f} {z:.{d}f} {rotation_y:.{d}f}"
                     + (f" {float(scores[i]):.4f}" if scores is not None else ""))
    return lines


def _image_boxes(boxes: np.ndarray, calib: Calibration) -> list:
    """Per box: its projected 2D box and the part inside the image
    ``(x1, y1, x2, y2, cx1, cy1, cx2, cy2)``, or None when KITTI would not label it."""
    from lidar_quality_core.box_geometry import corners_3d

    width, height = calib.image_size
    out = []
    for corners in corners_3d(np.asarray(boxes, dtype=np.float64).reshape(-1, 7)):
        rect = calib.velo_to_rect(corners)
        if (rect[:, 2] <= 0.1).any():
            out.append(None)  # behind or beside the camera: KITTI labels only what the image sees
            continue
        uv = calib.project(rect)
        x1, y1 = uv.min(axis=0)
        x2, y2 = uv.max(axis=0)
        cx1, cy1 = max(x1, 0.0), max(y1, 0.0)
        cx2, cy2 = min(x2, width - 1.0), min(y2, height - 1.0)
        out.append((x1, y1, x2, y2, cx1, cy1, cx2, cy2) if cx1 < cx2 and cy1 < cy2 else None)
    return out


def in_image(boxes: np.ndarray, *, calib: Calibration) -> np.ndarray:
    """Which lidar boxes KITTI labels: those whose projection meets the camera image."""
    return np.array([b is not None for b in _image_boxes(boxes, calib)], dtype=bool)


def _wrap(a: float) -> float:
    return float(wrap_angle(a))


OBJECT_CALIB = (("P0", P0), ("P1", P1), ("P2", P2), ("P3", P3), ("R0_rect", R0_RECT),
                ("Tr_velo_to_cam", TR_VELO_TO_CAM), ("Tr_imu_to_velo", TR_IMU_TO_VELO))


def calib_text(rows=OBJECT_CALIB) -> str:
    """KITTI calibration file text: one ``key: row-major values`` line per matrix."""
    return "".join(f"{k}: {' '.join(f'{v:.12e}' for v in np.asarray(m).reshape(-1))}\n"
                   for k, m in rows)


#: The simulator's fixed calibration: only for data that has no calibration of its own.
SIM_CALIB = Calibration(P2, R0_RECT, TR_VELO_TO_CAM,
                        extra=tuple((k, m) for k, m in OBJECT_CALIB if k not in _SHAPES),
                        source="lidar_sim.kitti.SIM_CALIB (the simulator's calibration)")


def write_velodyne(path: Path, xyz: np.ndarray, intensity: np.ndarray) -> None:
    """``.bin`` scan: float32 x, y, z, reflectance per point, little endian."""
    scan = np.empty((len(xyz), 4), dtype="<f4")
    scan[:, :3] = xyz
    scan[:, 3] = intensity
    path.write_bytes(scan.tobytes())


def write_frame(root: Path, frame_id: str, xyz, intensity, boxes, types, occluded_fraction,
                split: str = "training", *, calib: Calibration) -> int:
    """Write one frame's scan, labels and calibration; returns the number of labels."""
    base = Path(root) / split
    for sub in ("velodyne", "label_2", "calib"):
        (base / sub).mkdir(parents=True, exist_ok=True)
    write_velodyne(base / "velodyne" / f"{frame_id}.bin", xyz, intensity)
    lines = label_lines(boxes, types, occluded_fraction, calib=calib)
    (base / "label_2" / f"{frame_id}.txt").write_text("".join(line + "\n" for line in lines))
    calib_path(base, frame_id).write_text(calib.text())
    return len(lines)


def write_results(directory, frame_id: str, boxes, types, scores, *, calib: Calibration) -> int:
    """``<directory>/<frame_id>.txt`` in KITTI's result format (occlusion 0: results carry
    no estimate) and the calibration it was written with, ``<directory>/calib/<frame_id>.txt``;
    returns the number of lines."""
    lines = label_lines(boxes, types, np.zeros(len(types)), scores, calib=calib)
    (Path(directory) / "calib").mkdir(parents=True, exist_ok=True)
    (Path(directory) / f"{frame_id}.txt").write_text("".join(line + "\n" for line in lines))
    calib_path(directory, frame_id).write_text(calib.text())
    return len(lines)


def write_image_sets(root: Path, splits: dict[str, list[str]]) -> None:
    """``ImageSets/<name>.txt`` with one frame id per line (e.g. train, val, test)."""
    (Path(root) / "ImageSets").mkdir(parents=True, exist_ok=True)
    for name, ids in splits.items():
        (Path(root) / "ImageSets" / f"{name}.txt").write_text("".join(f"{i}\n" for i in ids))
