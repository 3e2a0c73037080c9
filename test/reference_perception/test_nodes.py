"""The reference perception nodes over real DDS: parameters, QoS, outputs of a simulated
frame, bad input, clean start / stop of the installed executables."""
import copy

import numpy as np
import pytest
from sim_clouds import frame_cloud
from lidar_quality_core.boxes import detections_to_arrays
from lidar_quality_core.pointcloud import read_fields, xyz_intensity
from lidar_quality_msgs.msg import BoxVarianceArray
from lidar_sim.classes import CLASS_NAMES
from node_shell_checks import (assert_declared_with_descriptions, assert_launch_file,
                               assert_sensor_qos, assert_yaml_matches_declared,
                               run_executable_and_signal, wait_until)
from sensor_msgs.msg import PointCloud2, PointField
from vision_msgs.msg import Detection3DArray

from reference_perception.detector_node import DetectorNode
from reference_perception.messages import probability_field
from reference_perception.multihead_node import MultiHeadNode
from reference_perception.segmenter_node import SegmenterNode

PKG = "reference_perception"


def _bad_cloud(good):
    """A cloud without y / z, stamped one second before ``good``."""
    bad = PointCloud2(header=copy.deepcopy(good.header), height=1, width=3, point_step=4, row_step=12,
                      data=bytes(12))
    bad.header.stamp.sec = good.header.stamp.sec - 1
    bad.fields = [PointField(name="x", offset=0, datatype=PointField.FLOAT32, count=1)]
    return bad


def test_detector_node(ros, sim_cloud):
    node = ros.start(DetectorNode)
    assert_declared_with_descriptions(node, {"model_dir", "publish_proposals", "sync_queue_size",
                                             "processing_queue_size", "diagnostics_period"})
    assert_yaml_matches_declared(node, PKG)
    assert_sensor_qos(node, "input/points")
    pub = ros.sensor_publisher(PointCloud2, "input/points")
    dets = ros.collector(Detection3DArray, "output/detections")
    props = ros.collector(Detection3DArray, "output/proposals")
    assert ros.wait_for_match(pub)
    pub.publish(_bad_cloud(sim_cloud))
    pub.publish(sim_cloud)
    assert dets.wait_for(1, timeout=30.0) and props.wait_for(1, timeout=10.0)
    d, p = dets.messages[0], props.messages[0]
    assert d.header == sim_cloud.header == p.header
    da, pa = detections_to_arrays(d), detections_to_arrays(p)
    assert 0 < len(da) < len(pa)
    assert set(da.ids) <= set(pa.ids)                  # survivors are proposals
    rows = [int(i) for i in da.ids]
    np.testing.assert_allclose(da.boxes, pa.boxes[rows], atol=1e-9)
    assert da.labels == [pa.labels[r] for r in rows]
    for det in d.detections:
        scores = [r.hypothesis.score for r in det.results]
        assert scores == sorted(scores, reverse=True) and sum(scores) <= 1 + 1e-6
    assert wait_until(lambda: node.diag.dropped == 1)


def test_segmenter_node(ros, sim_frame):
    node = ros.start(SegmenterNode, parameters={"quantize_probabilities": True})
    assert_declared_with_descriptions(node, {"model_path", "quantize_probabilities", "class_names"})
    assert_sensor_qos(node, "input/points")
    pub = ros.sensor_publisher(PointCloud2, "input/points")
    out = ros.collector(PointCloud2, "output/points")
    assert ros.wait_for_match(pub)
    cloud = frame_cloud(sim_frame, sec=8)
    # a non-finite point keeps its place and gets the uniform distribution
    xyz = sim_frame.xyz.copy()
    xyz[5] = np.nan
    sim_frame_nan = type(sim_frame)(**{**sim_frame.__dict__, "xyz": xyz})
    pub.publish(frame_cloud(sim_frame_nan, sec=7))
    pub.publish(cloud)
    assert out.wait_for(2, timeout=30.0)
    for msg, ref in zip(out.messages, (xyz, sim_frame.xyz)):
        got, _ = xyz_intensity(msg)
        np.testing.assert_array_equal(np.isnan(got), np.isnan(ref))
        p = read_fields(msg, [probability_field(n) for n in CLASS_NAMES], dtype=np.float64) / 255
        assert p.shape == (len(ref), len(CLASS_NAMES))
        np.testing.assert_allclose(p.sum(axis=1), 1.0, atol=len(CLASS_NAMES) * 0.5 / 255)
    assert [m.header.stamp.sec for m in out.messages] == [7, 8]
    p0 = read_fields(out.messages[0], [probability_field(n) for n in CLASS_NAMES]) / 255
    assert np.ptp(p0[5]) < 2 / 255
    # a learned segmenter: most points of a simulated frame get their class
    pred = read_fields(out.messages[1], [probability_field(n) for n in CLASS_NAMES]).argmax(1)
    assert (pred == sim_frame.semantic).mean() > 0.6


def test_multihead_node(ros, sim_cloud):
    node = ros.start(MultiHeadNode, parameters={"num_heads": 2})
    assert_declared_with_descriptions(node, {"model_dir", "num_heads"})
    assert_yaml_matches_declared(node, PKG)
    pub = ros.sensor_publisher(PointCloud2, "input/points")
    heads = [ros.collector(Detection3DArray, f"output/head_{k}") for k in range(2)]
    var = [ros.collector(BoxVarianceArray, f"output/head_{k}/variance") for k in range(2)]
    assert ros.wait_for_match(pub)
    pub.publish(sim_cloud)
    for c in heads + var:
        assert c.wait_for(1, timeout=30.0)
    for h, v in zip(heads, var):
        d, vv = h.messages[0], v.messages[0]
        assert d.header == vv.header == sim_cloud.header
        assert [x.id for x in d.detections] == [x.detection_id for x in vv.variances]
        assert len(d.detections) > 0
        for det, bv in zip(d.detections, vv.variances):
            cov = np.asarray(det.results[0].pose.covariance).reshape(6, 6)
            np.testing.assert_allclose(np.diag(cov)[[0, 1, 2, 5]], [bv.x, bv.y, bv.z, bv.yaw])
            assert min(bv.x, bv.y, bv.z, bv.length, bv.width, bv.height, bv.yaw) > 0


@pytest.mark.parametrize("name", ["detector_node", "segmenter_node", "multihead_node"])
def test_executables_start_and_stop(ros, name):
    run_executable_and_signal(ros, PKG, name, ["input/points"], "SIGTERM", timeout=40.0)


@pytest.mark.parametrize("name", ["detector_node", "segmenter_node", "multihead_node"])
def test_launch_files(name):
    assert_launch_file(PKG, name)
