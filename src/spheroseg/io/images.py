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

import glob as _glob
import math
import os
import re
import tempfile
from pathlib import Path

import numpy as np

from .atomic import write_atomically
from ..volumes.beamspace import CONVENTIONS, BeamGeometry, BeamVolume
from ..volumes.budget import BUDGET_VARIABLE, DEFAULT_BUDGET_GB, budget_bytes  # noqa: F401 (their old home)
from ..volumes.volume import ImageGrid, Volume

__all__ = ["volume_with_no_data", "load", "load_sequence", "load_frames", "save_mask", "save_volume", "image_format", "image_files",
           "frame_order", "shown_path", "is_sequence_file", "check_image_size", "beam_header",
           "beam_geometry_from_header", "ImageFileError", "IMAGE_SUFFIXES", "MASK_SUFFIXES", "BEAM_SUFFIXES",
           "BEAM_KEYS", "BEAM_OPTIONAL_KEYS", "BUDGET_VARIABLE", "VOXEL_BYTES"]

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


def shown_path(path) -> str:
    """A path as text for a message, whatever its bytes: those that are not
    UTF-8 written ``\\xff``."""
    return os.fsencode(os.fspath(path)).decode("utf-8", "backslashreplace")


def _itk_path(path) -> str:
    """``path`` as the text SimpleITK takes.  SimpleITK aborts the process
    (in C++, no exception) on a path that is not UTF-8: every path given to
    it passes here first and such a one is refused with its bytes shown."""
    text = os.fspath(path)
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        raise ImageFileError(f"{shown_path(path)}: the path is not UTF-8 text, which the image library cannot open; "
                             "rename it (or a folder above it)") from None
    return text


def _missing(path) -> FileNotFoundError:
    path = Path(path)
    if path.exists() or path.is_symlink():  # there, but this user may not read it (or a dangling link)
        if path.is_symlink() and not path.exists():
            return FileNotFoundError(f"{shown_path(path)}: a link to a missing file")
        return PermissionError(f"{shown_path(path)}: cannot read (permission denied)")
    hint = " (a pattern? give --glob)" if any(ch in str(path) for ch in "*?[") else ""
    return FileNotFoundError(f"{shown_path(path)}: no such file{hint}")


#: the frame number of a frame's file: the last run of digits in its name
_FRAME_NUMBER = re.compile(r"(\d+)(?!.*\d)")


def frame_order(files) -> list[Path]:
    """The frames of a folder (or of a pattern) in the order of the numbers
    in their names (``frame_2`` before ``frame_10``: natural order, not the
    text's), each name's last number its frame's.

    Raises
    ------
    ValueError
        A frame without a number in its name (of two or more), two frames of
        one number (``frame_1`` and ``frame_01``) or a number missing between
        the first and the last: the sequence would be out of time order.
    """
    files = [Path(f) for f in files]
    if len(files) < 2:
        return files
    numbered = []
    for f in files:
        stem = f.name[:len(f.name) - len(image_format(f))]
        found = _FRAME_NUMBER.search(stem)
        if found is None:
            raise ValueError(f"{shown_path(f)}: no frame number in the name; the frames of a sequence are ordered by "
                             "the numbers in their names (frame_0, frame_1, ...)")
        numbered.append((int(found.group(1)), f))
    numbered.sort(key=lambda item: (item[0], item[1].name))
    for (a, fa), (b, fb) in zip(numbered, numbered[1:]):
        if a == b:
            raise ValueError(f"{shown_path(fa)} and {fb.name}: two frames numbered {a}")
        if b != a + 1:
            missing = f"frame {a + 1}" if b == a + 2 else f"frames {a + 1} to {b - 1}"
            raise ValueError(f"{shown_path(fa.parent)}: {missing} missing between {fa.name} and {fb.name}")
    return [f for _, f in numbered]


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


