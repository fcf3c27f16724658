"""The array work of an iteration, behind one interface with two backends.

:class:`NumpyBackend` is the readable reference: it calls
:meth:`SampledSurface.geometry`, :meth:`Volume.sample` and
:func:`spheroseg.energy.normal_speed` and restates none of them.
:class:`CompiledBackend` does the same work in the compiled kernels of
:mod:`spheroseg._kernels` (prolate spheroidal system only), writing into
arrays allocated once (a :class:`~spheroseg.beamspace.BeamVolume` too: the
kernels take either's arrays); the tests require both to give
the same segmentations.  :func:`select_backend` chooses once, as trimesh picks a ray
engine.

The methods, for a model of ``n`` sample points and parameters ``p``:

- :meth:`~NumpyBackend.observe`: the surface at the samples (``f``, the scale
  factor ``h0``, ``A_K``, world points, outward normals) and the grey level
  there; optionally the mean grey levels in bands along the normals;
- :meth:`~NumpyBackend.observe_term`: that, and what a data term reads (the
  band means smoothed over the surface, the global region means, samples at
  its own offsets): the data term is then a function of the observation;
- :meth:`~NumpyBackend.samples_along`, :meth:`~NumpyBackend.mean_along`:
  samples along the normals, raw or averaged;
- :meth:`~NumpyBackend.cavity_sums`: samples inside the cavity along the
  model's rays, weighted by the volume element ``V = h0 h1 h2`` (eq. 19);
- :meth:`~NumpyBackend.gather`, :meth:`~NumpyBackend.scatter`: ``B p`` and
  ``B^T v`` for the Hermite basis ``B`` at the samples;
  :meth:`~NumpyBackend.product`: a sparse matrix times a vector;
- :meth:`~NumpyBackend.displacement`: the region force of eq. 22 as a
  ``v0`` displacement per sample point, weighted by the quadrature.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from .._compiled._runtime import (PARALLEL_LOCK, compiled_available, idle_cores, kernel_thread_count, kernel_threads,
                       usable_cores)
from ..volumes.beamspace import BeamVolume
from ..geometry.coords import ProlateSpheroidal
from .dataterms import CAVITY_FRACTIONS, Reads
from ..geometry.energy import Geometry, SampledSurface, normal_speed

__all__ = ["Observation", "NumpyBackend", "CompiledBackend", "select_backend", "sample_points", "compiled_available",
           "kernel_threads", "kernel_thread_count", "idle_cores", "usable_cores", "MIN_COS"]

#: least cosine between the normal and the v0 direction when converting a
#: normal displacement into a v0 displacement (keeps grazing rays bounded)
MIN_COS = 0.3
# along-normal offset (mm) of the grey level at the surface: averaging over
# +-1 mm changed no result on the phantoms or CETUS Patient 7 (the projection
# already averages 64 points per patch) and cost two thirds of the samples
_SURFACE_OFFSETS = np.array([0.0])


@dataclass
class Observation:
    """What an iteration reads at the sample points.  A compiled backend
    reuses its arrays: valid until its next observation."""

    f: np.ndarray
    h0: np.ndarray  #: scale factor of v0 at the surface (mm per unit v0)
    cos: np.ndarray  #: cosine between the outward normal and dx/dv0
    area: np.ndarray  #: A_K, the area element of (v1, v2)
    world: np.ndarray  #: surface points (world mm), (3, n)
    normal: np.ndarray  #: unit outward normals (world), (3, n)
    u: np.ndarray  #: grey level at the surface
    inside: np.ndarray | None = None  #: mean grey level in the inner band, on the band rows
    outside: np.ndarray | None = None  #: the same in the outer band
    geometry: Geometry | None = None  #: the full geometry, when asked for
    #: ``(c_in, c_out)``: the band means smoothed over the surface, at every sample point
    band_means: tuple | None = None
    #: ``(cavity, shell)``: the global region means (grey levels)
    region_means: tuple | None = None
    along: np.ndarray | None = None  #: grey levels at a data term's own offsets, on the band rows


def _ratio(numerator: float, denominator: float) -> float:
    return float(numerator / denominator) if denominator > 0 else np.nan


def row_nanmean(values: np.ndarray) -> np.ndarray:
    """Mean of each row's finite values; NaN for a row with none."""
    ok = np.isfinite(values)
    n = ok.sum(axis=1)
    total = np.where(ok, values, 0.0).sum(axis=1)
    return np.where(n > 0, total / np.maximum(n, 1), np.nan)


