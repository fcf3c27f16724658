import numpy as np
import pytest

from spheroseg.geometry.coords import Pose, Spherical
from spheroseg.geometry.hermite import HermiteGrid
from spheroseg.surfaces.metrics import dice, ejection_fraction, mask_volume_ml, surface_distances
from spheroseg.surfaces.surface import Surface


def hemisphere(radius):
    system = Spherical()
    grid = HermiteGrid(8, 8, (0.0, np.pi / 2), poles=system.poles)
    s = Surface.from_function(system, Pose.from_apex_base([0, 0, 1.0], [0, 0, 0]), grid, radius)
    return s.mesh(128, 64, closed=False)


def test_dice():
    a = np.zeros((10, 10, 10), bool)
    b = np.zeros_like(a)
    a[:5] = True
    b[2:7] = True
    assert dice(a, b) == pytest.approx(2 * 300 / 1000)
    assert dice(a, a) == 1.0
    with pytest.raises(ValueError, match="shape"):
        dice(a, b[:5])


def test_surface_distance_of_concentric_hemispheres():
    d = surface_distances(hemisphere(20.0), hemisphere(23.0))
    # the rims are 3 mm apart too; the polygonal sphere sags by < 0.01 mm
    assert d["mean"] == pytest.approx(3.0, abs=0.1)
    assert d["hausdorff"] == pytest.approx(3.0, abs=0.15)


def test_ejection_fraction_and_volume():
    assert ejection_fraction(120.0, 50.0) == pytest.approx(58.333333)
    with pytest.raises(ValueError):
        ejection_fraction(0.0, 1.0)
    assert mask_volume_ml(np.ones((10, 10, 10), bool), (2.0, 1.0, 0.5)) == pytest.approx(1.0)


def test_vertices_no_face_uses_are_ignored():
    points, faces = hemisphere(20.0)
    stray = np.concatenate([points, [[500.0, 500.0, 500.0]]])
    assert surface_distances((stray, faces), hemisphere(20.0))["hausdorff"] < 0.2
