"""Reading and writing images of the field through SimpleITK.

MetaImage (.mhd/.raw, .mha: the CETUS format), NIfTI (.nii, .nii.gz), NRRD
(.nrrd, .nhdr; 3D Slicer's 3D+t ``.seq.nrrd``), DICOM series (a folder), and
plain numpy ``.npy`` arrays (no geometry: give the spacing).  Geometry is
ITK's physical space: LPS, millimetres.

Beam-space volumes (:class:`~spheroseg.beamspace.BeamVolume`) are MetaImage
or NRRD files whose header carries ITK's ``PhasedArray3DSpecialCoordinatesImage``
fields under ITK's names (:data:`BEAM_KEYS`, all four required) and
spheroseg's optional ones (:data:`BEAM_OPTIONAL_KEYS`); the array is
``[radius, elevation, azimuth]`` (ITK index ``(azimuth, elevation, radius)``)
with offset 0, spacing 1 and identity direction, which ITK ignores for that
image type.
"""

from __future__ import annotations

import glob
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from .beamspace import CONVENTIONS, BeamGeometry, BeamVolume
from .raster import outside_sector
from .volume import ImageGrid, Volume

__all__ = ["load", "load_sequence", "load_frames", "save_mask", "save_volume", "read_markups", "write_markups", "image_format",
           "IMAGE_SUFFIXES", "MASK_SUFFIXES", "BEAM_SUFFIXES", "BEAM_KEYS", "BEAM_OPTIONAL_KEYS", "beam_header",
           "beam_geometry_from_header", "write_atomically", "ImageFileError"]

IMAGE_SUFFIXES = (".mhd", ".mha", ".nii", ".nii.gz", ".nrrd", ".nhdr", ".npy")
#: what a mask can be written as
MASK_SUFFIXES = (".mhd", ".mha", ".nii", ".nii.gz", ".nrrd", ".npy")
#: what keeps a beam-space header (NIfTI drops unknown keys)
BEAM_SUFFIXES = (".mhd", ".mha", ".nrrd", ".nhdr", ".seq.nrrd")
#: ITK PhasedArray3DSpecialCoordinatesImage fields: radians, radians, mm, mm
BEAM_KEYS = ("AzimuthAngularSeparation", "ElevationAngularSeparation", "RadiusSampleSize", "FirstSampleDistance")
#: spheroseg's additions, defaults reproducing ITK: convention "tan", centre
#: indices (n - 1) / 2, identity probe pose (16 numbers, row-major, mm), no
#: no-data value
BEAM_OPTIONAL_KEYS = ("BeamSpaceConvention", "AzimuthCenterIndex", "ElevationCenterIndex", "ProbeToWorldTransform",
                      "NoDataValue")


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
        array = np.asarray(array)
        if array.dtype.kind in "iu":
            # the Volume keeps these float32 voxels (it takes them without a
            # copy) and they have the same zeros: the search reads them in place
            array = np.ascontiguousarray(array, dtype=np.float32)
        return Volume(array, **geometry, no_data_mask=outside_sector(array))
    return Volume(array, **geometry, no_data_value=no_data_value)


def _voxels(image) -> np.ndarray:
    """The image's voxels ``[z, y, x]`` for a :class:`Volume`, which converts
    them to a new float32 array: a view of SimpleITK's buffer (no copy
    before that conversion), or a copy when they are float32 already (the
    conversion would keep the view, which must not outlive ``image``)."""
    view = _sitk().GetArrayViewFromImage(image)
    return view.copy() if view.dtype == np.float32 else view


def _volume_from_image(image, no_data_value) -> Volume:
    if image.GetDimension() != 3:
        raise ValueError(f"expected a 3D image, got {image.GetDimension()}D")
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise ValueError(f"expected a scalar image, got {image.GetNumberOfComponentsPerPixel()} components per voxel")
    return _make_volume(
        _voxels(image),
        no_data_value,
        spacing=image.GetSpacing(),
        origin=image.GetOrigin(),
        direction=np.array(image.GetDirection()).reshape(3, 3),
    )


