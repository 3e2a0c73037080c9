"""LidarMetaDetect feature figures: one frame of ~120k points, 50 detections, 500 proposals.

* ``lmd.features_ms`` (p50 / p99; target p50 <= 5 ms, p99 <= 10 ms): mode "threshold" on
  ``synthetic_frame`` (the frame of the core.* geometry figures): detections are noisy
  copies of the 50 objects, proposals are the 50 detections themselves (a detector
  publishes its survivors among its proposals) plus 450 jittered copies around the
  objects and background boxes.
* ``lmd.features_hdl64_ms`` (p50 / p99): the same on a simulated HDL-64 street frame
  (``lidar_sim``, 118k points): the 50 objects with the most points, up to thousands per
  near car, so many more (point, proposal) pairs.
* ``lmd.features_exact_ms``: mode "exact", the node running NMS itself (IoU 0.5, top 50)
  on the same 500 proposals; the NMS is not timed.
* ``lmd.features_none_ms``: mode "none" (post-NMS boxes only), synthetic frame.

Timed on one thread (BLAS pools limited; numpy ufuncs are single-threaded anyway).
"""
from __future__ import annotations

import numpy as np
from threadpoolctl import threadpool_limits

from lidar_quality_core.nms import rotated_nms
from lidar_quality_core.synthetic import synthetic_frame
from lidar_quality_core.lmd.features import ProposalSets, compute_features

N_DET, N_PROP = 50, 500


def _jitter(rng, b, sxy, sz, srel, syaw):
    o = b.copy()
    n = len(b)
    o[:, :2] += rng.normal(size=(n, 2)) * sxy
    o[:, 2] += rng.normal(size=n) * sz
    o[:, 3:6] *= np.clip(1.0 + rng.normal(size=(n, 3)) * srel, 0.5, 1.5)
    o[:, 6] += rng.normal(size=n) * syaw
    return o


def _synthetic():
    f = synthetic_frame(n_points=120_000, n_objects=N_DET, n_proposals=N_PROP - N_DET, seed=0)
    props = np.concatenate([f.detections, f.proposals])
    pscores = np.concatenate([f.det_scores, f.prop_scores])
    plabels = np.concatenate([f.det_classes, f.prop_classes])
    return f, (props, pscores, plabels)


def _hdl64():
    from lidar_sim.frames import sequence_frames

    fr = next(sequence_frames(7000, 1))
    rng = np.random.default_rng(0)
    top = np.argsort(-fr.gt_num_points, kind="stable")[:N_DET]
    gt = fr.gt_boxes[top]
    dets = _jitter(rng, gt, 0.15, 0.05, 0.05, 0.05)
    src = np.arange(N_PROP - N_DET) % N_DET
    props = np.concatenate([dets, _jitter(rng, gt[src], 0.4, 0.1, 0.1, 0.15)])
    pscores = rng.uniform(0.1, 0.95, N_PROP)
    labels = fr.gt_class[top].astype(np.int64)
    return fr, dets, pscores[:N_DET], labels, (props, pscores)


def figures():
    f, prop = _synthetic()
    with threadpool_limits(limits=1):
        yield ("lmd.features_ms",
               lambda: compute_features(f.points, f.intensity, f.detections, f.det_scores,
                                        f.det_classes, proposals=prop, mode="threshold"),
               "percentiles")

    fr, dets, dsc, dlab, hprop = _hdl64()
    with threadpool_limits(limits=1):
        yield ("lmd.features_hdl64_ms",
               lambda: compute_features(fr.xyz, fr.intensity, dets, dsc, dlab,
                                        proposals=hprop, mode="threshold"),
               "percentiles")

    pb, ps, pl = prop
    nms = rotated_nms(pb, ps, 0.5, max_output=N_DET)
    pre = ProposalSets.from_nms(nms.suppressed_by, nms.keep)
    k = nms.keep
    with threadpool_limits(limits=1):
        yield ("lmd.features_exact_ms",
               lambda: compute_features(f.points, f.intensity, pb[k], ps[k], pl[k],
                                        proposals=prop, mode="exact", preimage=pre))
        yield ("lmd.features_none_ms",
               lambda: compute_features(f.points, f.intensity, f.detections, f.det_scores,
                                        f.det_classes, mode="none"))
