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

A data term of one's own
    Subclass :class:`DataTerm`, give the distances :attr:`DataTerm.offsets`
    (mm along the outward normal, negative inside) at which the image is
    sampled, and write :meth:`DataTerm.statistics`, a pure function of that
    observation (the grey levels at the surface and the samples along the
    normals) to a :class:`Force`; pass the class as ``mode``.  It reads no
    backend and keeps no state: the iteration samples the image, calls it,
    and keeps what a result reports (as for the built-in terms, whose
    :meth:`DataTerm.force` reads the band means or the region means that the
    observation carries).  Such a term runs iteration by
    iteration on either backend (the compiled level loop computes only the
    built-in terms).  For example, a Rayleigh likelihood of the echo
    amplitude in each band (Sarti et al. 2005)::

        class Rayleigh(DataTerm):
            offsets = np.array([-6.0, -4.0, -2.0, 2.0, 4.0, 6.0])

            def statistics(self, u, along):
                inner, outer = along[:, :3], along[:, 3:]
                a, b = np.nanmean(inner**2) / 2, np.nanmean(outer**2) / 2  # sigma^2 of each region
                mid = 2 * a * b * np.log(b / a) / (b - a)  # where the likelihoods cross, in u^2
                half = b - a
                return Force(u**2, mid - half, mid + half, (2 * half) ** 2)

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
.. [4] Sarti A, Corsi C, Mazzini E, Lamberti C. Maximum likelihood
   segmentation of ultrasound images with Rayleigh distribution. IEEE Trans.
   Ultrason. Ferroelectr. Freq. Control 52(6):947-960 (2005).
   doi:10.1109/TUFFC.2005.1504017
