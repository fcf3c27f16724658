"""The epicardium: a second graph surface outside a segmented endocardium.

The epicardium ``v0 = f_epi(v1, v2) = f_endo(v1, v2) + t(v1, v2)`` shares
the endocardium's coordinate system, pose and Hermite grid, so the
myocardium is the region ``f_endo < v0 <= f_epi`` below the mitral plane and
the wall thickness is measured along ``v0`` (:mod:`spheroseg.myocardium`).

It is found by the endocardium's own descent (:class:`spheroseg.Tracker`,
the least-squares step of eq. 25 with its data terms), started from the
endocardium moved out by a prior thickness.  The descent's thin-plate prior
acts on the departure from that start: on ``t`` minus the prior thickness,
a prior on the thickness and its smoothness.  The outer boundary of the
myocardium is mostly bright myocardium against darker tissue, lung and the
right ventricle's blood: when the wall is the brighter side of it (measured
at the start), the local means run with the wall inside
(:func:`wall_term`: ``LocalMeans(polarity=-1)``, in the compiled level loop
as the endocardium's) and put the boundary where the echo intensity is half
way between the wall's and what lies beyond it: the midpoint of the grey
levels lies on the dim side of a blurred edge.  A thickness below
``min_thickness_mm`` is raised to it afterwards (:func:`enforce_thickness`):
the epicardium never lies inside the endocardium.
"""

from __future__ import annotations

import numpy as np

from ..descent.backends import sample_points
from ..descent.dataterms import LocalMeans, NoSpeckleError, speckle_nepers
from ..geometry.hermite import gauss_legendre
from ..surfaces.myocardium import SegmentConvention, cell_centres, wall_thickness_grid
from ..descent.quality import wall_report
from ..descent.results import SegmentationResult
from ..surfaces.surface import Surface
from .tracker import Tracker
from ..volumes.volume import Volume

#: the epicardium's iteration cap: a bright wall's outer boundary settles in
#: 5-12 iterations from the prior thickness across the image-formation
#: sweep; a wall still moving after this many has no clear outer boundary
#: (a dark wall collapses slowly towards the endocardium) and is flagged
MAX_ITERATIONS = 30
#: a dark wall's cap: its weak outer edge gives the local means no boundary
#: to settle on and they drift inwards (on the sweep's ``contrast_low``
#: the median thickness falls by about 0.1 mm an iteration from 6.5 mm at
#: 10 to 4.8 at 30); it is flagged (:data:`DARK_EPICARDIUM`) wherever it
#: stops, so it stops at half the bright wall's cap: a boundary that
#: cannot be found costs no more time than one that can
DARK_MAX_ITERATIONS = 15
#: the prior wall thickness (mm): the epicardium's start, within the normal
#: adult range (6-10 mm; Lang et al. 2015)
PRIOR_THICKNESS_MM = 8.0
#: the endocardium's warning when its wall is darker than what lies beyond it
DARK_WALL = ("the myocardium is darker than what lies beyond it: past a thin wall its grey level may be read "
             "too high and the wall placed outside (the volume too large)")
#: how much darker than what lies beyond it (a fraction of the blood-wall
#: contrast) a wall must read for :data:`DARK_WALL`: tissue 1 dB brighter
#: at 30 dB, read as the wall's level, moves the volume by about 2 %
DARK_WALL_MARGIN = 0.03
#: the epicardium's warning on such a wall: the local means of its weak outer
#: edge lean on the cavity's darker blood and pull it in
DARK_EPICARDIUM = ("the myocardium is darker than what lies beyond it: its outer edge is weak and the epicardium "
                   "may lie inside it (the mass too low)")

__all__ = ["MAX_ITERATIONS", "DARK_MAX_ITERATIONS", "PRIOR_THICKNESS_MM", "DARK_WALL", "DARK_WALL_MARGIN",
           "DARK_EPICARDIUM", "initial_epicardium", "conserving_start", "enforce_thickness", "wall_polarity",
           "check_wall_polarity", "wall_nepers", "wall_term", "segment_epicardium", "add_epicardium"]


