"""Analytic tests of lidar_sim.raycast.cast (exact intersections, occlusion, culling)."""
import numpy as np
import pytest

from lidar_sim.primitives import Primitives
from lidar_sim.raycast import (KIND_BOX, KIND_CYLINDER, KIND_ELLIPSOID, KIND_GROUND,
                               KIND_NONE, cast)

FIELDS = ("t", "kind", "index", "normal", "semantic", "instance", "reflectivity")


def prims(boxes=(), cyl=(), ell=(), porosity=None, ground_z=None, **kw):
    """Primitives with distinct ground truth per primitive: class 100+i / 200+i / 300+i,
    instance 1+i / 11+i / 21+i, reflectivity 0.1 + i / 100 etc."""
    b = np.asarray(boxes, np.float64).reshape(-1, 7)
    c = np.asarray(cyl, np.float64).reshape(-1, 5)
    e = np.asarray(ell, np.float64).reshape(-1, 6)
    nb, nc, ne = len(b), len(c), len(e)
    return Primitives(
        boxes=b, box_class=np.arange(100, 100 + nb, dtype=np.int32),
        box_instance=np.arange(1, 1 + nb, dtype=np.int32),
        box_reflectivity=0.1 + np.arange(nb) / 100,
        cylinders=c, cylinder_class=np.arange(200, 200 + nc, dtype=np.int32),
        cylinder_instance=np.arange(11, 11 + nc, dtype=np.int32),
        cylinder_reflectivity=0.4 + np.arange(nc) / 100,
        ellipsoids=e, ellipsoid_class=np.arange(300, 300 + ne, dtype=np.int32),
        ellipsoid_instance=np.arange(21, 21 + ne, dtype=np.int32),
        ellipsoid_reflectivity=0.7 + np.arange(ne) / 100,
        ellipsoid_porosity=np.zeros(ne) if porosity is None else np.asarray(porosity, float),
        ground_z=ground_z, **kw)


def sph(az, el):
    az, el = np.broadcast_arrays(np.asarray(az, float), np.asarray(el, float))
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)


def grid(n_az=720, n_el=40, el_lo=-0.6, el_hi=0.6, az_lo=-np.pi, az_hi=np.pi):
    az = np.linspace(az_lo, az_hi, n_az, endpoint=False)
    el = np.linspace(el_lo, el_hi, n_el)
    A, E = np.meshgrid(az, el)
    return sph(A.ravel(), E.ravel())


def assert_same(a, b):
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)


def box_signed_distance(p, box):
    """Signed distance of points to an oriented box (negative inside), for reference."""
    x, y, z, l, w, h, yaw = box
    c, s = np.cos(yaw), np.sin(yaw)
    q = p - [x, y, z]
    loc = np.stack([c * q[:, 0] + s * q[:, 1], c * q[:, 1] - s * q[:, 0], q[:, 2]], 1)
    e = np.abs(loc) - [l / 2, w / 2, h / 2]
    out = np.linalg.norm(np.maximum(e, 0), axis=1)
    return out + np.minimum(e.max(axis=1), 0)


# ------------------------------------------------------------------------------ walls

def test_wall_ranges_normals_and_ground_truth():
    d = 12.0
    P = prims(boxes=[[d + 0.5, 0, 0, 1.0, 200, 200, 0.0]])
    az = np.deg2rad(np.linspace(-70, 70, 141))
    el = np.deg2rad(np.array([-20, -5, 0, 3, 15]))[:, None]
    dirs = sph(az[None, :], el).reshape(-1, 3)
    h = cast(P, (0, 0, 0), dirs, 200.0)
    A, E = np.broadcast_arrays(az[None, :], el)
    np.testing.assert_allclose(h.t, d / (np.cos(A) * np.cos(E)).ravel(), rtol=1e-12)
    assert np.all(h.kind == KIND_BOX) and np.all(h.index == 0)
    np.testing.assert_allclose(h.normal, np.tile([-1.0, 0, 0], (len(dirs), 1)), atol=1e-12)
    assert np.all(h.semantic == 100) and np.all(h.instance == 1)
    np.testing.assert_allclose(h.reflectivity, 0.1)
    # rays pointing away from the wall see nothing
    back = cast(P, (0, 0, 0), -dirs, 200.0)
    assert np.all(back.kind == KIND_NONE) and np.all(np.isinf(back.t))
    assert np.all(back.index == -1) and np.all(back.semantic == -1)


