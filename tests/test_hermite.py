import numpy as np
import pytest

from spheroseg.geometry.hermite import HermiteGrid, basis_norms, global_basis, hermite_basis, patch_dofs


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
        expected = bicubic(coef, v1, v2, d1, d2)
        np.testing.assert_allclose(grid.evaluate(c, v1, v2, d1, d2), expected, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(grid.basis_matrix(v1, v2, d1, d2) @ c.ravel(), expected, rtol=1e-9, atol=1e-9)


def test_evaluate_sums_the_terms_in_a_fixed_order(rng):
    """evaluate's vectorised sum equals the 16 terms added one by one in
    the order (a2, a1, e2, e1), to the last bit (segmentations that fit a
    surface must not change)."""
    grid = HermiteGrid(5, 3, (0.0, np.pi / 2))
    c = rng.normal(size=grid.shape).ravel()
    v1, v2 = rng.uniform(-1, 7, 200), rng.uniform(-0.1, 1.7, 200)
    for d1, d2 in ((0, 0), (1, 0), (0, 1), (1, 1)):
        # the point's patch, local coordinates and basis in global units
        u1, u2 = np.mod(v1, 2 * np.pi) * (grid.n1 / (2 * np.pi)), v2 * (grid.n2 / (np.pi / 2))
        i1, i2 = np.clip(np.floor(u1).astype(int), 0, grid.n1 - 1), np.clip(np.floor(u2).astype(int), 0, grid.n2 - 1)
        w1, w2 = 2 * np.pi / grid.n1, np.pi / 2 / grid.n2
        b1 = hermite_basis(u1 - i1, d1) * (np.array([1.0, w1, 1.0, w1]) / w1**d1)[:, None]
        b2 = hermite_basis(u2 - i2, d2) * (np.array([1.0, w2, 1.0, w2]) / w2**d2)[:, None]
        expected = np.zeros(v1.shape)
        for a2 in (0, 1):
            for a1 in (0, 1):
                base = ((i2 + a2) * grid.n1 + (i1 + a1) % grid.n1) * 4
                for e2 in (0, 1):
                    for e1 in (0, 1):
                        expected += (b1[2 * a1 + e1] * b2[2 * a2 + e2]) * c[base + e1 + 2 * e2]
        np.testing.assert_array_equal(grid.evaluate(c, v1, v2, d1, d2), expected)
        # a tensor grid as a row and a column: the same values, point by point
        row, column = v1[:24], v2[:10, None]
        grid_v1, grid_v2 = np.meshgrid(row, column)
        flat = grid.evaluate(c, grid_v1.ravel(), grid_v2.ravel(), d1, d2).reshape(grid_v1.shape)
        np.testing.assert_array_equal(grid.evaluate(c, row, column, d1, d2), flat)
        np.testing.assert_array_equal(grid.evaluate(c, row, column[0, 0], d1, d2), flat[0])


@pytest.mark.parametrize("grid", [HermiteGrid(2, 2), HermiteGrid(8, 8), HermiteGrid(5, 3, (0.2, 1.7), poles=())])
def test_parameter_rows_are_the_sparse_product(rng, grid):
    """The dense rows equal the sparse basis times the constraints, to the
    last bit, at the poles' rows too."""
    v1, v2 = rng.uniform(0, 2 * np.pi, 7), np.r_[grid.v2_range[0], rng.uniform(*grid.v2_range, 5), grid.v2_range[1]]
    expected = (grid.basis_matrix(v1, v2) @ grid.constraints).toarray()
    np.testing.assert_array_equal(grid.parameter_rows(v1, v2), expected)
    np.testing.assert_array_equal(grid.parameter_rows(v1[:1], v2[:1]), expected[:1])


def test_quadrature_and_tables_are_cached_read_only():
    """The cached quadrature and patch tables equal fresh ones, and no
    caller can change them for the next."""
    grid = HermiteGrid(4, 3, (0.1, 1.4))
    again = HermiteGrid(4, 3, (0.1, 1.4))
    for method, n in ((HermiteGrid.quadrature, 3), (HermiteGrid.patch_tables, 2)):
        fresh = method.__wrapped__(grid, 6)
        cached = method(again, 6)
        assert cached is method(grid, 6)
        assert len(cached) == n
        for a, b in zip(cached, fresh):
            np.testing.assert_array_equal(a, b)
            with pytest.raises(ValueError, match="read-only"):
                a[0] = 1.0


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


@pytest.mark.parametrize("grid", [HermiteGrid(2, 2), HermiteGrid(8, 8), HermiteGrid(5, 3, (0.2, 1.7), poles=())])
def test_evaluate_grid_is_evaluate_on_the_grid(rng, grid):
    """The two matrix products equal the point-by-point sum (rounding
    apart), across the seam of v1 and beyond the v2 range."""
    c = grid.constrain(rng.normal(size=grid.shape))
    lo, hi = grid.v2_range
    v1, v2 = rng.uniform(-1, 7, 40), np.r_[lo - 0.05, rng.uniform(lo, hi, 10), hi, hi + 0.05]
    full_v1, full_v2 = np.meshgrid(v1, v2)
    np.testing.assert_allclose(grid.evaluate_grid(c, v1, v2), grid.evaluate(c, full_v1, full_v2), rtol=1e-13, atol=1e-13)
    # its basis is kept by the parameters' values: other values of the same
    # sizes (and the first again, as a list) are not given the kept one
    other = v2[::-1].copy()
    np.testing.assert_allclose(grid.evaluate_grid(c, v1, other), grid.evaluate(c, *np.meshgrid(v1, other)),
                               rtol=1e-13, atol=1e-13)
    np.testing.assert_array_equal(grid.evaluate_grid(c, list(v1), v2), grid.evaluate_grid(c, v1, v2))


@pytest.mark.parametrize("derivative", [1, 2])
def test_global_basis_is_the_derivative_in_v(derivative):
    # a patch 0.7 wide: the slope dofs multiply width psi^1, each derivative in v divides by the width
    width, t, eps = 0.7, np.linspace(0.05, 0.95, 11), 1e-6
    fd = (global_basis(t + eps / width, width, derivative - 1) - global_basis(t - eps / width, width, derivative - 1))
    np.testing.assert_allclose(global_basis(t, width, derivative), fd / (2 * eps), atol=1e-6)
    # at the nodes: values and slopes (in v) of 1 where their dof is
    np.testing.assert_allclose(global_basis(np.array([0.0, 1.0]), width, 1), [[0, 0], [1, 0], [0, 0], [0, 1]],
                               atol=1e-12)


def test_patch_dofs_lay_out_each_patch_as_evaluate_reads_it():
    grid = HermiteGrid(5, 3, (0.0, 2.0))
    c = np.random.default_rng(3).standard_normal(grid.shape)
    dofs = patch_dofs(grid.n1, grid.n2)
    w1, w2 = 2 * np.pi / grid.n1, 2.0 / grid.n2
    for i2, i1 in ((0, 0), (2, 4), (1, 2)):  # (2, 4): the periodic patch
        t1, t2 = np.array([0.3, 0.8]), np.array([0.6, 0.1])
        patch = c.ravel()[dofs[i2, i1]]  # [2 a1 + e1, 2 a2 + e2]
        f = np.einsum("jp,jm,mp->p", global_basis(t1, w1), patch, global_basis(t2, w2))
        np.testing.assert_allclose(f, grid.evaluate(c, (i1 + t1) * w1, (i2 + t2) * w2), atol=1e-12)
    assert not dofs.flags.writeable

