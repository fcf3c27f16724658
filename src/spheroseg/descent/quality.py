"""How far a segmentation can be trusted: a few numbers a user can read.

A descent always returns a surface.  On an image it cannot handle (strong
clutter, a lost acoustic window, a click far off the ventricle) that surface
is a shape no heart has, and nothing in the volume says so.  The quality
report says what the descent saw and did:

``contrast``
    Median local contrast ``c_out - c_in`` at the end, in units of the
    grey-level spread around the initial surface (a clear wall gives 1 or
    more).
``low_contrast_fraction``
    Fraction of the surface where the local contrast is under a tenth of
    that spread: dropout, or both bands in one tissue.
``no_data_fraction``
    Fraction of the surface with no image under it (out of the sector).
``converged``
    Whether the last level stopped because the surface stopped moving.
``apex_shift_mm``
    Distance from the clicked apex to the surface's apex.
``volume_ratio``
    Final volume over the initial half-ellipsoid's.
``landmark_residuals_mm``
    Distance from each landmark the user gave to the final surface, in the
    order given.  A landmark is held by a weight against the data, not
    forced: one put off the wall (a misclick) pulls the wall part way only.
``bulge``
    How much farther the wall went out in its most-moved place than it did
    elsewhere (:func:`wall_bulge`): a leak through a stretch of wall without
    echo pushes one region out, while a ventricle larger or smaller than the
    clicks suggest scales all of it.
``beyond_wall``, ``beyond_wall_fraction``
    Grey levels the intensity interface took off the myocardium's level
    because its outer band read brighter tissue beyond a thin wall
    (:func:`spheroseg.descent.speckle.beyond_wall_excess`), and the fraction of
    the band's rise they are (1: all of it; less where the rise may be a
    blurred edge's); 0 when it read none.
``wall_contrast``
    With the points checked or located: the wall's median grey level minus
    that of the tissue beyond it (:func:`spheroseg.epicardium.check_wall_polarity`);
    negative, a myocardium darker than what lies beyond it, is a warning
    unless the intensity interface took all of the band's rise beyond it
    off (``beyond_wall_fraction`` 1).

``warnings`` lists what is out of the ordinary, in words, and ``poor`` is
True when there is any.  The bounds are plausibility bounds, not tuned
values: a ventricle is not a third or three times the size of the shape the
clicks describe, its apex not a centimetre from the clicked one.  The bulge
bound, 1.6, was checked on the 32 cases of the image-formation sweep (at most
1.11), CETUS Patient 7 (1.31 at end-diastole, 1.24 at end-systole) and
phantoms whose wall lost its echo over 10 to 37 % of it (1.11 for no leak;
1.46 for a leak of +25 % in volume, not flagged; 1.98 and 2.08 for +84 and
+147 %).
"""

from __future__ import annotations

import math

import numpy as np

from .dataterms import nanmedian
from ..surfaces.fit import point_to_surface_distance

__all__ = ["quality_report", "quality_warning", "wall_bulge", "axis_distances", "landmark_residuals", "wall_report",
           "FrameQuality"]

#: the bounds of a plausible result
LIMITS = {"contrast": 0.5, "low_contrast_fraction": 0.3, "no_data_fraction": 0.1, "apex_shift_mm": 10.0,
          "volume_ratio": (1 / 3, 3.0), "bulge": 1.6, "landmark_residual_mm": 2.0, "moved_mm": 0.25}


def wall_bulge(surface, initial, *, reference: np.ndarray | None = None) -> float:
    """The largest ratio of the wall's distance from the long axis to the
    initial surface's, over the median ratio.

    Both surfaces are evaluated at the same parameters ``(v1, v2)`` (48 x 16,
    the apex cap and the base rim left out: 15 % and 5 % of the ``v2``
    range); distances are from the initial surface's axis (through its
    origin along its pose's first axis).  1 for a wall that moved out (or
    in) by the same factor everywhere.  ``reference`` is
    ``axis_distances(initial, initial)`` when already computed (the frames
    of a sequence compare with one initial surface).
    """
    if reference is None:
        reference = axis_distances(initial, initial)
    ratio = axis_distances(surface, initial) / reference
    return float(ratio.max() / nanmedian(ratio))  # NaN if any is: so is the max


def landmark_residuals(surface, landmarks) -> np.ndarray:
    """Distance (mm) from each landmark ``(k, 3)`` to ``surface``'s wall
    (:func:`spheroseg.fit.point_to_surface_distance`: the nearest of a
    coarse sampling of the wall, refined on the wall's parameters; a
    landmark beyond the base plane gets its distance to the base ring)."""
    points = np.asarray(landmarks, dtype=float).reshape(-1, 3)
    if not len(points):
        return np.zeros(0)
    # a coarse start suffices: a landmark lies near the wall it pulls
    return point_to_surface_distance(points, surface, n_v1=64, n_v2=32)


