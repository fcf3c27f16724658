import numpy as np
import pytest

from spheroseg.geometry.discretisation import BAND_STRIDE, ROUGHNESS_SCALE, discretise
from spheroseg.geometry.hermite import HermiteGrid


@pytest.fixture(scope="module")
def disc():
    return discretise(HermiteGrid(4, 6, (0.0, np.pi / 2)), 6)


def test_quadrature_integrates_the_domain(disc):
    area = 2 * np.pi * np.pi / 2
    assert disc.area == pytest.approx(area, rel=1e-12)
    assert disc.band_weights.sum() == pytest.approx(area, rel=1e-12)
    # a smooth function of (v1, v2) integrates to its analytic value
    integral = disc.weights @ (np.cos(disc.v1) ** 2 * np.sin(disc.v2))
    assert integral == pytest.approx(np.pi * 1.0, rel=1e-9)


def test_band_rows_are_every_other_position_of_a_patch(disc):
    assert len(disc.band_rows) * BAND_STRIDE**2 == disc.n_samples
    x, _ = np.polynomial.legendre.leggauss(disc.order)
    kept = ((x + 1) / 2)[::BAND_STRIDE]
    local_v1 = np.mod(disc.v1[disc.band_rows] / (2 * np.pi / 4), 1.0)
    assert np.all(np.min(np.abs(local_v1[:, None] - kept[None, :]), axis=1) < 1e-12)


def test_inverses(disc):
    n = disc.n_parameters
    np.testing.assert_allclose(disc.mass_inverse @ disc.mass, np.eye(n), atol=1e-8)
    for smoothness in (0.0, 1.0, 7.5):
        system = disc.mass + disc.smoothing(smoothness).toarray()
        np.testing.assert_allclose(disc.system_inverse(smoothness) @ system, np.eye(n), atol=1e-8)
    # the mass matrix is B^T W B, from the sparse basis at the samples
    b = disc.b_f.toarray()
    np.testing.assert_allclose(disc.mass, b.T @ (disc.weights[:, None] * b), rtol=1e-12, atol=1e-14)


def test_patch_tables_give_the_basis_matrix(disc):
    """f at the samples from the two per-patch tables equals the sparse basis."""
    grid, order = disc.grid, disc.order
    rng = np.random.default_rng(0)
    coefficients = rng.standard_normal(grid.shape)
    expected = grid.basis_matrix(disc.v1, disc.v2) @ coefficients.ravel()
    t1, t2 = disc.tables
    f = np.empty(disc.n_samples)
    for i2 in range(grid.n2):
        for i1 in range(grid.n1):
            patch = np.array([[coefficients[i2 + a2, (i1 + a1) % grid.n1, e1 + 2 * e2] for a2 in (0, 1)
                               for e2 in (0, 1)] for a1 in (0, 1) for e1 in (0, 1)])
            for b in range(order):
                q = ((i2 * order + b) * grid.n1 + i1) * order
                f[q:q + order] = t1[0] @ patch @ t2[0, b]
    np.testing.assert_allclose(f, expected, atol=1e-12)


def test_shared_and_read_only():
    a = discretise(HermiteGrid(4, 4, (0.0, 1.5)), 8)
    assert discretise(HermiteGrid(4, 4, (0.0, 1.5)), 8) is a  # equal grids share it
    assert a.system_inverse(1.0) is a.system_inverse(1.0)
    with pytest.raises(ValueError):
        a.mass[0, 0] = 1.0
    with pytest.raises(ValueError, match="order"):
        discretise(HermiteGrid(4, 4, (0.0, 1.5)), 0)


def test_smoothing_is_cached_read_only():
    """The cached a T equals the thin-plate matrix scaled afresh, and no
    descent can change its values for the next."""
    d = discretise(HermiteGrid(4, 4), 8)
    for smoothness in (1.0, 0.25):
        expected = (smoothness * float(d.weights.sum()) / ROUGHNESS_SCALE) * d.roughness.toarray()
        np.testing.assert_array_equal(d.smoothing(smoothness).toarray(), expected)
        assert d.smoothing(smoothness) is d.smoothing(smoothness)
        with pytest.raises(ValueError, match="read-only"):
            d.smoothing(smoothness).data[0] = 1.0