def test_max_range_cuts_hits():
    P = prims(boxes=[[50.5, 0, 0, 1.0, 10, 10, 0.0]], ground_z=-1.73)
    dirs = sph([0.0, 0.0], [0.0, np.deg2rad(-1.0)])  # 2nd beam: ground at 99 m
    h = cast(P, (0, 0, 0), dirs, 40.0)
    assert np.all(h.kind == KIND_NONE)
    h = cast(P, (0, 0, 0), dirs, 50.0)  # inclusive bound
    assert h.kind[0] == KIND_BOX and h.t[0] == pytest.approx(50.0)


def test_direction_need_not_be_unit():
    P = prims(boxes=[[10.5, 0, 0, 1.0, 30, 10, 0.0]])
    h = cast(P, (0, 0, 0), [[3.0, 0, 0], [0.5, 0.5, 0]], 100)
    np.testing.assert_allclose(h.t, [10.0, 10 * np.sqrt(2)])


# ------------------------------------------------------------------------------ ground

def test_ground_plane_ranges_and_regions():
    h0 = 1.73
    P = prims(ground_z=-h0, ground_regions=np.array([[0, 50, -5, 5], [-100, 100, -10, 10]]),
              ground_class=np.array([40, 48], np.int32), ground_reflectivity=np.array([0.1, 0.3]),
              default_ground_class=72, default_ground_reflectivity=0.25)
    e = np.deg2rad(np.array([-30, -10, -3, -1, -1, -0.5, 0.0, 0.5, 10]))
    az = np.array([0.0, 0.1, 0.0, 0.0, np.pi / 2, 0.0, 0.0, 0.0, 0.0])
    h = cast(P, (0, 0, 0), sph(az, e), 120.0)
    down = e < 0
    expect = np.full(len(e), np.inf)
    expect[down] = h0 / np.sin(-e[down])
    expect[expect > 120] = np.inf  # -0.5 deg reaches the ground at 198 m
    np.testing.assert_allclose(h.t, expect, rtol=1e-12)
    hit = np.isfinite(expect)
    assert np.all(h.kind[hit] == KIND_GROUND) and np.all(h.kind[~hit] == KIND_NONE)
    np.testing.assert_allclose(h.normal[hit], np.tile([0, 0, 1.0], (hit.sum(), 1)))
    # ground points at x = 3.0, 9.8 (beam 1 slightly off-axis), 33 m: region 40; x = 99 m:
    # region 48; y = 99 m: outside both regions -> the default class
    x = np.where(hit, h.t, 0) * np.cos(e) * np.cos(az)
    y = np.where(hit, h.t, 0) * np.cos(e) * np.sin(az)
    for i in np.flatnonzero(hit):
        if 0 <= x[i] <= 50 and abs(y[i]) <= 5:
            assert (h.semantic[i], h.reflectivity[i]) == (40, 0.1)
        elif abs(x[i]) <= 100 and abs(y[i]) <= 10:
            assert (h.semantic[i], h.reflectivity[i]) == (48, 0.3)
        else:
            assert (h.semantic[i], h.reflectivity[i]) == (72, 0.25)
    assert set(h.semantic[hit]) == {40, 48, 72}
    assert np.all(h.instance == 0)


def test_first_matching_ground_region_wins():
    P = prims(ground_z=-2.0, ground_regions=np.array([[0, 10, -1, 1], [0, 10, -1, 1]]),
              ground_class=np.array([7, 8], np.int32), ground_reflectivity=np.array([0.5, 0.6]))
    h = cast(P, (0, 0, 0), [[1.0, 0, -1.0]], 50)
    assert h.semantic[0] == 7 and h.reflectivity[0] == 0.5


def test_ground_seen_from_sensor_origin_offset():
    P = prims(ground_z=-1.0)
    h = cast(P, (5.0, 3.0, 2.0), sph(0.3, -np.pi / 6)[None], 50)
    assert h.t[0] == pytest.approx(3.0 / np.sin(np.pi / 6))


# ------------------------------------------------------------------------------ boxes

def test_rotated_box_known_face_and_distance():
    yaw = np.deg2rad(30)
    P = prims(boxes=[[10.0, 0, 0, 4.0, 2.0, 1.5, yaw]])
    h = cast(P, (0, 0, 0), [[1.0, 0, 0]], 100)
    # box frame: origin at (-10 cos30, 10 sin30), dir (cos30, -sin30): y-slab entry t = 8
    # beats x-slab entry t = (10 cos30 - 2) / cos30, so the +y face is hit
    assert h.t[0] == pytest.approx(8.0, abs=1e-12)
    np.testing.assert_allclose(h.normal[0], [-np.sin(yaw), np.cos(yaw), 0], atol=1e-12)