def _node_offsets(surface: Surface, thickness_mm: float) -> np.ndarray:
    """``t`` at the grid's nodes such that the ``v0`` curve from the
    surface to ``f + t`` is ``thickness_mm`` long there: Newton's method on
    ``int_f^{f+t} h0 dv0 = thickness_mm`` (its derivative is ``h0(f + t)``)."""
    grid = surface.grid
    v2, v1 = np.meshgrid(grid.node_v2, grid.node_v1, indexing="ij")
    f = np.maximum(surface.coefficients[..., 0], 0.0)  # f at a node is its value there, as radius()
    x, w = gauss_legendre(4)  # h0 is smooth across a wall (as wall_thickness_grid's order 4)
    # the start: h0 a typical offset out, not at f, where a surface collapsed onto the focal segment has h0 = 0
    h0 = surface.system.scale_factors(f, v1, v2)[0]
    typical = thickness_mm / float(np.median(h0[h0 > 0])) if np.any(h0 > 0) else 1.0
    t = thickness_mm / surface.system.scale_factors(f + typical, v1, v2)[0]
    for _ in range(6):  # quadratic convergence from within a few per cent: 3 reach rounding
        v0 = f[..., None] + t[..., None] * x
        length = (surface.system.scale_factors(v0, v1[..., None], v2[..., None])[0] @ w) * t
        error = length - thickness_mm
        t = t - error / surface.system.scale_factors(f + t, v1, v2)[0]
        if np.abs(error).max() <= 1e-12 * thickness_mm:
            break
    return t


def initial_epicardium(endocardium: Surface, *, thickness_mm: float) -> Surface:
    """The endocardium moved out along ``v0`` so that the wall is
    ``thickness_mm`` thick at its nodes (Newton's method; the offset's
    slopes 0 there)."""
    if not (np.isfinite(thickness_mm) and thickness_mm > 0):
        raise ValueError(f"thickness_mm must be a positive number of mm, got {thickness_mm!r}")
    t = np.zeros(endocardium.coefficients.shape)
    t[..., 0] = _node_offsets(endocardium, thickness_mm)
    return endocardium.with_coefficients(endocardium.grid.constrain(endocardium.coefficients + t))


def conserving_start(endocardium: Surface, previous_endocardium: Surface, previous_epicardium: Surface, *,
                     iterations: int = 40) -> Surface:
    """The previous frame's wall moved onto this frame's endocardium, its
    myocardial volume kept (the myocardium is nearly incompressible).

    The previous offset ``t = f_epi - f_endo`` (in ``v0``) is added to this
    endocardium scaled by the factor ``s`` for which ``V(epi) - V(endo)``
    equals the previous frame's (bisection on ``s``: the volume grows with
    it).  The surfaces must share the system and the grid.
    """
    offset = previous_epicardium.coefficients - previous_endocardium.coefficients
    target = previous_epicardium.volume_ml() - previous_endocardium.volume_ml()
    inner = endocardium.volume_ml()

    def start(s):
        return endocardium.with_coefficients(endocardium.coefficients + s * offset)

    lo, hi = 0.0, 1.0
    while start(hi).volume_ml() - inner < target and hi < 64:
        hi *= 2
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if start(mid).volume_ml() - inner < target else (lo, mid)
    return start(0.5 * (lo + hi))


def enforce_thickness(endocardium: Surface, epicardium: Surface, *, min_thickness_mm: float,
                      n: int = 48) -> Surface:
    """The epicardium with its thickness raised to at least
    ``min_thickness_mm`` (mm, along ``v0``).

    Nodes whose thickness is below it are set to it with flat slopes
    (projected back on the pole constraints); where the Hermite
    interpolation still dips below it between nodes, on the centres of an
    ``n x n`` grid of cells of ``(v1, v2)``
    (:func:`spheroseg.myocardium.cell_centres`),
    the whole thickness is raised by the deficit there.
    """
    return _enforced(endocardium, epicardium, min_thickness_mm, n)[0]


def _enforced(endocardium: Surface, epicardium: Surface, min_thickness_mm: float, n: int):
    """:func:`enforce_thickness`, and the wall thickness it leaves on
    :func:`spheroseg.myocardium.cell_centres` (rows ``v2``)."""
    if not (np.isfinite(min_thickness_mm) and min_thickness_mm >= 0):
        raise ValueError(f"min_thickness_mm must be a number of mm >= 0, got {min_thickness_mm!r}")
    grid = endocardium.grid
    t = epicardium.coefficients - endocardium.coefficients
    floor = _node_offsets(endocardium, min_thickness_mm)
    low = t[..., 0] < floor
    t[low] = 0.0
    t[..., 0][low] = floor[low]
    epi = endocardium.with_coefficients(grid.constrain(endocardium.coefficients + t))
    v1, v2 = cell_centres(endocardium, n)
    # 4 Gauss nodes: h0 is smooth across a wall (8 agree to 1e-13 mm on a phantom's)
    thickness = wall_thickness_grid(endocardium, epi, v1, v2, order=4)
    deficit = min_thickness_mm - thickness.min()
    if deficit > 0:
        # a constant in v0 moves the wall out by at least its times the smallest h0 there
        f = endocardium.radius_grid(v1, v2)
        h0 = endocardium.system.scale_factors(f, v1[None, :], v2[:, None])[0]
        lift = np.zeros(t.shape)
        lift[..., 0] = 1.001 * deficit / h0.min()
        epi = epi.with_coefficients(grid.constrain(epi.coefficients + lift))
        thickness = wall_thickness_grid(endocardium, epi, v1, v2, order=4)
    return epi, thickness


