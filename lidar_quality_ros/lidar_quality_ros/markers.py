"""RViz / Foxglove markers of the quality outputs: boxes or points coloured by confidence.

Colour map: confidence 0 red, 0.5 yellow, 1 green; NaN (no estimate) grey. Each
MarkerArray starts with a DELETEALL marker so that boxes of the previous frame vanish
even when the new frame has fewer. Boxes are LINE_LIST wire frames (12 edges) with a
text label above them; ``lifetime`` 0 (until replaced).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from geometry_msgs.msg import Point
from lidar_quality_core.box_geometry import corners_3d
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

# corners_3d order: bottom 0-3, top 4-7 (same winding)
_EDGES = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4],
                   [0, 4], [1, 5], [2, 6], [3, 7]])


def confidence_color(conf: float, alpha: float = 1.0) -> ColorRGBA:
    """Red (0) -> yellow (0.5) -> green (1); grey for NaN."""
    if not np.isfinite(conf):
        return ColorRGBA(r=0.6, g=0.6, b=0.6, a=float(alpha))
    c = float(np.clip(conf, 0.0, 1.0))
    return ColorRGBA(r=float(min(1.0, 2 * (1 - c))), g=float(min(1.0, 2 * c)), b=0.0,
                     a=float(alpha))


def _delete_all(header) -> Marker:
    return Marker(header=header, action=Marker.DELETEALL)


def box_markers(header, boxes, confidences, texts: Sequence[str] | None = None, *,
                ns: str = "quality", line_width: float = 0.08) -> MarkerArray:
    """Wire-frame boxes (N, 7: x, y, z, l, w, h, yaw) coloured by ``confidences``, with
    optional text labels. Boxes with non-finite values or sizes <= 0 are skipped."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    conf = np.asarray(confidences, dtype=np.float64).reshape(-1)
    arr = MarkerArray()
    arr.markers.append(_delete_all(header))
    ok = np.isfinite(boxes).all(axis=1) & (boxes[:, 3:6] > 0).all(axis=1)
    if not ok.any():
        return arr
    corners = np.zeros((len(boxes), 8, 3))
    corners[ok] = corners_3d(boxes[ok])
    for i in np.flatnonzero(ok):
        color = confidence_color(conf[i])
        m = Marker(header=header, ns=ns, id=int(2 * i), type=Marker.LINE_LIST,
                   action=Marker.ADD)
        m.pose.orientation.w = 1.0
        m.scale.x = float(line_width)
        m.color = color
        m.points = [Point(x=float(p[0]), y=float(p[1]), z=float(p[2]))
                    for p in corners[i][_EDGES.reshape(-1)]]
        arr.markers.append(m)
        if texts is not None:
            t = Marker(header=header, ns=ns + "_text", id=int(2 * i + 1),
                       type=Marker.TEXT_VIEW_FACING, action=Marker.ADD, text=str(texts[i]))
            t.pose.position.x, t.pose.position.y = float(boxes[i, 0]), float(boxes[i, 1])
            t.pose.position.z = float(boxes[i, 2] + boxes[i, 5] / 2 + 0.5)
            t.pose.orientation.w = 1.0
            t.scale.z = 0.6
            t.color = color
            arr.markers.append(t)
    return arr


def point_markers(header, positions, confidences, *, ns: str = "quality",
                  scale: float = 0.5) -> MarkerArray:
    """One SPHERE_LIST of ``positions`` (N, 3), each coloured by its confidence."""
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    conf = np.asarray(confidences, dtype=np.float64).reshape(-1)
    arr = MarkerArray()
    arr.markers.append(_delete_all(header))
    ok = np.isfinite(pos).all(axis=1)
    if ok.any():
        m = Marker(header=header, ns=ns, id=0, type=Marker.SPHERE_LIST, action=Marker.ADD)
        m.pose.orientation.w = 1.0
        m.scale.x = m.scale.y = m.scale.z = float(scale)
        m.color = ColorRGBA(r=1.0, g=1.0, b=1.0, a=1.0)
        m.points = [Point(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in pos[ok]]
        m.colors = [confidence_color(c) for c in conf[ok]]
        arr.markers.append(m)
    return arr