def test_rotated_box_hits_on_surface_against_ray_marching():
    box = [9.0, 4.0, 0.3, 4.0, 2.0, 1.5, np.deg2rad(30)]
    P = prims(boxes=[box])
    dirs = grid(n_az=160, n_el=40, el_lo=-0.25, el_hi=0.25, az_lo=0.1, az_hi=0.75)
    h = cast(P, (0, 0, 0), dirs, 100)
    hit = h.kind == KIND_BOX
    assert 300 < hit.sum() < len(dirs) - 300  # the grid straddles the silhouette
    pts = h.t[hit, None] * dirs[hit]
    np.testing.assert_allclose(box_signed_distance(pts, box), 0.0, atol=1e-9)
    # the reported face faces the sensor and is the face the point lies on
    assert np.all(np.einsum("ij,ij->i", h.normal[hit], dirs[hit]) < 0)
    nudge = box_signed_distance(pts + 1e-4 * h.normal[hit], box)
    np.testing.assert_allclose(nudge, 1e-4, rtol=1e-3)
    # ray marching reference: signed distance along every ray
    ts = np.linspace(5.0, 15.0, 2001)  # the box lies between 7 and 13 m
    sd = np.stack([box_signed_distance(t * dirs, box) for t in ts], 1)
    clearly_in = (sd < -0.02).any(axis=1)
    clearly_out = (sd > 0.02).all(axis=1)
    assert np.all(hit[clearly_in]) and not np.any(hit[clearly_out])
    assert clearly_in.sum() > 300 and clearly_out.sum() > 300
    # no earlier entry than the reported range
    first_in = np.array([ts[np.argmax(r < 0)] if (r < 0).any() else np.inf for r in sd])
    assert np.all(first_in[hit] >= h.t[hit] - 1e-9)
    assert np.all(first_in[clearly_in] <= h.t[clearly_in] + 0.006)


def test_sensor_inside_box_hits_inner_walls():
    P = prims(boxes=[[0.0, 0, 0, 4.0, 6.0, 2.0, 0.0]])
    dirs = np.array([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, 0, -1], [1, 1, 0]]) / \
        np.array([1, 1, 1, 1, np.sqrt(2)])[:, None]
    h = cast(P, (0, 0, 0), dirs, 100)
    np.testing.assert_allclose(h.t, [2, 2, 3, 1, 2 * np.sqrt(2)])
    np.testing.assert_allclose(h.normal[:4], [[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 0, 1]],
                               atol=1e-12)


def test_occlusion_small_box_in_front_of_big_box():
    P = prims(boxes=[[20.0, 0, 0, 1.0, 20, 20, 0.0], [10.0, 0, 0, 1.0, 1.0, 1.0, 0.0]])
    dirs = grid(n_az=300, n_el=300, el_lo=-0.15, el_hi=0.15, az_lo=-0.15, az_hi=0.15)
    h = cast(P, (0, 0, 0), dirs, 100)
    # the small box's silhouette is its front face x = 9.5
    y, z = 9.5 * dirs[:, 1] / dirs[:, 0], 9.5 * dirs[:, 2] / dirs[:, 0]
    m = np.maximum(np.abs(y), np.abs(z))
    small, big = m < 0.5 - 1e-6, m > 0.5 + 1e-6
    assert small.sum() > 1000 and big.sum() > 1000
    assert np.all(h.index[small] == 1) and np.all(h.semantic[small] == 101)
    np.testing.assert_allclose(h.t[small], 9.5 / dirs[small, 0], rtol=1e-12)
    assert np.all(h.index[big] == 0)
    np.testing.assert_allclose(h.t[big], 19.5 / dirs[big, 0], rtol=1e-12)


# ------------------------------------------------------------------------------ cylinders

