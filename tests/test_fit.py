import numpy as np
import pytest

from conftest import cetus_file
from spheroseg.geometry.coords import annulus_plane
from spheroseg.surfaces.fit import (annulus_of_open_mesh, apex_base_of_open_mesh, fit_surface, point_to_surface_distance)
from spheroseg.surfaces.surface import Surface
from spheroseg.io.surface_io import read_mesh


def test_recovers_known_surface(rng):
    truth = Surface.from_apex_base([0, 0, 80.0], [0, 0, 0], patches=(6, 6))
    a = truth.grid.constraints
    params = truth.grid.parameters(truth.coefficients)
    truth = truth.with_coefficients(a @ (params + 0.02 * rng.normal(size=params.shape)))
    th, mu = rng.uniform(0, 2 * np.pi, 4000), rng.uniform(0, np.pi / 2, 4000)
    fitted = fit_surface(truth.points(th, mu), system=truth.system, pose=truth.pose, patches=(6, 6), smoothness=0)
    np.testing.assert_allclose(fitted.coefficients, truth.coefficients, atol=1e-8)


def test_smoothness_shrinks_wiggles(rng):
    truth = Surface.from_apex_base([0, 0, 80.0], [0, 0, 0])
    th, mu = rng.uniform(0, 2 * np.pi, 3000), rng.uniform(0, np.pi / 2, 3000)
    noisy = truth.points(th, mu) + rng.normal(scale=1.0, size=(3000, 3))
    rough = fit_surface(noisy, system=truth.system, pose=truth.pose, smoothness=0)
    smooth = fit_surface(noisy, system=truth.system, pose=truth.pose, smoothness=1e-5)
    err = lambda s: np.abs(s.evaluate(th, mu) - truth.evaluate(th, mu)).mean()
    assert err(smooth) < err(rough)


def test_bad_points():
    s = Surface.from_apex_base([0, 0, 80.0], [0, 0, 0])
    with pytest.raises(ValueError, match="finite"):
        fit_surface(np.full((100, 3), np.nan), system=s.system, pose=s.pose)
    with pytest.raises(ValueError, match="too few"):
        fit_surface(np.ones((5, 3)), system=s.system, pose=s.pose)


def test_annulus_of_open_mesh_gives_the_mitral_plane():
    # a surface closed by a tilted mitral plane, meshed open there: its ring
    # gives back the plane, its centre and the apex
    tilt = np.radians(25.0)
    n = np.array([np.sin(tilt), 0.0, np.cos(tilt)])
    t = np.arange(7) * (2 * np.pi / 7)
    e2, e3 = np.array([0, 1.0, 0]), np.cross(n, [0, 1.0, 0])
    annulus = 20 * (np.cos(t)[:, None] * e2 + np.sin(t)[:, None] * e3)
    apex = 80 * n + 6 * e2
    s = Surface.from_annulus(apex, annulus)
    points, faces = s.mesh(48, 24, closed=False)
    ring = annulus_of_open_mesh(points, faces)
    assert len(ring) == 48
    centre, normal = annulus_plane(ring)
    np.testing.assert_allclose(centre, 0.0, atol=1e-4)  # the Hermite ring is nearly a circle
    np.testing.assert_allclose(abs(normal @ n), 1.0, atol=1e-12)
    top, base = apex_base_of_open_mesh(points, faces)
    np.testing.assert_allclose(base, centre)
    assert 79.5 < (top - base) @ n <= 80.0 + 1e-9  # the apex: the mesh point farthest from the plane
    with pytest.raises(ValueError, match="no open boundary"):
        annulus_of_open_mesh(*s.mesh(48, 24, closed=True))


@pytest.mark.parametrize("system", ["prolate", "spherical"])
def test_point_to_surface_distance_is_exact(system, rng):
    # points moved a known distance along the wall's normal (less than its
    # radii of curvature)
    s = Surface.from_apex_base([0, 0, 80.0], [0, 0, 0], system=system)
    th, mu = rng.uniform(0, 2 * np.pi, 500), rng.uniform(0.1, np.pi / 2 - 0.1, 500)
    e = 1e-5
    normal = np.cross(s.points(th + e, mu) - s.points(th - e, mu), s.points(th, mu + e) - s.points(th, mu - e))
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    shift = rng.uniform(-2, 2, 500)
    d = point_to_surface_distance(s.points(th, mu) + shift[:, None] * normal, s)
    np.testing.assert_allclose(d, np.abs(shift), atol=1e-6)
    # beyond the base plane: the distance to the base ring
    ring = s.points(th, np.full(500, np.pi / 2))
    beyond = ring + np.array([0, 0, -3.0])
    np.testing.assert_allclose(point_to_surface_distance(beyond, s), 3.0, atol=1e-3)


@pytest.mark.parametrize("phase", ["ED", "ES"])
@pytest.mark.parametrize("patches", [(4, 4), (8, 8)])
def test_fit_cetus_reference_mesh(phase, patches):
    """How well a Hermite surface posed by the mitral ring represents a real
    ventricle (CETUS Patient 1): fitted to the expert's vertices, distances
    from 20 % of them left out."""
    points, faces = read_mesh(cetus_file(f"Patient1_{phase}_truth.vtk"))
    points = points * 1000.0  # the reference meshes are in metres
    apex, _ = apex_base_of_open_mesh(points, faces)
    init = Surface.from_annulus(apex, annulus_of_open_mesh(points, faces))
    held = np.random.default_rng(0).random(len(points)) < 0.2
    fitted = fit_surface(points[~held], system=init.system, pose=init.pose, patches=patches)
    d = point_to_surface_distance(points[held], fitted)
    print(f"Patient1 {phase} {patches}: held-out mean {d.mean():.3f} mm, max {d.max():.3f} mm")
    assert d.mean() < (0.04 if patches == (8, 8) else 0.15)
    assert d.max() < (0.6 if patches == (8, 8) else 1.0)
