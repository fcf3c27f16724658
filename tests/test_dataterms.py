"""Data terms against a two-region image whose means are known exactly."""

from dataclasses import replace

import numpy as np
import pytest

from spheroseg.descent.backends import NumpyBackend, select_backend
from spheroseg.descent.stepper import freeze_samples
from spheroseg.descent.dataterms import (DATA_TERMS, FixedInterface, GlobalMeans, IntensityInterface, LocalMeans,
                                         band_offsets, otsu_threshold, shell_offsets)
from spheroseg.descent.speckle import FORMED_SPECKLE_SMOOTHING_MM, band_contamination, nanmedian, speckle_nepers
from spheroseg.geometry.energy import SampledSurface
from spheroseg.tracking.segment import segment
from spheroseg.surfaces.surface import Surface
from spheroseg.volumes.volume import Volume

C_IN, C_OUT = 20.0, 120.0


@pytest.fixture(scope="module")
def two_regions():
    """Blood (20) inside a cavity, tissue (120) outside, 1 mm voxels; the
    model's surface on the interface (``p_on``) and 4 mm inside (``p_in``)."""
    apex, base = np.array([50.0, 50.0, 15.0]), np.array([50.0, 50.0, 85.0])
    truth = Surface.from_apex_base(apex + [0, 0, -4.0], base, radius_ratio=0.4)
    k, j, i = np.mgrid[:100, :100, :100]
    inside = truth.contains(np.stack([i, j, k], -1).reshape(-1, 3).astype(float)).reshape(100, 100, 100)
    volume = Volume(np.where(inside, C_IN, C_OUT))
    start = Surface.from_apex_base(apex, base, radius_ratio=0.4 * 0.8)
    model = SampledSurface(truth.system, truth.pose, truth.grid, 8)
    inner = SampledSurface(start.system, start.pose, start.grid, 8)
    return volume, model, model.parameters(truth.coefficients), inner, inner.parameters(start.coefficients)


@pytest.mark.parametrize("backend", ["numpy", "auto"])
def test_global_means_are_the_region_values(two_regions, backend):
    volume, model, p, _, _ = two_regions
    b = NumpyBackend(model) if backend == "numpy" else select_backend(model)
    term = GlobalMeans()
    state = term.start(np.array([C_IN, C_OUT]), band_out=15.0)
    c_in, c_out, scale = term.force(b.observe_term(p, volume, term.reads(state)), state)[1:4]
    # the cavity along the rays (to 0.95 f) and the shell 3 to 15 mm outside
    assert c_in == pytest.approx(C_IN, abs=0.5)
    assert c_out == pytest.approx(C_OUT, abs=0.5)
    assert scale == pytest.approx((c_out - c_in) ** 2)
    # inside brighter than outside: no force, the least scale; the means as measured
    flipped = Volume(C_IN + C_OUT - volume.array)
    force = term.force(b.observe_term(p, flipped, term.reads(state)), state)
    assert force.c_out == force.c_in == pytest.approx(C_OUT, abs=0.5) and force.scale == state.min_scale
    assert force.grey_means[1] == pytest.approx(C_IN, abs=0.5)


@pytest.mark.parametrize("backend", ["numpy", "auto"])
@pytest.mark.parametrize("term_class", [FixedInterface, GlobalMeans, LocalMeans])
def test_a_data_term_keeps_nothing_of_what_it_measures(two_regions, term_class, backend):
    """The force is a function of the observation and the state: the term's
    and the state's attributes are the same objects after it, and the
    measured means travel in the :class:`Force` (``grey_means``), the
    region means as measured."""
    volume, model, p, _, _ = two_regions
    b = NumpyBackend(model) if backend == "numpy" else select_backend(model)
    term = term_class()
    state = term.start(np.array([C_IN, C_OUT]))
    before, state_before = dict(vars(term)), dict(vars(state))
    obs = b.observe_term(p, volume, term.reads(state))
    force = term.force(obs, state)
    assert vars(term).keys() == before.keys() and vars(state).keys() == state_before.keys()
    assert all(vars(term)[name] is value for name, value in before.items())
    assert all(vars(state)[name] is value for name, value in state_before.items())
    c_in, c_out = force.grey_means
    assert nanmedian(c_in) == pytest.approx(C_IN, abs=1.0) and nanmedian(c_out) == pytest.approx(C_OUT, abs=1.0)