def test_cylinder_side_caps_and_inside():
    P = prims(cyl=[[10.0, 0, -1.0, 2.0, 1.0]])
    a = np.deg2rad(np.linspace(-8, 8, 33))
    h = cast(P, (0, 0, 0), sph(a, 0 * a), 100)
    s = 10 * np.sin(a)
    expect = np.where(np.abs(s) <= 1, 10 * np.cos(a) - np.sqrt(np.maximum(1 - s * s, 0)), np.inf)
    np.testing.assert_allclose(h.t, expect, rtol=1e-12)
    hit = np.isfinite(expect)
    assert hit.sum() > 5 and (~hit).sum() > 5
    p = h.t[hit, None] * sph(a[hit], 0 * a[hit])
    n_exp = (p - [10, 0, 0]) * [1, 1, 0]
    np.testing.assert_allclose(h.normal[hit], n_exp, atol=1e-9)  # radius 1: unit already
    assert np.all(h.semantic[hit] == 200) and np.all(h.instance[hit] == 11)

    cases = [  # origin, dir, expected t, expected normal
        ((10, 0, 5.0), (0, 0, -1.0), 3.0, (0, 0, 1.0)),  # top cap from above
        ((10, 0.5, 5.0), (0, 0, -1.0), 3.0, (0, 0, 1.0)),
        ((10, 0, -3.0), (0, 0, 1.0), 2.0, (0, 0, -1.0)),  # bottom cap from below
        ((10, 0, 0.0), (1, 0, 0.0), 1.0, (-1, 0, 0.0)),  # inside: the wall, facing in
        ((10, 0, 0.0), (0, 0, 1.0), 2.0, (0, 0, -1.0)),  # inside: the top cap from below
        ((0, 0, 2.5), (1, 0, 0.0), np.inf, (0, 0, 0.0)),  # passes above
        ((10, 3, 5.0), (0, 0, -1.0), np.inf, (0, 0, 0.0)),  # beside it
    ]
    for o, dvec, t, n in cases:
        h = cast(P, o, [dvec], 100)
        assert h.t[0] == pytest.approx(t), (o, dvec)
        np.testing.assert_allclose(h.normal[0], n, atol=1e-12)


def test_cylinder_slanted_ray_enters_through_top_cap():
    P = prims(cyl=[[10.0, 0, -1.0, 0.0, 2.0]])
    o = np.array([0.0, 0, 1.0])
    # o + s * dvec reaches the cap plane z = 0 at s = 2/3 (x = 6.7, outside the disk) and
    # the side x = 8 at s = 0.8 with z = -0.2 in [-1, 0]: a side hit
    dvec = np.array([10.0, 0, -1.5])
    h = cast(P, o, [dvec], 100)
    assert h.t[0] == pytest.approx(0.8 * np.linalg.norm(dvec))
    np.testing.assert_allclose(h.normal[0], [-1, 0, 0], atol=1e-12)
    # z = 0 at s = 0.9 (x = 9, inside the disk); at the side (s = 0.8) z = 0.11 > 0: cap
    dvec = np.array([10.0, 0, -1.0 / 0.9])
    h = cast(P, o, [dvec], 100)
    assert h.t[0] == pytest.approx(0.9 * np.linalg.norm(dvec))
    np.testing.assert_allclose(h.normal[0], [0, 0, 1], atol=1e-12)


# ------------------------------------------------------------------------------ ellipsoids

def test_ellipsoid_analytic():
    c, r = np.array([10.0, 0, 0.5]), np.array([2.0, 1.0, 0.5])
    P = prims(ell=[[*c, *r]])
    h = cast(P, (0, 0, 0.5), [[1, 0, 0], [0, 1, 0]], 100)
    assert h.t[0] == pytest.approx(8.0) and np.isinf(h.t[1])
    np.testing.assert_allclose(h.normal[0], [-1, 0, 0], atol=1e-12)
    P2 = prims(ell=[[0, 10.0, 0, 2, 3, 1]])
    h = cast(P2, (0, 0, 0), [[0, 1, 0]], 100)
    assert h.t[0] == pytest.approx(7.0)
    # random rays towards it: on the surface, normal along the gradient, facing the sensor
    rng = np.random.default_rng(1)
    tgt = c + rng.uniform(-1, 1, (500, 3)) * r
    dirs = tgt / np.linalg.norm(tgt, axis=1, keepdims=True)
    h = cast(P, (0, 0, 0), dirs, 100)
    hit = h.kind == KIND_ELLIPSOID
    inside = (((tgt - c) / r) ** 2).sum(1) < 1
    assert np.all(hit[inside]) and hit.sum() > 200
    p = h.t[hit, None] * dirs[hit]
    np.testing.assert_allclose((((p - c) / r) ** 2).sum(1), 1.0, atol=1e-9)
    g = (p - c) / r ** 2
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    np.testing.assert_allclose(h.normal[hit], g, atol=1e-9)
    assert np.all(np.einsum("ij,ij->i", h.normal[hit], dirs[hit]) < 0)


