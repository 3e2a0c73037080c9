"""Rigid transforms and a small transform buffer (tf2's model, no rclpy).

A :class:`Transform` ``T_a_b`` (translation + unit quaternion ``x, y, z, w``) maps points
given in frame ``b`` into frame ``a``: ``p_a = R p_b + t``; ``T_a_b * T_b_c = T_a_c``. A
``geometry_msgs/TransformStamped`` with ``header.frame_id = a`` and ``child_frame_id = b``
is ``T_a_b``, and ``lookup(target=a, source=b)`` returns it, as in tf2.

Boxes (``x, y, z, l, w, h, yaw``, see ``boxes``) are upright: :meth:`Transform.apply_boxes`
moves the centre by the full transform and adds the transform's yaw to the box yaw; a
transform that tilts (|roll| or |pitch| above ``boxes.TILT_TOLERANCE_DEG``) would tilt the
boxes, which upright boxes cannot hold, so only its yaw is applied to the orientation and
an issue text says so.

:class:`TransformBuffer` holds a tree of frames (each child has one parent; the newest
message for a child decides it), static edges (valid at any time) and timestamped ones
(a bounded history per edge, linear / slerp interpolation between samples; a stamp outside
the samples by more than ``extrapolation_tolerance_ns`` is refused). ``lookup(target,
source, stamp_ns)`` chains edges through the tree; a missing transform raises a
:class:`TransformError` naming the frames and the stamp. Thread-safe (a listener fills it
while a frame worker reads it).
"""
from __future__ import annotations

import bisect
import threading
from collections import deque
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .boxes import TILT_TOLERANCE_DEG, quaternion_to_rpy
from .frame import FrameRejected
from .parameters import param

__all__ = ["Transform", "TransformError", "ConnectivityError", "ExtrapolationError",
           "TransformBuffer", "Lookup", "transform_from_msg", "add_tf_message", "stamp_ns",
           "normalize_frame", "NoTransformError", "input_transforms"]

#: ``lookup(target, source, stamp_ns) -> Transform`` (a buffer's bound method, or any callable)
Lookup = Callable[[str, str, "int | None"], "Transform"]


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz])


