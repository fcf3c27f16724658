"""Segmentation and tracking: the descent of paper eq. 25 on the Hermite
parameters, initialised from apex and base points.

One iteration:

1. the surface at the fixed sample points (the Hermite basis there is
   precomputed) and one coordinate transform;
2. the image at each surface point (trilinear), and the region means
   ``c_in``, ``c_out`` from samples along the outward normals;
3. the region force ``r = (u - c_in)^2 - (u - c_out)^2`` (paper eq. 22),
   made dimensionless by the contrast and clipped to ``[-1, 1]``, gives a
   normal displacement of at most ``step`` mm;
4. that displacement, converted to ``v0`` units, is projected onto the
   Hermite space (least squares with the mass matrix ``M``: the exact form
   of eq. 10's normalisation, so the update is ``dH = -dt M^-1 dF/dH``
   with the force per unit area instead of per unit ``v1 v2``); an
   implicit thin-plate step towards the initial shape (``smoothness``) and
   landmark rows (the clicked apex, the user's points) join that
   least-squares problem.

Steps 1-2 run in one compiled loop when numba is installed
(:mod:`spheroseg._kernels`, prolate system); the numpy code here is the
reference it is tested against.

Data terms (``mode``):

``"fast"``
    The paper's fast mode: ``c_in``, ``c_out`` fixed once (Otsu on the
    samples of the initial surface, or ``interface`` given).
``"chan-vese"``
    Global two-region means re-estimated every iteration from samples in
    model space: the cavity along each ray, and a shell of ``band_out`` mm
    outside the surface.
``"local"`` (default)
    Means local to each surface point, from a band of ``band`` mm on each
    side along the normal, smoothed over the surface by the same Hermite
    projection (localised region energy, Lankton & Tannenbaum 2008; as in
    BEAS, Barbosa et al. 2012).  Where the local contrast is low (dropout,
    or both bands in the blood pool) the force fades instead of leaking.
    The coarse levels of the coarse-to-fine schedule use the global means,
    which bring the surface to the walls from afar.  Means are taken on a
    quarter of the sample points (they are smoothed over the surface).

All image access is at points set by the model; no step touches every voxel.
"""

from __future__ import annotations

import time
from functools import lru_cache
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
import scipy.linalg

from . import _kernels
from .coords import ProlateSpheroidal
from .energy import Landmarks, SampledSurface, _grid_matrices, area_gradient, region_force
from .surface import DEFAULT_RADIUS_RATIO, Surface
from .volume import Volume

__all__ = ["segment", "track", "SegmentationResult", "TrackingResult", "MODES"]

MODES = ("local", "chan-vese", "fast")

# along-normal offsets (mm) of the grey level at the surface: averaging over
# +-1 mm changed no result on the phantoms or CETUS Patient 7 (the projection
# already averages 64 points per patch) and cost two thirds of the samples
_SURFACE_OFFSETS = np.array([0.0])
# band means are taken on every other sample point in each direction
_BAND_STRIDE = 2
# the thin-plate matrix relative to the mass matrix for smoothness = 1:
# its eigenvalues grow as k^4 for angular wavenumber k; this makes
# smoothness = 1 damp a k = 8 wave (patch scale at 8 x 8) by half per step
_ROUGHNESS_SCALE = 8.0**4
# least cosine between the normal and the v0 direction when converting a
# normal displacement into a v0 displacement (keeps grazing rays bounded)
_MIN_COS = 0.3


@dataclass
class SegmentationResult:
    """What :func:`segment` found.

    Attributes
    ----------
    surface : Surface
    iterations : int
        Iterations run, over all levels.
    converged : bool
        Whether the last level stopped on surface motion (not the cap).
    c_in, c_out : float
        Median region means at the end (image units).
    seconds : float
        Wall time of the segmentation.
    """

    surface: Surface
    iterations: int
    converged: bool
    c_in: float
    c_out: float
    seconds: float
    parameters: dict = field(default_factory=dict)

    @property
    def volume_ml(self) -> float:
        """Volume of the cavity, closed at the base plane (mL)."""
        return self.surface.volume_ml()

    def mask(self, volume: Volume) -> np.ndarray:
        """Boolean mask ``[z, y, x]`` of the cavity on ``volume``'s grid."""
        return self.surface.mask(volume.grid)

    def mesh(self, n_v1: int = 64, n_v2: int = 32, *, closed: bool = True):
        """Triangle mesh ``(points [n, 3] world mm, faces [m, 3])``."""
        return self.surface.mesh(n_v1, n_v2, closed=closed)


