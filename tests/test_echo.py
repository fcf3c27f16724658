import numpy as np
import pytest

from spheroseg.volumes.beamspace import BeamGeometry, BeamVolume, scan_convert
from spheroseg.synthetic.echo import (
    RAYLEIGH_DB_STD, TOP_DB, ImageFormation, PostProcessing, form_image, log_compress, multiplicative_speckle,
    postprocess, sector_geometry, speckle_envelope,
)
from spheroseg.volumes.volume import ImageGrid

# no depth dependence and no noise: the speckle alone
FLAT = dict(attenuation_db_per_cm=0.0, tgc_db_per_cm=0.0, noise_db=-200.0, clutter_db=None)


def grid_for(formation, *, r0=30.0, r1=110.0, n_angle=61, refine=1):
    dr, de, da = formation.sampling()
    nr = int((r1 - r0) / (dr / refine)) + 1
    return BeamGeometry((nr, n_angle, n_angle), dr / refine, r0, azimuth_angular_separation=da / refine,
                        elevation_angular_separation=de / refine)


def test_rayleigh_statistics_of_uniform_speckle():
    f = ImageFormation(dynamic_range_db=60.0, gain_db=-15.0, **FLAT)
    g = grid_for(f)
    env = speckle_envelope(np.full(g.shape, 2.0, np.float32), g, f, np.random.default_rng(1))
    power = env.astype(float) ** 2 * 10 ** (-f.gain_db / 10)
    inner = (slice(None), slice(10, -10), slice(10, -10))  # away from the sector's edge
    # unit-energy PSF: mean intensity = echogenicity
    assert power[inner].mean() == pytest.approx(2.0, rel=0.03)
    # Rayleigh amplitude: std / mean = sqrt(4 / pi - 1)
    a = env[inner].astype(float)
    assert a.std() / a.mean() == pytest.approx(np.sqrt(4 / np.pi - 1), rel=0.02)
    # in dB its spread is 5.57 dB (so 5.57 * 254 / DR grey levels) and its
    # mean 10 log10(e) * (-Euler gamma) = -2.51 dB below the mean power
    grey = log_compress(env, f)[inner].astype(float)
    assert RAYLEIGH_DB_STD == pytest.approx(5.57, abs=0.005)
    assert grey.std() == pytest.approx(RAYLEIGH_DB_STD * 254 / f.dynamic_range_db, rel=0.03)
    mean_db = 10 * np.log10(2.0) + f.gain_db - 10 * np.log10(np.e) * np.euler_gamma
    assert grey.mean() == pytest.approx(1 + 254 * (mean_db - TOP_DB + 60) / 60, abs=0.5)


def _fwhm_from_autocovariance(intensity, axis, step):
    """FWHM of the PSF from the intensity autocovariance along ``axis``: for a
    Gaussian PSF of std s the intensity autocovariance is exp(-d^2 / (2 s^2))."""
    x = np.moveaxis(intensity, axis, -1)
    x = (x - x.mean()) / x.std()
    sigmas = []
    for lag in (1, 2):
        c = np.mean(x[..., :-lag] * x[..., lag:])
        sigmas.append(lag * step / np.sqrt(-2 * np.log(c)))
    return np.mean(sigmas) * 2 * np.sqrt(2 * np.log(2))


@pytest.mark.parametrize("depth", [40.0, 100.0])
def test_psf_widths_from_speckle_autocorrelation(depth):
    f = ImageFormation(lateral_psf_mm=3.0, elevation_psf_mm=4.0, axial_psf_mm=1.0, **FLAT)
    g = grid_for(f, r0=depth - 12, r1=depth + 12, refine=2)
    env = speckle_envelope(np.ones(g.shape, np.float32), g, f, np.random.default_rng(2))
    slab = (env.astype(float) ** 2)[:, 15:-15, 15:-15]  # central beams: lateral mm = depth * angle
    lateral = _fwhm_from_autocovariance(slab, 2, depth * g.azimuth_angular_separation)
    elevation = _fwhm_from_autocovariance(slab, 1, depth * g.elevation_angular_separation)
    axial = _fwhm_from_autocovariance(slab[5:-5], 0, g.radius_sample_size)
    assert lateral == pytest.approx(f.beam_width(depth), rel=0.05)
    assert elevation == pytest.approx(f.beam_width(depth, direction="elevation"), rel=0.05)
    assert axial == pytest.approx(1.0, rel=0.05)


def test_beam_width_grows_with_depth():
    f = ImageFormation()
    assert f.beam_width(f.reference_depth_mm) == pytest.approx(f.lateral_psf_mm)
    assert f.beam_width(f.reference_depth_mm, direction="elevation") == pytest.approx(f.elevation_psf_mm)
    w = f.beam_width(np.linspace(10, 160, 31))
    assert np.all(np.diff(w) > 0)
    # an adult apical scan: 2-4 mm at 80 mm depth
    assert 2.0 <= f.beam_width(80.0) <= 4.0 and 0.5 <= f.axial_psf_mm <= 1.0