def wall_polarity(volume: Volume, endocardium: Surface, epicardium: Surface, *, shell_mm: float = 8.0,
                  n: int = 16) -> float:
    """The median grey level of the wall (between the two surfaces) minus
    that of a shell ``shell_mm`` thick outside the epicardium, sampled along
    ``v0`` on an ``n x n`` grid of ``(v1, v2)``; NaN without data."""
    v1, v2 = cell_centres(endocardium, n)
    f_in, f_out = endocardium.radius_grid(v1, v2), epicardium.radius_grid(v1, v2)
    v1, v2 = v1[None, :], v2[:, None]
    h0 = endocardium.system.scale_factors(f_out, v1, v2)[0]
    fractions = np.linspace(0.25, 1.0, 4)
    wall = f_in[..., None] + (f_out - f_in)[..., None] * (fractions - 0.125)
    shell = f_out[..., None] + (shell_mm / h0)[..., None] * fractions

    def grey(v0):
        local = endocardium.system.to_cartesian(v0, v1[..., None], v2[..., None])
        values = sample_points(volume, endocardium.pose.to_world(local))
        return np.nanmedian(values) if np.isfinite(values).any() else np.nan

    return float(grey(wall) - grey(shell))


def check_wall_polarity(result: SegmentationResult, volume: Volume, *,
                        thickness_mm: float = PRIOR_THICKNESS_MM) -> str:
    """Whether ``result``'s myocardium is brighter than what lies beyond it
    ("bright") or not ("dark"): :func:`wall_polarity` of a wall
    ``thickness_mm`` thick outside its endocardium.  The report keeps the
    contrast (``wall_contrast``, grey levels; NaN without data, taken as
    bright), and a wall darker by more than :data:`DARK_WALL_MARGIN` of the
    blood-wall contrast (``c_out - c_in``) adds :data:`DARK_WALL` to it
    unless the intensity interface took all of what its outer band read
    beyond it off the wall's level (``quality["beyond_wall_fraction"]``
    1): a wall as bright as the tissue beyond it is not flagged.

    The intensity interface reads the myocardium's grey level from band
    means 2-8 mm outside the local means' wall
    (:class:`spheroseg.dataterms.IntensityInterface`); past a thin wall
    that is darker than what lies beyond it, the far offsets read that
    tissue.  Where the band's profile shows it clearly
    (:func:`spheroseg.descent.speckle.beyond_wall_excess`) the interface takes it
    off; where it does not (a dark wall as thick as the band, or a profile
    a smoothing blurred into one rise, whose steps may be an edge's), the
    level may be read too high and the wall moved out.  Of the image-formation sweep only
    ``contrast_low`` (the myocardium 5 dB darker than the tissue around the
    heart) has a dark wall (docs/benchmarks.md)."""
    contrast = wall_polarity(volume, result.surface, initial_epicardium(result.surface, thickness_mm=thickness_mm))
    polarity = "dark" if contrast < 0 else "bright"
    if result.quality is not None:
        result.quality["wall_contrast"] = float(contrast)
        margin = DARK_WALL_MARGIN * (result.c_out - result.c_in)
        darker = contrast < -margin if margin > 0 else polarity == "dark"
        if darker and result.quality.get("beyond_wall_fraction", 0.0) < 1:
            result.quality["warnings"] = list(result.quality["warnings"]) + [DARK_WALL]
            result.quality["poor"] = True
    return polarity


