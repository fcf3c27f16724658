"""The compiled rasteriser and sector-padding pass against the numpy code
they replace (kept here as the reference), voxel for voxel."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import spheroseg
from spheroseg.geometry.hermite import global_basis
from spheroseg._compiled.raster import block_means
from spheroseg.synthetic.phantom import make_phantom
from spheroseg.surfaces.surface import ImageGrid, Surface
from spheroseg.volumes.volume import outside_sector

# the compiled rasteriser against the reference: nothing to test where it is
# not built (a source tree); that an installed package has it is
# tests/test_warmup.py's
pytest.importorskip("spheroseg._compiled._raster", reason="the compiled kernels are not built")
from spheroseg._compiled._raster import (FRESH_ZEROS_BYTES, SLOPE_MARGIN, SLOPE_SAMPLES,  # noqa: E402
                                         fresh_zeros, gradient_bound, hermite_at, patch_slopes, status)

APEX, BASE = np.array([3.0, -4.0, 85.0]), np.array([0.0, 0.0, 5.0])


def reference_mask(surface: Surface, grid: ImageGrid) -> np.ndarray:
    """Surface.mask before the compiled rasteriser: every voxel centre of the
    bounding box through Surface.contains."""
    out = np.zeros(grid.shape, dtype=bool)
    lo, hi = surface.bounding_box()
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    idx = grid.world_to_index(corners)
    start = np.clip(np.floor(idx.min(0)).astype(int), 0, np.array(grid.shape[::-1]))
    stop = np.clip(np.ceil(idx.max(0)).astype(int) + 1, 0, np.array(grid.shape[::-1]))
    if np.any(stop <= start):
        return out
    k, j, i = np.meshgrid(*(np.arange(a, b) for a, b in zip(start[::-1], stop[::-1])), indexing="ij")
    world = grid.index_to_world(np.stack([i, j, k], axis=-1).reshape(-1, 3))
    out[start[2]:stop[2], start[1]:stop[1], start[0]:stop[0]] = surface.contains(world).reshape(i.shape)
    return out


def reference_padding(array: np.ndarray, *, min_fraction: float = 0.01):
    """outside_sector before the compiled pass: scipy labels of the zeros."""
    from scipy import ndimage

    zero = np.asarray(array) == 0
    if zero.mean() < min_fraction:
        return None
    labels, n = ndimage.label(zero)
    faces = np.concatenate([labels[[0, -1]].ravel(), labels[:, [0, -1]].ravel(), labels[:, :, [0, -1]].ravel()])
    touching = np.unique(faces[faces > 0])
    if touching.size == 0:
        return None
    mask = np.isin(labels, touching)
    return mask if mask.mean() >= min_fraction else None


def bumpy(system, rng, amplitude=0.08, apex=APEX, base=BASE, patches=(8, 8)):
    """An initial surface with random, pole-constrained perturbations."""
    s = Surface.from_apex_base(apex, base, system=system, patches=patches)
    params = s.grid.parameters(s.coefficients)
    return s.with_coefficients(s.grid.constraints @ (params * (1 + amplitude * rng.normal(size=params.shape))))


GRIDS = {
    "isotropic": ImageGrid((100, 70, 70), spacing=(1.0, 1.0, 1.0), origin=(-33.2, -37.7, -2.1)),
    "anisotropic": ImageGrid((60, 95, 80), spacing=(0.8, 0.55, 1.45), origin=(-31.1, -29.7, -1.3)),
    "oblique": ImageGrid((90, 80, 75), spacing=(0.9, 1.1, 1.0), origin=(-20.0, -60.0, 10.0),
                         direction=Rotation.from_euler("zyx", [25, -15, 35], degrees=True).as_matrix()),
}


@pytest.mark.parametrize("grid", list(GRIDS))
@pytest.mark.parametrize("system", ["prolate", "spherical", "cylindrical"])
def test_mask_equals_reference(system, grid, rng):
    g = GRIDS[grid]
    for amplitude in (0.0, 0.1):
        s = bumpy(system, rng, amplitude)
        mask = s.mask(g)
        assert mask.sum() > 1000  # the cavity is on the grid
        np.testing.assert_array_equal(mask, reference_mask(s, g))


@pytest.mark.parametrize("system", ["prolate", "spherical", "cylindrical"])
def test_mask_equals_reference_tilted_and_cropped(system, rng):
    # long axis tilted off every image axis; the grid cuts the cavity
    apex = np.array([30.0, -25.0, 70.0])
    base = np.array([-5.0, 8.0, 4.0])
    g = ImageGrid((70, 66, 50), spacing=(1.2, 0.7, 0.9), origin=(-40.0, -30.0, -5.0),
                  direction=Rotation.from_euler("xyz", [10, 20, -30], degrees=True).as_matrix())
    s = bumpy(system, rng, 0.12, apex=apex, base=base, patches=(4, 6))
    mask = s.mask(g)
    assert 0 < mask.sum() < mask.size
    np.testing.assert_array_equal(mask, reference_mask(s, g))


@pytest.mark.parametrize("system", ["prolate", "spherical", "cylindrical"])
def test_mask_equals_reference_on_the_axis_plane_and_foci(system, rng):
    # apex and base on voxel centres, the long axis along z: whole lines of
    # voxel centres lie on the axis (and, prolate, on the focal segment,
    # where the fast coordinates give way to the exact ones) and a plane of
    # them on the base plane; half-voxel steps put more on the axis
    g = ImageGrid((81, 81, 111), spacing=(0.5, 0.5, 0.75), origin=(-20.0, -20.0, -3.0))
    s = bumpy(system, rng, 0.1, apex=np.array([0.0, 0.0, 75.0]), base=np.array([0.0, 0.0, 0.0]))
    codes = s.mask(g)
    assert codes.sum() > 10000
    np.testing.assert_array_equal(codes, reference_mask(s, g))
    if system == "prolate":
        d = s.system.focal_length
        on_segment = [p for p in g.index_to_world(np.argwhere(codes)[:, ::-1]) if np.hypot(p[0], p[1]) == 0 and p[2] < d]
        assert len(on_segment) > 10  # voxel centres on the focal segment


@pytest.mark.parametrize("seed", range(6))
def test_mask_equals_reference_on_random_surfaces_and_grids(seed):
    # patch counts, bumps, voxel sizes, rotations and offsets drawn at random
    rng = np.random.default_rng(seed)
    system = ["prolate", "spherical", "cylindrical"][seed % 3]
    s = bumpy(system, rng, rng.uniform(0.0, 0.2), apex=rng.uniform(-10, 10, 3) + [0.0, 0.0, 80.0],
              base=rng.uniform(-5, 5, 3), patches=tuple(int(n) for n in rng.integers(3, 9, 2)))
    spacing = rng.uniform(0.8, 1.6, 3)
    g = ImageGrid(tuple(int(n) for n in 110 / spacing[::-1]), spacing=spacing,
                  origin=rng.uniform(-3, 3, 3) + [-40.0, -40.0, -10.0],
                  direction=Rotation.from_euler("xyz", rng.uniform(-30, 30, 3), degrees=True).as_matrix())
    mask = s.mask(g)
    assert mask.sum() > 1000
    np.testing.assert_array_equal(mask, reference_mask(s, g))


@pytest.mark.parametrize("step_at, height", [(0.6, 0.5), (0.9, 0.6), (0.4, 0.7)])
def test_mask_equals_reference_where_the_slope_changes_from_row_to_row(step_at, height):
    # the radius steps up across one row of patches and is flat elsewhere:
    # a ball centred in a flat row must take the steep row's slopes when it
    # reaches it (with the centre row's alone, 11 and 21 voxels differ)
    s = Surface.from_apex_base(np.array([0.0, 0.0, 80.0]), np.zeros(3), patches=(8, 8))
    coefficients = np.zeros(s.grid.shape)
    coefficients[:, :, 0] = (0.45 + height * (s.grid.node_v2 > step_at))[:, None]
    s = s.with_coefficients(s.grid.constrain(coefficients))
    g = ImageGrid((90, 90, 100), spacing=(0.9, 0.9, 0.9), origin=(-40.0, -40.0, -5.0))
    np.testing.assert_array_equal(s.mask(g), reference_mask(s, g))


@pytest.mark.parametrize("system", ["prolate", "spherical", "cylindrical"])
@pytest.mark.parametrize("column, height", [(3, 0.5), (7, 0.7), (0, 0.4)])
def test_mask_equals_reference_where_the_slope_changes_around_the_axis(system, column, height):
    # the radius steps up across one column of patches around the axis (at
    # the seam v1 = 0 for the last) and is flat elsewhere: a ball centred in
    # a flat patch must take the steep patch's slopes when it reaches it
    s = Surface.from_apex_base(np.array([0.0, 0.0, 80.0]), np.zeros(3), system=system, patches=(8, 8))
    coefficients = np.zeros(s.grid.shape)
    steep = np.arange(s.grid.n1) > column if column else np.arange(s.grid.n1) == 0
    coefficients[:, :, 0] = 0.45 + height * steep[None, :] * (s.grid.node_v2 > 0.3)[:, None]
    if system != "prolate":
        coefficients[:, :, 0] *= 40.0
    s = s.with_coefficients(s.grid.constrain(coefficients))
    g = ImageGrid((90, 90, 100), spacing=(0.9, 0.9, 0.9), origin=(-40.0, -40.0, -5.0))
    mask = s.mask(g)
    assert mask.sum() > 1000
    np.testing.assert_array_equal(mask, reference_mask(s, g))


def test_mask_of_segmentation_equals_reference():
    ph = make_phantom(seed=3, spacing=0.8, tilt_deg=20.0)
    res = spheroseg.segment(ph.volume, apex=ph.apex, base=ph.base)
    np.testing.assert_array_equal(res.mask(ph.volume), reference_mask(res.surface, ph.volume.grid))


def test_mask_nonplanar_v2_range_equals_reference(rng):
    # a v2 range that ends before the base plane: no planar shortcut
    s = bumpy("prolate", rng, 0.05)
    from spheroseg.geometry.hermite import HermiteGrid

    grid = HermiteGrid(8, 8, (0.0, 1.3), poles=s.system.poles)
    s = Surface.from_function(s.system, s.pose, grid, 0.6)
    g = GRIDS["oblique"]
    np.testing.assert_array_equal(s.mask(g), reference_mask(s, g))


@pytest.mark.parametrize("dtype", [np.uint8, bool, np.int64])
@pytest.mark.parametrize("voxels", [1000, FRESH_ZEROS_BYTES + 3])
def test_fresh_zeros_are_writable_zeros_of_the_shape(dtype, voxels):
    # the mask and padding tests on phantoms (over a MiB) write into the mapped ones
    shape = (voxels, 1, 1)
    a = fresh_zeros(shape, dtype)
    assert a.shape == shape and a.dtype == np.dtype(dtype) and a.flags.c_contiguous and a.flags.writeable
    np.testing.assert_array_equal(a, np.zeros(shape, dtype))
    a[-1] = 1
    assert a[-1] == 1 and a.sum() == 1


@pytest.mark.parametrize("seed", [0, 1])
def test_padding_equals_reference_on_phantoms(seed):
    ph = make_phantom(seed=seed, spacing=1.0)
    array = ph.volume.array
    expected = reference_padding(array)
    assert expected is not None and expected.any()
    np.testing.assert_array_equal(outside_sector(array), expected)


def test_padding_keeps_inner_zeros_and_handles_edge_cases():
    a = np.ones((9, 10, 11), np.float32)
    a[0, :, :5] = 0  # a face region
    a[4, 4:6, 4:6] = 0  # inner zeros: not connected to a face
    a[1:5, 2, 0] = 0  # touching the x face
    expected = reference_padding(a, min_fraction=0.0)
    got = outside_sector(a, min_fraction=0.0)
    np.testing.assert_array_equal(got, expected)
    assert not got[4, 4, 4]
    assert outside_sector(np.ones((5, 5, 5))) is None
    assert outside_sector(a, min_fraction=0.5) is None
    zeros = np.zeros((3, 4, 5))
    np.testing.assert_array_equal(outside_sector(zeros), reference_padding(zeros))


@pytest.mark.parametrize("phase", ["ED", "ES"])
def test_padding_and_mask_equal_reference_on_cetus(phase, tmp_path):
    import json

    from conftest import cetus_file

    points = json.loads(cetus_file("Patient7_points.json").read_text())
    array = np.load(cetus_file(points[phase]["file"]))
    expected = reference_padding(array)
    assert expected is not None and expected.mean() > 0.2  # the sector's padding
    np.testing.assert_array_equal(outside_sector(array), expected)
    # through load, as the CLI reads it
    np.save(tmp_path / "p7.npy", array)
    spacing = points["assumed_spacing_mm"]
    vol = spheroseg.load(tmp_path / "p7.npy", spacing=(spacing,) * 3)
    np.testing.assert_array_equal(vol.no_data_mask, expected)
    apex = np.array(points[phase]["apex_index"][::-1], float) * spacing
    base = np.array(points[phase]["base_index"][::-1], float) * spacing
    res = spheroseg.segment(vol, apex=apex, base=base)
    np.testing.assert_array_equal(res.mask(vol), reference_mask(res.surface, vol.grid))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_padding_equals_reference_on_random_zeros(seed):
    """Zero runs inside rows, reached from the padding through chains of
    other rows (and not): noise zeros in a sector-like cone, a corridor
    that winds in from a face, and the all-zero corner cases."""
    rng = np.random.default_rng(seed)
    k, j, i = np.indices((23, 19, 29))
    cone = (i - 14) ** 2 + (j - 9) ** 2 <= (0.4 * k + 2) ** 2
    a = np.where(cone, 1 + rng.integers(0, 5, cone.shape), 0).astype(np.int16)
    a[rng.random(a.shape) < 0.3] = 0  # zeros inside: some reach the padding, some not
    a[5:18, 4:15, 6:22] = 7  # a block of data with a corridor through it
    a[6, 5:14, 7] = a[6, 13, 7:21] = a[6:17, 13, 20] = 0
    for array in (a, np.zeros_like(a), np.ones_like(a)):
        np.testing.assert_array_equal(outside_sector(array, min_fraction=0.0),
                                      reference_padding(array, min_fraction=0.0))
    from spheroseg._compiled._raster import face_connected_zeros  # a stack grown from its first size
    noise = np.where(rng.random((40, 40, 40)) < 0.45, 0, 1)
    mask, count = face_connected_zeros(noise)
    assert count == mask.sum()
    np.testing.assert_array_equal(mask, reference_padding(noise, min_fraction=0.0))


def sector_like(rng, dtype):
    """A cone of data in zero padding, with zeros inside it (some reach the
    padding through zero runs inside rows, some not)."""
    k, j, i = np.indices((21, 17, 26))
    cone = (i - 12.5) ** 2 + (j - 8) ** 2 <= (0.5 * k + 2) ** 2
    a = np.where(cone, 1 + rng.integers(0, 5, cone.shape), 0).astype(dtype)
    a[rng.random(a.shape) < 0.25] = 0
    return a


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.uint8, np.int16])
def test_padding_equals_reference_for_every_type_and_layout(dtype, rng, tmp_path):
    # float32 is searched in place, other types by their non-zeros: a
    # float64 1e-50 is data though float32 rounds it to 0; -0.0 is a zero
    # and NaN is data, as for ==; read-only, non-contiguous inputs and
    # load give the same, and the input is left as it was
    a = sector_like(rng, dtype)
    if a.dtype.kind == "f":
        a[0, :3, :3] = 1e-50 if dtype == np.float64 else np.nan
        a[0, 5, :4] = -0.0
    expected = reference_padding(a)
    assert expected is not None
    if a.dtype.kind == "f":
        assert not expected[0, 0, 0] and expected[0, 5, 0]
    before = a.copy()
    np.testing.assert_array_equal(outside_sector(a), expected)
    np.testing.assert_array_equal(a, before)
    from spheroseg._compiled._raster import face_connected_zeros  # rows of zeros counted too

    assert face_connected_zeros(a)[1] == expected.sum()
    assert a.flags.writeable
    wide = np.zeros(a.shape[:2] + (2 * a.shape[2],), dtype)
    wide[:, :, ::2] = a
    np.testing.assert_array_equal(outside_sector(wide[:, :, ::2]), expected)
    a.flags.writeable = False
    np.testing.assert_array_equal(outside_sector(a), expected)
    if dtype != np.float32 or not np.isnan(a).any():  # (a Volume refuses NaN)
        np.save(tmp_path / "a.npy", a)
        np.testing.assert_array_equal(spheroseg.load(tmp_path / "a.npy", spacing=(1, 1, 1)).no_data_mask, expected)


def test_padding_of_a_2d_array_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="expected a 3D array"):
        outside_sector(np.zeros((4, 5)))
    np.save(tmp_path / "flat.npy", np.zeros((4, 5), np.uint8))
    with pytest.raises(ValueError, match="3D"):
        spheroseg.load(tmp_path / "flat.npy", spacing=(1, 1, 1))


def test_patch_slopes_are_the_largest_sampled_derivatives(rng):
    s = bumpy("prolate", rng, 0.15, patches=(5, 7))
    lo, hi = s.grid.v2_range
    n = SLOPE_SAMPLES
    v2, v1 = np.meshgrid(np.linspace(lo, hi, n * s.grid.n2 + 1), np.linspace(0, 2 * np.pi, n * s.grid.n1 + 1),
                         indexing="ij")
    got = patch_slopes(np.ascontiguousarray(s.coefficients), lo, hi, n)
    for column, d in enumerate(((1, 0), (0, 1))):
        e = np.abs(s.evaluate(v1, v2, *d))
        expected = [[e[n * i2:n * i2 + n + 1, n * i1:n * i1 + n + 1].max() for i1 in range(s.grid.n1)]
                    for i2 in range(s.grid.n2)]
        np.testing.assert_allclose(got[..., column], expected, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("stepped", [False, True])
@pytest.mark.parametrize("system", ["prolate", "spherical", "cylindrical"])
def test_a_ball_the_rasteriser_decides_at_once_shares_its_status(system, stepped, rng):
    # every point of a ball whose status _status says it shares (its
    # centre near the wall, its radius up to 6 mm, or up to 0.95 of the
    # distance to the axis: it reaches several patches around it) has that status,
    # the reference's; on a bumpy surface, and on one whose radius steps up
    # across one column of patches and is flat on the others
    s = bumpy(system, rng, 0.2, patches=(6, 8))
    if stepped:
        coefficients = np.zeros(s.grid.shape)
        coefficients[:, :, 0] = np.where(np.arange(s.grid.n1) == 2, 1.8, 1.0)[None, :] * s.coefficients[:, :, 0].mean()
        s = s.with_coefficients(s.grid.constrain(coefficients))
    lo, hi = s.grid.v2_range
    coefficients = np.ascontiguousarray(s.coefficients)
    slopes = SLOPE_MARGIN * patch_slopes(coefficients, lo, hi, SLOPE_SAMPLES) + 1e-9
    kind = {"prolate": 0, "spherical": 1, "cylindrical": 2}[system]
    param = s.system.height if system == "cylindrical" else getattr(s.system, "focal_length", 1.0)
    planar = lo == 0 and abs(hi - (param if system == "cylindrical" else np.pi / 2)) < 1e-12
    m = 2000
    v1, v2 = rng.uniform(0, 2 * np.pi, m), rng.uniform(lo, hi, m)
    centres = s.system.to_cartesian(s.evaluate(v1, v2) * (1 + rng.uniform(-0.25, 0.25, m)), v1, v2)
    rho = np.hypot(centres[:, 1], centres[:, 2])
    reaches = np.where(np.arange(m) % 2, rng.uniform(0.3, 6.0, m), rng.uniform(0.2, 0.95, m) * np.minimum(rho, 10.0))
    directions = rng.normal(size=(300, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    decided = 0
    for x, reach in zip(centres, reaches):
        code, shared = status(*x, kind, param, coefficients, lo, hi, planar, slopes, reach)
        if not shared or code == 2:
            continue
        decided += 1
        ball = x + reach * rng.uniform(0, 1, (len(directions), 1)) ** (1 / 3) * directions
        assert np.all(s.contains(s.pose.to_world(ball)) == (code == 1))
    assert decided > 150


def test_the_gradient_bound_takes_the_slopes_of_the_patches_the_ball_reaches():
    # one steep patch (the last column, next to the seam v1 = 0) among flat
    # ones: a ball 2 mm across at 20 mm from the axis spans 0.11 rad of v1
    n2, n1 = 4, 8
    slopes = np.zeros((n2, n1, 2))
    slopes[1, n1 - 1, 0] = 50.0
    width, v2 = 2 * np.pi / n1, 1.5 * (np.pi / 2) / n2  # in row 1
    rho, delta = 20.0, 2.0

    def bound(v1):
        return gradient_bound(delta, 0, 100.0, 100.0, rho, v1, v2, 0.0, np.pi / 2, slopes)

    steep = 50.0 / (rho - delta)
    for v1 in ((n1 - 0.5) * width, (n1 - 1) * width - 0.1, 0.1, 2 * np.pi - 1e-12):
        assert bound(v1) > steep
    for v1 in ((n1 - 1) * width - 0.2, 0.2, 3.5 * width):
        assert bound(v1) < 0.1 * steep


@pytest.mark.parametrize("derivative", [0, 1])
def test_the_compiled_basis_is_the_numpy_one(derivative):
    for t in (0.0, 0.3, 0.75, 1.0):
        np.testing.assert_allclose(hermite_at(t, 0.4, derivative), global_basis(np.array(t), 0.4, derivative),
                                   rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
@pytest.mark.parametrize("factor", [(2, 2, 2), (3, 1, 2), (4, 3, 5)])
def test_block_means_are_their_definition(dtype, factor):
    """Block by block, numpy's mean over the samples with data: NaN where
    half a block has none, the remainder past the last whole block cut off;
    8-bit grey levels do not overflow."""
    rng = np.random.default_rng(2)
    array = rng.integers(200, 256, size=(23, 17, 26)).astype(dtype)
    missing = rng.random(array.shape) < 0.3
    missing[:4, :3, :5] = True  # whole blocks without data
    means = block_means(array, missing, factor)
    shape = np.array(array.shape) // factor
    assert means.shape == tuple(shape)
    for index in np.ndindex(*shape):
        block = tuple(slice(i * f, (i + 1) * f) for i, f in zip(index, factor))
        ok = ~missing[block]
        expected = array[block][ok].astype(float).mean() if ok.sum() > 0.5 * ok.size else np.nan
        np.testing.assert_allclose(means[index], expected, rtol=1e-6)
    assert np.isnan(means[0, 0, 0])