def beam_header(geometry: BeamGeometry, *, no_data_value: float | None = None) -> dict[str, str]:
    """The header keys of a beam-space file for ``geometry`` (values as text,
    ``repr`` precision)."""
    e_c, a_c = geometry.centre_index
    keys = {
        "AzimuthAngularSeparation": repr(geometry.azimuth_angular_separation),
        "ElevationAngularSeparation": repr(geometry.elevation_angular_separation),
        "RadiusSampleSize": repr(geometry.radius_sample_size),
        "FirstSampleDistance": repr(geometry.first_sample_distance),
        "BeamSpaceConvention": geometry.convention,
        "AzimuthCenterIndex": repr(a_c),
        "ElevationCenterIndex": repr(e_c),
        "ProbeToWorldTransform": " ".join(repr(float(v)) for v in geometry.probe_to_world.ravel()),
    }
    if no_data_value is not None:
        keys["NoDataValue"] = repr(float(no_data_value))
    return keys


def _numbers(keys: dict, name: str, count: int, source) -> np.ndarray:
    try:
        values = np.array([float(v) for v in str(keys[name]).replace(",", " ").split()])
    except ValueError:
        values = np.array([])
    if len(values) != count or not np.all(np.isfinite(values)):
        what = "a number" if count == 1 else f"{count} numbers"
        raise ImageFileError(f"{source}: header key {name} must be {what}, got {keys[name]!r}")
    return values


def beam_geometry_from_header(keys: dict, shape, *, source="header") -> tuple[BeamGeometry, float | None] | None:
    """The beam geometry (and ``NoDataValue``, or ``None``) a header describes;
    ``None`` when it has none of :data:`BEAM_KEYS` and :data:`BEAM_OPTIONAL_KEYS`.

    Parameters
    ----------
    keys : dict
        Header keys and their text values (SimpleITK's meta-data).
    shape : (n_r, n_e, n_a)
        The array's shape.

    Raises
    ------
    ImageFileError
        For missing or contradictory keys, with the file (``source``) named.
    """
    present = [k for k in BEAM_KEYS + BEAM_OPTIONAL_KEYS if k in keys]
    if not present:
        return None
    missing = [k for k in BEAM_KEYS if k not in keys]
    if missing:
        raise ImageFileError(f"{source}: a beam-space header needs {', '.join(BEAM_KEYS)}; missing "
                             f"{', '.join(missing)} (it has {', '.join(present)})")
    az, el, dr, r0 = (_numbers(keys, k, 1, source)[0] for k in BEAM_KEYS)
    convention = str(keys.get("BeamSpaceConvention", "tan")).strip().lower()
    if convention not in CONVENTIONS:
        raise ImageFileError(f"{source}: BeamSpaceConvention must be one of {', '.join(CONVENTIONS)}, "
                             f"got {keys['BeamSpaceConvention']!r}")
    centre = None
    given = [k in keys for k in ("ElevationCenterIndex", "AzimuthCenterIndex")]
    if any(given):
        if not all(given):
            raise ImageFileError(f"{source}: give both ElevationCenterIndex and AzimuthCenterIndex, or neither")
        centre = tuple(_numbers(keys, k, 1, source)[0] for k in ("ElevationCenterIndex", "AzimuthCenterIndex"))
    pose = np.eye(4) if "ProbeToWorldTransform" not in keys else \
        _numbers(keys, "ProbeToWorldTransform", 16, source).reshape(4, 4)
    no_data = _numbers(keys, "NoDataValue", 1, source)[0] if "NoDataValue" in keys else None
    try:
        geometry = BeamGeometry(tuple(shape), dr, r0, az, el, convention=convention, centre_index=centre,
                                probe_to_world=pose)
    except ValueError as exc:
        raise ImageFileError(f"{source}: {exc}") from None
    return geometry, no_data


def _meta(image) -> dict:
    return {k: image.GetMetaData(k) for k in image.GetMetaDataKeys()}


def _beam_geometry(image, path, spacing):
    """The beam geometry of a read image (3D, or 4D with time last), or None."""
    found = beam_geometry_from_header(_meta(image), image.GetSize()[:3][::-1], source=path)
    if found is None:
        return None
    d = image.GetDimension()
    direction = np.array(image.GetDirection()).reshape(d, d)[:3, :3]
    if (not np.allclose(image.GetOrigin()[:3], 0) or not np.allclose(image.GetSpacing()[:3], 1)
            or not np.allclose(direction, np.eye(3))):
        raise ImageFileError(f"{path}: a beam-space file must have offset 0, spacing 1 and identity direction "
                             "(ITK ignores them): put the probe's pose in ProbeToWorldTransform")
    if spacing is not None:
        raise ValueError(f"{path}: a beam-space file has no voxel spacing to override")
    return found


