import json
import locale

import numpy as np
import pytest
import SimpleITK as sitk

import spheroseg

from spheroseg.io import (ImageFileError, frame_order, image_files, image_format, load, load_frames, load_sequence,
                         read_markups, save_mask,
                         write_folder_atomically, write_markups)
from spheroseg.volumes.volume import Volume

DIRECTION = (0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0)


def write_3d(path, array, spacing=(0.8, 0.9, 1.1), origin=(-10.0, 5.0, 2.0)):
    image = sitk.GetImageFromArray(array)
    image.SetSpacing(spacing)
    image.SetOrigin(origin)
    if image.GetDimension() == 3:
        image.SetDirection(DIRECTION)
    sitk.WriteImage(image, str(path))


@pytest.mark.parametrize("suffix", [".mha", ".mhd", ".nii.gz", ".nrrd"])
def test_load_keeps_geometry(tmp_path, suffix, rng):
    array = rng.integers(0, 255, size=(6, 7, 8)).astype(np.uint8)
    write_3d(tmp_path / f"img{suffix}", array)
    vol = load(tmp_path / f"img{suffix}")
    np.testing.assert_array_equal(vol.array, array)
    np.testing.assert_allclose(vol.spacing, (0.8, 0.9, 1.1), rtol=1e-6)
    np.testing.assert_allclose(vol.origin, (-10.0, 5.0, 2.0), rtol=1e-6)
    np.testing.assert_allclose(vol.direction.ravel(), DIRECTION, atol=1e-6)
    # the world position of a voxel agrees with SimpleITK's
    image = sitk.ReadImage(str(tmp_path / f"img{suffix}"))
    np.testing.assert_allclose(vol.index_to_world([[3, 2, 1]])[0], image.TransformIndexToPhysicalPoint((3, 2, 1)), atol=1e-5)


def test_4d_round_trip_needs_is_vector_false(tmp_path, rng):
    frames = rng.random((5, 6, 7, 8)).astype(np.float32)  # [t, z, y, x]
    image = sitk.GetImageFromArray(frames, isVector=False)
    assert image.GetDimension() == 4
    sitk.WriteImage(image, str(tmp_path / "seq.mha"))
    seq = load_sequence(tmp_path / "seq.mha")
    assert len(seq) == 5
    for t in range(5):
        np.testing.assert_array_equal(seq[t].array, frames[t])
    with pytest.raises(ValueError, match="3D\\+t"):
        load(tmp_path / "seq.mha")


def test_slicer_sequence_as_vector_image(tmp_path, rng):
    frames = rng.integers(0, 255, size=(3, 6, 7, 8)).astype(np.uint8)
    image = sitk.GetImageFromArray(np.moveaxis(frames, 0, -1), isVector=True)  # components are frames
    sitk.WriteImage(image, str(tmp_path / "cine.seq.nrrd"))
    seq = load_sequence(tmp_path / "cine.seq.nrrd")
    assert [v.shape for v in seq] == [(6, 7, 8)] * 3
    np.testing.assert_array_equal(seq[2].array, frames[2])
    assert image_format(tmp_path / "cine.seq.nrrd") == ".seq.nrrd"


def test_folder_and_glob_of_frames(tmp_path, rng):
    arrays = [rng.integers(0, 9, size=(4, 5, 6)).astype(np.int16) for _ in range(3)]
    for t, a in enumerate(arrays):
        write_3d(tmp_path / f"frame_{t:02d}.nii.gz", a)
    for source, glob in ((tmp_path, False), (str(tmp_path / "frame_*.nii.gz"), True)):
        seq = load_sequence(source, glob=glob)
        assert len(seq) == 3
        np.testing.assert_array_equal(seq[1].array, arrays[1])
    # a pattern only when asked for: without glob=True it is a file name
    with pytest.raises(FileNotFoundError, match=r"frame_\*.nii.gz: no such file \(a pattern\? give --glob\)"):
        load_sequence(str(tmp_path / "frame_*.nii.gz"))


