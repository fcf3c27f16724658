"""The compiled kernels against the numpy code they replace."""

import numpy as np
import pytest

from spheroseg.descent.backends import MIN_COS, CompiledBackend, NumpyBackend, Observation
from spheroseg.volumes.beamspace import to_beam_space
from spheroseg.geometry.discretisation import discretise
from spheroseg.geometry.energy import SampledSurface
from spheroseg.synthetic.phantom import make_phantom, probe_sector
from spheroseg.surfaces.surface import Surface

# not built (a source tree on PYTHONPATH): nothing to test here; that an
# installed package has them is tests/test_warmup.py's
_kernels = pytest.importorskip("spheroseg._compiled._kernels", reason="the compiled kernels are not built")



def read_only(rows):
    """A row index read-only, as a segmentation's band rows: the kernels
    take both."""
    rows.flags.writeable = False
    return rows

@pytest.fixture(scope="module")
def case():
    ph = make_phantom(seed=5, spacing=1.5)
    s = Surface.from_apex_base(ph.apex, ph.base, patches=(4, 6))
    model = SampledSurface(s.system, s.pose, s.grid, 6)
    rng = np.random.default_rng(0)
    p = model.parameters(s.coefficients) + 0.02 * rng.standard_normal(model.n_parameters)
    return ph, model, p, discretise(s.grid, 6)


def test_gather_and_scatter_are_the_basis_matrix_and_its_transpose(case):
    _, model, p, level = case
    rng = np.random.default_rng(1)
    fields = np.stack([p, rng.standard_normal(len(p))])
    coefficients = np.stack([(model.constraints @ f).reshape(model.grid.shape) for f in fields])
    out = np.empty((2, model.n_samples))
    _kernels.gather(coefficients, model.order, *level.tables, out)
    np.testing.assert_allclose(out, (model.b_f @ fields.T).T, atol=1e-12)

    values = rng.standard_normal((2, model.n_samples))
    back = np.empty((2,) + model.grid.shape)
    _kernels.scatter(values, model.order, *level.tables, back)
    expected = model.grid.basis_matrix(model.v1, model.v2).T @ values.T
    np.testing.assert_allclose(back.reshape(2, -1).T, expected, atol=1e-12)
    # on the band rows: every other position of a patch, with the band tables
    rows = level.band_rows
    band = values[:, rows]
    _kernels.scatter(band, level.band_tables[0].shape[1], *level.band_tables, back)
    expected = model.grid.basis_matrix(model.v1[rows], model.v2[rows]).T @ band.T
    np.testing.assert_allclose(back.reshape(2, -1).T, expected, atol=1e-12)


def test_csr_product_equals_scipy_to_the_last_bit(case):
    # the constraint matrices and their transposes, and a random CSR matrix
    import scipy.sparse

    _, model, p, level = case
    rng = np.random.default_rng(2)
    random = scipy.sparse.random(120, 90, density=0.05, random_state=3, format="csr")
    for matrix in (level.constraints, level.constraints_t, random):
        for _ in range(20):
            x = rng.standard_normal(matrix.shape[1])
            out = np.empty(matrix.shape[0])
            _kernels.csr_product(matrix.indptr, matrix.indices, matrix.data, x, out)
            np.testing.assert_array_equal(out, matrix @ x)


def test_surface_kernel_matches_geometry(case):
    _, model, p, level = case
    n = model.n_samples
    out = [np.empty(n) for _ in range(4)] + [np.empty((3, n)), np.empty((3, n))]
    _kernels.prolate_surface((model.constraints @ p).reshape(model.grid.shape), model.order, *level.tables,
                             *level.trig, model.system.focal_length, model.pose.rotation, model.pose.origin, *out)
    f, h0, cos, area, world, normal = out
    g = model.geometry(p)
    np.testing.assert_allclose(f, g.f, atol=1e-12)
    np.testing.assert_allclose(h0, model.system.scale_factors(g.f, model.v1, model.v2)[0], rtol=1e-12)
    np.testing.assert_allclose(area, g.area, rtol=1e-10)
    np.testing.assert_allclose(world, g.world.T, atol=1e-9)
    np.testing.assert_allclose(normal, g.normal.T, atol=1e-10)
    expected_cos = np.einsum("ij,ij->i", g.normal @ model.pose.rotation, g.jacobian[:, :, 0]) / h0
    np.testing.assert_allclose(cos, expected_cos, atol=1e-10)


