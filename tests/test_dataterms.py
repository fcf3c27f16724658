"""Data terms against a two-region image whose means are known exactly."""

import numpy as np
import pytest

from spheroseg.backends import NumpyBackend, select_backend
from spheroseg.dataterms import DATA_TERMS, FixedInterface, GlobalMeans, LocalMeans, otsu_threshold
from spheroseg.energy import SampledSurface
from spheroseg.surface import Surface
from spheroseg.volume import Volume

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
    term = GlobalMeans(np.array([C_IN, C_OUT]), band_out=15.0)
    c_in, c_out, scale = term.force(b, volume, b.observe(p, volume))[1:4]
    # the cavity along the rays (to 0.95 f) and the shell 3 to 15 mm outside
    assert c_in == pytest.approx(C_IN, abs=0.5)
    assert c_out == pytest.approx(C_OUT, abs=0.5)
    assert scale == pytest.approx((c_out - c_in) ** 2)


def test_local_means_are_the_band_values_and_respect_polarity(two_regions):
    volume, model, p, inner, p_inner = two_regions
    b = NumpyBackend(model)
    term = LocalMeans(np.array([C_IN, C_OUT]), band=8.0)
    obs = b.observe(p, volume, band_offsets=term.band_offsets)
    _, c_in, c_out, scale, _ = term.force(b, volume, obs)
    # on the interface: blood in the inner band, tissue in the outer one
    assert np.median(c_in) == pytest.approx(C_IN, abs=1.0) and np.median(c_out) == pytest.approx(C_OUT, abs=1.0)
    assert scale == pytest.approx(np.median(c_out - c_in) ** 2)
    # 4 mm inside: the outer band (2 to 8 mm) is part blood, so its mean lies between
    b = NumpyBackend(inner)
    c_in, c_out = term.band_means(b, b.observe(p_inner, volume, band_offsets=term.band_offsets))
    assert np.median(c_in) == pytest.approx(C_IN, abs=1.0) and C_IN + 20 < np.median(c_out) < C_OUT - 20
    # inside brighter than outside: no contrast, no force, the least scale
    b = NumpyBackend(model)
    flipped = Volume(C_IN + C_OUT - volume.array)
    obs = b.observe(p, flipped, band_offsets=term.band_offsets)
    _, c_in, c_out, scale, _ = term.force(b, flipped, obs)
    np.testing.assert_allclose(c_out, c_in)
    assert scale == term.min_scale


def test_fixed_interface_levels():
    samples = np.concatenate([np.full(50, C_IN), np.full(50, C_OUT)])
    term = FixedInterface(samples)
    assert (term.c_in, term.c_out) == (C_IN, C_OUT)
    assert otsu_threshold(samples) == pytest.approx(70.0)
    given = FixedInterface(samples, interface=60.0)
    assert (given.c_in, given.c_out) == (10.0, 110.0)  # the class means' half gap about the given level
    obs = type("Obs", (), {"u": np.zeros(3)})()
    assert given.force(None, None, obs)[1:] == (10.0, 110.0, 100.0**2, 1.0)


def test_modes_map_to_one_class_each():
    assert DATA_TERMS == {"local": LocalMeans, "chan-vese": GlobalMeans, "fast": FixedInterface}
    assert LocalMeans.needs_bands and not GlobalMeans.needs_bands
    assert LocalMeans(np.arange(10.0), band=8.0).band_offsets.tolist() == [2.0, 4.0, 6.0, 8.0]
