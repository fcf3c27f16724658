import numpy as np
import pytest
from scipy import integrate

from spheroseg.geometry.coords import Pose, ProlateSpheroidal
from spheroseg.geometry.hermite import HermiteGrid
from spheroseg.surfaces.myocardium import (
    SEGMENT_NAMES, SegmentConvention, cavity_length, lv_mass_g, myocardial_volume_ml, segment_labels,
    segment_table, segment_volumes_ml, systolic_dyssynchrony_index, times_to_minimum, wall_thickness,
)
from spheroseg.surfaces.surface import ImageGrid, Surface

APEX, BASE = np.array([3.0, -4.0, 85.0]), np.array([0.0, 0.0, 5.0])
D = 40.0


def constant_prolate(l0, d=D, pose=None):
    system = ProlateSpheroidal(d)
    grid = HermiteGrid(8, 8, (0.0, np.pi / 2), poles=system.poles)
    return Surface.from_function(system, pose or Pose.from_apex_base(APEX, BASE), grid, l0)


def half_spheroid_ml(l0, d=D):
    a, b = d * np.cosh(l0), d * np.sinh(l0)
    return 2 / 3 * np.pi * a * b * b / 1000


def slab_ml(l0, lo, hi, d=D):
    """Volume of the half spheroid between the heights lo and hi (mm)."""
    a, b = d * np.cosh(l0), d * np.sinh(l0)
    lo, hi = np.clip([lo, hi], 0, a)
    prim = lambda x: np.pi * b * b * (x - x**3 / (3 * a * a))  # noqa: E731
    return (prim(hi) - prim(lo)) / 1000


def test_shell_volume_and_mass_are_analytic():
    endo, epi = constant_prolate(0.8), constant_prolate(0.95)
    expected = half_spheroid_ml(0.95) - half_spheroid_ml(0.8)
    np.testing.assert_allclose(myocardial_volume_ml(endo, epi), expected, rtol=1e-6)
    np.testing.assert_allclose(lv_mass_g(myocardial_volume_ml(endo, epi)), 1.05 * expected, rtol=1e-6)


def test_wall_thickness_along_lambda_is_analytic():
    l1, l2 = 0.8, 0.95
    endo, epi = constant_prolate(l1), constant_prolate(l2)
    # at the apex the lambda curve is the axis: the difference of the semi-major axes
    np.testing.assert_allclose(wall_thickness(endo, epi, 1.0, 0.0), D * (np.cosh(l2) - np.cosh(l1)), rtol=1e-9)
    # at the base plane it is radial: the difference of the semi-minor axes
    np.testing.assert_allclose(wall_thickness(endo, epi, 2.0, np.pi / 2), D * (np.sinh(l2) - np.sinh(l1)), rtol=1e-9)
    # in between, the arc length of the hyperbola by adaptive quadrature
    mu = 0.6
    arc = integrate.quad(lambda lam: D * np.sqrt(np.sinh(lam) ** 2 + np.sin(mu) ** 2), l1, l2)[0]
    np.testing.assert_allclose(wall_thickness(endo, epi, 0.3, mu), arc, rtol=1e-9)


def test_mismatched_surfaces_are_refused():
    other = constant_prolate(0.9, pose=Pose.from_apex_base(APEX + 1, BASE))
    with pytest.raises(ValueError, match="one coordinate system and one pose"):
        myocardial_volume_ml(constant_prolate(0.8), other)


@pytest.mark.parametrize("psi_deg, h, label", [
    (-30, 0.1, 1), (30, 0.1, 2), (90, 0.2, 3), (150, 0.3, 4), (210, 0.0, 5), (270, 0.3, 6),
    (-30, 0.5, 7), (30, 0.4, 8), (90, 0.6, 9), (150, 0.5, 10), (210, 0.5, 11), (270, 0.5, 12),
    (-30, 0.8, 13), (10, 0.9, 13), (20, 0.9, 14), (100, 0.7, 14), (110, 0.7, 15), (190, 1.0, 15),
    (200, 0.7, 16), (280, 0.7, 16), (0, 1.05, 17), (123, 1.5, 17), (45, -0.01, 0),
])
@pytest.mark.parametrize("rv_insertion, direction", [(0.0, 1), (2.0, -1)])
def test_segment_labels_follow_the_definition(psi_deg, h, label, rv_insertion, direction):
    length = 80.0
    theta = rv_insertion + direction * np.radians(psi_deg)
    point = np.array([h * length, 12 * np.cos(theta), 12 * np.sin(theta)])
    assert segment_labels(point, length=length, convention=SegmentConvention(rv_insertion, direction)) == label
    if label:
        assert SEGMENT_NAMES[label - 1].split()[0] in ("basal", "mid", "apical", "apex")


