import numpy as np
import pytest

from spheroseg.hermite import HermiteGrid, basis_norms, hermite_basis


def test_basis_interpolates_nodes():
    b = hermite_basis(np.array([0.0, 1.0]))
    d = hermite_basis(np.array([0.0, 1.0]), 1)
    np.testing.assert_allclose(b, [[1, 0], [0, 0], [0, 1], [0, 0]], atol=1e-15)
    np.testing.assert_allclose(d, [[0, 0], [1, 0], [0, 0], [0, 1]], atol=1e-15)


@pytest.mark.parametrize("derivative", [1, 2])
def test_basis_derivatives_finite_difference(derivative):
    t = np.linspace(0.05, 0.95, 11)
    eps = 1e-6
    fd = (hermite_basis(t + eps, derivative - 1) - hermite_basis(t - eps, derivative - 1)) / (2 * eps)
    np.testing.assert_allclose(hermite_basis(t, derivative), fd, atol=1e-7)


def cubic_coefficients(grid, coef):
    """Nodal coefficients of the bicubic sum a_ij (v1/2pi)^i v2^j (not periodic)."""
    v2, v1 = np.meshgrid(grid.node_v2, grid.node_v1, indexing="ij")
    return np.stack([bicubic(coef, v1, v2, d1, d2) for d1, d2 in ((0, 0), (1, 0), (0, 1), (1, 1))], -1)


def bicubic(coef, v1, v2, d1=0, d2=0):
    out = 0.0
    for i in range(4):
        for j in range(4):
            if i < d1 or j < d2:
                continue
            ci = np.prod(np.arange(i, i - d1, -1)) if d1 else 1
            cj = np.prod(np.arange(j, j - d2, -1)) if d2 else 1
            out = out + coef[i, j] * ci * cj * v1 ** (i - d1) * v2 ** (j - d2)
    return out


def test_reproduces_bicubic_exactly(rng):
    # in v1 periodicity breaks a global cubic; test one period away from the seam
    grid = HermiteGrid(6, 5, (0.2, 1.7), poles=())
    coef = rng.normal(size=(4, 4))
    c = cubic_coefficients(grid, coef)
    v1 = rng.uniform(0, 2 * np.pi * 5 / 6, 300)  # patches not touching the seam
    v2 = rng.uniform(0.2, 1.7, 300)
    for d1, d2 in ((0, 0), (1, 0), (0, 1), (1, 1), (2, 0), (0, 2)):
        np.testing.assert_allclose(grid.evaluate(c, v1, v2, d1, d2), bicubic(coef, v1, v2, d1, d2), rtol=1e-9, atol=1e-9)


