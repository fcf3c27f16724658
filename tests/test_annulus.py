"""The mitral annulus followed from frame to frame (spheroseg.tracking.annulus)."""

import numpy as np
import pytest

from spheroseg.tracking.annulus import annulus_shift, basal_profile
from spheroseg.volumes.volume import Volume

SPACING = 1.0
SHAPE = (64, 48, 48)  # [z, y, x]
BASE = np.array([24.0, 24.0, 40.0])  # x, y, z (mm)
RING = 10.0  # base ring radius (mm)


def voxel_centres(shape=SHAPE, spacing=SPACING):
    z, y, x = np.meshgrid(*(np.arange(n) * spacing for n in shape), indexing="ij")
    return np.stack([x, y, z], axis=-1)  # world mm (origin 0, identity direction)


def annulus_image(axis, descent=0.0):
    """A basal region of revolution about ``axis`` through BASE: a bright
    ring (the annulus) at the base plane, a dimmer ring (the atrial wall) 12
    mm beyond it and a dark orifice between them, every structure moved by
    ``descent`` mm along ``axis`` (towards the apex: positive)."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    d = voxel_centres() - BASE
    z = d @ axis - descent  # height above the moved base plane, towards the apex
    r = np.linalg.norm(d - z[..., None] * axis - descent * axis, axis=-1)
    ring = 200 * np.exp(-((r - RING) ** 2 + z**2) / (2 * 2.5**2))
    wall = 90 * np.exp(-((r - 1.3 * RING) ** 2 + (z + 12) ** 2) / (2 * 3.0**2))
    ventricle = 40 / (1 + np.exp(-z / 2.0))  # the cavity side, a ramp of grey
    return Volume((20 + ring + wall + ventricle).astype(np.float32), spacing=(SPACING,) * 3)


def test_basal_profile_of_a_linear_image_is_its_value_on_the_axis():
    """The angle average of a linear field ``g . x`` over a ring about the
    axis is its value at the ring's centre (the ring's points sum to its
    centre): the profile is ``g . (base + z axis)`` at every radius, exactly
    (trilinear interpolation reproduces a linear field)."""
    gradient = np.array([0.7, -1.3, 2.1])
    image = Volume((voxel_centres() @ gradient).astype(np.float64), spacing=(SPACING,) * 3)
    axis = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])
    heights = np.linspace(-15, 5, 9)
    radii = np.array([0.3, 0.8, 1.2])
    profile = basal_profile(image, BASE, axis, RING, heights=heights, radii=radii, n_angles=12)
    assert profile.shape == (3, 9)
    expected = (BASE + heights[:, None] * axis) @ gradient
    np.testing.assert_allclose(profile, np.broadcast_to(expected, (3, 9)), atol=1e-9)


def test_basal_profile_is_nan_off_the_data_and_averages_what_is_on_it():
    image = Volume(np.ones(SHAPE, np.float32) * 7, spacing=(SPACING,) * 3)
    axis = np.array([0.0, 0.0, 1.0])
    # heights far below the image: no angle has data
    profile = basal_profile(image, BASE, axis, RING, heights=[-100.0, 0.0], radii=[0.5, 3.0])
    assert np.isnan(profile[:, 0]).all()
    assert profile[0, 1] == pytest.approx(7.0)
    # radius 30 mm from (24, 24): part of the ring is off the 48 mm image; the rest is averaged, not zero-filled
    assert profile[1, 1] == pytest.approx(7.0)


@pytest.mark.parametrize("descent", [6.4, -3.7, 11.3, 0.0])
@pytest.mark.parametrize("axis", [(0.0, 0.0, 1.0), (0.25, -0.15, 1.0)])
def test_annulus_shift_finds_a_translated_annulus(axis, descent):
    """The basal structures moved ``descent`` mm along the long axis are
    found ``descent`` mm away (positive: towards the apex), between the 1 mm
    samples of the search by its parabolic refinement."""
    axis = np.asarray(axis) / np.linalg.norm(axis)
    before, after = annulus_image(axis), annulus_image(axis, descent)
    shift = annulus_shift(before, after, BASE, axis, RING)
    assert shift == pytest.approx(descent, abs=0.1)


def test_annulus_shift_is_antisymmetric():
    axis = np.array([0.0, 0.0, 1.0])
    before, after = annulus_image(axis), annulus_image(axis, 4.5)
    forward = annulus_shift(before, after, BASE, axis, RING)
    # back from the moved frame, whose base plane is 4.5 mm nearer the apex
    backward = annulus_shift(after, before, BASE + 4.5 * axis, axis, RING)
    assert forward == pytest.approx(4.5, abs=0.25) and backward == pytest.approx(-4.5, abs=0.25)


def test_annulus_shift_without_data_is_zero():
    """With no profile to compare (the base far outside the image) the
    annulus is taken not to have moved."""
    image = annulus_image((0.0, 0.0, 1.0))
    assert annulus_shift(image, image, BASE + [500.0, 0.0, 0.0], [0.0, 0.0, 1.0], RING) == 0.0
