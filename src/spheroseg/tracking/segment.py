"""Segmentation and tracking: short loops over a :class:`spheroseg.Tracker`.

The parts of an iteration live in modules named for them:
:mod:`spheroseg.tracker` (the stepper), :mod:`spheroseg.stepper` (the schedule),
:mod:`spheroseg.descent` (the least-squares step of eq. 25),
:mod:`spheroseg.dataterms` (``c_in``, ``c_out`` of eq. 22),
:mod:`spheroseg.backends` (the array work: numpy reference and compiled),
:mod:`spheroseg.discretisation` (the grid's sample points and matrices) and
:mod:`spheroseg.energy` (the energies and their gradients).
"""

from __future__ import annotations

import contextlib

from typing import Callable, Sequence

import numpy as np

from .initial import check_volume
from .locate import annotate, initialise
from .epicardium import PRIOR_THICKNESS_MM, add_epicardium, check_wall_polarity
from ..descent.options import MODES
from ..descent.results import Intermediate, SegmentationResult, TrackingResult
from ..surfaces.surface import Surface
from .tracker import Tracker

__all__ = ["segment", "track", "tracking_order", "add_checks", "SegmentationResult", "TrackingResult", "Intermediate", "MODES"]


def add_checks(result: SegmentationResult, volume, initialisation: dict, located, *,
               thickness_mm: float = PRIOR_THICKNESS_MM) -> str | None:
    """What a result gets after its descent: how it was initialised and
    the click checks (:func:`spheroseg.locate.annotate`) and, when the
    ventricle was located (``located`` not None), the wall's polarity
    (:func:`spheroseg.epicardium.check_wall_polarity` of a wall
    ``thickness_mm`` thick), which it returns; None without it."""
    annotate(result, initialisation, located)
    return None if located is None else check_wall_polarity(result, volume, thickness_mm=thickness_mm)


