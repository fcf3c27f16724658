"""Speckle physics against its definitions: log-compressed speckle of known
spread, correlation and blur, and blurred edges integrated numerically."""

import numpy as np
import pytest

from spheroseg.descent.speckle import (MAX_EDGE_BLUR_MM, band_contamination,
                                       beyond_wall_excess, edge_blur_mm, interface_level, interface_nepers, nanmedian,
                                       profile_blur_mm, smoothed_edge_drop, speckle_correlations, speckle_nepers,
                                       speckle_smoothing_mm)


def test_interface_level_is_the_half_way_intensity():
    # independent: exponentiate, compare with the intensities' mean
    k = 17.0
    dark, bright = np.array([40.0, 100.0, 100.0, 2000.0]), np.array([80.0, 101.0, 240.0, 9000.0])
    level = interface_level(dark, bright, k)
    np.testing.assert_allclose(level[:3], k * np.log((np.exp(dark[:3] / k) + np.exp(bright[:3] / k)) / 2))
    assert level[1] == pytest.approx(100.5, abs=0.01)  # weak contrast: the midpoint
    assert level[2] == pytest.approx(240.0 - k * np.log(2.0), abs=0.01)  # strong: half the bright intensity
    assert level[3] == pytest.approx(9000.0 - k * np.log(2.0))  # where exp() overflows


def test_interface_nepers_holds_the_log_compression_under_smoothing():
    """Speckle averaged over 9 independent samples (a scanner's smoothing)
    has a third of the spread: the spread alone gives k / 3; the contrast
    of the region means (35 dB, kept by smoothing) bounds it from below at
    ``C / ln(10^4)`` (40 dB), and unsmoothed speckle is left to its spread."""
    rng = np.random.default_rng(3)
    k = 20.0
    patch = np.repeat(np.arange(64), 16)
    raw = k * np.log(rng.exponential(size=(len(patch), 4, 9)))
    smoothed = raw.mean(axis=2)
    contrast = k * 35 / 10 * np.log(10)  # 35 dB in grey levels
    assert speckle_nepers(smoothed, patch) == pytest.approx(k / 3, rel=0.08)
    assert interface_nepers(smoothed, patch, contrast) == pytest.approx(contrast / np.log(1e4), rel=1e-12)
    assert interface_nepers(smoothed, patch, contrast) == pytest.approx(0.875 * k, rel=1e-12)
    assert interface_nepers(raw[:, :, 0], patch, contrast) == speckle_nepers(raw[:, :, 0], patch)
    assert interface_nepers(smoothed, patch, np.nan) == speckle_nepers(smoothed, patch)
    assert interface_nepers(smoothed, patch, contrast, max_contrast_db=50.0) == pytest.approx(
        contrast / np.log(1e5), rel=1e-12)


def test_speckle_nepers_is_its_definition(rng):
    """The variance across each patch's rays at each offset (finite values,
    patches with at least min_rays), those over three times the median left
    out, averaged: patch by patch with numpy's var."""
    patch = rng.permutation(np.repeat(np.array([3, 7, 8, 20, 21, 40]), [9, 12, 5, 14, 8, 10]))
    grey = rng.normal(size=(len(patch), 4)) * rng.uniform(1, 4, 41)[patch, None]
    grey[rng.random(grey.shape) < 0.15] = np.nan
    variances = []
    for p in np.unique(patch):
        for column in grey[patch == p].T:
            finite = column[np.isfinite(column)]
            if finite.size >= 6:
                variances.append(np.var(finite, ddof=1))
    variances = np.array(variances)
    typical = variances[variances <= 3 * np.median(variances)]
    expected = np.sqrt(typical.mean()) / (np.pi / np.sqrt(6.0))  # the spread of ln I of exponential intensity
    assert speckle_nepers(grey, patch) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("sigma_voxels, spacing", [(1.5, 1.0), (2.5, 0.8), (0.0, 1.0)])
