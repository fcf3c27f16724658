"""Energies of the paper (section 4) and their gradients in the Hermite
parameters.

Everything is evaluated at fixed sample points ``(v1_q, v2_q)`` with
quadrature weights ``w_q`` (Gauss-Legendre per patch), so the cost of a
gradient is set by the model, never by the image.  Gradients are with
respect to the free parameters ``p`` of the surface (the Hermite
coefficients are ``H = A p``, see :mod:`spheroseg.hermite`).

Data term (paper eqs. 14, 20-22).  With ``r(u) = (u - c_in)^2 - (u - c_out)^2``

    F(p) = int dv1 dv2 int_0^f r(u(x(v0, v1, v2))) V(v0, v1, v2) dv0   (+ const)
    dF/dp_i = int dv1 dv2  f_i r(u(x_K)) V_K                           (eq. 22)

where ``V = h0 h1 h2`` (eq. 19) and ``x_K`` is the surface point.  ``c_in``
and ``c_out`` are constants (global Chan-Vese, and the paper's fast mode
where only ``(c_in + c_out) / 2`` matters) or fields over ``(v1, v2)``
(means local to each surface point); they are frozen while differentiating,
which is exact at their optimum (the means) and is how they are used.

Area term (eqs. 16-17, 23-24): ``F = int A_K dv1 dv2``.

Landmarks: ``F = sum_k (h0_k (v0_k - f(v1_k, v2_k)))^2``, the squared
distance (mm, to first order) from each landmark to the surface along
``v0``, with ``h0_k`` taken at the landmark.

References
----------
.. [1] Duan Q, Angelini ED, Laine AF et al. Variational segmentation
   framework in prolate spheroidal coordinates for 3D real-time
   echocardiography. Proc. SPIE 6144, 61444A (2006). doi:10.1117/12.653692
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from .coords import CoordinateSystem, Pose
from .discretisation import discretise
from .hermite import HermiteGrid

__all__ = [
    "SampledSurface",
    "Geometry",
    "region_force",
    "normal_speed",
    "data_energy",
    "data_gradient",
    "area_energy",
    "area_gradient",
    "Landmarks",
    "landmark_energy",
    "landmark_gradient",
]

Sampler = Callable[[np.ndarray], np.ndarray]


@dataclass
class Geometry:
    """The surface at the sample points: ``f`` and its slopes, local and
    world points, scale factors, unit outward normal (world), ``A_K``, ``V_K``."""

    f: np.ndarray
    f1: np.ndarray
    f2: np.ndarray
    local: np.ndarray
    world: np.ndarray
    jacobian: np.ndarray
    normal: np.ndarray
    area: np.ndarray
    volume: np.ndarray


class SampledSurface:
    """Fixed sample points of a Hermite surface and the sparse matrices that
    map its parameters to ``f``, ``df/dv1`` and ``df/dv2`` there.

    Parameters
    ----------
    system, pose, grid
        The surface model.
    order : int
        Gauss-Legendre points per patch along each direction (paper: 8).
    """

    def __init__(self, system: CoordinateSystem, pose: Pose, grid: HermiteGrid, order: int = 8):
        self.system, self.pose, self.grid, self.order = system, pose, grid, order
        self.discretisation = d = discretise(grid, order)
        self.v1, self.v2, self.weights, self.constraints = d.v1, d.v2, d.weights, d.constraints
        self.b_f, self.b_1, self.b_2, self.mass_matrix = d.b_f, d.b_1, d.b_2, d.mass

    @property
    def n_parameters(self) -> int:
        return self.constraints.shape[1]

    @property
    def n_samples(self) -> int:
        return len(self.weights)

    def parameters(self, coefficients) -> np.ndarray:
        return self.grid.parameters(coefficients)

    def coefficients(self, parameters) -> np.ndarray:
        return (self.constraints @ parameters).reshape(self.grid.shape)

    def geometry(self, p: np.ndarray) -> Geometry:
        """Evaluate the surface at the sample points."""
        f, f1, f2 = self.b_f @ p, self.b_1 @ p, self.b_2 @ p
        local = self.system.to_cartesian(f, self.v1, self.v2)
        jac = self.system.jacobian(f, self.v1, self.v2)
        # tangents x_v1 = f1 J0 + J1, x_v2 = f2 J0 + J2 (eq. 16)
        t1 = f1[:, None] * jac[:, :, 0] + jac[:, :, 1]
        t2 = f2[:, None] * jac[:, :, 0] + jac[:, :, 2]
        n = np.cross(t1, t2)
        area = np.linalg.norm(n, axis=1)
        # orient outwards: along +dx/dv0
        sign = np.sign(np.einsum("ij,ij->i", n, jac[:, :, 0]))
        n = n * (sign / np.where(area > 0, area, 1.0))[:, None]
        h0, h1, h2 = self.system.scale_factors(f, self.v1, self.v2)
        return Geometry(
            f=f,
            f1=f1,
            f2=f2,
            local=local,
            world=self.pose.to_world(local),
            jacobian=jac,
            normal=n @ self.pose.rotation.T,
            area=area,
            volume=h0 * h1 * h2,
        )


def region_force(u, c_in, c_out) -> np.ndarray:
    """``r = (u - c_in)^2 - (u - c_out)^2 = 2 (c_out - c_in)(u - (c_in + c_out)/2)``:
    the change of the two-region energy per unit volume moved from outside
    to inside (paper eq. 22's integrand without ``f_i V_K``)."""
    return (c_out - c_in) * (2.0 * u - c_in - c_out)


def normal_speed(u, c_in, c_out, scale, clip: float = 1.0) -> np.ndarray:
    """Outward normal speed of the surface, in steps, from the region force:
    ``-clip(r / scale, -clip, clip)`` with ``r`` of :func:`region_force`.

    This is the descent direction of paper eq. 22 per unit area of surface:
    ``dF/dp_i = int f_i r V_K``, and moving the surface outwards by ``dn``
    where ``r > 0`` raises ``F`` by ``r dn dA``, so the surface moves against
    ``r``.  Dividing by ``scale`` (the squared contrast) makes it
    dimensionless; the clip bounds a step in mm whatever the image's units
    (a clip above 1 lets a heavy-tailed ``u``, speckle intensity, average
    out before it is bounded: clipping a skewed distribution at 1 biases
    where its mean force vanishes).
    A point with no finite grey level does not move, except a point off the
    image's data (``u`` not finite): it is pulled back in (speed -1), since
    the cavity is where the data are.
    """
    r = region_force(u, c_in, c_out) / scale
    return np.where(np.isfinite(r), -np.clip(r, -clip, clip), np.where(np.isfinite(u), 0.0, -1.0))


def data_energy(model: SampledSurface, p, sampler: Sampler, c_in, c_out, n_radial: int = 24) -> float:
    """``int dv1 dv2 int_0^f r(u) V dv0`` by Gauss-Legendre along each ray.

    For checking :func:`data_gradient`; an iteration never needs it.
    """
    f = model.b_f @ p
    x, w = np.polynomial.legendre.leggauss(n_radial)
    t, w = (x + 1) / 2, w / 2
    v0 = f[:, None] * t[None, :]
    v1 = np.broadcast_to(model.v1[:, None], v0.shape)
    v2 = np.broadcast_to(model.v2[:, None], v0.shape)
    u = sampler(model.pose.to_world(model.system.to_cartesian(v0, v1, v2)))
    c_in = np.broadcast_to(np.asarray(c_in, float), f.shape)[:, None]
    c_out = np.broadcast_to(np.asarray(c_out, float), f.shape)[:, None]
    radial = (region_force(u, c_in, c_out) * model.system.volume_element(v0, v1, v2) * w).sum(1) * f
    return float(model.weights @ radial)


def data_gradient(model: SampledSurface, p, sampler: Sampler, c_in, c_out, geometry: Geometry | None = None):
    """``dF/dp = B^T W (r(u_K) V_K)`` (paper eq. 22)."""
    g = geometry or model.geometry(p)
    r = region_force(sampler(g.world), c_in, c_out)
    return model.b_f.T @ (model.weights * r * g.volume)


def area_energy(model: SampledSurface, p) -> float:
    """Surface area (mm^2), ``int A_K dv1 dv2`` (eq. 16-17)."""
    return float(model.weights @ model.geometry(p).area)


def area_gradient(model: SampledSurface, p, geometry: Geometry | None = None) -> np.ndarray:
    """Paper eq. 23, with the ``v0``-derivatives of the scale factors (eq. 24)."""
    g = geometry or model.geometry(p)
    s = model.system
    h0, h1, h2 = s.scale_factors(g.f, model.v1, model.v2)
    d0, d1, d2 = s.scale_factor_derivatives(g.f, model.v1, model.v2)
    a = np.where(g.area > 0, g.area, np.inf)
    coef_1 = g.f1 * (h0 * h2) ** 2 / a
    coef_2 = g.f2 * (h0 * h1) ** 2 / a
    coef_f = (
        h1 * h2 * (d1 * h2 + h1 * d2)
        + g.f1**2 * h0 * h2 * (d0 * h2 + h0 * d2)
        + g.f2**2 * h0 * h1 * (d0 * h1 + h0 * d1)
    ) / a
    w = model.weights
    return model.b_1.T @ (w * coef_1) + model.b_2.T @ (w * coef_2) + model.b_f.T @ (w * coef_f)


@dataclass
class Landmarks:
    """World points the surface should pass through, in model terms."""

    v0: np.ndarray
    h0: np.ndarray
    basis: np.ndarray  # f at the landmarks from the parameters, (landmarks, parameters): a few dense rows

    @classmethod
    def from_world(cls, model: SampledSurface, points) -> "Landmarks":
        points = np.asarray(points, dtype=float).reshape(-1, 3)
        if not np.all(np.isfinite(points)):
            raise ValueError("landmarks must be finite points")
        v0, v1, v2 = model.system.from_cartesian(model.pose.to_local(points))
        lo, hi = model.grid.v2_range
        # a point on the base plane itself (the tracker's base ring) comes
        # back from the coordinate map a rounding error beyond it
        rounding = 1e-9 * max(1.0, abs(hi - lo))
        if np.any((v2 < lo - rounding) | (v2 > hi + rounding)):
            raise ValueError("a landmark lies beyond the base plane (outside the cavity's range)")
        v2 = np.clip(v2, lo, hi)
        h0 = model.system.scale_factors(v0, v1, v2)[0]
        # dense: for a few points (the apex) the sparse basis times the
        # constraints costs several times more, and the descent multiplies
        # by the dense rows
        return cls(v0, h0, model.grid.parameter_rows(v1, v2))

    def __len__(self) -> int:
        return len(self.v0)


def landmark_energy(landmarks: Landmarks, p) -> float:
    res = landmarks.h0 * (landmarks.v0 - landmarks.basis @ p)
    return float(res @ res)


def landmark_gradient(landmarks: Landmarks, p) -> np.ndarray:
    res = landmarks.v0 - landmarks.basis @ p
    return -2.0 * (landmarks.basis.T @ (landmarks.h0**2 * res))
