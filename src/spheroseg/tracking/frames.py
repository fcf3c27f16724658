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
from ..geometry.energy import data_energy
from ..surfaces.fit import fit_surface
from .initial import start_surface
from ..descent.options import SegmentOptions
from ..descent.stepper import Level, schedule
from ..surfaces.surface import Surface

__all__ = ["BASE_RING_MM", "RESEGMENT_MARGIN", "LEFT_BEHIND", "base_ring_floor", "base_ring_points", "followed_base",
           "keep_better_start", "wall_sides", "followed_the_wall", "wall_motion_mm"]

#: plausible radii of the mitral annulus in adults, mm (the base ring's range)
BASE_RING_MM = (10.0, 20.0)
#: a frame segmented again replaces the stepped one when its data energy is
#: lower by more than this fraction of the stepped one's: below it the
#: candidates differ by the descent's own noise (0.0001-0.3 % on phantom
#: cycles of 4-20 frames), a stepped wall left behind by 3 % and more
RESEGMENT_MARGIN = 0.01
#: a sector of a stepped frame's wall is left behind when the band just
#: inside the surface is this much of the way from the blood's grey level to
#: the wall's, or the band just outside no more than this (0 blood, 1 wall):
#: on frames the stepped descent followed, the inner band reads -0.4 to 0.1
#: and the outer 0.44 to 0.6 (0.23 where the wall lost its echo); where the
#: basal wall moved past half the local means' band, 0.57 to 0.7 inside
#: (phantom cycles of 4 to 20 frames, and end-diastole to end-systole
#: directly, across the image formations and post-processings: docs/benchmarks.md)
LEFT_BEHIND = 0.25
#: sectors of the wall the sides are read in, around the axis and along
#: it, over this span of the ``v2`` range from the apex: the basal wall,
#: which moves most over a cycle (the annulus descends towards an apex that
#: barely moves); the apical cavity is where near-field clutter reads bright
WALL_SECTORS = (4, 3)
WALL_SPAN = (0.55, 1.0)


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


def wall_sides(descent, volume, levels, *, width: float) -> np.ndarray:
    """Where the grey levels either side of a descent's surface lie between
    the blood's and the wall's, sector by sector of the wall.

    ``volume`` is read along the outward normals at the sample points of the
    ``descent`` (a :class:`spheroseg.descent.Descent`, through its backend),
    at 1 mm steps over ``width`` mm inside and outside, and each sample is
    scaled as ``(u - c_in) / (c_out - c_in)`` with ``levels = (c_in,
    c_out)``.  Returns an array ``(sectors, 2)``: the mean scaled level of
    the inner and of the outer band in each of :data:`WALL_SECTORS` (NaN
    where no sample has image data).
    """
    model, backend = descent.model, descent.backend
    observation = backend.observe(descent.p, volume)
    offsets = np.concatenate([-np.arange(1.0, width + 0.5), np.arange(1.0, width + 0.5)])
    samples = backend.samples_along(volume, observation, offsets)
    c_in, c_out = levels
    scaled = (samples - c_in) / (c_out - c_in)
    inner = offsets < 0
    lo, hi = model.grid.v2_range
    around, along = WALL_SECTORS
    sector_1 = np.minimum((model.v1 % (2 * np.pi)) * (around / (2 * np.pi)), around - 1).astype(int)
    t2 = ((model.v2 - lo) / (hi - lo) - WALL_SPAN[0]) / (WALL_SPAN[1] - WALL_SPAN[0])
    read = (t2 >= 0) & (t2 < 1)
    sector = (sector_1 * along + np.floor(t2 * along).astype(int))[read]
    sides = np.empty((around * along, 2))
    for side, band in enumerate((scaled[read][:, inner], scaled[read][:, ~inner])):
        finite = np.isfinite(band)
        total = np.bincount(sector, np.where(finite, band, 0.0).sum(axis=1), minlength=around * along)
        count = np.bincount(sector, finite.sum(axis=1), minlength=around * along)
        sides[:, side] = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return sides