def _porous_scene(porosity, n_crowns=1):
    ell = [[10.0 + 5 * i, 0, 0, 1.0, 1.0, 1.0] for i in range(n_crowns)]
    return prims(boxes=[[30.5, 0, 0, 1.0, 40, 40, 0.0]], ell=ell,
                 porosity=[porosity] * n_crowns)


def _through_crown_rays(n=4000, seed=0):
    rng = np.random.default_rng(seed)
    tgt = np.c_[np.full(n, 10.0), rng.uniform(-0.6, 0.6, (n, 2))]
    return tgt / np.linalg.norm(tgt, axis=1, keepdims=True)


@pytest.mark.parametrize("porosity, lo, hi", [(0.0, 0.0, 0.0), (0.5, 0.45, 0.55),
                                              (0.3, 0.25, 0.35), (0.999, 0.99, 1.0)])
def test_porous_ellipsoid_pass_through_share(porosity, lo, hi):
    dirs = _through_crown_rays()
    h = cast(_porous_scene(porosity), (0, 0, 0), dirs, 100, np.random.default_rng(3))
    assert np.all(h.kind > 0)
    share = np.mean(h.kind == KIND_BOX)  # went through and hit the wall behind
    assert lo <= share <= hi
    assert np.all(h.kind[h.kind != KIND_BOX] == KIND_ELLIPSOID)


def test_porosity_is_per_ray_and_ellipsoid():
    dirs = _through_crown_rays()
    h = cast(_porous_scene(0.5, n_crowns=2), (0, 0, 0), dirs, 100, np.random.default_rng(5))
    share = np.bincount(h.index[h.kind == KIND_ELLIPSOID], minlength=2) / len(dirs)
    assert abs(share[0] - 0.5) < 0.05 and abs(share[1] - 0.25) < 0.05
    assert abs(np.mean(h.kind == KIND_BOX) - 0.25) < 0.05


def test_porosity_draws_follow_the_rng():
    dirs = _through_crown_rays()
    P = _porous_scene(0.5)
    a = cast(P, (0, 0, 0), dirs, 100, np.random.default_rng(7))
    b = cast(P, (0, 0, 0), dirs, 100, np.random.default_rng(7))
    c = cast(P, (0, 0, 0), dirs, 100, np.random.default_rng(8))
    assert_same(a, b)
    assert np.mean(a.kind != c.kind) > 0.3


# ------------------------------------------------------------------------------ culling

def test_object_straddling_the_seam_behind_the_sensor():
    P = prims(boxes=[[-10.5, 0, 0, 1.0, 4.0, 2.0, 0.0]], cyl=[[-8.0, 0.3, -1, 1, 0.5]])
    dirs = grid(n_az=3600, n_el=3, el_lo=-0.05, el_hi=0.05)
    h = cast(P, (0, 0, 0), dirs, 100)
    az = np.arctan2(dirs[:, 1], dirs[:, 0])
    hit = h.kind > 0
    assert np.any(hit & (az > 3.0)) and np.any(hit & (az < -3.0))
    # the wall face x = -10 spans |y| <= 2, i.e. |az| >= pi - atan(0.2)
    y = -10.0 * np.tan(az)
    inside = (np.abs(az) > np.pi / 2) & (np.abs(y) < 2 - 1e-6)
    outside = (np.abs(az) < np.pi / 2) | (np.abs(y) > 2 + 1e-6)
    assert np.all(hit[inside]) and not np.any(hit[outside])
    assert_same(h, cast(P, (0, 0, 0), dirs, 100, cull=False))


def test_primitives_containing_or_near_the_origin():
    P = prims(boxes=[[0.0, 0, 0, 30, 30, 30, 0.3], [0.4, 0.1, 0, 0.5, 0.5, 0.5, 0]],
              cyl=[[0.3, 0.0, -1, 1, 0.25], [0, 0, -5, -3, 1.0]],
              ell=[[0.0, 0, 0, 3, 2, 1], [0.5, 0.5, 1.0, 0.2, 0.2, 0.2]], porosity=[0.6, 0.0],
              ground_z=-1.73)
    dirs = grid(n_az=360, n_el=90, el_lo=-1.5, el_hi=1.5)
    h = cast(P, (0, 0, 0), dirs, 100, 11)
    assert np.all(h.kind > 0)  # enclosed: every ray hits something
    assert {KIND_BOX, KIND_CYLINDER, KIND_ELLIPSOID, KIND_GROUND} <= set(h.kind.tolist())
    assert_same(h, cast(P, (0, 0, 0), dirs, 100, 11, cull=False))


