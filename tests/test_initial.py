"""The initial model: the points checked one line each, the pose and the start surface."""

import numpy as np
import pytest

from spheroseg.geometry.coords import Pose
from spheroseg.descent.dataterms import GlobalMeans
from spheroseg.tracking.initial import check_landmarks, fitted_start, initial_model, start_surface
from spheroseg.descent.options import SegmentOptions
from spheroseg.descent.stepper import schedule
from spheroseg.surfaces.surface import Surface
from spheroseg.volumes.volume import Volume

VOLUME = Volume(np.zeros((50, 50, 50)), spacing=(2.0, 2.0, 2.0))  # x, y, z from 0 to 98 mm
APEX, BASE = np.array([50.0, 50.0, 85.0]), np.array([50.0, 50.0, 20.0])
OPTIONS = SegmentOptions()
LEVELS = schedule(OPTIONS)


def test_apex_and_base_pose_the_half_ellipsoid():
    model = initial_model(VOLUME, APEX.tolist(), BASE, levels=LEVELS, options=OPTIONS)
    expected = Surface.from_apex_base(APEX, BASE, patches=LEVELS[0].patches)
    np.testing.assert_array_equal(model.surface.coefficients, expected.coefficients)
    np.testing.assert_array_equal(model.base, BASE)
    assert model.annulus is None and model.landmarks.shape == (0, 3) and model.levels == LEVELS


def test_the_annulus_poses_its_plane():
    annulus = BASE + np.array([[15.0, 0, 2], [0, 15, -1], [-15, 0, 2], [0, -15, -1]])
    model = initial_model(VOLUME, APEX, None, annulus=annulus, levels=LEVELS, options=OPTIONS)
    pose = Pose.from_annulus(APEX, annulus)
    np.testing.assert_allclose(model.base, pose.origin, atol=1e-12)
    # the base plane is the annulus points' least-squares plane: their mean offset from it is 0
    assert abs(np.mean(model.surface.pose.to_local(annulus)[:, 0])) < 1e-9
    np.testing.assert_array_equal(
        model.surface.coefficients,
        start_surface(APEX, None, annulus=annulus, options=OPTIONS, patches=LEVELS[0].patches).coefficients)


@pytest.mark.parametrize("annulus", [None, BASE + np.array([[15.0, 0, 2], [0, 15, -1], [-15, 0, 2], [0, -15, -1]])])
def test_the_fitted_start_holds_the_volume_asked_in_the_starts_frame(annulus):
    """The start's half-ellipsoid widened or narrowed to a volume: same
    system, pose and grid; its volume the one asked (the half-ellipsoid's
    ``2 pi h b^2 / 3``, to the Hermite interpolation's error); none where
    its base radius would reach its height."""
    start = start_surface(APEX, BASE, annulus=annulus, options=OPTIONS, patches=(8, 8))
    height = start.pose.to_local(APEX)[0]
    for ratio in (0.2, 0.4):
        volume_ml = 2 * np.pi * height * (ratio * height) ** 2 / 3 / 1000
        fitted = fitted_start(APEX, BASE, volume_ml, annulus=annulus, options=OPTIONS, patches=(8, 8))
        assert fitted.system == start.system and fitted.grid == start.grid
        np.testing.assert_allclose(fitted.pose.rotation, start.pose.rotation, atol=1e-12)
        np.testing.assert_allclose(fitted.pose.origin, start.pose.origin, atol=1e-12)
        assert abs(fitted.volume_ml() / volume_ml - 1) < 0.01, (ratio, fitted.volume_ml(), volume_ml)
        np.testing.assert_allclose(fitted.tip(), APEX, atol=0.05)
    # a base radius 1.1 times the height: no half-ellipsoid of the family
    assert fitted_start(APEX, BASE, 2 * np.pi * height * (1.1 * height) ** 2 / 3 / 1000, annulus=annulus,
                        options=OPTIONS, patches=(8, 8)) is None


@pytest.mark.parametrize("args, kwargs, error, match", [
    ((APEX + 200, BASE), {}, ValueError, r"^apex \(.*\) lies outside the image"),
    ((APEX, [1.0, np.nan, 2.0]), {}, ValueError, "^base must be 3 finite numbers"),
    ((APEX, None), {}, ValueError, "^give the base point"),
    ((APEX, APEX), {}, ValueError, "^apex and base must be distinct"),
    ((APEX, APEX + [0, 0, 0.001]), {}, ValueError, r"^apex and base are 0.001 mm apart: they are the ends"),
    ((APEX, BASE), {"init": "surface"}, TypeError, "^init must be a spheroseg.Surface"),
    ((APEX, BASE), {"landmarks": [[1.0, 2.0, 300.0]]}, ValueError, r"^landmark 0 \("),
    ((APEX, BASE), {"levels": ()}, TypeError, "^levels must be"),
    ((APEX, BASE), {"levels": [((2, 2), GlobalMeans, 5, 0.1)]}, TypeError, "^levels must be"),
])
def test_bad_points_fail_in_one_line(args, kwargs, error, match):
    kwargs = {"levels": LEVELS, **kwargs}
    with pytest.raises(error, match=match) as info:
        initial_model(VOLUME, *args, options=OPTIONS, **kwargs)
    assert "\n" not in str(info.value)


def test_landmarks_are_points():
    assert check_landmarks(VOLUME, [[10.0, 20.0, 30.0], [40, 50, 60]]).shape == (2, 3)
    with pytest.raises(ValueError, match="^landmarks must be points"):
        check_landmarks(VOLUME, [[1.0, 2.0]])