#: bytes a voxel of a loaded image holds at the peak: its float32 voxels,
#: the mask of its voxels without data and the copy the sampling reads
#: (NaN on those voxels)
VOXEL_BYTES = 4 + 1 + 4


def check_image_size(path, shape, components: int = 1) -> None:
    """Refuse an image whose declared voxels, as a loaded volume holds them
    (:data:`VOXEL_BYTES` a voxel), exceed the memory budget
    (``SPHEROSEG_MAX_IMAGE_GB``, default 4 GB), before its pixels are read.

    Parameters
    ----------
    path : str or Path
        Named in the message.
    shape : sequence of int
        The declared size (any order; every axis, frames included).
    components : int
        Values per voxel (frames of a ``.seq.nrrd``).
    """
    voxels = math.prod(int(n) for n in shape) * int(components)
    need, budget = float(VOXEL_BYTES) * voxels, budget_bytes()
    if need > budget:
        size = " x ".join(str(int(n)) for n in shape) + (f" x {components} components" if components > 1 else "")
        raise ImageFileError(f"{path}: declares {size} voxels, {need / 1e9:.3g} GB once loaded ({VOXEL_BYTES} bytes "
                             "a voxel: float32 voxels, their no-data mask, the copy sampling reads), over the memory "
                             f"budget of {budget / 1e9:.3g} GB (set {BUDGET_VARIABLE} to raise it)")


#: what ITK prints when a read failed though it returned an image (of zeros)
_FAILED_READS = ("Uncompress failed",)


def _quietly(call, *, succeeded=lambda returned: True, path=None):
    """``call()`` with the process's stderr (file descriptor 2) captured:
    what the C++ readers (MetaIO, GDCM, ITK) print there themselves.  On
    success their lines are passed on to ``sys.stderr``; on failure (an
    exception, or ``succeeded(returned)`` false) they are dropped, since the
    error raised says why in one line."""
    import sys

    try:
        saved = os.dup(2)
    except OSError:  # no stderr to capture
        return call()
    with tempfile.TemporaryFile() as noise:
        os.dup2(noise.fileno(), 2)
        try:
            returned = call()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        noise.seek(0)
        text = noise.read().decode(errors="replace")
    failed = next((line.strip() for line in text.splitlines() if any(m in line for m in _FAILED_READS)), None)
    if path is not None and failed is not None:
        raise ImageFileError(f"{path}: cannot read image ({failed[:200]}: is CompressedData right?)")
    if text.strip() and succeeded(returned):
        sys.stderr.write(text)
    return returned


def _read_image(path: Path):
    sitk = _sitk()
    if path.is_dir():
        reader = sitk.ImageSeriesReader()
        series = _quietly(lambda: reader.GetGDCMSeriesIDs(_itk_path(path)), succeeded=bool)
        if not series:
            raise ImageFileError(f"{path}: a folder with no DICOM series (for a folder of 3D frames use load_sequence)")
        reader.SetFileNames([_itk_path(f) for f in reader.GetGDCMSeriesFileNames(_itk_path(path), series[0])])
        return _quietly(reader.Execute)
    if not path.is_file() or not os.access(path, os.R_OK):
        raise _missing(path)
    reader = sitk.ImageFileReader()
    reader.SetFileName(_itk_path(path))
    try:
        _quietly(reader.ReadImageInformation)
    except RuntimeError:
        pass  # not an image: ReadImage below says why, in one line
    else:
        check_image_size(path, reader.GetSize(), reader.GetNumberOfComponents())
        _check_data_file(path)
    try:
        return _quietly(lambda: sitk.ReadImage(_itk_path(path)), path=path)
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()
        detail = next((line for line in first if "ERROR" in line or "Unable" in line), first[-1] if first else "")
        teem = [line.split(":", 1)[-1].strip() for line in first if line.startswith("[nrrd]")]
        if teem:  # NRRD's reader gives its reason last, below ITK's "Error reading ...:"
            detail = f"{detail.strip().rstrip(':')}: {teem[-1]}"
        raise ImageFileError(f"{path}: cannot read image ({detail.strip()[:300]})") from None


