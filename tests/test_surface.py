import numpy as np
import pytest

from spheroseg.geometry.coords import Pose, ProlateSpheroidal
from spheroseg.geometry.hermite import HermiteGrid
from spheroseg.surfaces.surface import ImageGrid, Surface, signed_volume

APEX, BASE = np.array([3.0, -4.0, 85.0]), np.array([0.0, 0.0, 5.0])


def constant_prolate(l0, d=40.0, v2_range=(0.0, np.pi / 2)):
    system = ProlateSpheroidal(d)
    grid = HermiteGrid(8, 8, v2_range, poles=system.poles)
    return Surface.from_function(system, Pose.from_apex_base(APEX, BASE), grid, l0)


def test_constant_lambda_volume_is_analytic():
    d, l0 = 40.0, 0.7
    a, b = d * np.cosh(l0), d * np.sinh(l0)
    full = constant_prolate(l0, d, (0.0, np.pi))
    np.testing.assert_allclose(full.volume_ml(), 4 / 3 * np.pi * a * b * b / 1000, rtol=1e-6)
    half = constant_prolate(l0, d)
    np.testing.assert_allclose(half.volume_ml(), 2 / 3 * np.pi * a * b * b / 1000, rtol=1e-6)


def test_wall_area_of_a_half_spheroid_is_analytic():
    """Half a prolate spheroid's area, ``pi b^2 (1 + a / (b e) asin e)``
    with ``e = sqrt(1 - b^2 / a^2)``; the base plane is not wall."""
    d, l0 = 40.0, 0.7
    a, b = d * np.cosh(l0), d * np.sinh(l0)
    e = np.sqrt(1 - (b / a) ** 2)
    half = np.pi * b**2 * (1 + a / (b * e) * np.arcsin(e))
    np.testing.assert_allclose(constant_prolate(l0, d).wall_area_mm2(), half, rtol=1e-6)
    np.testing.assert_allclose(constant_prolate(l0, d, (0.0, np.pi)).wall_area_mm2(), 2 * half, rtol=1e-6)


@pytest.mark.parametrize("system", ["prolate", "spherical", "cylindrical"])
def test_initial_surface_is_half_ellipsoid_through_apex(system):
    s = Surface.from_apex_base(APEX, BASE, system=system, radius_ratio=0.35)
    length = np.linalg.norm(APEX - BASE)
    # the hemi-ellipsoid of semi-axes (L, 0.35 L, 0.35 L); the cylindrical
    # Hermite fit of sqrt(1 - z^2) near the apex is the coarsest
    tol = 0.02 if system == "cylindrical" else 1e-3
    np.testing.assert_allclose(s.volume_ml(), 2 / 3 * np.pi * length * (0.35 * length) ** 2 / 1000, rtol=tol)
    p, _ = s.mesh(closed=True)
    assert np.min(np.linalg.norm(p - APEX, axis=1)) < 0.02 * length


def test_mask_of_ellipsoid_matches_analytic_volume():
    s = constant_prolate(0.6)
    # a grid whose voxel centres do not line up with the base plane
    grid = ImageGrid((100, 80, 80), spacing=(0.9, 0.9, 0.9), origin=(-35.3, -35.6, 0.2))
    mask = s.mask(grid)
    voxel_ml = 0.9**3 / 1000
    # voxelisation error: about (surface area) x (voxel size) x 0.1 in the
    # worst case; the half-ellipsoid here has ~ 8000 mm^2 of surface
    assert abs(mask.sum() * voxel_ml - s.volume_ml()) < 8000 * 0.9 * 0.1 / 1000
    # and every voxel centre agrees with the analytic inside test
    k, j, i = np.nonzero(np.ones(grid.shape, bool))
    world = grid.index_to_world(np.stack([i, j, k], 1))
    local = s.pose.to_local(world)
    lam, _, mu = s.system.from_cartesian(local)
    analytic = ((lam <= 0.6) & (mu <= np.pi / 2)).reshape(grid.shape)
    np.testing.assert_array_equal(mask, analytic)


