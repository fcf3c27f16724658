"""Every gradient against a central finite difference of its energy."""

import numpy as np
import pytest

from spheroseg.geometry.energy import (
    Landmarks,
    SampledSurface,
    area_energy,
    area_gradient,
    data_energy,
    data_gradient,
    landmark_energy,
    landmark_gradient,
    region_force,
)
from spheroseg.surfaces.surface import Surface

APEX, BASE = np.array([5.0, -3.0, 82.0]), np.array([0.0, 0.0, 2.0])


def smooth_image(x):
    """An analytic, smooth 'image' (mm -> grey level): a bright shell."""
    r = np.linalg.norm((x - [0, 0, 30]) * [1.0, 1.0, 0.45], axis=-1)
    return 20.0 + 100.0 / (1.0 + np.exp(-(r - 24.0) / 3.0)) + 5.0 * np.sin(x[..., 0] / 7.0)


def random_model(system, rng, patches=(4, 4), order=6):
    s = Surface.from_apex_base(APEX, BASE, system=system, patches=patches)
    model = SampledSurface(s.system, s.pose, s.grid, order)
    p = model.parameters(s.coefficients)
    scale = np.abs(p).max()
    return model, p + 0.02 * scale * rng.normal(size=p.shape)


def central_difference(fun, p, rng, n_directions=4, eps=1e-5):
    out = []
    for _ in range(n_directions):
        d = rng.normal(size=p.shape)
        d /= np.linalg.norm(d)
        out.append((d, (fun(p + eps * d) - fun(p - eps * d)) / (2 * eps)))
    return out


def assert_gradient(fun, grad, p, rng, rtol=1e-4):
    g = grad(p)
    for d, fd in central_difference(fun, p, rng):
        assert abs(g @ d - fd) <= rtol * np.linalg.norm(g), (g @ d, fd)


@pytest.mark.parametrize("system", ["prolate", "spherical", "cylindrical"])
@pytest.mark.parametrize("local_means", [False, True])
def test_data_gradient(system, local_means, rng):
    model, p = random_model(system, rng)
    if local_means:  # per-point means, frozen (the localised term)
        c_in = 30.0 + 10 * rng.random(model.n_samples)
        c_out = 110.0 + 10 * rng.random(model.n_samples)
    else:
        c_in, c_out = 30.0, 115.0
    fun = lambda q: data_energy(model, q, smooth_image, c_in, c_out, n_radial=48)
    grad = lambda q: data_gradient(model, q, smooth_image, c_in, c_out)
    assert_gradient(fun, grad, p, rng)


@pytest.mark.parametrize("system", ["prolate", "spherical", "cylindrical"])
def test_area_gradient(system, rng):
    model, p = random_model(system, rng)
    assert_gradient(lambda q: area_energy(model, q), lambda q: area_gradient(model, q), p, rng)


def test_area_of_sphere():
    """The area term integrates to the analytic area of a sphere."""
    s = Surface.from_apex_base([0, 0, 30.0], [0, 0, 0], system="spherical")
    model = SampledSurface(s.system, s.pose, s.grid)
    p = model.parameters(np.where(np.arange(4) == 0, 30.0, 0.0) * np.ones(s.grid.shape))
    np.testing.assert_allclose(area_energy(model, p), 2 * np.pi * 30.0**2, rtol=1e-6)


def test_landmark_gradient(rng):
    model, p = random_model("prolate", rng)
    lm = Landmarks.from_world(model, APEX * 0.5 + BASE * 0.5 + rng.normal(scale=15, size=(3, 3)) * [1, 1, 0.2])
    assert_gradient(lambda q: landmark_energy(lm, q), lambda q: landmark_gradient(lm, q), p, rng)


def test_landmark_rows_are_the_sparse_basis(rng):
    """The landmarks' rows (dense) equal the sparse basis at
    their (v1, v2) times the constraints, to the last bit, the apex too."""
    model, _ = random_model("prolate", rng)
    points = np.concatenate([APEX[None], APEX * 0.5 + BASE * 0.5 + rng.normal(scale=15, size=(3, 3)) * [1, 1, 0.2]])
    lm = Landmarks.from_world(model, points)
    _, v1, v2 = model.system.from_cartesian(model.pose.to_local(points))
    expected = (model.grid.basis_matrix(v1, v2) @ model.constraints).toarray()
    np.testing.assert_array_equal(lm.basis, expected)


def test_landmark_beyond_base_is_refused(rng):
    model, _ = random_model("prolate", rng)
    with pytest.raises(ValueError, match="beyond the base plane"):
        Landmarks.from_world(model, [BASE - 10 * (APEX - BASE) / np.linalg.norm(APEX - BASE)])


@pytest.mark.parametrize("system", ["prolate", "spherical", "cylindrical"])
def test_landmarks_on_the_base_plane_are_in_range(system, rng):
    """Points in the base plane itself (the tracker's base ring) come back
    from the coordinate map a rounding error beyond it: they are held, on
    the plane; 0.1 mm beyond it they are refused."""
    model, _ = random_model(system, rng)
    pose = model.pose
    angles = np.linspace(0, 2 * np.pi, 97)
    ring = np.stack([np.zeros_like(angles), 12.0 * np.cos(angles), 12.0 * np.sin(angles)], axis=1)
    lm = Landmarks.from_world(model, pose.to_world(ring))
    assert lm.v0.shape == (len(angles),) and np.all(np.isfinite(lm.v0)) and np.all(np.isfinite(lm.basis))
    with pytest.raises(ValueError, match="beyond the base plane"):
        Landmarks.from_world(model, pose.to_world(ring - [0.1, 0.0, 0.0]))


def test_region_force_sign():
    # dark (blood-like) grey at the surface: moving the surface out lowers the energy
    assert region_force(20.0, 30.0, 110.0) < 0 < region_force(100.0, 30.0, 110.0)
    assert region_force(70.0, 30.0, 110.0) == 0


def test_geometry_normals_point_outwards(rng):
    model, p = random_model("prolate", rng)
    g = model.geometry(p)
    centre = model.pose.to_world(np.array([30.0, 0, 0]))
    assert np.mean(np.einsum("ij,ij->i", g.normal, g.world - centre) > 0) > 0.95
    np.testing.assert_allclose(np.linalg.norm(g.normal, axis=1), 1.0)