class NumpyBackend:
    """The reference: numpy and sparse matrices (any coordinate system)."""

    name = "numpy"

    def __init__(self, model: SampledSurface):
        self.model = model
        self.discretisation = model.discretisation

    # the surface and the image ---------------------------------------------

    def observe(self, p, volume, *, band_offsets=None, geometry: bool = False, exponent: float = 0.0) -> Observation:
        """The surface of parameters ``p`` at the samples and the image there;
        with ``band_offsets`` (mm, positive), the mean grey levels at those
        distances inside and outside along the normal, on the band rows.  A
        non-zero ``exponent`` ``a`` reads ``exp(a v)`` for every sample ``v``."""
        m = self.model
        g = m.geometry(p)
        h0 = m.system.scale_factors(g.f, m.v1, m.v2)[0]
        cos = np.einsum("ij,ij->i", g.normal @ m.pose.rotation, g.jacobian[:, :, 0]) / h0
        obs = Observation(g.f, h0, cos, g.area, g.world.T, g.normal.T, u=None, geometry=g)
        obs.u = row_nanmean(self.samples_along(volume, obs, _SURFACE_OFFSETS, exponent=exponent))
        if band_offsets is not None:
            rows = self.discretisation.band_rows
            obs.inside = row_nanmean(self.samples_along(volume, obs, -band_offsets, rows, exponent=exponent))
            obs.outside = row_nanmean(self.samples_along(volume, obs, band_offsets, rows, exponent=exponent))
        return obs

    def observe_term(self, p, volume, reads: Reads, *, geometry: bool = False) -> Observation:
        """:meth:`observe` with what a data term reads (its
        :meth:`~spheroseg.descent.dataterms.DataTerm.reads`): the band means
        smoothed over the surface (:meth:`band_means`, at
        ``reads.band_offsets``), the global region means
        (:meth:`region_means`, with ``reads.shell_offsets``) and the samples
        at its own ``reads.offsets`` on the band rows."""
        obs = self.observe(p, volume, band_offsets=reads.band_offsets, geometry=geometry, exponent=reads.exponent)
        if reads.band_offsets is not None:
            obs.band_means = self.band_means(obs)
        if reads.shell_offsets is not None:
            obs.region_means = self.region_means(volume, obs, reads.shell_offsets)
        if reads.offsets is not None:
            obs.along = self.samples_along(volume, obs, reads.offsets, self.discretisation.band_rows)
        return obs

    def band_means(self, obs: Observation) -> tuple[np.ndarray, np.ndarray]:
        """The band means ``obs.inside``, ``obs.outside`` (a missing one
        replaced by its band's mean) projected on the Hermite space (the
        band rows' quadrature: ``M^-1 B_b^T W_b m``) and evaluated at every
        sample point: ``(c_in, c_out)``."""
        d = self.discretisation
        fields = np.stack([obs.inside, obs.outside])
        ok = np.isfinite(fields)
        if not ok[0].any() or not ok[1].any():
            raise ValueError("no image data around the surface (is it inside the image's sector?)")
        if not ok.all():
            fields = np.where(ok, fields, np.nanmean(fields, axis=1)[:, None])
        rhs = self.scatter(d.band_weights * fields, band=True)
        # both fields in one product: one pass over the inverse, not two
        smooth = d.mass_inverse @ rhs
        c_in, c_out = self.gather(smooth)
        return c_in, c_out

    def region_means(self, volume, obs: Observation, shell_offsets) -> tuple[float, float]:
        """The global means: the cavity's, weighted by the volume element
        along the rays of the band rows (at :data:`CAVITY_FRACTIONS` of
        ``f``), and the area-weighted mean of a shell outside the surface
        (at ``shell_offsets`` mm); NaN without weight."""
        d = self.discretisation
        rows = d.band_rows
        cavity, volume_sum = self.cavity_sums(volume, obs, CAVITY_FRACTIONS, rows)
        shell, count = self.mean_along(volume, obs, shell_offsets, rows)
        # per ray: cavity = sum of V u, volume = sum of V over the finite samples
        weights = d.weights[rows]
        w_in = weights * obs.f[rows]
        w_out = weights * obs.area[rows] * count
        shell[count == 0] = 0.0  # no sample, no weight (np.nan_to_num checks every value)
        return _ratio(w_in @ cavity, w_in @ volume_sum), _ratio(w_out @ shell, w_out.sum())

    def samples_along(self, volume, obs: Observation, offsets, rows=slice(None), *, exponent: float = 0.0,
                      order: int = 1) -> np.ndarray:
        """Grey levels (or ``exp(exponent v)``) at ``world + s normal`` for
        ``s`` in ``offsets`` (mm): ``(rows, offsets)``, NaN off the data;
        trilinear, or the nearest voxel with ``order=0``."""
        pts = obs.world.T[rows, None, :] + np.asarray(offsets)[None, :, None] * obs.normal.T[rows, None, :]
        values = volume.sample(pts) if order == 1 else volume.sample(pts, order=order)
        return np.exp(exponent * values) if exponent else values

    def mean_along(self, volume, obs: Observation, offsets, rows, *, exponent: float = 0.0):
        """Mean (NaN if none) and number of the finite samples along the
        normals of ``rows``."""
        u = self.samples_along(volume, obs, offsets, rows, exponent=exponent)
        return row_nanmean(u), np.isfinite(u).sum(axis=1)

    def cavity_sums(self, volume, obs: Observation, fractions, rows) -> tuple[np.ndarray, np.ndarray]:
        """For each ray of ``rows``, samples at ``v0 = t f`` for ``t`` in
        ``fractions``: the sums of ``V u`` and of ``V`` over finite samples."""
        m = self.model
        v0 = obs.f[rows, None] * fractions[None, :]
        v1 = np.broadcast_to(m.v1[rows, None], v0.shape)
        v2 = np.broadcast_to(m.v2[rows, None], v0.shape)
        u = volume.sample(m.pose.to_world(m.system.to_cartesian(v0, v1, v2)))
        element = np.where(np.isfinite(u), m.system.volume_element(v0, v1, v2), 0.0)
        return (element * np.nan_to_num(u)).sum(axis=1), element.sum(axis=1)

    # the Hermite basis at the samples ---------------------------------------

    def gather(self, p) -> np.ndarray:
        """``B p`` for parameters ``(n,)`` or fields ``(n, k)``: ``(samples,)``
        or ``(k, samples)``."""
        return (self.discretisation.b_f @ p).T

    def product(self, matrix, x) -> np.ndarray:
        """``matrix @ x`` for a sparse (CSR) matrix and a vector."""
        return matrix @ x

    def scatter(self, values, *, band: bool = False) -> np.ndarray:
        """``B^T values`` in the parameters, for values ``(samples,)`` or
        ``(k, samples)`` at every sample point, or at the band rows."""
        d = self.discretisation
        return (d.band_transpose if band else d.b_f.T) @ values.T

    # the force ----------------------------------------------------------------

    def descends(self, volume) -> bool:
        """Whether :meth:`descend` runs a whole level on ``volume`` (the
        compiled backend on a Cartesian volume)."""
        return False

    def displacement(self, obs: Observation, c_in, c_out, scale: float, *, step: float, h0_floor: float,
                     clip: float = 1.0, u=None,
                     area_speed: Callable[[np.ndarray], np.ndarray] | None = None) -> np.ndarray:
        """``W dv0``: the normal speed of :func:`~spheroseg.energy.normal_speed`
        times ``step`` (mm), converted to ``v0`` (``h0 cos``, both bounded
        below: near a focal point or at grazing rays ``v0`` barely moves the
        surface), times the quadrature weights.  ``u`` replaces the observed
        grey level (a data term's transform of it); ``clip`` bounds the speed;
        ``area_speed`` adds a speed (steps) given the conversion factor."""
        speed = normal_speed(obs.u if u is None else u, c_in, c_out, scale, clip)
        normal_to_v0 = self.normal_to_v0(obs, h0_floor)
        if area_speed is not None:
            speed = speed + area_speed(normal_to_v0)
        return self.model.weights * step * speed / normal_to_v0

    @staticmethod
    def normal_to_v0(obs: Observation, h0_floor: float) -> np.ndarray:
        """mm of normal motion per unit ``v0`` at each sample point: ``h0 cos``,
        bounded below (near a focal point, or at grazing rays, ``v0`` barely
        moves the surface)."""
        return np.maximum(obs.h0 * np.maximum(obs.cos, MIN_COS), h0_floor)


