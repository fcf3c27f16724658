"""Beam-space geometry, sampling, scan conversion and its inverse.

The formulas the geometry is checked against are written out here again,
separately, from the tools' own sources (../shared/notes/beamspace.md):
ITK's ``PhasedArray3DSpecialCoordinatesImage.h`` for "tan" and EchoXFlow's
``scan/spherical.py`` for "sin".  Corner points off the central planes are
where the two conventions differ.
"""

import math

import numpy as np
import pytest

from spheroseg.volumes.beamspace import (BeamGeometry, BeamVolume, beam_mask, beam_mask_volume_ml, scan_convert,
                                 to_beam_space)
from spheroseg.volumes.volume import ImageGrid, Volume

SHAPE = (60, 21, 25)  # [r, e, a]
DR, R0 = 1.5, 12.0
DA, DE = math.radians(2.5), math.radians(3.0)


def geometry(convention="tan", **kw):
    return BeamGeometry(SHAPE, DR, R0, DA, DE, convention=convention, **kw)


# --- independent formulas ----------------------------------------------------------

def itk_index_to_point(index, shape=SHAPE):
    """ITK PhasedArray3DSpecialCoordinatesImage::TransformIndexToPhysicalPoint
    (ITK index order: azimuth, elevation, radius)."""
    ia, ie, ir = index
    max_azimuth, max_elevation = shape[2] - 1, shape[1] - 1
    azimuth = (ia - max_azimuth / 2.0) * DA
    elevation = (ie - max_elevation / 2.0) * DE
    radius = ir * DR + R0
    tan_a, tan_e = math.tan(azimuth), math.tan(elevation)
    z = radius / math.sqrt(1 + tan_a * tan_a + tan_e * tan_e)
    return np.array([z * tan_a, z * tan_e, z])


def itk_point_to_index(point, shape=SHAPE):
    """ITK TransformPhysicalPointToContinuousIndex: (azimuth, elevation, radius) index."""
    x, y, z = point
    azimuth = math.atan(x / z)
    elevation = math.atan(y / z)
    radius = math.sqrt(x * x + y * y + z * z)
    max_azimuth, max_elevation = shape[2] - 1, shape[1] - 1
    return np.array([azimuth / DA + max_azimuth / 2.0, elevation / DE + max_elevation / 2.0, (radius - R0) / DR])


def sin_index_to_point(index, centre):
    """x = r sin a, y = r cos a sin e, z = r cos a cos e (EchoXFlow, UFF)."""
    ir, ie, ia = index
    a, e, r = (ia - centre[1]) * DA, (ie - centre[0]) * DE, R0 + ir * DR
    return np.array([r * math.sin(a), r * math.cos(a) * math.sin(e), r * math.cos(a) * math.cos(e)])


def sin_point_to_index(point, centre):
    """EchoXFlow: azimuth = arctan2(x, sqrt(y^2 + z^2)), elevation = arctan2(y, z)."""
    x, y, z = point
    a, e = math.atan2(x, math.sqrt(y * y + z * z)), math.atan2(y, z)
    return np.array([(math.sqrt(x * x + y * y + z * z) - R0) / DR, e / DE + centre[0], a / DA + centre[1]])


CORNERS = [np.array([r, e, a], dtype=float) for r in (0, SHAPE[0] - 1) for e in (0, SHAPE[1] - 1)
           for a in (0, SHAPE[2] - 1)] + [np.array([33.3, 2.7, 19.1])]


def test_tan_matches_itk_formulas_at_off_plane_corners():
    g = geometry("tan")
    for index in CORNERS:
        itk_index = index[::-1]  # ITK: azimuth fastest, index[0] = azimuth
        expected = itk_index_to_point(itk_index)
        np.testing.assert_allclose(g.index_to_world(index), expected, atol=1e-10)
        np.testing.assert_allclose(g.world_to_index(expected), itk_point_to_index(expected)[::-1], atol=1e-10)
        np.testing.assert_allclose(g.world_to_index(g.index_to_world(index)), index, atol=1e-10)


def test_sin_matches_echoxflow_formulas_with_an_asymmetric_sector():
    centre = (4.0, 15.5)  # tilted sector: the 0-rad beam off the middle
    g = geometry("sin", centre_index=centre)
    for index in CORNERS:
        expected = sin_index_to_point(index, centre)
        np.testing.assert_allclose(g.index_to_world(index), expected, atol=1e-10)
        np.testing.assert_allclose(g.world_to_index(expected), sin_point_to_index(expected, centre), atol=1e-10)
        np.testing.assert_allclose(g.world_to_index(g.index_to_world(index)), index, atol=1e-10)


