"""The compiled beam-space kernels against BeamVolume.sample and the numpy backend."""


import numpy as np
import pytest

from spheroseg import _beam_kernels
from spheroseg.backends import CompiledBackend, NumpyBackend
from spheroseg.beamspace import to_beam_space
from spheroseg.energy import SampledSurface
from spheroseg.phantom import make_phantom, probe_sector
from spheroseg.surface import Surface

pytestmark = pytest.mark.skipif(not _beam_kernels.AVAILABLE, reason="numba not installed")


@pytest.fixture(scope="module", params=[("tan", 0.0), ("sin", 10.0)])
def case(request):
    convention, tilt = request.param
    ph = make_phantom(seed=5, spacing=1.5)
    beam = to_beam_space(ph.volume, probe_sector(ph.volume, convention=convention, tilt_deg=tilt))
    s = Surface.from_apex_base(ph.apex, ph.base, patches=(4, 6))
    model = SampledSurface(s.system, s.pose, s.grid, 6)
    rng = np.random.default_rng(0)
    p = model.parameters(s.coefficients) + 0.02 * rng.standard_normal(model.n_parameters)
    return beam, model, p


def test_samples_match_beam_volume_sample_including_no_data(case):
    beam, model, p = case
    g = model.geometry(p)
    rng = np.random.default_rng(2)
    world = (g.world + rng.normal(0, 40, g.world.shape)).T.copy()  # some behind the probe, off the sector
    normal = g.normal.T.copy()
    offsets = np.array([-4.0, 0.0, 3.0])
    rows = np.arange(model.n_samples)
    mean, count = np.empty(len(rows)), np.empty(len(rows), np.int64)
    _beam_kernels.sample_along(*beam.sampling_view(), world, normal, rows, offsets, 0.0, mean, count)
    samples = beam.sample(world.T[:, None, :] + offsets[None, :, None] * normal.T[:, None, :])
    ok = np.isfinite(samples)
    assert 0 < (count == 0).sum() and (count == 3).sum() > 0  # both cases reached
    np.testing.assert_array_equal(count, ok.sum(axis=1))
    expected = np.where(ok, samples, 0).sum(axis=1) / np.maximum(ok.sum(axis=1), 1)
    np.testing.assert_allclose(mean[count > 0], expected[count > 0], rtol=1e-9, atol=1e-9)
    assert np.isnan(mean[count == 0]).all()
    # log compression undone: exp(a v) of each sample
    a = 0.02
    _beam_kernels.sample_along(*beam.sampling_view(), world, normal, rows, offsets, a, mean, count)
    expected = np.where(ok, np.exp(a * np.nan_to_num(samples)), 0).sum(axis=1) / np.maximum(ok.sum(axis=1), 1)
    np.testing.assert_allclose(mean[count > 0], expected[count > 0], rtol=1e-9)


def test_compiled_backend_samples_beam_space_as_the_numpy_backend(case):
    beam, model, p = case
    numpy_backend, compiled = NumpyBackend(model), CompiledBackend(model)
    offsets = np.array([2.0, 4.0])
    ref = numpy_backend.observe(p, beam, band_offsets=offsets)
    obs = compiled.observe(p, beam, band_offsets=offsets)
    assert np.isfinite(ref.u).mean() > 0.9
    for name in ("u", "inside", "outside"):
        np.testing.assert_allclose(getattr(obs, name), getattr(ref, name), rtol=1e-7, atol=1e-7, err_msg=name)
    rows = np.arange(0, model.n_samples, 3)
    fractions = np.linspace(0.05, 0.95, 7)
    total, weight = compiled.cavity_sums(beam, obs, fractions, rows)
    ref_total, ref_weight = numpy_backend.cavity_sums(beam, ref, fractions, rows)
    assert (ref_weight > 0).mean() > 0.9
    np.testing.assert_allclose(total, ref_total, rtol=1e-7)
    np.testing.assert_allclose(weight, ref_weight, rtol=1e-9)