@dataclass
class TrackingResult:
    """Per-frame results of :func:`track`, and the clinical indices."""

    frames: list[SegmentationResult]

    @property
    def volumes_ml(self) -> np.ndarray:
        return np.array([f.volume_ml for f in self.frames])

    @property
    def ed_frame(self) -> int:
        """End-diastole: the frame of largest volume."""
        return int(np.argmax(self.volumes_ml))

    @property
    def es_frame(self) -> int:
        """End-systole: the frame of smallest volume."""
        return int(np.argmin(self.volumes_ml))

    @property
    def edv_ml(self) -> float:
        return float(self.volumes_ml.max())

    @property
    def esv_ml(self) -> float:
        return float(self.volumes_ml.min())

    @property
    def ef(self) -> float:
        """Ejection fraction in percent, ``100 (EDV - ESV) / EDV``."""
        return 100.0 * (self.edv_ml - self.esv_ml) / self.edv_ml


def _check_point(volume: Volume, point, name: str) -> np.ndarray:
    p = np.asarray(point, dtype=float)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ValueError(f"{name} must be 3 finite numbers (x, y, z in mm), got {point!r}")
    if not volume.contains(p):
        lo, hi = volume.bounds
        raise ValueError(f"{name} {tuple(p.round(2))} lies outside the image (x, y, z from {tuple(lo.round(1))} to {tuple(hi.round(1))} mm)")
    return p


def _otsu(values: np.ndarray) -> float:
    """Threshold maximising the between-class variance of the values."""
    v = np.sort(values)
    n = len(v)
    csum = np.cumsum(v)
    k = np.arange(1, n)
    m0 = csum[:-1] / k
    m1 = (csum[-1] - csum[:-1]) / (n - k)
    score = k * (n - k) * (m1 - m0) ** 2
    i = int(np.argmax(score))
    return float((v[i] + v[i + 1]) / 2)


@dataclass
class _Observation:
    """What an iteration reads at the sample points (the compiled path's
    arrays are reused: valid until the next observation)."""

    f: np.ndarray
    h0: np.ndarray  # scale factor of v0 at the surface (mm per unit v0)
    cos: np.ndarray  # cosine between the outward normal and dx/dv0
    area: np.ndarray  # A_K, the area element of (v1, v2)
    world: np.ndarray  # surface points (world mm), (3, n)
    normal: np.ndarray  # unit outward normals (world), (3, n)
    u: np.ndarray  # grey level at the surface, averaged along the normal
    inside: np.ndarray | None = None  # band means on the band rows
    outside: np.ndarray | None = None
    geometry: object = None  # the full Geometry (numpy path only)


@dataclass(frozen=True)
class _Level:
    """What a level precomputes from the grid alone: shared, read-only, by
    every segmentation at this resolution (:func:`_level_matrices`)."""

    mass: np.ndarray
    mass_inverse: np.ndarray
    constraints_t: object  # A^T (sparse), from coefficients to parameters
    smoothing: np.ndarray
    system_inverse: np.ndarray  # (M + smoothing)^-1
    band_rows: np.ndarray  # indices of the sample points of the band means
    band_transpose: object  # B^T on the band rows (sparse)
    band_weights: np.ndarray
    tables: tuple  # the compiled path's basis tables (v1, v2) at every sample position
    band_tables: tuple  # the same at the band rows' positions
    trig: tuple  # cos, sin of v1 and v2 at the sample points