def test_conventions_agree_on_the_central_planes_only():
    tan, sin = geometry("tan"), geometry("sin")
    ce, ca = tan.centre_index
    central = np.array([[59, ce, 0], [59, ce, 24], [59, 0, ca], [59, 20, ca], [10, ce, ca]], dtype=float)
    np.testing.assert_allclose(tan.index_to_world(central), sin.index_to_world(central), atol=1e-9)
    # at the far corners (r = 100.5 mm, +-30 deg azimuth, +-30 deg elevation) they differ by millimetres
    corner = np.array([59, 20, 24], dtype=float)
    gap = np.linalg.norm(tan.index_to_world(corner) - sin.index_to_world(corner))
    assert 3.0 < gap < 10.0
    # the notes' figure: 6.0 mm at +-30/+-30 deg, 100 mm
    wide = dict(radius_sample_size=1.0, first_sample_distance=0.0, azimuth_angular_separation=math.radians(30),
                elevation_angular_separation=math.radians(30))
    t, s = (BeamGeometry((101, 3, 3), convention=c, **wide).index_to_world([100, 2, 2]) for c in ("tan", "sin"))
    assert np.linalg.norm(t - s) == pytest.approx(6.0, abs=0.05)


def test_probe_to_world_moves_the_sector_rigidly():
    angle = math.radians(35)
    m = np.eye(4)
    m[:3, :3] = [[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]]
    m[:3, 3] = [10.0, -20.0, 5.0]
    for convention in ("tan", "sin"):
        placed, probe = geometry(convention, probe_to_world=m), geometry(convention)
        for index in CORNERS:
            expected = m[:3, :3] @ probe.index_to_world(index) + m[:3, 3]
            np.testing.assert_allclose(placed.index_to_world(index), expected, atol=1e-10)
            np.testing.assert_allclose(placed.world_to_index(expected), index, atol=1e-9)


def test_outside_the_sector():
    g = geometry("tan")
    behind = g.world_to_index([[0.0, 0.0, -30.0]])
    assert np.isnan(behind).any()
    assert not g.contains([[0.0, 0.0, -30.0]])[0]
    assert not g.contains(g.index_to_world([[SHAPE[0] - 1 + 0.5, 3, 3]]))[0]
    assert not g.contains(g.index_to_world([[5, 3, -0.5]]))[0]
    assert g.contains(g.index_to_world(np.array(CORNERS))).all()


def test_jacobian_is_the_determinant_of_the_index_to_world_derivative():
    for convention in ("tan", "sin"):
        g = geometry(convention)
        for index in CORNERS:
            h = 1e-5
            columns = [(g.index_to_world(index + h * e) - g.index_to_world(index - h * e)) / (2 * h) for e in np.eye(3)]
            assert g.jacobian(index) == pytest.approx(abs(np.linalg.det(np.array(columns).T)), rel=1e-6)


def test_geometry_rejects_bad_input():
    with pytest.raises(ValueError, match="convention"):
        geometry("cos")
    with pytest.raises(ValueError, match="radius_sample_size"):
        BeamGeometry(SHAPE, 0.0, R0, DA, DE)
    with pytest.raises(ValueError, match="90 degrees"):
        BeamGeometry(SHAPE, DR, R0, math.radians(10), DE)
    with pytest.raises(ValueError, match="rigid"):
        geometry(probe_to_world=np.diag([2.0, 1, 1, 1]))
    with pytest.raises(ValueError, match="shape"):
        BeamGeometry((5, 1, 5), DR, R0, DA, DE)


# --- sampling ----------------------------------------------------------------------

def linear_in_index(g):
    """Samples that are an affine function of the index: trilinear
    interpolation in [r, e, a] reproduces it exactly at any point."""
    r, e, a = np.meshgrid(*[np.arange(n, dtype=float) for n in g.shape], indexing="ij")
    values = 2.0 * r - 3.0 * e + 0.5 * a + 7.0
    return values, lambda idx: 2.0 * idx[..., 0] - 3.0 * idx[..., 1] + 0.5 * idx[..., 2] + 7.0


@pytest.mark.parametrize("convention", ["tan", "sin"])
def test_sample_interpolates_in_beam_index(convention, rng):
    g = geometry(convention, centre_index=(9.0, 13.0))
    values, truth = linear_in_index(g)
    vol = BeamVolume(values, g)
    index = rng.uniform(0, 1, (500, 3)) * g.upper
    np.testing.assert_allclose(vol.sample(g.index_to_world(index)), truth(index), atol=1e-4)
    # nearest sample
    np.testing.assert_allclose(vol.sample(g.index_to_world(index), order=0), truth(np.rint(index)), atol=1e-4)
    # outside the sector, and touching a no-data sample
    assert np.isnan(vol.sample(g.index_to_world([[-0.5, 3, 3], [4, 3, SHAPE[2] - 0.5]]))).all()
    holed = BeamVolume(values, g, no_data_mask=(values == values[10, 10, 10]) & (np.indices(g.shape)[0] == 10))
    assert np.isnan(holed.sample(g.index_to_world([[10.5, 10.2, 10.7]])))
    assert np.isfinite(holed.sample(g.index_to_world([[12.5, 10.2, 10.7]])))