def test_speckle_smoothing_is_the_width_of_a_gaussian_smoothing(sigma_voxels, spacing):
    """White noise smoothed by a Gaussian of standard deviation s: the
    correlation of neighbouring voxels is exp(-1 / (4 s^2)), which gives s
    back (in mm); unsmoothed noise does not correlate (0); patches of their
    own means (each patch its own tissue) change nothing."""
    from scipy import ndimage

    rng = np.random.default_rng(5)
    field = rng.standard_normal((48, 48, 48))
    if sigma_voxels:
        field = ndimage.gaussian_filter(field, sigma_voxels)
    index = rng.integers(4, 40, size=(600, 3))
    patch = np.arange(600) % 12
    field_at = lambda offset: (field[tuple((index + offset).T)] + 5.0 * patch)[:, None]  # noqa: E731
    samples = field_at(np.zeros(3, int))
    neighbours = np.stack([field_at(np.eye(3, dtype=int)[axis]) for axis in range(3)])
    s = speckle_smoothing_mm(speckle_correlations(samples, neighbours, patch), spacing)
    assert s == pytest.approx(sigma_voxels * spacing, rel=0.08, abs=0.15)


@pytest.mark.parametrize("spacing", [1.0, 0.7])
def test_edge_blur_is_the_point_spread_function_read_from_log_speckle(spacing):
    """Fully developed speckle (complex scatterers) through a Gaussian
    amplitude point-spread function of standard deviation 0.3, 1.5 and 2.5
    voxels along the three axes, log-compressed: the correlation of
    neighbouring voxels gives the blur of a wall's mean intensity, the
    amplitude's width over sqrt(2), along the two wide axes (in mm); the
    narrowest axis, what all share, reads 0.  The log's correlation is
    under the intensity's (Li2): read as a Gaussian's, the wide axes would
    come out 0.73 and 0.63 of their blur."""
    from scipy import ndimage

    rng = np.random.default_rng(11)
    shape, sigma = (40, 64, 64), (0.3, 1.5, 2.5)
    field = ndimage.gaussian_filter(rng.standard_normal(shape), sigma) + 1j * ndimage.gaussian_filter(
        rng.standard_normal(shape), sigma)
    grey = 12.0 * np.log(np.abs(field) ** 2)
    index = np.stack([rng.integers(5, n - 6, size=4000) for n in shape], axis=1)
    patch = np.arange(4000) % 16
    at = lambda offset: grey[tuple((index + offset).T)][:, None]  # noqa: E731
    correlations = speckle_correlations(at(np.zeros(3, int)), np.stack([at(np.eye(3, dtype=int)[a]) for a in range(3)]),
                                        patch)
    blur = edge_blur_mm(correlations, spacing)
    expected = np.array(sigma) * spacing / np.sqrt(2)
    assert blur[0] == 0
    np.testing.assert_allclose(blur[1:], expected[1:], rtol=0.12)
    gaussian = np.sqrt(-spacing**2 / (2 * np.log(correlations[1:])) - (-spacing**2 / (2 * np.log(correlations[0]))))
    assert np.all(gaussian / np.sqrt(2) < 0.8 * expected[1:])