def test_a_file_name_with_glob_characters_is_that_file(tmp_path, rng):
    """``cine[12].mha`` is the sequence of that name, not cine1 and cine2
    (round 4: tracked as the two frames the pattern matches)."""
    arrays = [rng.integers(0, 9, size=(4, 5, 6)).astype(np.int16) for _ in range(4)]
    image = sitk.JoinSeries([sitk.GetImageFromArray(a) for a in arrays])
    sitk.WriteImage(image, str(tmp_path / "cine[12].mha"))
    for k in (1, 2):
        write_3d(tmp_path / f"cine{k}.mha", arrays[0] + 100)
    for reader in (load_sequence, load_frames):
        seq = reader(tmp_path / "cine[12].mha")
        assert len(seq) == 4
        np.testing.assert_array_equal(seq[3].array, arrays[3])
    assert image_files(str(tmp_path / "cine[12].mha")) == [tmp_path / "cine[12].mha"]
    assert len(load_sequence(str(tmp_path / "cine[12].mha"), glob=True)) == 2  # asked for: the pattern


def test_frames_of_a_folder_in_the_order_of_their_numbers(tmp_path, rng):
    """frame_2 before frame_10 (round 4: tracked 0, 1, 10, 2, ... silently);
    a gap or a repeated number is an error naming the frames."""
    arrays = [np.full((4, 5, 6), t, np.int16) for t in range(12)]
    for t, a in enumerate(arrays):
        write_3d(tmp_path / f"frame_{t}.mha", a)
    seq = load_sequence(tmp_path)
    assert [int(v.array[0, 0, 0]) for v in seq] == list(range(12))
    assert [p.name for p in frame_order([tmp_path / "b_10.mha", tmp_path / "a_9.mha"])] == ["a_9.mha", "b_10.mha"]
    write_3d(tmp_path / "frame_05.mha", arrays[5])
    with pytest.raises(ValueError, match=r"frame_05.mha and frame_5.mha: two frames numbered 5"):
        load_sequence(tmp_path)
    (tmp_path / "frame_05.mha").unlink()
    (tmp_path / "frame_7.mha").unlink()
    with pytest.raises(ValueError, match=r"frame 7 missing between frame_6.mha and frame_8.mha"):
        load_sequence(tmp_path)
    with pytest.raises(ValueError, match=r"no frame number in the name"):
        frame_order([tmp_path / "ed.mha", tmp_path / "es.mha"])


def test_dicom_series(tmp_path, rng, request):
    array = rng.integers(0, 1000, size=(4, 6, 5)).astype(np.int16)
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    # GDCM's writer sets the process's C locale; put it back, or every later
    # subprocess of this test run decodes its output as ASCII
    ctype = locale.setlocale(locale.LC_CTYPE)
    request.addfinalizer(lambda: locale.setlocale(locale.LC_CTYPE, ctype))
    for k in range(array.shape[0]):
        s = sitk.GetImageFromArray(array[k : k + 1])
        s.SetSpacing((0.7, 0.7, 1.5))
        s.SetOrigin((0.0, 0.0, 1.5 * k))
        s.SetMetaData("0020|0032", f"0\\0\\{1.5 * k}")
        s.SetMetaData("0020|0013", str(k))
        s.SetMetaData("0020|000e", "1.2.826.0.1.3680043.2.1125.1")
        s.SetMetaData("0020|0037", "1\\0\\0\\0\\1\\0")
        writer.SetFileName(str(tmp_path / f"slice{k}.dcm"))
        writer.Execute(s)
    vol = load(tmp_path)
    assert vol.shape == (4, 6, 5)
    np.testing.assert_array_equal(vol.array, array)
    np.testing.assert_allclose(vol.spacing[2], 1.5, rtol=1e-4)


def test_npy_needs_spacing(tmp_path):
    np.save(tmp_path / "a.npy", np.zeros((4, 4, 4)))
    with pytest.raises(ValueError, match="spacing"):
        load(tmp_path / "a.npy")
    assert load(tmp_path / "a.npy", spacing=(0.9, 0.9, 0.9)).spacing[0] == 0.9


