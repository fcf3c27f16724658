"""The command line, end to end: through a real subprocess where the test is
about the process (exit statuses, one-line errors, timings, a verb's whole
run), else :func:`spheroseg.cli.main` in this process (no interpreter or
SciPy to start, some 2 s a command)."""

import json
import os
import subprocess
import sys

import meshio
import numpy as np
import pytest
import SimpleITK as sitk
from conftest import cli

from spheroseg.surfaces.fit import annulus_of_open_mesh
from spheroseg.io import load, write_markups
from spheroseg.synthetic.phantom import make_phantom, make_sequence
from spheroseg.tracking.segment import segment


def run(*args, cwd=None):
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    return subprocess.run([sys.executable, "-m", "spheroseg", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, env=env, timeout=300)


def assert_one_line_error(proc, pattern=""):
    assert proc.returncode != 0
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("spheroseg: error:"), proc.stderr
    assert "Traceback" not in proc.stderr
    assert pattern.lower() in lines[0].lower(), lines[0]


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """A phantom written as an image, with its apex and base."""
    folder = tmp_path_factory.mktemp("case")
    ph = make_phantom(seed=41, spacing=1.5)
    image = sitk.GetImageFromArray(ph.volume.array.astype(np.uint8))
    image.SetSpacing(tuple(ph.volume.spacing))
    image.SetOrigin((12.0, -30.0, 5.0))
    return folder, image, ph


def points_args(ph, shift):
    return ["--apex", *(ph.apex + shift), "--base", *(ph.base + shift)]


def test_segment_with_the_myocardium(capfd, case, tmp_path):
    """``--myocardium``: the API's mass and myocardium mask, the epicardial
    mesh and the heart as CMISS volume elements; ``--force`` then replaces
    the whole set, these files included."""
    folder, image, ph = case
    path = folder / "myo.mha"
    sitk.WriteImage(image, str(path))
    shift = np.array(image.GetOrigin())
    rv = ph.base + shift + [0.0, 20.0, 0.0]
    out = tmp_path / "out"
    proc = cli(capfd, "segment", path, *points_args(ph, shift), "--myocardium", "--rv-insertion", *rv, "--out", out,
                "--quiet", "--no-report", "--allow-poor")
    assert proc.returncode == 0, proc.stderr
    results = json.loads((out / "results.json").read_text())
    vol = load(path)
    api = segment(vol, ph.apex + shift, ph.base + shift, myocardium=True, rv_insertion=rv)
    assert results["myocardium"]["lv_mass_g"] == pytest.approx(api.lv_mass_g, rel=1e-9)
    mask = sitk.GetArrayFromImage(sitk.ReadImage(str(out / "myocardium.mha"))).astype(bool)
    np.testing.assert_array_equal(mask, api.myocardium_mask(vol))
    for name in ("epicardium.vtk", "epicardium.ply", "epicardium.json", "heart.exnode", "heart.exelem"):
        assert (out / name).stat().st_size > 0, name
    proc = cli(capfd, "segment", path, *points_args(ph, shift), "--out", out, "--quiet", "--no-report", "--force")
    assert proc.returncode == 0, proc.stderr
    assert not (out / "myocardium.mha").exists() and not (out / "heart.exnode").exists()


@pytest.mark.parametrize("suffix", [".mha", ".mhd", ".nii.gz", ".nrrd"])
def test_segment_each_format(capfd, case, suffix, tmp_path):
    folder, image, ph = case
    path = folder / f"case{suffix}"
    sitk.WriteImage(image, str(path))
    shift = np.array(image.GetOrigin())
    out = tmp_path / "out"
    proc = cli(capfd, "segment", path, *points_args(ph, shift), "--out", out, "--quiet", "--stl")
    assert proc.returncode == 0, proc.stderr
    results = json.loads((out / "results.json").read_text())
    # the same segmentation through the Python API
    vol = load(path)
    api = segment(vol, ph.apex + shift, ph.base + shift)
    assert results["volume_ml"] == pytest.approx(api.volume_ml, rel=1e-9)
    mask_image = sitk.ReadImage(str(out / f"mask{suffix}"))
    np.testing.assert_array_equal(sitk.GetArrayFromImage(mask_image).astype(bool), api.mask(vol))
    np.testing.assert_allclose(mask_image.GetOrigin(), image.GetOrigin(), atol=1e-6)
    for mesh_file in ("mesh.vtk", "mesh.ply", "mesh.stl"):
        mesh = meshio.read(out / mesh_file)
        assert len(mesh.points) > 100
        np.testing.assert_allclose(mesh.points.mean(0), api.mesh()[0].mean(0), atol=1e-3)
    assert b"SPACE=LPS" in (out / "mesh.vtk").read_bytes()[:200]
    surface = json.loads((out / "surface.json").read_text())
    assert surface["coordinate_system"]["name"] == "prolate"
    assert (out / "surface.exnode").exists() and (out / "surface.exelem").exists()
    assert (out / "report.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_smoothing_reference_from_the_command_line(capfd, case, tmp_path):
    """``--smoothness-reference fitted`` reaches the segmentation: the API's
    volume with that option, not the default's."""
    folder, image, ph = case
    path = folder / "case.mha"
    sitk.WriteImage(image, str(path))
    shift = np.array(image.GetOrigin())
    proc = cli(capfd, "segment", path, *points_args(ph, shift), "--out", tmp_path / "o", "--quiet", "--no-report",
               "--smoothness-reference", "fitted")
    assert proc.returncode == 0, proc.stderr
    volume_ml = json.loads((tmp_path / "o" / "results.json").read_text())["volume_ml"]
    vol = load(path)
    fitted = segment(vol, ph.apex + shift, ph.base + shift, smoothness_reference="fitted").volume_ml
    start = segment(vol, ph.apex + shift, ph.base + shift).volume_ml
    assert volume_ml == pytest.approx(fitted, rel=1e-9) and abs(fitted / start - 1) > 1e-3, (volume_ml, fitted, start)


def test_points_from_markups_and_landmarks(capfd, case, tmp_path):
    folder, image, ph = case
    path = folder / "case.mha"
    sitk.WriteImage(image, str(path))
    shift = np.array(image.GetOrigin())
    wall = ph.truth_mesh[0]
    on_wall = wall[np.argmin(np.linalg.norm(wall - ((ph.apex + ph.base) / 2 + [12.0, 0, 0]), axis=1))]
    doc = {"markups": [{"coordinateSystem": "LPS", "controlPoints": [
        {"label": "apex", "position": list(ph.apex + shift)},
        {"label": "base", "position": list(ph.base + shift)},
        {"label": "landmark", "position": list(on_wall + shift)},  # on the true wall: no warning
    ]}]}
    (tmp_path / "p.mrk.json").write_text(json.dumps(doc))
    proc = cli(capfd, "segment", path, "--points", tmp_path / "p.mrk.json", "--out", tmp_path / "o", "--quiet",
                "--no-report")
    assert proc.returncode == 0, proc.stderr
    results = json.loads((tmp_path / "o" / "results.json").read_text())
    assert len(results["landmarks"]) == 1
    assert len(results["quality"]["landmark_residuals_mm"]) == 1 and results["quality"]["landmark_residuals_mm"][0] < 2


def test_annulus_from_the_command_line_and_markups(capfd, case, tmp_path):
    # the mitral plane from --annulus (base omitted), and the same points
    # from a markups file: the results of the Python API
    folder, image, ph = case
    path = folder / "case.mha"
    sitk.WriteImage(image, str(path))
    shift = np.array(image.GetOrigin())
    ring = annulus_of_open_mesh(*ph.truth_mesh)
    annulus = ring[:: len(ring) // 5][:5] + shift
    api = segment(load(path), ph.apex + shift, annulus=annulus)
    flags = [a for p in annulus for a in ("--annulus", *p)]
    proc = cli(capfd, "segment", path, "--apex", *(ph.apex + shift), *flags, "--out", tmp_path / "a", "--quiet",
                "--no-report")
    assert proc.returncode == 0, proc.stderr
    write_markups(tmp_path / "p.mrk.json", apex=ph.apex + shift, annulus=annulus)
    proc = cli(capfd, "segment", path, "--points", tmp_path / "p.mrk.json", "--out", tmp_path / "b", "--quiet",
                "--no-report")
    assert proc.returncode == 0, proc.stderr
    for out in ("a", "b"):
        results = json.loads((tmp_path / out / "results.json").read_text())
        assert results["volume_ml"] == pytest.approx(api.volume_ml, rel=1e-9)
        np.testing.assert_allclose(results["annulus"], annulus)
        np.testing.assert_allclose(results["base"], annulus.mean(0), atol=1e-9)
        np.testing.assert_allclose(results["long_axis"], api.surface.pose.axis, atol=1e-12)
    two = flags[:8]
    assert_one_line_error(cli(capfd, "segment", path, "--apex", *(ph.apex + shift), *two, "--out", tmp_path / "c"),
                          "at least 3 annulus points, got 2")


def test_track_4d_image_and_frames(tmp_path):
    seq = make_sequence(seed=42, n_frames=4, spacing=2.0)
    frames = np.stack([v.array for v in seq.volumes]).astype(np.uint8)
    image = sitk.GetImageFromArray(frames, isVector=False)
    image.SetSpacing((2.0, 2.0, 2.0, 1.0))
    sitk.WriteImage(image, str(tmp_path / "seq.mha"))
    first = seq.frames[0]
    proc = run("track", tmp_path / "seq.mha", "--apex", *first.apex, "--base", *first.base, "--out", tmp_path / "o",
               "--quiet")
    assert proc.returncode == 0, proc.stderr
    results = json.loads((tmp_path / "o" / "results.json").read_text())
    assert len(results["volumes_ml"]) == 4
    assert results["ef_percent"] == pytest.approx(100 * (results["edv_ml"] - results["esv_ml"]) / results["edv_ml"])
    assert len(list((tmp_path / "o" / "masks").iterdir())) == 4
    assert (tmp_path / "o" / "report.png").exists()
    # --force over that longer run replaces the whole set: no stale frames
    sitk.WriteImage(image[:, :, :, :2], str(tmp_path / "short.mha"))
    (tmp_path / "o" / "notes.txt").write_text("mine")
    proc = run("track", tmp_path / "short.mha", "--apex", *first.apex, "--base", *first.base, "--out", tmp_path / "o",
               "--quiet", "--force", "--no-report")
    assert proc.returncode == 0, proc.stderr
    assert len(json.loads((tmp_path / "o" / "results.json").read_text())["volumes_ml"]) == 2
    assert sorted(p.name for p in (tmp_path / "o" / "masks").iterdir()) == ["frame_000.mha", "frame_001.mha"]
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == ["masks", "meshes", "notes.txt", "results.json"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o", "seq.mha", "short.mha"]  # nothing hidden left


def test_track_with_the_myocardium(capfd, tmp_path):
    """``track --myocardium``: the API's mass per frame, segmental volume
    curves, times to minimum and SDI in results.json, every frame's
    myocardium mask as the API's."""
    from spheroseg.io import load_sequence
    from spheroseg.tracking.segment import track

    seq = make_sequence(seed=42, n_frames=3, spacing=2.0)
    image = sitk.GetImageFromArray(np.stack([v.array for v in seq.volumes]).astype(np.uint8), isVector=False)
    image.SetSpacing((2.0, 2.0, 2.0, 1.0))
    path = tmp_path / "seq.mha"
    sitk.WriteImage(image, str(path))
    first = seq.frames[0]
    rv = first.base + [0.0, 20.0, 0.0]
    proc = cli(capfd, "track", path, "--apex", *first.apex, "--base", *first.base, "--myocardium", "--rv-insertion",
                *rv, "--out", tmp_path / "o", "--quiet", "--no-report", "--allow-poor")
    assert proc.returncode == 0, proc.stderr
    block = json.loads((tmp_path / "o" / "results.json").read_text())["myocardium"]
    volumes = load_sequence(str(path))
    api = track(volumes, first.apex, first.base, myocardium=True, rv_insertion=rv)
    np.testing.assert_allclose(block["lv_mass_g"], api.masses_g, rtol=1e-9)
    np.testing.assert_allclose(block["segment_volumes_ml"], api.segment_volumes_ml, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(block["times_to_minimum_percent"], api.times_to_minimum, rtol=1e-9)
    assert block["sdi_percent"] == pytest.approx(api.sdi, rel=1e-9)
    assert np.shape(block["segment_volumes_ml"]) == (3, 17) and len(block["segment_names"]) == 17
    assert block["segment_convention"] == api.frames[0].segment_convention.to_dict()
    masses = block["lv_mass_g"]
    ed, es = int(np.argmax(api.volumes_ml)), int(np.argmin(api.volumes_ml))
    assert block["ed_es_mass_difference_percent"] == pytest.approx(100 * abs(masses[es] / masses[ed] - 1))
    for t, (name, volume) in enumerate(zip(block["masks"], volumes)):
        mask = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "o" / name))).astype(bool)
        np.testing.assert_array_equal(mask, api.frames[t].myocardium_mask(volume))


def test_demo(tmp_path):
    # without --out: a new folder beside an earlier demo's, nothing overwritten
    (tmp_path / "spheroseg-demo").mkdir()
    (tmp_path / "spheroseg-demo" / "results.json").write_text("earlier")
    proc = run("demo", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "EF" in proc.stdout
    assert (tmp_path / "spheroseg-demo" / "results.json").read_text() == "earlier"
    summary = json.loads((tmp_path / "spheroseg-demo-2" / "results.json").read_text())
    assert abs(summary["ef_percent"] - summary["truth"]["ef_percent"]) < 5
    # --out is the folder written: an existing one is refused before any work, and left as it was
    before = (tmp_path / "spheroseg-demo-2" / "results.json").read_bytes()
    assert_one_line_error(run("demo", "--out", tmp_path / "spheroseg-demo-2", "--quiet"), "--force")
    assert (tmp_path / "spheroseg-demo-2" / "results.json").read_bytes() == before


def test_refuses_to_overwrite_without_force(case, tmp_path):
    folder, image, ph = case
    path = folder / "case.nii.gz"
    sitk.WriteImage(image, str(path))
    shift = np.array(image.GetOrigin())
    args = ["segment", path, *points_args(ph, shift), "--out", tmp_path / "o", "--quiet", "--no-report"]
    assert run(*args).returncode == 0
    before = (tmp_path / "o" / "results.json").read_bytes()
    assert_one_line_error(run(*args), "--force")
    assert (tmp_path / "o" / "results.json").read_bytes() == before
    assert run(*args, "--force").returncode == 0


def test_poor_result_warns_and_exits_3_with_its_outputs(case, tmp_path):
    folder, image, ph = case
    path = folder / "case.mha"
    sitk.WriteImage(image, str(path))
    shift = np.array(image.GetOrigin())
    args = ["segment", path, *points_args(ph, shift), "--quiet", "--no-report", "--max-iterations", 1]
    proc = run(*args, "--out", tmp_path / "o")  # one iteration: the surface is still moving
    assert proc.returncode == 3, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("spheroseg: warning: check this segmentation"), proc.stderr
    results = json.loads((tmp_path / "o" / "results.json").read_text())
    assert results["quality"]["poor"] is True
    assert run(*args, "--out", tmp_path / "o2", "--allow-poor").returncode == 0
    assert "3 done, outputs written, but the result is poor" in " ".join(run("segment", "--help").stdout.split())


def test_never_overwrites_the_input(capfd, case, tmp_path):
    folder, image, ph = case
    path = tmp_path / "mask.mha"  # an input named like the output
    sitk.WriteImage(image, str(path))
    before = path.read_bytes()
    shift = np.array(image.GetOrigin())
    proc = cli(capfd, "segment", path, *points_args(ph, shift), "--out", tmp_path, "--force", "--quiet")
    assert_one_line_error(proc, "overwrite an input")
    assert path.read_bytes() == before


def test_an_image_without_padding_is_segmented(case, tmp_path):
    """No voxel is 0 (no sector padding to mark as no data, as in a cropped
    or simulated image): the padding search finds none, and the command
    segments it (it raised an AttributeError)."""
    folder, image, ph = case
    img = tmp_path / "unpadded.mha"
    unpadded = sitk.GetImageFromArray(np.maximum(ph.volume.array, 1).astype(np.uint8))
    unpadded.CopyInformation(image)
    sitk.WriteImage(unpadded, str(img))
    apex, base = ph.apex + image.GetOrigin(), ph.base + image.GetOrigin()
    proc = run("segment", img, "--apex", *apex, "--base", *base, "--out", tmp_path / "out", "--no-report",
               "--allow-poor")
    assert proc.returncode == 0, proc.stderr
    results = json.loads((tmp_path / "out" / "results.json").read_text())
    assert results["volume_ml"] == pytest.approx(ph.truth_volume_ml, rel=0.1)


@pytest.mark.parametrize(
    "make_args, pattern",
    [
        (lambda d, img: ["segment", d / "missing.mha", "--apex", 0, 0, 0, "--base", 0, 0, 9, "--out", d / "o"], "no such file"),
        (lambda d, img: ["segment", d / "notes.txt", "--apex", 0, 0, 0, "--base", 0, 0, 9, "--out", d / "o"], "cannot read"),
        (lambda d, img: ["segment", d / "flat.mha", "--apex", 0, 0, 0, "--base", 0, 0, 9, "--out", d / "o"], "3D"),
        (lambda d, img: ["segment", img, "--apex", 9999, 0, 0, "--base", 20, 20, 20, "--out", d / "o"], "outside the image"),
        (lambda d, img: ["segment", img, "--apex", 20, 20, 20, "--base", 20, 20, 20, "--out", d / "o"], "distinct"),
        (lambda d, img: ["segment", img, "--points", d / "bad.mrk.json", "--out", d / "o"], "markups"),
        (lambda d, img: ["segment", img, "--apex", 20, 20, 20, "--out", d / "o"], "base"),
        (lambda d, img: ["segment", img, "--apex", 20, 20, 20, "--base", 20, 20, 60, "--out", d / "notes.txt"], "is a file"),
        (lambda d, img: ["track", img, "--apex", 20, 20, 20, "--base", 20, 20, 60, "--out", d / "o"], "3D+t"),
        (lambda d, img: ["segment", img, "--apex", 20, 20, 20, "--base", 20, 20, 60, "--out", d / "o", "--threads", 0],
         "threads must be a positive integer"),
        (lambda d, img: ["track", img, "--apex", 20, 20, 20, "--base", 20, 20, 60, "--out", d / "o", "--threads", -2],
         "threads must be a positive integer"),
        (lambda d, img: ["segment", img, "--apex", 20, 20, 20, "--base", 20, 20, 60, "--out", d / "o", "--patches",
                         200, 200], "--patches must be at most 32 in each direction"),
        (lambda d, img: ["segment", img, "--apex", 20, 20, 20, "--base", 20, 20, 60, "--out", d / "o", "--step", 1e9],
         "--step must be at most 10 mm"),
        (lambda d, img: ["segment", img, "--apex", 20, 20, 20, "--base", 20, 20, 60, "--out", d / "o",
                         "--max-iterations", 0], "--max-iterations must be from 1 to 10000"),
        (lambda d, img: ["track", img, "--apex", 20, 20, 20, "--base", 20, 20, 60, "--out", d / "o",
                         "--iterations-per-frame", 0], "--iterations-per-frame must be from 1 to 10000"),
        (lambda d, img: ["segment", img, "--apex", 20, 20, 20, "--base", 20, 20, 1e308, "--out", d / "o"],
         "(20.00, 20.00, 1e+308) lies outside the image"),
        # C++ readers' own lines (GDCM, MetaIO) do not precede the error line
        (lambda d, img: ["segment", d / "empty", "--apex", 0, 0, 0, "--base", 0, 0, 9, "--out", d / "o"],
         "no DICOM series"),
        (lambda d, img: ["segment", d / "cut.mha", "--apex", 0, 0, 0, "--base", 0, 0, 9, "--out", d / "o"],
         "cannot read image"),
        (lambda d, img: ["segment", d / "huge.mhd", "--apex", 0, 0, 0, "--base", 0, 0, 9, "--out", d / "o"],
         "over the memory budget of 4 GB"),
        (lambda d, img: ["segment", d / "zeros.mha", "--apex", 5, 5, 2, "--base", 5, 5, 9, "--out", d / "o"],
         "zeros.mha: every voxel is 0: the image holds no echo data"),
        (lambda d, img: ["segment", img, "--apex", 20, 20, 20, "--base", 20, 20, 20.001, "--out", d / "o"],
         "apex and base are 0.001 mm apart"),
    ],
)
def test_bad_input_is_one_line(case, tmp_path, make_args, pattern):
    folder, image, ph = case
    img = folder / "case.mha"
    sitk.WriteImage(image, str(img))
    (tmp_path / "notes.txt").write_text("hello")
    (tmp_path / "bad.mrk.json").write_text("{not json")
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((5, 6), np.uint8)), str(tmp_path / "flat.mha"))
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((12, 11, 10), np.uint8)), str(tmp_path / "zeros.mha"), True)
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "readme.txt").write_text("no images here")
    (tmp_path / "cut.mha").write_bytes(img.read_bytes()[:4000])
    (tmp_path / "huge.mhd").write_text("ObjectType = Image\nNDims = 3\nDimSize = 2000 2000 2000\n"
                                       "ElementType = MET_FLOAT\nElementDataFile = notes.txt\n")
    before = sorted(p.name for p in tmp_path.iterdir())
    proc = run(*make_args(tmp_path, img))
    assert_one_line_error(proc, pattern)
    assert proc.returncode == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no --out left, nothing hidden


