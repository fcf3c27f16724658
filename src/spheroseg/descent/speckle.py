"""The physics of log-compressed speckle that the intensity interface reads.

B-mode grey levels are ``v = a + k ln I``: the echo intensity ``I`` of
fully developed speckle (exponential, so that ``ln I`` spreads by
:data:`LOG_SPREAD` whatever its mean), blurred by the point-spread function
and log-compressed by ``k`` grey levels per neper.  Here are the estimates
:class:`spheroseg.descent.dataterms.IntensityInterface` makes of an image
from the samples about a wall, and the models of a blurred wall's edge it
corrects its levels with:

- the log compression ``k`` from the speckle's spread
  (:func:`speckle_nepers`, bounded by the contrast: :func:`interface_nepers`)
  and the level whose intensity is half way (:func:`interface_level`);
- a smoothing after compression and the point-spread function's blur, from
  the speckle's correlation between neighbouring voxels
  (:func:`speckle_correlations`, :func:`speckle_smoothing_mm`,
  :func:`edge_blur_mm`);
- what a blurred edge leaves in the band means (:func:`band_contamination`,
  :func:`smoothed_edge_drop`), the blur a band's profile shows
  (:func:`profile_blur_mm`), and what a band reads past a thin wall
  (:func:`beyond_wall_excess`).

Pure functions of arrays: nothing here samples an image.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from scipy import optimize, special

__all__ = ["nanmedian", "LOG_SPREAD", "MAX_CONTRAST_DB", "EDGE_PSF_MM", "FORMED_SPECKLE_SMOOTHING_MM", "SHRINKING_EDGE_STEP",
           "GROWING_FAR_STEP", "MAX_EDGE_BLUR_MM", "NoSpeckleError", "interface_level", "interface_nepers",
           "speckle_nepers", "speckle_correlations", "speckle_smoothing_mm", "edge_blur_mm", "band_contamination",
           "profile_blur_mm", "beyond_wall_excess", "smoothed_edge_drop"]

#: standard deviation of ln I for exponential (fully developed speckle) intensity
LOG_SPREAD = np.pi / np.sqrt(6.0)


def nanmedian(values) -> np.float64:
    """:func:`numpy.nanmedian` of all the values, equal to the last bit, by
    one partition (numpy's overhead dominates at the few thousand values of
    a surface); NaN, without a warning, when there are none."""
    x = np.asarray(values, dtype=float).ravel()
    x = x[~np.isnan(x)]
    n = x.size
    if n == 0:
        return np.float64(np.nan)
    low, high = (n - 1) // 2, n // 2
    part = np.partition(x, [low, high])
    return (part[low] + part[high]) / 2  # as numpy: the mean of the middle one or two
#: the largest blood-to-myocardium backscatter contrast taken for echo, dB
#: (published figures are 20-40 dB): it bounds the log compression from below
MAX_CONTRAST_DB = 40.0


#: full width at half maximum (mm) of the point-spread function across the
#: beam that blurs a wall's edge: an adult apical 3D scan's, 3 mm at 80 mm
#: depth (it scales how far a scanner's smoothing lowers the edge's level)
EDGE_PSF_MM = 3.0


#: the most smoothing (mm, :func:`speckle_smoothing_mm`) of speckle as a
#: scanner forms it: scan conversion's interpolation reads 0.3-0.5 mm, a
#: scanner's filters of 1 mm and more 1-2 mm; below it the speckle's
#: correlation gives the point-spread function (:func:`edge_blur_mm`)
FORMED_SPECKLE_SMOOTHING_MM = 0.75


#: the outer band's last step over its first (:func:`beyond_wall_excess`):
#: at most this across a blurred edge alone (a blur of up to 3 mm, standard
#: deviation, at 15-40 dB), and at least the next where the far half reads
#: tissue beyond the wall (a blurred edge reaches it only with a blur of
#: over 4 mm)
SHRINKING_EDGE_STEP = 0.5


GROWING_FAR_STEP = 0.75


#: the widest blur (mm, standard deviation) :func:`profile_blur_mm` reads:
#: up to it a blurred edge's last step is under :data:`SHRINKING_EDGE_STEP`
#: of its first (15-40 dB); beyond it the band, too short to see the
#: edge's foot, reads blurs alike whose deficits are not
MAX_EDGE_BLUR_MM = 3.0


def interface_level(dark, bright, nepers):
    """The grey level whose echo intensity is half way between those of the
    grey levels ``dark`` and ``bright`` (``dark <= bright``; scalars or
    arrays), with ``nepers`` grey levels per neper of intensity::

        g* = k ln((exp(dark / k) + exp(bright / k)) / 2)

    written so that it neither overflows nor cancels:
    ``bright + k (ln(exp(dark / k) + exp(bright / k)) - bright / k - ln 2)``.
    ``(dark + bright) / 2`` as ``k`` grows, ``bright - k ln 2`` for a strong
    contrast (half the brighter region's intensity).  Compiled as it stands
    for the level loop (:mod:`spheroseg._kernels`)."""
    return bright + nepers * (np.logaddexp(dark / nepers, bright / nepers) - bright / nepers - np.log(2.0))


class NoSpeckleError(ValueError):
    """No speckle to estimate the log compression from (a noise-free or
    heavily smoothed image): :func:`speckle_nepers` cannot measure it."""


def interface_nepers(samples: np.ndarray, patch: np.ndarray, contrast: float, *,
                     max_contrast_db: float = MAX_CONTRAST_DB) -> float:
    """Grey levels per neper of intensity that set the intensity interface.

    ``k = max(k_s, C / ln(10^(max_contrast_db / 10)))``: ``k_s`` from the
    spread of the speckle (:func:`speckle_nepers` of ``samples``, ``patch``)
    and ``C`` the contrast of the region means in grey levels.  The spread
    gives ``k`` on unprocessed speckle; smoothing (a scanner's Gaussian,
    median or speckle-reducing filters, persistence) narrows it and leaves
    the region means, so that the contrast bound then holds ``k``: it takes
    the blood-to-myocardium contrast at most ``max_contrast_db`` (dB of
    intensity).  A non-finite or non-positive ``C`` sets no bound.
    """
    nepers = speckle_nepers(samples, patch)
    if np.isfinite(contrast) and contrast > 0:
        nepers = max(nepers, float(contrast) / np.log(10.0 ** (max_contrast_db / 10)))
    return nepers


def speckle_correlations(samples: np.ndarray, neighbours: np.ndarray, patch: np.ndarray) -> np.ndarray:
    """Correlation coefficient of the speckle with its next voxel along each
    image axis.

    ``samples`` ``(rays, offsets)`` are grey levels at voxel centres along
    rays whose patch is ``patch`` (as :func:`speckle_nepers`);
    ``neighbours`` ``(axes, rays, offsets)`` those of the next voxel along
    each axis.  Both are centred on the mean of their (patch, offset) bin
    (each bin one tissue), so that the coefficient is the speckle's, not the
    anatomy's.  0 for an axis without spread.
    """
    patch = np.asarray(patch)
    shape = (patch.max() + 1) * samples.shape[1]
    bins = (patch.reshape(-1, 1) * samples.shape[1] + np.arange(samples.shape[1])).ravel()
    correlations = []
    for other in neighbours:
        ok = (np.isfinite(samples) & np.isfinite(other)).ravel()
        a, b, key = samples.ravel()[ok], other.ravel()[ok], bins[ok]
        count = np.maximum(np.bincount(key, minlength=shape), 1)
        a = a - (np.bincount(key, a, minlength=shape) / count)[key]
        b = b - (np.bincount(key, b, minlength=shape) / count)[key]
        norm = np.sqrt(np.sum(a * a) * np.sum(b * b))
        correlations.append(np.sum(a * b) / norm if norm > 0 else 0.0)
    return np.array(correlations, dtype=float)


def _correlation_widths(correlations, steps) -> np.ndarray:
    """``w^2 = -step^2 / (2 ln c)`` per axis: the squared width (mm^2) of a
    Gaussian correlation of coefficient ``c`` at ``step`` (0 where ``c <= 0``)."""
    c = np.asarray(correlations, dtype=float)
    step = np.broadcast_to(np.asarray(steps, dtype=float), c.shape)
    return np.where(c > 0, -step**2 / (2 * np.log(np.clip(c, 1e-300, 0.999))), 0.0)


def speckle_smoothing_mm(correlations, steps) -> float:
    """Standard deviation (mm) of a smoothing that the grey levels went
    through after log compression, from the speckle's correlation between
    neighbouring voxels (:func:`speckle_correlations`, one per image axis,
    ``steps`` mm apart).

    A correlation ``c`` along an axis gives the width of a Gaussian
    correlation ``w^2 = -step^2 / (2 ln c)``.  Scanners sample along the
    beam at half the axial point-spread function (under a millimetre), so
    that along the axis nearest the beam raw speckle hardly correlates from
    voxel to voxel; a Gaussian smoothing of standard deviation ``s`` widens
    the correlation by ``2 s^2`` along every axis, and persistence
    (averaging independent speckle) not at all.  The least width over the
    axes gives ``s = w / sqrt(2)`` (the speckle's own width along the beam
    counted in: about 0.4 mm on the raw phantoms).  0 when the speckle does
    not correlate.
    """
    widths = _correlation_widths(correlations, steps)
    return float(np.sqrt(widths.min() / 2)) if widths.size else 0.0


@lru_cache(maxsize=1)
def _log_correlation_table() -> tuple[np.ndarray, np.ndarray]:
    # the log intensity's correlation (6 / pi^2) Li2(rho) against the intensity's rho, increasing
    rho = np.linspace(0.0, 1.0, 2001)
    return special.spence(1.0 - rho) * 6 / np.pi**2, rho


def edge_blur_mm(correlations, steps) -> np.ndarray:
    """Standard deviation (mm), along each image axis, of the blur of a
    wall's mean echo intensity, from the correlation of log-compressed
    speckle as the scanner formed it (:func:`speckle_correlations`, voxels
    ``steps`` mm apart).

    A Gaussian point-spread function of the echo amplitude, of standard
    deviation ``sigma_h``, correlates the intensity of fully developed
    speckle as ``rho(d) = exp(-d^2 / (2 sigma_h^2))`` and blurs the mean
    intensity by ``|h|^2``, of standard deviation ``sigma_h / sqrt(2)``.
    Logarithms correlate less: ``corr(ln I_1, ln I_2) = (6 / pi^2)
    Li2(rho)`` for a circular Gaussian field [1]_, inverted here.  What
    every axis shares (the least width over the axes, the widening of
    scan conversion's interpolation; along the beam the point-spread
    function is under a voxel) is removed first, as in
    :func:`speckle_smoothing_mm`.  Only for speckle that was not smoothed
    after log compression: a smoothing's correlation is not a
    point-spread function's.

    References
    ----------
    .. [1] Goodman JW. Speckle Phenomena in Optics. Roberts, 2007, ch. 3
       (the joint statistics of speckle intensities).
    """
    steps = np.broadcast_to(np.asarray(steps, dtype=float), np.shape(correlations))
    widths = _correlation_widths(correlations, steps)
    own = np.maximum(widths - widths.min(), 0.0)
    log_rho = np.where(own > 0, np.exp(-steps**2 / (2 * np.where(own > 0, own, 1.0))), 0.0)
    table, rho = _log_correlation_table()
    intensity_rho = np.clip(np.interp(log_rho, table, rho), 1e-12, 0.999)
    return np.where(own > 0, np.sqrt(-steps**2 / (2 * np.log(intensity_rho))) / np.sqrt(2), 0.0)


def _log_edge(t, eps: float):
    # ln of the mean intensity relative to the bright side's, t standard deviations of the blur across the edge
    return np.log(eps + (1 - eps) * special.ndtr(t))


def band_contamination(sigma_mm: float, contrast_nepers: float, offsets, *,
                       reads=None) -> tuple[float, np.ndarray]:
    """How far (nepers of intensity) the band means about the local means'
    wall lie above the dark region's level and below the bright region's,
    across a wall whose mean intensity is blurred by a Gaussian of standard
    deviation ``sigma_mm``.

    Along the normal ``x`` (mm, 0 at the wall), the mean log intensity is
    ``ln(eps + (1 - eps) Phi(x / sigma))`` below the bright side's (``eps
    = exp(-contrast_nepers)``, ``Phi`` the normal distribution).  The local
    means' wall ``x0`` is where it is half way between its means at ``x0 -
    offsets`` and at ``x0 + offsets`` (the inner and outer band means, as
    :class:`LocalMeans` reads them); it lies on the dark side by about two
    ``sigma`` at echo contrasts, so that the near offsets of the outer band
    are still in the blurred edge.  Returns ``(inside, outside)``: the inner
    band's mean less the dark level (``>= 0``), and at each of ``offsets``
    the outer band's reading less the bright level (``<= 0``, an array:
    its mean is the outer band mean's), or at each of ``reads`` (mm
    outside that wall) where given.  ``0`` for an unblurred wall.
    """
    d = np.ravel(np.asarray(offsets, dtype=float))
    n = len(d)
    outer = d if reads is None else np.ravel(np.asarray(reads, dtype=float))
    if not sigma_mm > 0 or not contrast_nepers > 0:
        return 0.0, np.zeros(len(outer))
    contrast_nepers = min(float(contrast_nepers), 100.0)  # 434 dB: beyond it the dark side reads as no echo
    sigma, eps = float(sigma_mm), math.exp(-contrast_nepers)
    reads = np.concatenate([[0.0], -d, d]) / sigma  # the wall, the inner band, the outer band

    def means(x0):  # (wall, inner band's mean, outer band's readings) for walls at x0 (mm, an array)
        g = _log_edge(np.asarray(x0)[..., None] / sigma + reads, eps)
        return g[..., 0], g[..., 1:1 + n].mean(axis=-1), g[..., 1 + n:]

    # the balance is positive at the interface, negative on the dark side where the outer band still reaches the
    # bright side, and 0 again beyond it (both bands in the dark): the root nearest the interface, first on a grid
    # walked from it (one evaluation), then linear between the two points about it (the deficits within 1e-3
    # nepers of a root finder's)
    x0 = -np.linspace(0.0, float(d.max()) + 6 * sigma, 161)
    wall, inside, outside = means(x0)
    balance = wall - (inside + outside.mean(axis=-1)) / 2
    below = np.flatnonzero(balance <= 0)
    if balance[0] <= 0 or not below.size:  # no local means' wall: nothing to remove
        return 0.0, np.zeros(len(outer))
    i = below[0]
    root = x0[i - 1] + (x0[i] - x0[i - 1]) * balance[i - 1] / (balance[i - 1] - balance[i])
    _, inside, outside = means(root)
    if reads is not None:
        outside = _log_edge((root + outer) / sigma, eps)
    return float(inside) + contrast_nepers, outside


def profile_blur_mm(profile, *, sigma_mm: float, contrast_nepers: float, nepers: float, offsets,
                    deficits=None, beyond=None) -> float:
    """The blur (mm, standard deviation) of a wall's edge read from the
    outer band's profile: at least ``sigma_mm``, more where the profile
    still rises across the band as a blurred edge does.

    ``profile`` is the outer band's grey level at each of ``offsets`` (the
    medians over the surface, about the local means' wall), ``nepers`` the
    grey levels per neper, ``contrast_nepers`` the regions' contrast,
    ``deficits`` (optional) the readings' deficits at ``sigma_mm`` in grey
    levels.  Less the deficits the blurred edge leaves at the offsets
    (:func:`band_contamination`), the profile of a wall's plateau is flat.
    Where, less those of ``sigma_mm``, its far half still reads above its
    near half and its steps shrink as a blurred edge's do (the fraction
    :func:`beyond_wall_excess` does not take for tissue beyond the wall is
    below 1), the blur read is the one whose deficits leave no such rise,
    at most :data:`MAX_EDGE_BLUR_MM`; weighted by that fraction's
    complement, so that a profile near the bound does not make it jump.

    ``beyond`` (optional), ``(offsets, readings)`` past the band's, tells
    a rise that goes on past the band: where, less that blur's deficits,
    what lies beyond reads above the wall's plateau the blur implies, the
    band's rise is that brighter tissue's too (a dark wall blurred as
    widely as the band is long), and the blur read falls back towards
    ``sigma_mm`` in proportion: none of it kept where the tissue reads
    above that plateau by as much as the read raised the plateau.

    Speckle shows its point-spread function (:func:`edge_blur_mm`) unless
    it was made otherwise: an image whose speckle is independent from
    voxel to voxel under a blurred intensity reads none, and its walls
    would go in by the blur's deficit (the volume 7 % low at 1.5 mm, 15 %
    at 2 mm: ``tests/test_dataterms.py``).
    """
    profile = np.ravel(np.asarray(profile, dtype=float))
    offsets = np.ravel(np.asarray(offsets, dtype=float))
    half = len(profile) // 2
    if half < 1 or len(offsets) != len(profile) or not np.all(np.isfinite(profile)) or not contrast_nepers > 0:
        return float(sigma_mm)

    def unexplained(sigma):  # the far half's rise over the near half with this blur's deficits removed
        corrected = profile - nepers * band_contamination(sigma, contrast_nepers, offsets)[1]
        return corrected[-half:].mean() - corrected[:half].mean(), corrected

    if deficits is None:
        rise, corrected = unexplained(sigma_mm)
    else:  # those of sigma_mm, known to the caller
        corrected = profile - np.ravel(deficits)
        rise = corrected[-half:].mean() - corrected[:half].mean()
    fraction = beyond_wall_excess(corrected)[1] if rise > 0 else 1.0
    if fraction >= 1 or sigma_mm >= MAX_EDGE_BLUR_MM or not unexplained(sigma_mm)[0] > 0:
        return float(sigma_mm)
    if unexplained(MAX_EDGE_BLUR_MM)[0] > 0:
        read = MAX_EDGE_BLUR_MM
    else:
        read = optimize.brentq(lambda sigma: unexplained(sigma)[0], sigma_mm, MAX_EDGE_BLUR_MM, xtol=0.01)
    kept = 1.0 - fraction
    if beyond is not None:
        far_offsets, far = (np.ravel(np.asarray(a, dtype=float)) for a in beyond)
        if len(far) and len(far_offsets) == len(far) and np.all(np.isfinite(far)):
            at_read = band_contamination(read, contrast_nepers, offsets)[1]
            plateau = profile - nepers * at_read
            tissue = far - nepers * band_contamination(read, contrast_nepers, offsets, reads=far_offsets)[1]
            # how far the read blur raised the plateau over the given one's
            raised = nepers * (band_contamination(sigma_mm, contrast_nepers, offsets)[1].mean() - at_read.mean())
            if raised > 0:
                kept *= float(np.clip(1.0 - (tissue.mean() - plateau.mean()) / raised, 0.0, 1.0))
    return float(sigma_mm + kept * (read - sigma_mm))


def beyond_wall_excess(profile) -> tuple[float, float]:
    """How far (grey levels) the outer band's mean lies above the mean of
    its near half because its far half reads brighter tissue beyond the
    wall, and the fraction of that rise taken for it: ``(excess,
    fraction)``, ``(0, 0)`` when the far half reads nothing beyond.

    ``profile`` is the outer band's grey level at each of its offsets (in
    increasing order; the medians over the surface), what the blurred edge
    takes from each removed where it is known (:func:`band_contamination`).
    Past a wall thinner than the band and darker than what lies beyond it,
    the far offsets read that tissue and the profile rises towards its far
    end.  A blurred edge alone, whose width was not read (smoothed speckle),
    also rises across the band, but by ever smaller steps: the mean log
    intensity ``ln(eps + (1 - eps) Phi(x / sigma))`` is concave (the normal
    distribution function is log-concave), and about the local means' wall
    the last of the band's steps is under half the first for blurs up to
    3 mm (standard deviation) at 15-40 dB (:func:`band_contamination`'s
    readings), and under three quarters of it up to 4 mm at 15-60 dB.  So
    where the far half reads above the near half, the rise is the band's
    mean less its near half's, and the fraction taken is all of it where
    the last step is three quarters of the first or more (or the first
    does not rise), none where it is half or less
    (:data:`SHRINKING_EDGE_STEP`, :data:`GROWING_FAR_STEP`), and in
    proportion between: a profile near that bound does not make the level
    jump from one frame to the next.
    """
    profile = np.ravel(np.asarray(profile, dtype=float))
    half = len(profile) // 2
    if half < 1 or not np.all(np.isfinite(profile)):
        return 0.0, 0.0
    near, far = profile[:half].mean(), profile[-half:].mean()
    if not far > near:
        return 0.0, 0.0
    first, last = np.diff(profile)[[0, -1]]
    fraction = 1.0 if not first > 0 else float(np.clip((last / first - SHRINKING_EDGE_STEP) /
                                                       (GROWING_FAR_STEP - SHRINKING_EDGE_STEP), 0.0, 1.0))
    return fraction * float(profile.mean() - near), fraction


#: Gauss-Hermite nodes and weights (probabilists': weight exp(-z^2 / 2)) of the edge's expectation
_HERMITE = np.polynomial.hermite_e.hermegauss(48)


def smoothed_edge_drop(ratio: float, contrast_nepers: float) -> float:
    """How far (nepers of intensity, times ``k`` in grey levels) a Gaussian
    smoothing of the log-compressed grey levels lowers their mean at a
    blood-tissue interface.

    Across the interface the mean intensity is ``I_b + (I_t - I_b) Phi(x /
    sigma)`` (a point-spread function of standard deviation ``sigma``
    across it), so the mean grey level is ``c_out + k ln(eps + (1 - eps)
    Phi(x / sigma))`` with ``eps = I_b / I_t = exp(-contrast_nepers)``: at
    the interface ``c_out + k ln((1 + eps) / 2)``, the intensity interface's
    level.  The logarithm is concave there, so a Gaussian of standard
    deviation ``s = ratio sigma`` lowers it to ``c_out + k E[ln(eps + (1 -
    eps) Phi(ratio Z))]``, ``Z`` standard normal (Gauss-Hermite
    quadrature).  Returns the difference, ``<= 0`` (0 for ``ratio`` 0).
    """
    eps = float(np.exp(-max(contrast_nepers, 0.0)))
    z, w = _HERMITE
    edge = _log_edge(ratio * z, eps)
    return float(w @ edge / w.sum() - np.log((1 + eps) / 2))


def speckle_nepers(samples: np.ndarray, patch: np.ndarray, *, min_rays: int = 6) -> float:
    """Grey levels per neper of intensity from log-compressed speckle.

    ``samples`` ``(rays, offsets)`` are grey levels along rays whose patch is
    ``patch`` (non-negative integer labels); at each offset, the rays of one
    patch sample independent speckle of one tissue, whose ``ln I`` has the
    standard deviation ``pi / sqrt(6)``.  The grey-level variance across
    the rays of a patch, averaged over patches and offsets, gives
    ``k^2 pi^2 / 6``.  Variances over three times their median (a patch
    across two tissues) are left out.
    """
    # per (patch, offset): count, sum and sum of squares of the finite values,
    # each one bincount over the bins (patch, offset), rays in order; a
    # label no ray has counts none (cheaper than np.unique's compact labels)
    patch = np.asarray(patch)
    ok = np.isfinite(samples)
    values = np.where(ok, samples, 0.0)
    shape = (patch.max() + 1, samples.shape[1])
    bins = (patch.reshape(-1, 1) * shape[1] + np.arange(shape[1])).ravel()
    count, total, squares = (np.bincount(bins, weights.ravel(), minlength=shape[0] * shape[1]).reshape(shape)
                             for weights in (ok, values, values**2))
    enough = count >= min_rays
    n = count[enough]
    variances = (squares[enough] - total[enough] ** 2 / n) / (n - 1)
    median = nanmedian(variances)
    if not variances.size or median <= 0:
        raise NoSpeckleError("no speckle around the surface to estimate the log compression from "
                         "(use mode='local' for images that are not log-compressed echo)")
    typical = variances[variances <= 3 * median]
    return float(np.sqrt(typical.mean())) / LOG_SPREAD
