"""One level of the descent: the Hermite parameters moved by the region force.

The paper's scheme (eq. 25) is ``H <- H - dt dF/dH`` with ``dF/dH`` of
eq. 22.  Here the force is a normal displacement of at most ``step`` mm
(:meth:`spheroseg.backends.NumpyBackend.displacement`), converted to ``v0``
and projected onto the Hermite space by least squares with the mass matrix
``M = B^T W B``: the exact form of eq. 10's normalisation, so the update is
``dH = -dt M^-1 dF/dH`` with the force per unit area instead of per unit
``v1 v2``.  Two terms join that least-squares problem: an implicit
thin-plate step towards the reference (initial) shape, and landmark rows.
The new parameters solve

    (M + a T + L^T Omega L) p+ = M p + B^T W dv0 + a T p_ref + L^T Omega (L p + r)

with ``T`` the thin-plate matrix, ``a`` the smoothness, ``L`` the surface
at the landmarks and ``r`` the landmarks' residuals along ``v0``, each
clipped to a step.  Subtracting the system times ``p`` from both sides
gives the step itself,

    dp = p+ - p = S (B^T W dv0 + a T (p_ref - p) + L^T Omega r),

with ``S`` the system's inverse: one dense product a step (``T`` is sparse).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from scipy.linalg import blas

from .backends import Observation, select_backend
from .dataterms import CAVITY_FRACTIONS, DataTerm, Force, Reads, TermState, nanmedian
from ..geometry.energy import Landmarks, SampledSurface, area_gradient
from ..surfaces.surface import Surface

__all__ = ["Descent", "LevelRun"]

# a landmark of weight 1 outweighs the data over this fraction of the
# (v1, v2) domain: about one patch at 4 x 4
_LANDMARK_AREA = 0.05
_NO_OFFSETS = np.empty(0)  # the compiled loop's band offsets where it takes no bands


class LevelRun(NamedTuple):
    """What :meth:`Descent.run` did: the iterations it ran, the RMS motion
    of the last (mm), whether that fell below the tolerance, and the last
    observation and force (as :meth:`Descent.observe` and the data term's
    ``force`` give them)."""

    iterations: int
    motion: float
    converged: bool
    observation: Observation
    force: Force


def add_rows(inverse: np.ndarray, rows: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """``(K + L^T diag(w) L)^-1`` from the symmetric ``K^-1`` (Woodbury: a
    few landmark rows need no new factorisation)."""
    u = inverse @ rows.T
    core = np.eye(len(rows)) + weights[:, None] * (rows @ u)
    # the low-rank update in place (BLAS wants Fortran order, which the
    # symmetric inverse's transpose has), without a copy of the product
    out = blas.dgemm(-1.0, u, np.linalg.solve(core, weights[:, None] * u.T), beta=1.0,
                     c=inverse.T.copy(order="F"), overwrite_c=True)
    return out.T


class Descent:
    """The iteration on one Hermite grid.

    Parameters
    ----------
    surface : Surface
        The start; its grid is the level's.
    reference : Surface
        The shape the thin-plate prior pulls towards (same grid).
    order, step, smoothness, nu : see :class:`spheroseg.SegmentOptions`
    landmarks : array (k, 3), optional
        World points held by the landmark rows, with ``landmark_weights`` (k,).
    backend : {"auto", "compiled", "numpy"}
    """

    def __init__(self, surface: Surface, reference: Surface, *, order: int, step: float, smoothness: float,
                 nu: float = 0.0, landmarks=None, landmark_weights=None, backend: str = "auto",
                 adaptive_step: bool = False):
        self.model = SampledSurface(surface.system, surface.pose, surface.grid, order)
        self.discretisation = self.model.discretisation
        self.backend = select_backend(self.model, compiled=backend != "numpy")
        self.template = surface  # the system, pose and grid of the surfaces it returns
        self.p = self.model.parameters(surface.coefficients)
        self.step, self.nu, self.smoothness = step, nu, smoothness
        self.adaptive_step = adaptive_step
        self._initial_step = step
        self._previous_motion = None
        self._smoothing = self.discretisation.smoothing(smoothness)
        self._area = self.discretisation.area
        self.set_reference(reference)
        self.set_landmarks(landmarks, landmark_weights)
        self.h0_floor = None  # fixed per level on the first iteration
        self._no_means = np.zeros(self.model.n_samples)  # the compiled loop's means of a term without fixed ones
        self._radius = None

    @property
    def surface(self) -> Surface:
        """The current surface."""
        return self.template.with_coefficients(self.model.coefficients(self.p))

    def set_surface(self, surface: Surface) -> None:
        """Continue from ``surface`` (same grid and pose)."""
        self.p = self.model.parameters(surface.coefficients)

    def set_reference(self, reference: Surface) -> None:
        """The shape the thin-plate prior pulls towards."""
        self.reference = self.model.parameters(reference.coefficients)

    def set_landmarks(self, landmarks, weights=None) -> None:
        """Hold the surface through world points ``(k, 3)`` with weights ``(k,)``."""
        d = self.discretisation
        self.system_inverse = d.system_inverse(self.smoothness)
        self.landmarks = None
        if landmarks is not None and len(landmarks):
            self.landmarks = Landmarks.from_world(self.model, landmarks)
            self.omega = np.asarray(weights, float) * _LANDMARK_AREA * d.area
            self._landmark_pull = self.landmarks.basis.T * self.omega  # L^T Omega
            self.system_inverse = add_rows(self.system_inverse, self.landmarks.basis, self.omega)
        # the same for the compiled loop (Descent.run): _kernels.LoopPrior's fields
        lm, empty, n = self.landmarks, np.empty(0), len(self.p)
        self._loop_prior = ((self._smoothing.indptr, self._smoothing.indices, self._smoothing.data),
                            self.system_inverse,
                            *((lm.basis, lm.v0, lm.h0, np.ascontiguousarray(self._landmark_pull)) if lm is not None
                              else (np.empty((0, n)), empty, empty, np.empty((n, 0)))))

    def observe(self, volume, reads: Reads) -> Observation:
        """The surface and the image at the sample points, with what a data
        term ``reads`` (:meth:`~spheroseg.descent.backends.NumpyBackend.observe_term`)
        and, with an area term, the geometry."""
        return self.backend.observe_term(self.p, volume, reads, geometry=self.nu > 0)

    def iterate(self, obs: Observation, force: Force) -> float:
        """One step with the data term's force; returns the RMS motion of
        the surface (mm)."""
        m = self.model
        if self.h0_floor is None:  # fixed per level: a median per iteration costs more than the rest
            self.h0_floor = 0.3 * float(nanmedian(obs.h0))

        def area_speed(normal_to_v0):
            return self.nu * self._area_speed(obs.geometry, normal_to_v0)

        wdv0 = self.backend.displacement(obs, force.c_in, force.c_out, force.scale, step=self.step,
                                         h0_floor=self.h0_floor, clip=force.clip, u=force.u,
                                         area_speed=area_speed if self.nu else None)
        rhs = self.backend.scatter(wdv0)
        rhs += self.backend.product(self._smoothing, self.reference - self.p)
        if self.landmarks is not None:
            # rows omega |L p_new - (L p + res)|^2: move towards each landmark
            # by at most a step
            lm = self.landmarks
            res = (lm.v0 - lm.basis @ self.p) * lm.h0
            res = np.minimum(np.maximum(res, -self.step), self.step) / lm.h0  # (np.clip checks more)
            rhs += self._landmark_pull @ res
        dp = self.system_inverse @ rhs
        self.p = self.p + dp
        motion = self.backend.gather(dp)
        motion *= obs.h0
        squared = np.dot(m.weights, motion * motion)
        if self.adaptive_step:
            self._adapt_step(motion, squared)
        return math.sqrt(squared / self._area)

    def run(self, volume, data_term: DataTerm, state: TermState, *, tol: float,
            max_iterations: int) -> LevelRun | None:
        """:meth:`observe` and :meth:`iterate` with ``data_term``'s force
        (its ``state`` held) until the RMS motion falls below ``tol`` (mm)
        or ``max_iterations`` have run, in one compiled loop
        (:func:`spheroseg._compiled._kernels.descend`: the built-in terms
        as its specialisations).

        Returns a :class:`LevelRun`, or None where that loop does not apply
        and nothing ran: the numpy backend, a beam-space volume, the area
        term, a data term it does not compute (``data_term.loop_kind``)."""
        kind = data_term.loop_kind(state)
        if kind is None or self.nu > 0 or not self.backend.descends(volume):
            return None
        from .._compiled import _kernels

        n = self.model.n_samples
        if kind == "fixed":
            fixed = data_term.fixed_force(state)
            means = tuple(np.broadcast_to(np.asarray(c, float), n).copy() for c in (fixed.c_in, fixed.c_out))
        else:
            fixed, means = Force(None, 0.0, 0.0, 0.0), (self._no_means, self._no_means)
        term = _kernels.LoopTerm(
            {"fixed": _kernels.FIXED_MEANS, "global": _kernels.GLOBAL_MEANS, "local": _kernels.LOCAL_MEANS}[kind],
            *means, float(fixed.scale), state.min_scale, CAVITY_FRACTIONS, state.shell_offsets,
            state.band_offsets if kind == "local" else _NO_OFFSETS,
            *((float(data_term.polarity), float(data_term.boundary_nepers)) if kind == "local" else ()))
        previous = np.zeros(n) if self._previous_motion is None else self._previous_motion[0].copy()
        state = np.zeros(1, dtype=_kernels.LOOP_STATE)
        s = state[0]
        s["step"], s["initial_step"], s["adaptive"] = self.step, self._initial_step, float(self.adaptive_step)
        s["h0_floor"] = -1.0 if self.h0_floor is None else self.h0_floor
        s["previous_squared"] = -1.0 if self._previous_motion is None else self._previous_motion[1]
        s["motion"] = s["c_in"] = s["c_out"] = s["scale"] = np.nan
        p = self.p.copy()
        status, obs, means = self.backend.descend(p, self.reference, volume, prior=_kernels.LoopPrior(*self._loop_prior),
                                                  term=term, state=state, previous=previous, tol=tol,
                                                  max_iterations=max_iterations)
        s = state[0]
        self.p, self.step = p, float(s["step"])
        self.h0_floor = float(s["h0_floor"]) if s["h0_floor"] >= 0 else self.h0_floor
        if self.adaptive_step and s["previous_squared"] >= 0:
            self._previous_motion = previous, float(s["previous_squared"])
        if status == _kernels.NO_BAND_DATA:
            raise ValueError("no image data around the surface (is it inside the image's sector?)")
        if kind != "local":
            obs.inside = obs.outside = None
        scale = float(s["scale"])
        if kind == "global":
            c_in, c_out = float(s["c_in"]), float(s["c_out"])
            force = Force(obs.u, c_in, max(c_out, c_in), scale, measured=(c_in, c_out))
        elif kind == "local":
            force = Force(obs.u, means[0], means[2], scale, measured=(means[3], means[1]))
        else:
            force = fixed._replace(u=obs.u, scale=scale)
        return LevelRun(int(s["iterations"]), float(s["motion"]), status == _kernels.CONVERGED, obs, force)

    def restart(self, step: float) -> None:
        """Begin a new level on this grid from the current surface, as a new
        :class:`Descent` would (the step, the scale-factor floor and the
        typical radius measured anew), without rebuilding its matrices."""
        self.set_surface(self.surface)
        self.reset_step(step)
        self.h0_floor = self._radius = None

    def reset_step(self, step: float) -> None:
        """Start again from ``step`` mm (a new frame, new landmarks)."""
        self.step = self._initial_step = step
        self._previous_motion = None

    def _adapt_step(self, motion: np.ndarray, squared: float) -> None:
        """Halve the step (``squared``: the weighted sum of ``motion**2``) when the surface turns back on itself: a motion
        against the previous one (negative correlation over the surface)
        means the step is larger than the force's zero crossing is sharp,
        and the surface would oscillate about it instead of settling."""
        if self._previous_motion is not None:
            previous, previous_squared = self._previous_motion
            dot = np.dot(self.model.weights, motion * previous)
            norms = np.sqrt(squared * previous_squared)
            if norms > 0 and dot < -0.5 * norms:
                self.step = max(0.5 * self.step, self._initial_step / 8)
        self._previous_motion = motion, squared

    def _area_speed(self, g, normal_to_v0) -> np.ndarray:
        """Normal speed (steps, outward) of the area term: minus the mean
        curvature from the gradient of paper eq. 23, made dimensionless by
        the typical radius so that ``nu = 1`` moves a sphere by a step.

        ``dA/dp = int G f_i`` where ``G = 2H h0 cos A_K`` (``2H`` the sum of
        the principal curvatures); ``B M^-1 dA/dp`` is ``G`` projected on the
        Hermite space."""
        field = self.backend.gather(self.discretisation.mass_inverse @ area_gradient(self.model, self.p, g))
        two_h = field / (np.maximum(g.area, 1e-12) * normal_to_v0)
        if self._radius is None:
            self._radius = float(np.median(np.linalg.norm(g.local, axis=1)))
        return -np.clip(0.5 * two_h * self._radius, -1.0, 1.0)