def axis_distances(surface, initial) -> np.ndarray:
    """Distances (mm) of ``surface``'s wall from ``initial``'s long axis at
    the parameters :func:`wall_bulge` compares."""
    lo, hi = initial.grid.v2_range
    v1 = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    v2 = np.linspace(lo + 0.15 * (hi - lo), hi - 0.05 * (hi - lo), 16)
    if surface.pose is initial.pose:  # one frame (a tracker's frames): the axis is its first coordinate
        p = surface.grid_points(v1, v2, local=True).reshape(-1, 3)
        return np.hypot(p[:, 1], p[:, 2])
    origin, axis = initial.pose.origin, initial.pose.rotation[:, 0]
    p = surface.grid_points(v1, v2).reshape(-1, 3) - origin
    return np.linalg.norm(p - np.outer(p @ axis, axis), axis=1)


def quality_report(*, contrast: float, low_contrast_fraction: float, no_data_fraction: float, converged: bool,
                   apex_shift_mm: float, volume_ratio: float, bulge: float = math.nan,
                   landmark_residuals_mm=(), moved_mm: float = math.nan) -> dict:
    """The report of :mod:`spheroseg.quality` from its measurements (plain
    floats and bools, ready for JSON), with ``warnings`` and ``poor``."""
    warnings = []
    if not converged:
        warnings.append("the surface was still moving when the descent stopped")
    if not contrast >= LIMITS["contrast"]:
        warnings.append(f"low contrast between the cavity and the wall ({contrast:.2f} of the grey-level spread)")
    if low_contrast_fraction > LIMITS["low_contrast_fraction"]:
        warnings.append(f"{100 * low_contrast_fraction:.0f} % of the surface has no contrast (dropout?)")
    if no_data_fraction > LIMITS["no_data_fraction"]:
        warnings.append(f"{100 * no_data_fraction:.0f} % of the surface lies outside the image's data")
    if apex_shift_mm > LIMITS["apex_shift_mm"]:
        warnings.append(f"the apex moved {apex_shift_mm:.0f} mm from the clicked point")
    low, high = LIMITS["volume_ratio"]
    if not low <= volume_ratio <= high:
        warnings.append(f"the volume changed {volume_ratio:.2f}-fold from the initial shape")
    if bulge > LIMITS["bulge"]:
        warnings.append(f"the wall bulges out {bulge:.1f} times as far in one region as elsewhere (a leak? a landmark "
                        "on the wall there stops it)")
    if moved_mm < LIMITS["moved_mm"]:  # NaN (not measured): no warning
        warnings.append(f"the surface did not move from its start (its wall {moved_mm:.2f} mm from it on average): "
                        "the descent saw no motion (a step too small for tol?)")
    residuals = [float(r) for r in np.ravel(landmark_residuals_mm)]
    far = [(k + 1, r) for k, r in enumerate(residuals) if not r <= LIMITS["landmark_residual_mm"]]
    if far:
        warnings.append("the surface misses landmark " + ", ".join(f"{k} by {r:.1f} mm" for k, r in far)
                        + " (is it on the wall?)")
    return {"contrast": float(contrast), "low_contrast_fraction": float(low_contrast_fraction),
            "no_data_fraction": float(no_data_fraction), "converged": bool(converged),
            "apex_shift_mm": float(apex_shift_mm), "volume_ratio": float(volume_ratio), "bulge": float(bulge),
            "landmark_residuals_mm": residuals, "moved_mm": float(moved_mm), "warnings": warnings,
            "poor": bool(warnings)}