def followed_the_wall(tracker) -> bool:
    """Whether ``tracker``'s stepped frame settled on the wall: its finest
    level converged, and in every sector of the wall the band just inside
    the surface (half the local means' band, ``options.band / 2`` mm) reads
    as blood and the band just outside as wall (:data:`LEFT_BEHIND`, on
    the interface's levels).

    A wall that moved by more than the finest levels' bands can follow is
    left with tissue on the surface's inner side (systole) or blood on its
    outer side (diastole), where the local means balance on the wrong side
    of it; only then is the frame segmented again
    (:func:`keep_better_start`: two more segmentations and their energies).
    """
    if tracker.status != 0:
        return False
    with np.errstate(invalid="ignore", divide="ignore"):  # a sector without image data: NaN, not left behind
        sides = wall_sides(tracker.stepper.descent, tracker.volume, tracker.interface_levels(),
                           width=tracker.options.band / 2)
    inner, outer = sides[:, 0], sides[:, 1]
    return not (np.any(inner > LEFT_BEHIND) or np.any(outer < LEFT_BEHIND))


def wall_motion_mm(start: Surface, surface: Surface) -> float:
    """How far the wall moved between ``start`` and ``surface`` on the
    whole (mm): the change of the cavity's volume over the mean area of
    the two walls, ``|V_1 - V_0| / ((A_0 + A_1) / 2)`` (a wall moved
    everywhere by ``w`` along its normals changes the volume by ``w A`` to
    first order; the base plane left open).

    Where :func:`followed_the_wall` cannot look, it bounds what the finest
    levels were asked to follow: their local means find a wall within half
    their band (``options.band / 2``).  The stepped surface moves less
    than a wall it left behind, so this is a lower bound of the wall's
    motion.
    """
    mean_area = (start.wall_area_mm2() + surface.wall_area_mm2()) / 2
    return 1000.0 * abs(surface.volume_ml() - start.volume_ml()) / mean_area


def keep_better_start(tracker, start: Surface, *, left_behind: bool = False) -> None:
    """Segment ``tracker``'s current frame again through the coarse data
    term, from ``start`` (the frame's start surface) and from the initial
    shape posed at the current apex and base (coarse to fine, smoothed on
    the finest patches towards that shape fitted to the coarse levels'
    volume: ``smoothness_reference="fitted"``), and keep the
    segmentation of the lowest data energy: the stepped one unless another
    is lower by more than :data:`RESEGMENT_MARGIN` of it.  Where the
    stepped surface ``left_behind`` the wall (:func:`followed_the_wall`)
    the same check judges the others, and the one of lowest energy among
    those on the wall replaces it (by energy as above where none is): the
    energy's scalar levels can prefer a wall left inside the surface where
    the time-gain compensation left it dark.

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
    # the clicked shape's proportions are the first frame's; a frame far from it (an end-systole reached from
    # end-diastole) is smoothed towards the shape holding what the coarse levels found in it
    fresh = type(tracker)(tracker.volume, tracker.apex, tracker.base, **place,
                          **{**options, "smoothness_reference": "fitted"})
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

    energies = np.array([data_energy(model, model.parameters(candidate.surface.coefficients), sample, *levels)
                         for candidate in candidates])
    # where the stepped wall was left behind, the check that found it judges the others: one on the wall wins
    on_wall = [k for k, candidate in enumerate(candidates) if k and followed_the_wall(candidate)] if left_behind else []
    if on_wall:
        stepper.adopt(candidates[min(on_wall, key=lambda k: energies[k])].stepper)
    elif energies[0] - energies.min() > RESEGMENT_MARGIN * abs(energies[0]):
        stepper.adopt(candidates[int(np.argmin(energies))].stepper)
    stepper.seconds += time.perf_counter() - started