@pytest.mark.parametrize("sigma_mm, contrast_db", [(0.7, 35.0), (1.3, 35.0), (2.0, 20.0), (3.0, 40.0)])
def test_band_contamination_is_the_blurred_edge_read_as_the_local_means_read_it(sigma_mm, contrast_db):
    """A step of echo intensity blurred numerically by a Gaussian (no normal
    distribution function), its log; the local means' wall found on a fine
    grid where the profile is half way between its band means at 2, 4, 6
    and 8 mm each side; those band means less the regions' log levels.
    Without blur the bands read the regions exactly."""
    from scipy import ndimage

    nepers = contrast_db / 10 * np.log(10)
    x = np.linspace(-30, 30, 60001)
    dx = x[1] - x[0]
    intensity = ndimage.gaussian_filter1d(np.where(x < 0, np.exp(-nepers), 1.0), sigma_mm / dx, mode="nearest",
                                          truncate=12.0)  # the tail reaches the dark band at 40 dB
    profile = np.log(intensity)
    offsets = np.array([2.0, 4.0, 6.0, 8.0])
    shift = np.round(offsets / dx).astype(int)
    centre = np.arange(9000, len(x) - 9000)  # 9 mm from the ends
    inside = profile[centre[:, None] - shift].mean(axis=1)
    outside = profile[centre[:, None] + shift].mean(axis=1)
    balance = profile[centre] - (inside + outside) / 2
    near = np.abs(x[centre]) < 8  # the root nearest the edge (far out both bands lie in one region)
    wall = np.flatnonzero(near[:-1] & (np.sign(balance[:-1]) != np.sign(balance[1:])))[0]
    deficit_in, deficit_out = band_contamination(sigma_mm, nepers, offsets)
    assert deficit_in == pytest.approx(inside[wall] + nepers, abs=2e-3)
    np.testing.assert_allclose(deficit_out, profile[centre[wall] + shift], atol=2e-3)  # each offset's reading
    assert deficit_out.mean() == pytest.approx(outside[wall], abs=2e-3)
    assert deficit_in >= 0 and np.all(deficit_out <= 0)
    past = offsets + 8.0  # readings past the band, about the same wall
    np.testing.assert_allclose(band_contamination(sigma_mm, nepers, offsets, reads=past)[1],
                               profile[centre[wall] + shift + shift[-1]], atol=2e-3)
    unblurred = band_contamination(0.0, nepers, offsets)
    assert unblurred[0] == 0.0 and np.array_equal(unblurred[1], np.zeros(4))


@pytest.mark.parametrize("contrast_db", [15.0, 25.0, 40.0])
@pytest.mark.parametrize("sigma_mm", [1.0, 2.0, 3.0])
def test_a_blurred_edge_reads_nothing_beyond_the_wall(sigma_mm, contrast_db):
    """The outer band's readings of a blurred edge about the local means'
    wall (checked above against a numerically blurred one), with no blur
    removed: they rise across the band but by shrinking steps, so nothing
    is taken for tissue beyond the wall, up to a blur of 3 mm (standard
    deviation) at 15-40 dB, and never all of the rise at 4 mm and up to
    60 dB."""
    _, readings = band_contamination(sigma_mm, contrast_db / 10 * np.log(10), np.array([2.0, 4.0, 6.0, 8.0]))
    steps = np.diff(readings)
    assert np.all(steps > 0) and readings[2:].mean() > readings[:2].mean()  # it rises, far half above near half
    assert beyond_wall_excess(10.0 * readings) == (0.0, 0.0)
    # wider still, some of it may be taken, never all: the last step stays under three quarters of the first
    _, readings = band_contamination(4.0, contrast_db / 10 * np.log(10) * 1.5, np.array([2.0, 4.0, 6.0, 8.0]))
    excess, fraction = beyond_wall_excess(10.0 * readings)
    assert 0 < fraction < 1 and excess == pytest.approx(fraction * 10.0 * (readings.mean() - readings[:2].mean()))