def _spd_inverse(matrix: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive definite matrix (through Cholesky).

    An iteration applies the inverses as mat-vecs: at 259 unknowns that is
    5 us against 23 for a triangular solve."""
    factor = scipy.linalg.cho_factor(matrix)
    inverse = scipy.linalg.cho_solve(factor, np.eye(len(matrix)))
    return (inverse + inverse.T) / 2


@lru_cache(maxsize=16)
def _level_matrices(grid, order: int, smoothness: float) -> _Level:
    """The :class:`_Level` of a grid, sample order and smoothness (cached)."""
    v1, v2, weights, _, b_f, _, _, mass = _grid_matrices(grid, order)
    total = float(weights.sum())  # the area of the (v1, v2) domain
    # the thin-plate matrix T is per unit area, M is not
    smoothing = smoothness * total / _ROUGHNESS_SCALE * grid.roughness_matrix().toarray()
    # band means on every other sample position of a patch in each direction
    # (a quarter of the points): they are smoothed over the surface anyway
    local = np.arange(order) % _BAND_STRIDE == 0
    n_row = grid.n1 * order
    q = np.arange(len(weights))
    band_rows = np.flatnonzero(local[(q % n_row) % order] & local[(q // n_row) % order])
    band_weights = weights[band_rows] * (total / weights[band_rows].sum())
    tables = _kernels.basis_tables(grid, order)
    level = _Level(
        mass=mass, mass_inverse=_spd_inverse(mass), constraints_t=grid.constraints.T.tocsr(), smoothing=smoothing,
        system_inverse=_spd_inverse(mass + smoothing), band_rows=band_rows,
        band_transpose=b_f[band_rows].T.tocsr(), band_weights=band_weights, tables=tables,
        band_tables=tuple(np.ascontiguousarray(t[:, local]) for t in tables),
        trig=(np.cos(v1), np.sin(v1), np.cos(v2), np.sin(v2)))
    for value in vars(level).values():
        for array in value if isinstance(value, tuple) else (value,):
            if isinstance(array, np.ndarray):
                array.flags.writeable = False
    return level


class _Descent:
    """The iteration at one level of the coarse-to-fine schedule."""

    def __init__(self, volume, surface, reference, *, order, step, band, band_out, landmarks, landmark_weights, nu,
                 smoothness, compiled=True):
        self.volume = volume
        self.model = SampledSurface(surface.system, surface.pose, surface.grid, order)
        self.p = self.model.parameters(surface.coefficients)
        self.step, self.nu = step, nu
        level = self.level = _level_matrices(surface.grid, order, float(smoothness))
        self._total_weight = total = float(self.model.weights.sum())
        # the update solves (M + a T + w L^T L) p_new = M p + B^T W dv0 + a T p_ref + w L^T res:
        # least squares on the displacement, an implicit (unconditionally
        # stable) thin-plate smoothing step of the departure from the
        # reference (initial) shape, and the landmark rows
        self.set_reference(reference)
        self.system_inverse = level.system_inverse
        self.landmarks = None
        if landmarks is not None and len(landmarks):
            self.landmarks = Landmarks.from_world(self.model, landmarks)
            # weight 1: a landmark outweighs the data over 5 % of the (v1, v2)
            # domain, about one patch at 4 x 4
            self.omega = np.asarray(landmark_weights, float) * 0.05 * total
            self._landmark_basis = self.landmarks.basis.toarray()
            self.system_inverse = _add_rows(level.system_inverse, self._landmark_basis, self.omega)
        self._inside_t = np.array([0.15, 0.35, 0.55, 0.75, 0.95])
        self._shell = np.linspace(0, band_out, 6)[1:]
        self._band = np.linspace(0, band, 5)[1:]
        self.band_rows = level.band_rows
        self._h0_floor = None
        self._radius = None
        self.kernel = _kernels.AVAILABLE and compiled and isinstance(surface.system, ProlateSpheroidal)
        if self.kernel:
            n, nb = self.model.n_samples, len(self.band_rows)
            self._all_rows = np.arange(n)
            self._buffers = dict(
                f=np.empty(n), h0=np.empty(n), cos=np.empty(n), area=np.empty(n), world=np.empty((3, n)),
                normal=np.empty((3, n)), u=np.empty(n), inside=np.empty(nb), outside=np.empty(nb))
            self._counts = np.empty(n, np.int64)
            self._displacement = np.empty(n)

    def set_reference(self, reference: Surface) -> None:
        """The shape the thin-plate prior pulls towards."""
        self.prior = self.level.smoothing @ self.model.parameters(reference.coefficients)

    # the Hermite basis at the sample points ----------------------------------

    def _at_samples(self, p) -> np.ndarray:
        """``B p``: the function(s) of parameters ``p`` (``(n,)`` or ``(n, k)``)
        at every sample point (``(samples,)`` or ``(k, samples)``)."""
        m = self.model
        if not self.kernel:
            return (m.b_f @ p).T
        fields = p.reshape(len(p), -1)
        coefficients = np.ascontiguousarray((m.constraints @ fields).T).reshape((-1,) + m.grid.shape)
        out = np.empty((len(coefficients), m.n_samples))
        _kernels.gather(coefficients, m.order, *self.level.tables, out)
        return out[0] if p.ndim == 1 else out

    def _transpose(self, values, *, band: bool = False) -> np.ndarray:
        """``B^T values`` in the parameters, for values ``(samples,)`` or
        ``(k, samples)`` at every sample point, or at the band rows."""
        m = self.model
        if not self.kernel:
            return (self.level.band_transpose if band else m.b_f.T) @ values.T
        fields = values.reshape(-1, values.shape[-1])
        coefficients = np.empty((len(fields),) + m.grid.shape)
        tables = self.level.band_tables if band else self.level.tables
        _kernels.scatter(fields, tables[0].shape[1], *tables, coefficients)
        out = self.level.constraints_t @ coefficients.reshape(len(fields), -1).T
        return out[:, 0] if values.ndim == 1 else out

    # image samples -------------------------------------------------------

    def _image(self):
        vol = self.volume
        return vol._flat, vol._strides, vol._upper, vol._to_index, vol.grid.origin

    def _along_normal(self, obs, offsets, rows=slice(None)):
        pts = obs.world.T[rows, None, :] + offsets[None, :, None] * obs.normal.T[rows, None, :]
        return self.volume.sample(pts)

    def observe(self, bands: bool, geometry: bool = False) -> _Observation:
        """The surface at the sample points and the image along its normals
        (with ``geometry``, also the full :class:`Geometry`: numpy path)."""
        if self.kernel and not geometry:
            return self._observe_compiled(bands)
        m = self.model
        g = m.geometry(self.p)
        h0 = m.system.scale_factors(g.f, m.v1, m.v2)[0]
        cos = np.einsum("ij,ij->i", g.normal @ m.pose.rotation, g.jacobian[:, :, 0]) / h0
        obs = _Observation(g.f, h0, cos, g.area, g.world.T, g.normal.T, geometry=g, u=None)
        obs.u = _row_nanmean(self._along_normal(obs, _SURFACE_OFFSETS))
        if bands:
            obs.inside = _row_nanmean(self._along_normal(obs, -self._band, self.band_rows))
            obs.outside = _row_nanmean(self._along_normal(obs, self._band, self.band_rows))
        return obs

    def _observe_compiled(self, bands: bool) -> _Observation:
        m, b = self.model, self._buffers
        coefficients = (m.constraints @ self.p).reshape(m.grid.shape)
        _kernels.prolate_surface(coefficients, m.order, *self.level.tables, *self.level.trig, m.system.focal_length,
                                 m.pose.rotation, m.pose.origin, b["f"], b["h0"], b["cos"], b["area"], b["world"],
                                 b["normal"])
        image = self._image()
        _kernels.sample_along(*image, b["world"], b["normal"], self._all_rows, _SURFACE_OFFSETS, b["u"], self._counts)
        obs = _Observation(**b)
        if bands:
            counts = self._counts[:len(self.band_rows)]
            _kernels.sample_along(*image, b["world"], b["normal"], self.band_rows, -self._band, b["inside"], counts)
            _kernels.sample_along(*image, b["world"], b["normal"], self.band_rows, self._band, b["outside"], counts)
        else:
            obs.inside = obs.outside = None
        return obs

    # region statistics ----------------------------------------------------

    def global_means(self, obs: _Observation):
        """Volume-weighted cavity mean and area-weighted shell mean, from the
        rays of the band rows (a quarter of the sample points)."""
        m, rows = self.model, self.band_rows
        if self.kernel:
            image = self._image()
            cavity, volume = np.empty(len(rows)), np.empty(len(rows))
            _kernels.cavity_sums(*image, obs.f, *self.level.trig, m.system.focal_length, m.pose.rotation,
                                 m.pose.origin, rows, self._inside_t, cavity, volume)
            shell, count = np.empty(len(rows)), np.empty(len(rows), np.int64)
            _kernels.sample_along(*image, obs.world, obs.normal, rows, self._shell, shell, count)
        else:
            v0 = obs.f[rows, None] * self._inside_t[None, :]
            v1 = np.broadcast_to(m.v1[rows, None], v0.shape)
            v2 = np.broadcast_to(m.v2[rows, None], v0.shape)
            u_in = self.volume.sample(m.pose.to_world(m.system.to_cartesian(v0, v1, v2)))
            element = np.where(np.isfinite(u_in), m.system.volume_element(v0, v1, v2), 0.0)
            cavity, volume = (element * np.nan_to_num(u_in)).sum(axis=1), element.sum(axis=1)
            u_out = self._along_normal(obs, self._shell, rows)
            shell, count = _row_nanmean(u_out), np.isfinite(u_out).sum(axis=1)
        # per ray: cavity = sum of V u, volume = sum of V over the finite samples
        w_in = m.weights[rows] * obs.f[rows]
        w_out = m.weights[rows] * obs.area[rows] * count
        return _ratio(w_in @ cavity, w_in @ volume), _ratio(w_out @ np.nan_to_num(shell), w_out.sum())

    def local_means(self, obs: _Observation):
        """Band means smoothed over the surface: the L2 projection onto the
        Hermite space (the band rows' quadrature), evaluated everywhere;
        ``(c_in, c_out)``, or ``None`` with no data in a band."""
        fields = np.stack([obs.inside, obs.outside])
        ok = np.isfinite(fields)
        if not ok[0].any() or not ok[1].any():
            return None
        if not ok.all():
            fields = np.where(ok, fields, np.nanmean(fields, axis=1)[:, None])
        rhs = self._transpose(self.level.band_weights * fields, band=True)
        # one mat-vec a field: BLAS multiplies a 259 x 2 block slower than that
        smooth = np.stack([self.level.mass_inverse @ column for column in rhs.T], axis=1)
        return self._at_samples(smooth)

    # the step ---------------------------------------------------------------

    def iterate(self, obs: _Observation, c_in, c_out, scale):
        m = self.model
        if self._h0_floor is None:  # fixed per level: a median per iteration costs more than the rest
            self._h0_floor = 0.3 * float(np.median(obs.h0))
        if self.kernel and not self.nu:
            wdv0 = self._displacement
            c_in, c_out = (np.full(m.n_samples, c) if np.ndim(c) == 0 else c for c in (c_in, c_out))
            _kernels.normal_displacement(obs.u, c_in, c_out, scale, obs.h0, obs.cos, self._h0_floor, _MIN_COS,
                                         self.step, m.weights, wdv0)
        else:
            r = region_force(obs.u, c_in, c_out) / scale
            # mm per step, outward; a surface point off the image's data (out of
            # the sector) is pulled back: the cavity is where the data are
            speed = np.where(np.isfinite(r), -np.clip(r, -1.0, 1.0), np.where(np.isfinite(obs.u), 0.0, -1.0))
            # mm of wall per unit v0 (h0 is bounded below too: near a focal
            # point v0 barely moves the surface)
            normal_to_v0 = np.maximum(obs.h0 * np.maximum(obs.cos, _MIN_COS), self._h0_floor)
            if self.nu:
                speed = speed + self.nu * self._area_speed(obs.geometry, normal_to_v0)
            wdv0 = m.weights * self.step * speed / normal_to_v0
        rhs = self._transpose(wdv0)
        if self.landmarks is not None:
            # rows omega |L p_new - (L p + res)|^2: move towards each landmark
            # by at most a step
            lm = self.landmarks
            f = self._landmark_basis @ self.p
            res = np.clip((lm.v0 - f) * lm.h0, -self.step, self.step) / lm.h0
            rhs += self._landmark_basis.T @ (self.omega * (f + res))
        p_new = self.system_inverse @ (self.level.mass @ self.p + self.prior + rhs)
        dp = p_new - self.p
        self.p = p_new
        return np.sqrt(np.dot(m.weights, (obs.h0 * self._at_samples(dp)) ** 2) / self._total_weight)

    def _area_speed(self, g, normal_to_v0) -> np.ndarray:
        """Normal speed (steps, outward) of the area term: minus the mean
        curvature from the gradient of paper eq. 23, made dimensionless by
        the typical radius so that ``nu = 1`` moves a sphere by a step.

        ``dA/dp = int G f_i`` where ``G = 2H h0 cos A_K`` (``2H`` the sum of
        the principal curvatures); ``B M^-1 dA/dp`` is ``G`` projected on the
        Hermite space."""
        m = self.model
        field = self._at_samples(self.level.mass_inverse @ area_gradient(m, self.p, g))
        two_h = field / (np.maximum(g.area, 1e-12) * normal_to_v0)
        if self._radius is None:
            self._radius = float(np.median(np.linalg.norm(g.local, axis=1)))
        return -np.clip(0.5 * two_h * self._radius, -1.0, 1.0)

    def surface(self, like: Surface) -> Surface:
        return like.with_coefficients(self.model.coefficients(self.p))


def _add_rows(inverse: np.ndarray, rows: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """``(K + L^T diag(w) L)^-1`` from ``K^-1`` (Woodbury: a few landmark
    rows need no new factorisation)."""
    u = inverse @ rows.T
    core = np.eye(len(rows)) + weights[:, None] * (rows @ u)
    return inverse - u @ np.linalg.solve(core, weights[:, None] * u.T)


def _ratio(numerator: float, denominator: float) -> float:
    return float(numerator / denominator) if denominator > 0 else np.nan


def _row_nanmean(values: np.ndarray) -> np.ndarray:
    """Mean of each row's finite values; NaN for a row with none."""
    ok = np.isfinite(values)
    n = ok.sum(axis=1)
    total = np.where(ok, values, 0.0).sum(axis=1)
    return np.where(n > 0, total / np.maximum(n, 1), np.nan)


def _levels(patches: tuple[int, int], coarse_to_fine: bool) -> list[tuple[int, int]]:
    levels = [tuple(patches)]
    while coarse_to_fine and min(levels[0]) >= 4 and levels[0][0] % 2 == 0 and levels[0][1] % 2 == 0:
        levels.insert(0, (levels[0][0] // 2, levels[0][1] // 2))
    return levels


def _run_level(descent: _Descent, mode, stats, *, max_iterations, tol, callback, like, first_iteration):
    """Iterate one level; returns (iterations, converged, c_in, c_out)."""
    c_in = c_out = np.nan
    global_means = mode == "chan-vese" or stats.get("global_level")
    for it in range(max_iterations):
        obs = descent.observe(bands=mode == "local" and not global_means, geometry=descent.nu > 0)
        if mode == "fast":
            c_in, c_out = stats["c_in"], stats["c_out"]
            scale = (c_out - c_in) ** 2
        elif global_means:
            c_in, c_out = descent.global_means(obs)
            scale = max((c_out - c_in) ** 2, stats["min_scale"])
        else:
            means = descent.local_means(obs)
            if means is None:
                raise ValueError("no image data around the surface (is it inside the image's sector?)")
            c_in, c_out = means[0], means[1]
            contrast = np.maximum(c_out - c_in, 0.0)
            c_out = c_in + contrast  # wrong polarity (inside brighter): no force
            scale = max(np.median(contrast) ** 2, stats["min_scale"])
        motion = descent.iterate(obs, c_in, c_out, scale)
        if callback is not None:
            callback(descent.surface(like), first_iteration + it)
        if motion < tol:
            return it + 1, True, c_in, c_out
    return max_iterations, False, c_in, c_out


def segment(
    volume: Volume,
    apex,
    base,
    *,
    system: str = "prolate",
    patches: tuple[int, int] = (8, 8),
    mode: str = "local",
    step: float = 1.0,
    max_iterations: int = 60,
    tol: float = 0.05,
    coarse_to_fine: bool = True,
    band: float = 8.0,
    band_out: float = 15.0,
    interface: float | None = None,
    nu: float = 0.0,
    smoothness: float = 1.0,
    landmarks=None,
    landmark_weight: float = 1.0,
    apex_weight: float = 1.0,
    order: int = 8,
    radius_ratio: float = DEFAULT_RADIUS_RATIO,
    init: Surface | None = None,
    iter_callback: Callable[[Surface, int], None] | None = None,
    _state: dict | None = None,
) -> SegmentationResult:
    """Segment the left-ventricular cavity from an apex and a base point.

    Parameters
    ----------
    volume : Volume
        3D echo image (blood dark, tissue bright).
    apex, base : (x, y, z)
        World points (mm, ITK physical space): the endocardial apex and the
        centre of the mitral plane.  The cavity is closed at the plane
        through ``base`` perpendicular to the apex-base axis.
    system : {"prolate", "spherical", "cylindrical"}
        Coordinate system of the surface (paper eq. 2).
    patches : (int, int)
        Hermite patches around (theta) and along (apex to base) the cavity;
        the paper's 8 x 8 by default.
    mode : {"local", "chan-vese", "fast"}
        Data term (module docstring).
    step : float
        Largest normal displacement of the surface per iteration, mm.  The
        default 1 mm is about 4 % of a ventricle's radius: the paper's
        ``dt = 0.04``.
    max_iterations : int
        Cap on iterations at each level of the coarse-to-fine schedule.
    tol : float
        A level stops when the RMS motion of the surface in an iteration
        falls below ``tol`` mm.
    coarse_to_fine : bool
        Start on a quarter and then half of the patches (exact refinement).
    band, band_out : float
        Widths (mm) of the bands of the local means and of the outer shell
        of the global means.
    interface : float, optional
        Grey level of the interface for ``mode="fast"`` (default: Otsu's
        threshold of the samples around the initial surface).
    nu : float
        Weight of the area term (paper eqs. 16-17, 23-24), 0 as in the paper:
        a normal speed of ``nu`` times the mean curvature times the typical
        radius, in steps (1 moves a sphere inwards by a step).
    smoothness : float
        Weight of a thin-plate regularisation of the surface's departure
        from its initial shape (the half-ellipsoid, or ``init``), applied as
        an implicit step each iteration (0 for the paper's method).  It costs
        nothing per iteration and keeps the surface from squeezing through
        gaps in the wall (dropout) at the patch scale; 1 halves a wave of
        the patch size at 8 x 8 patches per step.
    landmarks : array (k, 3), optional
        World points the surface must pass through (to stop a leak).
    landmark_weight : float
        How strongly the landmarks hold the surface (1: a landmark
        outweighs the data over 5 % of the surface, about a patch at 4 x 4).
    apex_weight : float
        The apex point is a landmark of this weight (0: free apex).
    order : int
        Sample points per patch and direction (paper: 8).
    radius_ratio : float
        Base radius of the initial half-ellipsoid over the apex-base distance.
    init : Surface, optional
        Start from this surface instead (tracking); ``apex`` and ``base``
        are then only checked.
    iter_callback : callable, optional
        Called as ``iter_callback(surface, iteration)`` after every
        iteration (the scikit-image convention).

    Returns
    -------
    SegmentationResult
    """
    started = time.perf_counter()
    if not isinstance(volume, Volume):
        raise TypeError(f"volume must be a spheroseg.Volume, got {type(volume).__name__}")
    apex = _check_point(volume, apex, "apex")
    base = _check_point(volume, base, "base")
    if np.linalg.norm(apex - base) < 1e-6:
        raise ValueError("apex and base must be distinct points")
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    for name, value in (("step", step), ("tol", tol), ("band", band), ("band_out", band_out)):
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a positive number, got {value!r}")
    if not (isinstance(max_iterations, (int, np.integer)) and max_iterations >= 0):
        raise ValueError(f"max_iterations must be a non-negative integer, got {max_iterations!r}")
    if min(nu, landmark_weight, apex_weight, smoothness) < 0:
        raise ValueError("nu, smoothness, landmark_weight and apex_weight must be >= 0")
    if landmarks is not None:
        landmarks = np.asarray(landmarks, dtype=float).reshape(-1, 3)
        for k, lm in enumerate(landmarks):
            _check_point(volume, lm, f"landmark {k}")
    if apex_weight > 0:
        # the apex is a point of the endocardium the user clicked: hold the
        # surface there (near-field clutter would otherwise push it down)
        held = landmarks if landmarks is not None else np.empty((0, 3))
        landmarks = np.concatenate([held, apex[None]])
        weights = np.concatenate([np.full(len(held), landmark_weight), [apex_weight]])
    else:
        weights = None if landmarks is None else np.full(len(landmarks), landmark_weight)

    levels = _levels(patches, coarse_to_fine and init is None)
    if init is None:
        surface = Surface.from_apex_base(apex, base, system=system, patches=levels[0], radius_ratio=radius_ratio)
    else:
        surface = init
    settings = dict(order=order, step=step, band=band, band_out=band_out, landmarks=landmarks,
                    landmark_weights=weights, nu=nu, smoothness=smoothness)

    # region statistics of the initial surface: a check that there is
    # something to segment, the scale of the contrast, the fast mode's levels
    if _state is not None and init is not None and _state.get("descent") is not None \
            and _state["descent"].model.grid == init.grid:
        return _follow(volume, init, _state, mode, max_iterations, tol, iter_callback, started)
    reference = surface
    probe = _Descent(volume, surface, reference, **settings)
    obs = probe.observe(bands=False)
    c_in0, c_out0 = probe.global_means(obs)
    rows = probe.band_rows
    samples = np.concatenate([probe._along_normal(obs, -probe._band, rows).ravel(),
                              probe._along_normal(obs, probe._shell, rows).ravel()])
    samples = samples[np.isfinite(samples)]
    if samples.size < 10 or np.ptp(samples) <= 1e-6 * max(np.abs(samples).max(), 1.0):
        raise ValueError("the image is constant (or empty) around the initial surface: nothing to segment")
    spread = np.std(samples)
    stats = {"min_scale": (0.05 * spread) ** 2}
    if mode == "fast":
        mid = _otsu(samples) if interface is None else float(interface)
        lo, hi = samples[samples <= mid], samples[samples > mid]
        half = (hi.mean() - lo.mean()) / 2 if lo.size and hi.size else spread
        stats.update(c_in=mid - half, c_out=mid + half)

    total, converged, c_in, c_out = 0, False, c_in0, c_out0
    for li, level in enumerate(levels):
        while (surface.grid.n1, surface.grid.n2) != level:
            surface, reference = surface.refine(), reference.refine()
        descent = probe if li == 0 else _Descent(volume, surface, reference, **settings)
        stats["global_level"] = mode == "local" and li < len(levels) - 1
        n, converged, c_in, c_out = _run_level(
            descent, mode, stats, max_iterations=max_iterations, tol=tol, callback=iter_callback,
            like=surface, first_iteration=total,
        )
        total += n
        surface = descent.surface(surface)
    if _state is not None:
        _state.update(descent=descent, stats=stats, parameters=None)

    result = SegmentationResult(
        surface=surface,
        iterations=total,
        converged=converged,
        c_in=float(np.nanmedian(c_in)),
        c_out=float(np.nanmedian(c_out)),
        seconds=time.perf_counter() - started,
        parameters=dict(system=surface.system.name, patches=list(patches), mode=mode, step=step,
                        max_iterations=max_iterations, tol=tol, coarse_to_fine=coarse_to_fine, band=band,
                        band_out=band_out, interface=interface, nu=nu, smoothness=smoothness, landmark_weight=landmark_weight,
                        apex_weight=apex_weight,
                        order=order, radius_ratio=radius_ratio),
    )
    if _state is not None:
        _state["parameters"] = result.parameters
    return result


def _follow(volume, init: Surface, state: dict, mode, max_iterations, tol, iter_callback, started) -> SegmentationResult:
    """Continue the finest level of an earlier segmentation on a new frame:
    same model, precomputed matrices and region statistics; the previous
    surface is the start and the reference shape of the smoothing prior."""
    descent = state["descent"]
    descent.volume = volume
    descent.p = descent.model.parameters(init.coefficients)
    descent.set_reference(init)
    stats = state["stats"]
    n, converged, c_in, c_out = _run_level(descent, mode, stats, max_iterations=max_iterations, tol=tol,
                                           callback=iter_callback, like=init, first_iteration=0)
    return SegmentationResult(
        surface=descent.surface(init), iterations=n, converged=converged, c_in=float(np.nanmedian(c_in)),
        c_out=float(np.nanmedian(c_out)), seconds=time.perf_counter() - started,
        parameters={**state["parameters"], "max_iterations": max_iterations, "coarse_to_fine": False})


def track(
    volumes: Sequence[Volume],
    apex,
    base,
    *,
    iterations_per_frame: int = 20,
    progress: Callable[[int, int], None] | None = None,
    **kwargs,
) -> TrackingResult:
    """Segment every frame of a 3D+t sequence.

    The first frame is segmented from ``apex`` and ``base`` (all of
    :func:`segment`'s keywords apply); every later frame starts from the
    previous frame's coefficients and runs until the surface stops moving
    (``tol``), at most ``iterations_per_frame`` iterations: the paper used
    3 to 5; on the 10-frame phantom cycles, where the wall moves up to 4 mm
    between frames, 4 to 7 are run.  The model, its precomputed matrices and
    the region statistics of the first frame are reused.  The apex and base
    points, so the base plane, stay those of the first frame.

    Returns
    -------
    TrackingResult
        ``.volumes_ml``, ``.edv_ml``, ``.esv_ml``, ``.ef`` (percent).
    """
    volumes = list(volumes)
    if len(volumes) < 2:
        raise ValueError(f"a sequence needs at least 2 frames, got {len(volumes)}")
    if not (isinstance(iterations_per_frame, (int, np.integer)) and iterations_per_frame >= 1):
        raise ValueError(f"iterations_per_frame must be a positive integer, got {iterations_per_frame!r}")
    kwargs.pop("init", None)
    state: dict = {}  # the finest level's model and statistics, reused frame to frame
    first = segment(volumes[0], apex, base, _state=state, **kwargs)
    frames = [first]
    if progress is not None:
        progress(1, len(volumes))
    follow = {**kwargs, "max_iterations": iterations_per_frame, "coarse_to_fine": False}
    for t, vol in enumerate(volumes[1:], start=2):
        frames.append(segment(vol, apex, base, init=frames[-1].surface, _state=state, **follow))
        if progress is not None:
            progress(t, len(volumes))
    return TrackingResult(frames)