def test_first_derivatives_finite_difference(rng):
    grid = HermiteGrid(8, 8)
    c = rng.normal(size=grid.shape)
    v1, v2 = rng.uniform(0, 2 * np.pi, 200), rng.uniform(0.01, np.pi / 2 - 0.01, 200)
    eps = 1e-6
    fd1 = (grid.evaluate(c, v1 + eps, v2) - grid.evaluate(c, v1 - eps, v2)) / (2 * eps)
    fd2 = (grid.evaluate(c, v1, v2 + eps) - grid.evaluate(c, v1, v2 - eps)) / (2 * eps)
    np.testing.assert_allclose(grid.evaluate(c, v1, v2, 1, 0), fd1, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(grid.evaluate(c, v1, v2, 0, 1), fd2, rtol=1e-6, atol=1e-6)


def test_seam_continuity(rng):
    grid = HermiteGrid(8, 6)
    c = rng.normal(size=grid.shape)
    v2 = np.linspace(0, np.pi / 2, 50)
    eps = 1e-9
    for d1, d2 in ((0, 0), (1, 0), (0, 1)):
        below = grid.evaluate(c, 2 * np.pi - eps, v2, d1, d2)
        above = grid.evaluate(c, eps, v2, d1, d2)
        np.testing.assert_allclose(below, above, atol=1e-7)
    # and v1 is periodic
    np.testing.assert_allclose(grid.evaluate(c, 1.0 + 2 * np.pi, v2), grid.evaluate(c, 1.0, v2))


def test_pole_is_one_point_with_one_tangent_plane(rng):
    """f(., 0) is constant and df/dmu(., 0) is a first harmonic, for any parameters."""
    grid = HermiteGrid(8, 8)
    a = grid.constraints
    c = (a @ rng.normal(size=a.shape[1])).reshape(grid.shape)
    th = np.linspace(0, 2 * np.pi, 97)
    f0 = grid.evaluate(c, th, 0.0)
    np.testing.assert_allclose(f0, f0[0], atol=1e-12)
    np.testing.assert_allclose(grid.evaluate(c, th, 0.0, 1, 0), 0, atol=1e-12)
    slope = grid.evaluate(c, th, 0.0, 0, 1)
    p = np.linalg.lstsq(np.stack([np.cos(th), np.sin(th)], 1), slope, rcond=None)[0]
    # cubic Hermite interpolation of a sinusoid: error O(h^4), h = 2 pi / 8
    assert np.abs(slope - np.stack([np.cos(th), np.sin(th)], 1) @ p).max() < 2e-3 * np.abs(p).max()
    # constrain() is a projection that keeps well-formed coefficients
    np.testing.assert_allclose(grid.constrain(c), c, atol=1e-12)
    assert grid.pole_rows == (0,)


def test_refinement_changes_no_value(rng):
    grid = HermiteGrid(4, 3, (0.0, np.pi / 2))
    c = rng.normal(size=grid.shape)
    fine, cf = grid.refine(c)
    assert (fine.n1, fine.n2) == (8, 6)
    v1, v2 = rng.uniform(0, 2 * np.pi, 400), rng.uniform(0, np.pi / 2, 400)
    for d1, d2 in ((0, 0), (1, 0), (0, 1), (1, 1)):
        np.testing.assert_allclose(fine.evaluate(cf, v1, v2, d1, d2), grid.evaluate(c, v1, v2, d1, d2), atol=1e-10)


def test_quadrature_integrates_polynomials():
    grid = HermiteGrid(4, 4, (0.0, 2.0), poles=())
    v1, v2, w = grid.quadrature(8)
    assert len(w) == 4 * 8 * 4 * 8
    np.testing.assert_allclose(w.sum(), 2 * np.pi * 2.0)
    np.testing.assert_allclose(w @ (v2**5 * np.cos(v1) ** 2), np.pi * 2.0**6 / 6, rtol=1e-12)


def test_eq10_norms_match_gram_matrix():
    """The normalisation of paper eq. 10 is the diagonal of the Gram matrix."""
    grid = HermiteGrid(6, 5, (0.0, 1.3), poles=())
    v1, v2, w = grid.quadrature(8)
    b = grid.basis_matrix(v1, v2)
    gram = (b.T @ (b.multiply(w[:, None]))).diagonal()
    np.testing.assert_allclose(np.sqrt(gram), basis_norms(6, 5, (0.0, 1.3)).ravel(), rtol=1e-12)


@pytest.mark.parametrize("n1, n2", [(1, 8), (8, 1), (0, 4), (2.5, 4)])
def test_too_few_patches(n1, n2):
    with pytest.raises(ValueError, match="number of patches"):
        HermiteGrid(n1, n2)


@pytest.mark.parametrize("order", [3, 8])
def test_quadrature_values_are_the_surface_at_the_quadrature_points(rng, order):
    """The patch-table evaluation against the sparse basis, point by point,
    on a grid with a pole row and one without."""
    for grid in (HermiteGrid(6, 4, (0.0, 2.0)), HermiteGrid(2, 3, (0.4, 2.5))):
        c = rng.normal(size=grid.shape)
        v1, v2, _ = grid.quadrature(order)
        np.testing.assert_allclose(grid.quadrature_values(c, order), grid.basis_matrix(v1, v2) @ c.ravel(),
                                   rtol=0, atol=1e-12)
