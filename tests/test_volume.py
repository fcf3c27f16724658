import numpy as np
import pytest

from spheroseg.volumes.volume import Volume, outside_sector


def affine_volume():
    rng = np.random.default_rng(3)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    direction = q * np.sign(np.linalg.det(q))
    shape = (9, 11, 13)  # z, y, x
    k, j, i = np.meshgrid(*(np.arange(n) for n in shape), indexing="ij")
    values = 2.0 * i - 3.0 * j + 0.5 * k + 7.0  # linear in the index: trilinear is exact
    return Volume(values, spacing=(0.7, 1.1, 1.3), origin=(5.0, -2.0, 10.0), direction=direction)


def test_world_index_round_trip(rng):
    vol = affine_volume()
    idx = rng.uniform(0, 8, size=(50, 3))
    np.testing.assert_allclose(vol.world_to_index(vol.index_to_world(idx)), idx, atol=1e-10)


def test_trilinear_is_exact_for_linear_images(rng):
    vol = affine_volume()
    idx = rng.uniform(0, 1, size=(200, 3)) * [12, 10, 8]
    expected = 2.0 * idx[:, 0] - 3.0 * idx[:, 1] + 0.5 * idx[:, 2] + 7.0
    np.testing.assert_allclose(vol.sample(vol.index_to_world(idx)), expected, atol=1e-4)
    # voxel centres give the voxels, including the last ones
    corner = np.array([[12.0, 10.0, 8.0]])
    assert vol.sample(vol.index_to_world(corner))[0] == pytest.approx(vol.array[8, 10, 12])


def test_outside_is_fill_value():
    vol = affine_volume()
    out = vol.index_to_world(np.array([[-0.01, 0, 0], [0, 10.01, 0], [0, 0, 100]]))
    assert np.all(np.isnan(vol.sample(out)))
    assert np.all(vol.sample(out, fill_value=-1.0) == -1.0)
    # points in and out along each axis: the fill exactly where contains() says out
    rng = np.random.default_rng(1)
    points = vol.index_to_world(rng.uniform(-1, 1, (300, 3)) * 2 + rng.choice([0.0, 4.0, 8.0, 12.0], (300, 3)))
    for order in (0, 1):
        np.testing.assert_array_equal(np.isnan(vol.sample(points, order=order)), ~vol.contains(points))


def test_no_data_value_marks_missing_samples():
    a = np.full((4, 4, 4), 50.0)
    a[:, :, 0] = 0
    vol = Volume(a, no_data_value=0)
    s = vol.sample(np.array([[0.5, 1, 1], [2.0, 1, 1], [1.0, 1, 1]]))
    assert np.isnan(s[0]) and s[1] == 50.0 and s[2] == 50.0


@pytest.mark.parametrize(
    "array, kwargs, message",
    [
        (np.zeros((4, 4)), {}, "3D"),
        (np.zeros((2, 4, 4, 4)), {}, "3D"),
        (np.full((4, 4, 4), np.nan), {}, "NaN"),
        (np.full((4, 4, 4), 1e39), {}, "infinite"),  # beyond float32
        (np.full((4, 4, 4), -np.inf, np.float32), {}, "infinite"),
        # one bad voxel among finite ones, at either extreme
        (np.where(np.arange(64).reshape(4, 4, 4) == 37, np.nan, 1.0), {}, "NaN"),
        (np.where(np.arange(64).reshape(4, 4, 4) == 37, np.inf, -1.0), {}, "infinite"),
        (np.where(np.arange(64).reshape(4, 4, 4) == 37, -np.inf, 1.0), {}, "infinite"),
        (np.zeros((4, 4, 4)), {"spacing": (1, 0, 1)}, "spacing"),
        (np.zeros((4, 4, 4)), {"direction": np.zeros((3, 3))}, "direction"),
        (np.zeros((1, 4, 4)), {}, "at least 2"),
    ],
)
def test_bad_volumes(array, kwargs, message):
    with pytest.raises(ValueError, match=message):
        Volume(array, **kwargs)


def test_outside_sector_is_the_padding_not_the_blood():
    from spheroseg.volumes.volume import outside_sector

    a = np.full((30, 30, 30), 80.0)
    a[:, :, :6] = 0  # padding touching the faces
    a[12:18, 12:18, 12:18] = 0  # a noise-free blood pool: zero but enclosed
    mask = outside_sector(a)
    assert mask[:, :, :6].all() and not mask[12:18, 12:18, 12:18].any() and mask.sum() == 30 * 30 * 6
    assert outside_sector(np.full((10, 10, 10), 5.0)) is None
    vol = Volume(a, no_data_mask=mask)
    assert np.isnan(vol.sample(np.array([[2.0, 15, 15]])))[0]  # x = 2: padding
    assert vol.sample(np.array([[15.0, 15, 15]]))[0] == 0.0  # the pool is data