class FrameQuality:
    """The quality report of the frames segmented from one initial surface.

    Parameters
    ----------
    initial : Surface
        The initial shape the frames are compared with (its volume and its
        wall's distances from the axis are computed once).
    apex : array (3,)
        The clicked apex (world mm).
    """

    def __init__(self, initial, apex: np.ndarray):
        self.initial, self.apex = initial, apex
        self._initial_volume_ml = self._axis_distances = None  # on the first report

    @property
    def initial_volume_ml(self) -> float:
        """The initial shape's volume (mL)."""
        if self._initial_volume_ml is None:
            self._initial_volume_ml = self.initial.volume_ml()
        return self._initial_volume_ml

    def report(self, surface, *, observed, converged: bool, landmarks: np.ndarray, no_speckle: bool,
               beyond_wall: tuple[float, float] = (0.0, 0.0)) -> dict:
        """:func:`quality_report` of ``surface``, given what the last
        iteration ``observed`` (``(u, force, spread)``: the grey levels at
        the sample points, the data term's force, the grey-level spread
        around the initial surface; None before any iteration), whether it
        ``converged``, the ``landmarks`` held (world mm), whether the
        frame fell back to the local means for ``no_speckle`` and what the
        intensity interface took off the myocardium's level
        (``beyond_wall``: grey levels, and the fraction of the outer band's
        rise they are)."""
        if observed is not None:
            u, force, spread = observed
            # abs: a bright wall's term (LocalMeans.polarity -1) has c_in above c_out
            no_data, contrast = float(np.mean(~np.isfinite(u))), np.abs(np.asarray(force.c_out - force.c_in, float))
        else:
            no_data, contrast, spread = np.nan, np.full(1, np.nan), np.nan
        if self._axis_distances is None:
            self._axis_distances = axis_distances(self.initial, self.initial)
        distances = axis_distances(surface, self.initial)
        with np.errstate(invalid="ignore", divide="ignore"):
            report = quality_report(
                contrast=float(nanmedian(contrast) / spread), no_data_fraction=no_data,
                low_contrast_fraction=float(np.mean(np.broadcast_to(contrast, (1,) + np.shape(contrast)) < 0.1 * spread)),
                converged=converged, apex_shift_mm=float(np.linalg.norm(surface.tip() - self.apex)),
                volume_ratio=surface.volume_ml() / self.initial_volume_ml,
                bulge=float((distances / self._axis_distances).max() / nanmedian(distances / self._axis_distances)),
                landmark_residuals_mm=landmark_residuals(surface, landmarks),
                moved_mm=float(np.mean(np.abs(distances - self._axis_distances))))
        report["beyond_wall"], report["beyond_wall_fraction"] = (float(v) for v in beyond_wall)
        if no_speckle:
            report["warnings"].append("no speckle around the surface to undo the log compression with (a noise-free "
                                      "or smoothed image?): the wall is the local means' (mode='local')")
            report["poor"] = True
        return report


#: the bounds of a plausible wall (mm): more of it than this fraction at the
#: smallest thickness allowed is a collapse; a 95th percentile above this a
#: wall thicker than severe hypertrophy (17 mm and more; Lang et al. 2015);
#: a median below this thinner than an adult wall (6-10 mm normal; a scar
#: thins a region, not the median of the whole wall)
WALL_LIMITS = {"floor_fraction": 0.1, "p95_mm": 25.0, "median_min_mm": 4.0}


def wall_report(thickness_mm, *, min_thickness_mm: float, settled: bool = True) -> dict:
    """How plausible a myocardium is, from its wall thickness (mm) sampled
    over the endocardium: the 5th, 50th and 95th percentiles, the fraction
    within 0.5 mm of ``min_thickness_mm`` (where the epicardium fell onto
    its floor), ``warnings`` and ``poor``.  A collapse, a median thinner than
    an adult wall and a 95th percentile thicker than one are flagged
    (:data:`WALL_LIMITS`), and so is an epicardium that had not ``settled``
    (its descent still moving at its iteration cap)."""
    t = np.asarray(thickness_mm, dtype=float).ravel()
    p5, p50, p95 = (float(v) for v in np.percentile(t, [5, 50, 95]))
    floor = float(np.mean(t <= min_thickness_mm + 0.5))
    warnings = []
    if floor > WALL_LIMITS["floor_fraction"]:
        warnings.append(f"the wall collapsed to its smallest thickness ({min_thickness_mm:.1f} mm) over "
                        f"{100 * floor:.0f} % of it")
    if p50 < WALL_LIMITS["median_min_mm"] and floor <= WALL_LIMITS["floor_fraction"]:
        warnings.append(f"the wall is implausibly thin (median {p50:.1f} mm): the epicardium found no outer boundary")
    if p95 > WALL_LIMITS["p95_mm"]:
        warnings.append(f"the wall is implausibly thick (95th percentile {p95:.0f} mm): the epicardium went astray")
    if not settled:
        warnings.append("the epicardium was still moving at its iteration cap: no clear outer boundary")
    return {"thickness_p5_mm": p5, "thickness_median_mm": p50, "thickness_p95_mm": p95, "floor_fraction": floor,
            "warnings": warnings, "poor": bool(warnings)}


def quality_notes(frames) -> list[str]:
    """What a user is told that does not make a result poor (the
    ``notes`` of the reports: checks that could not be made), each once."""
    notes = []
    for frame in frames:
        for note in (frame.quality or {}).get("notes", []):
            if note not in notes:
                notes.append(note)
    return notes


def quality_warning(frames) -> str | None:
    """One line for a user about results whose report is poor (None if none
    is): the first one's warnings, and which frames of a sequence."""
    poor = [(t, f.quality["warnings"]) for t, f in enumerate(frames) if f.quality and f.quality["poor"]]
    if not poor:
        return None
    if len(frames) == 1:
        return f"check this segmentation: {'; '.join(poor[0][1])}"
    which = ", ".join(str(t) for t, _ in poor)
    return f"check frame(s) {which}: {'; '.join(poor[0][1])} (see results.json)"