def wall_nepers(volume: Volume, endocardium: Surface, epicardium: Surface, *, per_patch: int = 6) -> float:
    """Grey levels per neper of echo intensity (:func:`speckle_nepers`)
    from the speckle of the wall: the nearest voxels at a quarter, half and
    three quarters of the way from the endocardium to ``epicardium`` on
    ``per_patch x per_patch`` rays per patch of the grid."""
    grid = endocardium.grid
    m1, m2 = grid.n1 * per_patch, grid.n2 * per_patch
    v1, v2 = cell_centres(endocardium, m1, m2)
    patch = (np.arange(m2)[:, None] // per_patch) * grid.n1 + np.arange(m1)[None, :] // per_patch
    f_in, f_out = endocardium.radius_grid(v1, v2), epicardium.radius_grid(v1, v2)
    v1, v2 = v1[None, :], v2[:, None]
    v0 = f_in[..., None] + (f_out - f_in)[..., None] * np.array([0.25, 0.5, 0.75])
    local = endocardium.system.to_cartesian(v0, v1[..., None], v2[..., None])
    samples = sample_points(volume, endocardium.pose.to_world(local), order=0)
    return speckle_nepers(samples.reshape(-1, 3), patch.ravel())


def wall_term(nepers: float = np.inf) -> LocalMeans:
    """The data term of a bright wall's outer boundary: the local means
    with the wall inside (``polarity`` -1), the boundary where the echo
    intensity is half way between the wall's and what lies beyond it at
    ``nepers`` grey levels per neper (:func:`wall_nepers`; inf: the grey
    levels' midpoint)."""
    return LocalMeans(polarity=-1.0, boundary_nepers=float(nepers))


def segment_epicardium(volume: Volume, endocardium: Surface, *, thickness_mm: float = PRIOR_THICKNESS_MM,
                       min_thickness_mm: float = 2.0, polarity: str = "auto", boundary: str = "intensity",
                       nepers: float | None = None, start: Surface | None = None, **options) -> SegmentationResult:
    """The epicardium of a segmented endocardium.

    Parameters
    ----------
    volume : Volume
        The image the endocardium was segmented on.
    endocardium : Surface
        The endocardium (:attr:`SegmentationResult.surface`).
    thickness_mm : float
        Prior wall thickness (mm): the start, and what the thin-plate prior
        (``smoothness``) pulls the thickness's variations back towards.
        8 mm is within the normal adult range (6-10 mm; Lang et al. 2015).
    min_thickness_mm : float
        Smallest thickness allowed (mm).
    polarity : {"auto", "bright", "dark"}
        Whether the myocardium is brighter ("bright") or darker than what
        lies outside it; "auto" measures it at the start
        (:func:`wall_polarity`).
    boundary : {"intensity", "midpoint"}
        Where a bright wall's outer boundary lies: where the echo intensity
        is half way between the wall's and what lies beyond it
        (:func:`wall_term`; the midpoint where the image has no
        speckle to read its log compression from), or at the midpoint of
        the band means' grey levels (:class:`spheroseg.dataterms.LocalMeans`).
        Unused with ``mode`` given.
    nepers : float, optional
        Grey levels per neper of the image's log compression, for the
        "intensity" boundary: the endocardium's estimate
        (:attr:`SegmentationResult.log_compression`, which
        :func:`add_epicardium` hands over), read from the same wall's
        speckle and bounded by its contrast
        (:func:`spheroseg.descent.speckle.interface_nepers`), so that smoothed
        speckle does not lower it; by default :func:`wall_nepers`.
    start : Surface, optional
        The start (and the thin-plate prior's reference) instead of the
        endocardium moved out by ``thickness_mm``: in a sequence,
        :func:`conserving_start` of the previous frame.
    **options
        :class:`spheroseg.SegmentOptions` of the descent; by default
        ``mode="local"`` (:func:`wall_term` on a bright wall; a ``mode``
        given runs on the image as it is, the wall inside), ``band=4`` (the
        inner band stays in the wall), ``apex_weight=0`` (the epicardial
        apex is not clicked), ``max_iterations`` :data:`MAX_ITERATIONS` (a
        wall still moving then is flagged poor; a dark wall's
        :data:`DARK_MAX_ITERATIONS`); on a bright wall
        ``tol=0.1`` (mm of RMS motion, the coarse levels' tolerance: the edge of the wall's
        intensity, blurred over a point-spread function's width, is not
        found to the endocardium's 0.05 mm).  A dark wall keeps the
        endocardium's: where the wall is not brighter than what lies
        beyond it the wall can collapse slowly, and a coarser tolerance
        stops the collapse part-way (the wall is flagged either way).

    Returns
    -------
    SegmentationResult
        Its ``surface`` is the epicardium, on the endocardium's grid; its
        ``quality`` the wall's (:func:`spheroseg.quality.wall_report` of the
        thickness on 48 x 48 :func:`spheroseg.myocardium.cell_centres`),
        with :data:`DARK_EPICARDIUM` on a dark wall.
    """
    if polarity not in ("auto", "bright", "dark"):
        raise ValueError(f"polarity must be 'auto', 'bright' or 'dark', got {polarity!r}")
    if boundary not in ("intensity", "midpoint"):
        raise ValueError(f"boundary must be 'intensity' or 'midpoint', got {boundary!r}")
    own_mode = "mode" in options
    if start is None:
        start = initial_epicardium(endocardium, thickness_mm=thickness_mm)
    elif not isinstance(start, Surface) or start.grid.shape != endocardium.grid.shape:
        raise ValueError("start must be a Surface on the endocardium's grid")
    if polarity == "auto":
        contrast = wall_polarity(volume, endocardium, start)
        polarity = "dark" if contrast < 0 else "bright"
    if polarity == "bright" and not own_mode:
        options = {"tol": 0.1, **options}
    options = {"mode": "local", "band": 4.0, "apex_weight": 0.0,
               "max_iterations": DARK_MAX_ITERATIONS if polarity == "dark" else MAX_ITERATIONS,
               "patches": (endocardium.grid.n1, endocardium.grid.n2), **options}
    if own_mode:
        boundary = None
    elif polarity == "bright":
        if boundary == "midpoint":
            nepers = np.inf
        elif nepers is None:
            try:
                nepers = wall_nepers(volume, endocardium, start)
            except NoSpeckleError:  # no speckle to read the log compression from: the grey levels' midpoint
                nepers, boundary = np.inf, "midpoint"
        elif not (np.isfinite(nepers) and nepers > 0):
            raise ValueError(f"nepers must be a positive number of grey levels per neper, got {nepers!r}")
        options["mode"] = wall_term(nepers)
    else:
        boundary = "midpoint"
    apex = endocardium.tip()
    # the thickness floor holds it outside the endocardium, whose base ring was held open
    result = Tracker(volume, apex, endocardium.pose.origin, init=start, **options).run(report=False, base_ring=False)
    result.surface, thickness = _enforced(endocardium, result.surface, min_thickness_mm, 48)
    result.quality = wall_report(thickness, min_thickness_mm=min_thickness_mm, settled=result.status != 1)
    if polarity == "dark":
        result.quality["warnings"].append(DARK_EPICARDIUM)
        result.quality["poor"] = True
    result.parameters = {**result.parameters, "thickness_mm": thickness_mm, "min_thickness_mm": min_thickness_mm,
                         "polarity": polarity, "boundary": boundary,
                         "nepers": float(nepers) if boundary == "intensity" else None}
    return result


def add_epicardium(result: SegmentationResult, volume: Volume, *, rv_insertion=None,
                   previous: SegmentationResult | None = None, **options) -> SegmentationResult:
    """``result`` (an endocardium) with its epicardium, its segment
    convention and the wall in its quality report.

    Parameters
    ----------
    result : SegmentationResult
    volume : Volume
    rv_insertion : float, (x, y, z) or SegmentConvention, optional
        Where segment 1 starts: ``theta`` (radians) of the anterior RV
        insertion in the model's frame, a world point (mm) on it, or a
        :class:`~spheroseg.myocardium.SegmentConvention`; default
        ``theta = 0``.
    previous : SegmentationResult, optional
        The previous frame of a sequence, with its epicardium: this frame's
        starts from its wall with its myocardial volume
        (:func:`conserving_start`).
    **options
        Of :func:`segment_epicardium`; ``nepers`` by default the result's
        :attr:`~SegmentationResult.log_compression`.
    """
    if isinstance(rv_insertion, SegmentConvention):
        convention = rv_insertion
    elif rv_insertion is None:
        convention = SegmentConvention()
    elif np.ndim(rv_insertion) == 0:
        convention = SegmentConvention(float(rv_insertion))
    else:
        convention = SegmentConvention.from_points(result.surface, rv_insertion)
    endo = result.surface
    if previous is not None and previous.epicardium is not None and "start" not in options:
        options["start"] = conserving_start(endo, previous.surface, previous.epicardium)
    options.setdefault("nepers", result.log_compression)  # the image's, as the endocardium read it
    epi = segment_epicardium(volume, endo, **options)
    wall = epi.quality
    quality = dict(result.quality or {"warnings": [], "poor": False})
    quality["epicardium"] = wall
    quality["warnings"] = list(quality.get("warnings", [])) + [f"epicardium: {w}" for w in wall["warnings"]]
    quality["poor"] = bool(quality["warnings"])
    result.epicardium = epi.surface
    result.segment_convention = convention
    result.quality = quality
    result.seconds += epi.seconds
    result.parameters = {**result.parameters, "epicardium": {k: v for k, v in epi.parameters.items()
                                                             if k in ("mode", "band", "smoothness", "thickness_mm",
                                                                      "min_thickness_mm", "polarity", "boundary",
                                                                      "nepers", "tol", "max_iterations")},
                         "segment_convention": convention.to_dict()}
    return result
