"""Following frames: the base ring's floor and the points that hold it open."""

import numpy as np

from spheroseg.frames import BASE_RING_MM, base_ring_floor, base_ring_points
from spheroseg.surface import Surface

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
