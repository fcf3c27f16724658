"""Reading and writing images (spheroseg.io.images): geometry through the
file formats, the files an image reads, the memory budget.

Reading files SimpleITK wrote (every format, DICOM, 3D+t, .seq.nrrd, bad
files, the sector padding, a .raw larger than its header) is
tests/test_io.py's; beam-space files are tests/test_beam_io.py's."""

import numpy as np
import pytest
import SimpleITK as sitk

from spheroseg.io.images import (
    BUDGET_VARIABLE, ImageFileError, check_image_size, image_files, image_format, load, load_frames, load_sequence,
    save_mask, save_volume,
)
from spheroseg.volumes.volume import ImageGrid, Volume


def rotation(axis, angle):
    """Rodrigues' rotation matrix."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


OBLIQUE = rotation([0.3, -1.0, 0.7], 0.61)
SPACING = (0.3127, 0.81, 1.123456789)
ORIGIN = (-12.3456789, 7.1, 0.017)
#: geometry NIfTI keeps exactly: it stores spacing, origin and direction as float32
NIFTI_SPACING, NIFTI_ORIGIN = (0.5, 0.75, 1.25), (-12.25, 7.5, 0.125)
NIFTI_DIRECTION = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def volume(rng, shape=(3, 4, 5), **geometry):
    return Volume(rng.normal(size=shape).astype(np.float32), **geometry)


def assert_same_geometry(got, expected, atol=1e-9):
    np.testing.assert_allclose(got.spacing, expected.spacing, rtol=0, atol=atol)
    np.testing.assert_allclose(got.origin, expected.origin, rtol=0, atol=atol)
    np.testing.assert_allclose(got.direction, expected.direction, rtol=0, atol=atol)


@pytest.mark.parametrize("suffix", [".mha", ".mhd", ".nrrd", ".nhdr"])
def test_save_then_load_keeps_an_oblique_geometry(tmp_path, rng, suffix):
    original = volume(rng, spacing=SPACING, origin=ORIGIN, direction=OBLIQUE)
    save_volume(tmp_path / f"v{suffix}", original)
    back = load(tmp_path / f"v{suffix}", no_data_value=None)
    np.testing.assert_array_equal(back.array, original.array)
    assert_same_geometry(back, original)
    # the voxel's world position is SimpleITK's, for the file as written
    image = sitk.ReadImage(str(tmp_path / f"v{suffix}"))
    index = (3.5, 1.25, 2.0)
    np.testing.assert_allclose(back.index_to_world([index])[0], image.TransformContinuousIndexToPhysicalPoint(index),
                               rtol=0, atol=1e-9)


def test_nifti_keeps_float32_geometry_exactly_and_others_to_float32(tmp_path, rng):
    exact = volume(rng, spacing=NIFTI_SPACING, origin=NIFTI_ORIGIN, direction=NIFTI_DIRECTION)
    save_volume(tmp_path / "v.nii.gz", exact)
    back = load(tmp_path / "v.nii.gz", no_data_value=None)
    np.testing.assert_array_equal(back.array, exact.array)
    assert_same_geometry(back, exact)
    oblique = volume(rng, spacing=SPACING, origin=ORIGIN, direction=OBLIQUE)
    save_volume(tmp_path / "o.nii.gz", oblique)
    assert_same_geometry(load(tmp_path / "o.nii.gz", no_data_value=None), oblique, atol=1e-6)


def test_npy_is_the_array_indexed_z_y_x_with_the_spacing_given(tmp_path, rng):
    array = rng.normal(size=(3, 4, 5)).astype(np.float32)
    np.save(tmp_path / "v.npy", array)
    back = load(tmp_path / "v.npy", spacing=(0.5, 0.6, 0.7), no_data_value=None)
    np.testing.assert_array_equal(back.array, array)
    np.testing.assert_array_equal(back.spacing, (0.5, 0.6, 0.7))
    np.testing.assert_array_equal(back.origin, 0.0)
    np.testing.assert_array_equal(back.direction, np.eye(3))
    # index (x, y, z) = (4, 3, 2) is array[2, 3, 4], at (4 * 0.5, 3 * 0.6, 2 * 0.7) mm
    np.testing.assert_allclose(back.index_to_world([[4, 3, 2]])[0], [2.0, 1.8, 1.4], rtol=1e-15)
    assert back.sample(np.array([[2.0, 1.8, 1.4]]))[0] == array[2, 3, 4]
    with pytest.raises(ValueError, match=r"v\.npy: \.npy keeps no geometry; write \.mha or \.nrrd"):
        save_volume(tmp_path / "v.npy", back)


def test_the_spacing_given_overrides_the_file_and_keeps_the_rest(tmp_path, rng):
    original = volume(rng, spacing=SPACING, origin=ORIGIN, direction=OBLIQUE)
    save_volume(tmp_path / "v.mha", original)
    back = load(tmp_path / "v.mha", spacing=(2.0, 3.0, 4.0), no_data_value=None)
    np.testing.assert_array_equal(back.spacing, (2.0, 3.0, 4.0))
    np.testing.assert_allclose(back.origin, ORIGIN, rtol=0, atol=1e-12)
    np.testing.assert_allclose(back.direction, OBLIQUE, rtol=0, atol=1e-12)


@pytest.mark.parametrize("suffix", [".mha", ".nrrd", ".nii.gz"])
def test_a_sequence_is_one_4d_file_time_last_and_reads_back_as_frames(tmp_path, rng, suffix):
    geometry = ({"spacing": NIFTI_SPACING, "origin": NIFTI_ORIGIN, "direction": NIFTI_DIRECTION}
                if suffix == ".nii.gz" else {"spacing": SPACING, "origin": ORIGIN, "direction": OBLIQUE})
    frames = [volume(rng, **geometry) for _ in range(3)]
    save_volume(tmp_path / f"cine{suffix}", frames)
    image = sitk.ReadImage(str(tmp_path / f"cine{suffix}"))
    assert image.GetDimension() == 4 and image.GetSize() == (5, 4, 3, 3)
    for back in (load_sequence(tmp_path / f"cine{suffix}", no_data_value=None),
                 load_frames(tmp_path / f"cine{suffix}", no_data_value=None)):
        assert len(back) == 3
        for got, expected in zip(back, frames):
            np.testing.assert_array_equal(got.array, expected.array)
            assert_same_geometry(got, expected)


def test_save_volume_writes_no_data_as_zero(tmp_path):
    array = np.full((2, 3, 4), 5.0, np.float32)
    mask = np.zeros(array.shape, bool)
    mask[0, 1, 2] = mask[1, 0, 0] = True
    save_volume(tmp_path / "v.mha", Volume(array, no_data_mask=mask))
    written = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "v.mha")))
    np.testing.assert_array_equal(written, np.where(mask, 0.0, 5.0))


def test_save_volume_checks_its_input(tmp_path, rng):
    with pytest.raises(TypeError, match="save_volume takes a Volume, a BeamVolume or a non-empty list"):
        save_volume(tmp_path / "v.mha", np.zeros((2, 2, 2)))
    with pytest.raises(TypeError, match="non-empty list"):
        save_volume(tmp_path / "v.mha", [])
    with pytest.raises(ValueError, match="the frames of a sequence must all be of one kind and one shape"):
        save_volume(tmp_path / "v.mha", [volume(rng), volume(rng, shape=(3, 4, 6))])
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("suffix", [".mha", ".nii.gz", ".nrrd"])
def test_save_mask_is_uint8_on_its_grid(tmp_path, rng, suffix):
    grid = ImageGrid((3, 4, 5), spacing=NIFTI_SPACING, origin=NIFTI_ORIGIN, direction=NIFTI_DIRECTION)
    mask = rng.random(grid.shape) > 0.5
    save_mask(tmp_path / f"m{suffix}", mask, grid)
    image = sitk.ReadImage(str(tmp_path / f"m{suffix}"))
    assert image.GetPixelID() == sitk.sitkUInt8
    np.testing.assert_array_equal(sitk.GetArrayFromImage(image), mask)
    np.testing.assert_allclose(image.GetSpacing(), NIFTI_SPACING, rtol=0, atol=1e-9)
    np.testing.assert_allclose(image.GetOrigin(), NIFTI_ORIGIN, rtol=0, atol=1e-9)
    np.testing.assert_allclose(image.GetDirection(), NIFTI_DIRECTION.ravel(), rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match=r"the mask's shape \(3, 4, 6\) is not its grid's \(3, 4, 5\)"):
        save_mask(tmp_path / "bad.mha", np.zeros((3, 4, 6), bool), grid)
    assert not (tmp_path / "bad.mha").exists()


@pytest.mark.parametrize("name, suffix", [("a.mha", ".mha"), ("A.NII.GZ", ".nii.gz"), ("b.nii", ".nii"),
                                          ("cine.Seq.Nrrd", ".seq.nrrd"), ("x.nrrd", ".nrrd"), ("dir.v1/none", ""),
                                          ("p.mrk.json", ".json")])
def test_image_format(name, suffix):
    assert image_format(name) == suffix


def test_image_files_are_the_files_an_image_reads(tmp_path, rng):
    v = volume(rng)
    save_volume(tmp_path / "a.mhd", v)  # a.mhd and a.zraw (compressed)
    save_volume(tmp_path / "b.nhdr", v)  # b.nhdr and b.raw.gz
    save_volume(tmp_path / "c.mha", v)
    assert image_files(str(tmp_path / "a.mhd")) == [tmp_path / "a.mhd", tmp_path / "a.zraw"]
    assert image_files(str(tmp_path / "b.nhdr")) == [tmp_path / "b.nhdr", tmp_path / "b.raw.gz"]
    assert image_files(str(tmp_path / "c.mha")) == [tmp_path / "c.mha"]
    assert image_files(str(tmp_path / "missing.mhd")) == [tmp_path / "missing.mhd"]
    # a glob's matches in name order, each with its data file once
    assert image_files(str(tmp_path / "[ab].*"), glob=True) == [tmp_path / n for n in ("a.mhd", "a.zraw", "b.nhdr",
                                                                                      "b.raw.gz")]
    assert image_files(str(tmp_path / "[ab].*")) == [tmp_path / "[ab].*"]  # a name is a name unless asked
    (tmp_path / "frames" / "deep").mkdir(parents=True)
    save_volume(tmp_path / "frames" / "f0.mha", v)
    save_volume(tmp_path / "frames" / "deep" / "f1.mha", v)
    assert image_files(str(tmp_path / "frames")) == [tmp_path / "frames" / "deep" / "f1.mha",
                                                     tmp_path / "frames" / "f0.mha"]


def test_check_image_size_at_the_budget(monkeypatch):
    from spheroseg.io.images import VOXEL_BYTES

    monkeypatch.setenv(BUDGET_VARIABLE, str(600000 * VOXEL_BYTES / 1e9))  # 600000 voxels as a volume holds them
    check_image_size("v.mha", (100, 100, 60))  # exactly the budget
    check_image_size("v.mha", (100, 100, 20), components=3)
    with pytest.raises(ImageFileError, match=rf"^v\.mha: declares 100 x 100 x 61 voxels, .*{VOXEL_BYTES} bytes a "
                                             r"voxel.*over the memory budget of .* \(set SPHEROSEG_MAX_IMAGE_GB"):
        check_image_size("v.mha", (100, 100, 61))
    with pytest.raises(ImageFileError, match=r"100 x 100 x 20 x 4 components voxels"):
        check_image_size("v.mha", (100, 100, 20), components=4)
    for bad in ("0", "-1", "inf", "nan"):
        monkeypatch.setenv(BUDGET_VARIABLE, bad)
        with pytest.raises(ValueError, match=f"^SPHEROSEG_MAX_IMAGE_GB must be a positive number of GB, got '{bad}'$"):
            check_image_size("v.mha", (1, 1, 1))
    monkeypatch.setenv(BUDGET_VARIABLE, " ")  # blank: the default, 4 GB
    most = int(4e9 // VOXEL_BYTES) // 10 ** 6
    check_image_size("v.mha", (1000, 1000, most))
    with pytest.raises(ImageFileError, match="over the memory budget of 4 GB"):
        check_image_size("v.mha", (1000, 1000, most + 1))
