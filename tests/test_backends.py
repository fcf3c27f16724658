"""The compiled backend against the numpy reference, method by method."""

import numpy as np
import pytest

from spheroseg.descent.backends import CompiledBackend, NumpyBackend, compiled_available, sample_points, select_backend
from spheroseg.geometry.energy import SampledSurface
from spheroseg.synthetic.phantom import make_phantom
from spheroseg.surfaces.surface import Surface

pytestmark = pytest.mark.skipif(not compiled_available(), reason="the compiled kernels are not built")


@pytest.fixture(scope="module")
def case():
    ph = make_phantom(seed=6, spacing=1.5, dropout=True)
    s = Surface.from_apex_base(ph.apex, ph.base, patches=(4, 4))
    model = SampledSurface(s.system, s.pose, s.grid, 8)
    p = model.parameters(s.coefficients) + 0.03 * np.random.default_rng(0).standard_normal(model.n_parameters)
    return ph.volume, model, p


def test_selection():
    ph = make_phantom(seed=6, spacing=3.0)
    for system, name in (("prolate", "compiled"), ("spherical", "numpy"), ("cylindrical", "numpy")):
        s = Surface.from_apex_base(ph.apex, ph.base, system=system, patches=(4, 4))
        model = SampledSurface(s.system, s.pose, s.grid, 8)
        assert select_backend(model).name == name
        assert select_backend(model, compiled=False).name == "numpy"


def test_every_method_agrees(case):
    volume, model, p = case
    ref, fast = NumpyBackend(model), CompiledBackend(model)
    offsets = np.array([2.0, 4.0, 6.0, 8.0])
    o_ref = ref.observe(p, volume, band_offsets=offsets)
    o_fast = fast.observe(p, volume, band_offsets=offsets)
    for name in ("f", "h0", "cos", "area", "world", "normal", "u", "inside", "outside"):
        np.testing.assert_allclose(getattr(o_fast, name), getattr(o_ref, name), rtol=1e-9, atol=1e-9, err_msg=name)
    rows = model.discretisation.band_rows
    # on the compiled observation (equal to the reference's, above): its
    # C-ordered world points are the kernel's signature of a real run
    for a, b in zip(fast.mean_along(volume, o_fast, offsets, rows), ref.mean_along(volume, o_fast, offsets, rows)):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9)
    fractions = np.array([0.2, 0.6, 0.9])
    for a, b in zip(fast.cavity_sums(volume, o_ref, fractions, rows), ref.cavity_sums(volume, o_ref, fractions, rows)):
        np.testing.assert_allclose(a, b, rtol=1e-9)
    fields = np.stack([p, np.cos(np.arange(len(p)))], axis=1)
    np.testing.assert_allclose(fast.gather(p), ref.gather(p), atol=1e-12)
    np.testing.assert_allclose(fast.gather(fields), ref.gather(fields), atol=1e-12)
    values = np.stack([o_ref.f, o_ref.area])
    np.testing.assert_allclose(fast.scatter(values), ref.scatter(values), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(fast.scatter(values[0]), ref.scatter(values[0]), rtol=1e-10, atol=1e-12)
    band = values[:, rows]
    np.testing.assert_allclose(fast.scatter(band, band=True), ref.scatter(band, band=True), rtol=1e-10, atol=1e-12)
    c_in, c_out = np.full(model.n_samples, 30.0), np.linspace(60, 120, model.n_samples)
    np.testing.assert_allclose(fast.displacement(o_ref, c_in, c_out, 900.0, step=1.0, h0_floor=5.0),
                               ref.displacement(o_ref, c_in, c_out, 900.0, step=1.0, h0_floor=5.0), rtol=1e-12)
    np.testing.assert_allclose(fast.displacement(o_ref, 30.0, 90.0, 900.0, step=1.0, h0_floor=5.0),
                               ref.displacement(o_ref, 30.0, 90.0, 900.0, step=1.0, h0_floor=5.0), rtol=1e-12)


def test_geometry_observation_falls_back_to_the_reference(case):
    volume, model, p = case
    obs = CompiledBackend(model).observe(p, volume, geometry=True)
    assert obs.geometry is not None
    np.testing.assert_allclose(obs.f, NumpyBackend(model).observe(p, volume).f)


@pytest.mark.parametrize("order", [0, 1])
def test_sample_points_is_volume_sample(case, order):
    """The compiled sampler at any world points (the image's dropout and
    points off it included: NaN where the reference's are) equals
    Volume.sample, trilinear to rounding and the nearest voxel exactly."""
    volume = case[0]
    lo, hi = volume.index_to_world(np.zeros(3)), volume.index_to_world(np.array(volume.shape[::-1]) - 1.0)
    points = lo - 4 + (hi - lo + 8) * np.random.default_rng(1).random((300, 5, 3))
    fast, ref = sample_points(volume, points, order=order), volume.sample(points, order=order)
    assert fast.shape == (300, 5)
    assert 0.05 < np.isnan(ref).mean() < 0.95  # both kinds of point are there
    np.testing.assert_array_equal(np.isnan(fast), np.isnan(ref))
    np.testing.assert_allclose(fast, ref, rtol=0, atol=0 if order == 0 else 1e-10)

