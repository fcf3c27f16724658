import numpy as np
import pytest

from spheroseg.geometry.coords import Cylindrical, Pose, ProlateSpheroidal, Spherical, annulus_plane, coordinate_system

SYSTEMS = [ProlateSpheroidal(37.0), Spherical(), Cylindrical(90.0)]


def random_coords(system, rng, n=500, margin=0.05):
    v1 = rng.uniform(0, 2 * np.pi, n)
    if isinstance(system, ProlateSpheroidal):
        return rng.uniform(0.1, 2.0, n), v1, rng.uniform(margin, np.pi - margin, n)
    if isinstance(system, Spherical):
        return rng.uniform(1.0, 80.0, n), v1, rng.uniform(margin, np.pi - margin, n)
    return rng.uniform(1.0, 80.0, n), v1, rng.uniform(-50, 50, n)


@pytest.mark.parametrize("system", SYSTEMS, ids=lambda s: s.name)
def test_round_trip(system, rng):
    v = random_coords(system, rng)
    back = system.from_cartesian(system.to_cartesian(*v))
    for a, b in zip(v, back):
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-10)
    x = rng.normal(scale=40.0, size=(500, 3))
    np.testing.assert_allclose(system.to_cartesian(*system.from_cartesian(x)), x, atol=1e-10)


def test_prolate_finite_near_poles_and_foci():
    s = ProlateSpheroidal(30.0)
    x = np.array([[30.0, 0, 0], [30.0 + 1e-9, 1e-12, 0], [0, 0, 0], [-30, 1e-9, 0], [50, 0, 0], [29.0, 0, 0]])
    v = s.from_cartesian(x)
    assert all(np.all(np.isfinite(c)) for c in v)
    np.testing.assert_allclose(s.to_cartesian(*v), x, atol=1e-7)
    # on the axis beyond the focus mu = 0 exactly, between the foci lambda = 0
    assert v[2][4] == 0 and v[0][5] == 0


def numerical_jacobian(system, v, eps=1e-6):
    cols = []
    for i in range(3):
        hi = [c.copy() for c in v]
        lo = [c.copy() for c in v]
        hi[i] = hi[i] + eps
        lo[i] = lo[i] - eps
        cols.append((system.to_cartesian(*hi) - system.to_cartesian(*lo)) / (2 * eps))
    return np.stack(cols, axis=-1)  # (..., 3 xyz, 3 v)


@pytest.mark.parametrize("system", SYSTEMS, ids=lambda s: s.name)
def test_scale_factors_and_volume_element(system, rng):
    v = random_coords(system, rng, n=200)
    jac = numerical_jacobian(system, v)
    np.testing.assert_allclose(system.jacobian(*v), jac, rtol=1e-7, atol=1e-6)
    h = np.stack(system.scale_factors(*v), axis=-1)
    np.testing.assert_allclose(np.linalg.norm(jac, axis=-2), np.abs(h), rtol=1e-7, atol=1e-7)
    # orthogonal system: J^T J is diagonal
    gram = np.einsum("nij,nik->njk", jac, jac)
    off = gram - np.einsum("nj,jk->njk", np.diagonal(gram, axis1=1, axis2=2), np.eye(3))
    assert np.abs(off).max() < 1e-5 * np.abs(gram).max()
    np.testing.assert_allclose(np.abs(np.linalg.det(jac)), np.abs(system.volume_element(*v)), rtol=1e-6)


