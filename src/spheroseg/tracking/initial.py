"""The initial model of a segmentation: the user's points checked against
the image, the pose they give and the start surface.

The points are world points (mm, ITK physical space).  An apex and a base
point pose the half-ellipsoid along the apex-base line
(:meth:`Surface.from_apex_base`); an apex and the mitral annulus pose it by
the annulus' least-squares plane (:meth:`Surface.from_annulus`).  Every
check fails with one line naming the point.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..geometry.coords import Pose, annulus_plane
from ..descent.options import SegmentOptions, format_point
from ..descent.stepper import Level
from ..surfaces.surface import Surface

__all__ = ["InitialModel", "initial_model", "start_surface", "fitted_start", "check_volume", "check_point",
           "check_landmarks", "MIN_LONG_AXIS_MM"]

#: the least apex-to-base distance taken (mm): a mouse's left ventricle is
#: some 6 mm long, and a descent from a start of a few micrometres ends in
#: non-finite coefficients
MIN_LONG_AXIS_MM = 1.0


def check_volume(volume) -> None:
    """A ``TypeError`` unless ``volume`` samples like a :class:`spheroseg.Volume`."""
    if not (callable(getattr(volume, "sample", None)) and hasattr(volume, "contains") and hasattr(volume, "grid")):
        raise TypeError(f"volume must be a spheroseg.Volume, got {type(volume).__name__}")


def check_point(volume, point, name: str) -> np.ndarray:
    """``point`` as an array (3,): 3 finite numbers inside ``volume``."""
    try:
        p = np.asarray(point, dtype=float)
    except (TypeError, ValueError):
        p = np.full(0, np.nan)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ValueError(f"{name} must be 3 finite numbers (x, y, z in mm), got {point!r}")
    if not volume.contains(p):
        lo, hi = volume.bounds
        raise ValueError(f"{name} {format_point(p)} lies outside the image "
                         f"(x, y, z from {format_point(lo)} to {format_point(hi)} mm)")
    return p


def check_landmarks(volume, landmarks) -> np.ndarray:
    """``landmarks`` as an array (k, 3) of points inside ``volume`` (k = 0 for None)."""
    if landmarks is None:
        return np.empty((0, 3))
    try:
        points = np.asarray(landmarks, dtype=float).reshape(-1, 3)
    except (TypeError, ValueError):
        raise ValueError(f"landmarks must be points (x, y, z in mm), got {landmarks!r}") from None
    for k, point in enumerate(points):
        check_point(volume, point, f"landmark {k}")
    return points


def _check_annulus(volume, annulus) -> np.ndarray:
    annulus_plane(annulus)  # its points' form: (k >= 3, 3), finite, not on a line
    points = np.asarray(annulus, dtype=float)
    for k, point in enumerate(points):
        check_point(volume, point, f"annulus point {k}")
    return points


def start_surface(apex: np.ndarray, base: np.ndarray | None, *, annulus: np.ndarray | None,
                  options: SegmentOptions, patches: tuple[int, int]) -> Surface:
    """The half-ellipsoid on ``patches`` posed by the apex and the annulus
    (``base``, if given, projected on its plane) or, without an annulus, by
    the apex and ``base``."""
    if annulus is not None:
        return Surface.from_annulus(apex, annulus, base=base, system=options.system, patches=patches,
                                    radius_ratio=options.radius_ratio)
    return Surface.from_apex_base(apex, base, system=options.system, patches=patches,
                                  radius_ratio=options.radius_ratio)


def fitted_start(apex: np.ndarray, base: np.ndarray | None, volume_ml: float, *, annulus: np.ndarray | None,
                 options: SegmentOptions, patches: tuple[int, int]) -> Surface | None:
    r"""The start surface's half-ellipsoid widened or narrowed to enclose
    ``volume_ml``: the same pose and apex height ``h``, the base radius
    ``b = sqrt(3 V / (2 pi h))`` (a half-ellipsoid, sheared or not, holds
    ``2 pi h b^2 / 3``), or None where no such shape is posed (``b`` not
    under ``h``, or the apex further off the axis than ``b``).  Every
    coordinate system's fit depends on ``h`` alone, so the shape shares the
    start's system and grid."""
    if annulus is not None:
        height = float(Pose.from_annulus(apex, annulus, base=base).to_local(np.asarray(apex, float))[0])
    else:
        height = float(np.linalg.norm(np.asarray(apex, float) - np.asarray(base, float)))
    radius_ratio = np.sqrt(3.0 * 1000.0 * volume_ml / (2.0 * np.pi * height)) / height
    if not 0 < radius_ratio < 1:
        return None
    try:
        return start_surface(apex, base, annulus=annulus, options=replace(options, radius_ratio=float(radius_ratio)),
                             patches=patches)
    except ValueError:  # the apex off the sheared axis by more than the new radius
        return None


@dataclass(frozen=True)
class InitialModel:
    """What a segmentation starts from, checked.

    Attributes
    ----------
    apex, base : array (3,)
        World points (mm); ``base`` is the pose's origin (the annulus
        plane's point when posed by an annulus).
    annulus : array (k, 3) or None
        The mitral annulus' points (mm).
    landmarks : array (k, 3)
        The user's landmarks (mm), possibly none.
    levels : tuple of Level
        The schedule.
    surface : Surface
        The start surface, on the first level's patches (or a given one
        that refines to them).
    """

    apex: np.ndarray
    base: np.ndarray
    annulus: np.ndarray | None
    landmarks: np.ndarray
    levels: tuple[Level, ...]
    surface: Surface


def initial_model(volume, apex, base=None, *, annulus=None, landmarks=None, init: Surface | None = None,
                  levels, options: SegmentOptions) -> InitialModel:
    """Check the points against ``volume`` and pose the start surface on
    the first of ``levels`` (or take ``init``; see :class:`spheroseg.Tracker`
    for the arguments)."""
    check_volume(volume)
    apex = check_point(volume, apex, "apex")
    annulus = None if annulus is None else _check_annulus(volume, annulus)
    if base is None and annulus is None:
        raise ValueError("give the base point (the centre of the mitral plane) or the annulus "
                         "(3 or more points of the mitral ring)")
    given_base = None if base is None else check_point(volume, base, "base")
    if annulus is None:
        base = given_base
        length = float(np.linalg.norm(apex - base))
        if length < 1e-6:
            raise ValueError("apex and base must be distinct points")
        if length < MIN_LONG_AXIS_MM:
            raise ValueError(f"apex and base are {length:.3g} mm apart: they are the ends of the ventricle's long "
                             f"axis (at least {MIN_LONG_AXIS_MM:g} mm)")
    else:
        base = Pose.from_annulus(apex, annulus, base=given_base).origin
    if init is not None and not isinstance(init, Surface):
        raise TypeError(f"init must be a spheroseg.Surface, got {type(init).__name__}")
    landmarks = check_landmarks(volume, landmarks)
    levels = tuple(levels)
    if not levels or not all(isinstance(level, Level) for level in levels):
        raise TypeError("levels must be a non-empty sequence of spheroseg.tracker.Level")
    surface = init if init is not None else start_surface(apex, given_base if annulus is not None else base,
                                                          annulus=annulus, options=options,
                                                          patches=levels[0].patches)
    return InitialModel(apex, base, annulus, landmarks, levels, surface)
