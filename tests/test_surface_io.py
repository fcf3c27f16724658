import numpy as np
import pytest

from spheroseg.surfaces.surface import Surface
from spheroseg.io.surface_io import read_mesh, read_surface_json, write_cmiss, write_mesh, write_surface_json


@pytest.fixture
def surface(rng):
    s = Surface.from_apex_base([3.0, -2.0, 80.0], [1.0, 0.0, 2.0], patches=(8, 6))
    p = s.grid.parameters(s.coefficients)
    return s.with_coefficients(s.grid.constraints @ (p + 0.03 * rng.normal(size=p.shape)))


@pytest.mark.parametrize("suffix", [".vtk", ".ply", ".stl", ".obj"])
def test_mesh_round_trip(tmp_path, surface, suffix):
    points, faces = surface.mesh()
    write_mesh(tmp_path / f"m{suffix}", points, faces)
    p, f = read_mesh(tmp_path / f"m{suffix}")
    np.testing.assert_allclose(p, points, atol=1e-5)  # STL stores float32
    np.testing.assert_array_equal(f, faces)


def test_vtk_is_marked_lps(tmp_path, surface):
    write_mesh(tmp_path / "m.vtk", *surface.mesh())
    assert b"SPACE=LPS" in (tmp_path / "m.vtk").read_bytes().split(b"\n")[1]


@pytest.mark.parametrize("suffix", [".vtk", ".ply", ".stl", ".obj"])
def test_mesh_bytes_are_reproducible(tmp_path, surface, suffix):
    """The same mesh written twice (meshio dates its PLY header) gives the same bytes."""
    points, faces = surface.mesh()
    write_mesh(tmp_path / f"a{suffix}", points, faces)
    write_mesh(tmp_path / f"b{suffix}", points, faces)
    assert (tmp_path / f"a{suffix}").read_bytes() == (tmp_path / f"b{suffix}").read_bytes()


def test_surface_json_round_trip(tmp_path, surface):
    write_surface_json(tmp_path / "s.json", surface, volume_ml=surface.volume_ml())
    back = read_surface_json(tmp_path / "s.json")
    np.testing.assert_array_equal(back.coefficients, surface.coefficients)
    np.testing.assert_array_equal(back.pose.rotation, surface.pose.rotation)
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(ValueError, match="not a spheroseg surface"):
        read_surface_json(tmp_path / "bad.json")


def test_cmiss_export_matches_zinc(tmp_path, surface, rng):
    """Zinc (OpenCMISS) reads the exnode/exelem pair and evaluates the same
    surface, across the theta seam and at the apex."""
    zinc = pytest.importorskip("cmlibs.zinc.context")
    from cmlibs.zinc.field import Field

    write_cmiss(tmp_path / "lv", surface)
    context = zinc.Context("test")  # keep it alive while the region is used
    region = context.getDefaultRegion()
    assert region.readFile(str(tmp_path / "lv.exnode")) == 1
    assert region.readFile(str(tmp_path / "lv.exelem")) == 1
    fm = region.getFieldmodule()
    cartesian = fm.createFieldCoordinateTransformation(fm.findFieldByName("coordinates"))
    cartesian.setCoordinateSystemType(Field.COORDINATE_SYSTEM_TYPE_RECTANGULAR_CARTESIAN)
    mesh, cache = fm.findMeshByDimension(2), fm.createFieldcache()
    n1, n2 = surface.grid.n1, surface.grid.n2
    h1, h2 = 2 * np.pi / n1, (np.pi / 2) / n2
    theta = np.concatenate([rng.uniform(0, 2 * np.pi, 200), [2 * np.pi - 1e-9, 0.0, 1.0, 3.0]])
    mu = np.concatenate([rng.uniform(0, np.pi / 2, 200), [0.7, 0.0, 0.0, np.pi / 2]])
    for th, m in zip(theta, mu):
        j, r = min(int(th / h1), n1 - 1), min(int(m / h2), n2 - 1)
        xi = np.clip([th / h1 - j, m / h2 - r], 0.0, 1.0)
        cache.setMeshLocation(mesh.findElementByIdentifier(r * n1 + j + 1), list(xi))
        ok, x = cartesian.evaluateReal(cache, 3)
        assert ok == 1, (th, m, xi, r * n1 + j + 1)
        expected = surface.system.to_cartesian(surface.evaluate(th, m), th, m)
        np.testing.assert_allclose(x, expected, atol=1e-9)


def test_cmiss_needs_prolate(tmp_path):
    s = Surface.from_apex_base([0, 0, 80.0], [0, 0, 0], system="spherical")
    with pytest.raises(ValueError, match="prolate"):
        write_cmiss(tmp_path / "x", s)


def test_cmiss_heart_volume_elements_match_zinc(tmp_path, surface, rng):
    """Zinc reads the two-layer volume mesh and gives lambda linear between
    the endocardium (xi3 = 0) and the epicardium (xi3 = 1)."""
    from spheroseg.io.surface_io import write_cmiss_heart

    zinc = pytest.importorskip("cmlibs.zinc.context")
    c = surface.coefficients.copy()
    c[..., 0] += 0.15 + 0.05 * np.cos(surface.grid.node_v1)[None, :] * (np.arange(len(c)) > 0)[:, None]
    epicardium = surface.with_coefficients(surface.grid.constrain(c))
    write_cmiss_heart(tmp_path / "heart", surface, epicardium)
    context = zinc.Context("heart")
    region = context.getDefaultRegion()
    assert region.readFile(str(tmp_path / "heart.exnode")) == 1
    assert region.readFile(str(tmp_path / "heart.exelem")) == 1
    fm = region.getFieldmodule()
    coordinates = fm.findFieldByName("coordinates")
    mesh, cache = fm.findMeshByDimension(3), fm.createFieldcache()
    assert mesh.getSize() == surface.grid.n1 * surface.grid.n2
    n1, n2 = surface.grid.n1, surface.grid.n2
    h1, h2 = 2 * np.pi / n1, (np.pi / 2) / n2
    for th, m, x3 in zip(rng.uniform(0, 2 * np.pi, 100), rng.uniform(0, np.pi / 2, 100), rng.uniform(0, 1, 100)):
        j, r = min(int(th / h1), n1 - 1), min(int(m / h2), n2 - 1)
        cache.setMeshLocation(mesh.findElementByIdentifier(r * n1 + j + 1), [th / h1 - j, m / h2 - r, x3])
        ok, (lam, mu, theta) = coordinates.evaluateReal(cache, 3)
        assert ok == 1
        expected = (1 - x3) * surface.evaluate(th, m) + x3 * epicardium.evaluate(th, m)
        np.testing.assert_allclose([lam, mu, theta], [expected, m, th], atol=1e-9)
    with pytest.raises(ValueError, match="share"):
        write_cmiss_heart(tmp_path / "x", surface, epicardium.refine())