def test_bad_files(tmp_path):
    """Errors by cause, as nibabel: a missing file is FileNotFoundError, an
    unreadable one ImageFileError (a ValueError); the message starts with the path."""
    for missing in ("missing.mha", "missing.npy", "missing.mrk.json"):
        with pytest.raises(FileNotFoundError, match=f"^{tmp_path / missing}: no such file$"):
            (read_markups if missing.endswith(".json") else load)(tmp_path / missing)
    with pytest.raises(FileNotFoundError, match="no such file"):
        load_sequence(tmp_path / "missing.npy", spacing=(1, 1, 1))
    (tmp_path / "junk.mha").write_text("not an image")
    with pytest.raises(ImageFileError, match=f"^{tmp_path / 'junk.mha'}: cannot read image") as err:
        load(tmp_path / "junk.mha")
    assert isinstance(err.value, ValueError)
    (tmp_path / "junk.npy").write_text("not an array")
    with pytest.raises(ImageFileError, match="cannot read numpy array"):
        load(tmp_path / "junk.npy", spacing=(1, 1, 1))
    write_3d(tmp_path / "flat.mha", np.zeros((5, 6), np.uint8), spacing=(1, 1), origin=(0, 0))
    with pytest.raises(ValueError, match="3D"):
        load(tmp_path / "flat.mha")



def test_a_raw_file_larger_than_its_header_declares_is_refused(tmp_path, rng):
    """ITK reads the first bytes of a too large .raw silently: a DimSize cut
    along x scrambles the image."""
    array = rng.integers(1, 200, (6, 5, 4)).astype(np.float32)
    write_3d(tmp_path / "a.mhd", array)
    np.testing.assert_array_equal(load(tmp_path / "a.mhd", no_data_value=None).array, array)
    header = (tmp_path / "a.mhd").read_text()
    assert "DimSize = 4 5 6" in header and "ElementDataFile = a.raw" in header
    for dims, extra in (("3 5 6", 6 * 5 * 4), ("4 5 5", 5 * 4 * 4)):
        (tmp_path / "cut.mhd").write_text(header.replace("DimSize = 4 5 6", f"DimSize = {dims}"))
        with pytest.raises(ImageFileError, match=rf"^{tmp_path / 'cut.mhd'}: its data file a.raw holds 480 bytes, "
                                                 rf"{extra} more than the header declares \(DimSize {dims}, MET_FLOAT\)"):
            load(tmp_path / "cut.mhd")
    # what SimpleITK writes, of every scalar type, is read: the check counts its bytes right
    small = array % 100 + 1  # within every type's range
    for dtype in (np.int8, np.uint8, np.int16, np.uint16, np.int32, np.uint32, np.int64, np.uint64, np.float64):
        write_3d(tmp_path / f"{np.dtype(dtype).name}.mhd", small.astype(dtype))
        np.testing.assert_array_equal(load(tmp_path / f"{np.dtype(dtype).name}.mhd", no_data_value=None).array, small)

@pytest.mark.parametrize("suffix", [".mhd", ".nii.gz", ".nrrd", ".npy"])
def test_save_mask_round_trip(tmp_path, suffix, rng):
    like = Volume(np.zeros((5, 6, 7)), spacing=(0.5, 0.6, 0.7), origin=(1.0, 2.0, 3.0))
    mask = (rng.random((7, 6, 5)) > 0.5).transpose(2, 1, 0)  # not C-contiguous
    save_mask(tmp_path / f"mask{suffix}", mask, like)
    back = np.load(tmp_path / "mask.npy") if suffix == ".npy" else sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / f"mask{suffix}")))
    assert back.dtype == np.uint8
    np.testing.assert_array_equal(back, mask.astype(np.uint8))  # 0 and 1
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".spheroseg-")], "no temporary left behind"