def _rotation_matrix(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


@dataclass(frozen=True, eq=False)
class Transform:
    """Rigid transform ``T_a_b``: ``translation`` (3,), ``rotation`` unit quaternion
    (x, y, z, w). Built with a quaternion of any norm > 0 (normalised here)."""

    translation: np.ndarray
    rotation: np.ndarray

    def __post_init__(self):
        t = np.asarray(self.translation, dtype=np.float64).reshape(3)
        q = np.asarray(self.rotation, dtype=np.float64).reshape(4)
        n = float(np.linalg.norm(q))
        if not (np.isfinite(t).all() and np.isfinite(q).all()) or n < 1e-9:
            raise ValueError(f"not a rigid transform: translation {t.tolist()}, "
                             f"rotation {q.tolist()}")
        q = q / n
        if q[3] < 0:  # one sign per rotation: comparisons and slerp take the short way
            q = -q
        object.__setattr__(self, "translation", t)
        object.__setattr__(self, "rotation", q)

    @classmethod
    def identity(cls) -> "Transform":
        return cls(np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))

    @classmethod
    def from_yaw(cls, yaw: float, translation=(0.0, 0.0, 0.0)) -> "Transform":
        """A rotation of ``yaw`` [rad] about +z, then ``translation``."""
        return cls(np.asarray(translation, np.float64),
                   np.array([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)]))

    @classmethod
    def from_matrix(cls, m: np.ndarray) -> "Transform":
        """From a 4x4 homogeneous matrix (its 3x3 block must be a rotation)."""
        m = np.asarray(m, np.float64)
        r = m[:3, :3]
        tr = np.trace(r)
        # Shepperd: the largest of w, x, y, z first, for a stable quaternion
        k = int(np.argmax([tr, r[0, 0], r[1, 1], r[2, 2]]))
        if k == 0:
            s = 2.0 * np.sqrt(1.0 + tr)
            q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s,
                 s / 4]
        elif k == 1:
            s = 2.0 * np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
            q = [s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s,
                 (r[2, 1] - r[1, 2]) / s]
        elif k == 2:
            s = 2.0 * np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
            q = [(r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s,
                 (r[0, 2] - r[2, 0]) / s]
        else:
            s = 2.0 * np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
            q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4,
                 (r[1, 0] - r[0, 1]) / s]
        return cls(m[:3, 3], np.array(q))

    # -------------------------------------------------------------- algebra
    def rotation_matrix(self) -> np.ndarray:
        return _rotation_matrix(self.rotation)

    def matrix(self) -> np.ndarray:
        """4x4 homogeneous matrix."""
        m = np.eye(4)
        m[:3, :3] = self.rotation_matrix()
        m[:3, 3] = self.translation
        return m

    def __mul__(self, other: "Transform") -> "Transform":
        """``T_a_b * T_b_c = T_a_c`` (``other`` applied first)."""
        if not isinstance(other, Transform):
            return NotImplemented
        return Transform(self.rotation_matrix() @ other.translation + self.translation,
                         _quat_mul(self.rotation, other.rotation))

    compose = __mul__

    def inverse(self) -> "Transform":
        x, y, z, w = self.rotation
        qi = np.array([-x, -y, -z, w])
        return Transform(-(_rotation_matrix(qi) @ self.translation), qi)

    def rpy(self) -> tuple[float, float, float]:
        """Roll, pitch, yaw [rad] (ZYX, as ``boxes.quaternion_to_rpy``)."""
        r, p, y = quaternion_to_rpy(self.rotation[None])[0]
        return float(r), float(p), float(y)

    def tilt_deg(self) -> float:
        """Larger of |roll| and |pitch| [deg]."""
        r, p, _ = self.rpy()
        return float(np.degrees(max(abs(r), abs(p))))

    def is_identity(self, atol: float = 1e-12) -> bool:
        return bool(np.allclose(self.translation, 0.0, atol=atol)
                    and np.allclose(self.rotation[:3], 0.0, atol=atol))

    def close_to(self, other: "Transform", atol: float = 1e-9) -> bool:
        return bool(np.allclose(self.translation, other.translation, atol=atol)
                    and np.allclose(self.rotation, other.rotation, atol=atol))

    # -------------------------------------------------------------- application
    def apply_points(self, xyz: np.ndarray) -> np.ndarray:
        """(N, 3) points in frame b -> frame a (float64; NaN stays NaN)."""
        xyz = np.asarray(xyz)
        if self.is_identity(0.0):
            return xyz
        return xyz.astype(np.float64, copy=False) @ self.rotation_matrix().T + self.translation

    def apply_boxes(self, boxes: np.ndarray,
                    tolerance_deg: float = TILT_TOLERANCE_DEG) -> tuple[np.ndarray, str | None]:
        """(N, 7) upright boxes in frame b -> frame a, and an issue text when the transform
        tilts by more than ``tolerance_deg`` (then only its yaw turns the boxes). Yaw is
        wrapped to [-pi, pi)."""
        b = np.array(boxes, dtype=np.float64, copy=True).reshape(-1, 7)
        _, _, yaw = self.rpy()
        b[:, :3] = self.apply_points(b[:, :3])
        b[:, 6] = (b[:, 6] + yaw + np.pi) % (2 * np.pi) - np.pi
        tilt = self.tilt_deg()
        issue = None
        if tilt > tolerance_deg and len(b):
            issue = (f"the transform tilts by {tilt:.1f} deg (roll/pitch): box centres are "
                     "moved by the full transform, orientations turned by its yaw only "
                     "(boxes stay upright)")
        return b, issue

    def __repr__(self) -> str:
        t = ", ".join(f"{v:.6g}" for v in self.translation)
        q = ", ".join(f"{v:.6g}" for v in self.rotation)
        return f"Transform(t=[{t}], q=[{q}])"