#: bytes per value of MetaImage element types (MET_LONG's size is the
#: writer's platform's: not checked; ITK writes 64 bits as MET_LONG_LONG)
_META_BYTES = {"MET_CHAR": 1, "MET_UCHAR": 1, "MET_SHORT": 2, "MET_USHORT": 2, "MET_INT": 4, "MET_UINT": 4,
               "MET_LONG_LONG": 8, "MET_ULONG_LONG": 8, "MET_FLOAT": 4, "MET_DOUBLE": 8}


#: MetaImage keys of numbers that ITK reads as 0 when they are not numbers
_META_NUMBERS = ("Offset", "Origin", "Position", "ElementSpacing", "TransformMatrix", "Rotation", "Orientation",
                 "CenterOfRotation")


def _meta_keys(path: Path) -> dict | None:
    """The header keys of a MetaImage file (.mhd; the text head of a .mha),
    None for other formats."""
    if image_format(path) not in (".mhd", ".mha"):
        return None
    with open(path, "rb") as handle:
        head = handle.read(1 << 16)
    keys = {}
    for line in head.decode("latin-1").splitlines():
        key, sep, value = line.partition("=")
        if not sep:
            continue
        keys[key.strip()] = value.strip()
        if key.strip() == "ElementDataFile":  # the voxels follow in a .mha
            break
    return keys


def _check_data_file(path: Path) -> None:
    """Refuse a MetaImage header whose numbers of geometry are not numbers
    (ITK reads ``Offset = nan`` as 0, silently), or (``.mhd``) whose raw
    data file holds more bytes than it declares: ITK reads the first ones
    silently, and a wrong ``DimSize`` or ``ElementType`` scrambles the
    image (a data file that is too short, ITK refuses itself).  Compressed,
    listed and embedded data are left to ITK."""
    if image_format(path) == ".nhdr":
        _check_nrrd_data_file(path)
        return
    keys = _meta_keys(path)
    if keys is None:
        return
    for key in _META_NUMBERS:
        if key in keys:
            try:
                values = [float(v) for v in keys[key].split()]
            except ValueError:
                values = [math.nan]
            if not all(math.isfinite(v) for v in values):
                raise ImageFileError(f"{path}: header key {key} must be finite numbers, got {keys[key]!r}")
    if image_format(path) != ".mhd":
        return
    name = keys.get("ElementDataFile", "")
    try:
        dims = [int(n) for n in keys.get("DimSize", "").split()]
        channels = int(keys.get("ElementNumberOfChannels", "1"))
        header = int(keys.get("HeaderSize", "0"))
    except ValueError:
        return  # ITK says what is wrong with the header
    if (keys.get("CompressedData", "False").lower() == "true" or name in ("", "LOCAL") or name.startswith("LIST")
            or "%" in name or header < 0 or keys.get("ElementType") not in _META_BYTES or not dims):
        return
    data = path.parent / name
    if not data.is_file():
        return
    declared = header + math.prod(dims) * channels * _META_BYTES[keys["ElementType"]]
    size = data.stat().st_size
    if size > declared:
        raise ImageFileError(f"{path}: its data file {name} holds {size} bytes, {size - declared} more than the "
                             f"header declares (DimSize {' '.join(map(str, dims))}, {keys['ElementType']}): "
                             "a wrong size or type would scramble the image")


#: bytes per value of NRRD types (their common spellings)
_NRRD_BYTES = {**dict.fromkeys(("int8", "uint8", "char", "uchar", "signed char", "unsigned char", "int8_t",
                                "uint8_t"), 1),
               **dict.fromkeys(("int16", "uint16", "short", "ushort", "unsigned short", "int16_t", "uint16_t"), 2),
               **dict.fromkeys(("int32", "uint32", "int", "uint", "unsigned int", "int32_t", "uint32_t", "float"), 4),
               **dict.fromkeys(("int64", "uint64", "longlong", "ulonglong", "int64_t", "uint64_t", "double"), 8)}