def scattered_points(model, p, seed):
    """The surface's points moved up to far off it (some out of the sector
    and out of the image), with its normals: ``(3, n)`` each, as the kernels read them."""
    g = model.geometry(p)
    world = (g.world + np.random.default_rng(seed).normal(0, 30, g.world.shape)).T.copy()
    return world, g.normal.T.copy()


@pytest.mark.parametrize("offsets", [[-4.0, 0.0, 3.0], [2.5]], ids=["band", "one offset"])
def test_samples_match_volume_sample_including_no_data(case, offsets):
    """Several offsets a row, and one (the surface's samples: a loop of its own)."""
    ph, model, p, level = case
    vol = ph.volume
    world, normal = scattered_points(model, p, 2)
    offsets = np.array(offsets)
    rows = read_only(np.arange(model.n_samples))
    mean, count = np.empty(len(rows)), np.empty(len(rows), np.int64)
    _kernels.sample_along(*_kernels.sampler(vol.sampling_view()), world, normal, rows, offsets, 0.0, mean, count)
    samples = vol.sample(world.T[:, None, :] + offsets[None, :, None] * normal.T[:, None, :])
    ok = np.isfinite(samples)
    assert 0 < (count == 0).sum() and (count == len(offsets)).sum() > 0  # the test reaches both cases
    np.testing.assert_array_equal(count, ok.sum(axis=1))
    with np.errstate(invalid="ignore"):
        expected = np.nansum(samples, axis=1) / ok.sum(axis=1)
    np.testing.assert_allclose(mean, expected, rtol=1e-9, atol=1e-9)
    # with log compression undone: the mean of exp(a v), not exp of the mean
    _kernels.sample_along(*_kernels.sampler(vol.sampling_view()), world, normal, rows, offsets, 0.05, mean, count)
    with np.errstate(invalid="ignore"):
        expected = np.nansum(np.exp(0.05 * samples), axis=1) / ok.sum(axis=1)
    np.testing.assert_allclose(mean, expected, rtol=1e-9, atol=1e-9)


def test_samples_at_are_volume_sample_nearest_and_trilinear(case):
    """The raw samples along normals against Volume.sample: the nearest voxel
    to the last bit (the speckle estimate reads them), trilinear to rounding."""
    ph, model, p, _ = case
    vol = ph.volume
    world, normal = scattered_points(model, p, 5)
    offsets = np.array([-4.0, 0.0, 0.5, 3.0])
    rows = read_only(np.arange(0, model.n_samples, 3))
    points = world.T[rows, None, :] + offsets[None, :, None] * normal.T[rows, None, :]
    for order in (0, 1):
        out = np.empty((len(rows), len(offsets)))
        _kernels.samples_at(*_kernels.sampler(vol.sampling_view()), world, normal, rows, offsets, order == 0, out)
        expected = vol.sample(points, order=order)
        assert 0 < np.isnan(expected).sum() < expected.size  # on and off the data
        np.testing.assert_array_equal(np.isnan(out), np.isnan(expected))
        if order == 0:
            np.testing.assert_array_equal(out, expected)
        else:
            np.testing.assert_allclose(out, expected, rtol=1e-12, atol=1e-9)