"""

from __future__ import annotations

import warnings
from dataclasses import replace
from functools import lru_cache
from typing import NamedTuple

import numpy as np

from .speckle import (EDGE_PSF_MM, FORMED_SPECKLE_SMOOTHING_MM, LOG_SPREAD, NoSpeckleError, band_contamination,
                      beyond_wall_excess, edge_blur_mm, interface_level, interface_nepers, nanmedian, profile_blur_mm,
                      smoothed_edge_drop, speckle_correlations, speckle_nepers, speckle_smoothing_mm)

# the speckle physics (:mod:`.speckle`) that 0.1 held here stays importable from here
__all__ = ["DataTerm", "Force", "FixedInterface", "GlobalMeans", "LocalMeans", "IntensityInterface", "DATA_TERMS",
           "band_offsets", "shell_offsets", "otsu_threshold", "patch_of_rows", "nanmedian", "NoSpeckleError",
           "interface_level", "interface_nepers", "speckle_nepers"]

#: fractions of f at which the cavity is sampled along each ray (the global means)
CAVITY_FRACTIONS = np.array([0.15, 0.35, 0.55, 0.75, 0.95])
# the force's scale is at least this fraction of the grey-level spread
# around the initial surface, squared (a flat region must not blow it up)
_MIN_CONTRAST = 0.05


def band_offsets(band: float) -> np.ndarray:
    """Distances (mm) along the normal of the band means: 4 in ``(0, band]``."""
    return _offsets(float(band), 4).copy()


def shell_offsets(band_out: float) -> np.ndarray:
    """Distances (mm) outside the surface of the global outer mean: 5 in ``(0, band_out]``."""
    return _offsets(float(band_out), 5).copy()


@lru_cache(maxsize=16)
def _offsets(width: float, n: int) -> np.ndarray:
    # a segmentation makes four data terms, each two sets of offsets:
    # a copy of a cached linspace is cheaper than a new one
    return np.linspace(0, width, n + 1)[1:]


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
    by, the bound of the resulting speed (in steps), and the region means
    as measured (``measured``: in image units, before a term bounds or
    moves them; None: ``c_in``, ``c_out`` themselves)."""

    u: np.ndarray
    c_in: object
    c_out: object
    scale: float
    clip: float = 1.0
    measured: tuple | None = None

    @property
    def grey_means(self) -> tuple:
        """The region means a result reports: :attr:`measured`, else
        ``(c_in, c_out)`` (scalars, or arrays over the sample points whose
        medians a result reports)."""
        return (self.c_in, self.c_out) if self.measured is None else self.measured


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
        Whether :meth:`force` reads the observation's band means
        (``Observation.band_means``).
    needs_region_means : bool
        Whether it reads the global region means (``Observation.region_means``).
    band_offsets : array or None
        Their distances along the normal (mm).
    exponent : float or None
        The observation reads ``exp(exponent * v)`` for each grey level
        ``v`` (0: the grey levels; None: not known yet).
    step_factor : float
        The step of this term's stage, in multiples of the ``step`` option.
    hands_over_bands : bool
        Whether the ``measured`` means of its forces are the band means at
        the sample points, from which a following stage may start
        (:class:`LocalMeans`).
    starts_from_bands : bool
        Whether its stage starts from the band means the previous stage
        measured last (:meth:`IntensityInterface.freeze`).
    loop_kind : {"fixed", "global", "local"} or None
        How a level run in one compiled loop computes this force
        (:meth:`spheroseg.descent.Descent.run`): from :meth:`fixed_force`,
        as the region means, as the band means; None: it
        cannot (the level then runs iteration by iteration).
    offsets : array or None
        A term of one's own: the distances (mm along the outward normal,
        negative inside) at which :meth:`statistics` reads the image.
    """

    needs_bands = False
    needs_region_means = False
    exponent: float | None = 0.0
    step_factor = 1.0
    hands_over_bands = False
    starts_from_bands = False
    loop_kind: str | None = None
    offsets: np.ndarray | None = None

    def __init__(self, samples: np.ndarray, *, band: float = 8.0, band_out: float = 15.0,
                 interface: float | None = None):
        self.spread = float(np.std(samples))
        self.min_scale = (_MIN_CONTRAST * self.spread) ** 2
        self.band_offsets = band_offsets(band) if self.needs_bands else None
        self.shell_offsets = shell_offsets(band_out)

    def force(self, obs) -> Force:
        """The :class:`Force` for the observation ``obs``
        (:meth:`spheroseg.backends.NumpyBackend.observe_term`): a function
        of it and of the term's constants; the term keeps nothing of it (the
        tracker keeps what a result reports, :attr:`Force.grey_means`).

        Here: :meth:`statistics` of the samples at :attr:`offsets` along
        the normals of the band rows (the built-in terms override this)."""
        if self.offsets is None:
            raise NotImplementedError(f"{type(self).__name__} defines neither force() nor offsets and statistics()")
        return self.statistics(obs.u, obs.along)

    def statistics(self, u: np.ndarray, along: np.ndarray) -> Force:
        """A term of one's own: the force from what the iteration observed.

        A pure function: it reads only its arguments and the term's
        constants, and changes nothing.

        Parameters
        ----------
        u : array (n,)
            Grey levels at the surface's sample points (NaN off the data).
        along : array (rows, len(offsets))
            Grey levels at :attr:`offsets` (mm) along the outward normals of
            the band rows (a quarter of the sample points), trilinear; NaN
            off the data.

        Returns
        -------
        Force
            ``u`` as the force compares it (the grey levels, or a transform
            of them), ``c_in`` and ``c_out`` in the same units (scalars, or
            arrays over the ``n`` points), the scale the region force
            ``(u - c_in)^2 - (u - c_out)^2`` is divided by (the squared
            contrast) and the clip of the resulting speed (in steps).  The
            cavity is the region of ``c_in``; where ``u`` lies nearer
            ``c_out`` the surface moves inwards.
        """
        raise NotImplementedError

    def reset(self) -> None:
        """Forget what was measured on earlier frames (a new frame starts)."""

    def fixed_force(self, u=None) -> Force:
        """The force, at grey levels ``u``, of a term whose statistics do
        not change in a level (``loop_kind`` "fixed")."""
        raise NotImplementedError


class FixedInterface(DataTerm):
    """The paper's fast mode: ``c_in``, ``c_out`` fixed from the samples
    around the initial surface (``interface``: Otsu's threshold by default;
    the two levels are the class means about it, centred on it)."""

    loop_kind = "fixed"

    def __init__(self, samples, *, band=8.0, band_out=15.0, interface=None):
        super().__init__(samples, band=band, band_out=band_out)
        mid = otsu_threshold(samples) if interface is None else float(interface)
        lo, hi = samples[samples <= mid], samples[samples > mid]
        half = (hi.mean() - lo.mean()) / 2 if lo.size and hi.size else self.spread
        self.c_in, self.c_out = mid - half, mid + half

    def force(self, obs) -> Force:
        return self.fixed_force(obs.u)

    def fixed_force(self, u=None) -> Force:
        return Force(u, self.c_in, self.c_out, (self.c_out - self.c_in) ** 2)


class GlobalMeans(DataTerm):
    """Global Chan-Vese means, re-estimated every iteration.

    The cavity must be the darker region (blood): means of the wrong
    polarity (``c_in > c_out``) give no force, as :class:`LocalMeans` does
    locally.  Chan-Vese's force would otherwise pull bright tissue in and
    push the blood out, and a start whose two means are nearly equal (CETUS
    Patient 7 resampled to 256^3: 88.92 inside against 88.91 outside) would
    collapse on its own feedback instead of leaving the wall to the next
    level.
    """

    loop_kind = "global"
    needs_region_means = True

    def force(self, obs) -> Force:
        c_in, measured_out = obs.region_means
        c_out = max(measured_out, c_in)
        return Force(obs.u, c_in, c_out, max((c_out - c_in) ** 2, self.min_scale), measured=(c_in, measured_out))


class LocalMeans(DataTerm):
    """Band means along each normal, smoothed over the surface.

    The boundary lies where the grey level is half way between the inner
    and the outer band means, or, with :attr:`boundary_nepers` finite,
    where the echo intensity is (:func:`interface_level`).  Band means of
    the wrong :attr:`polarity` give no force there.
    """

    needs_bands = True
    hands_over_bands = True
    loop_kind = "local"
    #: +1: the inside (``c_in``'s region) is the darker, as the cavity's
    #: blood; -1: the brighter, as a bright wall seen from within
    polarity = 1.0
    #: grey levels per neper of echo intensity of the half-way intensity
    #: boundary; inf: the grey levels' midpoint
    boundary_nepers = np.inf

    def force(self, obs) -> Force:
        c_in, c_out = obs.band_means
        sign = self.polarity
        contrast = np.maximum(sign * (c_out - c_in), 0.0)  # the wrong polarity: no force
        force_in, force_out = c_in, c_in + sign * contrast
        if np.isfinite(self.boundary_nepers):
            dark, bright = (force_in, force_out) if sign > 0 else (force_out, force_in)
            level = interface_level(dark, bright, self.boundary_nepers)
            force_in, force_out = level - sign * contrast / 2, level + sign * contrast / 2
        return Force(obs.u, force_in, force_out, max(nanmedian(contrast) ** 2, self.min_scale),
                     measured=(c_in, c_out))


class IntensityInterface(LocalMeans):
    """The wall where the echo intensity is half way between blood and
    myocardium: the bias of log-domain means removed.

    B-mode grey levels are ``v = a + k ln I`` (log compression of the echo
    intensity ``I``, ``k`` grey levels per neper) of an intensity that the
    point-spread function (PSF) blurred.  Across a blood-tissue interface the
    mean intensity is ``I_b + (I_t - I_b) Phi(x / sigma)``: half way between
    the two at the interface.  :class:`LocalMeans` puts the wall where the
    grey level is half way between the regions' mean grey levels, i.e. where
    ``I`` is near their geometric mean: on the blood side, by about two PSF
    widths at 30 dB of contrast (1.5-4 mm; volumes 10-25 % low).

    This term moves the wall to the grey level ``g*`` whose mean over speckle
    belongs to half the two regions' mean intensity.  For fully developed
    speckle ``E[v] = a + k (ln m - gamma)`` for a region of mean intensity
    ``m``, so with the regions' mean grey levels ``c_in``, ``c_out``::

        g* = k ln((exp(c_in / k) + exp(c_out / k)) / 2)

    (``c_out - k ln 2`` for a strong contrast: half the tissue's power;
    :func:`interface_level`).  The force stays in grey levels, so a bright speckle weighs no more than
    in :class:`LocalMeans`.

    It is the second stage of the finest level: :class:`LocalMeans` first
    finds the wall (robustly: a log-domain midpoint lies well below the
    myocardium whatever lies beyond it), then this term takes ``c_in``,
    ``c_out`` from their last band means about that wall (:meth:`freeze`;
    measured on its first observation when none were handed over), freezes
    them, and moves the surface to ``g*``.  Frozen, because measured about
    the moving surface the outer band would reach past a myocardium dimmer
    than what lies beyond it (pericardium, lung interface), raise ``g*``
    above the myocardium and let the wall creep outwards through it.
    :meth:`reset` measures them again (a new frame of a sequence).

    ``k`` is estimated from the data, once: fully developed speckle has an
    exponential intensity, so ``ln I`` has a standard deviation of
    ``pi / sqrt(6)`` (5.57 dB) whatever its mean (:func:`speckle_nepers`,
    read at voxel centres: interpolation averages the log and narrows its
    spread).  Speckle that scan conversion or the scanner's filters averaged
    has a smaller spread: ``k`` comes out low and ``g*`` a little high (the
    wall a fraction of a PSF width outwards).  A contrast of over
    :data:`MAX_CONTRAST_DB` per ``k`` is not echo: it bounds ``k`` from below
    (:func:`interface_nepers`), which holds when smoothing has narrowed the
    spread and leaves the contrast of the region means.

    A smoothing of the grey levels also lowers the mean level at the
    interface itself (the log of the blurred edge is concave there), so that
    ``g*`` lies outside it by a fraction of the smoothing's width.  The
    smoothing's width is estimated once from the speckle's correlation
    between neighbouring voxels (:func:`speckle_smoothing_mm`: persistence
    narrows the spread but leaves it), and ``g*`` is lowered by the drop of
    the smoothed edge (:func:`smoothed_edge_drop`) across a point-spread
    function of :data:`EDGE_PSF_MM`.

    The band means are read about the local means' wall, some two widths of
    the point-spread function inside the interface, so that across a wide
    point-spread function the outer band's near offsets are still in the
    blurred edge and ``c_out`` comes out low (the wall inwards).  On speckle
    as the scanner formed it, the same correlation gives that width along
    each image axis (:func:`edge_blur_mm`), and the band means lose the
    deficit the blurred edge leaves in them (:meth:`unblurred_levels`,
    :func:`band_contamination`); where the outer band's profile still
    rises as a blurred edge's does, by the wider blur that profile shows
    (:func:`profile_blur_mm`: speckle that does not show its walls' blur).

    References
    ----------
    .. [1] Wagner RF, Smith SW, Sandrik JM, Lopez H. Statistics of speckle in
       ultrasound B-scans. IEEE Trans. Sonics Ultrason. 30(3):156-163 (1983).
       doi:10.1109/T-SU.1983.31404
    .. [2] Tao Z, Tagare HD, Beaty JD. Evaluation of four probability
       distribution models for speckle in clinical cardiac ultrasound images.
       IEEE Trans. Med. Imaging 25(11):1483-1491 (2006). doi:10.1109/TMI.2006.881376
    """

    LOG_SPREAD = LOG_SPREAD
    #: The stage starts at the local means' wall, within the blurred edge,
    #: where the force grows with the distance to the interface: at the
    #: option's step an iteration there removed about a quarter of that
    #: distance, and the stage stopped (on ``tol``) some 0.15 mm short of the
    #: interface.  Twice the step halves it each iteration (the adaptive
    #: step halves it back if the surface oscillates); taken only when the
    #: local means settled (see ``Tracker``).
    step_factor = 2.0
    hands_over_bands = False
    starts_from_bands = True

    _frozen = None  # the levels, once set (:meth:`freeze`)

    def __init__(self, samples, *, band=8.0, band_out=15.0, interface=None):
        super().__init__(samples, band=band, band_out=band_out)
        self.nepers = None  #: grey levels per neper of intensity, once estimated
        self.smoothing_mm = 0.0  #: the grey levels' smoothing (mm), estimated with ``nepers``
        #: covariance (mm^2, world axes) of the wall's blur in the speckle as formed, estimated with ``nepers``
        self.edge_blur_covariance = None
        #: the wall's blur (mm, standard deviation along the normals) whose
        #: deficits the last :meth:`freeze` removed (0: none removed)
        self.wall_blur_mm = 0.0
        #: grey levels taken off the myocardium's level at the last
        #: :meth:`freeze`: what the outer band's far half read beyond a
        #: thin wall darker than what lies beyond it
        #: (:func:`beyond_wall_excess`); 0 when it read none
        self.beyond_wall = 0.0
        #: the fraction of the far half's rise that :attr:`beyond_wall` took
        #: (1: all of it; between 0 and 1 where the rise may be an edge's)
        self.beyond_wall_fraction = 0.0

    def reset(self) -> None:
        """Measure the region means again on the next observation."""
        self._frozen = None

    @property
    def needs_bands(self) -> bool:
        """Only until the region means are frozen: the band samples after
        that would be read by nothing (two thirds of an iteration's samples)."""
        return self._frozen is None

    @property
    def loop_kind(self) -> str | None:
        """Fixed once frozen; before, the first observation measures them
        (and the log compression) iteration by iteration."""
        return None if self._frozen is None else "fixed"

    @property
    def frozen(self) -> bool:
        """Whether its levels are set (:meth:`freeze`)."""
        return self._frozen is not None

    def force(self, obs) -> Force:
        if self._frozen is None:
            raise RuntimeError("the intensity interface's levels are not set: freeze() them from band means first")
        return self.fixed_force(obs.u)

    def fixed_force(self, u=None) -> Force:
        return Force(u, *self._frozen, measured=self._measured)

    def freeze(self, backend, volume, obs, c_in, c_out) -> None:
        """Set the frozen levels from the band means ``c_in``, ``c_out``
        (fields at the sample points, ``Observation.band_means``) about
        the surface of ``obs`` (an observation with its bands).  The
        schedule hands over the local means' last ones, measured about the
        wall they settled on, so that this stage's first observation needs
        no bands.  The levels lose the blurred edge's deficits
        (:meth:`unblurred_levels`) and ``c_out`` what the outer band read
        beyond a thin wall (:attr:`beyond_wall`)."""
        if self.nepers is None:
            self.nepers = self.estimate_nepers(backend, volume, obs)
            self.smoothing_mm, self.edge_blur_covariance = self.estimate_blur(backend, volume, obs)
        contrast = np.maximum(c_out - c_in, 0.0)
        c_out = c_in + contrast
        k = self.nepers
        self._measured = (c_in, c_out)  # what a result reports (their medians)

        def medians(offsets):  # the outer band's median grey level at each offset
            outer = backend.samples_along(volume, obs, offsets, backend.discretisation.band_rows)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # an offset off the data everywhere: NaN
                return np.nanmedian(outer, axis=0)

        band = medians(self.band_offsets)
        past = self.band_offsets + self.band_offsets[-1]  # as far again past the band: what lies beyond the wall
        c_in, c_out, deficits = self.unblurred_levels(obs, c_in, c_out, band, lambda: (past, medians(past)))
        self.beyond_wall, self.beyond_wall_fraction = beyond_wall_excess(band - deficits)
        c_out = c_out - self.beyond_wall
        contrast = c_out - c_in
        threshold = interface_level(c_in, c_out, k)
        if self.smoothing_mm > 0:
            sigma = EDGE_PSF_MM / (2 * np.sqrt(2 * np.log(2)))
            threshold = threshold + k * smoothed_edge_drop(self.smoothing_mm / sigma, float(nanmedian(contrast)) / k)
        self._frozen = (threshold - contrast / 2, threshold + contrast / 2,
                        max(float(nanmedian(contrast)) ** 2, self.min_scale))

    def unblurred_levels(self, obs, c_in: np.ndarray, c_out: np.ndarray, profile=None,
                         beyond=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The band means ``c_in``, ``c_out`` less what the wall's blurred
        edge left in them (:func:`band_contamination`), where the speckle is
        as the scanner formed it: smoothed by less than
        :data:`FORMED_SPECKLE_SMOOTHING_MM`, and what it left at each of the
        outer band's offsets (grey levels, ``<= 0``).  Unchanged, and
        zeros, otherwise: a smoothing's correlation hides the point-spread
        function's (a voxel apart, its speckle correlates by 0.8-0.97 along
        every axis), and :func:`smoothed_edge_drop` models the smoothed
        edge.

        The edge's blur along the surface's normals is the median of the
        quadratic form of :attr:`edge_blur_covariance` on them, or more
        where the outer band's ``profile`` (its grey level at each offset,
        the medians over the surface) still rises as a blurred edge does
        (:func:`profile_blur_mm`; ``beyond`` returns the offsets and the
        readings past the band): an image whose speckle does not show the
        blur of its walls.  It is kept as :attr:`wall_blur_mm`.
        """
        k = self.nepers
        contrast = float(nanmedian(c_out - c_in))
        none = np.zeros(len(self.band_offsets))
        self.wall_blur_mm = 0.0
        if self.edge_blur_covariance is None or not contrast > 0 or self.smoothing_mm >= FORMED_SPECKLE_SMOOTHING_MM:
            return c_in, c_out, none

        def deficits(sigma):  # the regions' contrast is the band means' less what the edge took from it
            inside, outside = 0.0, none
            for _ in range(2):
                inside, outside = band_contamination(sigma, (contrast - k * (outside.mean() - inside)) / k,
                                                     self.band_offsets)
            return inside, outside

        n = obs.normal  # (3, samples), unit
        sigma = float(np.sqrt(nanmedian(np.einsum("is,ij,js->s", n, self.edge_blur_covariance, n))))
        deficit_in, deficits_out = deficits(sigma)
        if profile is not None:
            options = dict(sigma_mm=sigma, nepers=k, offsets=self.band_offsets, deficits=k * deficits_out,
                           contrast_nepers=contrast / k - (deficits_out.mean() - deficit_in))
            read = profile_blur_mm(profile, **options)
            if read > sigma and beyond is not None:  # what lies past the band, read only when it matters
                read = profile_blur_mm(profile, beyond=beyond(), **options)
            if read > sigma:
                sigma = read
                deficit_in, deficits_out = deficits(sigma)
        self.wall_blur_mm = sigma
        return c_in - k * deficit_in, c_out - k * deficits_out.mean(), k * deficits_out

    def estimate_nepers(self, backend, volume, obs) -> float:
        """``k`` of :func:`interface_nepers` from the grey levels of the outer
        band at voxel centres and the band means' contrast."""
        d = backend.discretisation
        rows = d.band_rows
        outer = backend.samples_along(volume, obs, self.band_offsets, rows, order=0)  # (rows, offsets)
        return interface_nepers(outer, patch_of_rows(d.grid, d.order, rows), nanmedian(obs.outside - obs.inside))

    def estimate_blur(self, backend, volume, obs) -> tuple[float, np.ndarray | None]:
        """The speckle's correlation between the outer band's voxel centres
        and their next voxels along the image's axes
        (:func:`speckle_correlations`): :func:`speckle_smoothing_mm` and the
        covariance (mm^2, world axes) of the wall's blur,
        :func:`edge_blur_mm` along the image axes.  ``(0, None)`` in beam
        space (no post-processing there, and axes of angles)."""
        if not hasattr(volume, "direction"):
            return 0.0, None
        d = backend.discretisation
        rows = d.band_rows
        direction = np.asarray(volume.direction, float)
        steps = direction * np.asarray(volume.spacing, float)  # columns: one voxel
        outer, *neighbours = (backend.samples_along(volume, replace(obs, world=obs.world + step[:, None]),
                                                    self.band_offsets, rows, order=0)
                              for step in (np.zeros(3), *steps.T))
        correlations = speckle_correlations(outer, np.stack(neighbours), patch_of_rows(d.grid, d.order, rows))
        blur = edge_blur_mm(correlations, volume.spacing)
        return speckle_smoothing_mm(correlations, volume.spacing), (direction * blur**2) @ direction.T


def patch_of_rows(grid, order: int, rows: np.ndarray) -> np.ndarray:
    """The patch (``i2 n1 + i1``) of each sample point of ``rows``
    (samples are numbered as :meth:`HermiteGrid.quadrature` orders them)."""
    n_row = grid.n1 * order
    return ((rows // n_row) // order) * grid.n1 + (rows % n_row) // order


#: the data term of each ``mode``
DATA_TERMS = {"intensity": IntensityInterface, "local": LocalMeans, "chan-vese": GlobalMeans, "fast": FixedInterface}