@pytest.mark.parametrize("system", SYSTEMS, ids=lambda s: s.name)
def test_scale_factor_derivatives(system, rng):
    v0, v1, v2 = random_coords(system, rng, n=200)
    eps = 1e-6
    hi = system.scale_factors(v0 + eps, v1, v2)
    lo = system.scale_factors(v0 - eps, v1, v2)
    for d, a, b in zip(system.scale_factor_derivatives(v0, v1, v2), hi, lo):
        np.testing.assert_allclose(d, (a - b) / (2 * eps), rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("system", SYSTEMS, ids=lambda s: s.name)
def test_radial_volume_is_integral_of_volume_element(system, rng):
    f = rng.uniform(0.3, 1.5, 20) * (1 if isinstance(system, ProlateSpheroidal) else 40)
    v2 = rng.uniform(0.1, 1.5, 20)
    x, w = np.polynomial.legendre.leggauss(40)
    t = (x + 1) / 2
    numeric = (w / 2 * f[:, None] * system.volume_element(f[:, None] * t, 0.0, v2[:, None])).sum(1)
    np.testing.assert_allclose(system.radial_volume(f, v2), numeric, rtol=1e-10)


def test_bad_focal_length():
    for d in (0.0, -1.0, np.nan):
        with pytest.raises(ValueError, match="focal_length"):
            ProlateSpheroidal(d)
    with pytest.raises(ValueError, match="coordinate system"):
        coordinate_system("toroidal")


def test_pose_from_apex_base(rng):
    apex, base = np.array([10.0, 20, 90]), np.array([12.0, 25, 10])
    pose = Pose.from_apex_base(apex, base)
    np.testing.assert_allclose(pose.rotation.T @ pose.rotation, np.eye(3), atol=1e-12)
    assert np.linalg.det(pose.rotation) > 0
    np.testing.assert_allclose(pose.to_local(base), 0, atol=1e-12)
    np.testing.assert_allclose(pose.to_local(apex), [np.linalg.norm(apex - base), 0, 0], atol=1e-12)
    x = rng.normal(size=(10, 3))
    np.testing.assert_allclose(pose.to_world(pose.to_local(x)), x, atol=1e-12)
    again = Pose.from_dict(pose.to_dict())
    np.testing.assert_array_equal(again.rotation, pose.rotation)


@pytest.mark.parametrize(
    "apex, base, message",
    [
        ([0, 0, 1], [0, 0, 1], "apex and base"),
        ([0, np.nan, 1], [0, 0, 0], "apex"),
        ([0, 0, 1], [0, np.inf, 0], "base"),
        ([0, 0], [0, 0, 0], "apex"),
    ],
)
def test_pose_bad_points(apex, base, message):
    with pytest.raises(ValueError, match=message):
        Pose.from_apex_base(apex, base)


def random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def tilted_ring(rng, *, k=8, radius=22.0, start=0.0):
    """k points evenly spaced on a circle in a random plane: (points, centre, normal)."""
    rotation = random_rotation(rng)
    centre = rng.uniform(-50, 50, 3)
    t = start + np.arange(k) * (2 * np.pi / k)
    local = np.stack([0 * t, radius * np.cos(t), radius * np.sin(t)], 1)
    return local @ rotation.T + centre, centre, rotation[:, 0]


@pytest.mark.parametrize("k", [3, 5, 40])
def test_annulus_plane_of_tilted_circle(k, rng):
    points, centre, normal = tilted_ring(rng, k=k, start=0.3)
    c, n = annulus_plane(points)
    np.testing.assert_allclose(c, centre, atol=1e-10)  # evenly spaced: the centroid is the centre
    np.testing.assert_allclose(abs(n @ normal), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(n), 1.0, atol=1e-12)


def test_annulus_plane_is_least_squares(rng):
    # a saddle (+-h out of the plane, alternating) keeps the plane; the
    # normal of three points is their cross product
    points, centre, normal = tilted_ring(rng, k=6)
    saddle = points + np.array([1, -1, 1, -1, 1, -1])[:, None] * 2.0 * normal
    c, n = annulus_plane(saddle)
    np.testing.assert_allclose(c, centre, atol=1e-10)
    np.testing.assert_allclose(abs(n @ normal), 1.0, atol=1e-12)
    a, b, d = rng.normal(size=(3, 3))
    cross = np.cross(b - a, d - a)
    np.testing.assert_allclose(abs(annulus_plane([a, b, d])[1] @ cross), np.linalg.norm(cross), rtol=1e-10)


def test_pose_from_annulus(rng):
    points, centre, normal = tilted_ring(rng)
    lateral = np.cross(normal, rng.normal(size=3))
    lateral /= np.linalg.norm(lateral)
    apex = centre - 85.0 * normal + 9.0 * lateral  # on the side opposite to the normal given
    pose = Pose.from_annulus(apex, points)
    np.testing.assert_allclose(pose.origin, centre, atol=1e-10)
    np.testing.assert_allclose(pose.axis, -normal, atol=1e-12)
    np.testing.assert_allclose(pose.rotation.T @ pose.rotation, np.eye(3), atol=1e-12)
    assert np.linalg.det(pose.rotation) > 0
    np.testing.assert_allclose(pose.to_local(apex), [85.0, 9.0, 0.0], atol=1e-10)
    np.testing.assert_allclose(pose.to_local(points)[:, 0], 0.0, atol=1e-10)  # the ring is the plane x1 = 0
    x = rng.normal(size=(10, 3)) * 50
    np.testing.assert_allclose(pose.to_world(pose.to_local(x)), x, atol=1e-10)
    again = Pose.from_dict(pose.to_dict())
    np.testing.assert_array_equal(again.rotation, pose.rotation)
    # a base point given is projected on the plane
    base = centre + 3.0 * lateral + 4.0 * normal
    moved = Pose.from_annulus(apex, points, base=base)
    np.testing.assert_allclose(moved.origin, centre + 3.0 * lateral, atol=1e-10)
    np.testing.assert_allclose(moved.axis, -normal, atol=1e-12)
    # an apex on the axis gives the apex-base frame
    on_axis = centre + 70.0 * normal
    np.testing.assert_allclose(Pose.from_annulus(on_axis, points).rotation,
                               Pose.from_apex_base(on_axis, centre).rotation, atol=1e-12)


@pytest.mark.parametrize(
    "annulus, apex, message",
    [
        ([[0, 0, 0], [1, 0, 0]], [0, 0, 50], "at least 3"),
        ([[0, 0, 0], [1, 0, 0], [2, 0, 0], [5, 0, 0]], [0, 0, 50], "line"),
        ([[0, 0, 0], [1, 0, 0], [0, np.nan, 0]], [0, 0, 50], "finite"),
        ([[0, 0], [1, 0], [0, 1]], [0, 0, 50], "shape"),
        ([[0, 0, 0], [10, 0, 0], [0, 10, 0]], [5, 5, 0], "apex lies in the mitral plane"),
        ([[0, 0, 0], [10, 0, 0], [0, 10, 0]], [5, 5, np.inf], "apex"),
    ],
)
def test_pose_from_annulus_bad_points(annulus, apex, message):
    with pytest.raises(ValueError, match=message):
        Pose.from_annulus(apex, annulus)


@pytest.mark.parametrize("system", [ProlateSpheroidal(35.0), Spherical(), Cylindrical(90.0)])
def test_to_cartesian_of_a_row_and_a_column_is_the_grids(rng, system):
    """Coordinates of different shapes broadcast: a tensor grid as a row and
    a column gives the points of the full grid, to the last bit."""
    v0, v1, v2 = (c.reshape(20, 25) for c in random_coords(system, rng))
    row, column = v1[:1], v2[:, :1]
    full_v1, full_v2 = np.broadcast_arrays(row, column)
    np.testing.assert_array_equal(system.to_cartesian(v0, row, column), system.to_cartesian(v0, full_v1, full_v2))
    np.testing.assert_array_equal(system.to_cartesian(v0[0, 0], row[0], column[0, 0]),
                                  system.to_cartesian(np.full(25, v0[0, 0]), row[0], np.full(25, column[0, 0])))


@pytest.mark.parametrize("perturbation", [0.0, 1e-10, 5e-10, 2e-9, 1e-6, 1e-3, np.nan])
def test_pose_accepts_the_rotations_allclose_accepts(rng, perturbation):
    """A rotation is checked as np.allclose(R^T R, I, atol=1e-9) checks it,
    off the diagonal and on it, and must be proper."""
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    for k in range(9):
        rotation = q.copy()
        rotation.flat[k] += perturbation
        proper = np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-9) and np.linalg.det(rotation) >= 0
        if proper:
            Pose(np.zeros(3), rotation)
        else:
            with pytest.raises(ValueError, match="proper orthonormal"):
                Pose(np.zeros(3), rotation)
    with pytest.raises(ValueError, match="proper orthonormal"):
        Pose(np.zeros(3), -q)
