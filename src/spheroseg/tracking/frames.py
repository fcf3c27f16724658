"""Following the ventricle from frame to frame: the base plane moved with
the mitral annulus, the base ring held open, and a frame segmented again
when the wall moved farther than the finest levels can follow.

These are what :meth:`spheroseg.Tracker.next_frame` decides a frame by,
as functions of plain data (surfaces, grey levels along the normals,
energies): whether the stepped surface followed the wall, how far the
wall moved, which of a frame's segmentations to keep.  The tracker samples
the image and runs the segmentations; nothing here steps one.
"""

from __future__ import annotations

import numpy as np

from .annulus import annulus_shift
from ..surfaces.fit import fit_surface
from .initial import start_surface
from ..descent.options import SegmentOptions
from ..surfaces.surface import Surface

__all__ = ["BASE_RING_MM", "RESEGMENT_MARGIN", "LEFT_BEHIND", "base_ring_floor", "base_ring_points", "followed_base",
           "wall_offsets", "wall_sides", "left_behind", "wall_motion_mm", "kept_candidate"]

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


def wall_offsets(width: float) -> np.ndarray:
    """The offsets (mm along the outward normal) the wall's sides are read
    at: 1 mm steps over ``width`` mm inside and outside."""
    return np.concatenate([-np.arange(1.0, width + 0.5), np.arange(1.0, width + 0.5)])


def wall_sides(samples: np.ndarray, offsets: np.ndarray, v1: np.ndarray, v2: np.ndarray, v2_range,
               levels) -> np.ndarray:
    """Where the grey levels either side of a surface lie between the
    blood's and the wall's, sector by sector of the wall.

    ``samples`` ``(n, len(offsets))`` are the grey levels at ``offsets``
    (:func:`wall_offsets`) along the outward normals at a surface's sample
    points of parameters ``v1``, ``v2`` (``v2_range`` its grid's), each
    scaled as ``(u - c_in) / (c_out - c_in)`` with ``levels = (c_in,
    c_out)``.  Returns an array ``(sectors, 2)``: the mean scaled level of
    the inner and of the outer band in each of :data:`WALL_SECTORS` (NaN
    where no sample has image data).
    """
    c_in, c_out = levels
    scaled = (samples - c_in) / (c_out - c_in)
    inner = np.asarray(offsets) < 0
    lo, hi = v2_range
    around, along = WALL_SECTORS
    sector_1 = np.minimum((v1 % (2 * np.pi)) * (around / (2 * np.pi)), around - 1).astype(int)
    t2 = ((v2 - lo) / (hi - lo) - WALL_SPAN[0]) / (WALL_SPAN[1] - WALL_SPAN[0])
    read = (t2 >= 0) & (t2 < 1)
    sector = (sector_1 * along + np.floor(t2 * along).astype(int))[read]
    sides = np.empty((around * along, 2))
    for side, band in enumerate((scaled[read][:, inner], scaled[read][:, ~inner])):
        finite = np.isfinite(band)
        total = np.bincount(sector, np.where(finite, band, 0.0).sum(axis=1), minlength=around * along)
        count = np.bincount(sector, finite.sum(axis=1), minlength=around * along)
        sides[:, side] = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return sides


def left_behind(sides: np.ndarray) -> bool:
    """Whether a surface left the wall behind: in some sector of
    :func:`wall_sides` the band just inside reads more than
    :data:`LEFT_BEHIND` of the way to the wall, or the band just outside
    less (a sector without image data leaves nothing behind).

    A wall that moved by more than the finest levels' bands can follow is
    left with tissue on the surface's inner side (systole) or blood on its
    outer side (diastole), where the local means balance on the wrong side
    of it.
    """
    with np.errstate(invalid="ignore"):
        return bool(np.any(sides[:, 0] > LEFT_BEHIND) or np.any(sides[:, 1] < LEFT_BEHIND))


def wall_motion_mm(start: Surface, surface: Surface) -> float:
    """How far the wall moved between ``start`` and ``surface`` on the
    whole (mm): the change of the cavity's volume over the mean area of
    the two walls, ``|V_1 - V_0| / ((A_0 + A_1) / 2)`` (a wall moved
    everywhere by ``w`` along its normals changes the volume by ``w A`` to
    first order; the base plane left open).

    Where :func:`left_behind` cannot look, it bounds what the finest
    levels were asked to follow: their local means find a wall within half
    their band (``options.band / 2``).  The stepped surface moves less
    than a wall it left behind, so this is a lower bound of the wall's
    motion.
    """
    mean_area = (start.wall_area_mm2() + surface.wall_area_mm2()) / 2
    return 1000.0 * abs(surface.volume_ml() - start.volume_ml()) / mean_area


def kept_candidate(energies, on_wall=()) -> int:
    """Which of a frame's segmentations to keep (0: the stepped one), from
    their data ``energies`` (the stepped one first) and the indices of
    those ``on_wall`` (the others that did not leave the wall behind, where
    the stepped one did): the one of lowest energy on the wall; else the
    stepped one unless another is lower by more than
    :data:`RESEGMENT_MARGIN` of its energy.  The energy's scalar levels can
    prefer a wall left inside the surface where the time-gain compensation
    left it dark: where the stepped surface left the wall, the check that
    found it judges the others first."""
    energies = np.asarray(energies, dtype=float)
    if len(on_wall):
        return int(min(on_wall, key=lambda k: energies[k]))
    if energies[0] - energies.min() > RESEGMENT_MARGIN * abs(energies[0]):
        return int(np.argmin(energies))
    return 0