def test_markups(tmp_path):
    doc = {"markups": [{"type": "Fiducial", "coordinateSystem": "RAS", "controlPoints": [
        {"label": "Apex", "position": [1.0, 2.0, 3.0]},
        {"label": "base", "position": [4.0, 5.0, 6.0]},
        {"label": "landmark-1", "position": [7.0, 8.0, 9.0]},
    ]}]}
    (tmp_path / "p.mrk.json").write_text(json.dumps(doc))
    marks = read_markups(tmp_path / "p.mrk.json")
    np.testing.assert_array_equal(marks["apex"], [-1.0, -2.0, 3.0])  # RAS -> LPS
    np.testing.assert_array_equal(marks["landmarks"], [[-7.0, -8.0, 9.0]])
    assert marks["annulus"].shape == (0, 3)
    (tmp_path / "bad.mrk.json").write_text("{\"markups\": 3}")
    with pytest.raises(ValueError, match="markups"):
        read_markups(tmp_path / "bad.mrk.json")


def _write_markups_doc(path, points, **markup):
    path.write_text(json.dumps({"markups": [{"type": "Fiducial", **markup, "controlPoints": points}]}))
    return path


def test_markups_undefined_point_refused_unless_unused(tmp_path):
    apex = {"label": "apex", "position": [1.0, 2.0, 3.0]}
    base = {"label": "base", "position": [0.0, 0.0, 0.0], "positionStatus": "undefined"}
    with pytest.raises(ValueError, match="'base' has positionStatus 'undefined'"):
        read_markups(_write_markups_doc(tmp_path / "u.mrk.json", [apex, base]))
    # a point spheroseg does not use may be unplaced
    note = {"label": "note", "position": [0.0, 0.0, 0.0], "positionStatus": "undefined"}
    marks = read_markups(_write_markups_doc(tmp_path / "n.mrk.json", [apex, note]))
    np.testing.assert_array_equal(marks["apex"], [1.0, 2.0, 3.0])


def test_markups_duplicate_apex_refused(tmp_path):
    points = [{"label": "apex", "position": [1.0, 2.0, 3.0]}, {"label": "Apex", "position": [4.0, 5.0, 6.0]}]
    with pytest.raises(ValueError, match="two control points labelled 'apex'"):
        read_markups(_write_markups_doc(tmp_path / "d.mrk.json", points))


@pytest.mark.parametrize("units, mm_per_unit", [("um", 1e-3), ("mm", 1.0), ("cm", 10.0), ("m", 1000.0),
                                                (["cm", "cm", "cm"], 10.0)])
def test_markups_units_converted_to_mm(tmp_path, units, mm_per_unit):
    points = [{"label": "apex", "position": [1.0, 2.0, 3.0]}, {"label": "landmark-1", "position": [4.0, 5.0, 6.0]}]
    marks = read_markups(_write_markups_doc(tmp_path / "p.mrk.json", points, coordinateSystem="RAS",
                                            coordinateUnits=units))
    np.testing.assert_allclose(marks["apex"], np.array([-1.0, -2.0, 3.0]) * mm_per_unit, rtol=1e-15)
    np.testing.assert_allclose(marks["landmarks"], [np.array([-4.0, -5.0, 6.0]) * mm_per_unit], rtol=1e-15)


@pytest.mark.parametrize("units", ["inch", ["mm", "cm", "mm"], 3])
def test_markups_unknown_units_refused(tmp_path, units):
    points = [{"label": "apex", "position": [1.0, 2.0, 3.0]}]
    with pytest.raises(ValueError, match="coordinateUnits must be one of"):
        read_markups(_write_markups_doc(tmp_path / "p.mrk.json", points, coordinateUnits=units))