def test_global_means_of_the_wrong_polarity_leave_the_surface(two_regions):
    """Bright blood in dark tissue: Chan-Vese's global force would move the
    wall to enclose the bright region; the blood-dark model does not move."""
    volume, _, _, _, _ = two_regions
    flipped = Volume(C_IN + C_OUT - volume.array)
    apex, base = np.array([50.0, 50.0, 15.0]), np.array([50.0, 50.0, 85.0])
    r = segment(flipped, apex, base, radius_ratio=0.4 * 0.8, mode="chan-vese")
    assert r.quality["volume_ratio"] == pytest.approx(1.0, abs=1e-3)  # to the initial shape's
    assert r.c_in > r.c_out and r.quality["poor"]  # reported: no contrast


def test_local_means_are_the_band_values_and_respect_polarity(two_regions):
    volume, model, p, inner, p_inner = two_regions
    b = NumpyBackend(model)
    term = LocalMeans()
    state = term.start(np.array([C_IN, C_OUT]), band=8.0)
    c_in, c_out, scale = term.force(b.observe_term(p, volume, term.reads(state)), state)[1:4]
    # on the interface: blood in the inner band, tissue in the outer one
    assert np.median(c_in) == pytest.approx(C_IN, abs=1.0) and np.median(c_out) == pytest.approx(C_OUT, abs=1.0)
    assert scale == pytest.approx(np.median(c_out - c_in) ** 2)
    # 4 mm inside: the outer band (2 to 8 mm) is part blood, so its mean lies between
    b = NumpyBackend(inner)
    c_in, c_out = b.observe_term(p_inner, volume, term.reads(state)).band_means
    assert np.median(c_in) == pytest.approx(C_IN, abs=1.0) and C_IN + 20 < np.median(c_out) < C_OUT - 20
    # inside brighter than outside: no contrast, no force, the least scale
    b = NumpyBackend(model)
    flipped = Volume(C_IN + C_OUT - volume.array)
    c_in, c_out, scale = term.force(b.observe_term(p, flipped, term.reads(state)), state)[1:4]
    np.testing.assert_allclose(c_out, c_in)
    assert scale == state.min_scale


@pytest.mark.parametrize("backend", ["numpy", "auto"])
def test_a_bright_inside_is_the_dark_inside_reflected(two_regions, backend):
    """``polarity = -1`` (a bright wall inside) on the grey levels ``-u``
    against ``polarity = +1`` on ``u``: the force's means and the measured
    means negated, the same scale; with ``boundary_nepers`` the level
    between its means is the half-way intensity of the band means.  (``-u``,
    not ``L - u``: the band means' smoothing does not reproduce a constant
    exactly.)"""
    volume, model, p, _, _ = two_regions
    b = NumpyBackend(model) if backend == "numpy" else select_backend(model)
    flipped = Volume(-volume.array)
    bright, dark = LocalMeans(polarity=-1.0), LocalMeans()
    state = dark.start(np.array([C_IN, C_OUT]), band=8.0)
    wall = bright.force(b.observe_term(p, flipped, bright.reads(state)), state)
    cavity = dark.force(b.observe_term(p, volume, dark.reads(state)), state)
    for a, c in [(wall.c_in, cavity.c_in), (wall.c_out, cavity.c_out), *zip(wall.grey_means, cavity.grey_means)]:
        np.testing.assert_allclose(a, -c, rtol=1e-12)
    assert wall.scale == pytest.approx(cavity.scale, rel=1e-12) and np.median(wall.c_in) > np.median(wall.c_out)
    k = 15.0
    bright = LocalMeans(polarity=-1.0, boundary_nepers=k)
    force = bright.force(b.observe_term(p, flipped, bright.reads(state)), state)
    c_in, c_out = force.grey_means
    middle = (force.c_in + force.c_out) / 2
    np.testing.assert_allclose(np.exp(middle / k), (np.exp(c_in / k) + np.exp(c_out / k)) / 2, rtol=1e-9)
    np.testing.assert_allclose(force.c_in - force.c_out, c_in - c_out, rtol=1e-12)


