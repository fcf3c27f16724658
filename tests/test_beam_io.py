"""Beam-space files: ITK's PhasedArray3DSpecialCoordinatesImage keys in .mha/.nrrd."""

import math

import numpy as np
import pytest
import SimpleITK as sitk

from spheroseg.volumes.beamspace import BeamGeometry, BeamVolume, scan_convert
from spheroseg.io import (BEAM_KEYS, ImageFileError, beam_geometry_from_header, beam_header, load, load_sequence,
                          save_mask, save_volume)

POSE = np.array([[0.0, -1.0, 0.0, 12.5], [1.0, 0.0, 0.0, -3.0], [0.0, 0.0, 1.0, 40.0], [0, 0, 0, 1]])


def beam(convention="sin", seed=0, no_data_value=None):
    g = BeamGeometry((24, 9, 13), 0.7, 4.0, math.radians(2.0), math.radians(2.5), convention=convention,
                     centre_index=(3.0, 7.5), probe_to_world=POSE)
    values = np.random.default_rng(seed).uniform(1, 200, g.shape)
    return BeamVolume(values, g, no_data_value=no_data_value)


@pytest.mark.parametrize("suffix", [".mha", ".nrrd"])
def test_single_frame_round_trip(suffix, tmp_path):
    vol = beam(no_data_value=0.0)
    save_volume(tmp_path / f"b{suffix}", vol)
    back = load(tmp_path / f"b{suffix}")
    assert isinstance(back, BeamVolume)
    assert back.geometry == vol.geometry
    np.testing.assert_array_equal(back.array, vol.array)
    assert back.no_data_value == 0.0
    # the header as ITK sees it: array [r, e, a] is ITK size (a, e, r)
    image = sitk.ReadImage(str(tmp_path / f"b{suffix}"))
    assert image.GetSize() == vol.shape[::-1]
    assert float(image.GetMetaData("AzimuthAngularSeparation")) == vol.geometry.azimuth_angular_separation
    assert float(image.GetMetaData("RadiusSampleSize")) == 0.7
    assert image.GetOrigin() == (0.0, 0.0, 0.0) and image.GetSpacing() == (1.0, 1.0, 1.0)


@pytest.mark.parametrize("suffix", [".mha", ".nrrd"])
def test_sequence_round_trip(suffix, tmp_path):
    frames = [beam(seed=k) for k in range(3)]
    save_volume(tmp_path / f"s{suffix}", frames)
    back = load_sequence(tmp_path / f"s{suffix}")
    assert len(back) == 3 and all(isinstance(b, BeamVolume) for b in back)
    for a, b in zip(frames, back):
        assert b.geometry == a.geometry
        np.testing.assert_array_equal(b.array, a.array)
    with pytest.raises(ValueError, match="3D\\+t"):
        load(tmp_path / f"s{suffix}")
    # a folder of single frames is a sequence too
    (tmp_path / "frames").mkdir()
    for k, f in enumerate(frames):
        save_volume(tmp_path / "frames" / f"f{k}{suffix}", f)
    assert [b.geometry for b in load_sequence(tmp_path / "frames")] == [f.geometry for f in frames]


def test_itk_defaults_when_only_the_four_keys_are_given(tmp_path):
    array = np.arange(5 * 4 * 6, dtype=np.float32).reshape(5, 4, 6)
    image = sitk.GetImageFromArray(array)
    for key, value in zip(BEAM_KEYS, ("0.05", "0.04", "0.5", "2")):
        image.SetMetaData(key, value)
    sitk.WriteImage(image, str(tmp_path / "itk.mha"))
    vol = load(tmp_path / "itk.mha")
    g = vol.geometry
    assert (g.convention, g.centre_index) == ("tan", (1.5, 2.5))
    np.testing.assert_array_equal(g.probe_to_world, np.eye(4))
    assert vol.no_data_value is None
    assert (g.azimuth_angular_separation, g.elevation_angular_separation, g.radius_sample_size,
            g.first_sample_distance) == (0.05, 0.04, 0.5, 2.0)


def header(**changes):
    keys = beam_header(beam().geometry)
    for k, v in changes.items():
        if v is None:
            keys.pop(k)
        else:
            keys[k] = v
    return keys


@pytest.mark.parametrize("changes, pattern", [
    (dict(RadiusSampleSize=None), "missing RadiusSampleSize"),
    (dict(AzimuthAngularSeparation=None, FirstSampleDistance=None), "missing AzimuthAngularSeparation, FirstSample"),
    (dict(AzimuthAngularSeparation="wide"), "AzimuthAngularSeparation must be a number"),
    (dict(RadiusSampleSize="-1"), "radius_sample_size must be a positive"),
    (dict(BeamSpaceConvention="cos"), "BeamSpaceConvention must be one of"),
    (dict(AzimuthCenterIndex=None), "both ElevationCenterIndex and AzimuthCenterIndex"),
    (dict(ProbeToWorldTransform="1 0 0"), "ProbeToWorldTransform must be 16 numbers"),
    (dict(ProbeToWorldTransform=" ".join(["2"] + ["0"] * 14 + ["1"])), "rigid"),
    (dict(AzimuthAngularSeparation="0.3"), "90 degrees"),
])
def test_missing_or_contradictory_keys(changes, pattern):
    with pytest.raises(ImageFileError, match=pattern) as info:
        beam_geometry_from_header(header(**changes), (24, 9, 13), source="f.mha")
    assert str(info.value).startswith("f.mha: ") and "\n" not in str(info.value)