def _slerp(q0: np.ndarray, q1: np.ndarray, a: float) -> np.ndarray:
    d = float(np.dot(q0, q1))
    if d < 0.0:  # the short way round
        q1, d = -q1, -d
    if d > 0.9995:  # nearly equal: lerp is exact enough and avoids 0/0
        q = q0 + a * (q1 - q0)
        return q / np.linalg.norm(q)
    th = np.arccos(min(d, 1.0))
    return (np.sin((1 - a) * th) * q0 + np.sin(a * th) * q1) / np.sin(th)


def interpolate(t0: Transform, t1: Transform, a: float) -> Transform:
    """Linear translation, slerp rotation; ``a`` = 0 gives ``t0``, 1 gives ``t1``."""
    return Transform(t0.translation + a * (t1.translation - t0.translation),
                     _slerp(t0.rotation, t1.rotation, a))


# ------------------------------------------------------------------ errors
class TransformError(LookupError):
    """No transform from ``source`` to ``target`` at ``stamp_ns`` (None: latest)."""

    def __init__(self, target: str, source: str, stamp_ns: int | None, why: str):
        self.target, self.source, self.stamp_ns, self.why = target, source, stamp_ns, why
        at = "latest" if stamp_ns is None else f"stamp {stamp_ns / 1e9:.9f} s"
        super().__init__(f"no transform from {source!r} to {target!r} at {at}: {why}")


class ConnectivityError(TransformError):
    """A frame is unknown, or the two frames are in different trees."""


class ExtrapolationError(TransformError):
    """The frames are connected, but a timestamped edge has no sample near the stamp."""


class NoTransformError(FrameRejected):
    """A frame dropped because an input cannot be brought into the computation frame."""

    reason = "no_transform"
    cause = "no_transform"


def normalize_frame(frame: str) -> str:
    """tf2 ignores a leading '/' (ROS 1 names)."""
    return frame[1:] if frame.startswith("/") else frame


# ------------------------------------------------------------------ buffer
class _Edge:
    """The transform parent <- child: static (one value) or a timestamped history."""

    __slots__ = ("parent", "static", "stamps", "values")

    def __init__(self, parent: str, static: bool, max_samples: int):
        self.parent, self.static = parent, static
        self.stamps: deque[int] = deque(maxlen=max_samples)
        self.values: deque[Transform] = deque(maxlen=max_samples)

    def add(self, stamp: int, value: Transform, history_ns: int) -> None:
        if self.static:
            self.stamps.clear()
            self.values.clear()
            self.stamps.append(stamp)
            self.values.append(value)
            return
        if not self.stamps or stamp > self.stamps[-1]:
            self.stamps.append(stamp)
            self.values.append(value)
        else:  # out of order (several publishers, a replayed bag): keep the history sorted
            s, v = list(self.stamps), list(self.values)
            i = bisect.bisect_left(s, stamp)
            if i < len(s) and s[i] == stamp:
                v[i] = value
            else:
                s.insert(i, stamp)
                v.insert(i, value)
            self.stamps.clear()
            self.values.clear()
            self.stamps.extend(s[-self.stamps.maxlen:])
            self.values.extend(v[-self.values.maxlen:])
        while len(self.stamps) > 1 and self.stamps[-1] - self.stamps[0] > history_ns:
            self.stamps.popleft()
            self.values.popleft()

    def at(self, stamp: int | None, tolerance_ns: int) -> Transform | str:
        """The value at ``stamp`` (None: newest), or why there is none."""
        if self.static or stamp is None:
            return self.values[-1]
        s = self.stamps
        if stamp < s[0] - tolerance_ns or stamp > s[-1] + tolerance_ns:
            return (f"stamp outside the samples of {self.parent!r} -> child "
                    f"({s[0] / 1e9:.9f} .. {s[-1] / 1e9:.9f} s, {len(s)} sample(s), "
                    f"tolerance {tolerance_ns / 1e9:g} s)")
        if stamp <= s[0]:
            return self.values[0]
        if stamp >= s[-1]:
            return self.values[-1]
        i = bisect.bisect_right(s, stamp)
        t0, t1 = s[i - 1], s[i]
        v0, v1 = self.values[i - 1], self.values[i]
        if t1 == t0:
            return v1
        return interpolate(v0, v1, (stamp - t0) / (t1 - t0))