class CompiledBackend(NumpyBackend):
    """The same work in the compiled kernels (prolate spheroidal system); falls back
    to the reference for what they do not compute (the full geometry that
    the area term needs)."""

    name = "compiled"

    def __init__(self, model: SampledSurface):
        super().__init__(model)
        from .._compiled import _kernels

        self.kernels = _kernels
        n, nb = model.n_samples, len(self.discretisation.band_rows)
        self._all_rows = np.arange(n)
        self._buffers = dict(f=np.empty(n), h0=np.empty(n), cos=np.empty(n), area=np.empty(n),
                             world=np.empty((3, n)), normal=np.empty((3, n)), u=np.empty(n),
                             inside=np.empty(nb), outside=np.empty(nb))
        self._counts = np.empty(n, np.int64)
        self._displacement = np.empty(n)
        self._sampled = self._sampling_arrays = None
        self._surface = None

    def observe(self, p, volume, *, band_offsets=None, geometry: bool = False, exponent: float = 0.0) -> Observation:
        if geometry:
            return super().observe(p, volume, band_offsets=band_offsets, geometry=True, exponent=exponent)
        m, d, b = self.model, self.discretisation, self._buffers
        coefficients = self.product(d.constraints, p).reshape(m.grid.shape)
        image = self._sampling(volume)
        with PARALLEL_LOCK:
            self.kernels.prolate_surface(coefficients, d.order, *d.tables, *d.trig, m.system.focal_length,
                                         m.pose.rotation, m.pose.origin, b["f"], b["h0"], b["cos"], b["area"],
                                         b["world"], b["normal"])
            self.kernels.sample_along(*image, b["world"], b["normal"], self._all_rows, _SURFACE_OFFSETS, exponent, b["u"],
                                 self._counts)
            if band_offsets is not None:
                rows = d.band_rows
                counts = self._counts[:len(rows)]
                self.kernels.sample_along(*image, b["world"], b["normal"], rows, -band_offsets, exponent, b["inside"],
                                     counts)
                self.kernels.sample_along(*image, b["world"], b["normal"], rows, band_offsets, exponent, b["outside"],
                                     counts)
        obs = Observation(**b)
        if band_offsets is None:
            obs.inside = obs.outside = None
        return obs

    def product(self, matrix, x) -> np.ndarray:
        """``matrix @ x`` for a CSR matrix and a vector, as scipy computes it
        (without scipy.sparse's per-call dispatch)."""
        out = np.empty(matrix.shape[0])
        self.kernels.csr_product(matrix.indptr, matrix.indices, matrix.data, np.ascontiguousarray(x, dtype=float), out)
        return out

    def _sampling(self, volume):
        """The arrays the kernels read to sample ``volume`` (Cartesian or beam
        space; kept for the last volume: an iteration asks up to three
        times, and would build the read-only views each time)."""
        if volume is not self._sampled:
            # (a plain tuple: the kernels take it unpacked)
            self._sampled, self._sampling_arrays = volume, self.kernels.sampler(volume.sampling_view())
        return self._sampling_arrays

    def samples_along(self, volume, obs: Observation, offsets, rows=slice(None), *, exponent: float = 0.0,
                      order: int = 1) -> np.ndarray:
        if isinstance(rows, slice) and rows == slice(None):
            rows = self._all_rows
        if isinstance(volume, BeamVolume) or exponent or isinstance(rows, slice) or order not in (0, 1):
            return super().samples_along(volume, obs, offsets, rows, exponent=exponent, order=order)
        offsets = np.ascontiguousarray(offsets, dtype=float)
        out = np.empty((len(rows), len(offsets)))
        image = self._sampling(volume)
        self.kernels.samples_at(*image, obs.world, obs.normal, rows, offsets, order == 0, out)
        return out

    def mean_along(self, volume, obs: Observation, offsets, rows, *, exponent: float = 0.0):
        mean, count = np.empty(len(rows)), np.empty(len(rows), np.int64)
        image = self._sampling(volume)
        with PARALLEL_LOCK:
            self.kernels.sample_along(*image, obs.world, obs.normal, rows, offsets, exponent, mean, count)
        return mean, count

    def cavity_sums(self, volume, obs: Observation, fractions, rows):
        m, d = self.model, self.discretisation
        total, weight = np.empty(len(rows)), np.empty(len(rows))
        image = self._sampling(volume)
        with PARALLEL_LOCK:
            self.kernels.cavity_sums(*image, obs.f, *d.trig, m.system.focal_length, m.pose.rotation, m.pose.origin, rows,
                                fractions, total, weight)
        return total, weight

    def gather(self, p) -> np.ndarray:
        m, d = self.model, self.discretisation
        if p.ndim == 1:
            coefficients = self.product(d.constraints, p).reshape((1,) + m.grid.shape)
        else:  # a product a field (the band means' two): scipy's dispatch of a sparse product costs more
            coefficients = np.stack([self.product(d.constraints, field) for field in p.T]).reshape((-1,) + m.grid.shape)
        out = np.empty((len(coefficients), m.n_samples))
        with PARALLEL_LOCK:
            self.kernels.gather(coefficients, d.order, *d.tables, out)
        return out[0] if p.ndim == 1 else out

    def scatter(self, values, *, band: bool = False) -> np.ndarray:
        m, d = self.model, self.discretisation
        fields = values.reshape(-1, values.shape[-1])
        coefficients = np.empty((len(fields),) + m.grid.shape)
        tables = d.band_tables if band else d.tables
        self.kernels.scatter(fields, tables[0].shape[1], *tables, coefficients)
        if values.ndim == 1:
            return self.product(d.constraints_t, coefficients.reshape(-1))
        return np.stack([self.product(d.constraints_t, c.reshape(-1)) for c in coefficients], axis=1)

    def displacement(self, obs: Observation, c_in, c_out, scale: float, *, step: float, h0_floor: float,
                     clip: float = 1.0, u=None, area_speed=None) -> np.ndarray:
        if area_speed is not None:
            return super().displacement(obs, c_in, c_out, scale, step=step, h0_floor=h0_floor, clip=clip, u=u,
                                        area_speed=area_speed)
        n = self.model.n_samples
        c_in, c_out = (np.full(n, c) if np.ndim(c) == 0 else c for c in (c_in, c_out))
        self.kernels.normal_displacement(obs.u if u is None else u, c_in, c_out, scale, clip, obs.h0, obs.cos,
                                         h0_floor, MIN_COS, step, self.model.weights, self._displacement)
        return self._displacement

    def descends(self, volume) -> bool:
        return not isinstance(volume, BeamVolume)  # (descend samples with the Cartesian kernels)

    def descend(self, p, reference, volume, *, prior: tuple, term: tuple, state: np.ndarray,
                previous: np.ndarray, tol: float, max_iterations: int) -> tuple[int, Observation, np.ndarray]:
        """Run a level of the descent in one compiled call
        (:func:`spheroseg._kernels.descend`, whose arguments these are),
        updating ``p``, ``state`` and ``previous`` in place.

        Returns its status, the last observation and the force's means
        ``(4, n)`` (``c_in``, the band means' ``c_out``, the force's ``c_out``,
        the band means' ``c_in``)."""
        m, d, b = self.model, self.discretisation, self._buffers
        if self._surface is None:  # what depends on the grid and pose only, and the buffers
            csr = tuple((a.indptr, a.indices, a.data) for a in (d.constraints, d.constraints_t))
            self._surface = self.kernels.LoopSurface(
                *csr, m.grid.shape, d.order, *d.tables, d.band_tables[0].shape[1], *d.band_tables, d.trig,
                m.system.focal_length, m.pose.rotation, m.pose.origin, m.weights, d.area, MIN_COS, self._all_rows,
                d.band_rows, d.band_weights, d.mass_inverse)
            self._observed = self.kernels.LoopObservation(**b)
        means = np.empty((4, m.n_samples))
        with PARALLEL_LOCK:
            status = self.kernels.descend(p, reference, max_iterations, tol, state, prior, self._surface,
                                          self._sampling(volume), term, self._observed, means, previous)
        return status, Observation(**b), means