def test_mask_outside_image_is_empty():
    s = constant_prolate(0.6)
    grid = ImageGrid((10, 10, 10), origin=(500.0, 500.0, 500.0))
    assert not s.mask(grid).any()


@pytest.mark.parametrize("system", ["prolate", "spherical", "cylindrical"])
def test_mesh_is_watertight_and_encloses_the_volume(system, rng):
    s = Surface.from_apex_base(APEX, BASE, system=system)
    a = s.grid.constraints
    params = s.grid.parameters(s.coefficients)
    s = s.with_coefficients(a @ (params * (1 + 0.03 * rng.normal(size=params.shape))))
    points, faces = s.mesh(96, 48)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2), "every edge in exactly two triangles"
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    assert len(np.unique(directed, axis=0)) == len(directed), "consistently oriented"
    np.testing.assert_allclose(signed_volume(points, faces) / 1000, s.volume_ml(), rtol=5e-3)
    open_points, open_faces = s.mesh(96, 48, closed=False)
    assert len(open_faces) == len(faces) - 96  # the base cap


def test_apex_is_smooth_for_random_coefficients(rng):
    """Normals around the apex agree: one tangent plane, no spike or crease."""
    s = Surface.from_apex_base(APEX, BASE)
    a = s.grid.constraints
    params = s.grid.parameters(s.coefficients) + 0.05 * rng.normal(size=a.shape[1])
    s = s.with_coefficients(a @ params)
    th = np.linspace(0, 2 * np.pi, 16, endpoint=False)

    def normal_spread(mu):
        eps = 1e-2 * mu
        dth = (s.points(th + eps, mu) - s.points(th - eps, mu)) / (2 * eps)
        dmu = (s.points(th, mu + eps) - s.points(th, mu - eps)) / (2 * eps)
        n = np.cross(dmu, dth)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        m = n.mean(0) / np.linalg.norm(n.mean(0))
        return np.degrees(np.arccos(np.clip(n @ m, -1, 1))).max()

    # normals turn in proportion to the distance from the apex (curvature),
    # a cone or crease would leave a spread that does not vanish
    assert normal_spread(1e-4) < 0.15 * normal_spread(1e-3) + 0.01
    # one apex point
    apex_points = s.points(th, 0.0)
    assert np.ptp(apex_points, axis=0).max() < 1e-9


def test_refine_keeps_surface(rng):
    s = Surface.from_apex_base(APEX, BASE, patches=(4, 4))
    fine = s.refine()
    th, mu = rng.uniform(0, 2 * np.pi, 100), rng.uniform(0, np.pi / 2, 100)
    np.testing.assert_allclose(fine.evaluate(th, mu), s.evaluate(th, mu), atol=1e-12)
    assert (fine.grid.n1, fine.grid.n2) == (8, 8)


def test_dict_round_trip():
    s = Surface.from_apex_base(APEX, BASE, system="cylindrical", patches=(6, 4))
    again = Surface.from_dict(s.to_dict())
    np.testing.assert_array_equal(again.coefficients, s.coefficients)
    assert again.system == s.system and again.grid == s.grid


def test_bad_input():
    with pytest.raises(ValueError, match="apex and base"):
        Surface.from_apex_base(BASE, BASE)
    with pytest.raises(ValueError, match="number of patches"):
        Surface.from_apex_base(APEX, BASE, patches=(1, 8))
    with pytest.raises(ValueError, match="radius_ratio"):
        Surface.from_apex_base(APEX, BASE, radius_ratio=0)
    with pytest.raises(ValueError, match="apex"):
        Surface.from_apex_base([np.nan, 0, 0], BASE)


def ring(centre, e2, e3, radius=21.0, k=9):
    t = np.arange(k) * (2 * np.pi / k) + 0.2
    return centre + radius * (np.cos(t)[:, None] * e2 + np.sin(t)[:, None] * e3)