def test_normal_displacement_matches_the_numpy_backend(case):
    """The kernel against NumpyBackend.displacement (through energy.normal_speed)."""
    _, model, _, _ = case
    rng = np.random.default_rng(3)
    n = model.n_samples
    u = rng.uniform(0, 100, n)
    u[:10] = np.nan  # off the data
    c_in, c_out = rng.uniform(0, 40, n), rng.uniform(40, 100, n)
    h0, cos = rng.uniform(5, 50, n), rng.uniform(-1, 1, n)
    obs = Observation(f=None, h0=h0, cos=cos, area=None, world=None, normal=None, u=u)
    out = np.empty(n)
    _kernels.normal_displacement(u, c_in, c_out, 300.0, 1.0, h0, cos, 8.0, MIN_COS, 1.5, model.weights, out)
    expected = NumpyBackend(model).displacement(obs, c_in, c_out, 300.0, step=1.5, h0_floor=8.0)
    np.testing.assert_allclose(out, expected, rtol=1e-12)
    wide = np.empty(n)
    _kernels.normal_displacement(u, c_in, c_out, 300.0, 3.0, h0, cos, 8.0, MIN_COS, 1.5, model.weights, wide)
    np.testing.assert_allclose(wide, NumpyBackend(model).displacement(obs, c_in, c_out, 300.0, step=1.5, h0_floor=8.0,
                                                                      clip=3.0), rtol=1e-12)
    assert np.abs(wide).max() > np.abs(out).max()
    # and by hand: off the data pulled in by a whole step, the rest clipped
    r = (c_out - c_in) * (2 * u - c_in - c_out) / 300.0
    speed = np.where(np.isfinite(r), -np.clip(r, -1, 1), -1.0)
    np.testing.assert_allclose(out, model.weights * 1.5 * speed / np.maximum(h0 * np.maximum(cos, 0.3), 8.0),
                               rtol=1e-12)


# beam space: the same kernels, the sampler picked by the image arguments (_kernels.sampler)


@pytest.fixture(scope="module", params=[("tan", 0.0), ("sin", 10.0)])
def beam_case(request):
    convention, tilt = request.param
    ph = make_phantom(seed=5, spacing=1.5)
    beam = to_beam_space(ph.volume, probe_sector(ph.volume, convention=convention, tilt_deg=tilt))
    s = Surface.from_apex_base(ph.apex, ph.base, patches=(4, 6))
    model = SampledSurface(s.system, s.pose, s.grid, 6)
    rng = np.random.default_rng(0)
    p = model.parameters(s.coefficients) + 0.02 * rng.standard_normal(model.n_parameters)
    return beam, model, p


def test_beam_space_samples_match_beam_volume_sample_including_no_data(beam_case):
    beam, model, p = beam_case
    g = model.geometry(p)
    rng = np.random.default_rng(2)
    world = (g.world + rng.normal(0, 40, g.world.shape)).T.copy()  # some behind the probe, off the sector
    normal = g.normal.T.copy()
    offsets = np.array([-4.0, 0.0, 3.0])
    rows = read_only(np.arange(model.n_samples))
    mean, count = np.empty(len(rows)), np.empty(len(rows), np.int64)
    _kernels.sample_along(*_kernels.sampler(beam.sampling_view()), world, normal, rows, offsets, 0.0, mean, count)
    samples = beam.sample(world.T[:, None, :] + offsets[None, :, None] * normal.T[:, None, :])
    ok = np.isfinite(samples)
    assert 0 < (count == 0).sum() and (count == 3).sum() > 0  # both cases reached
    np.testing.assert_array_equal(count, ok.sum(axis=1))
    expected = np.where(ok, samples, 0).sum(axis=1) / np.maximum(ok.sum(axis=1), 1)
    np.testing.assert_allclose(mean[count > 0], expected[count > 0], rtol=1e-9, atol=1e-9)
    assert np.isnan(mean[count == 0]).all()
    # log compression undone: exp(a v) of each sample
    a = 0.02
    _kernels.sample_along(*_kernels.sampler(beam.sampling_view()), world, normal, rows, offsets, a, mean, count)
    expected = np.where(ok, np.exp(a * np.nan_to_num(samples)), 0).sum(axis=1) / np.maximum(ok.sum(axis=1), 1)
    np.testing.assert_allclose(mean[count > 0], expected[count > 0], rtol=1e-9)


def test_compiled_backend_samples_beam_space_as_the_numpy_backend(beam_case):
    beam, model, p = beam_case
    numpy_backend, compiled = NumpyBackend(model), CompiledBackend(model)
    offsets = np.array([2.0, 4.0])
    ref = numpy_backend.observe(p, beam, band_offsets=offsets)
    obs = compiled.observe(p, beam, band_offsets=offsets)
    assert np.isfinite(ref.u).mean() > 0.9
    for name in ("u", "inside", "outside"):
        np.testing.assert_allclose(getattr(obs, name), getattr(ref, name), rtol=1e-7, atol=1e-7, err_msg=name)
    rows = read_only(np.arange(0, model.n_samples, 3))
    fractions = np.linspace(0.05, 0.95, 7)
    total, weight = compiled.cavity_sums(beam, obs, fractions, rows)
    ref_total, ref_weight = numpy_backend.cavity_sums(beam, ref, fractions, rows)
    assert (ref_weight > 0).mean() > 0.9
    np.testing.assert_allclose(total, ref_total, rtol=1e-7)
    np.testing.assert_allclose(weight, ref_weight, rtol=1e-9)


