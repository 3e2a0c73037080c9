"""SemanticKITTI files read back with plain numpy, as the SemanticKITTI API does."""
import numpy as np
import pytest
from lidar_sim import semantickitti as sk


def test_label_encoding_bits():
    raw = sk.encode_labels(np.array([10, 40, 30]), np.array([0, 0, 513]))
    assert raw.dtype == np.uint32
    assert raw.tolist() == [10, 40, (513 << 16) | 30]
    sem, inst = sk.decode_labels(raw)
    assert sem.tolist() == [10, 40, 30] and inst.tolist() == [0, 0, 513]
    with pytest.raises(ValueError):
        sk.encode_labels(np.array([70000]), np.array([0]))


def test_scan_labels_poses_roundtrip(tmp_path):
    rng = np.random.default_rng(1)
    xyz = rng.normal(size=(300, 3)).astype(np.float32)
    inten = rng.random(300).astype(np.float32)
    sem = rng.choice([0, 10, 30, 40, 48, 50, 70], 300)
    inst = np.where(np.isin(sem, [10, 30]), rng.integers(1, 40, 300), 0)
    sk.write_scan(tmp_path, 3, 12, xyz, inten, sem, inst)
    seq = tmp_path / "sequences" / "03"
    scan = np.fromfile(seq / "velodyne" / "000012.bin", dtype=np.float32).reshape(-1, 4)
    np.testing.assert_array_equal(scan[:, :3], xyz)
    raw = np.fromfile(seq / "labels" / "000012.label", dtype=np.uint32)
    assert len(raw) == len(scan)
    np.testing.assert_array_equal(raw & 0xFFFF, sem)
    np.testing.assert_array_equal(raw >> 16, inst)

    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 0, 3] = [100.0, 101.0, 102.5]  # driving along x
    poses[:, 1, 3] = 3.0
    sk.write_sequence_meta(tmp_path, 3, poses, np.array([0.0, 0.1, 0.2]))
    rel = sk.lidar_poses_from_files(seq)
    np.testing.assert_allclose(rel[:, 0, 3], [0.0, 1.0, 2.5], atol=1e-9)
    np.testing.assert_allclose(rel[:, :3, :3], np.tile(np.eye(3), (3, 1, 1)), atol=1e-12)
    cam = np.loadtxt(seq / "poses.txt").reshape(-1, 3, 4)
    np.testing.assert_allclose(cam[:, 2, 3], [0.0, 1.0, 2.5], atol=1e-9)  # camera z = forward
    assert np.loadtxt(seq / "times.txt").tolist() == [0.0, 0.1, 0.2]