@pytest.mark.parametrize("system", ["prolate", "spherical"])
@pytest.mark.parametrize("offset", [0.0, 8.0, 16.0])
def test_from_annulus_is_sheared_half_ellipsoid_through_apex(system, offset):
    # a mitral plane tilted 20 degrees from the xy plane, the apex 80 mm above
    # it and offset from the axis
    tilt = np.radians(20.0)
    n = np.array([0.0, -np.sin(tilt), np.cos(tilt)])
    e2, centre = np.array([1.0, 0, 0]), np.array([5.0, -3, 12])
    annulus = ring(centre, e2, np.cross(n, e2))
    height, ratio = 80.0, 0.3
    apex = centre + height * n + offset * e2
    s = Surface.from_annulus(apex, annulus, system=system, radius_ratio=ratio)
    b = ratio * height
    # through the apex, exactly
    _, v1, v2 = s.model_coordinates(apex)
    np.testing.assert_allclose(s.points(v1, v2), apex, atol=1e-9)
    # the base ring lies in the plane of the annulus, a circle of radius b about its centre
    th = np.linspace(0, 2 * np.pi, 50)
    base_ring = s.points(th, np.full(50, s.grid.v2_range[1]))
    np.testing.assert_allclose((base_ring - centre) @ n, 0.0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(base_ring - centre, axis=1), b, rtol=3e-3)
    # the wall satisfies the implicit equation of the sheared half-ellipsoid:
    # distance to it ~ |g| / |grad g| within the interpolation error at 8 x 8
    # patches (0.04 mm for the upright half-ellipsoid, 0.2 mm with the apex 16 mm off)
    th, mu = np.meshgrid(np.linspace(0, 2 * np.pi, 40), np.linspace(0, np.pi / 2, 30))
    local = s.pose.to_local(s.points(th.ravel(), mu.ravel()))
    lateral = local[:, 1:] - local[:, :1] * np.array([offset / height, 0.0])
    g = (local[:, 0] / height) ** 2 + (lateral**2).sum(1) / b**2 - 1
    grad = np.stack([2 * local[:, 0] / height**2 - 2 * lateral[:, 0] * offset / height / b**2,
                     2 * lateral[:, 0] / b**2, 2 * lateral[:, 1] / b**2], 1)
    assert np.max(np.abs(g) / np.linalg.norm(grad, axis=1)) < 0.25
    # a shear keeps the volume: 2 pi h b^2 / 3; the closed mesh and a voxel
    # count agree
    exact = 2 / 3 * np.pi * height * b**2 / 1000
    np.testing.assert_allclose(s.volume_ml(), exact, rtol=2e-3)
    np.testing.assert_allclose(signed_volume(*s.mesh(128, 64)) / 1000, exact, rtol=3e-3)
    if offset == 16.0:
        lo, hi = s.bounding_box()
        grid = ImageGrid(tuple(np.ceil(hi - lo)[::-1].astype(int) + 1), spacing=(1.0,) * 3, origin=lo)
        assert abs(s.mask(grid).sum() / 1000 - exact) < 0.01 * exact


def test_from_annulus_on_axis_is_from_apex_base():
    annulus = ring(BASE, np.array([1.0, 0, 0]), np.array([0, 1.0, 0]))
    apex = BASE + np.array([0, 0, 85.0])
    a = Surface.from_apex_base(apex, BASE)
    s = Surface.from_annulus(apex, annulus)
    np.testing.assert_array_equal(s.pose.rotation, a.pose.rotation)
    np.testing.assert_allclose(s.pose.origin, BASE, atol=1e-12)
    assert s.system == a.system
    th, mu = np.meshgrid(np.linspace(0, 2 * np.pi, 30), np.linspace(0, np.pi / 2, 30))
    assert np.abs(s.points(th, mu) - a.points(th, mu)).max() < 1e-5


def test_from_annulus_bad_input():
    annulus = ring(BASE, np.array([1.0, 0, 0]), np.array([0, 1.0, 0]))
    apex = BASE + np.array([0, 0, 80.0])
    with pytest.raises(ValueError, match="no apex pole"):
        Surface.from_annulus(apex, annulus, system="cylindrical")
    with pytest.raises(ValueError, match="from the normal of the mitral plane"):
        Surface.from_annulus(apex + [30.0, 0, 0], annulus)
    with pytest.raises(ValueError, match="radius_ratio"):
        Surface.from_annulus(apex, annulus, radius_ratio=1.5)
    with pytest.raises(ValueError, match="at least 3"):
        Surface.from_annulus(apex, annulus[:2])