def _make_beam_volume(array, found, no_data_value) -> BeamVolume:
    geometry, header_no_data = found
    if isinstance(no_data_value, str):
        if no_data_value != "auto":
            raise ValueError(f"no_data_value must be a number, None or 'auto', got {no_data_value!r}")
        no_data_value = header_no_data
    return BeamVolume(array, geometry, no_data_value=no_data_value)


def load(path: str | os.PathLike, *, spacing=None,
         no_data_value: float | str | None = "auto") -> Volume | BeamVolume:
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
        black padding around a scan-converted echo sector (CETUS); for a
        beam-space file, ``"auto"`` is its ``NoDataValue`` key, if any.

    Returns
    -------
    Volume or BeamVolume
        A :class:`~spheroseg.beamspace.BeamVolume` for a file with the
        beam-space keys (:data:`BEAM_KEYS`).
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
    beam = _beam_geometry(image, path, spacing)
    if beam is not None:
        return _make_beam_volume(_sitk().GetArrayFromImage(image), beam, no_data_value)
    volume = _volume_from_image(image, no_data_value)
    if spacing is not None:
        volume = Volume(volume.array, spacing=spacing, origin=volume.origin, direction=volume.direction,
                        no_data_mask=volume.no_data_mask)
    return volume


def load_frames(path: str | os.PathLike, *, spacing=None,
                no_data_value: float | str | None = "auto") -> list[Volume] | list[BeamVolume]:
    """Read a 3D image as one frame, or a 3D+t sequence as its frames
    (whichever the file holds; the keywords are :func:`load`'s).

    A folder or a glob pattern is a sequence (:func:`load_sequence`), as is
    a 4D image, a 3D image of several components or a 4D ``.npy``.
    """
    path_str = str(path)
    path = Path(path)
    if any(ch in path_str for ch in "*?[") or path.is_dir():
        return load_sequence(path_str, spacing=spacing, no_data_value=no_data_value)
    if image_format(path) == ".npy":
        if not path.is_file():
            raise _missing(path)
        try:
            sequence = np.load(path, mmap_mode="r", allow_pickle=False).ndim == 4
        except (ValueError, OSError):
            sequence = False  # load says why, in one line
    else:
        if not path.is_file():
            raise _missing(path)
        reader = _sitk().ImageFileReader()
        reader.SetFileName(str(path))
        try:
            reader.ReadImageInformation()
        except RuntimeError:
            return [load(path, spacing=spacing, no_data_value=no_data_value)]  # load says why, in one line
        sequence = reader.GetDimension() == 4 or reader.GetNumberOfComponents() > 1
    if sequence:
        return load_sequence(path, spacing=spacing, no_data_value=no_data_value)
    return [load(path, spacing=spacing, no_data_value=no_data_value)]


