"""The files a segmentation or a tracked sequence leaves in a folder.

One writer for the command line (``spheroseg segment | track``), the batch
runner (:mod:`spheroseg.batch`) and the viewer: a mask image per volume,
triangle meshes (``.vtk``, ``.ply``, optionally ``.stl``; world mm, LPS), the
Hermite surface as JSON and as CMISS ``.exnode``/``.exelem`` (prolate
surfaces), a PNG report and ``results.json``.  Every file is written to a
temporary name and renamed, so a reader never sees half a file.
"""

from __future__ import annotations

import json
import platform
import time
from pathlib import Path

import numpy as np

from .._version import __version__
from . import save_mask, write_atomically

__all__ = ["write_segmentation_outputs", "write_tracking_outputs", "write_surface_files", "write_frame_files",
           "write_json", "versions", "default_mask_suffix", "write_myocardium_files", "write_tracking_myocardium"]

_UNITS = {"points": "mm, LPS (ITK physical space)", "volume": "mL",
          "log_compression": "grey levels per neper of echo intensity"}


def versions() -> dict:
    """Versions of spheroseg, Python and the numerical libraries (recorded in results)."""
    import scipy
    import SimpleITK

    return {"spheroseg": __version__, "python": platform.python_version(), "numpy": np.__version__,
            "scipy": scipy.__version__, "SimpleITK": SimpleITK.Version_VersionString()}


def default_mask_suffix(source) -> str:
    """The mask's image type for an input: the input's own (a ``.seq.nrrd``
    or ``.nhdr`` gives ``.nrrd``), ``.nii.gz`` for folders, globs and DICOM."""
    from . import MASK_SUFFIXES, image_format

    source = Path(source)
    fmt = image_format(source) if source.is_file() else ".nii.gz"
    return {".seq.nrrd": ".nrrd", ".nhdr": ".nrrd"}.get(fmt, fmt if fmt in MASK_SUFFIXES else ".nii.gz")


