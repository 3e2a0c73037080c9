"""Per-object ground truth of simulate_frame: the occlusion estimate (unoccluded_beams)."""
from __future__ import annotations

import numpy as np
import pytest

from lidar_sim import classes as C
from lidar_sim import raycast
from lidar_sim.primitives import Primitives
from lidar_sim.sensor import beam_directions, hdl64
from lidar_sim.sequence import FramePrimitives, generate_sequence
from lidar_sim.simulate import simulate_frame, unoccluded_beams

GROUND_Z = -1.73


def _prims(boxes, instance, refl=0.5, ground_z=GROUND_Z) -> Primitives:
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    return Primitives(boxes=boxes, box_class=np.full(len(boxes), C.CAR, np.int32),
                      box_instance=np.asarray(instance, np.int32),
                      box_reflectivity=np.full(len(boxes), refl), ground_z=ground_z,
                      default_ground_class=C.ROAD)


def _all_beams_hitting(prims: Primitives, cfg) -> int:
    """Reference: cast every beam of the scan against the object alone."""
    h = raycast.cast(prims, np.zeros(3), beam_directions(cfg).reshape(-1, 3), cfg.max_range)
    return int((h.hit & (h.t >= cfg.min_range)).sum())


# Awkward placements: a long side seen from close by (its nearest point is mid-edge, not
# a corner: corner-based elevation windows missed the beams below the corners), a box
# over the sensor's footprint, one across the +-180 deg seam, a near car beside and behind.
CASES = {
    "bus_alongside_4m": [0.0, 4.0, GROUND_Z + 1.6, 12.0, 2.5, 3.2, 0.0],
    "low_long_box_4m": [0.0, 4.0, GROUND_Z + 0.5, 12.0, 2.0, 1.0, 0.0],
    "canopy_over_sensor": [0.0, 0.0, 0.6, 10.0, 10.0, 0.8, 0.3],
    "car_across_seam": [-8.0, 0.0, GROUND_Z + 0.75, 4.5, 1.8, 1.5, 0.1],
    "car_2m_beside": [0.0, -2.0, GROUND_Z + 0.75, 4.5, 1.8, 1.5, 0.0],
    "car_10m": [10.0, 3.0, GROUND_Z + 0.75, 4.5, 1.8, 1.5, 0.4],
    "beyond_max_range": [130.0, 0.0, GROUND_Z + 0.75, 4.5, 1.8, 1.5, 0.0],
}


@pytest.mark.parametrize("name", list(CASES))
def test_unoccluded_beams_equals_casting_every_beam(name):
    cfg = hdl64()
    box = np.array([CASES[name]])
    alone = _prims(box, [1], ground_z=None)
    want = _all_beams_hitting(alone, cfg)
    # the ground is in the scene but must not count: "were the object alone"
    got = unoccluded_beams(_prims(box, [1]), cfg, box, np.array([1]))
    assert got.tolist() == [want]
    if name != "beyond_max_range":
        assert want > 0


def _frame(boxes, gt_boxes, instance, gt_instance) -> FramePrimitives:
    n = len(gt_boxes)
    return FramePrimitives(
        index=0, stamp_ns=0, ego_pose=np.eye(4), sensor_height=-GROUND_Z,
        primitives=_prims(boxes, instance), gt_boxes=np.asarray(gt_boxes, np.float64),
        gt_class=np.full(n, C.CAR, np.int32), gt_instance=np.asarray(gt_instance, np.int32),
        gt_velocity=np.zeros((n, 2)), gt_kitti_type=("Car",) * n)


def test_occlusion_of_visible_hidden_and_half_hidden_objects():
    z = GROUND_Z + 0.75
    gt = np.array([[10.0, 0.0, GROUND_Z + 1.25, 5.0, 2.0, 2.5, 0.0],  # van, in full view
                   [20.0, 0.0, z, 4.5, 1.8, 1.5, 0.0],    # right behind the van: hidden
                   [20.0, 2.5, z, 4.5, 1.8, 1.5, 0.0],    # half of it behind the van
                   [-12.0, 6.0, z, 4.5, 1.8, 1.5, 0.0]])  # alone behind the sensor
    f = simulate_frame(_frame(gt, gt, [1, 2, 3, 4], [1, 2, 3, 4]), hdl64(), 0)
    occ = f.gt_occlusion
    print("occlusion", occ.round(3), "points", f.gt_num_points)
    assert ((occ >= 0) & (occ <= 1)).all()
    # visible objects lose only dropouts: p = 0.005 + 0.15 (1 - 0.5)^2 + range term ~ 4.5 %
    # (the old estimate counted every beam of the angular window: ~0.4 here)
    assert occ[0] < 0.1 and occ[3] < 0.1
    assert f.gt_num_points[1] == 0 and occ[1] == 1.0  # the van's top is above the sensor
    assert 0.3 < occ[2] < 0.8  # the van covers about half its azimuth window


def test_generated_frames_occlusion_is_plausible():
    cfg = hdl64()
    seq = generate_sequence(7000, 3)
    rng = np.random.default_rng(7000)
    for i in (0, 2):
        fp = seq.frame(i, max_range=cfg.max_range)
        f = simulate_frame(fp, cfg, rng)
        expected = unoccluded_beams(fp.primitives, cfg, fp.gt_boxes, fp.gt_instance)
        occ = f.gt_occlusion
        assert ((occ >= 0) & (occ <= 1)).all()
        # nothing is seen by more beams than reach it alone (before the clip to [0, 1])
        assert (f.gt_num_points <= expected).all()
        assert (occ[expected == 0] == 1).all()
        # the nearest object of a street frame is in plain view: only dropouts missing
        near = np.argmin(np.hypot(fp.gt_boxes[:, 0], fp.gt_boxes[:, 1]))
        assert occ[near] < 0.2
        # the estimate spans the range: some objects fully visible, some hidden
        assert (occ < 0.2).sum() >= 5 and (occ > 0.8).sum() >= 5