def test_attenuation_and_tgc_set_the_depth_slope():
    f = ImageFormation(attenuation_db_per_cm=2.0, tgc_db_per_cm=0.8, noise_db=-200.0, clutter_db=None,
                       dynamic_range_db=70.0, gain_db=-5.0)
    g = grid_for(f, r0=20.0, r1=120.0)
    grey = log_compress(speckle_envelope(np.ones(g.shape, np.float32), g, f, np.random.default_rng(3)), f)
    radius = g.first_sample_distance + np.arange(g.shape[0]) * g.radius_sample_size
    profile = grey[:, 10:-10, 10:-10].reshape(len(radius), -1).mean(1)
    slope = np.polyfit(radius, profile, 1)[0]  # grey levels per mm
    assert slope == pytest.approx((0.8 - 2.0) / 10 * 254 / 70, rel=0.03)


def test_noise_floor():
    f = ImageFormation(attenuation_db_per_cm=0.0, tgc_db_per_cm=0.0, noise_db=-30.0)
    g = grid_for(f)
    env = speckle_envelope(np.zeros(g.shape, np.float32), g, f, np.random.default_rng(4))
    assert np.mean(env.astype(float) ** 2) == pytest.approx(10 ** (-3.0), rel=0.03)


def test_sector_geometry_and_scan_conversion():
    f = ImageFormation()
    g = sector_geometry(f, half_angle_deg=38.0, max_radius_mm=120.0)
    dr, de, da = f.sampling()
    assert g.radius_sample_size == dr and g.convention == "tan" and g.first_sample_distance == 0
    assert g.azimuth_angular_separation <= da and g.elevation_angular_separation <= de  # at least as fine
    # the sector's edge beams at +-38 degrees, the last sample at (or just beyond) 120 mm
    a_max = g.azimuth_angular_separation * (g.shape[2] - 1) / 2
    assert np.degrees(a_max) == pytest.approx(38.0) and 120.0 <= (g.shape[0] - 1) * dr < 120.0 + dr
    # every sample is data: a scan-converted image is >= 1 inside the sector and 0 outside
    rng = np.random.default_rng(7)
    beam = form_image(np.ones(g.shape, np.float32), g, f, rng)
    assert isinstance(beam, BeamVolume) and beam.array.min() >= 1
    grid = ImageGrid((40, 30, 30), (4.0, 4.0, 4.0), (-58.0, -58.0, 0.0), np.eye(3))
    cart = scan_convert(beam, grid).array
    k, j, i = np.indices(grid.shape)
    x, y, z = i * 4.0 - 58.0, j * 4.0 - 58.0, k * 4.0
    inside = (z > 0) & (np.abs(np.arctan2(x, z)) < np.radians(37)) & (np.abs(np.arctan2(y, z)) < np.radians(37)) \
        & (np.sqrt(x**2 + y**2 + z**2) < 119)
    outside = (np.abs(np.arctan2(x, np.maximum(z, 1e-9))) > np.radians(39)) | (np.sqrt(x**2 + y**2 + z**2) > 121)
    assert np.all(cart[inside] >= 1) and np.all(cart[outside] == 0)


@pytest.mark.parametrize("bad", [dict(axial_psf_mm=0.0), dict(dynamic_range_db=-40.0), dict(gain_db=np.nan),
                                 dict(clutter_db=np.inf), dict(attenuation_db_per_cm=-1.0), dict(dropout_radius_mm=6.0),
                                 dict(dropout_radius_mm=np.nan)])
def test_formation_validation(bad):
    with pytest.raises(ValueError, match="ImageFormation"):
        ImageFormation(**bad)


def test_envelope_input_validation():
    f = ImageFormation()
    g = BeamGeometry((10, 5, 5), 0.4, 10.0, 0.02, 0.02)
    with pytest.raises(ValueError, match="shape"):
        speckle_envelope(np.ones((9, 5, 5)), g, f, np.random.default_rng(0))
    with pytest.raises(ValueError, match=">= 0"):
        speckle_envelope(-np.ones(g.shape), g, f, np.random.default_rng(0))


def sector_image(rng, shape=(24, 26, 28)):
    """Grey levels in 1-255 inside a cone, 0 (no data) outside."""
    k, j, i = np.indices(shape)
    inside = np.hypot(i - shape[2] / 2, j - shape[1] / 2) <= 0.6 * k + 2
    grey = rng.integers(1, 256, shape)
    return np.where(inside, grey, 0).astype(np.uint8), inside


def test_postprocess_keeps_no_data_and_a_constant_sector():
    """Normalised convolution: a constant sector stays constant up to its
    edge (the padding does not darken it); "no data" stays 0."""
    grey, inside = sector_image(np.random.default_rng(0))
    flat = np.where(inside, 120, 0).astype(np.uint8)
    for processing in (PostProcessing(gaussian_mm=1.5), PostProcessing(median_mm=1.0),
                       PostProcessing(diffusion_iterations=5)):
        out = postprocess(flat, 1.0, processing)
        assert out.dtype == np.uint8 and np.array_equal(out == 0, ~inside)
        assert np.all(out[inside] == 120)
        out = postprocess(grey, (1.0, 0.8, 0.8), processing)
        assert np.array_equal(out == 0, ~inside) and out[inside].min() >= 1


