import numpy as np

from reference_perception.ground import GroundConfig, estimate_ground


def _plane(rng, n, slope=0.0, z0=-1.7):
    xy = rng.uniform(-40, 40, size=(n, 2))
    return np.c_[xy, z0 + slope * xy[:, 0] + rng.normal(0, 0.02, n)]


def test_flat_ground_with_a_car_and_a_wall():
    rng = np.random.default_rng(0)
    ground = _plane(rng, 60_000)
    # a car body 0.3..1.5 m above ground, 4.5 x 1.8 m, and its roof
    car = np.c_[rng.uniform(8, 12.5, 3000), rng.uniform(-0.9, 0.9, 3000), rng.uniform(-1.4, -0.2, 3000)]
    wall = np.c_[rng.uniform(-30, 30, 5000), np.full(5000, 20.0), rng.uniform(-1.7, 6, 5000)]
    xyz = np.r_[ground, car, wall].astype(np.float32)
    g = estimate_ground(xyz)
    n0, n1 = len(ground), len(ground) + len(car)
    assert g.is_ground[:n0].mean() > 0.99
    assert not g.is_ground[n0:n1].any()          # the whole car stands above the ground
    np.testing.assert_allclose(g.height[n0:n1], xyz[n0:n1, 2] + 1.7, atol=0.12)
    assert g.is_ground[n1:].mean() < 0.06         # only the wall's foot


def test_slope_is_followed():
    rng = np.random.default_rng(1)
    xyz = _plane(rng, 80_000, slope=0.08).astype(np.float32)
    g = estimate_ground(xyz)
    assert g.is_ground.mean() > 0.97
    assert np.nanmax(np.abs(g.height)) < 0.45


def test_degenerate_inputs():
    g = estimate_ground(np.zeros((0, 3), np.float32))
    assert g.height.shape == (0,) and g.is_ground.shape == (0,)
    xyz = np.array([[np.nan, 0, 0], [1, 1, -1.7], [np.inf, 1, 1], [500, 500, 3]], np.float32)
    g = estimate_ground(xyz, GroundConfig(extent=50))
    assert np.isnan(g.height[0]) and not g.is_ground[0] and not g.is_ground[2]
    assert g.is_ground[1]
