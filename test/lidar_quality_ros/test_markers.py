"""Quality markers: colours, wire frames, skipped invalid boxes."""
import numpy as np
from lidar_quality_ros.markers import box_markers, confidence_color, point_markers
from std_msgs.msg import Header
from visualization_msgs.msg import Marker


def test_confidence_colors():
    assert (confidence_color(0.0).r, confidence_color(0.0).g) == (1.0, 0.0)
    assert (confidence_color(1.0).r, confidence_color(1.0).g) == (0.0, 1.0)
    assert (confidence_color(0.5).r, confidence_color(0.5).g) == (1.0, 1.0)
    assert confidence_color(float("nan")).b > 0


def test_box_markers():
    h = Header(frame_id="lidar")
    boxes = np.array([[1, 2, 0.5, 4, 2, 1.5, 0.3], [0, 0, 0, 0, 2, 1, 0], [5, 5, 0, 1, 1, 1, np.nan]])
    arr = box_markers(h, boxes, [0.9, 0.1, 0.5], texts=["car 0.90", "x", "y"])
    assert arr.markers[0].action == Marker.DELETEALL
    lines = [m for m in arr.markers if m.type == Marker.LINE_LIST]
    texts = [m for m in arr.markers if m.type == Marker.TEXT_VIEW_FACING]
    assert len(lines) == 1 and len(texts) == 1  # zero-size and NaN boxes skipped
    pts = np.array([[p.x, p.y, p.z] for p in lines[0].points])
    assert pts.shape == (24, 3)
    np.testing.assert_allclose(pts.mean(axis=0), [1, 2, 0.5], atol=1e-9)
    np.testing.assert_allclose([pts[:, 2].min(), pts[:, 2].max()], [-0.25, 1.25])
    assert texts[0].text == "car 0.90" and lines[0].header.frame_id == "lidar"


def test_point_markers():
    arr = point_markers(Header(), [[0, 0, 0], [1, 1, np.nan], [2, 0, 0]], [0.2, 0.5, 1.0])
    m = arr.markers[1]
    assert m.type == Marker.SPHERE_LIST and len(m.points) == len(m.colors) == 2