def test_postprocess_gaussian_and_median_against_scipy():
    """Away from the sector's edge the filters are scipy's (sigma in mm over
    the spacing; the median's cube of half width ``median_mm``)."""
    from scipy import ndimage

    rng = np.random.default_rng(1)
    grey = rng.integers(1, 256, (20, 20, 20)).astype(np.uint8)
    out = postprocess(grey, (1.0, 0.5, 0.5), PostProcessing(gaussian_mm=1.0))
    ref = ndimage.gaussian_filter(grey.astype(np.float32), (1.0, 2.0, 2.0))
    inner = (slice(6, -6),) * 3
    assert np.abs(out[inner].astype(float) - np.clip(np.round(ref[inner]), 1, 255)).max() <= 1
    out = postprocess(grey, 1.0, PostProcessing(median_mm=1.0))
    ref = ndimage.median_filter(grey, size=3)
    assert np.array_equal(out[inner], ref[inner])


def test_diffusion_reduces_speckle_keeps_the_mean_and_the_edge():
    """Perona-Malik conserves the grey levels' sum (no flux across the
    sector's edge), narrows the spread within a region, and keeps a strong
    edge where it was."""
    rng = np.random.default_rng(2)
    mean = np.where(np.arange(40)[None, None, :] < 20, 60.0, 200.0) * np.ones((20, 20, 1))
    grey = np.clip(np.round(mean + rng.normal(0, 12, mean.shape)), 1, 255).astype(np.uint8)
    out = postprocess(grey, 1.0, PostProcessing(diffusion_iterations=10)).astype(float)
    assert out.sum() == pytest.approx(grey.astype(float).sum(), rel=2e-3)
    assert out[:, :, 5:15].std() < 0.6 * grey[:, :, 5:15].std()
    profile = out.mean(axis=(0, 1))
    assert profile[18] < 130 < profile[21]


@pytest.mark.parametrize("bad", [dict(gaussian_mm=-1.0), dict(median_mm=np.nan), dict(diffusion_iterations=1.5),
                                 dict(persistence=0)])
def test_postprocessing_validation(bad):
    with pytest.raises(ValueError, match="PostProcessing"):
        PostProcessing(**bad)
    with pytest.raises(ValueError, match="3D"):
        postprocess(np.ones((3, 3), np.uint8), 1.0, PostProcessing())


def test_multiplicative_speckle_is_blurred_intensity_times_independent_speckle():
    """Uniform echogenicity 1 and e^-2: log-compressed exponential intensity
    has mean ``ln e - gamma`` and standard deviation ``pi / sqrt 6`` (times
    15 grey levels per neper about 128); neighbouring voxels do not
    correlate; across a step the mean intensity is the blurred step's (a
    Gaussian of 2 mm on 1 mm voxels: at 2 mm into the dark side
    ``e^-2 + (1 - e^-2) Phi(-1)``)."""
    echogenicity = np.ones((60, 60, 80))
    echogenicity[..., :40] = np.exp(-2.0)
    grey = multiplicative_speckle(echogenicity, blur_mm=2.0, spacing=1.0, seed=3).astype(float)
    k, gamma = 15.0, np.euler_gamma
    bright, dark = grey[..., 60:], grey[..., :20]
    assert bright.mean() == pytest.approx(128 - k * gamma, abs=0.3)
    assert bright.std() == pytest.approx(k * np.pi / np.sqrt(6), rel=0.02)
    assert dark.mean() == pytest.approx(128 + k * (-2.0 - gamma), abs=0.3)
    assert abs(np.corrcoef(bright[..., :-1].ravel(), bright[..., 1:].ravel())[0, 1]) < 0.02
    from scipy import stats

    intensity = np.exp((grey[..., 38] - 128) / k)  # 2 mm into the dark side of the step at 40 (voxel edges 39.5)
    expected = np.exp(-2.0) + (1 - np.exp(-2.0)) * stats.norm.cdf(-1.5 / 2.0)
    assert intensity.mean() == pytest.approx(expected, rel=0.05)  # 3600 exponentials: 1.7 % standard error
    assert intensity.mean() > np.exp(-2.0) * 2  # the step blurred: more than twice the dark side's
    assert multiplicative_speckle(echogenicity, blur_mm=2.0, spacing=1.0, seed=3).dtype == np.uint8


@pytest.mark.parametrize("bad", [dict(blur_mm=-1.0), dict(spacing=0.0), dict(nepers=0.0),
                                 dict(echogenicity=-np.ones((4, 4, 4))), dict(echogenicity=np.ones((4, 4)))])
def test_multiplicative_speckle_validation(bad):
    options = {"echogenicity": np.ones((4, 4, 4)), "blur_mm": 1.0, "spacing": 1.0, **bad}
    with pytest.raises(ValueError, match="must be"):
        multiplicative_speckle(options.pop("echogenicity"), **options)
    assert multiplicative_speckle(np.zeros((4, 4, 4)), blur_mm=0.0, spacing=1.0).max() == 1  # no echo: darkest