class TransformBuffer:
    """Static and timestamped transforms of a frame tree (module docstring).

    ``history_s``: how far back a timestamped edge keeps samples (tf2's default is 10 s);
    ``max_samples``: at most that many per edge (memory bound at high publish rates);
    ``extrapolation_tolerance_s``: how far outside an edge's samples a stamp may lie and
    still get its nearest sample (tf2 allows none; a few ms absorbs clock jitter between a
    cloud and a 100 Hz /tf).
    """

    def __init__(self, history_s: float = 10.0, max_samples: int = 1000,
                 extrapolation_tolerance_s: float = 0.0):
        if history_s <= 0 or max_samples < 2 or extrapolation_tolerance_s < 0:
            raise ValueError("need history_s > 0, max_samples >= 2, "
                             "extrapolation_tolerance_s >= 0")
        self.history_ns = int(round(history_s * 1e9))
        self.max_samples = int(max_samples)
        self.tolerance_ns = int(round(extrapolation_tolerance_s * 1e9))
        self._edges: dict[str, _Edge] = {}  # child -> edge to its parent
        self._lock = threading.Lock()

    def set_transform(self, parent: str, child: str, transform: Transform, stamp_ns: int = 0,
                      static: bool = False) -> None:
        """Add ``T_parent_child`` (a /tf_static entry with ``static``, else a /tf sample at
        ``stamp_ns``). Raises ``ValueError`` for an empty frame name or a self-loop, and for
        an edge that would close a cycle."""
        parent, child = normalize_frame(parent), normalize_frame(child)
        if not parent or not child or parent == child:
            raise ValueError(f"bad transform frames: parent {parent!r}, child {child!r}")
        with self._lock:
            p = parent
            while p in self._edges:  # would the new edge make child its own ancestor?
                p = self._edges[p].parent
                if p == child:
                    raise ValueError(f"transform {parent!r} -> {child!r} would close a cycle")
            e = self._edges.get(child)
            if e is None or e.parent != parent or e.static != static:
                e = _Edge(parent, static, self.max_samples)  # a new parent replaces the old
                self._edges[child] = e
            e.add(int(stamp_ns), transform, self.history_ns)

    def frames(self) -> list[str]:
        with self._lock:
            return sorted(set(self._edges) | {e.parent for e in self._edges.values()})

    def parent(self, frame: str) -> str | None:
        with self._lock:
            e = self._edges.get(normalize_frame(frame))
            return None if e is None else e.parent

    def _chain(self, frame: str) -> list[str]:
        out = [frame]
        while out[-1] in self._edges:
            out.append(self._edges[out[-1]].parent)
        return out

    def lookup(self, target: str, source: str, stamp_ns: int | None = None) -> Transform:
        """``T_target_source`` at ``stamp_ns`` (None or 0: the newest time every timestamped
        edge of the chain has, as tf2's Time(0)); raises :class:`TransformError`."""
        target, source = normalize_frame(target), normalize_frame(source)
        if stamp_ns == 0:
            stamp_ns = None
        if target == source:
            return Transform.identity()
        with self._lock:
            known = set(self._edges) | {e.parent for e in self._edges.values()}
            unknown = [f for f in (source, target) if f not in known]
            if unknown:
                raise ConnectivityError(
                    target, source, stamp_ns, " and ".join(f"frame {f!r}" for f in unknown)
                    + f" {'is' if len(unknown) == 1 else 'are'} unknown (known frames: "
                    f"{', '.join(sorted(known)) or 'none, no transform received'})")
            up_s, up_t = self._chain(source), self._chain(target)
            common = next((f for f in up_s if f in set(up_t)), None)
            if common is None:
                raise ConnectivityError(
                    target, source, stamp_ns, f"they are in different trees (roots "
                    f"{up_t[-1]!r} and {up_s[-1]!r})")
            path_s = up_s[:up_s.index(common)]
            path_t = up_t[:up_t.index(common)]
            edges = [self._edges[f] for f in path_s + path_t]
            if stamp_ns is None:
                dyn = [e.stamps[-1] for e in edges if not e.static]
                stamp = min(dyn) if dyn else None
            else:
                stamp = stamp_ns
            t_c_s = self._up(path_s, stamp, target, source, stamp_ns)
            t_c_t = self._up(path_t, stamp, target, source, stamp_ns)
        return t_c_t.inverse() * t_c_s

    def _up(self, path: list[str], stamp, target, source, stamp_ns) -> Transform:
        """``T_top_frame`` of ``path[0]`` up through ``path`` (every frame's parent edge)."""
        t = Transform.identity()
        for f in path:
            e = self._edges[f]
            v = e.at(stamp, self.tolerance_ns)
            if isinstance(v, str):
                raise ExtrapolationError(target, source, stamp_ns,
                                         f"edge {e.parent!r} -> {f!r}: {v}")
            t = v * t
        return t

    def can_transform(self, target: str, source: str, stamp_ns: int | None = None) -> bool:
        try:
            self.lookup(target, source, stamp_ns)
        except TransformError:
            return False
        return True