@pytest.mark.parametrize("contrast_db", [25.0, 35.0])
@pytest.mark.parametrize("sigma_mm", [1.0, 1.5, 2.0, 2.5])
def test_profile_blur_is_the_blur_whose_deficits_leave_the_profile_flat(sigma_mm, contrast_db):
    """The outer band's readings of an edge blurred by ``sigma_mm`` (a wall
    at 100 grey levels, 10 per neper): read from a smaller blur, the
    profile gives ``sigma_mm`` back; read from it, or from a wider one,
    nothing more.  A flat profile, a dark wall's growing steps, a missing
    offset: the blur given.  Wider than :data:`MAX_EDGE_BLUR_MM`, at most
    that (its last step nears three quarters of its first: part of the
    rise is left to :func:`beyond_wall_excess`)."""
    nepers, offsets = contrast_db / 10 * np.log(10), np.array([2.0, 4.0, 6.0, 8.0])
    profile = 100.0 + 10.0 * band_contamination(sigma_mm, nepers, offsets)[1]
    read = profile_blur_mm(profile, sigma_mm=0.3, contrast_nepers=nepers, nepers=10.0, offsets=offsets)
    assert read == pytest.approx(sigma_mm, abs=0.02)
    for given in (sigma_mm, sigma_mm + 0.5):
        assert profile_blur_mm(profile, sigma_mm=given, contrast_nepers=nepers, nepers=10.0,
                               offsets=offsets) == given
    for other in ([100.0] * 4, [100.0, 100.0, 106.0, 112.0], [100.0, 104.0, np.nan, 108.0]):
        assert profile_blur_mm(other, sigma_mm=0.3, contrast_nepers=nepers, nepers=10.0, offsets=offsets) == 0.3
    wider = 100.0 + 10.0 * band_contamination(MAX_EDGE_BLUR_MM + 1.0, nepers, offsets)[1]
    assert 0.3 < profile_blur_mm(wider, sigma_mm=0.3, contrast_nepers=nepers, nepers=10.0,
                                 offsets=offsets) <= MAX_EDGE_BLUR_MM


def test_profile_blur_falls_back_where_the_rise_goes_on_past_the_band():
    """A band profile blurred by 2 mm (30 dB, 10 grey levels per neper),
    the readings past it (10-16 mm) those of the same edge: the blur is
    read, as where the tissue beyond is darker; where that tissue reads
    above the plateau by as much as the read raised it (a blurred dark
    wall whose band rises towards it), the given blur stands, and half as
    much keeps half of the read."""
    nepers, offsets, past = 3 * np.log(10), np.array([2.0, 4.0, 6.0, 8.0]), np.array([10.0, 12.0, 14.0, 16.0])
    profile = 100.0 + 10.0 * band_contamination(2.0, nepers, offsets)[1]
    plateau_edge = 100.0 + 10.0 * band_contamination(2.0, nepers, offsets, reads=past)[1]
    raised = 10.0 * (band_contamination(0.3, nepers, offsets)[1].mean()
                     - band_contamination(2.0, nepers, offsets)[1].mean())
    options = dict(sigma_mm=0.3, contrast_nepers=nepers, nepers=10.0, offsets=offsets)
    assert profile_blur_mm(profile, **options) == pytest.approx(2.0, abs=0.02)
    for far in (plateau_edge, plateau_edge - 5.0):
        assert profile_blur_mm(profile, beyond=(past, far), **options) == pytest.approx(2.0, abs=0.02)
    assert profile_blur_mm(profile, beyond=(past, plateau_edge + raised), **options) == pytest.approx(0.3, abs=0.01)
    half = profile_blur_mm(profile, beyond=(past, plateau_edge + raised / 2), **options)
    assert half == pytest.approx(0.3 + (2.0 - 0.3) / 2, abs=0.02)


def test_profile_blur_takes_what_beyond_wall_excess_leaves():
    """A rise whose last step is between half and three quarters of its
    first is part edge, part tissue beyond the wall: the blur read is the
    full read's, weighted by the fraction not taken for that tissue, and
    continuous across the bound."""
    offsets, base = np.array([2.0, 4.0, 6.0, 8.0]), [100.0, 108.0, 114.0]
    reads = [profile_blur_mm(base + [118.0 + t], sigma_mm=0.5, contrast_nepers=6.0, nepers=10.0, offsets=offsets)
             for t in np.linspace(0.0, 2.0, 41)]
    assert reads[0] > 1.0 and reads[-1] == 0.5  # at 1/2 all edge, at 3/4 all beyond
    assert np.all(np.diff(reads) <= 0) and np.max(np.abs(np.diff(reads))) < 0.15
    fraction = beyond_wall_excess(base + [119.0])[1]
    full = profile_blur_mm([100.0, 108.0, 114.0, 117.0], sigma_mm=0.5, contrast_nepers=6.0, nepers=10.0,
                           offsets=offsets)
    assert 0 < fraction < 1 and full > reads[20] > 0.5


