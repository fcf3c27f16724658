"""Reading and writing images of the field through SimpleITK.

MetaImage (.mhd/.raw, .mha: the CETUS format), NIfTI (.nii, .nii.gz), NRRD
(.nrrd, .nhdr; 3D Slicer's 3D+t ``.seq.nrrd``), DICOM series (a folder), and
plain numpy ``.npy`` arrays (no geometry: give the spacing).  Geometry is
ITK's physical space: LPS, millimetres.
"""

from __future__ import annotations

import glob
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from .volume import Volume, outside_sector

__all__ = ["load", "load_sequence", "save_mask", "read_markups", "write_markups", "image_format", "IMAGE_SUFFIXES",
           "MASK_SUFFIXES",
           "write_atomically", "ImageFileError"]

IMAGE_SUFFIXES = (".mhd", ".mha", ".nii", ".nii.gz", ".nrrd", ".nhdr", ".npy")
#: what a mask can be written as
MASK_SUFFIXES = (".mhd", ".mha", ".nii", ".nii.gz", ".nrrd", ".npy")


class ImageFileError(ValueError):
    """A file that exists but cannot be read as an image (as nibabel's
    ``ImageFileError``; a ``ValueError``, so ``except ValueError`` catches it)."""


def _missing(path) -> FileNotFoundError:
    return FileNotFoundError(f"{path}: no such file")


def image_format(path: str | os.PathLike) -> str:
    """The image suffix of a path (``.nii.gz`` counts as one), lower case."""
    name = Path(path).name.lower()
    for suffix in (".seq.nrrd", ".nii.gz"):
        if name.endswith(suffix):
            return suffix
    return Path(name).suffix


def _sitk():
    import SimpleITK as sitk

    return sitk


def _read_image(path: Path):
    sitk = _sitk()
    if path.is_dir():
        reader = sitk.ImageSeriesReader()
        series = reader.GetGDCMSeriesIDs(str(path))
        if not series:
            raise ImageFileError(f"{path}: a folder with no DICOM series (for a folder of 3D frames use load_sequence)")
        reader.SetFileNames(reader.GetGDCMSeriesFileNames(str(path), series[0]))
        return reader.Execute()
    if not path.is_file():
        raise _missing(path)
    try:
        return sitk.ReadImage(str(path))
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()
        detail = next((line for line in first if "ERROR" in line or "Unable" in line), first[-1] if first else "")
        raise ImageFileError(f"{path}: cannot read image ({detail.strip()[:200]})") from None


def _make_volume(array, no_data_value, **geometry) -> Volume:
    """A Volume whose no-data voxels follow ``no_data_value``: a value,
    ``None``, or ``"auto"`` (the zero padding around an echo sector)."""
    if isinstance(no_data_value, str):
        if no_data_value != "auto":
            raise ValueError(f"no_data_value must be a number, None or 'auto', got {no_data_value!r}")
        return Volume(array, **geometry, no_data_mask=outside_sector(array))
    return Volume(array, **geometry, no_data_value=no_data_value)


def _volume_from_image(image, no_data_value) -> Volume:
    sitk = _sitk()
    if image.GetDimension() != 3:
        raise ValueError(f"expected a 3D image, got {image.GetDimension()}D")
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise ValueError(f"expected a scalar image, got {image.GetNumberOfComponentsPerPixel()} components per voxel")
    return _make_volume(
        sitk.GetArrayFromImage(image),
        no_data_value,
        spacing=image.GetSpacing(),
        origin=image.GetOrigin(),
        direction=np.array(image.GetDirection()).reshape(3, 3),
    )


