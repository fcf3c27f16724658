"""The output writers shared by the CLI, the batch runner and the viewer."""

import json

import numpy as np
import pytest
import SimpleITK as sitk

from spheroseg.io.outputs import write_segmentation_outputs, write_tracking_outputs
from spheroseg.synthetic.phantom import make_phantom, make_sequence
from spheroseg.tracking.segment import segment, track
from spheroseg.io.surface_io import read_surface_json

SEGMENT_KEYS = {"input", "volume_ml", "iterations", "converged", "status", "message", "quality", "c_in", "c_out",
                "log_compression", "seconds", "apex", "base", "landmarks", "parameters", "units", "files", "versions"}
TRACK_KEYS = {"input", "frames", "volumes_ml", "edv_ml", "esv_ml", "ef_percent", "ed_frame", "es_frame", "quality",
              "iterations", "log_compression", "seconds", "apex", "base", "parameters", "units", "versions"}


class WithQuality:
    """A result that carries ``quality`` (as another issue adds it)."""

    def __init__(self, result, quality):
        self._result, self.quality = result, quality

    def __getattr__(self, name):
        return getattr(self._result, name)


def test_segmentation_outputs_round_trip(tmp_path):
    ph = make_phantom(seed=5, spacing=2.5)
    result = segment(ph.volume, ph.apex, ph.base)
    landmark = (ph.apex + ph.base) / 2 + [10.0, 0, 0]
    written = write_segmentation_outputs(
        tmp_path / "o", ph.volume, WithQuality(result, {"score": 0.5}), source="case.mha", apex=ph.apex,
        base=ph.base, landmarks=[landmark], mask_suffix=".mha", report=False, seconds={"load": 0.25},
        extra={"id": "p01"})
    on_disk = json.loads((tmp_path / "o" / "results.json").read_text())
    assert written == on_disk
    assert SEGMENT_KEYS <= set(on_disk) and on_disk["id"] == "p01"
    assert on_disk["quality"] == {"score": 0.5}
    assert on_disk["status"] == result.status and on_disk["message"] == result.message
    # the caller's timings kept; the writer's own stages measured (no report here)
    seconds = on_disk["seconds"]
    assert {k: seconds.pop(k) for k in ("load", "segment")} == {"load": 0.25, "segment": result.seconds}
    assert set(seconds) == {"mask", "writes", "meshes"} and all(v > 0 for v in seconds.values())
    assert on_disk["volume_ml"] == pytest.approx(result.volume_ml, rel=1e-12)
    assert on_disk["log_compression"] == result.log_compression > 0  # the intensity interface's estimate
    np.testing.assert_allclose(on_disk["landmarks"], [landmark])
    mask = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "o" / on_disk["files"]["mask"]))).astype(bool)
    np.testing.assert_array_equal(mask, result.mask(ph.volume))
    surface = read_surface_json(tmp_path / "o" / "surface.json")
    assert surface.volume_ml() == pytest.approx(result.volume_ml, rel=1e-9)
    assert not (tmp_path / "o" / "report.png").exists()
    assert sorted(p.name for p in (tmp_path / "o").iterdir() if p.name.startswith(".")) == []


def test_tracking_outputs_round_trip(tmp_path):
    seq = make_sequence(seed=6, n_frames=3, spacing=2.5)
    first = seq.frames[0]
    result = track(seq.volumes, first.apex, first.base, iterations_per_frame=7)
    written = write_tracking_outputs(tmp_path, seq.volumes, result, apex=first.apex, base=first.base)
    on_disk = json.loads((tmp_path / "results.json").read_text())
    assert written == on_disk and TRACK_KEYS <= set(on_disk)
    assert on_disk["quality"] == json.loads(json.dumps(result.quality)) and on_disk["input"] is None
    assert len(on_disk["quality"]["frames"]) == 3 and on_disk["quality"]["poor"] == bool(on_disk["quality"]["warnings"])
    assert on_disk["parameters"]["iterations_per_frame"] == 7
    assert on_disk["log_compression"] == result.frames[0].log_compression > 0
    np.testing.assert_allclose(on_disk["volumes_ml"], result.volumes_ml, rtol=1e-12)
    assert on_disk["ef_percent"] == pytest.approx(100 * (1 - on_disk["esv_ml"] / on_disk["edv_ml"]))
    masks = sorted((tmp_path / "masks").iterdir())
    assert [m.name for m in masks] == [f"frame_{t:03d}.nii.gz" for t in range(3)]
    for t, path in enumerate(masks):
        mask = sitk.GetArrayFromImage(sitk.ReadImage(str(path))).astype(bool)
        np.testing.assert_array_equal(mask, result.frames[t].mask(seq.volumes[t]))
    assert (tmp_path / "report.png").read_bytes()[:4] == b"\x89PNG"


def test_myocardium_outputs_round_trip(tmp_path):
    from spheroseg.io.surface_io import read_mesh

    ph = make_phantom(seed=5, spacing=2.5)
    result = segment(ph.volume, ph.apex, ph.base, myocardium=True)
    on_disk = write_segmentation_outputs(tmp_path / "o", ph.volume, result, apex=ph.apex, base=ph.base,
                                         mask_suffix=".mha", report=False)
    files, block = on_disk["files"], on_disk["myocardium"]
    mask = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "o" / files["myocardium_mask"]))).astype(bool)
    np.testing.assert_array_equal(mask, result.myocardium_mask(ph.volume))
    assert block["lv_mass_g"] == pytest.approx(result.lv_mass_g, rel=1e-12)
    assert [row["segment"] for row in block["segments"]] == list(range(1, 18))
    epicardium = read_surface_json(tmp_path / "o" / files["epicardium_surface"])
    np.testing.assert_allclose(epicardium.coefficients, result.epicardium.coefficients, rtol=1e-12)
    points, _ = read_mesh(tmp_path / "o" / files["epicardium_mesh.ply"])
    np.testing.assert_allclose(points, result.epicardium.mesh()[0], atol=1e-4)
    assert b"SPACE=LPS" in (tmp_path / "o" / files["epicardium_mesh.vtk"]).read_bytes()[:300]
    assert files["cmiss_heart"] == ["heart.exnode", "heart.exelem"]
    assert (tmp_path / "o" / "heart.exelem").read_text().count("Element:") == 64