def test_beam_volume_validates():
    g = geometry()
    with pytest.raises(ValueError, match="does not match"):
        BeamVolume(np.zeros((4, 5, 6)), g)
    with pytest.raises(TypeError, match="BeamGeometry"):
        BeamVolume(np.zeros(SHAPE), None)
    with pytest.raises(ValueError, match="NaN"):
        BeamVolume(np.full(SHAPE, np.nan), g)


# --- scan conversion -------------------------------------------------------------------

def test_cartesian_grid_covers_the_sector():
    for convention in ("tan", "sin"):
        g = geometry(convention)
        grid = g.cartesian_grid()
        assert np.allclose(grid.spacing, g.default_spacing())
        lo = grid.index_to_world(np.zeros(3))
        hi = grid.index_to_world(np.array(grid.shape[::-1]) - 1.0)
        corners = g.index_to_world(np.array(CORNERS))
        assert np.all(corners >= lo - grid.spacing) and np.all(corners <= hi + grid.spacing)


@pytest.mark.parametrize("convention", ["tan", "sin"])
def test_scan_convert_marks_the_exact_sector(convention):
    g = geometry(convention)
    values, truth = linear_in_index(g)
    cart = scan_convert(BeamVolume(values, g), g.cartesian_grid(2.0))
    nz, ny, nx = cart.shape
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    world = cart.grid.index_to_world(np.stack([i, j, k], -1).reshape(-1, 3).astype(float))
    inside = g.contains(world).reshape(cart.shape)
    np.testing.assert_array_equal(~cart.no_data_mask, inside)
    np.testing.assert_allclose(cart.array[inside], truth(g.world_to_index(world))[inside.ravel()], atol=1e-3)


def test_to_beam_space_inverts_scan_conversion_of_a_smooth_image():
    g = geometry("tan")
    grid = g.cartesian_grid(0.5)
    cart = Volume(np.zeros(grid.shape), spacing=grid.spacing, origin=grid.origin)
    nz, ny, nx = grid.shape
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    world = grid.index_to_world(np.stack([i, j, k], -1).reshape(-1, 3).astype(float))
    # a function linear in world space: trilinear sampling of it is exact
    f = lambda w: 0.3 * w[..., 0] - 0.2 * w[..., 1] + 0.1 * w[..., 2]  # noqa: E731
    cart = Volume(f(world).reshape(grid.shape), spacing=grid.spacing, origin=grid.origin)
    beam = to_beam_space(cart, g)
    index = np.stack(np.meshgrid(*[np.arange(n, dtype=float) for n in g.shape], indexing="ij"), -1)
    ok = ~beam.no_data_mask if beam.no_data_mask is not None else np.ones(g.shape, bool)
    assert ok.mean() > 0.95
    np.testing.assert_allclose(beam.array[ok], f(g.index_to_world(index))[ok], atol=1e-3)


def test_scan_convert_default_grid_and_type_errors():
    g = BeamGeometry((20, 9, 9), 2.0, 10.0, math.radians(4), math.radians(4))
    vol = BeamVolume(np.ones(g.shape), g)
    cart = scan_convert(vol)
    assert cart.shape == vol.grid.shape and np.allclose(cart.origin, vol.grid.origin)
    assert np.allclose(cart.spacing, 29.0 * math.radians(4))  # the beams' spacing at mid depth (29 mm)
    with pytest.raises(TypeError):
        scan_convert(cart)
    with pytest.raises(TypeError):
        to_beam_space(vol, g)
    with pytest.raises(TypeError):
        scan_convert(vol, grid=(10, 10, 10))
    assert isinstance(vol.grid, ImageGrid)


class Ball:
    """A region with an exact volume: 4/3 pi R^3."""

    def __init__(self, centre, radius):
        self.centre, self.radius = np.asarray(centre, float), float(radius)

    def contains(self, world):
        return np.linalg.norm(np.asarray(world) - self.centre, axis=-1) <= self.radius


@pytest.mark.parametrize("convention", ["tan", "sin"])
def test_beam_mask_volume_with_the_jacobian(convention):
    g = BeamGeometry((140, 45, 45), 0.5, 20.0, math.radians(1.0), math.radians(1.0), convention=convention)
    # off the central planes: the conventions' cells differ there
    ball = Ball(g.index_to_world([70.0, 32.0, 12.0]), 9.0)
    mask = beam_mask(ball, g)
    exact = 4 / 3 * math.pi * 9.0**3 / 1000
    assert beam_mask_volume_ml(mask, g) == pytest.approx(exact, rel=0.005)
    # counting samples without the Jacobian is far off (cells grow with depth and angle)
    assert mask.sum() * 0.5 * math.radians(1) ** 2 / 1000 != pytest.approx(exact, rel=0.5)
    with pytest.raises(ValueError, match="not the geometry"):
        beam_mask_volume_ml(mask[1:], g)
