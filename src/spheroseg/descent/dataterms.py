"""The data terms of the descent: what ``c_in`` and ``c_out`` of paper eq. 22
are, and the scale that makes the force dimensionless.

Each data term is an object of one small protocol (:class:`DataTerm`, its
rules numbered there), its parameters the arguments of its class
(``LocalMeans(polarity=-1.0)``); a ``mode`` string names a built-in one
(:data:`DATA_TERMS`, as :func:`scipy.optimize.minimize` maps ``method``),
resolved once where the options are made:

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
    normals) to a :class:`Force`; pass an instance as ``mode``.  It reads
    no backend and keeps no state: the iteration samples the image, calls
    it, and keeps what a result reports (as for the built-in terms, whose
    :meth:`DataTerm.force` reads the band means or the region means that
    the observation carries, and whose measured levels the stepper keeps
    as a :class:`TermState`).  Such a term runs iteration by iteration on
    either backend (the compiled level loop computes only the built-in
    terms).  For example, a Rayleigh likelihood of the echo amplitude in
    each band (Sarti et al. 2005)::

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

from dataclasses import dataclass, replace
from functools import lru_cache
from typing import NamedTuple

import numpy as np

from .speckle import (EDGE_PSF_MM, FORMED_SPECKLE_SMOOTHING_MM, LOG_SPREAD, NoSpeckleError, band_contamination,
                      beyond_wall_excess, edge_blur_mm, interface_level, interface_nepers, nanmedian, profile_blur_mm,
                      smoothed_edge_drop, speckle_correlations, speckle_nepers, speckle_smoothing_mm)

# the speckle physics (:mod:`.speckle`) that 0.1 held here stays importable from here
__all__ = ["DataTerm", "Force", "Reads", "TermState", "FreezeSamples", "FixedInterface", "GlobalMeans", "LocalMeans", "IntensityInterface", "DATA_TERMS",
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


class Reads(NamedTuple):
    """What the iteration samples for a data term (:meth:`DataTerm.reads`),
    each None where the term reads none of it.

    ``band_offsets`` (mm): the inner and outer band means at these
    distances along the normals, smoothed over the surface
    (``Observation.band_means``); ``shell_offsets`` (mm): the global
    region means, the cavity and a shell at these distances outside
    (``Observation.region_means``); ``offsets`` (mm, negative inside):
    the grey levels at these distances along the normals of the band
    rows (``Observation.along``); ``exponent``: every sample ``v`` read as
    ``exp(exponent v)`` (0: the grey levels)."""

    band_offsets: np.ndarray | None = None
    shell_offsets: np.ndarray | None = None
    offsets: np.ndarray | None = None
    exponent: float = 0.0


@dataclass(frozen=True, eq=False)
class TermState:
    """What a data term measured on a segmentation: its constants from the
    grey levels about the initial surface (:meth:`DataTerm.start`), and what
    a term that measures its levels once a frame set (:meth:`DataTerm.freeze`).
    The stepper keeps it; the term never does.

    Attributes
    ----------
    spread : float
        Standard deviation of the grey levels about the initial surface.
    min_scale : float
        The least squared contrast the force is divided by.
    band_offsets, shell_offsets : array
        The band means' and the shell's offsets (mm) of the options' widths.
    levels : tuple or None
        ``(c_in, c_out, scale)`` of a term whose levels are fixed (the fast
        mode's, or the intensity interface's once frozen); None otherwise.
    measured : tuple or None
        The band means the levels were set from (what a result reports).
    nepers : float or None
        Grey levels per neper of intensity (the intensity interface's
        estimate, once made: it holds for every frame of a sequence).
    smoothing_mm, edge_blur_covariance
        The grey levels' smoothing (mm) and the covariance (mm^2, world
        axes) of the wall's blur in the speckle as formed, estimated with
        ``nepers`` (:mod:`spheroseg.descent.speckle`).
    wall_blur_mm : float
        The wall's blur (mm along the normals) whose deficits the last
        freeze removed (0: none).
    beyond_wall, beyond_wall_fraction : float
        Grey levels taken off the myocardium's level at the last freeze for
        what the outer band read beyond a thin wall, and the fraction of the
        band's rise they are (:func:`~spheroseg.descent.speckle.beyond_wall_excess`).
    """

    spread: float
    min_scale: float
    band_offsets: np.ndarray
    shell_offsets: np.ndarray
    levels: tuple | None = None
    measured: tuple | None = None
    nepers: float | None = None
    smoothing_mm: float = 0.0
    edge_blur_covariance: np.ndarray | None = None
    wall_blur_mm: float = 0.0
    beyond_wall: float = 0.0
    beyond_wall_fraction: float = 0.0

    @property
    def frozen(self) -> bool:
        """Whether fixed levels are set."""
        return self.levels is not None


class FreezeSamples(NamedTuple):
    """The samples :meth:`IntensityInterface.freeze` computes its levels
    from, taken by the stepper about the wall where the local means settled
    (:meth:`DataTerm.freeze_reads` says which).

    ``profile`` and ``beyond``: the outer band's median grey level at each
    of its offsets and at as many again past the band (trilinear);
    ``outer``: the outer band's grey levels at voxel centres ``(rows,
    offsets)`` with ``patch``, the patch of each row, and ``neighbours``
    ``(3, rows, offsets)`` those of the next voxel along each image axis,
    whose ``spacing`` and ``direction`` they are (None where the estimates
    are made already; ``neighbours`` None in beam space)."""

    profile: np.ndarray
    beyond: np.ndarray
    outer: np.ndarray | None = None
    patch: np.ndarray | None = None
    neighbours: np.ndarray | None = None
    spacing: np.ndarray | None = None
    direction: np.ndarray | None = None


class DataTerm:
    """Region statistics for the force of eq. 22: the protocol of a data term.

    1. A term is its parameters, the keyword arguments of its constructor
       (``LocalMeans(polarity=-1.0)``), kept as its public attributes and
       never changed after; terms of one type and equal parameters are
       equal.
    2. It declares what the iteration samples for it (:meth:`reads`: band
       means, region means, grey levels at its own :attr:`offsets` along the
       normals); the stepper samples them and hands over an observation.
    3. :meth:`start` gives its constants from the grey levels about the
       initial surface as a :class:`TermState`; the stepper keeps the state
       and hands it back with every observation.
    4. :meth:`force` is a pure function of the observation and the state:
       it samples nothing and changes nothing.
    5. A term whose levels are measured once a frame (the intensity
       interface) declares the samples that takes (:meth:`freeze_reads`)
       and gives a new state from them (:meth:`freeze`, pure as well);
       :meth:`reset` gives the state a new frame starts from.
    6. The built-in terms also run in the compiled level loop
       (:meth:`loop_kind`), a specialisation the tests hold equal to
       :meth:`force`; a term of one's own (``loop_kind`` None) runs the
       same iteration in Python, on either backend.

    A term of one's own sets :attr:`offsets` and writes :meth:`statistics`
    (the default :meth:`force` calls it with the grey levels at the surface
    and those at its offsets), and is passed as ``mode``.

    Attributes
    ----------
    offsets : array or None
        A term of one's own: the distances (mm along the outward normal,
        negative inside) at which :meth:`statistics` reads the image.
    exponent : float
        The observation reads ``exp(exponent * v)`` for each grey level ``v``
        (0: the grey levels).
    step_factor : float
        The step of this term's stage, in multiples of the ``step`` option.
    hands_over_bands : bool
        Whether the ``measured`` means of its forces are the band means at
        the sample points, from which a following stage may start
        (:class:`LocalMeans`).
    starts_from_bands : bool
        Whether its stage starts from the band means the previous stage
        measured last (:meth:`IntensityInterface.freeze`).
    """

    offsets: np.ndarray | None = None
    exponent = 0.0
    step_factor = 1.0
    hands_over_bands = False
    starts_from_bands = False

    # rule 1: a term is its parameters -----------------------------------------

    def parameters(self) -> dict:
        """The term's parameters (its constructor's keyword arguments)."""
        return dict(vars(self))

    def __eq__(self, other) -> bool:
        return type(other) is type(self) and _same(self.parameters(), other.parameters())

    def __hash__(self) -> int:
        return hash((type(self), tuple(sorted((k, repr(v)) for k, v in self.parameters().items()))))

    def __repr__(self) -> str:
        return f"{type(self).__name__}({', '.join(f'{k}={v!r}' for k, v in self.parameters().items())})"

    # rules 2 to 6 ---------------------------------------------------------------

    def start(self, samples: np.ndarray, *, band: float = 8.0, band_out: float = 15.0) -> TermState:
        """The term's constants from ``samples``, finite grey levels about the
        initial surface (both sides): the least scale of the force; with the
        band widths (mm) of :class:`spheroseg.SegmentOptions`."""
        spread = float(np.std(samples))
        return TermState(spread, (_MIN_CONTRAST * spread) ** 2, band_offsets(band), shell_offsets(band_out))

    def reads(self, state: TermState) -> Reads:
        """What the iteration samples for :meth:`force` (here: the grey
        levels at :attr:`offsets`)."""
        return Reads(offsets=None if self.offsets is None else np.asarray(self.offsets, dtype=float),
                     exponent=float(self.exponent or 0.0))

    def force(self, obs, state: TermState) -> Force:
        """The :class:`Force` for the observation ``obs``
        (:meth:`spheroseg.descent.backends.NumpyBackend.observe_term` of
        :meth:`reads`) and the term's ``state``.

        Here: :meth:`statistics` of the samples at :attr:`offsets` along
        the normals of the band rows (the built-in terms override this)."""
        if self.offsets is None:
            raise NotImplementedError(f"{type(self).__name__} defines neither force() nor offsets and statistics()")
        return self.statistics(obs.u, obs.along)

    def statistics(self, u: np.ndarray, along: np.ndarray) -> Force:
        """A term of one's own: the force from what the iteration observed.

        A pure function: it reads only its arguments and the term's
        parameters, and changes nothing.

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

    def reset(self, state: TermState) -> TermState:
        """The state a new frame starts from (here: the same)."""
        return state

    def loop_kind(self, state: TermState) -> str | None:
        """How a level run in one compiled loop computes this force
        (:meth:`spheroseg.descent.descent.Descent.run`): ``"fixed"`` from
        :meth:`fixed_force`, ``"global"`` as the region means, ``"local"``
        as the band means; None: it cannot (the level then runs iteration
        by iteration)."""
        return None

    def fixed_force(self, state: TermState, u=None) -> Force:
        """The force, at grey levels ``u``, of a term whose levels are fixed
        (``loop_kind`` ``"fixed"``): ``state.levels``."""
        return Force(u, *state.levels, measured=state.measured)

    def freeze_reads(self, state: TermState) -> dict | None:
        """What :meth:`freeze` needs sampled: the outer band's ``offsets``,
        those ``beyond`` it, and whether the speckle's ``estimates`` are
        still to be made (None: the term has no levels to freeze)."""
        return None

    def freeze(self, state: TermState, obs, c_in, c_out, samples: FreezeSamples) -> TermState:
        """A state with the term's levels set from the band means ``c_in``,
        ``c_out`` about the surface of ``obs``, and ``samples``."""
        raise NotImplementedError(f"{type(self).__name__} has no levels to freeze")


