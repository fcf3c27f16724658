import numpy as np
import pytest

from spheroseg.phantom import FAMILIES, make_phantom, make_sequence
from spheroseg.surface import signed_volume


@pytest.fixture(scope="module")
def phantom():
    return make_phantom(seed=5)


def test_truth_volume_matches_mask(phantom):
    voxels = phantom.truth_mask.sum() * np.prod(phantom.volume.spacing) / 1000
    # voxelisation at 1 mm of a ~15000 mm^2 wall: well under 1 %
    assert abs(voxels - phantom.truth_volume_ml) < 0.01 * phantom.truth_volume_ml


def test_truth_mesh_encloses_truth_volume(phantom):
    points, faces = phantom.truth_mesh
    # with the origin on the base plane the missing flat cap adds nothing to
    # the divergence-theorem volume
    vol = abs(signed_volume(points - phantom.base, faces)) / 1000
    np.testing.assert_allclose(vol, phantom.truth_volume_ml, rtol=5e-3)


def test_apex_and_base_are_on_the_truth(phantom):
    assert phantom.volume.contains(phantom.apex) and phantom.volume.contains(phantom.base)
    d = np.linalg.norm(phantom.truth_mesh[0] - phantom.apex, axis=1).min()
    assert d < 1e-6


def test_image_looks_like_apical_echo(phantom):
    a = phantom.volume.array
    assert a.dtype == np.float32 and a.min() == 0 and a.max() <= 255
    assert (a == 0).mean() > 0.2, "the black outside of the sector"
    blood = np.median(a[phantom.truth_mask])
    assert blood < np.median(a[(a > 0) & ~phantom.truth_mask]), "blood is dark"


def test_deterministic():
    a = make_phantom(seed=9, spacing=2.0)
    b = make_phantom(seed=9, spacing=2.0)
    np.testing.assert_array_equal(a.volume.array, b.volume.array)
    c = make_phantom(seed=10, spacing=2.0)
    assert not np.array_equal(a.volume.array.shape, c.volume.array.shape) or not np.array_equal(a.volume.array, c.volume.array)


def test_sequence_volume_curve():
    seq = make_sequence(seed=2, n_frames=4, spacing=2.5)
    v = seq.truth_volumes_ml
    assert np.argmax(v) == 0 and np.argmin(v) == 2
    assert 45 < seq.truth_ef < 65


def test_families_exist():
    assert {"clean", "speckle", "dropout", "clutter", "low_contrast", "tilted"} <= set(FAMILIES)
