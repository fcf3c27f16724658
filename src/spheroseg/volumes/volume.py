"""An image with its geometry, and trilinear sampling at world points."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from .._compiled import INDEX_TOLERANCE

__all__ = ["Volume", "ImageGrid", "SamplingView", "INDEX_TOLERANCE", "DIRECTION_TOLERANCE", "outside_sector",
           "sample_at_index"]

#: how far a direction's columns may be from orthonormal (largest entry of
#: D^T D - I): headers store directions to 6 decimals, NIfTI in float32; a
#: scaled or sheared matrix is far beyond it
DIRECTION_TOLERANCE = 1e-4
#: the largest coordinate an image's origin may have, mm (a kilometre): beyond
#: it the world -> index arithmetic loses the voxel (float64 keeps 16 digits)
MAX_COORDINATE_MM = 1e6


class _PENDING:
    """A no-data mask not yet searched for (a class: pickled by reference, it stays itself)."""


_SEARCH_LOCK = threading.Lock()


@dataclass(frozen=True)
class ImageGrid:
    """Geometry of an image in ITK physical space (what a mask is drawn on).

    ``world = origin + direction @ (spacing * index_xyz)``; arrays are
    indexed ``[z, y, x]``, so ``shape`` is ``(nz, ny, nx)`` while
    ``spacing`` and ``origin`` are ``(x, y, z)``.
    """

    shape: tuple[int, int, int]
    spacing: np.ndarray = field(default_factory=lambda: np.ones(3))
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    direction: np.ndarray = field(default_factory=lambda: np.eye(3))

    def __post_init__(self):
        object.__setattr__(self, "shape", tuple(int(s) for s in self.shape))
        object.__setattr__(self, "spacing", np.asarray(self.spacing, dtype=float).reshape(3))
        object.__setattr__(self, "origin", np.asarray(self.origin, dtype=float).reshape(3))
        object.__setattr__(self, "direction", np.asarray(self.direction, dtype=float).reshape(3, 3))
        if len(self.shape) != 3:
            raise ValueError(f"an image grid must be 3D, got shape {self.shape}")
        if not np.all(self.spacing > 0):
            raise ValueError(f"spacing must be positive, got {self.spacing}")
        if not np.all(np.abs(self.origin) <= MAX_COORDINATE_MM):  # NaN too
            raise ValueError(f"origin must be 3 finite numbers within +-{MAX_COORDINATE_MM:g} mm (x, y, z), got "
                             f"{self.origin.tolist()}")
        check_direction(self.direction)

    def index_to_world(self, index_xyz) -> np.ndarray:
        return (np.asarray(index_xyz, dtype=float) * self.spacing) @ self.direction.T + self.origin

    def world_to_index(self, world) -> np.ndarray:
        """Continuous index ``(i, j, k)`` (x, y, z order) of world points."""
        return np.linalg.solve(self.direction, (np.asarray(world, dtype=float) - self.origin).T).T / self.spacing


def check_direction(direction: np.ndarray) -> None:
    """Refuse a direction matrix that is not orthonormal (columns of unit
    length at right angles; a reflection is fine).  A scaled or sheared
    matrix would scale or shear every length and volume silently: the
    voxel size is the spacing's, the direction only turns the axes."""
    direction = np.asarray(direction, dtype=float)
    error = np.abs(direction.T @ direction - np.eye(3)).max() if np.all(np.isfinite(direction)) else np.inf
    if not error <= DIRECTION_TOLERANCE:
        rows = "; ".join(" ".join(f"{v:.6g}" for v in row) for row in direction)
        raise ValueError(f"the image's direction matrix [{rows}] is not orthonormal (a rotation, or one with a "
                         "reflection): its columns must be unit vectors at right angles; the voxel size belongs in "
                         "the spacing")


class SamplingView(NamedTuple):
    """What trilinear sampling reads, as plain arrays (read-only): for the
    compiled kernels, which take arrays, not objects."""

    values: np.ndarray  #: the voxels, flat (x fastest), NaN on no-data
    strides: np.ndarray  #: flat offsets of one step in x, y, z
    upper: np.ndarray  #: the last voxel index in x, y, z
    to_index: np.ndarray  #: world direction -> index, 3x3
    origin: np.ndarray  #: world point of voxel (0, 0, 0)