def load_sequence(path: str | os.PathLike, *, spacing=None,
                  no_data_value: float | str | None = "auto") -> list[Volume] | list[BeamVolume]:
    """Read a 3D+t sequence as a list of :class:`Volume` (of
    :class:`~spheroseg.beamspace.BeamVolume` for beam-space files).

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
    beam = _beam_geometry(image, path, spacing) if image.GetDimension() in (3, 4) else None
    if image.GetNumberOfComponentsPerPixel() > 1 and image.GetDimension() == 3:
        frames = [sitk.VectorIndexSelectionCast(image, k) for k in range(image.GetNumberOfComponentsPerPixel())]
    elif image.GetDimension() == 4:
        size = image.GetSize()
        frames = [sitk.Extract(image, size[:3] + (0,), [0, 0, 0, t]) for t in range(size[3])]
    else:
        raise ValueError(f"{path}: expected a 3D+t image (4D, or frames as components), got a {image.GetDimension()}D image")
    if beam is not None:
        return [_make_beam_volume(sitk.GetArrayFromImage(f), beam, no_data_value) for f in frames]
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


def save_mask(path: str | os.PathLike, mask: np.ndarray, like: Volume | BeamVolume | ImageGrid) -> None:
    """Write a boolean mask as an 8-bit image on ``like``'s grid (a
    :class:`~spheroseg.beamspace.BeamVolume`'s is the Cartesian grid covering
    its sector)."""
    sitk = _sitk()
    path = Path(path)
    grid = like if isinstance(like, ImageGrid) else like.grid
    mask = np.asarray(mask)
    # a boolean mask is its bytes already (a copy of a 256^3 one costs 5-10 ms in a fresh process)
    mask = mask.view(np.uint8) if mask.dtype == np.bool_ else mask.astype(np.uint8)
    if mask.shape != grid.shape:
        raise ValueError(f"the mask's shape {mask.shape} is not its grid's {grid.shape}")
    if image_format(path) == ".npy":
        write_atomically(path, lambda tmp: np.save(tmp, mask))
        return
    image = sitk.GetImageFromArray(mask)
    _set_grid(image, grid)
    write_atomically(path, lambda tmp: sitk.WriteImage(image, str(tmp), True))


def _set_grid(image, grid: ImageGrid) -> None:
    image.SetSpacing(tuple(float(s) for s in grid.spacing))
    image.SetOrigin(tuple(float(o) for o in grid.origin))
    image.SetDirection(tuple(float(d) for d in grid.direction.ravel()))


def save_volume(path: str | os.PathLike, volume, *, dtype=np.float32) -> None:
    """Write a :class:`Volume` or :class:`~spheroseg.beamspace.BeamVolume`,
    or a list of them (a 3D+t sequence, one 4D image, time last), as
    ``dtype`` (float32; values are cast, not rescaled).

    A beam-space volume keeps its geometry in the header
    (:func:`beam_header`; only :data:`BEAM_SUFFIXES` keep it); its no-data
    samples are written as its ``no_data_value`` (0 if it has only a mask),
    named in ``NoDataValue``.  A Cartesian volume's no-data voxels are
    written as 0, what :func:`load` finds again with ``no_data_value="auto"``.
    """
    sitk = _sitk()
    path = Path(path)
    frames = list(volume) if isinstance(volume, (list, tuple)) else [volume]
    if not frames or not all(isinstance(v, (Volume, BeamVolume)) for v in frames):
        raise TypeError("save_volume takes a Volume, a BeamVolume or a non-empty list of one kind of them")
    first = frames[0]
    beam = isinstance(first, BeamVolume)
    if any(isinstance(v, BeamVolume) != beam or v.shape != first.shape for v in frames):
        raise ValueError("the frames of a sequence must all be of one kind and one shape")
    if beam and any(v.geometry != first.geometry for v in frames):
        raise ValueError("the frames of a beam-space sequence must share one geometry")
    if beam and image_format(path) not in BEAM_SUFFIXES:
        raise ValueError(f"{path}: a beam-space volume needs a format that keeps its header keys "
                         f"({', '.join(BEAM_SUFFIXES)})")
    if image_format(path) == ".npy":
        raise ValueError(f"{path}: .npy keeps no geometry; write .mha or .nrrd")
    no_data = None
    if beam:
        no_data = first.no_data_value if first.no_data_value is not None else (
            0.0 if any(v.no_data_mask is not None for v in frames) else None)
    fill = 0.0 if no_data is None else no_data
    arrays = [(np.where(v.no_data_mask, np.float32(fill), v.array) if v.no_data_mask is not None else v.array)
              .astype(dtype, copy=False) for v in frames]
    if len(frames) == 1:
        image = sitk.GetImageFromArray(arrays[0])
        if not beam:
            _set_grid(image, first.grid)
    else:
        image = sitk.JoinSeries([sitk.GetImageFromArray(a) for a in arrays])
        if not beam:
            g = first.grid
            image.SetSpacing(tuple(float(s) for s in g.spacing) + (1.0,))
            image.SetOrigin(tuple(float(o) for o in g.origin) + (0.0,))
            direction = np.eye(4)
            direction[:3, :3] = g.direction
            image.SetDirection(tuple(float(d) for d in direction.ravel()))
    if beam:
        for key, value in beam_header(first.geometry, no_data_value=no_data).items():
            image.SetMetaData(key, value)
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