def test_fixed_interface_levels():
    samples = np.concatenate([np.full(50, C_IN), np.full(50, C_OUT)])
    assert FixedInterface().start(samples).levels[:2] == (C_IN, C_OUT)
    assert otsu_threshold(samples) == pytest.approx(70.0)
    given = FixedInterface(interface=60.0)
    state = given.start(samples)
    assert state.levels[:2] == (10.0, 110.0)  # the class means' half gap about the given level
    obs = type("Obs", (), {"u": np.zeros(3)})()
    assert given.force(obs, state)[1:5] == (10.0, 110.0, 100.0**2, 1.0)


def test_modes_map_to_one_class_each():
    assert DATA_TERMS == {"intensity": IntensityInterface, "local": LocalMeans, "chan-vese": GlobalMeans,
                          "fast": FixedInterface}
    state = LocalMeans().start(np.arange(10.0), band=8.0)
    assert LocalMeans().reads(state).band_offsets.tolist() == [2.0, 4.0, 6.0, 8.0]
    assert GlobalMeans().reads(state).band_offsets is None and GlobalMeans().reads(state).shell_offsets is not None


def test_a_term_is_its_parameters():
    """Rule 1 of the protocol: equal parameters, equal terms (the stepper
    keys their states by them); a parameter out of its range is refused."""
    assert LocalMeans(polarity=-1.0, boundary_nepers=12.0) == LocalMeans(polarity=-1, boundary_nepers=12.0)
    assert LocalMeans(polarity=-1.0) != LocalMeans() and IntensityInterface() != LocalMeans()
    assert len({LocalMeans(), LocalMeans(), GlobalMeans(), FixedInterface(interface=3.0)}) == 3
    assert repr(LocalMeans(polarity=-1.0)) == "LocalMeans(polarity=-1.0, boundary_nepers=inf)"
    with pytest.raises(ValueError, match="polarity must be 1"):
        LocalMeans(polarity=0.5)
    with pytest.raises(ValueError, match="boundary_nepers must be positive"):
        LocalMeans(boundary_nepers=0.0)


@pytest.mark.parametrize("dynamic_range_db", [40.0, 70.0])
def test_log_compression_is_estimated_from_speckle(dynamic_range_db):
    """Grey levels a + k ln I of exponential intensities (fully developed
    speckle): the spread across rays gives k, whatever the regions' means."""
    rng = np.random.default_rng(1)
    k = 2550 / (dynamic_range_db * np.log(10))  # grey levels per neper: 255 levels over the dynamic range
    patch = np.repeat(np.arange(64), 16)
    mean_db = rng.uniform(-30, 0, size=(64, 1)).repeat(16, axis=0)  # each patch its own echogenicity
    grey = 200 + k * (np.log(rng.exponential(size=(len(patch), 4))) + mean_db / 10 * np.log(10))
    assert speckle_nepers(grey, patch) == pytest.approx(k, rel=0.05)
    with pytest.raises(ValueError, match="no speckle"):
        speckle_nepers(np.full((len(patch), 4), 100.0), patch)


