"""Least-squares fitting of a surface to points or a mesh.

This is how a reference shape becomes Hermite coefficients, and how we learn
how well a given number of patches can represent a real ventricle.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .coords import CoordinateSystem, Pose
from .hermite import HermiteGrid
from .surface import Surface

__all__ = ["fit_surface", "apex_base_of_open_mesh", "surface_sample", "point_to_surface_distance"]


def fit_surface(
    points,
    *,
    system: CoordinateSystem,
    pose: Pose,
    patches: tuple[int, int] = (8, 8),
    v2_range: tuple[float, float] | None = None,
    smoothness: float = 1e-7,
) -> Surface:
    """Surface ``v0 = f(v1, v2)`` closest to world points, in ``v0``.

    Minimises ``sum_k (f(v1_k, v2_k) - v0_k)^2 / n + smoothness * T(f)``
    over the well-formed surfaces (pole constraints), where ``T`` is the
    thin-plate energy ``int f_11^2 + 2 f_12^2 + f_22^2 dv1 dv2`` divided by
    the domain's area.  Points whose ``v2`` is outside the range (beyond
    the base plane) are left out.

    Parameters
    ----------
    points : array (n, 3)
        World points (mm) on the target surface.
    system, pose : CoordinateSystem, Pose
        The model frame (e.g. from :meth:`Surface.from_apex_base`).
    patches : (int, int)
    v2_range : (float, float), optional
        Defaults to the system's range for the cavity.
    smoothness : float
        Weight of the thin-plate term, >= 0 (in units of ``v0`` squared).
    """
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError(f"points must have shape (n, 3) with n > 0, got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise ValueError("points must be finite")
    if smoothness < 0:
        raise ValueError(f"smoothness must be >= 0, got {smoothness!r}")
    if v2_range is None:
        v2_range = system.default_v2_range(float(np.max(pose.to_local(points)[:, 0])))
    grid = HermiteGrid(*patches, v2_range=v2_range, poles=system.poles)
    v0, v1, v2 = system.from_cartesian(pose.to_local(points))
    keep = (v2 >= v2_range[0]) & (v2 <= v2_range[1])
    if keep.sum() < grid.constraints.shape[1]:
        raise ValueError(f"{keep.sum()} points in the model's range: too few for {patches} patches")
    a = grid.constraints
    b = grid.basis_matrix(v1[keep], v2[keep]) @ a
    lhs = (b.T @ b) / keep.sum()
    rhs = b.T @ v0[keep] / keep.sum()
    if smoothness > 0:
        lhs = lhs + smoothness * grid.roughness_matrix()
    params = np.linalg.solve(lhs.toarray(), rhs)
    return Surface(system, pose, grid, a @ params)


def apex_base_of_open_mesh(points, faces) -> tuple[np.ndarray, np.ndarray]:
    """Apex and base points of a cavity mesh open at the mitral plane.

    The base is the centroid of the boundary loop (edges used by one
    triangle); the apex the mesh point farthest from the base along the
    loop's normal.
    """
    points = np.asarray(points, dtype=float)
    faces = np.asarray(faces)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    ring = np.unique(unique[counts == 1])
    if len(ring) < 3:
        raise ValueError("the mesh has no open boundary (mitral ring)")
    base = points[ring].mean(0)
    normal = np.linalg.svd(points[ring] - base)[2][2]
    along = (points - base) @ normal
    if abs(along.min()) > abs(along.max()):
        along = -along
    return points[np.argmax(along)], base


def surface_sample(points, faces, spacing: float = 0.5, seed: int = 0) -> np.ndarray:
    """Points on a triangle mesh, about one per ``spacing**2`` mm^2 of area
    (area-weighted, seeded), together with the vertices the faces use."""
    faces = np.asarray(faces)
    p = np.asarray(points, dtype=float)[faces]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    n = int(np.ceil(area.sum() / spacing**2))
    rng = np.random.default_rng(seed)
    tri = rng.choice(len(p), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    flip = r1 + r2 > 1
    r1[flip], r2[flip] = 1 - r1[flip], 1 - r2[flip]
    samples = p[tri, 0] + r1[:, None] * (p[tri, 1] - p[tri, 0]) + r2[:, None] * (p[tri, 2] - p[tri, 0])
    return np.concatenate([np.asarray(points, float)[np.unique(faces)], samples])


def point_to_surface_distance(points, surface: Surface, *, n_v1: int = 512, n_v2: int = 256) -> np.ndarray:
    """Distance (mm) from world points to the surface's wall, to the nearest
    of a dense sampling of the wall (spacing well under 0.5 mm for a
    ventricle)."""
    wall = surface_sample(*surface.mesh(n_v1, n_v2, closed=False), spacing=0.25)
    return cKDTree(wall).query(np.asarray(points, dtype=float))[0]