def segment(volume, apex=None, base=None, *, annulus=None, landmarks=None, init: Surface | None = None,
            iter_callback: Callable[[Intermediate], None] | None = None, check: bool = True,
            myocardium: bool = False, rv_insertion=None, epicardium_options: dict | None = None,
            **options) -> SegmentationResult:
    """Segment the left-ventricular cavity from an apex and a base point
    (or the mitral annulus).

    Parameters
    ----------
    volume : Volume
        3D echo image (blood dark, tissue bright).
    apex, base : (x, y, z)
        World points (mm, ITK physical space): the endocardial apex and the
        centre of the mitral plane.  The cavity is closed at the plane
        through ``base`` perpendicular to the apex-base axis, unless
        ``annulus`` is given (then ``base`` may be None).  Neither: the
        ventricle is found first (:func:`spheroseg.locate`).
    annulus : array (k, 3), optional
        ``k >= 3`` world points (mm) of the mitral annulus: the cavity is
        closed at their least-squares plane, whose normal is the long axis;
        the apex may lie off it (see :class:`spheroseg.Tracker`).
    landmarks : array (k, 3), optional
        World points of the wall the surface is drawn to (to stop a leak),
        held by ``landmark_weight``; ``quality["landmark_residuals_mm"]``
        gives how far it ends from each (over 2 mm: a warning).
    init : Surface, optional
        Start from this surface instead of the half-ellipsoid (no
        coarse-to-fine then); ``apex`` and ``base`` are then only checked.
    iter_callback : callable, optional
        Called as ``iter_callback(intermediate)`` after every iteration with
        an :class:`Intermediate` (surface, iteration, level, motion); raising
        ``StopIteration`` ends the run (``status`` 2), as in scipy.
    check : bool
        Check given points against the located ventricle
        (:func:`spheroseg.locate.check_points`): a gross disagreement makes
        ``quality["poor"]`` with a warning naming the point, and so does a
        ventricle too uncertain to check them against (refused, or under
        :data:`spheroseg.locate.CHECK_CONFIDENCE`): a warning that they
        were not checked.  The location reads a coarse copy of a fixed
        number of points per 3 mm, whatever the image's resolution.  With the
        points checked or located, a myocardium darker than what lies
        beyond it is a warning too
        (:func:`spheroseg.epicardium.check_wall_polarity`).
    **options
        Keyword options of :class:`spheroseg.SegmentOptions`: ``system``,
        ``patches`` (8 x 8), ``mode`` (``"intensity"``), ``step`` (1 mm),
        ``adaptive_step``, ``max_iterations`` (60 per level), ``tol``
        (0.05 mm), ``coarse_tol`` (twice ``tol``), ``coarse_to_fine``,
        ``band``, ``band_out``, ``interface``, ``nu``,
        ``smoothness``, ``landmark_weight``, ``apex_weight``, ``order``,
        ``radius_ratio``, ``backend``, ``threads``.
    myocardium : bool
        Also segment the epicardium after the endocardium
        (:func:`spheroseg.epicardium.segment_epicardium`): the result then
        has ``epicardium``, ``myocardium_mask(volume)``,
        ``myocardial_volume_ml``, ``lv_mass_g``, ``wall_thickness_mm`` and
        ``segments`` (the 17-segment table, :mod:`spheroseg.myocardium`).
    rv_insertion : float or (x, y, z), optional
        Where segment 1 starts: the anterior RV insertion, as ``theta``
        (radians) in the model's frame or a world point (mm).
    epicardium_options : dict, optional
        Keywords of :func:`spheroseg.epicardium.segment_epicardium`.

    Returns
    -------
    SegmentationResult
        ``surface``, ``volume_ml``, ``mask(volume)``, ``mesh()``, why it
        stopped (``status``, ``message``) and how it started
        (``initialisation``: ``method`` ``"located"`` or ``"given"``, the
        points, what was located).

    Notes
    -----
    The surface is ``v0 = f(v1, v2)``, ``f`` bicubic Hermite (paper section
    3).  One iteration (:class:`spheroseg.descent.Descent`) evaluates the
    surface at fixed Gauss-Legendre points, reads the grey level ``u`` there,
    and moves each point along its normal by
    ``step * -clip(r / s, -1, 1)`` mm, with ``r = (u - c_in)^2 - (u - c_out)^2``
    the integrand of eq. 22 and ``s`` the squared contrast.  That displacement
    in ``v0``, ``dv0``, is projected on the Hermite space together with a
    smoothing prior and the landmarks:

    .. math::

        (M + a T + L^T \\Omega L) p^+ = M p + B^T W \\Delta v_0 + a T p_{ref}
        + L^T \\Omega (L p + r)

    with ``M = B^T W B`` the mass matrix (eq. 10's normalisation), ``T`` a
    thin-plate matrix, ``L`` the surface at the landmarks and ``r`` their
    residuals.  A level stops when the RMS motion falls below ``tol``; the
    levels run coarse to fine (2 x 2, 4 x 4, 8 x 8 patches).

    Departures from the paper, each needed on real echo (CETUS):

    - the force is normalised by the contrast and clipped, so ``step`` is a
      distance (eq. 25's ``dt`` is the paper's 0.04 of the radius);
    - the update is preconditioned by ``M`` (least squares, not the raw
      gradient);
    - a thin-plate prior on the departure from the initial shape
      (``smoothness``; 0 is the paper's method);
    - the clicked apex is held as a landmark (``apex_weight``; 0 frees it);
    - the default data term takes means local to each surface point
      (``mode="local"``, Lankton & Tannenbaum 2008) instead of the global
      Chan-Vese means (``"chan-vese"``) or the fixed interface of the
      paper's experiments (``"fast"``);
    - the focal length is ``|apex - base| / cosh(1)``, so the paper's
      initial ``lambda = 1`` passes through the apex.

    References
    ----------
    .. [1] Duan Q, Angelini ED, Laine AF et al. Variational segmentation
       framework in prolate spheroidal coordinates for 3D real-time
       echocardiography. Proc. SPIE 6144, 61444A (2006). doi:10.1117/12.653692
    .. [2] Lankton S, Tannenbaum A. Localizing region-based active contours.
       IEEE Trans. Image Process. 17(11):2029-2039 (2008).
       doi:10.1109/TIP.2008.2004611
    .. [3] Barbosa D, Dietenbeck T, Schaerer J et al. B-spline explicit active
       surfaces. IEEE Trans. Image Process. 21(1):241-251 (2012).
       doi:10.1109/TIP.2011.2161484

    Examples
    --------
    >>> from spheroseg import segment
    >>> from spheroseg.synthetic.phantom import make_phantom
    >>> ph = make_phantom(seed=3, spacing=2.0)
    >>> res = segment(ph.volume, ph.apex, ph.base)
    >>> res.status, res.converged
    (0, True)
    >>> bool(abs(res.volume_ml - ph.truth_volume_ml) < 0.15 * ph.truth_volume_ml)
    True
    """
    check_volume(volume)  # a bare array: a TypeError here, not an AttributeError from deep inside
    apex, base, initialisation, located = initialise(volume, apex, base, annulus=annulus, init=init, check=check)
    result = Tracker(volume, apex, base, annulus=annulus, landmarks=landmarks, init=init, **options).run(iter_callback)
    epicardium_options = dict(epicardium_options or {})
    polarity = add_checks(result, volume, initialisation, located,
                          thickness_mm=epicardium_options.get("thickness_mm", PRIOR_THICKNESS_MM))
    if polarity is not None and "start" not in epicardium_options:  # the epicardium need not read it again
        epicardium_options.setdefault("polarity", polarity)
    if myocardium:
        result = add_epicardium(result, volume, rv_insertion=rv_insertion, **epicardium_options)
    return result