def test_optional_keys_alone_are_an_error_and_no_keys_a_cartesian_image(tmp_path):
    with pytest.raises(ImageFileError, match="needs AzimuthAngularSeparation"):
        beam_geometry_from_header({"BeamSpaceConvention": "sin"}, (4, 4, 4))
    assert beam_geometry_from_header({"Modality": "US"}, (4, 4, 4)) is None
    image = sitk.GetImageFromArray(np.ones((4, 5, 6), np.float32))
    for key, value in beam_header(beam().geometry).items():
        image.SetMetaData(key, value)
    image.SetOrigin((1.0, 0.0, 0.0))
    sitk.WriteImage(image, str(tmp_path / "moved.mha"))
    with pytest.raises(ImageFileError, match="offset 0, spacing 1 and identity direction"):
        load(tmp_path / "moved.mha")


def test_writing_checks_its_input(tmp_path):
    vol = beam()
    with pytest.raises(ValueError, match="keeps its header"):
        save_volume(tmp_path / "b.nii.gz", vol)
    with pytest.raises(ValueError, match="share one geometry"):
        save_volume(tmp_path / "b.mha", [vol, beam("tan")])
    with pytest.raises(TypeError):
        save_volume(tmp_path / "b.mha", vol.array)
    save_volume(tmp_path / "b.mha", vol)
    with pytest.raises(ValueError, match="no voxel spacing"):
        load(tmp_path / "b.mha", spacing=(1, 1, 1))


def test_scan_converted_volume_and_world_mask_files(tmp_path):
    vol = beam()
    cartesian = scan_convert(vol)
    save_volume(tmp_path / "c.nii.gz", cartesian)
    back = load(tmp_path / "c.nii.gz")  # no_data_value "auto": the zeros round the sector
    np.testing.assert_array_equal(back.no_data_mask, cartesian.no_data_mask)
    np.testing.assert_allclose(back.origin, cartesian.origin, atol=1e-4)
    np.testing.assert_allclose(back.direction, POSE[:3, :3], atol=1e-6)
    mask = ~cartesian.no_data_mask
    save_mask(tmp_path / "m.mha", mask, vol)  # a beam volume's masks are on its Cartesian grid
    m = load(tmp_path / "m.mha", no_data_value=None)
    np.testing.assert_array_equal(m.array.astype(bool), mask)
    np.testing.assert_allclose(m.origin, vol.grid.origin, atol=1e-5)
    with pytest.raises(ValueError, match="not its grid"):
        save_mask(tmp_path / "m2.mha", mask[1:], vol)


def test_itk_reads_our_file_into_a_phased_array_image(tmp_path):
    """The docs' recipe: ITK's reader, then the four setters; ITK's own
    index -> point mapping then agrees with ours ("tan", default centre)."""
    itk = pytest.importorskip("itk")
    g = BeamGeometry((24, 9, 13), 0.7, 4.0, math.radians(2.0), math.radians(2.5))
    vol = BeamVolume(np.random.default_rng(1).uniform(1, 200, g.shape), g)
    save_volume(tmp_path / "b.mha", vol)

    image_type = itk.PhasedArray3DSpecialCoordinatesImage[itk.F]
    reader = itk.ImageFileReader[image_type].New(FileName=str(tmp_path / "b.mha"))
    reader.Update()
    image = reader.GetOutput()
    keys = image.GetMetaDataDictionary()
    image.SetAzimuthAngularSeparation(float(keys["AzimuthAngularSeparation"]))
    image.SetElevationAngularSeparation(float(keys["ElevationAngularSeparation"]))
    image.SetRadiusSampleSize(float(keys["RadiusSampleSize"]))
    image.SetFirstSampleDistance(float(keys["FirstSampleDistance"]))
    for index in ([0, 0, 0], [12, 8, 23], [0, 8, 5], [12, 0, 17], [6, 4, 11]):  # ITK order (a, e, r)
        point = np.array(image.TransformIndexToPhysicalPoint(index))
        np.testing.assert_allclose(point, g.index_to_world(np.array(index[::-1], float)), atol=1e-9)
        assert image.GetPixel(index) == pytest.approx(vol.array[index[2], index[1], index[0]])
        back = np.array(image.TransformPhysicalPointToContinuousIndex(point.tolist()))
        np.testing.assert_allclose(back[::-1], index[::-1], atol=1e-6)