def _json_default(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def write_json(path: Path, data: dict | list) -> dict | list:
    """Write ``data`` as indented JSON atomically; return it as read back
    (plain lists and numbers instead of numpy values)."""
    text = json.dumps(data, indent=1, default=_json_default)
    write_atomically(path, lambda tmp: tmp.write_text(text))
    return json.loads(text)


def write_surface_files(out: Path, stem: str, surface_name: str, result, *, stl: bool = False) -> dict:
    """Meshes ``<stem>.vtk|.ply[|.stl]``, the surface JSON and, for a prolate
    surface, its CMISS files; returns ``{kind: file name}``."""
    from .surface_io import write_cmiss, write_mesh, write_surface_json

    points, faces = result.mesh()
    files = {}
    for suffix in (".vtk", ".ply") + ((".stl",) if stl else ()):
        write_mesh(out / f"{stem}{suffix}", points, faces)
        files[f"mesh{suffix}"] = f"{stem}{suffix}"
    write_surface_json(out / surface_name, result.surface, volume_ml=result.volume_ml)
    files["surface"] = surface_name
    if result.surface.system.name == "prolate":
        exnode, exelem = write_cmiss(out / Path(surface_name).stem, result.surface)
        files["cmiss"] = [exnode.name, exelem.name]
    return files


def write_myocardium_files(out: Path, volume, result, *, mask_suffix: str = ".nii.gz") -> tuple[dict, dict]:
    """The myocardium of a result with an epicardium: its mask
    ``myocardium<mask_suffix>``, the epicardium's meshes
    ``epicardium.vtk|.ply`` (world mm, LPS) and ``epicardium.json``;
    returns ``({kind: file name}, the results.json block)``: volume, mass,
    the convention and the 17-segment table.  For a prolate model also the
    myocardium as CMISS volume elements ``heart.exnode|.exelem``
    (:func:`spheroseg.surface_io.write_cmiss_heart`)."""
    from .surface_io import write_cmiss_heart, write_mesh, write_surface_json

    epicardium = result.epicardium
    save_mask(out / ("myocardium" + mask_suffix), result.myocardium_mask(volume), volume)
    files = {"myocardium_mask": "myocardium" + mask_suffix}
    points, faces = epicardium.mesh()
    for suffix in (".vtk", ".ply"):
        write_mesh(out / f"epicardium{suffix}", points, faces)
        files[f"epicardium_mesh{suffix}"] = f"epicardium{suffix}"
    write_surface_json(out / "epicardium.json", epicardium, volume_ml=epicardium.volume_ml())
    files["epicardium_surface"] = "epicardium.json"
    if epicardium.system.name == "prolate":
        exnode, exelem = write_cmiss_heart(out / "heart", result.surface, epicardium)
        files["cmiss_heart"] = [exnode.name, exelem.name]
    block = {"myocardial_volume_ml": result.myocardial_volume_ml, "lv_mass_g": result.lv_mass_g,
             "segment_convention": result.segment_convention.to_dict(), "segments": result.segments}
    return files, block


def write_frame_files(out: Path, volumes, result, *, mask_suffix: str = ".nii.gz", stl: bool = False) -> None:
    """Per-frame masks ``masks/frame_TTT<mask_suffix>`` and surfaces
    ``meshes/frame_TTT.*`` of a tracked sequence."""
    (out / "masks").mkdir(exist_ok=True)
    (out / "meshes").mkdir(exist_ok=True)
    for t, (frame, volume) in enumerate(zip(result.frames, volumes)):
        save_mask(out / "masks" / f"frame_{t:03d}{mask_suffix}", frame.mask(volume), volume)
        write_surface_files(out / "meshes", f"frame_{t:03d}", f"frame_{t:03d}_surface.json", frame, stl=stl)


def _outcome(result) -> dict:
    """``quality`` and ``initialisation`` always (None until results carry
    them), ``status`` and
    ``message`` when the result has them."""
    outcome = {"quality": getattr(result, "quality", None), "initialisation": getattr(result, "initialisation", None)}
    for name in ("status", "message"):
        if hasattr(result, name):
            outcome[name] = getattr(result, name)
    return outcome


def _points(landmarks):
    return [] if landmarks is None else np.asarray(landmarks, dtype=float).reshape(-1, 3)


def _displayable(volume):
    """The volume on the Cartesian grid its masks are drawn on (a beam-space
    one scan-converted, for the report's slices)."""
    from ..volumes.beamspace import BeamVolume, scan_convert

    return scan_convert(volume) if isinstance(volume, BeamVolume) else volume


def _placement(result, apex, base, annulus) -> dict:
    """The points given and the plane the cavity was closed at (the base used
    is the model's origin: the annulus's centre when only that was given)."""
    pose = result.surface.pose
    if apex is None:  # located (results.json's initialisation says so)
        apex = (getattr(result, "initialisation", None) or {}).get("apex")
    return {"apex": np.asarray(apex, dtype=float), "base": pose.origin if base is None else np.asarray(base, float),
            "annulus": _points(annulus), "long_axis": pose.rotation[:, 0]}


def _start_report(path: Path, worker, volume, surface, **kwargs):
    """Start the report (in ``worker``'s process when given, else drawn
    when the returned function is called, after the other files); call that
    function to finish it."""
    from .report import report_parts, save_parts

    parts = report_parts(volume, surface, **kwargs)
    if worker is None:
        return lambda: save_parts(path, parts)
    return worker.save(path, parts)


def write_segmentation_outputs(out: Path, volume, result, *, source=None, apex, base=None, annulus=None, landmarks=None,
                               mask_suffix: str = ".nii.gz", stl: bool = False, report: bool = True,
                               seconds: dict | None = None, extra: dict | None = None, report_worker=None) -> dict:
    """Write the outputs of :func:`spheroseg.segment` into the folder ``out``.

    Files: ``mask<mask_suffix>`` (the cavity on ``volume``'s grid, 8-bit),
    ``mesh.vtk``, ``mesh.ply`` (and ``mesh.stl`` if ``stl``), ``surface.json``,
    ``surface.exnode``/``surface.exelem`` (prolate surfaces), ``report.png``
    (if ``report``) and ``results.json``.

    Parameters
    ----------
    out : Path
        Folder, created if missing.  Existing files of these names are replaced.
    volume : Volume
        The image that was segmented (the mask's grid, the report's slices).
    result : SegmentationResult
    source : str or Path, optional
        The input's path, recorded as ``input`` and named in the report title.
    apex, base : array_like (3,)
        The points given, world mm (LPS), recorded (``base`` may be None
        with an ``annulus``: the model's origin is recorded).
    annulus : array_like (k, 3), optional
        Points of the mitral annulus given, recorded with the long axis.
    landmarks : array_like (k, 3), optional
    mask_suffix : str
        Image type of the mask, e.g. ``.nii.gz``, ``.mha``, ``.npy``.
    stl, report : bool
        Also write an STL mesh; write the PNG report.
    seconds : dict, optional
        Timings to record beside the segmentation's own (e.g. ``{"load": s}``);
        the ``seconds`` block of ``results.json`` adds ``mask`` (rasterising),
        ``meshes`` (meshes, surface JSON, CMISS), ``writes`` (the mask file)
        and ``report`` (the PNG) as measured here, unless given.
    extra : dict, optional
        More top-level entries for ``results.json`` (they win over the defaults).
    report_worker : ReportWorker, optional
        Draws the report in its process while the other files are written
        (:mod:`spheroseg.report_worker`); ``seconds["report"]`` is then the
        time spent preparing it and waiting for it.  Default: drawn here.

    Returns
    -------
    dict
        The content of ``results.json`` as written (plain JSON values).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    timings = dict(seconds or {})
    timings.setdefault("segment", result.seconds)
    clock = time.perf_counter()

    def lap(stage: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        timings.setdefault(stage, now - clock)
        clock = now

    mask = result.mask(volume)
    lap("mask")
    if report:
        name = Path(source).name if source is not None else "segmentation"
        epicardium = getattr(result, "epicardium", None)
        wall = None if epicardium is None else result.wall_thickness_mm
        drawing = _start_report(out / "report.png", report_worker, _displayable(volume), result.surface, mask=mask,
                                title=f"{name}: {result.volume_ml:.1f} mL", wall_thickness_mm=wall,
                                epicardium_mask=None if epicardium is None else epicardium.mask(volume.grid))
        lap("report")
    save_mask(out / ("mask" + mask_suffix), mask, volume)
    lap("writes")
    files = {"mask": "mask" + mask_suffix, **write_surface_files(out, "mesh", "surface.json", result, stl=stl)}
    myocardium = {}
    if getattr(result, "epicardium", None) is not None:
        myocardium_files, myocardium = write_myocardium_files(out, volume, result, mask_suffix=mask_suffix)
        files.update(myocardium_files)
    lap("meshes")
    if report:
        drawing()
        files["report"] = "report.png"
        timings["report"] += time.perf_counter() - clock
    results = {
        "input": None if source is None else str(source), "volume_ml": result.volume_ml,
        "iterations": result.iterations, "converged": result.converged, **_outcome(result),
        "c_in": result.c_in, "c_out": result.c_out, "log_compression": result.log_compression, "seconds": timings,
        **_placement(result, apex, base, annulus), "landmarks": _points(landmarks),
        "parameters": result.parameters, "units": dict(_UNITS), "files": files, "versions": versions(),
        **({"myocardium": myocardium} if myocardium else {}), **(extra or {}),
    }
    return write_json(out / "results.json", results)


def write_tracking_outputs(out: Path, volumes, result, *, source=None, apex, base=None, annulus=None, landmarks=None,
                           mask_suffix: str = ".nii.gz", stl: bool = False, report: bool = True,
                           seconds: dict | None = None, extra: dict | None = None, report_worker=None) -> dict:
    """Write the outputs of :func:`spheroseg.track` into the folder ``out``.

    Files: ``masks/frame_TTT<mask_suffix>``, ``meshes/frame_TTT.vtk|.ply[|.stl]``,
    ``meshes/frame_TTT_surface.json`` and CMISS files per frame, ``report.png``
    (volume curve and the end-diastolic frame, if ``report``) and
    ``results.json`` (volumes per frame, EDV, ESV in mL, EF in percent);
    with the myocardium (``track(..., myocardium=True)``), its masks and
    block (:func:`write_tracking_myocardium`).

    Parameters
    ----------
    out : Path
    volumes : sequence of Volume
        The frames that were tracked.
    result : TrackingResult
    source, apex, base, landmarks, mask_suffix, stl, report, seconds, extra, report_worker
        As :func:`write_segmentation_outputs`; ``seconds["segment"]`` defaults
        to the list of per-frame times.

    Returns
    -------
    dict
        The content of ``results.json`` as written.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    volumes = list(volumes)
    if report:
        name = Path(source).name if source is not None else "sequence"
        ed = result.ed_frame
        drawing = _start_report(
            out / "report.png", report_worker, _displayable(volumes[ed]), result.frames[ed].surface,
            volumes_ml=result.volumes_ml, ed_frame=ed, es_frame=result.es_frame,
            title=f"{name}: EDV {result.edv_ml:.1f} mL, ESV {result.esv_ml:.1f} mL, EF {result.ef:.1f} %")
    write_frame_files(out, volumes, result, mask_suffix=mask_suffix, stl=stl)
    myocardium = (write_tracking_myocardium(out, volumes, result, mask_suffix=mask_suffix)
                  if result.frames[0].epicardium is not None else None)
    if report:
        drawing()
    timings = dict(seconds or {})
    timings.setdefault("segment", [f.seconds for f in result.frames])
    start = getattr(result, "start_frame", 0)
    first = result.frames[start]
    later = result.frames[1 if start == 0 else 0].parameters if len(result.frames) > 1 else {}
    results = {
        "input": None if source is None else str(source), "frames": len(result.frames), "start_frame": start,
        "volumes_ml": result.volumes_ml, "edv_ml": result.edv_ml, "esv_ml": result.esv_ml, "ef_percent": result.ef,
        "ed_frame": result.ed_frame, "es_frame": result.es_frame, **_outcome(result),
        "iterations": [f.iterations for f in result.frames], "log_compression": first.log_compression,
        "seconds": timings,
        **_placement(first, apex, base, annulus), "landmarks": _points(landmarks),
        "bases": [f.surface.pose.origin for f in result.frames],
        "parameters": {**first.parameters, "iterations_per_frame": later.get("max_iterations")},
        "units": {**_UNITS, "ef": "percent"}, "versions": versions(),
        **({"myocardium": myocardium} if myocardium else {}), **(extra or {}),
    }
    return write_json(out / "results.json", results)


def write_tracking_myocardium(out: Path, volumes, result, *, mask_suffix: str = ".nii.gz") -> dict:
    """Every frame's myocardium mask ``masks/frame_TTT_myocardium<mask_suffix>``
    of ``track(..., myocardium=True)``; returns the ``myocardium`` block of
    ``results.json``: mass and myocardial volume per frame, the 17
    segments' cavity volume curves (``[frame][segment - 1]``, mL), their
    times to minimum volume and the SDI (% of the cycle, the frames being
    one cycle), the segment convention."""
    from ..surfaces.myocardium import SEGMENT_NAMES

    masks = []
    for t, (frame, volume) in enumerate(zip(result.frames, volumes)):
        masks.append(f"masks/frame_{t:03d}_myocardium{mask_suffix}")
        save_mask(out / masks[-1], frame.myocardium_mask(volume), volume)
    masses = result.masses_g
    return {"lv_mass_g": masses, "myocardial_volume_ml": [f.myocardial_volume_ml for f in result.frames],
            "ed_es_mass_difference_percent": 100 * abs(masses[result.es_frame] / masses[result.ed_frame] - 1),
            "segment_convention": result.frames[0].segment_convention.to_dict(), "segment_names": SEGMENT_NAMES,
            "segment_volumes_ml": result.segment_volumes_ml, "times_to_minimum_percent": result.times_to_minimum,
            "sdi_percent": result.sdi, "masks": masks}