class Volume:
    """A 3D image in ITK physical space.

    Parameters
    ----------
    array : array, shape (nz, ny, nx)
        Voxel values, indexed ``[z, y, x]`` as SimpleITK's ``GetArrayFromImage``.
    spacing, origin : (x, y, z) floats, mm
    direction : 3x3 array
        Columns are the image axes (i, j, k) in world coordinates.
    no_data_value : float, None or "auto"
        Value that marks voxels without data (the black outside of an
        echo sector, 0 in CETUS volumes).  Samples touching such a voxel are
        treated as missing.  ``None``: every voxel is data.  ``"auto"`` (the
        default, as :func:`spheroseg.load`'s): the black padding around a
        scan-converted sector, the exact zeros connected to the image's
        faces covering 1% of it or more (:func:`outside_sector`), searched
        once when first needed (a sample, ``no_data_mask``, the repr) and
        kept; a volume built from an array and one loaded from a file of
        the same voxels have the same no-data.
    no_data_mask : bool array, optional
        Voxels without data, in addition to those of a value; with
        ``"auto"``, the sector itself (no search).

    Notes
    -----
    ``world = origin + direction @ (spacing * (i, j, k))``; world points are
    ``(x, y, z)`` in mm (LPS).
    """

    def __init__(self, array, *, spacing=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0), direction=None, no_data_value="auto",
                 no_data_mask=None):
        array = np.asarray(array)
        if array.ndim != 3:
            raise ValueError(f"a volume must be a 3D array [z, y, x], got {array.ndim}D with shape {array.shape}")
        if min(array.shape) < 2:
            raise ValueError(f"a volume needs at least 2 voxels along each axis, got shape {array.shape}")
        if not np.issubdtype(array.dtype, np.number) or np.iscomplexobj(array):
            raise ValueError(f"volume values must be real numbers, got dtype {array.dtype}")
        with np.errstate(over="ignore"):  # beyond float32: an infinity, reported below
            self.array = np.ascontiguousarray(array, dtype=np.float32)
        # integers convert to finite float32: only floating-point input is
        # checked, by its extremes (a NaN or an infinity is one of them; two
        # reductions cost half of np.isfinite's boolean image)
        if array.dtype.kind == "f" and not (np.isfinite(self.array.min()) and np.isfinite(self.array.max())):
            raise ValueError("volume contains NaN or infinite voxels")
        spacing = np.asarray(spacing, dtype=float)
        if spacing.shape != (3,) or not np.all(np.isfinite(spacing)) or np.any(spacing <= 0):
            raise ValueError(f"spacing must be 3 positive numbers (x, y, z), got {spacing!r}")
        direction = np.eye(3) if direction is None else np.asarray(direction, dtype=float).reshape(3, 3)
        self.grid = ImageGrid(self.array.shape, spacing, origin, direction)
        auto = isinstance(no_data_value, str)
        if auto and no_data_value != "auto":
            raise ValueError(f"no_data_value must be a number, None or 'auto', got {no_data_value!r}")
        self.no_data_value = None if no_data_value is None or auto else float(no_data_value)
        # world -> continuous index (x, y, z order) as one affine map
        self._to_index = np.linalg.inv(direction * self.grid.spacing[None, :])
        missing = None if self.no_data_value is None else self.array == self.no_data_value
        if no_data_mask is not None:
            no_data_mask = np.asarray(no_data_mask, dtype=bool)
            if no_data_mask.shape != self.array.shape:
                raise ValueError(f"no_data_mask must have the volume's shape {self.array.shape}, got {no_data_mask.shape}")
        #: how the no-data voxels were given: "sector" (searched), "value", "mask" or None
        self._no_data_source = None
        if auto and no_data_mask is None:  # searched at the first sample: an image loaded and only looked at needs none
            self._missing = _PENDING
            # the zeros are the input's: a float64 1e-50 is data though float32 rounds it to 0
            # (integers and narrower floats have the zeros of their float32 copy)
            self._searched = array if array.dtype.kind == "f" and array.dtype.itemsize > 4 else self.array
        else:
            self._set_missing(missing, no_data_mask, "value" if missing is not None else None)
        nz, ny, nx = self.array.shape
        self._upper = np.array([nx - 1, ny - 1, nz - 1], dtype=float)
        self._strides = np.array([1, nx, nx * ny], dtype=np.int64)

    # no-data voxels -------------------------------------------------------

    def _set_missing(self, missing, mask, source) -> None:
        if mask is not None:
            missing, source = (mask, "mask") if missing is None else (missing | mask, source + " and mask")
        # what sampling reads: the values, with NaN on no-data voxels so that
        # any sample touching one comes out NaN without a second lookup
        if missing is not None and missing.any():
            self._samples = np.where(missing, np.float32(np.nan), self.array)
        else:
            self._samples = self.array
        self._flat_samples = self._samples.ravel()
        self._no_data_source = source
        self._missing = missing  # last: a thread that sees it set finds the samples set

    def _resolve(self) -> None:
        if self._missing is _PENDING:
            with _SEARCH_LOCK:  # threads sampling one new volume: one search
                if self._missing is _PENDING:
                    sector = outside_sector(self._searched)
                    self._searched = None
                    self._set_missing(sector, None, "sector" if sector is not None else None)

    @property
    def no_data_mask(self) -> np.ndarray | None:
        """The voxels without data (bool ``[z, y, x]``), or None: every voxel is data."""
        self._resolve()
        return self._missing

    @property
    def _flat(self) -> np.ndarray:
        self._resolve()
        return self._flat_samples

    # geometry ------------------------------------------------------------

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.array.shape

    @property
    def spacing(self) -> np.ndarray:
        return self.grid.spacing

    @property
    def origin(self) -> np.ndarray:
        return self.grid.origin

    @property
    def direction(self) -> np.ndarray:
        return self.grid.direction

    def world_to_index(self, world) -> np.ndarray:
        """Continuous index ``(i, j, k)`` (x, y, z order)."""
        return (np.asarray(world, dtype=float) - self.grid.origin) @ self._to_index.T

    def index_to_world(self, index_xyz) -> np.ndarray:
        return self.grid.index_to_world(index_xyz)

    def contains(self, world) -> np.ndarray:
        """Whether world points lie within the image (between the first and
        last voxel centres)."""
        idx = self.world_to_index(world)
        return np.all((idx >= -INDEX_TOLERANCE) & (idx <= self._upper + INDEX_TOLERANCE), axis=-1)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """World bounding box of the voxel centres."""
        corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)]) * self._upper
        w = self.index_to_world(corners)
        return w.min(0), w.max(0)

    # sampling ------------------------------------------------------------

    def sample(self, world, *, fill_value: float = np.nan, order: int = 1) -> np.ndarray:
        """Trilinear interpolation (``order=1``) or the nearest voxel
        (``order=0``) at world points, shape ``world.shape[:-1]``.

        Points outside the image (or touching a no-data voxel) get
        ``fill_value``.
        """
        if order not in (0, 1):
            raise ValueError(f"order must be 0 (nearest voxel) or 1 (trilinear), got {order!r}")
        world = np.asarray(world, dtype=float)
        out = sample_at_index(self._flat, self._strides, self._upper, self.world_to_index(world.reshape(-1, 3)),
                              order=order, fill_value=fill_value)
        return out.reshape(world.shape[:-1])

    def sampling_view(self) -> SamplingView:
        """The arrays :meth:`sample` reads (views, not copies; read-only)."""
        arrays = [np.ndarray.view(a) for a in (self._flat, self._strides, self._upper, self._to_index,
                                               self.grid.origin)]
        for a in arrays:
            a.flags.writeable = False
        return SamplingView(*arrays)

    def __call__(self, world) -> np.ndarray:
        return self.sample(world)

    def __repr__(self) -> str:
        missing = self.no_data_mask
        if missing is None:
            no_data = "none"
        else:
            source = self._no_data_source.replace("sector", "sector padding")
            if self.no_data_value is not None:
                source = source.replace("value", f"value {self.no_data_value:g}")
            no_data = f"{source}, {100 * np.count_nonzero(missing) / missing.size:.1f}% of voxels"
        spacing, origin = (tuple(float(v) for v in values.round(n)) for values, n in ((self.spacing, 4), (self.origin, 3)))
        return f"Volume(shape={self.shape}, spacing={spacing}, origin={origin}, no_data={no_data!r})"


