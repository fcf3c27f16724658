"""The mitral annulus followed from frame to frame.

In systole the mitral annulus moves 8-15 mm towards the apex while the apex
barely moves.  A tracker that keeps the first frame's base plane closes the
end-systolic cavity a centimetre into the atrium: ESV too large, EF too low.

The annulus is found again in each frame by matching the structures beyond
the mitral plane along the long axis.  Below the base point (on the atrial
side), the image is averaged over the angle about the axis into a profile
``P(r, z)`` of radius ``r`` (from the axis, scaled by the base ring's
radius) and height ``z`` (along the axis, towards the apex, ``z <= 0``):
the annulus, the mitral orifice, the atrium and its wall.  These move with
the annulus, while the ventricle's own wall thickens and draws in through
systole (profiles reaching into the ventricle over-estimated the descent by
a third on the phantom's sequences).  Averaging over the angle removes the
speckle (which decorrelates between frames) and keeps the anatomy.  The
shift ``dz`` that maximises the normalised cross-correlation of the previous
frame's profile with the new frame's, ``P_t(r, z + dz)``, is how far the
annulus moved towards the apex (parabolic refinement between the samples).
"""

from __future__ import annotations

import numpy as np

__all__ = ["basal_profile", "annulus_shift"]


def basal_profile(volume, base, axis, ring_radius: float, *, heights, radii=None, n_angles: int = 48) -> np.ndarray:
    """Grey levels averaged over the angle about the long axis.

    Parameters
    ----------
    volume : Volume
        Anything with ``sample(points)`` (NaN off the data).
    base : (3,) array
        The base point (world mm).
    axis : (3,) array
        Unit vector of the long axis, towards the apex.
    ring_radius : float
        Radius of the base ring (mm): the radii are fractions of it.
    heights : array
        ``z`` (mm) along the axis.
    radii : array, optional
        Fractions of ``ring_radius`` (default 0.3 to 1.6).

    Returns
    -------
    array (len(radii), len(heights))
        Mean grey level at each (r, z) (NaN where no angle has data).
    """
    radii = np.linspace(0.3, 1.6, 14) if radii is None else np.asarray(radii, float)
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    e2 = np.cross(axis, [1.0, 0.0, 0.0])
    if np.linalg.norm(e2) < 0.1:
        e2 = np.cross(axis, [0.0, 1.0, 0.0])
    e2 /= np.linalg.norm(e2)
    e3 = np.cross(axis, e2)
    angles = np.linspace(0, 2 * np.pi, n_angles, endpoint=False)
    ring = np.cos(angles)[:, None] * e2 + np.sin(angles)[:, None] * e3  # (angles, 3)
    r = ring_radius * radii
    points = (np.asarray(base, float) + r[:, None, None, None] * ring[None, None, :, :]
              + np.asarray(heights, float)[None, :, None, None] * axis)  # (r, z, angle, 3)
    values = volume.sample(points)
    ok = np.isfinite(values)
    with np.errstate(invalid="ignore"):
        return np.where(ok.any(-1), np.where(ok, values, 0.0).sum(-1) / ok.sum(-1), np.nan)


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 10:
        return -np.inf
    a, b = a[ok] - a[ok].mean(), b[ok] - b[ok].mean()
    denominator = np.sqrt((a * a).sum() * (b * b).sum())
    return float((a * b).sum() / denominator) if denominator > 0 else -np.inf


def annulus_shift(previous, volume, base, axis, ring_radius: float, *, reach: float = 20.0, search: float = 16.0,
                  resolution: float = 1.0) -> float:
    """How far (mm) the basal structures moved along ``axis`` (towards the
    apex positive) from ``previous`` to ``volume``.

    Parameters
    ----------
    previous, volume : Volume
        Consecutive frames.
    base, axis, ring_radius
        The previous frame's base point, long axis (towards the apex) and
        base ring radius (mm).
    reach : float
        Depth (mm) of the profile beyond the base plane.
    search : float
        Largest shift tried each way (mm): the whole systolic descent (8-15
        mm), so that frames far apart in the cycle (few frames a cycle, or
        end-diastole to end-systole directly) stay in reach.
    resolution : float
        Spacing (mm) of the heights and shifts tried.
    """
    heights = np.arange(-reach, resolution / 2, resolution)
    shifts = np.arange(-search, search + resolution / 2, resolution)
    reference = basal_profile(previous, base, axis, ring_radius, heights=heights)
    extended = np.arange(-reach - search, search + resolution / 2, resolution)
    moved = basal_profile(volume, base, axis, ring_radius, heights=extended)
    n = len(heights)
    scores = np.array([_ncc(reference, moved[:, k:k + n]) for k in range(len(shifts))])
    if not np.isfinite(scores).any():
        return 0.0
    k = int(np.nanargmax(scores))
    shift = float(shifts[k])
    if 0 < k < len(shifts) - 1 and np.all(np.isfinite(scores[k - 1:k + 2])):
        left, centre, right = scores[k - 1:k + 2]
        curvature = left - 2 * centre + right
        if curvature < 0:
            shift += resolution * 0.5 * (left - right) / curvature
    return shift