def test_beyond_wall_excess_is_what_the_far_half_reads_above_the_wall():
    """A wall at 100 grey levels over the band's near half and tissue 12
    above it over the far half: the band's mean is 6 above the wall's; a
    steady rise the same; a profile that falls beyond the wall (a bright
    wall), a flat one, one with a missing offset: nothing."""
    assert beyond_wall_excess([100.0, 100.0, 112.0, 112.0]) == pytest.approx((6.0, 1.0))
    assert beyond_wall_excess([100.0, 104.0, 108.0, 112.0]) == pytest.approx((4.0, 1.0))
    assert beyond_wall_excess([100.0, 101.0, 104.0, 112.0, 115.0]) == pytest.approx((6.4 - 0.5, 1.0))
    for profile in ([100.0, 104.0, 100.0, 95.0], [100.0] * 4, [100.0, 100.0, np.nan, 112.0], [100.0]):
        assert beyond_wall_excess(profile) == (0.0, 0.0)
    assert beyond_wall_excess([100.0, 110.0, 113.0, 114.0]) == (0.0, 0.0)  # a blurred edge's shrinking steps
    # between a last step half the first and three quarters of it, in proportion: no jump
    assert beyond_wall_excess([100.0, 108.0, 113.0, 117.0]) == (0.0, 0.0)
    assert beyond_wall_excess([100.0, 108.0, 114.0, 119.0]) == pytest.approx((0.5 * (110.25 - 104.0), 0.5))
    assert beyond_wall_excess([100.0, 108.0, 114.0, 120.0]) == pytest.approx((110.5 - 104.0, 1.0))
    ramp = [beyond_wall_excess([100.0, 108.0, 114.0, 118.0 + t])[0] for t in np.linspace(0.0, 2.0, 41)]
    assert np.all(np.diff(ramp) >= 0) and np.max(np.diff(ramp)) < 0.4


@pytest.mark.parametrize("contrast_db", [20.0, 35.0])
@pytest.mark.parametrize("ratio", [0.0, 0.5, 1.0, 2.0])
def test_smoothed_edge_drop_is_the_smoothed_profile(contrast_db, ratio):
    """The mean log-compressed edge ln(eps + (1 - eps) Phi(x / sigma))
    smoothed numerically by a Gaussian of ``ratio`` sigma: its value at the
    interface less the unsmoothed one, ln((1 + eps) / 2)."""
    from scipy import ndimage, special

    nepers = contrast_db / 10 * np.log(10)
    eps = np.exp(-nepers)
    x = np.linspace(-40, 40, 16001)
    profile = np.log(eps + (1 - eps) * special.ndtr(x / 1.3))
    smoothed = ndimage.gaussian_filter1d(profile, ratio * 1.3 / (x[1] - x[0]), truncate=8) if ratio else profile
    expected = smoothed[8000] - np.log((1 + eps) / 2)
    assert smoothed_edge_drop(ratio, nepers) == pytest.approx(expected, abs=1e-4)
    assert smoothed_edge_drop(ratio, nepers) <= 0


@pytest.mark.parametrize("n", [1, 2, 3, 4, 7, 50, 51, 1024, 4097])
def test_nanmedian_is_numpys(rng, n):
    """The partition median equals numpy's to the last bit, NaNs left out."""
    x = rng.normal(size=n) * 10.0 ** rng.integers(-3, 4, n)
    assert nanmedian(x) == np.median(x)
    x[rng.random(n) < 0.3] = np.nan
    if np.isnan(x).all():
        assert np.isnan(nanmedian(x))
    else:
        assert nanmedian(x) == np.nanmedian(x)
    assert nanmedian(x.reshape(1, -1)) == nanmedian(x)


def test_nanmedian_of_nothing_and_of_a_scalar():
    assert np.isnan(nanmedian(np.full(3, np.nan))) and np.isnan(nanmedian(np.empty(0)))
    assert nanmedian(2.5) == 2.5