def _same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) if isinstance(a[k], np.ndarray) else a[k] == b[k]
                                        for k in a)


class FixedInterface(DataTerm):
    """The paper's fast mode: ``c_in``, ``c_out`` fixed from the samples
    around the initial surface (``interface``: Otsu's threshold by default;
    the two levels are the class means about it, centred on it)."""

    def __init__(self, *, interface: float | None = None):
        self.interface = None if interface is None else float(interface)

    def start(self, samples, *, band=8.0, band_out=15.0) -> TermState:
        state = super().start(samples, band=band, band_out=band_out)
        mid = otsu_threshold(samples) if self.interface is None else self.interface
        lo, hi = samples[samples <= mid], samples[samples > mid]
        half = (hi.mean() - lo.mean()) / 2 if lo.size and hi.size else state.spread
        c_in, c_out = mid - half, mid + half
        return replace(state, levels=(c_in, c_out, (c_out - c_in) ** 2))

    def reads(self, state) -> Reads:
        return Reads()

    def force(self, obs, state) -> Force:
        return self.fixed_force(state, obs.u)

    def loop_kind(self, state) -> str:
        return "fixed"


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

    def reads(self, state) -> Reads:
        return Reads(shell_offsets=state.shell_offsets)

    def force(self, obs, state) -> Force:
        c_in, measured_out = obs.region_means
        c_out = max(measured_out, c_in)
        return Force(obs.u, c_in, c_out, max((c_out - c_in) ** 2, state.min_scale), measured=(c_in, measured_out))

    def loop_kind(self, state) -> str:
        return "global"