def edge_indices(upper, rng, n=400):
    """Continuous indices on and about the faces of a box ``[0, upper]``
    (x, y, z): each coordinate on a face, within the samplers' tolerance
    outside it (``INDEX_TOLERANCE``), just beyond it, or anywhere inside;
    corners and edges included."""
    from spheroseg._compiled import INDEX_TOLERANCE

    upper = np.asarray(upper, float)
    choices = np.array([0.0, 0.5, 2.0])  # on, within the tolerance, beyond: in tolerances
    index = rng.uniform(0, 1, (n, 3)) * upper
    face = rng.integers(0, 3, (n, 3))  # 0: inside, 1: the low face, 2: the high face
    step = choices[rng.integers(0, 3, (n, 3))] * INDEX_TOLERANCE
    index = np.where(face == 1, -step, index)
    index = np.where(face == 2, upper + step, index)
    return index


def test_samples_at_the_faces_of_the_image_are_the_reference(case, rng):
    """Random points on, just inside the tolerance of and just beyond the
    image's faces, edges and corners: NaN where the reference says so, the
    nearest voxel to the last bit and trilinear to 1e-12 relative."""
    ph, _, _, _ = case
    vol = ph.volume
    index = edge_indices(np.array(vol.shape[::-1]) - 1, rng)
    world = np.ascontiguousarray(vol.grid.index_to_world(index).T)
    rows = np.arange(world.shape[1])
    for order in (0, 1):
        out = np.empty((len(rows), 1))
        _kernels.samples_at(*_kernels.sampler(vol.sampling_view()), world, np.zeros_like(world), rows,
                            np.zeros(1), order == 0, out)
        expected = vol.sample(world.T, order=order)
        assert 0 < np.isnan(expected).sum() < 0.9 * expected.size  # on and off the image
        np.testing.assert_array_equal(np.isnan(out[:, 0]), np.isnan(expected))
        if order == 0:
            np.testing.assert_array_equal(out[:, 0], expected)
        else:
            np.testing.assert_allclose(out[:, 0], expected, rtol=1e-12, atol=0)
    mean, count = np.empty(len(rows)), np.empty(len(rows), np.int64)
    _kernels.sample_along(*_kernels.sampler(vol.sampling_view()), world, np.zeros_like(world), rows, np.zeros(1),
                          0.0, mean, count)
    np.testing.assert_array_equal(np.isnan(mean), np.isnan(expected))
    np.testing.assert_allclose(mean, expected, rtol=1e-12, atol=0)


def test_samples_at_the_edges_of_the_sector_are_the_reference(beam_case, rng):
    """Random points on and about the beam-space volume's faces (the
    sector's range and angle ends, corners included): as
    BeamVolume.sample, NaN outside, to 1e-9 relative (the angles' atan)."""
    beam = beam_case[0]
    index = edge_indices(np.array(beam.shape[::-1]) - 1, rng)  # (a, e, r) order is x, y, z of the samples
    world = np.ascontiguousarray(beam.index_to_world(index[:, ::-1]).T)
    rows = np.arange(world.shape[1])
    mean, count = np.empty(len(rows)), np.empty(len(rows), np.int64)
    _kernels.sample_along(*_kernels.sampler(beam.sampling_view()), world, np.zeros_like(world), rows, np.zeros(1),
                          0.0, mean, count)
    expected = beam.sample(world.T)
    assert 0 < np.isnan(expected).sum() < 0.9 * expected.size
    np.testing.assert_array_equal(np.isnan(mean), np.isnan(expected))
    np.testing.assert_allclose(mean, expected, rtol=1e-9, atol=0)