# ------------------------------------------------------------------ messages
def stamp_ns(stamp) -> int:
    """``builtin_interfaces/Time`` (sec, nanosec) -> ns."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def transform_from_msg(tf) -> Transform:
    """A ``geometry_msgs/Transform`` (or anything with its fields: rosbags messages) ->
    :class:`Transform`; ``ValueError`` for a non-finite one or a zero quaternion."""
    t, q = tf.translation, tf.rotation
    return Transform(np.array([t.x, t.y, t.z], np.float64),
                     np.array([q.x, q.y, q.z, q.w], np.float64))


def add_tf_message(buffer: TransformBuffer, msg, static: bool) -> list[str]:
    """Add every ``TransformStamped`` of a ``tf2_msgs/TFMessage`` (rclpy or rosbags) to
    ``buffer``; returns one text per entry that was refused (bad numbers or frames)."""
    bad = []
    for ts in msg.transforms:
        try:
            buffer.set_transform(ts.header.frame_id, ts.child_frame_id,
                                 transform_from_msg(ts.transform), stamp_ns(ts.header.stamp),
                                 static=static)
        except ValueError as exc:
            bad.append(f"{ts.header.frame_id!r} -> {ts.child_frame_id!r}: {exc}")
    return bad


def input_transforms(target: str, inputs: dict, lookup: Lookup | None, *,
                     fix: str = "") -> tuple[dict, list[str]]:
    """``({name: T_target_input}, notes)`` for the inputs (name -> message with a header, or
    None) whose ``frame_id`` differs from ``target``, each looked up at its own stamp.
    An input in ``target`` needs nothing; an empty ``frame_id`` (on either side) cannot be
    looked up and is taken as ``target`` (a note says so). Raises :class:`NoTransformError`
    naming the input, both frames and the stamp when ``lookup`` has no transform (or is
    None); ``fix`` is appended to its text."""
    out, notes = {}, []
    target = normalize_frame(target or "")
    for name, msg in inputs.items():
        header = getattr(msg, "header", None)
        if header is None:
            continue
        src = normalize_frame(header.frame_id or "")
        if src == target:
            continue
        if not src or not target:
            notes.append(f"{name} frame_id {src!r} vs {target!r}: an empty frame_id cannot be "
                         "transformed, taken as the same frame")
            continue
        t_ns = stamp_ns(header.stamp)
        if lookup is None:
            raise NoTransformError(f"{name} is in {src!r}, the computation frame is {target!r}, "
                                   f"and no transform source is set{fix}")
        try:
            t = lookup(target, src, t_ns)
        except TransformError as exc:
            raise NoTransformError(f"{name}: {exc}{fix}") from None
        if not t.is_identity(0.0):
            out[name] = t
    return out, notes


def transform_tolerance_param():
    """The ``transform_tolerance`` parameter field of the nodes that transform their inputs."""
    return param(0.05, "Seconds a stamp may lie outside the samples of a moving (/tf) transform "
                       "and still take the nearest one (static transforms hold at any time).",
                 min_value=0.0)
