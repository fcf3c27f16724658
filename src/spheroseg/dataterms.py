"""The data terms of the descent: what ``c_in`` and ``c_out`` of paper eq. 22
are, and the scale that makes the force dimensionless.

Each data term is one class with the same small interface, chosen once from
the ``mode`` string (:data:`DATA_TERMS`, as :func:`scipy.optimize.minimize`
maps ``method``):

``"fast"``: :class:`FixedInterface`
    The paper's fast mode: ``c_in``, ``c_out`` fixed once (Otsu's threshold
    of the samples around the initial surface, or ``interface`` given).
``"chan-vese"``: :class:`GlobalMeans`
    Global two-region means re-estimated every iteration from samples in
    model space: the cavity along each ray (weighted by the volume element
    ``V`` of eq. 19), and a shell of ``band_out`` mm outside the surface.
``"local"``: :class:`LocalMeans`
    Means local to each surface point, from a band of ``band`` mm on each
    side along the normal, smoothed over the surface by the Hermite L2
    projection (localised region energy, Lankton & Tannenbaum 2008; as in
    BEAS, Barbosa et al. 2012).  Where the local contrast is low (dropout,
    or both bands in the blood pool) the force fades instead of leaking.
    The coarse levels of its schedule use :class:`GlobalMeans`, which bring
    the surface to the walls from afar.

Means are taken on the band rows (a quarter of the sample points,
:class:`spheroseg.discretisation.Discretisation`).

References
----------
.. [1] Duan Q, Angelini ED, Laine AF et al. Variational segmentation
   framework in prolate spheroidal coordinates for 3D real-time
   echocardiography. Proc. SPIE 6144, 61444A (2006). doi:10.1117/12.653692
.. [2] Lankton S, Tannenbaum A. Localizing region-based active contours.
   IEEE Trans. Image Process. 17(11):2029-2039 (2008). doi:10.1109/TIP.2008.2004611
.. [3] Barbosa D, Dietenbeck T, Schaerer J et al. B-spline explicit active
   surfaces: an efficient framework for real-time 3-D region-based
   segmentation. IEEE Trans. Image Process. 21(1):241-251 (2012).
   doi:10.1109/TIP.2011.2161484
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["DataTerm", "Force", "FixedInterface", "GlobalMeans", "LocalMeans", "LocalIntensityMeans", "DATA_TERMS",
           "band_offsets", "shell_offsets", "otsu_threshold", "speckle_nepers", "patch_of_rows"]

# fractions of f at which the cavity is sampled along each ray
_CAVITY_FRACTIONS = np.array([0.15, 0.35, 0.55, 0.75, 0.95])
# the force's scale is at least this fraction of the grey-level spread
# around the initial surface, squared (a flat region must not blow it up)
_MIN_CONTRAST = 0.05


def band_offsets(band: float) -> np.ndarray:
    """Distances (mm) along the normal of the band means: 4 in ``(0, band]``."""
    return np.linspace(0, band, 5)[1:]


def shell_offsets(band_out: float) -> np.ndarray:
    """Distances (mm) outside the surface of the global outer mean: 5 in ``(0, band_out]``."""
    return np.linspace(0, band_out, 6)[1:]


def otsu_threshold(values: np.ndarray) -> float:
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


class Force(NamedTuple):
    """What the force of eq. 22 needs at the sample points: the grey level
    ``u`` (or a data term's transform of it), the region means in the same
    units (scalars or arrays), the squared contrast the force is divided
    by, and the bound of the resulting speed (in steps)."""

    u: np.ndarray
    c_in: object
    c_out: object
    scale: float
    clip: float | None = 1.0  #: None: bound the displacement after averaging over the surface


def _ratio(numerator: float, denominator: float) -> float:
    return float(numerator / denominator) if denominator > 0 else np.nan


class DataTerm:
    """Region statistics for the force of eq. 22.

    Parameters
    ----------
    samples : array
        Finite grey levels around the initial surface (both sides): they set
        the least scale of the force (and the fast mode's levels).
    band, band_out : float
        Band widths (mm), as :class:`spheroseg.SegmentOptions`.
    interface : float, optional
        The fast mode's interface grey level.

    Attributes
    ----------
    needs_bands : bool
        Whether :meth:`force` reads the observation's band means.
    band_offsets : array or None
        Their distances along the normal (mm).
    exponent : float or None
        The observation reads ``exp(exponent * v)`` for each grey level
        ``v`` (0: the grey levels; None: not known yet).
    """

    needs_bands = False
    exponent: float | None = 0.0

    def __init__(self, samples: np.ndarray, *, band: float = 8.0, band_out: float = 15.0,
                 interface: float | None = None):
        self.spread = float(np.std(samples))
        self.min_scale = (_MIN_CONTRAST * self.spread) ** 2
        self.band_offsets = band_offsets(band) if self.needs_bands else None
        self.shell_offsets = shell_offsets(band_out)

    def force(self, backend, volume, obs) -> Force:
        """The :class:`Force` for the observation ``obs``.  Sets
        :attr:`grey_means`, the median region means in image units."""
        raise NotImplementedError

    def global_means(self, backend, volume, obs) -> tuple[float, float]:
        """Volume-weighted cavity mean and area-weighted shell mean, from the
        rays of the band rows."""
        d = backend.discretisation
        rows = d.band_rows
        cavity, volume_sum = backend.cavity_sums(volume, obs, _CAVITY_FRACTIONS, rows)
        shell, count = backend.mean_along(volume, obs, self.shell_offsets, rows)
        # per ray: cavity = sum of V u, volume = sum of V over the finite samples
        w_in = d.weights[rows] * obs.f[rows]
        w_out = d.weights[rows] * obs.area[rows] * count
        return _ratio(w_in @ cavity, w_in @ volume_sum), _ratio(w_out @ np.nan_to_num(shell), w_out.sum())


class FixedInterface(DataTerm):
    """The paper's fast mode: ``c_in``, ``c_out`` fixed from the samples
    around the initial surface (``interface``: Otsu's threshold by default;
    the two levels are the class means about it, centred on it)."""

    def __init__(self, samples, *, band=8.0, band_out=15.0, interface=None):
        super().__init__(samples, band=band, band_out=band_out)
        mid = otsu_threshold(samples) if interface is None else float(interface)
        lo, hi = samples[samples <= mid], samples[samples > mid]
        half = (hi.mean() - lo.mean()) / 2 if lo.size and hi.size else self.spread
        self.c_in, self.c_out = mid - half, mid + half

    def force(self, backend, volume, obs) -> Force:
        self.grey_means = (self.c_in, self.c_out)
        return Force(obs.u, self.c_in, self.c_out, (self.c_out - self.c_in) ** 2)


class GlobalMeans(DataTerm):
    """Global Chan-Vese means, re-estimated every iteration."""

    def force(self, backend, volume, obs) -> Force:
        c_in, c_out = self.global_means(backend, volume, obs)
        self.grey_means = (c_in, c_out)
        return Force(obs.u, c_in, c_out, max((c_out - c_in) ** 2, self.min_scale))


class LocalMeans(DataTerm):
    """Band means along each normal, smoothed over the surface."""

    needs_bands = True

    def force(self, backend, volume, obs) -> Force:
        c_in, c_out = self.band_means(backend, obs)
        contrast = np.maximum(c_out - c_in, 0.0)
        self.grey_means = (float(np.nanmedian(c_in)), float(np.nanmedian(c_out)))
        return Force(obs.u, c_in, c_in + contrast, max(np.median(contrast) ** 2, self.min_scale))

    def band_means(self, backend, obs):
        """The band means projected on the Hermite space (the band rows'
        quadrature: ``M^-1 B_b^T W_b m``) and evaluated at every sample
        point.  Inside brighter than outside (wrong polarity) gives no force."""
        d = backend.discretisation
        fields = np.stack([obs.inside, obs.outside])
        ok = np.isfinite(fields)
        if not ok[0].any() or not ok[1].any():
            raise ValueError("no image data around the surface (is it inside the image's sector?)")
        if not ok.all():
            fields = np.where(ok, fields, np.nanmean(fields, axis=1)[:, None])
        rhs = backend.scatter(d.band_weights * fields, band=True)
        # one mat-vec a field: BLAS multiplies a 259 x 2 block slower than that
        smooth = np.stack([d.mass_inverse @ column for column in rhs.T], axis=1)
        c_in, c_out = backend.gather(smooth)
        return c_in, c_out




class LocalIntensityMeans(LocalMeans):
    """Local means of the echo intensity: the log compression undone.

    B-mode grey levels are ``v = a + k ln I`` (log compression of the echo
    intensity ``I`` to ``k`` grey levels per neper, ``a`` the gain) after a
    point-spread function blurred ``I``.  Across a blood-tissue interface the
    blurred mean intensity is ``I_b + (I_t - I_b) Phi(x / sigma)``: it passes
    half way between the two at the interface, while the grey level half way
    between the two regions' means is reached where ``I`` is near their
    geometric mean, on the blood side (about two PSF widths in at 30 dB of
    contrast: the inward bias of :class:`LocalMeans` on log-compressed data).
    This term reads ``exp(v / k)`` for every sample, so its band means and
    the force are in the intensity domain and the boundary settles where the
    intensity is half way: at the interface.

    ``k`` is estimated from the data itself, once, on the first iteration:
    fully developed speckle has an exponential intensity, so ``ln I`` has a
    standard deviation of ``pi / sqrt(6)`` (5.57 dB) whatever its mean; the
    spread of the grey levels in the outer band (the myocardium), across
    the rays of each patch (a few mm apart: independent speckle) and at each
    offset, read at voxel centres (interpolation averages the log and
    narrows its spread), gives ``k`` (:func:`speckle_nepers`).  Speckle the
    scanner's filters have averaged has a smaller spread, so ``k`` comes out
    low and the intensity over-expanded: the boundary then moves a fraction
    of a PSF width outwards, where the log-domain means put it two widths
    inwards.  Without speckle (a contrast above 50 dB per ``k``) the
    contrast bounds ``k`` from below.

    The force is not clipped point by point: the intensity of speckle is
    heavy-tailed (exponential), and clipping a skewed force before it is
    averaged moves the point where its mean vanishes by a third of a PSF
    width.  The displacement is bounded after its projection on the Hermite
    space instead (``Force.clip = None``).

    References
    ----------
    .. [1] Tao Z, Tagare HD, Beaty JD. Evaluation of four probability
       distribution models for speckle in clinical cardiac ultrasound images.
       IEEE Trans. Med. Imaging 25(11):1483-1491 (2006). doi:10.1109/TMI.2006.881376
    .. [2] Wagner RF, Smith SW, Sandrik JM, Lopez H. Statistics of speckle in
       ultrasound B-scans. IEEE Trans. Sonics Ultrason. 30(3):156-163 (1983).
       doi:10.1109/T-SU.1983.31404
    """

    #: standard deviation of ln I for exponential (fully developed speckle) intensity
    LOG_SPREAD = np.pi / np.sqrt(6.0)

    def __init__(self, samples, *, band=8.0, band_out=15.0, interface=None):
        super().__init__(samples, band=band, band_out=band_out)
        self.exponent = None
        self.nepers = None  #: grey levels per neper of intensity, once estimated

    def force(self, backend, volume, obs) -> Force:
        if self.exponent is None:
            obs = self._undo_compression(backend, volume, obs)
        c_in, c_out = self.band_means(backend, obs)
        contrast = np.maximum(c_out - c_in, 0.0)
        median_out = float(np.nanmedian(c_out))
        # report the band means as grey levels, as the other terms do
        to_grey = lambda i: self.nepers * np.log(max(i, 1e-300))  # noqa: E731
        self.grey_means = (to_grey(float(np.nanmedian(c_in))), to_grey(median_out))
        scale = max(float(np.median(contrast)) ** 2, (_MIN_CONTRAST * median_out) ** 2)
        return Force(obs.u, c_in, c_in + contrast, scale, None)

    def _undo_compression(self, backend, volume, obs):
        """Estimate ``k`` from the grey levels of this observation, then read
        the observation again in the intensity domain."""
        from dataclasses import replace

        d = backend.discretisation
        rows = d.band_rows
        # at voxel centres: interpolation averages the log and narrows its spread
        outer = backend.samples_along(volume, obs, self.band_offsets, rows, order=0)  # (rows, offsets)
        self.nepers = speckle_nepers(outer, patch_of_rows(d.grid, d.order, rows))
        # a blood-tissue contrast beyond 50 dB of intensity is not echo: where
        # the grey levels have no speckle spread, the contrast bounds k
        contrast = np.nanmedian(obs.outside - obs.inside) if obs.inside is not None else np.nan
        if np.isfinite(contrast) and contrast > 0:
            self.nepers = max(self.nepers, float(contrast) / np.log(10.0**5))
        self.exponent = 1.0 / self.nepers
        u, _ = backend.mean_along(volume, obs, np.zeros(1), np.arange(d.n_samples), exponent=self.exponent)
        inside, _ = backend.mean_along(volume, obs, -self.band_offsets, rows, exponent=self.exponent)
        outside, _ = backend.mean_along(volume, obs, self.band_offsets, rows, exponent=self.exponent)
        return replace(obs, u=u, inside=inside, outside=outside)


def patch_of_rows(grid, order: int, rows: np.ndarray) -> np.ndarray:
    """The patch (``i2 n1 + i1``) of each sample point of ``rows``
    (samples are numbered as :meth:`HermiteGrid.quadrature` orders them)."""
    n_row = grid.n1 * order
    return ((rows // n_row) // order) * grid.n1 + (rows % n_row) // order


def speckle_nepers(samples: np.ndarray, patch: np.ndarray, *, min_rays: int = 6) -> float:
    """Grey levels per neper of intensity from log-compressed speckle.

    ``samples`` ``(rays, offsets)`` are grey levels along rays whose patch is
    ``patch``; at each offset, the rays of one patch sample independent
    speckle of one tissue, whose ``ln I`` has the standard deviation
    ``pi / sqrt(6)``.  The grey-level variance across the rays of a patch,
    averaged over patches and offsets, gives ``k^2 pi^2 / 6``.  Variances
    over three times their median (a patch across two tissues) are left out.
    """
    variances = []
    for p in np.unique(patch):
        block = samples[patch == p]
        for column in block.T:
            values = column[np.isfinite(column)]
            if len(values) >= min_rays:
                variances.append(np.var(values, ddof=1))
    variances = np.asarray(variances)
    if not variances.size or np.median(variances) <= 0:
        raise ValueError("no speckle around the surface to estimate the log compression from "
                         "(use mode='local' for images that are not log-compressed echo)")
    typical = variances[variances <= 3 * np.median(variances)]
    return float(np.sqrt(typical.mean())) / LocalIntensityMeans.LOG_SPREAD


#: the data term of each ``mode``
DATA_TERMS = {"intensity": LocalIntensityMeans, "local": LocalMeans, "chan-vese": GlobalMeans, "fast": FixedInterface}