def _check_nrrd_data_file(path: Path) -> None:
    """Refuse a detached NRRD header (``.nhdr``) of raw data whose data file
    holds more bytes than its ``sizes`` declare (read silently by ITK, as a
    MetaImage's: a scrambled image)."""
    keys = {}
    for line in path.read_text(errors="replace").splitlines()[1:]:
        if not line.strip():
            break
        key, sep, value = line.partition(":")
        if sep and not line.startswith("#"):
            keys[key.strip().lower()] = value.lstrip("=").strip()
    name, kind = keys.get("data file", keys.get("datafile", "")), keys.get("type", "").lower()
    try:
        sizes = [int(n) for n in keys.get("sizes", "").split()]
        skip = int(keys.get("byte skip", "0"))
    except ValueError:
        return  # ITK says what is wrong with the header
    if (keys.get("encoding", "raw").lower() != "raw" or kind not in _NRRD_BYTES or not sizes or not name
            or name.upper().startswith("LIST") or "%" in name or skip < 0 or "line skip" in keys):
        return
    data = path.parent / name
    if not data.is_file():
        return
    declared, size = skip + math.prod(sizes) * _NRRD_BYTES[kind], data.stat().st_size
    if size > declared:
        raise ImageFileError(f"{path}: its data file {name} holds {size} bytes, {size - declared} more than the "
                             f"header declares (sizes {' '.join(map(str, sizes))}, {kind}): a wrong size or type "
                             "would scramble the image")


def _load_npy(path: Path) -> np.ndarray:
    """A ``.npy`` array, its declared size checked against the budget first."""
    try:
        check_image_size(path, np.load(path, mmap_mode="r", allow_pickle=False).shape)
        return np.load(path, allow_pickle=False)
    except (ValueError, OSError) as exc:
        if isinstance(exc, ImageFileError):
            raise
        raise ImageFileError(f"{path}: cannot read numpy array ({exc})") from None


def volume_with_no_data(array, no_data_value, **geometry) -> Volume:
    """A Volume whose no-data voxels follow ``no_data_value``: a value,
    ``None``, or ``"auto"`` (the zero padding around an echo sector)."""
    return Volume(array, **geometry, no_data_value=no_data_value)  # "auto": the Volume searches when first sampled


class _ImageBuffer:
    """SimpleITK's voxel buffer as a numpy array that keeps its image alive
    (``np.asarray`` of this is a view whose base holds the image)."""

    def __init__(self, image):
        self.image = image
        self.__array_interface__ = _sitk().GetArrayViewFromImage(image).__array_interface__


def _voxels(image) -> np.ndarray:
    """The image's voxels ``[z, y, x]`` for a :class:`Volume`, without a
    copy: a read-only view of SimpleITK's buffer that keeps the image alive
    (float32 voxels then become the volume's array as they are: one working
    copy of the image, not two)."""
    return np.asarray(_ImageBuffer(image))