@pytest.mark.skipif(os.geteuid() == 0, reason="root ignores file permissions")
def test_unwritable_output(case, tmp_path):
    folder, image, ph = case
    img = folder / "case.mha"
    sitk.WriteImage(image, str(img))
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    shift = np.array(image.GetOrigin())
    assert_one_line_error(run("segment", img, *points_args(ph, shift), "--out", locked, "--quiet"), "not writable")


def test_profile_and_seconds_block(case, tmp_path):
    import time

    folder, image, ph = case
    path = folder / "profiled.mha"
    sitk.WriteImage(image, str(path))
    shift = np.array(image.GetOrigin())
    t0 = time.perf_counter()
    proc = run("segment", path, *points_args(ph, shift), "--out", tmp_path / "out", "--quiet", "--profile")
    wall = time.perf_counter() - t0
    assert proc.returncode == 0, proc.stderr
    seconds = json.loads((tmp_path / "out" / "results.json").read_text())["seconds"]
    stages = ["import", "read", "kernels", "padding", "segment", "descent", "mask", "meshes", "writes", "report"]
    assert sorted(seconds) == sorted(stages)
    assert all(seconds[k] > 0 for k in stages)
    # the stages happen one after the other inside the process's wall time;
    # the descent is part of the segment stage
    assert seconds["descent"] <= seconds["segment"]
    assert sum(seconds[k] for k in stages if k != "descent") < wall
    lines = proc.stderr.strip().splitlines()
    assert lines[0] == "spheroseg: seconds by stage"
    printed = {line.split()[0]: float(line.split()[1]) for line in lines[1:]}
    for k in stages:
        assert printed[k] == pytest.approx(1000 * seconds[k], abs=0.051)
    assert printed["total"] == pytest.approx(sum(printed[k] for k in stages if k != "descent"), abs=0.5)
    # without --profile nothing is printed, the block is still written
    proc = run("segment", path, *points_args(ph, shift), "--out", tmp_path / "quiet", "--quiet", "--no-report")
    assert proc.returncode == 0 and proc.stderr == ""
    assert "report" not in json.loads((tmp_path / "quiet" / "results.json").read_text())["seconds"]


