"""The myocardium between two surfaces: volume, mass, wall thickness and the
17-segment model.

The endocardium and the epicardium are graph surfaces ``v0 = f(v1, v2)`` of
one coordinate system and one pose, both closed at the base (mitral) plane
``x1 = 0`` of the model's frame, the epicardium outside the endocardium.  The
myocardium is the region between them below the mitral plane.

The 17 segments (Cerqueira et al. 2002) are defined on the model's frame:

* **levels** by the height ``x1`` above the mitral plane, in thirds of the
  cavity's length ``L`` (the largest ``x1`` of the endocardium): basal
  ``[0, L/3)``, mid ``[L/3, 2L/3)``, apical ``[2L/3, L]``; the **apex**
  (segment 17) is the myocardium beyond the cavity, ``x1 > L``;
* **sectors** by the angle ``psi = direction (theta - rv_insertion)`` around
  the long axis, from the anterior insertion of the right ventricle's wall
  into the septum, increasing towards the septum::

                     anterior (1, 7; 13)
                 6 /    psi = -30    \\ 2        rv_insertion: psi = 0,
      anterolateral                   anteroseptal   between 1 and 2
          (psi 240-300)              (psi 0-60)
               5                          3          inferior insertion:
      inferolateral                    inferoseptal   psi = 120
          (psi 180-240)              (psi 60-120)
                     \\  inferior (4)  /
                         psi 120-180

  basal (1-6) and mid (7-12) segments are 60 degrees wide, segment 1 (7)
  ``psi`` in ``[-60, 0)``, then 2 ... 6 every 60 degrees; the apical ones
  (13 anterior, 14 septal, 15 inferior, 16 lateral) are 90 degrees wide and
  centred on the anterior wall (``psi = -30``), the septum (``60``), the
  inferior wall (``150``) and the lateral wall (``240``).  Seen from the
  apex, as the bull's-eye plot shows it, the segments run anticlockwise
  when ``direction = +1`` and the image's axes are right-handed.

Wall thickness is measured along the ``v0`` coordinate curve (the lambda
direction in prolate spheroidal coordinates), from the endocardium to the
epicardium at the same ``(v1, v2)``: the arc length ``int h0 dv0``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.hermite import gauss_legendre
from .surface import Surface

__all__ = ["MYOCARDIAL_DENSITY", "SEGMENT_NAMES", "SegmentConvention", "myocardial_volume_ml", "lv_mass_g",
           "wall_thickness", "wall_thickness_grid", "cell_centres", "cavity_length", "segment_labels", "segment_volumes_ml", "segment_table",
           "times_to_minimum", "systolic_dyssynchrony_index"]

#: density of myocardium, g/mL (Lang et al., J Am Soc Echocardiogr 2015)
MYOCARDIAL_DENSITY = 1.05

#: the 17 segments of Cerqueira et al. (Circulation 2002), by number - 1
SEGMENT_NAMES = (
    "basal anterior", "basal anteroseptal", "basal inferoseptal", "basal inferior", "basal inferolateral",
    "basal anterolateral", "mid anterior", "mid anteroseptal", "mid inferoseptal", "mid inferior",
    "mid inferolateral", "mid anterolateral", "apical anterior", "apical septal", "apical inferior",
    "apical lateral", "apex",
)

_SIXTH, _QUARTER = np.pi / 3, np.pi / 2
#: where the sectors of a level start (psi, radians) and how wide they are
_SECTORS = {0: (-_SIXTH, _SIXTH, 6), 1: (-_SIXTH, _SIXTH, 6), 2: (np.radians(-75.0), _QUARTER, 4)}
_FIRST = {0: 1, 1: 7, 2: 13}


@dataclass(frozen=True)
class SegmentConvention:
    """Where segment 1 starts and which way the segments run.

    Parameters
    ----------
    rv_insertion : float
        ``theta`` (radians, in the model's frame) of the anterior insertion
        of the right ventricle into the septum: the boundary between
        segments 1 and 2.
    direction : {+1, -1}
        +1: ``theta`` increases from the anterior wall towards the septum.
    """

    rv_insertion: float = 0.0
    direction: int = 1

    def __post_init__(self):
        if not np.isfinite(self.rv_insertion):
            raise ValueError(f"rv_insertion must be a finite angle in radians, got {self.rv_insertion!r}")
        if self.direction not in (1, -1):
            raise ValueError(f"direction must be +1 or -1, got {self.direction!r}")

    @classmethod
    def from_points(cls, surface: Surface, rv_insertion, septum=None) -> "SegmentConvention":
        """The convention of a user's world points (mm): the anterior RV
        insertion and, optionally, a point on the septum (which sets the
        direction: the septum lies within 180 degrees of the insertion on
        its side)."""
        theta = cls._theta(surface, rv_insertion, "rv_insertion")
        direction = 1
        if septum is not None:
            turn = np.angle(np.exp(1j * (cls._theta(surface, septum, "septum") - theta)))
            direction = 1 if turn >= 0 else -1
        return cls(float(theta), direction)

    @staticmethod
    def _theta(surface: Surface, point, name: str) -> float:
        p = np.asarray(point, dtype=float)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise ValueError(f"{name} must be 3 finite numbers (x, y, z in mm), got {point!r}")
        local = surface.pose.to_local(p)
        if np.hypot(local[1], local[2]) < 1e-6:
            raise ValueError(f"{name} lies on the long axis: it gives no angle around it")
        return float(np.mod(np.arctan2(local[2], local[1]), 2 * np.pi))

    def psi(self, theta) -> np.ndarray:
        """The angle from the insertion towards the septum, in ``[0, 2 pi)``."""
        return np.mod(self.direction * (np.asarray(theta, dtype=float) - self.rv_insertion), 2 * np.pi)

    def to_dict(self) -> dict:
        return {"rv_insertion": float(self.rv_insertion), "direction": int(self.direction)}


def _check_pair(endocardium: Surface, epicardium: Surface) -> None:
    same_pose = endocardium.pose is epicardium.pose or (  # one pose object: as segmented
        np.allclose(endocardium.pose.origin, epicardium.pose.origin, atol=1e-9)
        and np.allclose(endocardium.pose.rotation, epicardium.pose.rotation, atol=1e-12))
    if endocardium.system != epicardium.system or not same_pose:
        raise ValueError("the endocardium and the epicardium must share one coordinate system and one pose")
    if tuple(endocardium.grid.v2_range) != tuple(epicardium.grid.v2_range):
        raise ValueError("the endocardium and the epicardium must span the same v2 range (closed at one base plane)")


def myocardial_volume_ml(endocardium: Surface, epicardium: Surface, *, order: int = 8) -> float:
    """Volume (mL) between the two surfaces below the mitral plane.

    ``V = V(epi) - V(endo)``, each the exact radial integral of the volume
    element (:meth:`Surface.volume_ml`): both regions are closed by the same
    base plane and the endocardium lies inside the epicardium.
    """
    _check_pair(endocardium, epicardium)
    return epicardium.volume_ml(order) - endocardium.volume_ml(order)


def lv_mass_g(myocardial_volume: float) -> float:
    """LV mass (g) of a myocardial volume (mL): ``1.05 g/mL x V``."""
    return MYOCARDIAL_DENSITY * float(myocardial_volume)


def wall_thickness(endocardium: Surface, epicardium: Surface, v1, v2, *, order: int = 8) -> np.ndarray:
    """Wall thickness (mm) at ``(v1, v2)`` along the ``v0`` coordinate curve.

    ``t = int_{f_endo}^{f_epi} h0(v0, v1, v2) dv0`` (Gauss-Legendre of
    ``order`` points; ``h0`` is smooth in ``v0``), the length of the
    coordinate curve (a hyperbola in prolate spheroidal coordinates, a ray
    in spherical and cylindrical ones) between the two surfaces.  Negative
    where the epicardium lies inside the endocardium.
    """
    _check_pair(endocardium, epicardium)
    v1, v2 = np.broadcast_arrays(np.asarray(v1, dtype=float), np.asarray(v2, dtype=float))
    return _arc_length(endocardium.system, endocardium.radius(v1, v2), epicardium.radius(v1, v2), v1, v2, order)


def cell_centres(surface: Surface, n1: int = 48, n2: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(v1, v2)``: the centres of ``n1 x n2`` cells (``n2`` default
    ``n1``) of the surface's ``(v1, v2)`` range, where the wall's thickness
    is read (the segment table, the quality report, the thickness floor)."""
    n2 = n1 if n2 is None else n2
    lo, hi = surface.grid.v2_range
    return (np.arange(n1) + 0.5) * (2 * np.pi / n1), lo + (np.arange(n2) + 0.5) * ((hi - lo) / n2)


def wall_thickness_grid(endocardium: Surface, epicardium: Surface, v1, v2, *, order: int = 8) -> np.ndarray:
    """:func:`wall_thickness` on the tensor grid of the ``v2`` values (rows)
    by the ``v1`` values (columns), shape ``(len(v2), len(v1))``, the
    surfaces evaluated by :meth:`Surface.radius_grid`."""
    _check_pair(endocardium, epicardium)
    v1, v2 = np.ravel(v1).astype(float), np.ravel(v2).astype(float)
    lo, hi = endocardium.radius_grid(v1, v2), epicardium.radius_grid(v1, v2)
    return _arc_length(endocardium.system, lo, hi, v1[None, :], v2[:, None], order)


def _arc_length(system, lo, hi, v1, v2, order):
    """``int_lo^hi h0(v0, v1, v2) dv0`` by Gauss-Legendre of ``order`` points."""
    t, w = gauss_legendre(order)
    length = hi - lo
    v0 = lo[..., None] + length[..., None] * t
    h0 = system.scale_factors(v0, np.asarray(v1)[..., None], np.asarray(v2)[..., None])[0]
    return (h0 @ w) * length


def cavity_length(endocardium: Surface, *, n: int = 64) -> float:
    """``L``: the largest height ``x1`` (mm) of the endocardium above the
    mitral plane (its apex), on an ``n x n`` grid of ``(v1, v2)`` and the tip."""
    v1 = np.linspace(0, 2 * np.pi, n, endpoint=False)
    v2 = np.linspace(*endocardium.grid.v2_range, n)
    heights = endocardium.grid_points(v1, v2, local=True)[..., 0]
    tip = endocardium.pose.to_local(endocardium.tip())[0]
    return float(max(heights.max(), tip))


def segment_labels(local, *, length: float, convention: SegmentConvention = SegmentConvention()) -> np.ndarray:
    """The segment (1-17) of points in the model's frame, 0 beyond the
    mitral plane (``x1 < 0``).

    Parameters
    ----------
    local : array (..., 3)
        Points in the model's local frame (mm), ``x1`` the height above the
        mitral plane.
    length : float
        ``L``, the cavity's length (:func:`cavity_length`), mm.
    convention : SegmentConvention

    Returns
    -------
    labels : int array (...)
    """
    local = np.asarray(local, dtype=float)
    if not (np.isfinite(length) and length > 0):
        raise ValueError(f"length must be a positive number of mm, got {length!r}")
    h = local[..., 0] / length
    psi = convention.psi(np.arctan2(local[..., 2], local[..., 1]))
    level = np.where(h < 1 / 3, 0, np.where(h < 2 / 3, 1, 2))
    labels = np.zeros(h.shape, dtype=np.int64)
    for k, (start, width, count) in _SECTORS.items():
        sector = np.floor(np.mod(psi - start, 2 * np.pi) / width).astype(np.int64)
        labels = np.where(level == k, _FIRST[k] + np.minimum(sector, count - 1), labels)
    labels = np.where(h > 1, 17, labels)
    return np.where(h < 0, 0, labels)


def segment_volumes_ml(surface: Surface, *, length: float, convention: SegmentConvention = SegmentConvention(),
                       n_v1: int = 8, n_v2: int = 512) -> np.ndarray:
    """Volume (mL) of the region under ``surface`` (``v0 <= f``) in each of
    the 17 segments' regions (index 0 is segment 1).

    In each half-plane ``theta = const`` the region lies between the long
    axis and the surface's meridian curve ``(x1(v2), rho(v2))``; by Green's
    theorem its volume per radian between the heights ``a`` and ``b`` is
    ``int rho^2 / 2 dx1`` along that curve with ``x1`` clipped to
    ``[a, b]`` (the axis and the cutting planes add nothing).  That is
    summed over ``n_v2`` chords of the curve, and integrated over ``theta``
    by Gauss-Legendre of ``n_v1`` points on pieces of every sector of at
    most 22.5 degrees (the sectors' and the patches' edges are the
    integrand's kinks).  The levels are those of
    :func:`segment_labels`; segment 17 holds what lies beyond ``length``.
    """
    if not (np.isfinite(length) and length > 0):
        raise ValueError(f"length must be a positive number of mm, got {length!r}")
    x, w = np.polynomial.legendre.leggauss(n_v1)
    v2 = np.linspace(*surface.grid.v2_range, n_v2 + 1)
    edges = [(0.0, length / 3), (length / 3, 2 * length / 3), (2 * length / 3, length)]
    out = np.zeros(17)

    def wedge(theta_lo, theta_hi, heights):
        """Volume per level (mm^3) of the region in the wedge between the
        angles (model theta), for each (a, b) of ``heights``."""
        # pieces of at most a sixteenth of a turn: the Hermite patches' edges are kinks too
        pieces = int(np.ceil((theta_hi - theta_lo) / (np.pi / 8) - 1e-9))
        half = (theta_hi - theta_lo) / (2 * pieces)
        theta = (theta_lo + half * (2 * np.arange(pieces)[:, None] + x + 1)).ravel()
        weights = np.tile(w, pieces)
        p = surface.grid_points(theta, v2, local=True)  # [v2, theta, 3]
        x1 = p[..., 0]
        rho2 = p[..., 1] ** 2 + p[..., 2] ** 2
        chord = (rho2[1:] + rho2[:-1]) / 4  # rho^2 / 2 at the chord's middle, by the trapezoid
        sign = np.sign(x1[0].mean() - x1[-1].mean()) or 1.0
        result = []
        for a, b in heights:
            clipped = np.clip(x1, a, b)
            result.append(sign * ((chord * (clipped[:-1] - clipped[1:])).sum(0) @ weights) * half)
        return result

    for k, (start, width, count) in _SECTORS.items():
        for s in range(count):
            lo = convention.rv_insertion + convention.direction * (start + s * width)
            hi = lo + convention.direction * width
            out[_FIRST[k] - 1 + s] = abs(wedge(min(lo, hi), max(lo, hi), [edges[k]])[0])
    out[16] = abs(wedge(0.0, 2 * np.pi, [(length, np.inf)])[0])
    return out / 1000.0


def segment_table(endocardium: Surface, epicardium: Surface | None = None, *,
                  convention: SegmentConvention = SegmentConvention(), n: int = 96) -> list[dict]:
    """The 17-segment table: per segment its number, name, cavity volume
    (mL) and, with an epicardium, its myocardial volume (mL) and mean wall
    thickness (mm).

    The cavity and the myocardium are cut by :func:`segment_labels`'s
    levels of the endocardium's length.  A segment's wall thickness is the
    mean of :func:`wall_thickness` over an ``n x n`` grid of ``(v1, v2)``
    whose endocardial points lie in it, weighted by the endocardium's
    area element ``h1 h2`` there; the apex's (17, beyond the cavity) is the
    thickness at the endocardial apex.
    """
    length = cavity_length(endocardium)
    cavity = segment_volumes_ml(endocardium, length=length, convention=convention)
    rows = [{"segment": k + 1, "name": SEGMENT_NAMES[k], "cavity_ml": float(cavity[k])} for k in range(17)]
    if epicardium is None:
        return rows
    _check_pair(endocardium, epicardium)
    myocardium = segment_volumes_ml(epicardium, length=length, convention=convention) - cavity
    lo = endocardium.grid.v2_range[0]
    v1, v2 = cell_centres(endocardium, n)
    thickness = wall_thickness_grid(endocardium, epicardium, v1, v2)
    f = endocardium.radius_grid(v1, v2)
    _, h1, h2 = endocardium.system.scale_factors(f, v1[None, :], v2[:, None])
    labels = segment_labels(endocardium.grid_points(v1, v2, local=True), length=length, convention=convention)
    apex_thickness = float(wall_thickness(endocardium, epicardium, 0.0, lo))
    for k, row in enumerate(rows):
        inside = labels == k + 1
        weight = (h1 * h2)[inside]
        mean = float(thickness[inside] @ weight / weight.sum()) if weight.sum() > 0 else float("nan")
        row["myocardium_ml"] = float(myocardium[k])
        row["wall_thickness_mm"] = apex_thickness if k == 16 else mean
    return rows


def times_to_minimum(curves) -> np.ndarray:
    """Time of each curve's minimum over one cycle, in % of the cycle.

    Parameters
    ----------
    curves : array (frames, k)
        ``k`` segmental volume curves sampled at ``frames`` equally spaced
        times of one cardiac cycle (frame ``t`` at ``t / frames`` of it).

    Returns
    -------
    array (k,)
        The minimum's time ``100 (t* / frames)``, ``t*`` the vertex of the
        parabola through the smallest sample and its two neighbours (the
        cycle taken as periodic), so that the time is not rounded to a
        frame.
    """
    v = np.asarray(curves, dtype=float)
    if v.ndim != 2 or v.shape[0] < 3:
        raise ValueError(f"curves must be an array (frames >= 3, segments), got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError("curves must be finite")
    n = v.shape[0]
    t = np.argmin(v, axis=0)
    cols = np.arange(v.shape[1])
    before, at, after = v[(t - 1) % n, cols], v[t, cols], v[(t + 1) % n, cols]
    curvature = before - 2 * at + after
    shift = np.where(curvature > 0, 0.5 * (before - after) / np.where(curvature > 0, curvature, 1.0), 0.0)
    return 100.0 * np.mod(t + np.clip(shift, -0.5, 0.5), n) / n


def systolic_dyssynchrony_index(curves) -> float:
    """SDI (% of the cycle): the standard deviation (``ddof = 0``) of the
    times to minimum volume of the 16 cavity segments (Kapetanakis et al.,
    Circulation 2005).

    Parameters
    ----------
    curves : array (frames, 16 or 17)
        Segmental volume curves of one cycle (:func:`times_to_minimum`); a
        17th column (the apex, which holds no cavity) is left out.
    """
    v = np.asarray(curves, dtype=float)
    if v.ndim != 2 or v.shape[1] not in (16, 17):
        raise ValueError(f"curves must be an array (frames, 16 or 17 segments), got shape {v.shape}")
    return float(np.std(times_to_minimum(v[:, :16])))
