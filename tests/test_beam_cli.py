"""The command line on beam-space files: scan-convert, segment, track.  One
scan-convert of each kind runs in a subprocess (the verb's whole run), the
rest through :func:`spheroseg.apps.cli.main` in this process (``conftest.cli``)."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import SimpleITK as sitk

from conftest import cli

from spheroseg.volumes.beamspace import BeamGeometry, BeamVolume, scan_convert, to_beam_space
from spheroseg.io import BEAM_KEYS, load, load_sequence, save_volume
from spheroseg.synthetic.phantom import make_phantom, make_sequence, probe_sector


def run(*args):
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    return subprocess.run([sys.executable, "-m", "spheroseg", *map(str, args)], capture_output=True, text=True,
                          env=env, timeout=300)


def assert_one_line_error(proc, pattern):
    assert proc.returncode != 0
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("spheroseg: error:"), proc.stderr
    assert pattern.lower() in lines[0].lower(), lines[0]


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    folder = tmp_path_factory.mktemp("beam")
    ph = make_phantom(seed=41, spacing=1.5)
    beam = to_beam_space(ph.volume, probe_sector(ph.volume, shape=(110, 41, 41), radius_spacing=1.4, angle_deg=1.4, convention="sin"))
    save_volume(folder / "beam.mha", beam)
    return folder, ph, beam


def test_scan_convert_verb(capfd, case, tmp_path):
    folder, _, beam = case
    proc = run("scan-convert", folder / "beam.mha", tmp_path / "cart.nii.gz", "--voxel-size", "2", "--quiet")
    assert proc.returncode == 0, proc.stderr
    out = load(tmp_path / "cart.nii.gz")
    expected = scan_convert(beam, beam.geometry.cartesian_grid(2.0))
    np.testing.assert_allclose(out.array, expected.array, atol=1e-3)
    np.testing.assert_array_equal(out.no_data_mask, expected.no_data_mask)
    np.testing.assert_allclose(out.origin, expected.origin, atol=1e-4)
    # never over an existing output without --force, never over the input
    assert_one_line_error(cli(capfd, "scan-convert", folder / "beam.mha", tmp_path / "cart.nii.gz"), "exists")
    assert_one_line_error(cli(capfd, "scan-convert", folder / "beam.mha", folder / "beam.mha", "--force"),
                          "would overwrite an input")
    assert cli(capfd, "scan-convert", folder / "beam.mha", tmp_path / "cart.nii.gz", "--force", "--nearest",
               "--quiet").returncode == 0


def test_scan_convert_a_sequence(tmp_path):
    g = BeamGeometry((12, 5, 7), 2.0, 10.0, 0.05, 0.05)
    frames = [BeamVolume(np.full(g.shape, 10.0 * (k + 1)), g) for k in range(3)]
    save_volume(tmp_path / "seq.nrrd", frames)
    proc = run("scan-convert", tmp_path / "seq.nrrd", tmp_path / "cart.mha", "--quiet")
    assert proc.returncode == 0, proc.stderr
    out = load_sequence(tmp_path / "cart.mha")
    assert len(out) == 3
    for k, v in enumerate(out):
        inside = ~v.no_data_mask
        assert inside.mean() > 0.3
        np.testing.assert_allclose(v.array[inside], 10.0 * (k + 1), rtol=1e-6)


def test_scan_convert_errors(capfd, case, tmp_path):
    folder, ph, _ = case
    image = sitk.GetImageFromArray(np.ones((6, 5, 4), np.float32))
    sitk.WriteImage(image, str(tmp_path / "cartesian.mha"))
    assert_one_line_error(cli(capfd, "scan-convert", tmp_path / "cartesian.mha", tmp_path / "o.mha"),
                          "not a beam-space")
    image.SetMetaData(BEAM_KEYS[0], "0.02")
    sitk.WriteImage(image, str(tmp_path / "half.mha"))
    assert_one_line_error(cli(capfd, "scan-convert", tmp_path / "half.mha", tmp_path / "o.mha"),
                          "missing ElevationAngular")
    assert_one_line_error(cli(capfd, "scan-convert", folder / "beam.mha", tmp_path / "o.npy"), "must be one of")
    assert_one_line_error(cli(capfd, "scan-convert", tmp_path / "absent.mha", tmp_path / "o.mha"), "no such file")
    assert_one_line_error(cli(capfd, "scan-convert", folder / "beam.mha", tmp_path / "o.mha", "--voxel-size", "0"),
                          "positive")


def test_segment_a_beam_space_file(capfd, case, tmp_path):
    folder, ph, beam = case
    out = tmp_path / "seg"
    proc = cli(capfd, "segment", folder / "beam.mha", "--apex", *ph.apex, "--base", *ph.base, "--out", out, "--quiet")
    assert proc.returncode == 0, proc.stderr
    results = json.loads((out / "results.json").read_text())
    assert results["volume_ml"] == pytest.approx(ph.truth_volume_ml, rel=0.12)
    mask = load(out / "mask.mha", no_data_value=None)
    assert mask.shape == beam.grid.shape
    np.testing.assert_allclose(mask.origin, beam.grid.origin, atol=1e-4)
    mask_ml = mask.array.sum() * np.prod(mask.spacing) / 1000
    assert mask_ml == pytest.approx(results["volume_ml"], rel=0.03)
    assert (out / "report.png").stat().st_size > 10_000
    # a beam-space file has no spacing to override
    assert_one_line_error(cli(capfd, "segment", folder / "beam.mha", "--apex", *ph.apex, "--base", *ph.base, "--out",
                              tmp_path / "x", "--spacing", "1", "1", "1"), "no voxel spacing")


def test_track_a_beam_space_sequence(capfd, tmp_path):
    seq = make_sequence(n_frames=3, seed=7, spacing=2.0)
    g = probe_sector(seq.volumes[0], shape=(110, 41, 41), radius_spacing=1.4, angle_deg=1.4)
    save_volume(tmp_path / "seq.mha", [to_beam_space(v, g) for v in seq.volumes])
    apex, base = seq.frames[0].apex, seq.frames[0].base
    proc = cli(capfd, "track", tmp_path / "seq.mha", "--apex", *apex, "--base", *base, "--out", tmp_path / "t",
               "--quiet", "--no-report")
    assert proc.returncode == 0, proc.stderr
    results = json.loads((tmp_path / "t" / "results.json").read_text())
    assert results["frames"] == 3
    assert len(list((tmp_path / "t" / "masks").iterdir())) == 3