def test_the_wall_blur_is_removed_only_from_speckle_as_formed(two_regions):
    """The interface's levels lose the blurred edge's deficits along the
    surface's normals (here a blur of 1.5 mm along every axis); not when the
    speckle was smoothed by a scanner (its correlation is not the
    point-spread function's), nor without a blur read (beam space)."""
    volume, model, p_on, _, _ = two_regions
    obs = NumpyBackend(model).observe(p_on, volume)
    term = IntensityInterface()
    state = replace(term.start(np.array([C_IN, C_OUT])), nepers=10.0, edge_blur_covariance=1.5**2 * np.eye(3))
    c_in, c_out = np.full(model.n_samples, C_IN), np.full(model.n_samples, C_OUT)
    deficit_in, deficit_out = band_contamination(1.5, (C_OUT - C_IN) / 10.0, state.band_offsets)
    deficit_in, deficit_out = band_contamination(1.5, (C_OUT - C_IN) / 10.0 - (deficit_out.mean() - deficit_in),
                                                 state.band_offsets)
    levels = term.unblurred_levels(state, obs, c_in, c_out)
    np.testing.assert_allclose(levels[0], C_IN - 10.0 * deficit_in)
    np.testing.assert_allclose(levels[1], C_OUT - 10.0 * deficit_out.mean())
    np.testing.assert_allclose(levels[2], 10.0 * deficit_out)  # grey levels at each of the outer band's offsets
    assert levels[1][0] > C_OUT + 1.0  # the outer band read the wall's level a grey level low or more
    assert levels[3] == 1.5  # the blur removed
    for smoothing_mm, covariance in ((FORMED_SPECKLE_SMOOTHING_MM, state.edge_blur_covariance), (0.0, None)):
        changed = replace(state, smoothing_mm=smoothing_mm, edge_blur_covariance=covariance)
        same_in, same_out, none, blur = term.unblurred_levels(changed, obs, c_in, c_out)
        assert same_in is c_in and same_out is c_out and np.array_equal(none, np.zeros(4)) and blur == 0


def test_the_interface_reads_the_wall_not_the_tissue_beyond_a_thin_dark_wall(monkeypatch):
    """A phantom whose myocardium is 5 dB darker than the tissue around the
    heart (``contrast_low``; its apical wall 4-5 mm thick along the normal,
    the outer band reaching 8 mm): the interface takes what the band's far
    half read beyond the wall off the myocardium's level, and the volume is
    within 5 %.  Taken as the wall's level, that tissue moves the wall out
    (over 8 %) and the checks flag it, as they do where only part of the
    band's rise was taken off."""
    from spheroseg.descent import dataterms
    from spheroseg.tracking.epicardium import DARK_WALL
    from spheroseg.synthetic.phantom import FORMATIONS, make_phantom

    ph = make_phantom(seed=0, spacing=1.5, formation=FORMATIONS["contrast_low"])
    result = segment(ph.volume, ph.apex, ph.base)
    assert abs(result.volume_ml / ph.truth_volume_ml - 1) < 0.05
    assert result.quality["beyond_wall"] > 0 > result.quality["wall_contrast"]
    assert DARK_WALL not in result.quality["warnings"]
    monkeypatch.setattr(dataterms, "beyond_wall_excess", lambda profile: (0.0, 0.0))
    read_beyond = segment(ph.volume, ph.apex, ph.base)
    assert read_beyond.volume_ml / ph.truth_volume_ml - 1 > 0.08
    assert read_beyond.quality["beyond_wall"] == 0.0 and DARK_WALL in read_beyond.quality["warnings"]
    monkeypatch.setattr(dataterms, "beyond_wall_excess", lambda profile: (2.0, 0.5))  # part of a rise taken
    partly = segment(ph.volume, ph.apex, ph.base)
    assert partly.quality["beyond_wall_fraction"] == 0.5 and DARK_WALL in partly.quality["warnings"]


