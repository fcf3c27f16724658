"""Following the ventricle from frame to frame: the base plane moved with
the mitral annulus, the base ring held open, and a frame segmented again
when the wall moved farther than the finest levels can follow.

These are the parts of :meth:`spheroseg.Tracker.next_frame` that look at
more than one frame or at more than one segmentation of a frame; the level
state machine itself is :class:`spheroseg.stepper.Stepper`.
"""

from __future__ import annotations

import time

import numpy as np

from .annulus import annulus_shift
from .energy import data_energy
from .fit import fit_surface
from .initial import start_surface
from .options import SegmentOptions
from .stepper import Level, schedule
from .surface import Surface

__all__ = ["BASE_RING_MM", "RESEGMENT_MARGIN", "base_ring_floor", "base_ring_points", "followed_base",
           "keep_better_start"]

#: plausible radii of the mitral annulus in adults, mm (the base ring's range)
BASE_RING_MM = (10.0, 20.0)
#: a frame segmented again replaces the stepped one when its data energy is
#: lower by more than this fraction of the stepped one's: below it the
#: candidates differ by the descent's own noise (0.0001-0.3 % on phantom
#: cycles of 4-20 frames), a stepped wall left behind by 3 % and more
RESEGMENT_MARGIN = 0.01


def base_ring_floor(annulus: np.ndarray | None) -> float:
    """The least radius (mm) of the base ring: :data:`BASE_RING_MM`'s
    lower end, or with a clicked annulus three quarters of its points'
    mean distance from their centre."""
    if annulus is None:
        return BASE_RING_MM[0]
    return 0.75 * float(np.mean(np.linalg.norm(annulus - annulus.mean(axis=0), axis=1)))


def base_ring_points(surface: Surface, floor: float, n: int = 32) -> np.ndarray | None:
    """Points (world mm) on the base plane at radius ``floor`` from the
    axis, at those of ``n`` angles where the surface's base ring is
    narrower; None where it is nowhere narrower.

    The mitral annulus is a ring (10-20 mm in radius in adults); in low
    contrast at the base nothing stops the smoothing prior and the bright
    mitral apparatus from closing the cavity into a cusp about the base
    point.  Held as landmarks, these points keep the ring open."""
    narrow = surface.base_radii(n) < floor
    if not narrow.any():
        return None
    v1 = np.linspace(0, 2 * np.pi, n, endpoint=False)[narrow]
    direction = surface.system.to_cartesian(np.ones_like(v1), v1, np.full_like(v1, surface.base_v2))
    direction[:, 0] = 0.0  # in the base plane, away from the axis
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    return surface.pose.to_world(floor * direction)


def followed_base(surface: Surface, volume, next_volume, *, apex: np.ndarray, annulus: np.ndarray | None,
                  options: SegmentOptions):
    """The base plane moved with the annulus from ``volume`` to
    ``next_volume`` (:func:`spheroseg.annulus.annulus_shift`), and the
    model posed there: the plane keeps its orientation, the apex stays; the
    surface is fitted in the new model (its points, extended a little beyond
    the old plane).

    Returns ``(base, annulus, surface)`` (the annulus None without one), or
    None when the plane moved less than 0.1 mm."""
    pose, grid = surface.pose, surface.grid
    axis = pose.rotation[:, 0]  # from the base towards the apex
    lo, hi = grid.v2_range
    v1 = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    ring = surface.points(v1, np.full_like(v1, hi))
    radius = float(np.mean(np.linalg.norm(ring - pose.origin, axis=1)))
    shift = annulus_shift(volume, next_volume, pose.origin, axis, radius)
    if abs(shift) < 0.1:
        return None
    patches = (grid.n1, grid.n2)
    base = pose.origin + shift * axis
    if annulus is not None:
        annulus = annulus + shift * axis
    start = start_surface(apex, base, annulus=annulus, options=options, patches=patches)
    # the old surface, extrapolated a little past its plane (diastole
    # moves the plane away from the apex, where it had no points)
    v1, v2 = np.meshgrid(np.linspace(0, 2 * np.pi, 96, endpoint=False), np.linspace(lo, hi + 0.25 * (hi - lo), 48))
    fitted = fit_surface(surface.points(v1.ravel(), v2.ravel()), system=start.system, pose=start.pose,
                         patches=patches, v2_range=start.grid.v2_range, smoothness=1e-5)
    return base, annulus, fitted


def keep_better_start(tracker, start: Surface) -> None:
    """Segment ``tracker``'s current frame again through the coarse data
    term, from ``start`` (the frame's start surface) and from the initial
    shape posed at the current apex and base (coarse to fine), and keep the
    segmentation of the lowest data energy (the stepped one unless another
    is lower by more than :data:`RESEGMENT_MARGIN` of it).

    A wall that moved between frames by more than the finest levels' bands
    can follow leaves the stepped surface where the local means balance on
    the wrong side of it (a long time step: few frames a cycle, or
    end-diastole to end-systole directly), while the global means bring the
    surface to the walls from afar.  The surfaces share the pose and the
    grid; all are scored by the Chan-Vese data energy (paper eq. 14) with
    the same scalar levels, the mean of the segmentations' interface levels:
    ``int_cavity (u - c_in)^2 - (u - c_out)^2 dV``, lowest when the cavity
    holds every voxel darker than the interface and none brighter.
    """
    started = time.perf_counter()
    stepper = tracker.stepper
    options = {name: getattr(tracker.options, name) for name in SegmentOptions.names()}
    place = dict(annulus=tracker.annulus, landmarks=tracker.landmarks if len(tracker.landmarks) else None)
    fresh = type(tracker)(tracker.volume, tracker.apex, tracker.base, **place, **options)
    coarse, finest = schedule(tracker.options)[0], schedule(tracker.options, coarse_to_fine=False)
    again_levels = (Level(finest[0].patches, coarse.data_term, coarse.max_iterations, coarse.tol), *finest)
    again = type(tracker)(tracker.volume, tracker.apex, tracker.base, init=start, levels=again_levels, **place,
                          **options)
    candidates = [tracker]
    for candidate in (again, fresh):
        candidate.run()
        if candidate.patches == tracker.patches:
            candidates.append(candidate)
    model = stepper.descent.model
    levels = np.mean([candidate.interface_levels() for candidate in candidates], axis=0)

    def sample(world):  # no data weighs nothing
        return tracker.volume.sample(world, fill_value=float(levels.mean()))

    energies = [data_energy(model, model.parameters(candidate.surface.coefficients), sample, *levels)
                for candidate in candidates]
    best = candidates[int(np.argmin(energies))]
    if energies[0] - min(energies) > RESEGMENT_MARGIN * abs(energies[0]):
        stepper.adopt(best.stepper)
    stepper.seconds += time.perf_counter() - started