def load(path: str | os.PathLike, *, spacing=None, no_data_value: float | str | None = "auto") -> Volume:
    """Read a 3D image as a :class:`Volume` (geometry kept: LPS, mm).

    Parameters
    ----------
    path : str or Path
        An image file SimpleITK reads, a DICOM series folder, or ``.npy``
        (indexed ``[z, y, x]``, origin 0, identity direction).
    spacing : (x, y, z) floats, optional
        Required for ``.npy``; overrides the file's spacing otherwise.
    no_data_value : float, None or "auto"
        Voxels without data: those of this value, none, or (``"auto"``, the
        default) the exact zeros connected to the image's faces, i.e. the
        black padding around a scan-converted echo sector (CETUS).
    """
    path = Path(path)
    if image_format(path) == ".npy":
        if not path.is_file():
            raise _missing(path)
        try:
            array = np.load(path, allow_pickle=False)
        except (ValueError, OSError) as exc:
            raise ImageFileError(f"{path}: cannot read numpy array ({exc})") from None
        if spacing is None:
            raise ValueError(f"{path}: a .npy array has no geometry; give its voxel spacing")
        return _make_volume(array, no_data_value, spacing=spacing)
    image = _read_image(path)
    if image.GetDimension() == 4 or image.GetNumberOfComponentsPerPixel() > 1:
        raise ValueError(f"{path}: a 3D+t image; use load_sequence (spheroseg track)")
    if image.GetDimension() != 3:
        raise ValueError(f"{path}: expected a 3D image, got {image.GetDimension()}D")
    volume = _volume_from_image(image, no_data_value)
    if spacing is not None:
        volume = Volume(volume.array, spacing=spacing, origin=volume.origin, direction=volume.direction,
                        no_data_mask=volume.no_data_mask)
    return volume


def load_sequence(path: str | os.PathLike, *, spacing=None, no_data_value: float | str | None = "auto") -> list[Volume]:
    """Read a 3D+t sequence as a list of :class:`Volume`.

    Accepts a 4D image (.mha, .nrrd, .nii: the fourth axis is time), a
    vector image whose components are frames (3D Slicer's ``.seq.nrrd``), a
    folder of 3D frames or a glob pattern (frames in name order), a
    DICOM series folder holding a 4D image, or a 4D ``.npy`` ``[t, z, y, x]``.
    """
    sitk = _sitk()
    path_str = str(path)
    if any(ch in path_str for ch in "*?["):
        files = sorted(glob.glob(path_str))
        if not files:
            raise ValueError(f"{path_str}: no files match")
        return [load(f, spacing=spacing, no_data_value=no_data_value) for f in files]
    path = Path(path)
    if path.is_dir():
        frames = sorted(p for p in path.iterdir() if image_format(p) in IMAGE_SUFFIXES and p.suffix != ".raw")
        if frames:
            return [load(f, spacing=spacing, no_data_value=no_data_value) for f in frames]
    if image_format(path) == ".npy":
        if not path.is_file():
            raise _missing(path)
        try:
            array = np.load(path, allow_pickle=False)
        except (ValueError, OSError) as exc:
            raise ImageFileError(f"{path}: cannot read numpy array ({exc})") from None
        if array.ndim != 4:
            raise ValueError(f"{path}: expected a 4D array [t, z, y, x], got {array.ndim}D")
        if spacing is None:
            raise ValueError(f"{path}: a .npy array has no geometry; give its voxel spacing")
        return [_make_volume(a, no_data_value, spacing=spacing) for a in array]
    image = _read_image(path)
    if image.GetNumberOfComponentsPerPixel() > 1 and image.GetDimension() == 3:
        frames = [sitk.VectorIndexSelectionCast(image, k) for k in range(image.GetNumberOfComponentsPerPixel())]
    elif image.GetDimension() == 4:
        size = image.GetSize()
        frames = [sitk.Extract(image, size[:3] + (0,), [0, 0, 0, t]) for t in range(size[3])]
    else:
        raise ValueError(f"{path}: expected a 3D+t image (4D, or frames as components), got a {image.GetDimension()}D image")
    volumes = [_volume_from_image(f, no_data_value) for f in frames]
    if spacing is not None:
        volumes = [Volume(v.array, spacing=spacing, origin=v.origin, direction=v.direction, no_data_mask=v.no_data_mask)
                   for v in volumes]
    return volumes


def write_atomically(target: str | os.PathLike, write) -> None:
    """Call ``write(tmp_path)`` on a path in a temporary folder beside
    ``target``, then move every file it made into ``target``'s folder
    (a MetaImage header and its .raw move together)."""
    target = Path(target)
    tmpdir = Path(tempfile.mkdtemp(prefix=".spheroseg-", dir=target.parent))
    try:
        write(tmpdir / target.name)
        for produced in tmpdir.iterdir():
            os.replace(produced, target.parent / produced.name)
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)


