"""Small simulated scans with noisy per-point probabilities, their PointCloud2 messages
and real LMS meta models fitted on them (tests of lms_ros.pipeline and lms_node)."""
import numpy as np
from lidar_quality_core.pointcloud import create_cloud
from std_msgs.msg import Header

COLS = 256  # 64 x 256 scans: ~15k points


def scans(seed: int = 3, n: int = 2):
    """``n`` simulated HDL-64 frames with 256 columns (lidar_sim: ring 0 = top beam)."""
    from lidar_sim.frames import sequence_frames
    from lidar_sim.sensor import hdl64

    return list(sequence_frames(seed, n, cfg=hdl64(columns=COLS)))


def settings(**kw):
    """The pipeline settings of these scans."""
    from lms_ros.pipeline import LmsSettings

    return LmsSettings(width=COLS, ring_zero_top=True, **kw)


def node_parameters(**kw) -> dict:
    """lms_node parameters matching :func:`settings`."""
    return {"width": COLS, "ring_zero_top": True, **kw}


def noisy_probs(xyz, ring, labels, seed, n_classes=14, noise=1.2, cols=COLS):
    """Softmax of noisy logits around ``labels``; part of the noise is shared by
    4-ring x 8-column patches so that errors form blobs (as a real network's)."""
    rng = np.random.default_rng(seed)
    n = len(xyz)
    az = np.arctan2(xyz[:, 1], xyz[:, 0])
    col = (np.floor(0.5 * (1 - az / np.pi) * cols).astype(np.int64)) % cols
    patch = (np.asarray(ring, np.int64) // 4) * (cols // 8) + col // 8
    n_patch = (int(np.max(ring, initial=0)) // 4 + 1) * (cols // 8)
    logits = rng.normal(0, 0.35, (n, n_classes))
    logits += noise * rng.normal(0, 1, (n_patch, n_classes))[patch]
    logits[np.arange(n), labels] += 3.5
    p = np.exp(logits - logits.max(axis=1, keepdims=True))
    return (p / p.sum(axis=1, keepdims=True)).astype(np.float32)


def frame_probs(frame, seed):
    return noisy_probs(frame.xyz, frame.ring, frame.semantic, seed)


def header(sec: int = 1, frame_id: str = "lidar", nanosec: int = 0):
    h = Header(frame_id=frame_id)
    h.stamp.sec, h.stamp.nanosec = sec, nanosec
    return h


def cloud(xyz, probs=None, *, intensity=None, ring=None, quantize=False, names=None,
          sec=1, extra=None, frame_id="lidar"):
    """PointCloud2: x, y, z [, intensity float32] [, ring uint16] [, one probability field
    per class, float32 or uint8 (``quantize``)] [, ``extra`` columns]."""
    from lms_ros.pipeline import CLASS_NAMES, probability_field

    names = CLASS_NAMES if names is None else names
    xyz = np.asarray(xyz, np.float32)
    cols = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}
    if intensity is not None:
        cols["intensity"] = np.asarray(intensity, np.float32)
    if ring is not None:
        cols["ring"] = np.asarray(ring, np.uint16)
    if probs is not None:
        p = np.rint(np.clip(probs, 0, 1) * 255).astype(np.uint8) if quantize else probs
        for k, name in enumerate(names):
            cols[probability_field(name)] = p[:, k]
    cols.update(extra or {})
    return create_cloud(header(sec, frame_id), cols)


def frame_cloud(frame, probs, **kw):
    return cloud(frame.xyz, probs, intensity=frame.intensity, ring=frame.ring, **kw)


def train_models(out_dir, frames, draws: int = 3):
    """XGBoost meta classifier / regressor (``meta_model`` defaults, one thread) fitted on
    the metrics and IoU_adj targets of ``frames`` (``draws`` noise draws each), saved as
    ``out_dir/lms_{classifier,regressor}.joblib``. Returns their paths."""
    from lidar_quality_core import meta_model
    from lms_ros.pipeline import decode, frame_metrics
    from lidar_quality_core.lms.targets import segment_targets

    s = settings()
    X, y = [], []
    for i, f in enumerate(frames):
        for d in range(draws):
            res = frame_metrics(decode(frame_cloud(f, frame_probs(f, 100 * i + d)), s), s)
            _, adj = segment_targets(res, f.semantic)
            ok = np.isfinite(adj)
            X.append(res.features[ok])
            y.append(adj[ok])
    X, y = np.concatenate(X), np.concatenate(y)
    assert 0 < (y > 0).mean() < 1
    clf = meta_model.fit_estimator("xgboost", "classification", X, (y > 0).astype(int))
    reg = meta_model.fit_estimator("xgboost", "regression", X, y)
    return meta_model.save_pair(out_dir, "lms", clf, reg, s.metric_names(),
                                training_data={"source": "lms_scans test fixture",
                                               "rows": int(len(y))})
