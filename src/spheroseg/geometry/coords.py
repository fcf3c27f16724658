"""Curvilinear coordinate systems of the surface model, and the pose.

A surface is a graph ``v0 = f(v1, v2)`` in one of three orthogonal systems
(paper eq. 2), all in the model's local frame whose first axis ``x1`` is the
long axis of the ventricle, pointing from the base towards the apex:

============  =======  ======  =================  ==========================
system        v0       v1      v2                 local Cartesian
============  =======  ======  =================  ==========================
prolate       lambda   theta   mu (0 at apex)     x1 = d cosh(l) cos(mu)
                                                  x2 = d sinh(l) sin(mu) cos(th)
                                                  x3 = d sinh(l) sin(mu) sin(th)
spherical     r        theta   phi (0 at apex)    x1 = r cos(phi)
                                                  x2 = r sin(phi) cos(th)
                                                  x3 = r sin(phi) sin(th)
cylindrical   r        theta   z (0 at base)      x1 = z, x2 = r cos(th),
                                                  x3 = r sin(th)
============  =======  ======  =================  ==========================

Lengths are in millimetres; angles in radians. The local origin is the base
point (the centre of the mitral plane), so the base plane is ``x1 = 0``: the
prolate and spherical ``v2 = pi/2`` coordinate surface and the cylindrical
``z = 0`` plane.  This makes the cavity, closed at the base, the region
``v0 <= f(v1, v2)`` over the model's ``v2`` range, with no clipping.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

__all__ = [
    "CoordinateSystem",
    "ProlateSpheroidal",
    "Spherical",
    "Cylindrical",
    "Pose",
    "coordinate_system",
    "annulus_plane",
]

_TWO_PI = 2.0 * np.pi


def _stack(*components) -> np.ndarray:
    """Points ``(..., 3)`` from their coordinates, broadcast together.  The
    systems compute each on the shapes of the coordinates it depends on (a
    tensor grid of a row and a column: the trigonometry of a row and of a
    column), then broadcast."""
    return np.stack(np.broadcast_arrays(*components), axis=-1)


def _check_points(x: np.ndarray, name: str = "points") -> np.ndarray:
    x = np.asarray(x, dtype=float)
    if x.shape[-1:] != (3,):
        raise ValueError(f"{name} must have shape (..., 3), got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name} must be finite")
    return x


class CoordinateSystem(ABC):
    """Orthogonal system ``(v0, v1, v2)`` with ``v1 = theta`` periodic.

    Subclasses give the map to local Cartesian coordinates, its inverse, the
    scale factors ``h_i = |dx/dv_i|`` and their ``v0``-derivatives (paper
    eq. 24), and the radial integral of the volume element used for volumes.
    """

    #: name used on the command line and in files
    name: str = ""
    #: values of v2 at which the surface degenerates to one point (a pole)
    poles: tuple[float, ...] = ()

    @abstractmethod
    def to_cartesian(self, v0, v1, v2) -> np.ndarray:
        """Local Cartesian coordinates, shape ``(..., 3)``, in mm."""

    @abstractmethod
    def from_cartesian(self, x) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(v0, v1, v2)`` of local points ``x`` (shape ``(..., 3)``);
        ``v1`` in ``[0, 2 pi)``."""

    @abstractmethod
    def jacobian(self, v0, v1, v2) -> np.ndarray:
        """``dx/dv``, shape ``(..., 3, 3)``: column ``i`` is ``dx/dv_i``."""

    @abstractmethod
    def scale_factors(self, v0, v1, v2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(h0, h1, h2)``, lengths of ``dx/dv_i`` (mm per unit of v_i)."""

    @abstractmethod
    def scale_factor_derivatives(self, v0, v1, v2):
        """``(dh0/dv0, dh1/dv0, dh2/dv0)``."""

    @abstractmethod
    def radial_volume(self, f, v2) -> np.ndarray:
        """``int_0^f h0 h1 h2 dv0`` (mm^3 per unit of v1 v2), for the volume
        enclosed by ``v0 <= f``; the systems here do not depend on v1."""

    @abstractmethod
    def default_v2_range(self, length: float) -> tuple[float, float]:
        """v2 interval of a cavity of apex-to-base ``length`` mm closed at
        the base plane ``x1 = 0``."""

    @abstractmethod
    def initial_v0(self, length: float, radius: float):
        """Return ``(system, v0)``: the system fitted to a cavity of this
        size (e.g. the focal length) and the ``v0`` of a constant surface
        through the apex, ``length`` mm from the base, with base radius
        ``radius``; or a callable ``v0(v2)`` where no constant fits."""

    def volume_element(self, v0, v1, v2) -> np.ndarray:
        """``h0 h1 h2`` (paper eq. 19)."""
        h0, h1, h2 = self.scale_factors(v0, v1, v2)
        return h0 * h1 * h2

    def to_dict(self) -> dict:
        return {"name": self.name}


@dataclass(frozen=True)
class ProlateSpheroidal(CoordinateSystem):
    """Prolate spheroidal coordinates ``(lambda, theta, mu)`` with foci at
    ``x1 = +-focal_length`` (paper eq. 1 with the focal length restored).

    Parameters
    ----------
    focal_length : float
        ``d`` in mm, > 0.
    """

    focal_length: float = 40.0
    name = "prolate"
    poles = (0.0, np.pi)

    def __post_init__(self):
        d = self.focal_length
        if not (np.isfinite(d) and d > 0):
            raise ValueError(f"focal_length must be a positive finite number, got {d!r}")

    def to_cartesian(self, v0, v1, v2):
        d = self.focal_length
        lam, th, mu = (np.asarray(v, dtype=float) for v in (v0, v1, v2))
        rho = d * np.sinh(lam) * np.sin(mu)
        return _stack(d * np.cosh(lam) * np.cos(mu), rho * np.cos(th), rho * np.sin(th))

    def from_cartesian(self, x):
        x = np.asarray(x, dtype=float)
        rho = np.hypot(x[..., 1], x[..., 2])
        # x1 + i rho = d cosh(lambda + i mu): the principal arccosh gives
        # lambda >= 0 and mu in [0, pi] to machine precision, also near the foci.
        w = np.arccosh((x[..., 0] + 1j * rho) / self.focal_length)
        theta = np.mod(np.arctan2(x[..., 2], x[..., 1]), _TWO_PI)
        return np.abs(w.real), theta, np.abs(w.imag)

    def jacobian(self, v0, v1, v2):
        d = self.focal_length
        lam, th, mu = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (v0, v1, v2)))
        sl, cl, sm, cm, st, ct = np.sinh(lam), np.cosh(lam), np.sin(mu), np.cos(mu), np.sin(th), np.cos(th)
        d_lam = np.stack([sl * cm, cl * sm * ct, cl * sm * st], -1)
        d_th = np.stack([0 * lam, -sl * sm * st, sl * sm * ct], -1)
        d_mu = np.stack([-cl * sm, sl * cm * ct, sl * cm * st], -1)
        return d * np.stack([d_lam, d_th, d_mu], -1)

    def scale_factors(self, v0, v1, v2):
        d = self.focal_length
        s = d * np.sqrt(np.sinh(v0) ** 2 + np.sin(v2) ** 2)
        return s, d * np.sinh(v0) * np.sin(v2) + 0.0 * v1, s

    def scale_factor_derivatives(self, v0, v1, v2):
        d = self.focal_length
        root = np.sqrt(np.sinh(v0) ** 2 + np.sin(v2) ** 2)
        ds = d * np.sinh(v0) * np.cosh(v0) / np.where(root > 0, root, np.inf)
        return ds, d * np.cosh(v0) * np.sin(v2) + 0.0 * v1, ds

    def radial_volume(self, f, v2):
        c = np.cosh(f)
        return self.focal_length**3 * np.sin(v2) * ((c**3 - 1.0) / 3.0 - np.cos(v2) ** 2 * (c - 1.0))

    def default_v2_range(self, length):
        return (0.0, np.pi / 2)

    def initial_v0(self, length, radius):
        # The paper's lambda = 1 coordinate surface passes through the apex:
        # d = length / cosh(1) puts the focus a third of the way down from
        # the apex, far from the wall, so the surface can move without
        # meeting the focal singularity.  The initial surface is the
        # half-ellipsoid of semi-axes (length, radius, radius) as lambda(mu).
        a, b = float(length), float(radius)
        d = a / np.cosh(1.0)

        def v0(mu):
            s2, c2 = np.sin(mu) ** 2, np.cos(mu) ** 2
            cosh_l = np.sqrt((1 + d * d * s2 / b**2) / (d * d * c2 / a**2 + d * d * s2 / b**2))
            return np.arccosh(np.maximum(cosh_l, 1.0))

        return ProlateSpheroidal(d), v0

    def to_dict(self):
        return {"name": self.name, "focal_length": self.focal_length}


@dataclass(frozen=True)
class Spherical(CoordinateSystem):
    """Spherical coordinates ``(r, theta, phi)``, ``phi`` measured from the
    long axis (``phi = 0`` at the apex), centred on the base point."""

    name = "spherical"
    poles = (0.0, np.pi)

    def to_cartesian(self, v0, v1, v2):
        r, th, ph = (np.asarray(v, dtype=float) for v in (v0, v1, v2))
        rho = r * np.sin(ph)
        return _stack(r * np.cos(ph), rho * np.cos(th), rho * np.sin(th))

    def from_cartesian(self, x):
        x = np.asarray(x, dtype=float)
        rho = np.hypot(x[..., 1], x[..., 2])
        return (
            np.hypot(x[..., 0], rho),
            np.mod(np.arctan2(x[..., 2], x[..., 1]), _TWO_PI),
            np.arctan2(rho, x[..., 0]),
        )

    def jacobian(self, v0, v1, v2):
        r, th, ph = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (v0, v1, v2)))
        sp_, cp, st, ct = np.sin(ph), np.cos(ph), np.sin(th), np.cos(th)
        d_r = np.stack([cp, sp_ * ct, sp_ * st], -1)
        d_th = np.stack([0 * r, -r * sp_ * st, r * sp_ * ct], -1)
        d_ph = np.stack([-r * sp_, r * cp * ct, r * cp * st], -1)
        return np.stack([d_r, d_th, d_ph], -1)

    def scale_factors(self, v0, v1, v2):
        one = np.ones_like(np.asarray(v0 + v1 + v2, dtype=float))
        return one, v0 * np.sin(v2) + 0.0 * v1, v0 * one

    def scale_factor_derivatives(self, v0, v1, v2):
        one = np.ones_like(np.asarray(v0 + v1 + v2, dtype=float))
        return 0.0 * one, np.sin(v2) * one, one

    def radial_volume(self, f, v2):
        return np.sin(v2) * f**3 / 3.0

    def default_v2_range(self, length):
        return (0.0, np.pi / 2)

    def initial_v0(self, length, radius):
        # the hemi-ellipsoid with semi-axes (length, radius, radius), as r(phi)
        a, b = float(length), float(radius)
        return self, lambda phi: a * b / np.sqrt((b * np.cos(phi)) ** 2 + (a * np.sin(phi)) ** 2)


@dataclass(frozen=True)
class Cylindrical(CoordinateSystem):
    """Cylindrical coordinates ``(r, theta, z)`` with ``z = x1`` along the
    long axis, ``z = 0`` on the base plane and ``z = height`` beyond the apex.

    There is no pole: the cavity is capped by the plane ``z = height``, where
    the surface may shrink to the axis (``f = 0``).
    """

    height: float = 100.0
    name = "cylindrical"
    poles = ()

    def __post_init__(self):
        if not (np.isfinite(self.height) and self.height > 0):
            raise ValueError(f"height must be a positive finite number, got {self.height!r}")

    def to_cartesian(self, v0, v1, v2):
        r, th, z = (np.asarray(v, dtype=float) for v in (v0, v1, v2))
        return _stack(z, r * np.cos(th), r * np.sin(th))

    def from_cartesian(self, x):
        x = np.asarray(x, dtype=float)
        return (
            np.hypot(x[..., 1], x[..., 2]),
            np.mod(np.arctan2(x[..., 2], x[..., 1]), _TWO_PI),
            x[..., 0].copy(),
        )

    def jacobian(self, v0, v1, v2):
        r, th, z = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (v0, v1, v2)))
        zero, one, st, ct = 0 * r, 0 * r + 1, np.sin(th), np.cos(th)
        return np.stack([np.stack([zero, ct, st], -1), np.stack([zero, -r * st, r * ct], -1), np.stack([one, zero, zero], -1)], -1)

    def scale_factors(self, v0, v1, v2):
        one = np.ones_like(np.asarray(v0 + v1 + v2, dtype=float))
        return one, v0 * one, one

    def scale_factor_derivatives(self, v0, v1, v2):
        one = np.ones_like(np.asarray(v0 + v1 + v2, dtype=float))
        return 0.0 * one, one, 0.0 * one

    def radial_volume(self, f, v2):
        return 0.0 * v2 + f**2 / 2.0

    def default_v2_range(self, length):
        return (0.0, self.height)

    def initial_v0(self, length, radius):
        # room beyond the apex so the cavity can grow there
        a, b = float(length), float(radius)
        system = Cylindrical(height=1.15 * a)
        return system, lambda z: b * np.sqrt(np.clip(1.0 - (z / a) ** 2, 0.0, None))

    def to_dict(self):
        return {"name": self.name, "height": self.height}


def coordinate_system(spec: dict | str | CoordinateSystem) -> CoordinateSystem:
    """A coordinate system from its name or its ``to_dict()``."""
    if isinstance(spec, CoordinateSystem):
        return spec
    if isinstance(spec, str):
        spec = {"name": spec}
    spec = dict(spec)
    name = spec.pop("name", None)
    classes = {"prolate": ProlateSpheroidal, "spherical": Spherical, "cylindrical": Cylindrical}
    if name not in classes:
        raise ValueError(f"coordinate system must be one of {sorted(classes)}, got {name!r}")
    return classes[name](**spec)


def annulus_plane(annulus) -> tuple[np.ndarray, np.ndarray]:
    """The least-squares plane of points of the mitral annulus.

    The plane through the centroid ``c`` of the ``k >= 3`` points whose
    normal ``n`` is the right singular vector of the centred points with the
    smallest singular value: it minimises ``sum_i ((a_i - c) . n)^2``.

    Parameters
    ----------
    annulus : array (k, 3)
        World points (mm) on the mitral ring, ``k >= 3``, not all on a line.

    Returns
    -------
    centre : array (3,)
        The centroid of the points (it lies on the plane), mm.
    normal : array (3,)
        Unit normal, unoriented (sign as the decomposition gives it).
    """
    try:
        points = np.asarray(annulus, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"annulus must be points (x, y, z in mm), got {annulus!r}") from None
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"annulus must be an array of points (k, 3), got shape {points.shape}")
    if len(points) < 3:
        raise ValueError(f"the mitral plane needs at least 3 annulus points, got {len(points)}")
    if not np.all(np.isfinite(points)):
        raise ValueError("annulus points must be finite")
    centre = points.mean(0)
    _, spread, vt = np.linalg.svd(points - centre, full_matrices=False)
    if spread[1] <= 1e-3 * spread[0]:
        raise ValueError("the annulus points lie on a line (or on one point): they do not define the mitral plane")
    return centre, vt[2]


def _frame(e1: np.ndarray) -> np.ndarray:
    """A proper rotation whose first column is the unit vector ``e1``; the
    other two are a fixed, deterministic completion."""
    helper = np.eye(3)[np.argmin(np.abs(e1))]
    e2 = helper - (helper @ e1) * e1
    e2 /= np.linalg.norm(e2)
    # e1 x e2 as np.cross computes it, without its checks (called per pose)
    e3 = e1[[1, 2, 0]] * e2[[2, 0, 1]] - e1[[2, 0, 1]] * e2[[1, 2, 0]]
    return np.column_stack([e1, e2, e3])


@dataclass(frozen=True)
class Pose:
    """Places the model's local frame in world space (ITK physical space, mm).

    ``world = origin + rotation @ local``; the columns of ``rotation`` are
    the local axes in world coordinates, the first being the long axis from
    the base towards the apex.
    """

    origin: np.ndarray
    rotation: np.ndarray

    def __post_init__(self):
        origin = _check_points(self.origin, "origin").reshape(3)
        rotation = np.asarray(self.rotation, dtype=float).reshape(3, 3)
        eye = np.eye(3)  # np.allclose(R^T R, I, atol=1e-9) spelled out, without its checks (per pose)
        if not np.all(np.abs(rotation.T @ rotation - eye) <= 1e-9 + 1e-5 * eye) or np.linalg.det(rotation) < 0:
            raise ValueError("rotation must be a proper orthonormal 3x3 matrix")
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "rotation", rotation)

    @classmethod
    def from_apex_base(cls, apex, base) -> "Pose":
        """Frame with its origin at ``base`` and its first axis towards
        ``apex`` (world mm); the two other axes are a fixed, deterministic
        completion."""
        apex = _check_points(apex, "apex").reshape(3)
        base = _check_points(base, "base").reshape(3)
        axis = apex - base
        length = float(np.linalg.norm(axis))
        if length < 1e-6:
            raise ValueError("apex and base must be distinct points")
        return cls(base, _frame(axis / length))

    @classmethod
    def from_annulus(cls, apex, annulus, *, base=None) -> "Pose":
        """Frame of the mitral plane: its origin on the plane, its first axis
        the plane's normal towards ``apex``.

        The plane is the least-squares plane of the annulus points
        (:func:`annulus_plane`); the origin is ``base`` projected on it, or
        the points' centroid when ``base`` is None.  The apex need not lie
        on the axis: the second axis points towards its offset from it
        (when it has one), so ``apex`` has local coordinates
        ``(h, s, 0)``, ``h > 0`` its height above the plane and ``s >= 0``
        its distance from the axis.

        Parameters
        ----------
        apex : (x, y, z)
            World point (mm) on the apex side of the plane.
        annulus : array (k, 3)
            ``k >= 3`` world points (mm) of the mitral ring.
        base : (x, y, z), optional
            A centre of the ring other than the centroid (projected on the
            plane).
        """
        apex = _check_points(apex, "apex").reshape(3)
        centre, normal = annulus_plane(annulus)
        if base is not None:
            base = _check_points(base, "base").reshape(3)
            centre = base - ((base - centre) @ normal) * normal
        offset = apex - centre
        height = float(offset @ normal)
        spread = np.linalg.norm(np.asarray(annulus, float) - centre, axis=1).max()
        if abs(height) <= 1e-6 * max(spread, 1.0):
            raise ValueError("the apex lies in the mitral plane of the annulus points")
        e1 = normal if height > 0 else -normal
        lateral = offset - (offset @ e1) * e1
        if np.linalg.norm(lateral) <= 1e-9 * abs(height):
            return cls(centre, _frame(e1))
        e2 = lateral / np.linalg.norm(lateral)
        return cls(centre, np.column_stack([e1, e2, np.cross(e1, e2)]))

    @property
    def axis(self) -> np.ndarray:
        """Unit long axis (base to apex), world coordinates."""
        return self.rotation[:, 0]

    def to_world(self, local) -> np.ndarray:
        return np.asarray(local) @ self.rotation.T + self.origin

    def to_local(self, world) -> np.ndarray:
        return (np.asarray(world) - self.origin) @ self.rotation

    def to_dict(self) -> dict:
        return {"origin": self.origin.tolist(), "rotation": self.rotation.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "Pose":
        return cls(np.array(d["origin"]), np.array(d["rotation"]))