@pytest.mark.parametrize("system", ["prolate", "spherical", "cylindrical"])
def test_volume_is_the_quadrature_of_the_radial_volume(system):
    """volume_ml (the trigonometry of v2 once a row of points) equals the
    quadrature over the points one by one, to the last bit."""
    s = Surface.from_apex_base([1.0, 2.0, 80.0], [0.0, 0.0, 0.0], system=system, patches=(4, 2))
    s = s.with_coefficients(s.coefficients * (1 + 0.1 * np.sin(np.arange(s.coefficients.size))).reshape(s.grid.shape))
    v1, v2, w = s.grid.quadrature(8)
    f = np.maximum(s.evaluate(v1, v2), 0.0)
    np.testing.assert_allclose(s.volume_ml(), w @ s.system.radial_volume(f, v2) / 1000, rtol=1e-14)
    f = np.maximum(s.grid.quadrature_values(s.coefficients), 0.0)
    assert s.volume_ml() == float(w @ s.system.radial_volume(f, v2)) / 1000


@pytest.mark.parametrize("system", ["prolate", "spherical", "cylindrical"])
def test_grid_points_are_the_points_on_the_grid(system):
    """grid_points (f by two matrix products) equals points at every point
    of the grid, rows along v2, rounding apart; a single row too."""
    s = Surface.from_apex_base(APEX, BASE, system=system, patches=(4, 2))
    s = s.with_coefficients(s.coefficients * (1 + 0.1 * np.sin(np.arange(s.coefficients.size))).reshape(s.grid.shape))
    lo, hi = s.grid.v2_range
    v1, v2 = np.linspace(-0.5, 7.0, 31), np.linspace(lo, hi, 9)
    full_v1, full_v2 = np.meshgrid(v1, v2)
    np.testing.assert_allclose(s.grid_points(v1, v2), s.points(full_v1, full_v2), rtol=1e-13, atol=1e-11)
    np.testing.assert_allclose(s.grid_points(v1, lo)[0], s.points(v1, np.full_like(v1, lo)), rtol=1e-13, atol=1e-11)
    # and the radius alone, clamped at 0 as radius() is (a surface dipping below the axis)
    dipped = s.with_coefficients(s.coefficients - np.median(s.coefficients[..., 0]) * (np.arange(4) == 0))
    assert (dipped.radius(full_v1, full_v2) == 0).any() and (dipped.radius(full_v1, full_v2) > 0).any()
    np.testing.assert_allclose(dipped.radius_grid(v1, v2), dipped.radius(full_v1, full_v2), rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("system", ["prolate", "spherical", "cylindrical"])
def test_tip_is_the_centre_of_the_end_ring(system):
    """tip(): at a pole the whole end ring is the one point of the first
    node's value; without a pole (cylindrical) the ring's centre."""
    s = Surface.from_apex_base(APEX, BASE, system=system, patches=(4, 2))
    wavy = s.coefficients * (1 + 0.1 * np.sin(np.arange(s.coefficients.size))).reshape(s.grid.shape)
    s = s.with_coefficients(s.grid.constrain(wavy))  # a well-formed surface: one point at a pole
    lo = s.grid.v2_range[0]
    ring = s.points(np.linspace(0, 2 * np.pi, 16, endpoint=False), np.full(16, lo))
    if 0 in s.grid.pole_rows:
        np.testing.assert_allclose(ring, np.broadcast_to(s.tip(), ring.shape), rtol=0, atol=1e-9)
    else:
        assert np.ptp(ring, axis=0).max() > 1.0  # a ring, not a point
    np.testing.assert_allclose(s.tip(), ring.mean(axis=0), rtol=0, atol=1e-9)