def select_backend(model: SampledSurface, *, compiled: bool = True) -> NumpyBackend:
    """The compiled backend where it applies (the package built, prolate
    spheroidal system, ``compiled``), else the numpy reference."""
    if compiled and isinstance(model.system, ProlateSpheroidal) and compiled_available():
        return CompiledBackend(model)
    return NumpyBackend(model)


def sample_points(volume, points, *, order: int = 1) -> np.ndarray:
    """``volume.sample(points, order=order)`` (world mm, shape ``(..., 3)``),
    in the compiled sampler where it applies (the package built, a Cartesian
    volume, ``order`` 0 or 1): equal to rounding, without the reference's
    temporary arrays."""
    points = np.asarray(points, dtype=float)
    if isinstance(volume, BeamVolume) or order not in (0, 1) or not compiled_available() or points.ndim < 1 \
            or points.shape[-1] != 3:
        return volume.sample(points, order=order)
    from .._compiled import _kernels

    world = np.ascontiguousarray(points.reshape(-1, 3).T)
    rows = np.arange(world.shape[1])
    out = np.empty((world.shape[1], 1))
    _kernels.samples_at(*_kernels.sampler(volume.sampling_view()), world, np.zeros_like(world), rows,
                        _SURFACE_OFFSETS, order == 0, out)
    return out.reshape(points.shape[:-1])