def test_segment_labels_partition_every_point_once():
    rng = np.random.default_rng(0)
    theta, rho = rng.uniform(0, 2 * np.pi, 20000), rng.uniform(0, 40, 20000)
    local = np.stack([rng.uniform(-5, 100, 20000), rho * np.cos(theta), rho * np.sin(theta)], -1)
    labels = segment_labels(local, length=80.0, convention=SegmentConvention(0.7))
    assert set(np.unique(labels)) == set(range(18))
    assert np.all((labels == 0) == (local[:, 0] < 0))
    # each level's sectors tile the circle: equal shares of uniform angles
    h = local[:, 0] / 80
    basal = labels[(h >= 0) & (h < 1 / 3)]
    np.testing.assert_allclose(np.bincount(basal, minlength=7)[1:] / len(basal), 1 / 6, atol=0.02)
    apical = labels[(h >= 2 / 3) & (h <= 1)]
    np.testing.assert_allclose(np.bincount(apical, minlength=17)[13:17] / len(apical), 1 / 4, atol=0.03)


def test_segment_volumes_of_a_half_spheroid_are_analytic():
    l1, l2 = 0.8, 0.95
    endo, epi = constant_prolate(l1), constant_prolate(l2)
    length = cavity_length(endo)
    np.testing.assert_allclose(length, D * np.cosh(l1), rtol=1e-9)
    conv = SegmentConvention(1.1, -1)
    cavity = segment_volumes_ml(endo, length=length, convention=conv)
    under_epi = segment_volumes_ml(epi, length=length, convention=conv)
    thirds = [(0, length / 3), (length / 3, 2 * length / 3), (2 * length / 3, length)]
    for k, (lo, hi) in enumerate(thirds):
        share = 1 / 6 if k < 2 else 1 / 4
        segs = slice(6 * k, 6 * k + 6) if k < 2 else slice(12, 16)
        np.testing.assert_allclose(cavity[segs], share * slab_ml(l1, lo, hi), rtol=2e-4)
        np.testing.assert_allclose(under_epi[segs], share * slab_ml(l2, lo, hi), rtol=2e-4)
    assert cavity[16] == pytest.approx(0, abs=1e-9)
    np.testing.assert_allclose(under_epi[16], slab_ml(l2, length, np.inf), rtol=2e-3)
    np.testing.assert_allclose(cavity.sum(), endo.volume_ml(), rtol=1e-4)


def test_segment_table_agrees_with_voxels_on_an_irregular_wall():
    # an endocardium and an epicardium of varying thickness, no symmetry
    endo = Surface.from_apex_base(APEX, BASE, radius_ratio=0.33)
    rng = np.random.default_rng(3)
    bump = np.zeros(endo.coefficients.shape)
    bump[1:, :, 0] = rng.uniform(0.1, 0.25, bump[1:, :, 0].shape)
    bump[0, :, 0] = 0.15
    epi = endo.with_coefficients(endo.coefficients + bump)
    conv = SegmentConvention(0.4)
    table = segment_table(endo, epi, convention=conv)
    assert [r["segment"] for r in table] == list(range(1, 18))
    # the definition, voxel by voxel: labels of the centres between the surfaces
    spacing = 0.5
    lo, hi = epi.bounding_box()
    shape = tuple(int(np.ceil(n)) for n in ((hi - lo) / spacing)[::-1])
    grid = ImageGrid(shape, np.full(3, spacing), lo, np.eye(3))
    cavity, outer = endo.mask(grid), epi.mask(grid)
    k, j, i = np.nonzero(outer)
    local = endo.pose.to_local(grid.index_to_world(np.stack([i, j, k], -1).astype(float)))
    labels = segment_labels(local, length=cavity_length(endo), convention=conv)
    voxel = spacing**3 / 1000
    counts_myo = np.bincount(labels[~cavity[k, j, i]], minlength=18)[1:] * voxel
    counts_cav = np.bincount(labels[cavity[k, j, i]], minlength=18)[1:] * voxel
    myo = np.array([r["myocardium_ml"] for r in table])
    cav = np.array([r["cavity_ml"] for r in table])
    np.testing.assert_allclose(myo, counts_myo, rtol=0.03, atol=0.05)
    np.testing.assert_allclose(cav, counts_cav, rtol=0.03, atol=0.05)
    np.testing.assert_allclose(myo.sum(), myocardial_volume_ml(endo, epi), rtol=2e-3)
    thick = np.array([r["wall_thickness_mm"] for r in table])
    assert np.all((thick > 0) & (thick < 25))


def test_times_to_minimum_and_sdi_of_shifted_cosines():
    n = 20
    delays = np.linspace(-0.06, 0.06, 16)  # fractions of the cycle
    t = np.arange(n)[:, None] / n
    curves = 10 + 3 * np.cos(2 * np.pi * (t - delays))  # minimum at 0.5 + delay
    expected = 100 * (0.5 + delays)
    np.testing.assert_allclose(times_to_minimum(curves), expected, atol=0.3)
    np.testing.assert_allclose(systolic_dyssynchrony_index(curves), np.std(expected), atol=0.2)
    with pytest.raises(ValueError, match="16 or 17"):
        systolic_dyssynchrony_index(curves[:, :5])