def test_markups_annulus_round_trip(tmp_path, rng):
    # Slicer labels as a user would type them; RAS converted to LPS
    doc = {"markups": [{"type": "Fiducial", "coordinateSystem": "RAS", "controlPoints": [
        {"label": "apex", "position": [1.0, 2.0, 3.0]},
        {"label": "Annulus", "position": [10.0, 0.0, 50.0]},
        {"label": "annulus-2", "position": [0.0, 10.0, 52.0]},
        {"label": "annulus 3", "position": [-10.0, 0.0, 51.0]},
        {"label": "annulus", "position": [0.0, -10.0, 49.0]},
    ]}]}
    (tmp_path / "p.mrk.json").write_text(json.dumps(doc))
    marks = read_markups(tmp_path / "p.mrk.json")
    np.testing.assert_array_equal(marks["annulus"], [[-10.0, 0, 50], [0, -10.0, 52], [10.0, 0, 51], [0, 10.0, 49]])
    assert marks["base"] is None and marks["landmarks"].shape == (0, 3)
    # written back (LPS) and read again: the same points, bit for bit
    annulus = rng.normal(size=(5, 3)) * 20
    write_markups(tmp_path / "out.mrk.json", apex=marks["apex"], annulus=annulus, landmarks=annulus[:2] + 1)
    again = read_markups(tmp_path / "out.mrk.json")
    np.testing.assert_array_equal(again["apex"], marks["apex"])
    np.testing.assert_array_equal(again["annulus"], annulus)
    np.testing.assert_array_equal(again["landmarks"], annulus[:2] + 1)
    assert again["base"] is None
    assert json.loads((tmp_path / "out.mrk.json").read_text())["markups"][0]["coordinateSystem"] == "LPS"
    with pytest.raises(ValueError, match="annulus"):
        write_markups(tmp_path / "bad.mrk.json", annulus=[[0, 0, np.nan]])
    assert not (tmp_path / "bad.mrk.json").exists()


def test_load_finds_the_sector_padding(tmp_path):
    a = np.full((20, 20, 20), 60, np.uint8)
    a[:, :3] = 0
    write_3d(tmp_path / "echo.mha", a)
    assert load(tmp_path / "echo.mha").no_data_mask.sum() == 20 * 3 * 20
    assert load(tmp_path / "echo.mha", no_data_value=None).no_data_mask is None
    with pytest.raises(ValueError, match="no_data_value"):
        load(tmp_path / "echo.mha", no_data_value="sometimes")


def test_load_frames_tells_a_volume_from_a_sequence(tmp_path):
    from spheroseg.io import load_frames
    from spheroseg.synthetic.phantom import make_sequence

    seq = make_sequence(seed=1, n_frames=3, spacing=3.0)
    spheroseg.save_volume(tmp_path / "cine.nrrd", list(seq.volumes))
    spheroseg.save_volume(tmp_path / "one.mha", seq.volumes[1])
    frames = load_frames(tmp_path / "cine.nrrd")
    assert len(frames) == 3
    np.testing.assert_array_equal(frames[2].array, seq.volumes[2].array)
    (only,) = load_frames(tmp_path / "one.mha")
    np.testing.assert_array_equal(only.array, seq.volumes[1].array)
    np.testing.assert_allclose(only.spacing, seq.volumes[1].spacing)
    np.save(tmp_path / "cine.npy", np.array([v.array for v in seq.volumes]))
    assert len(load_frames(tmp_path / "cine.npy", spacing=(3, 3, 3))) == 3
    with pytest.raises(FileNotFoundError):
        load_frames(tmp_path / "missing.mha")
    (tmp_path / "bad.mha").write_text("not an image")
    with pytest.raises(spheroseg.ImageFileError, match="bad.mha"):
        load_frames(tmp_path / "bad.mha")


def test_save_volume_casts_to_the_dtype_asked(tmp_path):
    volume = spheroseg.Volume(np.arange(24, dtype=float).reshape(2, 3, 4) * 10, spacing=(1, 2, 3))
    spheroseg.save_volume(tmp_path / "v.nii", volume, dtype=np.uint8)
    image = sitk.ReadImage(str(tmp_path / "v.nii"))
    assert image.GetPixelID() == sitk.sitkUInt8
    np.testing.assert_array_equal(sitk.GetArrayFromImage(image), (np.arange(24).reshape(2, 3, 4) * 10).astype(np.uint8))


@pytest.mark.parametrize("dtype", [np.uint8, np.int16, np.float32, np.float64])
def test_load_owns_its_voxels(tmp_path, dtype, rng):
    # load reads SimpleITK's buffer without a copy: float32 voxels stay a
    # read-only view of it, which must keep the image alive (one working
    # copy, not a dangling one); others are converted into a new array
    import gc

    array = (rng.random((6, 7, 8)) * 100).astype(dtype)
    sitk.WriteImage(sitk.GetImageFromArray(array), str(tmp_path / "v.mha"))
    vol = load(tmp_path / "v.mha", no_data_value=None)
    assert vol.array.dtype == np.float32
    assert vol.array.flags.owndata == (dtype != np.float32)
    assert vol.array.flags.owndata or not vol.array.flags.writeable
    gc.collect()
    overwrite = [sitk.GetImageFromArray(np.full(array.shape, -1.0, np.float32)) for _ in range(20)]
    np.testing.assert_array_equal(vol.array, array.astype(np.float32))
    assert len(overwrite) == 20