def speckle_cavity(spread_mm, seed=0):
    """Blood in an ellipsoidal cavity, tissue around it, 1 mm voxels: complex
    scatterers (intensity 30 dB apart) convolved with a Gaussian point-spread
    function, envelope, log compression over 50 dB to 8 bits."""
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    shape = (90, 80, 80)
    k, j, i = np.mgrid[:shape[0], :shape[1], :shape[2]].astype(float)
    centre, axes = np.array([40.0, 40.0, 55.0]), np.array([24.0, 24.0, 40.0])  # x, y, z; z the long axis
    inside = ((i - centre[0]) / axes[0]) ** 2 + ((j - centre[1]) / axes[1]) ** 2 + ((k - centre[2]) / axes[2]) ** 2 <= 1
    inside &= k <= centre[2]  # closed at the plane z = 55, the base
    amplitude = np.where(inside, 10 ** (-30 / 20), 1.0)
    field = amplitude * (rng.standard_normal(shape) + 1j * rng.standard_normal(shape))
    sigma = (0.5, spread_mm, spread_mm)  # axial along z (the probe is at z = 0), lateral wider
    field = ndimage.gaussian_filter(field.real, sigma) + 1j * ndimage.gaussian_filter(field.imag, sigma)
    db = 20 * np.log10(np.abs(field) / np.abs(field[~inside]).mean() + 1e-12)
    grey = np.clip((db + 45) / 50 * 255, 0, 255).round()
    truth_ml = 2 / 3 * np.pi * axes[0] * axes[1] * axes[2] / 1000
    apex, base = centre - [0, 0, axes[2]], centre
    return Volume(grey), apex, base, truth_ml


@pytest.mark.parametrize("spread_mm, local_below, unblurred_below", [(1.0, -0.10, None), (2.0, -0.20, -0.04)])
def test_intensity_interface_puts_the_wall_at_the_interface(spread_mm, local_below, unblurred_below):
    """On a speckle image with a point-spread function (sigma 1 and 2 mm
    across the beam), log-domain local means put the wall inside the cavity
    (volume 12 and 25 % low); the intensity interface puts it at the
    interface (within 1 and 2 %).  Its levels are read where the local
    means left the wall, which a wide PSF leaves far inside, so that the
    outer band's near offsets are still in the blurred edge: without the
    deficit the speckle's correlation predicts, the 2 mm spread's volume is
    5 % low (the 1 mm spread's deficit is negligible)."""
    volume, apex, base, truth_ml = speckle_cavity(spread_mm)
    errors = {mode: segment(volume, apex, base, mode=mode, check=False).volume_ml / truth_ml - 1
              for mode in ("local", "intensity")}
    assert errors["local"] < local_below, errors
    assert abs(errors["intensity"]) < 0.03, errors
    if unblurred_below is None:  # a 1 mm spread's deficit is under 0.1 % of the volume
        return
    blur = IntensityInterface.estimate_blur
    IntensityInterface.estimate_blur = staticmethod(lambda samples: (blur(samples)[0], None))
    try:
        errors["unblurred"] = segment(volume, apex, base, check=False).volume_ml / truth_ml - 1
    finally:
        IntensityInterface.estimate_blur = staticmethod(blur)
    assert errors["unblurred"] < unblurred_below, errors


def white_speckle_cavity(blur_mm, seed=0):
    """The cavity of :func:`speckle_cavity` made otherwise: its intensity
    (blood 30 dB below tissue) blurred by an isotropic Gaussian, times
    speckle independent from voxel to voxel, log-compressed at 15 grey
    levels per neper.  Its speckle does not show the blur."""
    from spheroseg.synthetic.echo import multiplicative_speckle

    shape = (90, 80, 80)
    k, j, i = np.mgrid[:shape[0], :shape[1], :shape[2]].astype(float)
    centre, axes = np.array([40.0, 40.0, 55.0]), np.array([24.0, 24.0, 40.0])
    inside = ((i - centre[0]) / axes[0]) ** 2 + ((j - centre[1]) / axes[1]) ** 2 + ((k - centre[2]) / axes[2]) ** 2 <= 1
    inside &= k <= centre[2]
    grey = multiplicative_speckle(np.where(inside, 1e-3, 1.0), blur_mm=blur_mm, spacing=1.0, seed=seed)
    truth_ml = 2 / 3 * np.pi * axes[0] * axes[1] * axes[2] / 1000
    return Volume(grey), centre - [0, 0, axes[2]], centre, truth_ml