def _volume_from_image(image, no_data_value, spacing=None) -> Volume:
    if image.GetDimension() != 3:
        raise ValueError(f"expected a 3D image, got {image.GetDimension()}D")
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise ValueError(f"expected a scalar image, got {image.GetNumberOfComponentsPerPixel()} components per voxel")
    return volume_with_no_data(
        _voxels(image),
        no_data_value,
        spacing=image.GetSpacing() if spacing is None else spacing,
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
        array = _load_npy(path)
        if spacing is None:
            raise ValueError(f"{path}: a .npy array has no geometry; give its voxel spacing")
        return volume_with_no_data(array, no_data_value, spacing=spacing)
    image = _read_image(path)
    if image.GetDimension() == 4 or image.GetNumberOfComponentsPerPixel() > 1:
        raise ValueError(f"{path}: a 3D+t image; use load_sequence (spheroseg track)")
    if image.GetDimension() != 3:
        raise ValueError(f"{path}: expected a 3D image, got {image.GetDimension()}D")
    beam = _beam_geometry(image, path, spacing)
    if beam is not None:
        return _make_beam_volume(_sitk().GetArrayFromImage(image), beam, no_data_value)
    return _volume_from_image(image, no_data_value, spacing)


def is_sequence_file(path: str | os.PathLike) -> bool:
    """Whether one file holds a 3D+t sequence (a 4D image, a 3D image of
    several components, a 4D ``.npy``), from its header; False when it
    cannot be read (the loader then says why, in one line)."""
    path = Path(path)
    if not path.is_file():
        return False
    try:
        if image_format(path) == ".npy":
            return np.load(path, mmap_mode="r", allow_pickle=False).ndim == 4
        reader = _sitk().ImageFileReader()
        reader.SetFileName(_itk_path(path))
        _quietly(reader.ReadImageInformation)
    except (ValueError, OSError, RuntimeError):
        return False
    return reader.GetDimension() == 4 or reader.GetNumberOfComponents() > 1


def _frame_files(path, glob: bool) -> list[Path] | None:
    """The frame files of a pattern (``glob``) or a folder, in frame order;
    None for anything else."""
    if glob:
        files = [Path(f) for f in _glob.glob(os.fspath(path)) if image_format(f) in IMAGE_SUFFIXES]
        if not files:
            raise FileNotFoundError(f"{shown_path(path)}: no image files match the pattern")
        return frame_order(files)
    path = Path(path)
    if path.is_dir():
        return frame_order(p for p in path.iterdir() if image_format(p) in IMAGE_SUFFIXES and p.is_file()
                           and not p.name.startswith("."))
    return None


def load_frames(path: str | os.PathLike, *, spacing=None, no_data_value: float | str | None = "auto",
                glob: bool = False) -> list[Volume] | list[BeamVolume]:
    """Read a 3D image as one frame, or a 3D+t sequence as its frames
    (whichever the file holds; the keywords are :func:`load_sequence`'s).

    A folder or (``glob=True``) a pattern is a sequence
    (:func:`load_sequence`), as is a 4D image, a 3D image of several
    components or a 4D ``.npy``.
    """
    if glob or Path(path).is_dir() or is_sequence_file(path):
        return load_sequence(path, spacing=spacing, no_data_value=no_data_value, glob=glob)
    return [load(path, spacing=spacing, no_data_value=no_data_value)]


def load_sequence(path: str | os.PathLike, *, spacing=None, no_data_value: float | str | None = "auto",
                  glob: bool = False) -> list[Volume] | list[BeamVolume]:
    """Read a 3D+t sequence as a list of :class:`Volume` (of
    :class:`~spheroseg.beamspace.BeamVolume` for beam-space files).

    Accepts a 4D image (.mha, .nrrd, .nii: the fourth axis is time), a
    vector image whose components are frames (3D Slicer's ``.seq.nrrd``), a
    folder of 3D frames, a DICOM series folder holding a 4D image, or a 4D
    ``.npy`` ``[t, z, y, x]``.  The frames of a folder are ordered by the
    numbers in their names (:func:`frame_order`: a gap or a repeated number
    is an error).

    Parameters
    ----------
    glob : bool
        ``path`` is a pattern (``frame_*.mha``) whose matches are the frames,
        in the same order.  Otherwise a name is a name: ``cine[12].mha`` is
        that file, whatever its characters.
    """
    sitk = _sitk()
    frames = _frame_files(path, glob)
    if frames:
        return [load(f, spacing=spacing, no_data_value=no_data_value) for f in frames]
    path = Path(path)
    if image_format(path) == ".npy":
        if not path.is_file():
            raise _missing(path)
        array = _load_npy(path)
        if array.ndim != 4:
            raise ValueError(f"{path}: expected a 4D array [t, z, y, x], got {array.ndim}D")
        if spacing is None:
            raise ValueError(f"{path}: a .npy array has no geometry; give its voxel spacing")
        return [volume_with_no_data(a, no_data_value, spacing=spacing) for a in array]
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
    return [_volume_from_image(f, no_data_value, spacing) for f in frames]


def _header_data_file(path: Path) -> Path | None:
    """The data file a MetaImage (.mhd) or detached NRRD (.nhdr) header names."""
    key = {".mhd": "elementdatafile", ".nhdr": "data file"}.get(path.suffix.lower())
    if key is None:
        return None
    try:
        with open(path, encoding="latin-1") as handle:
            for line in handle:
                name, sep, value = line.partition("=" if key == "elementdatafile" else ":")
                if sep and name.strip().lower() == key:
                    value = value.strip()
                    return None if value.upper() in ("LOCAL", "") else path.parent / value
    except OSError:
        return None
    return None


def image_files(image: str | os.PathLike, *, glob: bool = False) -> list[Path]:
    """The files an image reads: the file and the data file its header names
    (.mhd, .nhdr), a folder's files, a pattern's matches (``glob=True``)."""
    if glob:
        files = [Path(f) for f in sorted(_glob.glob(os.fspath(image)))]
    elif Path(image).is_dir():
        files = sorted(p for p in Path(image).rglob("*") if p.is_file())
    else:
        files = [Path(image)]
    for f in list(files):
        data = _header_data_file(f)
        if data is not None and data not in files:
            files.append(data)
    return files


def save_mask(path: str | os.PathLike, mask: np.ndarray, like: Volume | BeamVolume | ImageGrid) -> None:
    """Write a boolean mask as an 8-bit image on ``like``'s grid (a
    :class:`~spheroseg.beamspace.BeamVolume`'s is the Cartesian grid covering
    its sector)."""
    sitk = _sitk()
    path = Path(path)
    grid = like if isinstance(like, ImageGrid) else like.grid
    mask = np.asarray(mask)
    # a boolean mask is its bytes already: a view, not a copy of the whole mask
    mask = mask.view(np.uint8) if mask.dtype == np.bool_ else mask.astype(np.uint8)
    if mask.shape != grid.shape:
        raise ValueError(f"the mask's shape {mask.shape} is not its grid's {grid.shape}")
    if image_format(path) == ".npy":
        write_atomically(path, lambda tmp: np.save(tmp, mask))
        return
    image = sitk.GetImageFromArray(mask)
    _set_grid(image, grid)
    write_atomically(path, lambda tmp: _write_image(image, tmp, path))


def _write_image(image, tmp: Path, path: Path) -> None:
    """SimpleITK's write of ``image`` to ``tmp``; a full disk said so (ITK
    says "4097 requested and 1000 written"), other failures in one line."""
    try:
        _sitk().WriteImage(image, _itk_path(tmp), True)
    except RuntimeError as exc:
        size = image.GetNumberOfPixels() * image.GetNumberOfComponentsPerPixel() * image.GetSizeOfPixelComponent()
        try:
            stats = os.statvfs(Path(tmp).parent)
            full = stats.f_bavail * stats.f_frsize < size
        except (OSError, AttributeError):
            full = False
        if full:
            raise OSError(28, f"{path}: no space left on the device for its {size / 1e6:.3g} MB") from None
        lines = str(exc).strip().splitlines()
        detail = next((line for line in lines if "ERROR" in line or "rror" in line), lines[-1] if lines else "")
        raise ImageFileError(f"{path}: cannot write image ({detail.strip()[:200]})") from None


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
    write_atomically(path, lambda tmp: _write_image(image, tmp, path))
