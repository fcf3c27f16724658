"""The cavity surface ``v0 = f(v1, v2)``: evaluation, volume, mask, mesh.

A :class:`Surface` ties a coordinate system, a pose in world space and a
bicubic Hermite function together.  The cavity it bounds is

    { x : v0(x) <= f(v1(x), v2(x)) and v2(x) in v2_range }

which, with the pose's origin at the base point, is closed by the base
(mitral) plane ``x1 = 0`` (see :mod:`spheroseg.coords`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..geometry.coords import CoordinateSystem, Pose, coordinate_system
from ..geometry.energy import SampledSurface, area_energy
from ..geometry.hermite import HermiteGrid
from ..volumes.volume import ImageGrid

__all__ = ["Surface", "ImageGrid", "signed_volume"]

#: base radius / apex-to-base distance of the initial surface
DEFAULT_RADIUS_RATIO = 0.3


def signed_volume(points: np.ndarray, faces: np.ndarray) -> float:
    """Volume enclosed by a closed triangle mesh (divergence theorem), in the
    units of ``points`` cubed; positive for outward-facing triangles."""
    p = points[faces]
    return float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0)


@dataclass
class Surface:
    """A cavity surface: coordinate system, pose and Hermite coefficients.

    Parameters
    ----------
    system : CoordinateSystem
    pose : Pose
        Local frame in world space (origin at the base point).
    grid : HermiteGrid
    coefficients : array, shape ``grid.shape``
        Hermite coefficients of ``v0 = f(v1, v2)`` (see :mod:`spheroseg.hermite`).
    """

    system: CoordinateSystem
    pose: Pose
    grid: HermiteGrid
    coefficients: np.ndarray

    def __post_init__(self):
        c = np.asarray(self.coefficients, dtype=float)
        if c.size != self.grid.n_coefficients:
            raise ValueError(f"coefficients must have {self.grid.n_coefficients} values, got {c.size}")
        if not np.all(np.isfinite(c)):
            raise ValueError("coefficients must be finite")
        self.coefficients = c.reshape(self.grid.shape)

    # -- construction -----------------------------------------------------

    @classmethod
    def from_apex_base(
        cls,
        apex,
        base,
        *,
        system: str | CoordinateSystem = "prolate",
        patches: tuple[int, int] = (8, 8),
        radius_ratio: float = DEFAULT_RADIUS_RATIO,
    ) -> "Surface":
        """The initial surface, placed by the apex and base points.

        The local frame has its origin at ``base`` and its long axis towards
        ``apex``.  The surface is the half-ellipsoid through the apex with
        base radius ``radius_ratio * |apex - base|``.  In prolate spheroidal
        coordinates the focal length makes the paper's initial isosurface
        ``lambda = 1`` pass through the apex (see
        :meth:`ProlateSpheroidal.initial_v0`).
        """
        if not 0 < radius_ratio < 1:
            raise ValueError(f"radius_ratio must be in (0, 1), got {radius_ratio!r}")
        pose = Pose.from_apex_base(apex, base)
        length = float(np.linalg.norm(np.asarray(apex, float) - np.asarray(base, float)))
        system, v0 = coordinate_system(system).initial_v0(length, radius_ratio * length)
        grid = HermiteGrid(*patches, v2_range=system.default_v2_range(length), poles=system.poles)
        return cls.from_function(system, pose, grid, v0)

    @classmethod
    def from_annulus(
        cls,
        apex,
        annulus,
        *,
        base=None,
        system: str | CoordinateSystem = "prolate",
        patches: tuple[int, int] = (8, 8),
        radius_ratio: float = DEFAULT_RADIUS_RATIO,
    ) -> "Surface":
        r"""The initial surface, closed at the mitral plane of annulus points.

        The local frame is :meth:`Pose.from_annulus`: origin at the ring's
        centre (or ``base`` projected on the plane), long axis along the
        plane's normal.  The apex lies at height ``h`` above the plane and
        ``s`` mm off the axis; the surface is the half-ellipsoid of
        semi-axes ``(h, b, b)``, ``b = radius_ratio * h``, sheared parallel
        to the plane so that its tip is the apex:

        .. math::

            \left(\frac{x_1}{h}\right)^2 + \frac{|x_\perp - x_1 s / h|^2}{b^2} \le 1,
            \quad x_1 \ge 0,

        with ``s`` the apex's offset vector.  A shear keeps the volume,
        ``2 pi h b^2 / 3``, and the base ring, the circle of radius ``b``
        in the plane.  The Hermite surface interpolates the shape's
        ``v0(v1, v2)`` at the nodes (values and slopes, as
        :meth:`from_apex_base`; the second local axis points towards the
        apex, so the nodes at ``v1 = 0`` and ``pi`` catch the tilt), then
        takes the smallest change in the L2 norm that makes it pass through
        the apex exactly: the apex pole stays on the axis and its tilted
        tangent plane lets the tip lie off it.  With the apex on the axis
        this is the surface of :meth:`from_apex_base`.

        Parameters
        ----------
        apex : (x, y, z)
            World point (mm).
        annulus : array (k, 3)
            ``k >= 3`` world points (mm) on the mitral ring.
        base : (x, y, z), optional
            Centre of the ring, if not the points' centroid.
        system : {"prolate", "spherical"} or CoordinateSystem
            A system with an apex pole (the cylindrical one has none).
        patches : (int, int)
        radius_ratio : float
            ``b / h`` in (0, 1); the apex must lie less than ``b`` from the axis.
        """
        if not 0 < radius_ratio < 1:
            raise ValueError(f"radius_ratio must be in (0, 1), got {radius_ratio!r}")
        pose = Pose.from_annulus(apex, annulus, base=base)
        height, offset = pose.to_local(np.asarray(apex, float))[:2]
        radius = radius_ratio * height
        if offset >= radius:
            raise ValueError(f"the apex lies {offset:.1f} mm from the normal of the mitral plane through its centre, "
                             f"more than the initial base radius ({radius:.1f} mm = radius_ratio x the apex's "
                             f"height {height:.1f} mm above the plane)")
        system = coordinate_system(system)
        if not system.poles:
            raise ValueError(f"the {system.name} system has no apex pole: a tilted mitral plane needs "
                             "'prolate' or 'spherical'")
        system, _ = system.initial_v0(height, radius)
        grid = HermiteGrid(*patches, v2_range=system.default_v2_range(height), poles=system.poles)

        def inside(local):  # < 0 inside the sheared half-ellipsoid, > 0 outside
            lateral = local[..., 1] - local[..., 0] * (offset / height)
            return (local[..., 0] / height) ** 2 + (lateral**2 + local[..., 2] ** 2) / radius**2 - 1.0

        def v0(v1, v2):
            # the one crossing of the coordinate curve from v0 = 0 (on the
            # axis, inside) outwards, by bisection to machine precision
            lo, hi = np.zeros(np.shape(v1)), np.ones(np.shape(v1))
            for _ in range(64):  # an upper bracket: the shape is bounded
                within = inside(system.to_cartesian(hi, v1, v2)) <= 0
                if not within.any():
                    break
                hi = np.where(within, 2 * hi, hi)
            for _ in range(64):
                mid = 0.5 * (lo + hi)
                below = inside(system.to_cartesian(mid, v1, v2)) <= 0
                lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
            return 0.5 * (lo + hi)

        # Hermite interpolation at the nodes, as from_apex_base (values and
        # slopes by central differences), onto the well-formed surfaces
        v2, v1 = np.meshgrid(grid.node_v2, grid.node_v1, indexing="ij")
        e1, e2 = 1e-5, 1e-5 * (grid.v2_range[1] - grid.v2_range[0])
        nodal = np.stack([
            v0(v1, v2),
            (v0(v1 + e1, v2) - v0(v1 - e1, v2)) / (2 * e1),
            (v0(v1, v2 + e2) - v0(v1, v2 - e2)) / (2 * e2),
            (v0(v1 + e1, v2 + e2) - v0(v1 - e1, v2 + e2) - v0(v1 + e1, v2 - e2) + v0(v1 - e1, v2 - e2)) / (4 * e1 * e2),
        ], axis=-1)
        params = grid.parameters(nodal)
        # then the smallest change in the L2 norm (mass matrix M of the
        # parameters) that puts the apex on the surface: p += M^-1 c r / (c M^-1 c)
        a = grid.constraints
        q1, q2, w = grid.quadrature(6)
        b = (grid.basis_matrix(q1, q2) @ a).toarray()
        apex_v0, apex_v1, apex_v2 = system.from_cartesian(pose.to_local(np.asarray(apex, float)))
        c = (grid.basis_matrix(apex_v1, apex_v2) @ a).toarray()[0]
        x = np.linalg.solve(b.T @ (b * w[:, None]), c)
        params = params + x * (apex_v0 - c @ params) / (c @ x)
        return cls(system, pose, grid, a @ params)

    @classmethod
    def from_function(
        cls, system: CoordinateSystem, pose: Pose, grid: HermiteGrid, v0: float | Callable
    ) -> "Surface":
        """Surface from a constant or from a function of ``v2`` alone, its
        nodal slopes taken by central differences."""
        coefficients = np.zeros(grid.shape)
        if callable(v0):
            v2 = grid.node_v2
            eps = 1e-6 * (grid.v2_range[1] - grid.v2_range[0])
            # one call for the nodes and their neighbours: a call costs more than its points
            value, after, before = v0(np.concatenate([v2, v2 + eps, v2 - eps])).reshape(3, -1)
            coefficients[:, :, 0] = value[:, None]
            coefficients[:, :, 2] = ((after - before) / (2 * eps))[:, None]
            coefficients = np.nan_to_num(coefficients)
        else:
            coefficients[:, :, 0] = float(v0)
        return cls(system, pose, grid, grid.constrain(coefficients))

    # -- evaluation -------------------------------------------------------

    def evaluate(self, v1, v2, d1: int = 0, d2: int = 0) -> np.ndarray:
        """``f`` or its partial derivatives at ``(v1, v2)``."""
        return self.grid.evaluate(self.coefficients, v1, v2, d1, d2)

    def radius(self, v1, v2) -> np.ndarray:
        """``max(f, 0)``: where ``f`` dips below 0 the surface lies on the axis
        (the focal segment for prolate coordinates) and encloses nothing."""
        return np.maximum(self.evaluate(v1, v2), 0.0)

    def radius_grid(self, v1, v2) -> np.ndarray:
        """:meth:`radius` on the tensor grid of the ``v2`` values (rows) by
        the ``v1`` values (columns), shape ``(len(v2), len(v1))``, by
        :meth:`HermiteGrid.evaluate_grid` (equal to rounding, in a fraction
        of the time)."""
        return np.maximum(self.grid.evaluate_grid(self.coefficients, np.ravel(v1), np.ravel(v2)), 0.0)

    def points(self, v1, v2) -> np.ndarray:
        """World points (mm) of the surface at ``(v1, v2)``, shape ``(..., 3)``."""
        return self.pose.to_world(self.system.to_cartesian(self.radius(v1, v2), v1, v2))

    def grid_points(self, v1, v2, *, local: bool = False) -> np.ndarray:
        """World points (mm) on the tensor grid of the ``v2`` values (rows)
        by the ``v1`` values (columns), shape ``(len(v2), len(v1), 3)``: as
        :meth:`points` there, ``f`` by :meth:`HermiteGrid.evaluate_grid`
        (equal to rounding, in a third of the time).  With ``local``, in
        the model's frame instead (:meth:`Pose.to_local` of them)."""
        v1, v2 = np.ravel(v1), np.ravel(v2)
        f = self.radius_grid(v1, v2)
        points = self.system.to_cartesian(f, v1, v2[:, None])
        return points if local else self.pose.to_world(points)

    def tip(self) -> np.ndarray:
        """World point (mm) of the surface's end at the start of the ``v2``
        range: the apex.  Where that end is a pole of the coordinates the
        whole end ring is one point, whose ``f`` is the value of the first
        node (the Hermite basis there is 1 on it and 0 on every other
        coefficient); elsewhere the centre of the ring (16 points)."""
        lo = self.grid.v2_range[0]
        if 0 in self.grid.pole_rows:
            f = max(float(self.coefficients[0, 0, 0]), 0.0)  # as radius()
            return self.pose.to_world(self.system.to_cartesian(f, 0.0, lo))
        return self.grid_points(np.linspace(0, 2 * np.pi, 16, endpoint=False), lo)[0].mean(axis=0)

    @property
    def base_v2(self) -> float:
        """The end of the ``v2`` range that lies in the base plane."""
        return self.grid.v2_range[0 if self._base_row(1) == 0 else 1]

    def base_radii(self, n: int = 64) -> np.ndarray:
        """Distances (mm) from the long axis to ``n`` points of the surface's
        ring in the base plane, evenly spaced in ``v1`` from 0: the radius of
        the cavity's opening at the mitral plane, angle by angle."""
        v1 = np.linspace(0, 2 * np.pi, n, endpoint=False)
        p = self.grid_points(v1, self.base_v2, local=True)[0]
        return np.hypot(p[:, 1], p[:, 2])

    def model_coordinates(self, world) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(v0, v1, v2)`` of world points."""
        return self.system.from_cartesian(self.pose.to_local(world))

    def contains(self, world) -> np.ndarray:
        """Whether world points lie in the closed cavity."""
        v0, v1, v2 = self.model_coordinates(world)
        lo, hi = self.grid.v2_range
        inside = (v2 >= lo) & (v2 <= hi)
        f = np.full(v0.shape, -np.inf)
        f[inside] = self.evaluate(v1[inside], v2[inside])
        return inside & (v0 <= f)

    def volume_ml(self, order: int = 8) -> float:
        """Volume of the closed cavity in mL.

        ``V = int int R(f(v1, v2), v2) dv1 dv2`` where ``R`` is the radial
        integral of the volume element (:meth:`CoordinateSystem.radial_volume`), by
        Gauss-Legendre quadrature on every patch.
        """
        _, v2, w = self.grid.quadrature(order)
        f = np.maximum(self.grid.quadrature_values(self.coefficients, order), 0.0)  # as radius()
        # the points lie on rows of one v2 each: its trigonometry once a row
        rows = v2.reshape(self.grid.n2 * order, -1)[:, :1]
        return float(w @ self.system.radial_volume(f.reshape(len(rows), -1), rows).ravel()) / 1000.0

    def wall_area_mm2(self, order: int = 4) -> float:
        """Area (mm^2) of the cavity's wall, the base plane left open:
        ``int int A_K dv1 dv2`` (paper eq. 16-17,
        :func:`spheroseg.energy.area_energy`) by Gauss-Legendre quadrature,
        ``order`` points a patch along each direction."""
        model = SampledSurface(self.system, self.pose, self.grid, order)
        return area_energy(model, model.parameters(self.coefficients))

    def bounding_box(self, n: int = 48) -> tuple[np.ndarray, np.ndarray]:
        """World bounding box (min, max corners) of the closed cavity."""
        v2, v1 = np.meshgrid(np.linspace(*self.grid.v2_range, n), np.linspace(0, 2 * np.pi, 2 * n), indexing="ij")
        p = np.concatenate([self.points(v1, v2).reshape(-1, 3), self.pose.origin[None]])
        margin = 0.02 * np.ptp(p, axis=0).max()  # between sampled points
        return p.min(0) - margin, p.max(0) + margin

    def mask(self, grid: ImageGrid) -> np.ndarray:
        """Boolean mask ``[z, y, x]`` of voxel centres inside the closed
        cavity: :func:`spheroseg.raster.surface_mask` of this surface."""
        from .._compiled.raster import surface_mask

        return surface_mask(self, grid)

    def mesh(self, n_v1: int = 64, n_v2: int = 32, *, closed: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Triangle mesh of the cavity wall, world mm, outward-facing.

        Poles become one vertex; with ``closed=True`` every other end of the
        ``v2`` range is capped by a fan around the axis (the base plane, and
        for the cylindrical system the far end), so the mesh is watertight.
        With ``closed=False`` the base-plane cap is left open, as in the
        CETUS reference meshes.

        Returns
        -------
        points : array (n, 3), float
        faces : array (m, 3), int
        """
        v2 = np.linspace(*self.grid.v2_range, n_v2 + 1)
        v1 = np.arange(n_v1) * (2 * np.pi / n_v1)
        pole_at = {0: 0 in self.grid.pole_rows, n_v2: self.grid.n2 in self.grid.pole_rows}
        local = [None] * (n_v2 + 1)
        ring_start = []
        points = []
        count = 0
        radii = self.radius(*np.meshgrid(v1, v2))  # [ring, v1]: one evaluation (v1[0] = 0 for a pole)
        for r, v in enumerate(v2):
            if pole_at.get(r, False):
                ring = self.system.to_cartesian(radii[r, :1], 0.0, v)
            else:
                ring = self.system.to_cartesian(radii[r], v1, v)
            local[r] = ring
            ring_start.append(count)
            points.append(ring)
            count += len(ring)
        faces = []
        for r in range(n_v2):
            a, b = ring_start[r], ring_start[r + 1]
            na, nb = len(local[r]), len(local[r + 1])
            j = np.arange(n_v1)
            jn = (j + 1) % n_v1
            if na == 1:
                faces.append(np.stack([np.full(n_v1, a), b + j, b + jn], 1))
            elif nb == 1:
                faces.append(np.stack([a + j, np.full(n_v1, b), a + jn], 1))
            else:
                faces.append(np.stack([a + j, b + j, b + jn], 1))
                faces.append(np.stack([a + j, b + jn, a + jn], 1))
        base_row = self._base_row(n_v2)
        for r in (0, n_v2):
            if len(local[r]) == 1 or (r == base_row and not closed):
                continue
            centre = self.system.to_cartesian(0.0, 0.0, v2[r])[None]
            c = count
            points.append(centre)
            count += 1
            j = ring_start[r] + np.arange(n_v1)
            jn = ring_start[r] + (np.arange(n_v1) + 1) % n_v1
            # each ring edge runs opposite to its use by the wall triangles
            faces.append(np.stack([np.full(n_v1, c), j, jn] if r == 0 else [np.full(n_v1, c), jn, j], 1))
        points = self.pose.to_world(np.concatenate(points))
        faces = np.concatenate(faces).astype(np.int64)
        # fix the orientation once, by the sign of the enclosed volume of the
        # closed mesh (the open one inherits it)
        if closed:
            flip = signed_volume(points, faces) < 0
        else:
            flip = signed_volume(*self.mesh(n_v1, n_v2, closed=True)) < 0
        if flip:
            faces = faces[:, ::-1].copy()
        return points, faces

    def _base_row(self, n_v2: int) -> int:
        # the end of the v2 range that lies on the base plane x1 = 0
        ends = [0, n_v2]
        x1 = [abs(self.system.to_cartesian(1.0, 0.0, v)[0]) for v in self.grid.v2_range]
        return ends[int(np.argmin(x1))]

    # -- refinement and serialisation -------------------------------------

    def refine(self) -> "Surface":
        """The same surface on a grid with twice the patches (exact)."""
        grid, coefficients = self.grid.refine(self.coefficients)
        return Surface(self.system, self.pose, grid, coefficients)

    def with_coefficients(self, coefficients) -> "Surface":
        return Surface(self.system, self.pose, self.grid, coefficients)

    def to_dict(self) -> dict:
        return {
            "coordinate_system": self.system.to_dict(),
            "pose": self.pose.to_dict(),
            "patches": [self.grid.n1, self.grid.n2],
            "v2_range": list(self.grid.v2_range),
            "coefficient_order": ["f", "df/dv1", "df/dv2", "d2f/dv1dv2"],
            "coefficients": self.coefficients.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "Surface":
        system = coordinate_system(d["coordinate_system"])
        grid = HermiteGrid(*d["patches"], v2_range=tuple(d["v2_range"]), poles=system.poles)
        return cls(system, Pose.from_dict(d["pose"]), grid, np.array(d["coefficients"]))