def test_a_blur_the_speckle_does_not_show_is_read_from_the_band(monkeypatch):
    """Speckle independent from voxel to voxel under an intensity blurred by
    1.5 mm: its correlation reads no blur, but the outer band's profile
    still rises as the blurred edge's does, and the blur it shows is
    removed from the band means (volume within 4 %).  Read from the
    speckle alone, the outer band's near offsets lie in the blurred edge
    and the wall goes in (over 6 % low)."""
    from spheroseg.descent import dataterms

    volume, apex, base, truth_ml = white_speckle_cavity(1.5)
    error = segment(volume, apex, base, check=False).volume_ml / truth_ml - 1
    assert abs(error) < 0.04, error
    monkeypatch.setattr(dataterms, "profile_blur_mm", lambda profile, *, sigma_mm, **_: sigma_mm)
    speckle_only = segment(volume, apex, base, check=False).volume_ml / truth_ml - 1
    assert speckle_only < -0.06, speckle_only


def test_the_interface_reads_the_bands_only_until_its_means_are_frozen(two_regions):
    volume, model, p_on, _, _ = two_regions
    backend = NumpyBackend(model)
    term = IntensityInterface()
    state = replace(term.start(np.array([C_IN, C_OUT])), nepers=10.0)  # not speckle: k given
    assert term.reads(state).band_offsets is not None and term.loop_kind(state) is None
    obs = backend.observe_term(p_on, volume, term.reads(state))
    with pytest.raises(RuntimeError, match="freeze"):  # its levels come from band means, set by its stage
        term.force(obs, state)
    reads = term.freeze_reads(state)
    assert not reads["estimates"]  # k known: no voxel-centre samples
    frozen = term.freeze(state, obs, *obs.band_means, freeze_samples(backend, volume, obs, reads))
    assert state.levels is None  # the state given is left as it was (rule 5: freeze is pure)
    force = term.force(obs, frozen)
    assert term.reads(frozen).band_offsets is None and term.loop_kind(frozen) == "fixed"
    obs = backend.observe_term(p_on, volume, term.reads(frozen))  # no bands: the frozen means are used
    assert obs.inside is None and obs.band_means is None and term.force(obs, frozen)[1:5] == force[1:5]
    assert term.reset(frozen).levels is None and term.reset(frozen).nepers == 10.0


def test_offsets_are_fresh_arrays():
    """The cached offsets are linspace's, and a caller changing its copy
    changes no other's."""
    np.testing.assert_array_equal(band_offsets(8.0), np.linspace(0, 8.0, 5)[1:])
    np.testing.assert_array_equal(shell_offsets(15.0), np.linspace(0, 15.0, 6)[1:])
    changed = band_offsets(8.0)
    changed *= -1
    np.testing.assert_array_equal(band_offsets(8), np.linspace(0, 8.0, 5)[1:])


def test_a_smoothed_phantom_keeps_its_volume():
    """The default formation's export smoothed by a Gaussian of 2 mm: the
    speckle's spread falls to a third; held by the contrast bound alone,
    the edge's level fell with the smoothing and the volume came out
    +6.6 %; with the smoothing estimated from the speckle's correlation
    (1.9 mm) and the edge's level lowered by as much, +1.4 %."""
    from spheroseg.synthetic.echo import PostProcessing
    from spheroseg.synthetic.phantom import FORMATIONS, make_phantom

    ph = make_phantom(seed=0, formation=FORMATIONS["default"], postprocessing=PostProcessing(gaussian_mm=2.0))
    r = segment(ph.volume, ph.apex, ph.base)
    assert abs(r.volume_ml / ph.truth_volume_ml - 1) < 0.03