def test_write_folder_atomically_all_or_nothing(tmp_path):
    def write(files, fail=False):
        def into(folder):
            for name, text in files.items():
                (folder / name).parent.mkdir(exist_ok=True)
                (folder / name).write_text(text)
                if fail:
                    raise OSError(28, "No space left on device")
            return len(files)
        return into

    out = tmp_path / "new" / "out"
    with pytest.raises(OSError, match="No space"):
        write_folder_atomically(out, write({"a.txt": "1", "b.txt": "2"}, fail=True))
    assert list(tmp_path.iterdir()) == []  # no out, no parent, nothing hidden
    assert write_folder_atomically(out, write({"a.txt": "1", "f/1": "x", "f/2": "y"})) == 3
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == ["a.txt", "f", "f/1", "f/2"]
    (out / "mine.txt").write_text("kept")
    # a failure while writing the next set leaves the earlier one as it was
    with pytest.raises(OSError):
        write_folder_atomically(out, write({"a.txt": "new"}, fail=True), replaces=["a.txt", "f"])
    assert (out / "a.txt").read_text() == "1" and (out / "f" / "2").exists()
    # a complete set replaces the named entries (the folder f, all of it), keeps the others
    write_folder_atomically(out, write({"a.txt": "new", "f/1": "z"}), replaces=["a.txt", "f", "gone"])
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == ["a.txt", "f", "f/1", "mine.txt"]
    assert (out / "a.txt").read_text() == "new"
    assert sorted(p.name for p in tmp_path.rglob(".*")) == []


def _huge_header(path, n=2000):
    (path.parent / "tiny.raw").write_bytes(b"\0" * 64)
    path.write_text(f"ObjectType = Image\nNDims = 3\nDimSize = {n} {n} {n}\nElementType = MET_FLOAT\n"
                    "ElementSpacing = 1 1 1\nElementDataFile = tiny.raw\n")
    return path


def test_declared_size_over_the_budget_is_refused_before_reading(tmp_path, monkeypatch):
    monkeypatch.delenv("SPHEROSEG_MAX_IMAGE_GB", raising=False)
    huge = _huge_header(tmp_path / "huge.mhd")  # 2000^3 floats: 72 GB once loaded, 64 bytes of data
    for reader in (load, load_sequence):
        with pytest.raises(ImageFileError, match=r"2000 x 2000 x 2000 voxels, 72 GB once loaded \(9 bytes a voxel: "
                                                 r"float32 voxels, their no-data mask, the copy sampling reads\), "
                                                 r"over the memory budget of 4 GB \(set SPHEROSEG_MAX_IMAGE_GB"):
            reader(huge)
    # the budget is the user's: a small one refuses a small image, .npy included
    small = np.zeros((10, 20, 30), np.float32)
    np.save(tmp_path / "small.npy", small)
    monkeypatch.setenv("SPHEROSEG_MAX_IMAGE_GB", str(9 * small.size / 1e9 * 0.99))
    with pytest.raises(ImageFileError, match="over the memory budget"):
        load(tmp_path / "small.npy", spacing=(1, 1, 1))
    monkeypatch.setenv("SPHEROSEG_MAX_IMAGE_GB", str(9 * small.size / 1e9 * 1.01))
    assert load(tmp_path / "small.npy", spacing=(1, 1, 1), no_data_value=None).shape == small.shape
    monkeypatch.setenv("SPHEROSEG_MAX_IMAGE_GB", "lots")
    with pytest.raises(ValueError, match="SPHEROSEG_MAX_IMAGE_GB must be a positive number of GB, got 'lots'"):
        load(tmp_path / "small.npy", spacing=(1, 1, 1))
