"""Following frames: the base ring's floor and the points that hold it open."""

import numpy as np

from spheroseg import Tracker
from spheroseg.geometry.coords import Pose, ProlateSpheroidal
from spheroseg.tracking.frames import (BASE_RING_MM, LEFT_BEHIND, RESEGMENT_MARGIN, WALL_SECTORS, base_ring_floor,
                                      base_ring_points, kept_candidate, left_behind, wall_motion_mm, wall_offsets,
                                      wall_sides)
from spheroseg.geometry.hermite import HermiteGrid
from spheroseg.surfaces.surface import Surface
from spheroseg.volumes.volume import ImageGrid, Volume

APEX, BASE = np.array([10.0, -5.0, 90.0]), np.array([12.0, 3.0, 15.0])


def test_the_floor_is_three_quarters_of_the_annulus_radius():
    assert base_ring_floor(None) == BASE_RING_MM[0]
    angles = np.linspace(0, 2 * np.pi, 7, endpoint=False)
    ring = BASE + 16.0 * np.stack([np.cos(angles), np.sin(angles), np.zeros(7)], axis=1)
    assert abs(base_ring_floor(ring) - 12.0) < 1e-12


def test_ring_points_lie_on_the_base_plane_at_the_floor():
    surface = Surface.from_apex_base(APEX, BASE)
    radii = surface.base_radii(32)
    assert base_ring_points(surface, float(radii.min()) - 0.1) is None
    floor = float(np.median(radii))
    points = base_ring_points(surface, floor)
    assert len(points) == np.count_nonzero(radii < floor) > 0
    local = surface.pose.to_local(points)
    np.testing.assert_allclose(local[:, 0], 0.0, atol=1e-9)  # the base plane
    np.testing.assert_allclose(np.hypot(local[:, 1], local[:, 2]), floor, rtol=1e-12)
    everywhere = base_ring_points(surface, float(radii.max()) + 1.0)
    assert len(everywhere) == 32


def step_image(surface: Surface, *, c_in: float, c_out: float) -> Volume:
    """A noise-free image on 1 mm voxels: ``c_in`` inside ``surface``,
    ``c_out`` outside."""
    grid = ImageGrid((100, 60, 60), origin=(-18.0, -27.0, 5.0))
    return Volume(np.where(surface.mask(grid), c_in, c_out), origin=grid.origin)


def test_the_wall_sides_read_blood_inside_and_wall_outside():
    """On the wall of a step image the inner band reads the blood's level
    (0) and the outer band the wall's (1), to the trilinear blur of the
    1 mm samples nearest the step.  Around a cavity drawn two thirds as
    wide (the base radius 15 mm against 23), the surface reads wall on both
    sides: the wall left behind."""
    offsets = wall_offsets(4.0)

    def sides_of(image):  # of the start surface, before any iteration
        tracker = Tracker(image, APEX, BASE)
        model = tracker.descent.model
        return wall_sides(tracker.samples_along_normals(offsets), offsets, model.v1, model.v2, model.grid.v2_range,
                          (20.0, 120.0))

    np.testing.assert_array_equal(offsets, [-1.0, -2.0, -3.0, -4.0, 1.0, 2.0, 3.0, 4.0])
    image = step_image(Surface.from_apex_base(APEX, BASE), c_in=20.0, c_out=120.0)
    sides = sides_of(image)
    assert sides.shape == (WALL_SECTORS[0] * WALL_SECTORS[1], 2)
    assert np.all(sides[:, 0] < 0.1) and np.all(sides[:, 1] > 0.9) and not left_behind(sides)
    smaller = step_image(Surface.from_apex_base(APEX, BASE, radius_ratio=0.2), c_in=20.0, c_out=120.0)
    behind = sides_of(smaller)
    assert np.all(behind[:, 0] > LEFT_BEHIND) and np.all(behind[:, 1] > 0.9) and left_behind(behind)


def test_a_sector_without_data_leaves_nothing_behind():
    sides = np.array([[0.0, 1.0], [np.nan, np.nan], [0.1, 0.8]])
    assert not left_behind(sides)
    assert left_behind(np.array([[0.0, 1.0], [0.0, LEFT_BEHIND - 0.01]]))  # blood on the outer side


def test_the_candidate_kept_is_the_stepped_one_unless_another_is_clearly_lower():
    margin = RESEGMENT_MARGIN * 100.0
    assert kept_candidate([-100.0, -100.0 - 0.9 * margin, -90.0]) == 0  # within the descent's noise
    assert kept_candidate([-100.0, -100.0 - 1.1 * margin, -90.0]) == 1
    assert kept_candidate([-100.0, -90.0, -120.0]) == 2
    # where the stepped wall was left behind, one on the wall wins whatever the energies
    assert kept_candidate([-100.0, -90.0, -80.0], on_wall=[1, 2]) == 1
    assert kept_candidate([-100.0, -90.0, -95.0], on_wall=[1, 2]) == 2


def test_the_wall_motion_of_two_confocal_half_spheroids():
    """Confocal half-spheroids ``lambda = l0`` and ``l1``: the volume
    between them over their walls' mean area (the analytic volumes and
    areas); for a thin step, between the distances of the two walls at
    the apex, ``d (cosh l1 - cosh l0)``, and at the equator, ``d (sinh l1
    - sinh l0)``."""
    d = 40.0
    system = ProlateSpheroidal(d)
    grid = HermiteGrid(8, 8, (0.0, np.pi / 2), poles=system.poles)

    def half_spheroid(l0):
        a, b = d * np.cosh(l0), d * np.sinh(l0)
        e = np.sqrt(1 - (b / a) ** 2)
        surface = Surface.from_function(system, Pose.from_apex_base(APEX, BASE), grid, l0)
        return surface, 2 / 3 * np.pi * a * b * b, np.pi * b**2 * (1 + a / (b * e) * np.arcsin(e))

    (inner, v0, a0), (outer, v1, a1) = half_spheroid(0.6), half_spheroid(0.7)
    expected = (v1 - v0) / ((a0 + a1) / 2)
    np.testing.assert_allclose(wall_motion_mm(inner, outer), expected, rtol=1e-6)
    assert wall_motion_mm(outer, inner) == wall_motion_mm(inner, outer)
    assert wall_motion_mm(inner, inner) == 0.0
    thin = half_spheroid(0.61)[0]
    at_apex, at_equator = d * (np.cosh(0.61) - np.cosh(0.6)), d * (np.sinh(0.61) - np.sinh(0.6))
    assert at_apex < wall_motion_mm(inner, thin) < at_equator