def test_track_from_a_start_frame_is_recorded_and_reproduced(tmp_path):
    """``--start-frame`` is recorded in results.json; the API from the same
    frame gives the same EF to the last bit."""
    from spheroseg.tracking.segment import track

    seq = make_sequence(seed=42, n_frames=3, spacing=2.0)
    image = sitk.GetImageFromArray(np.stack([v.array for v in seq.volumes]).astype(np.uint8), isVector=False)
    image.SetSpacing((2.0, 2.0, 2.0, 1.0))
    sitk.WriteImage(image, str(tmp_path / "seq.mha"))
    clicked = seq.frames[1]
    proc = run("track", tmp_path / "seq.mha", "--apex", *clicked.apex, "--base", *clicked.base, "--out", tmp_path / "o",
               "--quiet", "--no-report", "--start-frame", 1)  # exit 0: unchecked clicks are a note
    assert proc.returncode == 0, proc.stderr
    results = json.loads((tmp_path / "o" / "results.json").read_text())
    assert results["start_frame"] == 1
    volumes = [v for v in __import__("spheroseg").load_sequence(tmp_path / "seq.mha")]
    api = track(volumes, clicked.apex, clicked.base, start_frame=1)
    assert results["ef_percent"] == api.ef
    proc = run("track", tmp_path / "seq.mha", "--apex", *clicked.apex, "--base", *clicked.base, "--out", tmp_path / "p",
               "--quiet", "--no-report", "--start-frame", 3)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "start_frame must be a frame" in proc.stderr