def test_integer_volumes_are_their_values_in_float32():
    a = np.array([0, 255, 2**31 - 1, -(2**31)], np.int64).repeat(16).reshape(4, 4, 4)
    v = Volume(a)
    assert v.array.dtype == np.float32 and np.array_equal(v.array, a.astype(np.float32))


@pytest.mark.parametrize("direction", [2 * np.eye(3), [[1, 0.3, 0], [0, 1, 0], [0, 0, 1]], np.diag([1, 1, np.nan])])
def test_a_direction_that_is_not_orthonormal_is_refused_with_the_matrix(direction):
    """A scaled direction (round 4: TransformMatrix = 2 0 0 0 2 0 0 0 2 gave
    1331 mL, 8 times the volume) or a sheared one scales the volumes
    silently; a reflection is a direction."""
    with pytest.raises(ValueError, match=r"direction matrix \[.*\] is not orthonormal"):
        Volume(np.zeros((4, 4, 4)), direction=direction)
    Volume(np.zeros((4, 4, 4)), direction=np.diag([1.0, -1.0, 1.0]))
    with pytest.raises(ValueError, match=r"origin must be 3 finite numbers within"):
        Volume(np.zeros((4, 4, 4)), origin=(0.0, np.nan, 0.0))


def test_a_scaled_direction_in_a_file_is_refused(tmp_path):
    import SimpleITK as sitk

    from spheroseg.io import load

    image = sitk.GetImageFromArray(np.zeros((4, 5, 6), np.float32))
    image.SetDirection((2.0, 0, 0, 0, 2.0, 0, 0, 0, 2.0))
    sitk.WriteImage(image, str(tmp_path / "scaled.mha"))
    with pytest.raises(ValueError, match=r"\[2 0 0; 0 2 0; 0 0 2\] is not orthonormal"):
        load(tmp_path / "scaled.mha", no_data_value=None)


def test_a_volume_from_an_array_finds_its_sector_as_load_does(tmp_path, monkeypatch):
    # one volume whatever its origin: the same voxels from an array and from
    # a file have the same no-data (the sector padding), the same samples,
    # the same repr and the same segmentation
    import SimpleITK as sitk

    import spheroseg
    from spheroseg.synthetic.phantom import make_phantom

    ph = make_phantom(seed=3, spacing=3.0)
    array = ph.volume.array.astype(np.uint8)
    assert (array == 0).mean() > 0.05  # the phantom's conical sector has padding
    image = sitk.GetImageFromArray(array)
    image.SetSpacing(tuple(ph.volume.spacing))
    image.SetOrigin(tuple(ph.volume.origin))
    sitk.WriteImage(image, str(tmp_path / "case.mha"))
    searched = []

    def counted(values, **kwargs):
        searched.append(values.shape)
        return outside_sector(values, **kwargs)

    monkeypatch.setattr("spheroseg.volumes.volume.outside_sector", counted)
    loaded = spheroseg.load(tmp_path / "case.mha")
    built = Volume(array, spacing=ph.volume.spacing, origin=ph.volume.origin)
    assert searched == []  # searched when first needed, not by load or the constructor
    expected = outside_sector(array)
    for volume in (loaded, built):
        np.testing.assert_array_equal(volume.no_data_mask, expected)
        np.testing.assert_array_equal(volume.no_data_mask, expected)
    assert len(searched) == 2  # once each, then kept
    assert repr(built) == repr(loaded) and "sector padding" in repr(built)
    assert "no_data='none'" in repr(Volume(array, spacing=ph.volume.spacing, no_data_value=None))
    points = ph.volume.index_to_world(np.random.default_rng(0).uniform(0, 20, (500, 3)))
    np.testing.assert_array_equal(built.sample(points), loaded.sample(points))
    assert np.isnan(built.sample(points)).any()  # some of them in the padding
    results = [spheroseg.segment(v, ph.apex, ph.base, threads=1) for v in (built, loaded)]
    assert results[0].volume_ml == results[1].volume_ml
    unmasked = spheroseg.segment(Volume(array, spacing=ph.volume.spacing, origin=ph.volume.origin,
                                        no_data_value=None), ph.apex, ph.base, threads=1)
    assert unmasked.volume_ml != results[0].volume_ml  # the padding changes the result: the check can fail


def test_auto_with_a_mask_takes_the_mask_and_a_bad_keyword_is_refused():
    a = np.full((6, 6, 6), 50.0)
    a[:, :, 0] = 0
    mask = np.zeros(a.shape, bool)
    mask[0] = True
    vol = Volume(a, no_data_mask=mask)
    np.testing.assert_array_equal(vol.no_data_mask, mask)
    assert "mask, 16.7% of voxels" in repr(vol)
    np.testing.assert_array_equal(Volume(a).no_data_mask, a == 0)
    with pytest.raises(ValueError, match="no_data_value must be a number, None or 'auto', got 'sector'"):
        Volume(a, no_data_value="sector")
