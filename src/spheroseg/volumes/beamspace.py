"""Beam-space volumes: echo samples on the scanner's own [radius, elevation,
azimuth] grid, sampled at world points without scan conversion.

A 3D echo volume is acquired as beams fanning out of the probe's (virtual)
apex.  Sample ``[r, e, a]`` lies on the beam of azimuth ``alpha`` and
elevation ``beta`` at distance ``rho`` from the apex::

    rho   = first_sample_distance + r * radius_sample_size            (mm)
    alpha = (a - a_c) * azimuth_angular_separation                    (rad)
    beta  = (e - e_c) * elevation_angular_separation                  (rad)

with ``(e_c, a_c)`` the index of the central beam (``(n - 1) / 2`` by
default, as ITK's ``PhasedArray3DSpecialCoordinatesImage``).  Two angle
conventions are in use:

``"tan"`` (ITK, zea)
    ``z = rho / sqrt(1 + tan^2 alpha + tan^2 beta)``, ``x = z tan alpha``,
    ``y = z tan beta``; inverse ``alpha = atan(x / z)``, ``beta = atan(y / z)``.
``"sin"`` (EchoXFlow, Philips research formats, UFF)
    ``x = rho sin alpha``, ``y = rho cos alpha sin beta``,
    ``z = rho cos alpha cos beta``; inverse ``alpha = atan2(x, sqrt(y^2 + z^2))``,
    ``beta = atan2(y, z)``.

They agree on the planes ``alpha = 0`` and ``beta = 0`` only.  ``(x, y, z)``
is the probe frame in mm (+z along the central beam); ``probe_to_world``
(a rigid 4x4 transform) places it in the world (LPS, mm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from .volume import INDEX_TOLERANCE, ImageGrid, Volume, sample_at_index

__all__ = ["BeamGeometry", "BeamVolume", "BeamSamplingView", "CONVENTIONS", "scan_convert", "check_scan_conversion",
           "to_beam_space",
           "beam_mask", "beam_mask_volume_ml"]

#: the angle conventions :class:`BeamGeometry` knows
CONVENTIONS = ("tan", "sin")


def _positive(name, value):
    value = float(value)
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a positive number, got {value!r}")
    return value


@dataclass(frozen=True, eq=False)
class BeamGeometry:
    """Where the samples of a beam-space volume lie (ITK's
    ``PhasedArray3DSpecialCoordinatesImage`` fields plus what ITK leaves out).

    Parameters
    ----------
    shape : (n_r, n_e, n_a) ints
        Samples along radius, elevation, azimuth: array index order ``[r, e, a]``
        (azimuth varies fastest, as ITK stores it).
    radius_sample_size : float
        mm between samples along a beam (ITK ``RadiusSampleSize``).
    first_sample_distance : float
        mm from the apex to sample 0 (ITK ``FirstSampleDistance``), >= 0.
    azimuth_angular_separation, elevation_angular_separation : float
        Radians between neighbouring beams (ITK ``AzimuthAngularSeparation``,
        ``ElevationAngularSeparation``).
    convention : {"tan", "sin"}
        Angle convention (module docstring); ``"tan"`` is ITK's.
    centre_index : (e_c, a_c) floats, optional
        Index (elevation, azimuth) of the 0-radian beam; ``None``: the middle,
        ``((n_e - 1) / 2, (n_a - 1) / 2)``, as ITK.
    probe_to_world : 4x4 array
        Rigid transform from the probe frame (mm) to world (LPS, mm).
    """

    shape: tuple[int, int, int]
    radius_sample_size: float
    first_sample_distance: float
    azimuth_angular_separation: float
    elevation_angular_separation: float
    convention: str = "tan"
    centre_index: tuple[float, float] | None = None
    probe_to_world: np.ndarray = field(default_factory=lambda: np.eye(4))

    def __post_init__(self):
        shape = tuple(int(s) for s in np.asarray(self.shape).ravel())
        if len(shape) != 3 or min(shape) < 2:
            raise ValueError(f"beam geometry shape must be 3 sizes (n_r, n_e, n_a), each >= 2, got {self.shape!r}")
        object.__setattr__(self, "shape", shape)
        for name in ("radius_sample_size", "azimuth_angular_separation", "elevation_angular_separation"):
            object.__setattr__(self, name, _positive(name, getattr(self, name)))
        r0 = float(self.first_sample_distance)
        if not (np.isfinite(r0) and r0 >= 0):
            raise ValueError(f"first_sample_distance must be a number >= 0 (mm), got {self.first_sample_distance!r}")
        object.__setattr__(self, "first_sample_distance", r0)
        if self.convention not in CONVENTIONS:
            raise ValueError(f"convention must be one of {CONVENTIONS}, got {self.convention!r}")
        centre = self.centre_index
        if centre is None:
            centre = ((shape[1] - 1) / 2.0, (shape[2] - 1) / 2.0)
        centre = tuple(float(c) for c in np.asarray(centre, dtype=float).ravel())
        if len(centre) != 2 or not all(np.isfinite(centre)):
            raise ValueError(f"centre_index must be 2 numbers (elevation, azimuth), got {self.centre_index!r}")
        object.__setattr__(self, "centre_index", centre)
        half = np.array([self.elevation_angular_separation * max(centre[0], shape[1] - 1 - centre[0]),
                         self.azimuth_angular_separation * max(centre[1], shape[2] - 1 - centre[1])])
        if np.any(half >= np.pi / 2):
            raise ValueError(f"the sector must stay within +-90 degrees of the central beam, got up to "
                             f"{np.degrees(half.max()):.1f} degrees")
        m = np.array(self.probe_to_world, dtype=float)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise ValueError(f"probe_to_world must be a 4x4 matrix, got shape {m.shape}")
        if not np.allclose(m[3], [0, 0, 0, 1]) or not np.allclose(m[:3, :3].T @ m[:3, :3], np.eye(3), atol=1e-6):
            raise ValueError("probe_to_world must be rigid: an orthonormal 3x3 rotation, a translation, "
                             "and a last row 0 0 0 1")
        m.flags.writeable = False
        object.__setattr__(self, "probe_to_world", m)

    def key(self) -> tuple:
        """The fields as a hashable tuple (equality and hashing)."""
        return (self.shape, self.radius_sample_size, self.first_sample_distance, self.azimuth_angular_separation,
                self.elevation_angular_separation, self.convention, self.centre_index,
                tuple(self.probe_to_world.ravel()))

    def __eq__(self, other) -> bool:
        return isinstance(other, BeamGeometry) and self.key() == other.key()

    def __hash__(self) -> int:
        return hash(self.key())

    # --- angles ----------------------------------------------------------

    @property
    def rotation(self) -> np.ndarray:
        """Probe axes in world coordinates (columns), 3x3."""
        return self.probe_to_world[:3, :3]

    @property
    def apex(self) -> np.ndarray:
        """World point of the (virtual) apex, mm."""
        return self.probe_to_world[:3, 3]

    @property
    def separations(self) -> np.ndarray:
        """``(radius_sample_size, elevation_angular_separation,
        azimuth_angular_separation)``: index step in mm and radians, [r, e, a] order."""
        return np.array([self.radius_sample_size, self.elevation_angular_separation,
                         self.azimuth_angular_separation])

    @property
    def index_offset(self) -> np.ndarray:
        """``(rho, beta, alpha)`` at index ``(0, 0, 0)``."""
        e_c, a_c = self.centre_index
        return np.array([self.first_sample_distance, -e_c * self.elevation_angular_separation,
                         -a_c * self.azimuth_angular_separation])

    @property
    def upper(self) -> np.ndarray:
        """The last index along r, e, a."""
        return np.array(self.shape, dtype=float) - 1

    def index_to_spherical(self, index) -> np.ndarray:
        """``(rho, beta, alpha)`` (mm, rad, rad) of continuous indices ``[r, e, a]``."""
        return np.asarray(index, dtype=float) * self.separations + self.index_offset

    # --- probe frame -----------------------------------------------------

    def spherical_to_probe(self, spherical) -> np.ndarray:
        """Probe-frame points (x, y, z) of ``(rho, beta, alpha)``."""
        s = np.asarray(spherical, dtype=float)
        rho, beta, alpha = s[..., 0], s[..., 1], s[..., 2]
        if self.convention == "tan":
            ta, tb = np.tan(alpha), np.tan(beta)
            z = rho / np.sqrt(1 + ta * ta + tb * tb)
            return np.stack([z * ta, z * tb, z], axis=-1)
        ca = np.cos(alpha)
        return np.stack([rho * np.sin(alpha), rho * ca * np.sin(beta), rho * ca * np.cos(beta)], axis=-1)

    def probe_to_spherical(self, points) -> np.ndarray:
        """``(rho, beta, alpha)`` of probe-frame points; NaN angles where the
        convention does not define them (``z <= 0`` for ``"tan"``, the apex)."""
        p = np.asarray(points, dtype=float)
        x, y, z = p[..., 0], p[..., 1], p[..., 2]
        rho = np.sqrt(x * x + y * y + z * z)
        with np.errstate(invalid="ignore", divide="ignore"):
            if self.convention == "tan":
                alpha = np.where(z > 0, np.arctan2(x, z), np.nan)
                beta = np.where(z > 0, np.arctan2(y, z), np.nan)
            else:
                alpha = np.where(rho > 0, np.arctan2(x, np.sqrt(y * y + z * z)), np.nan)
                beta = np.where(rho > 0, np.arctan2(y, z), np.nan)
        return np.stack([rho, beta, alpha], axis=-1)

    # --- world -----------------------------------------------------------

    def index_to_world(self, index) -> np.ndarray:
        """World points (x, y, z) mm of continuous indices ``[r, e, a]``, shape (..., 3)."""
        return self.spherical_to_probe(self.index_to_spherical(index)) @ self.rotation.T + self.apex

    def world_to_index(self, points) -> np.ndarray:
        """Continuous indices ``[r, e, a]`` of world points, shape (..., 3).

        Points off the sector get indices outside ``[0, n - 1]``, or NaN
        where the angles are undefined (behind the probe in the ``"tan"``
        convention, the apex).
        """
        probe = (np.asarray(points, dtype=float) - self.apex) @ self.rotation
        return (self.probe_to_spherical(probe) - self.index_offset) / self.separations

    def contains(self, points) -> np.ndarray:
        """Whether world points lie in the sector (between the first and last
        sample along each index)."""
        idx = self.world_to_index(points)
        with np.errstate(invalid="ignore"):
            return np.all((idx >= -INDEX_TOLERANCE) & (idx <= self.upper + INDEX_TOLERANCE), axis=-1)

    def jacobian(self, index) -> np.ndarray:
        """Volume (mm^3) per unit index cell at ``[r, e, a]``:
        ``|d world / d index| = dr * de * da * J(rho, beta, alpha)`` with
        ``J = rho^2 / (cos^2 a cos^2 b (1 + tan^2 a + tan^2 b)^(3/2))`` ("tan")
        or ``J = rho^2 cos a`` ("sin")."""
        rho, beta, alpha = np.moveaxis(self.index_to_spherical(index), -1, 0)
        if self.convention == "tan":
            ta, tb = np.tan(alpha), np.tan(beta)
            j = rho ** 2 / (np.cos(alpha) ** 2 * np.cos(beta) ** 2 * (1 + ta * ta + tb * tb) ** 1.5)
        else:
            j = rho ** 2 * np.cos(alpha)
        return j * np.prod(self.separations)

    def _face_points(self, n: int = 33) -> np.ndarray:
        """Probe-frame points on the sector's boundary (for its bounding box):
        the six faces of the index box, with the central beam's angles among
        the samples so that the extremes on the axes are hit exactly."""
        upper = self.upper
        axes = []
        for k, c in zip((1, 2), self.centre_index):
            ticks = np.linspace(0, upper[k], n)
            if 0 <= c <= upper[k]:
                ticks = np.append(ticks, c)
            axes.append(ticks)
        r = np.linspace(0, upper[0], n)
        faces = []
        for r_face in (np.array([0.0, upper[0]]), r):
            for e_face, a_face in ((axes[0], axes[1]), (np.array([0.0, upper[1]]), axes[1]),
                                   (axes[0], np.array([0.0, upper[2]]))):
                g = np.stack(np.meshgrid(r_face, e_face, a_face, indexing="ij"), axis=-1).reshape(-1, 3)
                faces.append(g)
        return self.spherical_to_probe(self.index_to_spherical(np.concatenate(faces)))

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """World bounding box (min, max) of the sector."""
        w = self._face_points() @ self.rotation.T + self.apex
        return w.min(0), w.max(0)

    def default_spacing(self) -> float:
        """The finest distance between neighbouring beams at the sector's
        mid depth (mm): the lateral sampling a Cartesian grid needs there.
        (The radial sample size is usually finer than the beams' resolution;
        a grid that fine would hold ~100 times the samples.)"""
        mid = self.first_sample_distance + 0.5 * self.upper[0] * self.radius_sample_size
        return float(mid * min(self.azimuth_angular_separation, self.elevation_angular_separation))

    def cartesian_grid(self, spacing=None) -> ImageGrid:
        """A Cartesian grid covering the sector, axes along the probe's.

        Parameters
        ----------
        spacing : float or (x, y, z) floats, optional
            Voxel size in mm; default :meth:`default_spacing`, isotropic.
        """
        spacing = np.broadcast_to(np.asarray(self.default_spacing() if spacing is None else spacing, dtype=float),
                                  (3,)).copy()
        if not np.all(np.isfinite(spacing) & (spacing > 0)):
            raise ValueError(f"spacing must be positive (mm), got {spacing!r}")
        probe = self._face_points()
        lo, hi = probe.min(0), probe.max(0)
        n = np.floor((hi - lo) / spacing + 1e-9).astype(int) + 1
        # centre the grid on the sector's box
        lo = lo + 0.5 * ((hi - lo) - (n - 1) * spacing)
        n = np.maximum(n, 2)
        origin = self.rotation @ lo + self.apex
        return ImageGrid((int(n[2]), int(n[1]), int(n[0])), spacing, origin, self.rotation)


class BeamSamplingView(NamedTuple):
    """What beam-space sampling reads, as plain arrays (read-only): for the
    compiled kernel, which takes arrays, not objects."""

    values: np.ndarray  #: the samples, flat (azimuth fastest), NaN on no-data
    strides: np.ndarray  #: flat offsets of one step in r, e, a
    upper: np.ndarray  #: the last index in r, e, a
    rotation: np.ndarray  #: probe axes in world (columns), 3x3
    apex: np.ndarray  #: world point of the apex
    separations: np.ndarray  #: index step (mm, rad, rad) in r, e, a
    index_offset: np.ndarray  #: (rho, beta, alpha) at index (0, 0, 0)
    sin_convention: bool  #: "sin" convention (else "tan")


class BeamVolume:
    """An echo volume in beam space, with :class:`~spheroseg.volume.Volume`'s
    sampling contract (world points in, grey levels out, NaN outside the sector).

    Parameters
    ----------
    array : array, shape (n_r, n_e, n_a)
        Samples, indexed ``[radius, elevation, azimuth]``.
    geometry : BeamGeometry
        Where the samples lie; its ``shape`` must be the array's.
    no_data_value : float, optional
        Value marking samples without data; samples touching one are missing.
    no_data_mask : bool array, optional
        Samples without data, in addition.

    Notes
    -----
    Masks and volumes stay in world space: :attr:`grid` is the Cartesian grid
    covering the sector at :meth:`BeamGeometry.default_spacing` (the beams'
    spacing at mid depth), on which ``result.mask(beam_volume)`` is drawn.
    """

    def __init__(self, array, geometry: BeamGeometry, *, no_data_value=None, no_data_mask=None):
        if not isinstance(geometry, BeamGeometry):
            raise TypeError(f"geometry must be a BeamGeometry, got {type(geometry).__name__}")
        array = np.asarray(array)
        if array.ndim != 3:
            raise ValueError(f"a beam-space volume must be a 3D array [r, e, a], got shape {array.shape}")
        if array.shape != geometry.shape:
            raise ValueError(f"array shape {array.shape} does not match the geometry's {geometry.shape}")
        if not np.issubdtype(array.dtype, np.number) or np.iscomplexobj(array):
            raise ValueError(f"volume values must be real numbers, got dtype {array.dtype}")
        self.array = np.ascontiguousarray(array, dtype=np.float32)
        if not np.all(np.isfinite(self.array)):
            raise ValueError("volume contains NaN or infinite samples")
        self.geometry = geometry
        self.no_data_value = None if no_data_value is None else float(no_data_value)
        missing = None if no_data_value is None else self.array == self.no_data_value
        if no_data_mask is not None:
            no_data_mask = np.asarray(no_data_mask, dtype=bool)
            if no_data_mask.shape != self.array.shape:
                raise ValueError(f"no_data_mask must have the volume's shape {self.array.shape}, "
                                 f"got {no_data_mask.shape}")
            missing = no_data_mask if missing is None else missing | no_data_mask
        self.no_data_mask = missing
        samples = np.where(missing, np.float32(np.nan), self.array) if missing is not None and missing.any() \
            else self.array
        self._flat = samples.ravel()
        n_r, n_e, n_a = self.array.shape
        self._strides = np.array([n_e * n_a, n_a, 1], dtype=np.int64)
        self._grid = None

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.array.shape

    @property
    def grid(self) -> ImageGrid:
        """The Cartesian grid covering the sector (masks are drawn on it)."""
        if self._grid is None:
            self._grid = self.geometry.cartesian_grid()
        return self._grid

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """World bounding box of the sector."""
        return self.geometry.bounds

    def world_to_index(self, world) -> np.ndarray:
        """Continuous index ``[r, e, a]`` of world points."""
        return self.geometry.world_to_index(world)

    def index_to_world(self, index) -> np.ndarray:
        return self.geometry.index_to_world(index)

    def contains(self, world) -> np.ndarray:
        """Whether world points lie within the sector."""
        return self.geometry.contains(world)

    def sample(self, world, *, fill_value: float = np.nan, order: int = 1) -> np.ndarray:
        """Trilinear interpolation in ``[r, e, a]`` (``order=1``) or the
        nearest sample (``order=0``) at world points, shape ``world.shape[:-1]``;
        ``fill_value`` outside the sector or touching no-data."""
        if order not in (0, 1):
            raise ValueError(f"order must be 0 (nearest sample) or 1 (trilinear), got {order!r}")
        world = np.asarray(world, dtype=float)
        out = sample_at_index(self._flat, self._strides, self.geometry.upper,
                              self.geometry.world_to_index(world.reshape(-1, 3)), order=order, fill_value=fill_value)
        return out.reshape(world.shape[:-1])

    def sampling_view(self) -> BeamSamplingView:
        """The arrays :meth:`sample` reads (read-only views), for the compiled kernel."""
        g = self.geometry
        arrays = [np.ndarray.view(a) for a in (self._flat, self._strides)] + [
            np.array(a, dtype=float) for a in (g.upper, g.rotation, g.apex, g.separations, g.index_offset)]
        for a in arrays:
            a.flags.writeable = False
        return BeamSamplingView(*arrays, g.convention == "sin")

    def __call__(self, world) -> np.ndarray:
        return self.sample(world)

    def __repr__(self) -> str:
        g = self.geometry
        return (f"BeamVolume(shape={self.shape}, radius_sample_size={g.radius_sample_size:g}, "
                f"first_sample_distance={g.first_sample_distance:g}, convention={g.convention!r})")


def _grid_slice_points(grid: ImageGrid, k: int) -> np.ndarray:
    """World points of the voxels of slice ``k`` (x fastest), (ny * nx, 3)."""
    _, ny, nx = grid.shape
    j, i = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    index = np.stack([i.ravel(), j.ravel(), np.full(i.size, k)], axis=-1).astype(float)
    return grid.index_to_world(index)


def _sample_points(volume: BeamVolume, points: np.ndarray, order: int) -> np.ndarray:
    """``volume.sample(points, order=order)``, trilinear through the compiled
    kernel where the package was built (tested equal)."""
    from .._compiled._runtime import PARALLEL_LOCK, compiled_available

    if order != 1 or not compiled_available():
        return volume.sample(points, order=order)
    from .._compiled import _kernels
    n = len(points)
    out, count = np.empty(n), np.empty(n, np.int64)
    with PARALLEL_LOCK:
        _kernels.sample_along(*_kernels.sampler(volume.sampling_view()), np.ascontiguousarray(points.T),
                              np.zeros((3, n)), np.arange(n), np.zeros(1), 0.0, out, count)
    return out


#: bytes a voxel of a scan conversion's grid holds at the peak, per frame
#: kept (the Volume's float32 voxels, its no-data mask and its NaN-marked
#: copy for sampling, the float32 copy a file is written from and
#: SimpleITK's) and once more for the frame being converted (its float64
#: samples, their NaN mask, the zero-filled copy)
SCAN_CONVERT_BYTES = {"per_frame": 4 + 1 + 4 + 4 + 4, "converting": 8 + 1 + 8}


def check_scan_conversion(grid: ImageGrid, frames: int = 1) -> None:
    """Refuse a scan conversion of ``frames`` frames onto ``grid`` whose
    arrays would exceed the memory budget (:mod:`spheroseg.volumes.budget`), before
    any is made: a fine voxel size makes a grid of its cube."""
    from .budget import check_allocation

    voxels = math.prod(grid.shape)
    need = voxels * (frames * SCAN_CONVERT_BYTES["per_frame"] + SCAN_CONVERT_BYTES["converting"])
    nz, ny, nx = grid.shape
    check_allocation(need, f"a scan conversion of {frames} frame(s) onto {nx} x {ny} x {nz} voxels of "
                           f"{grid.spacing[0]:.3g} mm")


def scan_convert(volume: BeamVolume, grid: ImageGrid | None = None, *, order: int = 1) -> Volume:
    """Resample a beam-space volume on a Cartesian grid.

    Parameters
    ----------
    volume : BeamVolume
    grid : ImageGrid, optional
        Default: ``volume.grid``, covering the sector at the beams' spacing at
        mid depth.
    order : {0, 1}
        Nearest sample or trilinear in ``[r, e, a]``.

    Returns
    -------
    Volume
        Voxels outside the sector (or touching no-data samples) are 0 and in
        its ``no_data_mask``: the exact sector, not a guess from the zeros.
    """
    if not isinstance(volume, BeamVolume):
        raise TypeError(f"scan_convert takes a BeamVolume, got {type(volume).__name__}")
    grid = volume.grid if grid is None else grid
    if not isinstance(grid, ImageGrid):
        raise TypeError(f"grid must be an ImageGrid, got {type(grid).__name__}")
    if order not in (0, 1):
        raise ValueError(f"order must be 0 (nearest sample) or 1 (trilinear), got {order!r}")
    check_scan_conversion(grid)
    values = np.stack([_sample_points(volume, _grid_slice_points(grid, k), order) for k in range(grid.shape[0])])
    values = values.reshape(grid.shape)
    missing = np.isnan(values)
    return Volume(np.where(missing, 0.0, values), spacing=grid.spacing, origin=grid.origin, direction=grid.direction,
                  no_data_mask=missing)


def to_beam_space(volume: Volume, geometry: BeamGeometry, *, order: int = 1) -> BeamVolume:
    """Resample a Cartesian volume on a beam-space geometry (inverse scan
    conversion, as ITKUltrasound's inverse filter): samples falling outside
    the image or on its no-data are 0 and in the result's ``no_data_mask``."""
    if not isinstance(volume, Volume):
        raise TypeError(f"to_beam_space takes a Volume, got {type(volume).__name__}")
    if not isinstance(geometry, BeamGeometry):
        raise TypeError(f"geometry must be a BeamGeometry, got {type(geometry).__name__}")
    index = np.stack(np.meshgrid(*[np.arange(n, dtype=float) for n in geometry.shape], indexing="ij"), axis=-1)
    values = volume.sample(geometry.index_to_world(index.reshape(-1, 3)), order=order).reshape(geometry.shape)
    missing = np.isnan(values)
    return BeamVolume(np.where(missing, 0.0, values), geometry, no_data_mask=missing if missing.any() else None)


def beam_mask(region, geometry: BeamGeometry) -> np.ndarray:
    """Boolean mask ``[r, e, a]`` of the samples inside ``region`` (anything
    with ``contains(world_points)``, e.g. a :class:`~spheroseg.Surface`):
    the beam-space alternative to a mask on a Cartesian grid."""
    if not isinstance(geometry, BeamGeometry):
        raise TypeError(f"geometry must be a BeamGeometry, got {type(geometry).__name__}")
    n_r, n_e, n_a = geometry.shape
    index = np.stack(np.meshgrid(np.arange(n_e, dtype=float), np.arange(n_a, dtype=float), indexing="ij"), -1)
    out = np.empty(geometry.shape, dtype=bool)
    for r in range(n_r):  # a shell at a time: bounded memory
        shell = np.concatenate([np.full(index.shape[:-1] + (1,), float(r)), index], axis=-1)
        out[r] = region.contains(geometry.index_to_world(shell))
    return out


def beam_mask_volume_ml(mask, geometry: BeamGeometry) -> float:
    """Volume (mL) of a beam-space mask: each sample counts the volume of its
    index cell, ``geometry.jacobian`` (mm^3) at the sample (midpoint rule)."""
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != geometry.shape:
        raise ValueError(f"the mask's shape {mask.shape} is not the geometry's {geometry.shape}")
    return float(geometry.jacobian(np.argwhere(mask).astype(float)).sum()) / 1000.0