def save_mask(path: str | os.PathLike, mask: np.ndarray, like: Volume) -> None:
    """Write a boolean mask as an 8-bit image with ``like``'s geometry."""
    sitk = _sitk()
    path = Path(path)
    if image_format(path) == ".npy":
        write_atomically(path, lambda tmp: np.save(tmp, np.asarray(mask, dtype=np.uint8)))
        return
    image = sitk.GetImageFromArray(np.asarray(mask, dtype=np.uint8))
    image.SetSpacing(tuple(float(s) for s in like.spacing))
    image.SetOrigin(tuple(float(o) for o in like.origin))
    image.SetDirection(tuple(float(d) for d in like.direction.ravel()))
    write_atomically(path, lambda tmp: sitk.WriteImage(image, str(tmp), True))


def read_markups(path: str | os.PathLike) -> dict:
    """Points from a 3D Slicer markups file (``.mrk.json``), in LPS mm.

    Control points labelled ``apex`` and ``base`` (any case) give those;
    every label starting with ``annulus`` is a point of the mitral annulus
    (three or more define the mitral plane), every label starting with
    ``landmark`` a landmark.  RAS files are converted to LPS.

    Returns
    -------
    dict
        ``{"apex": array or None, "base": array or None, "annulus": array (k, 3),
        "landmarks": array (k, 3)}``
    """
    import json

    path = Path(path)
    if not path.is_file():
        raise _missing(path)
    try:
        doc = json.loads(path.read_text())
        out = {"apex": None, "base": None, "annulus": [], "landmarks": []}
        for markup in doc["markups"]:
            ras = str(markup.get("coordinateSystem", "LPS")).upper() == "RAS"
            for point in markup.get("controlPoints", []):
                position = np.asarray(point["position"], dtype=float).reshape(3)
                if ras:
                    position = position * [-1.0, -1.0, 1.0]
                label = str(point.get("label", "")).strip().lower()
                if label in ("apex", "base"):
                    out[label] = position
                elif label.startswith("annulus"):
                    out["annulus"].append(position)
                elif label.startswith("landmark"):
                    out["landmarks"].append(position)
    except OSError as exc:
        raise ValueError(f"{path}: cannot read markups ({exc.strerror})") from None
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise ValueError(f"{path}: not a 3D Slicer markups file with control points ({type(exc).__name__}: {exc})") from None
    out["landmarks"] = np.array(out["landmarks"]).reshape(-1, 3)
    out["annulus"] = np.array(out["annulus"]).reshape(-1, 3)
    return out


def write_markups(path: str | os.PathLike, *, apex=None, base=None, annulus=None, landmarks=None) -> None:
    """Write points as a 3D Slicer markups file (``.mrk.json``, LPS mm) that
    :func:`read_markups` reads back: control points labelled ``apex``,
    ``base``, ``annulus`` (each annulus point) and ``landmark-1``, ...

    Parameters
    ----------
    path : str or Path
    apex, base : (x, y, z), optional
    annulus, landmarks : array (k, 3), optional
    """
    import json

    named = [("apex", apex), ("base", base)]
    named += [("annulus", p) for p in ([] if annulus is None else annulus)]
    named += [(f"landmark-{k + 1}", p) for k, p in enumerate([] if landmarks is None else landmarks)]
    points = []
    for label, position in named:
        if position is None:
            continue
        position = np.asarray(position, dtype=float)
        if position.shape != (3,) or not np.all(np.isfinite(position)):
            raise ValueError(f"{label} must be 3 finite numbers (x, y, z in mm), got {position.tolist()!r}")
        points.append({"id": str(len(points) + 1), "label": label, "position": position.tolist(),
                       "positionStatus": "defined"})
    doc = {"@schema": "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/Resources/"
                      "Schema/markups-schema-v1.0.3.json#",
           "markups": [{"type": "Fiducial", "coordinateSystem": "LPS", "coordinateUnits": "mm",
                        "controlPoints": points}]}
    write_atomically(path, lambda tmp: Path(tmp).write_text(json.dumps(doc, indent=1)))