def track(
    volumes: Sequence,
    apex=None,
    base=None,
    *,
    annulus=None,
    iterations_per_frame: int = 20,
    follow_base: bool = True,
    progress: Callable[[int, int], None] | None = None,
    landmarks=None,
    init: Surface | None = None,
    iter_callback: Callable[[Intermediate], None] | None = None,
    check: bool = True,
    myocardium: bool = False,
    rv_insertion=None,
    epicardium_options: dict | None = None,
    start_frame: int = 0,
    **options,
) -> TrackingResult:
    """Segment every frame of a 3D+t sequence.

    The start frame (the first by default) is segmented from ``apex`` and
    ``base`` as by :func:`segment` (all its keywords apply); every other
    frame starts from its neighbour's surface, forwards to the last frame
    and then backwards from the start frame to the first
    (:func:`tracking_order`; :meth:`Tracker.next_frame`), and runs until the
    surface stops moving (``tol``), at most ``iterations_per_frame``
    iterations: the paper used 3 to 5; on the 10-frame phantom cycles, where
    the wall moves up to 4 mm between frames, 4 to 7 are run.  The matrices
    of the first frame are reused.  The apex stays where it was clicked; the
    base (mitral) plane keeps its orientation and follows the annulus along
    the long axis from frame to frame (``follow_base``, see
    :mod:`spheroseg.annulus`: it moves 8-15 mm towards the apex in systole;
    kept still, the end-systolic cavity reaches into the atrium).

    Parameters
    ----------
    volumes : sequence of Volume
    apex, base, annulus, landmarks, init, iter_callback, check, **options
        As :func:`segment`; the ventricle is located (or the points
        checked) in the first frame.
    iterations_per_frame : int
        Cap on iterations of every frame after the first.
    follow_base : bool
        Move the base plane with the mitral annulus (False: the first
        frame's plane throughout).
    progress : callable, optional
        ``progress(frames_done, frames)`` after each frame.
    start_frame : int
        The frame the points are placed on (0-based; negative counts from
        the last), recorded in the result (``TrackingResult.start_frame``).
    myocardium, rv_insertion, epicardium_options
        As :func:`segment`, for every frame: the epicardium of each frame
        after the first starts from the previous frame's wall moved onto
        its endocardium with the same myocardial volume
        (:func:`spheroseg.epicardium.conserving_start`).

    Returns
    -------
    TrackingResult
        ``.frames``, ``.volumes_ml``, ``.edv_ml``, ``.esv_ml``, ``.ef``
        (percent); with ``myocardium``, ``.segment_volumes_ml``,
        ``.times_to_minimum``, ``.sdi`` and ``.masses_g``.
    """
    volumes = list(volumes)
    if len(volumes) < 2:
        raise ValueError(f"a sequence needs at least 2 frames, got {len(volumes)}")
    if not (isinstance(iterations_per_frame, (int, np.integer)) and iterations_per_frame >= 1):
        raise ValueError(f"iterations_per_frame must be a positive integer, got {iterations_per_frame!r}")
    for volume in volumes:
        check_volume(volume)
    order = tracking_order(len(volumes), start_frame)
    start = order[0]
    apex, base, initialisation, located = initialise(volumes[start], apex, base, annulus=annulus, init=init,
                                                     check=check)
    frames: dict[int, SegmentationResult] = {}
    for t in order:
        with _naming_frame(t):
            if t == start or t == start - 1:  # each direction starts from the start frame
                tracker = Tracker(volumes[start], apex, base, annulus=annulus, landmarks=landmarks, init=init,
                                  **options)
                first = tracker.run(iter_callback)
            if t == start:
                frames[t] = first
                add_checks(first, volumes[t], initialisation, located)
            else:
                frames[t] = tracker.next_frame(volumes[t], max_iterations=iterations_per_frame,
                                               iter_callback=iter_callback, follow_base=follow_base)
            if myocardium:
                neighbour = t - 1 if t > start else t + 1
                add_epicardium(frames[t], volumes[t], rv_insertion=rv_insertion, previous=frames.get(neighbour),
                               **(epicardium_options or {}))
        if progress is not None:
            progress(len(frames), len(volumes))
    return TrackingResult([frames[t] for t in range(len(volumes))], start_frame=start)


def tracking_order(n_frames: int, start_frame: int = 0) -> list[int]:
    """The order :func:`track` segments ``n_frames`` frames in from
    ``start_frame`` (negative: from the last): forwards to the last frame,
    then backwards from the start frame to the first, each direction
    stepping from its neighbour."""
    if not (isinstance(start_frame, (int, np.integer)) and not isinstance(start_frame, bool)
            and -n_frames <= start_frame < n_frames):
        raise ValueError(f"start_frame must be a frame of the sequence's {n_frames} (0 to {n_frames - 1}, or "
                         f"negative from the last), got {start_frame!r}")
    start = int(start_frame) % n_frames
    return list(range(start, n_frames)) + list(range(start - 1, -1, -1))


@contextlib.contextmanager
def _naming_frame(t: int):
    """A frame's error names the frame (one dark frame of sixty)."""
    try:
        yield
    except (ValueError, RuntimeError) as exc:
        if str(exc).startswith("frame "):
            raise
        try:
            named = type(exc)(f"frame {t}: {exc}")
        except Exception:  # an exception class of other arguments
            named = ValueError(f"frame {t}: {exc}")
        raise named from exc