def sample_at_index(flat: np.ndarray, strides: np.ndarray, upper: np.ndarray, index: np.ndarray, *,
                    order: int = 1, fill_value: float = np.nan) -> np.ndarray:
    """Trilinear interpolation (``order=1``) or the nearest sample
    (``order=0``) of an image stored as ``flat`` (``flat[index @ strides]``
    for integer ``index``), at continuous indices ``index`` ``(n, 3)``.

    ``fill_value`` where an index lies beyond ``[0, upper]`` (by more than
    :data:`INDEX_TOLERANCE`), is NaN, or touches a NaN (no-data) sample.
    A :class:`Volume`'s voxels and a beam-space volume's samples are both
    read this way.
    """
    with np.errstate(invalid="ignore"):
        within = (index >= -INDEX_TOLERANCE) & (index <= upper + INDEX_TOLERANCE)
    valid = within[:, 0] & within[:, 1] & within[:, 2]  # (np.all(axis=1) is slower)
    index = np.clip(np.nan_to_num(index), 0, upper)
    if order == 0:
        out = flat[np.rint(index).astype(np.int64) @ strides].astype(float)
    else:
        base = np.minimum(np.floor(index), np.maximum(upper - 1, 0)).astype(np.int64)
        t = index - base
        flat0 = base @ strides
        out = np.zeros(len(index))
        for d2 in (0, 1):
            w2 = t[:, 2] if d2 else 1 - t[:, 2]
            for d1 in (0, 1):
                w1 = t[:, 1] if d1 else 1 - t[:, 1]
                for d0 in (0, 1):
                    w0 = t[:, 0] if d0 else 1 - t[:, 0]
                    out += w0 * w1 * w2 * flat[flat0 + (d0 * strides[0] + d1 * strides[1] + d2 * strides[2])]
    out[~valid | np.isnan(out)] = fill_value
    return out


def outside_sector(array: np.ndarray, *, min_fraction: float = 0.01) -> np.ndarray | None:
    """The black padding around a scan-converted echo sector:
    :func:`spheroseg.raster.outside_sector`."""
    from .._compiled.raster import outside_sector as padding

    return padding(array, min_fraction=min_fraction)