class LocalMeans(DataTerm):
    """Band means along each normal, smoothed over the surface.

    The boundary lies where the grey level is half way between the inner
    and the outer band means, or, with ``boundary_nepers`` finite, where the
    echo intensity is (:func:`interface_level`).  Band means of the wrong
    polarity give no force there.

    Parameters
    ----------
    polarity : {1, -1}
        1: the inside (``c_in``'s region) is the darker, as the cavity's
        blood; -1: the brighter, as a bright wall seen from within.
    boundary_nepers : float
        Grey levels per neper of echo intensity of the half-way intensity
        boundary; inf: the grey levels' midpoint.
    """

    hands_over_bands = True

    def __init__(self, *, polarity: float = 1.0, boundary_nepers: float = np.inf):
        if polarity not in (1, -1):
            raise ValueError(f"polarity must be 1 (a dark inside) or -1 (a bright one), got {polarity!r}")
        if not boundary_nepers > 0:
            raise ValueError(f"boundary_nepers must be positive (inf: the grey levels' midpoint), "
                             f"got {boundary_nepers!r}")
        self.polarity, self.boundary_nepers = float(polarity), float(boundary_nepers)

    def reads(self, state) -> Reads:
        return Reads(band_offsets=state.band_offsets)

    def force(self, obs, state) -> Force:
        c_in, c_out = obs.band_means
        sign = self.polarity
        contrast = np.maximum(sign * (c_out - c_in), 0.0)  # the wrong polarity: no force
        force_in, force_out = c_in, c_in + sign * contrast
        if np.isfinite(self.boundary_nepers):
            dark, bright = (force_in, force_out) if sign > 0 else (force_out, force_in)
            level = interface_level(dark, bright, self.boundary_nepers)
            force_in, force_out = level - sign * contrast / 2, level + sign * contrast / 2
        return Force(obs.u, force_in, force_out, max(nanmedian(contrast) ** 2, state.min_scale),
                     measured=(c_in, c_out))

    def loop_kind(self, state) -> str:
        return "local"


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

    #: standard deviation of ln I for exponential (fully developed speckle) intensity
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

    def __init__(self):
        super().__init__()

    def parameters(self) -> dict:
        return {}  # the local means' defaults, not parameters of its own

    def reset(self, state) -> TermState:
        """Measure the region means again on the next observation (the log
        compression and the blur stay: one image formation a sequence)."""
        return replace(state, levels=None)

    def reads(self, state) -> Reads:
        """The band means until the levels are frozen; after that, the band
        samples would be read by nothing (two thirds of an iteration's)."""
        return Reads(band_offsets=state.band_offsets) if state.levels is None else Reads()

    def loop_kind(self, state) -> str | None:
        """Fixed once frozen; before, the first observation measures them
        (and the log compression) iteration by iteration."""
        return None if state.levels is None else "fixed"

    def force(self, obs, state) -> Force:
        if state.levels is None:
            raise RuntimeError("the intensity interface's levels are not set: freeze() them from band means first")
        return self.fixed_force(state, obs.u)

    def freeze_reads(self, state) -> dict:
        past = state.band_offsets + state.band_offsets[-1]  # as far again past the band: what lies beyond the wall
        return {"offsets": state.band_offsets, "beyond": past, "estimates": state.nepers is None}

    def freeze(self, state, obs, c_in, c_out, samples: FreezeSamples) -> TermState:
        """The state with the frozen levels set from the band means ``c_in``,
        ``c_out`` (fields at the sample points, ``Observation.band_means``)
        about the surface of ``obs`` (an observation with its bands).  The
        schedule hands over the local means' last ones, measured about the
        wall they settled on, so that this stage's first observation needs
        no bands.  The levels lose the blurred edge's deficits
        (:meth:`unblurred_levels`) and ``c_out`` what the outer band read
        beyond a thin wall (``beyond_wall``)."""
        if state.nepers is None:
            smoothing, covariance = self.estimate_blur(samples)
            state = replace(state, nepers=self.estimate_nepers(samples, obs), smoothing_mm=smoothing,
                            edge_blur_covariance=covariance)
        contrast = np.maximum(c_out - c_in, 0.0)
        c_out = c_in + contrast
        k = state.nepers
        measured = (c_in, c_out)  # what a result reports (their medians)
        band = samples.profile
        beyond = (self.freeze_reads(state)["beyond"], samples.beyond)
        c_in, c_out, deficits, wall_blur = self.unblurred_levels(state, obs, c_in, c_out, band, beyond)
        excess, fraction = beyond_wall_excess(band - deficits)
        c_out = c_out - excess
        contrast = c_out - c_in
        threshold = interface_level(c_in, c_out, k)
        if state.smoothing_mm > 0:
            sigma = EDGE_PSF_MM / (2 * np.sqrt(2 * np.log(2)))
            threshold = threshold + k * smoothed_edge_drop(state.smoothing_mm / sigma, float(nanmedian(contrast)) / k)
        levels = (threshold - contrast / 2, threshold + contrast / 2,
                  max(float(nanmedian(contrast)) ** 2, state.min_scale))
        return replace(state, levels=levels, measured=measured, wall_blur_mm=wall_blur, beyond_wall=excess,
                       beyond_wall_fraction=fraction)

    @staticmethod
    def unblurred_levels(state: TermState, obs, c_in: np.ndarray, c_out: np.ndarray, profile=None,
                         beyond=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """The band means ``c_in``, ``c_out`` less what the wall's blurred
        edge left in them (:func:`band_contamination`), where the speckle is
        as the scanner formed it: smoothed by less than
        :data:`FORMED_SPECKLE_SMOOTHING_MM`; what it left at each of the
        outer band's offsets (grey levels, ``<= 0``); and that blur (mm).
        Unchanged, zeros and 0 otherwise: a smoothing's correlation hides
        the point-spread function's (a voxel apart, its speckle correlates
        by 0.8-0.97 along every axis), and :func:`smoothed_edge_drop`
        models the smoothed edge.

        The edge's blur along the surface's normals is the median of the
        quadratic form of ``state.edge_blur_covariance`` on them, or more
        where the outer band's ``profile`` (its grey level at each offset,
        the medians over the surface) still rises as a blurred edge does
        (:func:`profile_blur_mm`; ``beyond``: the offsets and the readings
        past the band): an image whose speckle does not show the blur of
        its walls.
        """
        k, offsets = state.nepers, state.band_offsets
        contrast = float(nanmedian(c_out - c_in))
        none = np.zeros(len(offsets))
        if (state.edge_blur_covariance is None or not contrast > 0
                or state.smoothing_mm >= FORMED_SPECKLE_SMOOTHING_MM):
            return c_in, c_out, none, 0.0

        def deficits(sigma):  # the regions' contrast is the band means' less what the edge took from it
            inside, outside = 0.0, none
            for _ in range(2):
                inside, outside = band_contamination(sigma, (contrast - k * (outside.mean() - inside)) / k, offsets)
            return inside, outside

        n = obs.normal  # (3, samples), unit
        sigma = float(np.sqrt(nanmedian(np.einsum("is,ij,js->s", n, state.edge_blur_covariance, n))))
        deficit_in, deficits_out = deficits(sigma)
        if profile is not None:
            options = dict(sigma_mm=sigma, nepers=k, offsets=offsets, deficits=k * deficits_out,
                           contrast_nepers=contrast / k - (deficits_out.mean() - deficit_in))
            read = profile_blur_mm(profile, **options)
            if read > sigma and beyond is not None:  # what lies past the band matters
                read = profile_blur_mm(profile, beyond=beyond, **options)
            if read > sigma:
                sigma = read
                deficit_in, deficits_out = deficits(sigma)
        return c_in - k * deficit_in, c_out - k * deficits_out.mean(), k * deficits_out, sigma

    @staticmethod
    def estimate_nepers(samples: FreezeSamples, obs) -> float:
        """``k`` of :func:`interface_nepers` from the grey levels of the outer
        band at voxel centres and the band means' contrast."""
        return interface_nepers(samples.outer, samples.patch, nanmedian(obs.outside - obs.inside))

    @staticmethod
    def estimate_blur(samples: FreezeSamples) -> tuple[float, np.ndarray | None]:
        """The speckle's correlation between the outer band's voxel centres
        and their next voxels along the image's axes
        (:func:`speckle_correlations`): :func:`speckle_smoothing_mm` and the
        covariance (mm^2, world axes) of the wall's blur,
        :func:`edge_blur_mm` along the image axes.  ``(0, None)`` in beam
        space (no post-processing there, and axes of angles)."""
        if samples.neighbours is None:
            return 0.0, None
        correlations = speckle_correlations(samples.outer, samples.neighbours, samples.patch)
        blur = edge_blur_mm(correlations, samples.spacing)
        return (speckle_smoothing_mm(correlations, samples.spacing),
                (samples.direction * blur**2) @ samples.direction.T)


def patch_of_rows(grid, order: int, rows: np.ndarray) -> np.ndarray:
    """The patch (``i2 n1 + i1``) of each sample point of ``rows``
    (samples are numbered as :meth:`HermiteGrid.quadrature` orders them)."""
    n_row = grid.n1 * order
    return ((rows // n_row) // order) * grid.n1 + (rows % n_row) // order


#: the data term of each ``mode``
DATA_TERMS = {"intensity": IntensityInterface, "local": LocalMeans, "chan-vese": GlobalMeans, "fast": FixedInterface}