def random_scene(rng, n_box=40, n_cyl=15, n_ell=15):
    def pos(n, spread):
        r = rng.uniform(0, spread, n) ** 1.0
        a = rng.uniform(-np.pi, np.pi, n)
        return r * np.cos(a), r * np.sin(a)

    bx, by = pos(n_box, 40)
    boxes = np.c_[bx, by, rng.uniform(-2, 3, n_box), rng.uniform(0.2, 15, (n_box, 2)),
                  rng.uniform(0.2, 8, n_box), rng.uniform(-np.pi, np.pi, n_box)]
    cx, cy = pos(n_cyl, 30)
    z0 = rng.uniform(-3, 1, n_cyl)
    cyl = np.c_[cx, cy, z0, z0 + rng.uniform(0.1, 6, n_cyl), rng.uniform(0.05, 2, n_cyl)]
    ex, ey = pos(n_ell, 30)
    ell = np.c_[ex, ey, rng.uniform(-2, 4, n_ell), rng.uniform(0.2, 4, (n_ell, 3))]
    return prims(boxes=boxes, cyl=cyl, ell=ell, porosity=rng.uniform(0, 0.9, n_ell),
                 ground_z=rng.choice([-1.73, -0.5, np.inf]))


@pytest.mark.parametrize("seed", range(8))
def test_culled_equals_brute_force_on_random_scenes(seed):
    rng = np.random.default_rng(seed)
    P = random_scene(rng)
    # a subsampled spinning-lidar grid plus random directions over the whole sphere
    e = np.deg2rad(np.r_[np.linspace(2, -8.33, 32), np.linspace(-8.83, -24.8, 32)])
    a = np.pi - 2 * np.pi * (np.arange(2048) + 0.5) / 2048
    g = sph(a[None, ::7], e[:, None]).reshape(-1, 3)
    u = rng.normal(size=(3000, 3))
    dirs = np.r_[g, u / np.linalg.norm(u, axis=1, keepdims=True)]
    o = rng.uniform(-1, 1, 3) * [2, 2, 0.5]
    seed_c = int(rng.integers(1 << 30))
    h = cast(P, o, dirs, 80.0, seed_c)
    ref = cast(P, o, dirs, 80.0, seed_c, cull=False)
    assert_same(h, ref)
    assert np.mean(h.kind > 0) > 0.2
    # chunking must not change anything either
    assert_same(h, cast(P, o, dirs, 80.0, seed_c, chunk_pairs=997))


def test_per_ray_origins():
    rng = np.random.default_rng(4)
    P = random_scene(rng)
    P.ellipsoid_porosity[:] = 0  # the porosity draw depends on the ray's index
    u = rng.normal(size=(600, 3))
    dirs = u / np.linalg.norm(u, axis=1, keepdims=True)
    o1, o2 = np.array([0.0, 0, 0]), np.array([3.0, -2, 0.5])
    origins = np.where((np.arange(600) % 2 == 0)[:, None], o1, o2)
    h = cast(P, origins, dirs, 80.0)
    for o, sl in ((o1, slice(0, None, 2)), (o2, slice(1, None, 2))):
        ref = cast(P, o, dirs[sl], 80.0)
        for f in FIELDS:
            np.testing.assert_array_equal(getattr(h, f)[sl], getattr(ref, f), err_msg=f)
    # identical per-ray origins take the single-origin path
    assert_same(cast(P, np.tile(o2, (600, 1)), dirs, 80.0), cast(P, o2, dirs, 80.0))


def test_degenerate_directions_never_hit():
    P = prims(boxes=[[0.0, 0, 0, 10, 10, 10, 0.0]], ground_z=-1.0)
    h = cast(P, (0, 0, 0), [[0, 0, 0], [np.nan, 1, 0], [1, 0, 0], [0, 0, -2]], 100)
    np.testing.assert_array_equal(h.kind, [KIND_NONE, KIND_NONE, KIND_BOX, KIND_GROUND])
    np.testing.assert_array_equal(h.t, [np.inf, np.inf, 5.0, 1.0])


def test_empty_inputs():
    h = cast(prims(), (0, 0, 0), np.zeros((0, 3)), 100)
    assert h.t.shape == (0,) and h.normal.shape == (0, 3)
    h = cast(prims(ground_z=-1.0), (0, 0, 0), [[1.0, 0, -1]], 100)
    assert h.kind[0] == KIND_GROUND and h.t[0] == pytest.approx(np.sqrt(2))
