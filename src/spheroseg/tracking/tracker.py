"""The stepper: a surface model and its region statistics, advanced by
iterations and by frames.

A :class:`Tracker` holds what a segmentation carries from one iteration to
the next and advances by :meth:`~Tracker.iterate` (one iteration, as
scipy's ``OdeSolver.step``) or :meth:`~Tracker.next_frame` (a new frame of a
sequence); :func:`spheroseg.segment` and :func:`spheroseg.track` are short
loops over it, as :func:`scipy.integrate.solve_ivp` loops over its solver.
Its ``status`` is ``None`` while it runs, then says why it stopped.

It is a facade over four parts, one job each: :mod:`spheroseg.initial`
builds the initial model (the points checked, the pose, the start surface),
:class:`spheroseg.stepper.Stepper` runs the levels of the coarse-to-fine
:func:`schedule` on a frame, :mod:`spheroseg.frames` follows the ventricle
from frame to frame, and :class:`spheroseg.quality.FrameQuality` reports
how far a result can be trusted.
"""

from __future__ import annotations

import time
import warnings
from functools import partial

import numpy as np

from .frames import (BASE_RING_MM, base_ring_floor, base_ring_points, followed_base, followed_the_wall, keep_better_start,
                     wall_motion_mm)
from .initial import check_landmarks, check_volume, fitted_start, initial_model
from ..descent.dataterms import nanmedian
from ..descent.options import SegmentOptions
from ..descent.quality import FrameQuality
from ..descent.results import Intermediate, SegmentationResult, STATUS_MESSAGES
from ..descent.stepper import Level, Stepper, schedule
from ..surfaces.surface import Surface

__all__ = ["Tracker", "Level", "schedule", "BASE_RING_MM"]


class Tracker:
    """A segmentation that steps: iteration by iteration, frame by frame.

    Parameters
    ----------
    volume : Volume
        The first (or only) frame: a 3D echo image, blood dark, tissue bright.
    apex, base : (x, y, z)
        World points (mm, ITK physical space): the endocardial apex and the
        centre of the mitral plane.  ``base`` may be None when ``annulus``
        is given.
    annulus : array (k, 3), optional
        ``k >= 3`` world points (mm) of the mitral annulus.  The model is
        then posed by the mitral plane (:meth:`Surface.from_annulus`): the
        cavity is closed at the annulus points' least-squares plane, the
        long axis is its normal and the apex may lie off it; ``base``
        defaults to the points' centroid (a ``base`` given is projected on
        the plane).  Without it the base plane is perpendicular to the
        apex-base line through ``base``.
    landmarks : array (k, 3), optional
        World points of the wall the surface is drawn to (to stop a leak),
        held by ``landmark_weight``; ``quality["landmark_residuals_mm"]``
        gives how far it ends from each (over 2 mm: a warning).
    init : Surface, optional
        Start from this surface instead of the half-ellipsoid (no
        coarse-to-fine then); ``apex``, ``base`` and ``annulus`` are still
        checked.
    levels : sequence of Level, optional
        The schedule (default: :func:`schedule` of the options, without
        coarse-to-fine when ``init`` is given).
    **options
        :class:`spheroseg.SegmentOptions`.

    Attributes
    ----------
    status : int or None
        ``None`` while iterating; then as :attr:`SegmentationResult.status`.
    iteration : int
        Iterations run in the current frame.
    level : int
        Index of the current level in :attr:`levels`.
    motion : float
        RMS motion of the last iteration (mm).
    levels : tuple of Level
        The schedule.
    stepper : spheroseg.stepper.Stepper
        The level state machine of the current frame.

    Examples
    --------
    >>> from spheroseg import Tracker
    >>> from spheroseg.synthetic.phantom import make_phantom
    >>> ph = make_phantom(seed=1, spacing=2.0)
    >>> tracker = Tracker(ph.volume, ph.apex, ph.base)
    >>> while tracker.status is None:
    ...     motion = tracker.iterate()
    >>> result = tracker.result()
    >>> bool(abs(result.volume_ml - ph.truth_volume_ml) < 0.2 * ph.truth_volume_ml)
    True
    """


    def __init__(self, volume, apex, base=None, *, annulus=None, landmarks=None, init: Surface | None = None,
                 levels=None, **options):
        started = time.perf_counter()
        self.options = opts = SegmentOptions(**options)
        if levels is None:
            levels = schedule(opts, coarse_to_fine=opts.coarse_to_fine and init is None)
        model = initial_model(volume, apex, base, annulus=annulus, landmarks=landmarks, init=init, levels=levels,
                              options=opts)
        self.apex, self.base, self.annulus = model.apex, model.base, model.annulus
        # the clicked shape's family, for a smoothing reference fitted to the coarse levels' end
        family = None if init is not None else partial(fitted_start, model.apex, model.base, annulus=model.annulus,
                                                       options=opts)
        self.stepper = Stepper(volume, model.surface, levels=model.levels, options=opts, apex=model.apex,
                               landmarks=model.landmarks, fitted_start=family)
        self._quality = FrameQuality(model.surface, model.apex)
        self.stepper.seconds = time.perf_counter() - started

    # the current state, as the stepper holds it -----------------------------

    @property
    def volume(self):
        """The current frame."""
        return self.stepper.volume

    @volume.setter
    def volume(self, volume) -> None:
        self.stepper.volume = volume

    @property
    def landmarks(self) -> np.ndarray:
        """The user's landmarks (world mm, ``(k, 3)``)."""
        return self.stepper.landmarks

    @property
    def levels(self) -> tuple[Level, ...]:
        return self.stepper.levels

    @property
    def level(self) -> int:
        return self.stepper.level

    @property
    def status(self) -> int | None:
        return self.stepper.status

    @property
    def iteration(self) -> int:
        return self.stepper.iteration

    @property
    def motion(self) -> float:
        return self.stepper.motion

    @property
    def c_in(self):
        """The grey levels inside the wall the last iteration's force kept."""
        return self.stepper.c_in

    @property
    def c_out(self):
        """The grey levels outside the wall the last iteration's force kept."""
        return self.stepper.c_out

    @property
    def surface(self) -> Surface:
        """The current surface."""
        return self.stepper.surface

    @property
    def patches(self) -> tuple[int, int]:
        return self.stepper.patches

    @property
    def message(self) -> str:
        """Why the current frame stopped (empty while running)."""
        return self.stepper.message

    # stepping --------------------------------------------------------------

    def iterate(self) -> float:
        """Run one iteration; at the end of a level, move to the next.

        Returns
        -------
        float
            RMS motion of the surface in the iteration (mm).
        """
        return self.stepper.iterate()

    def run_level(self, max_iterations: int | None = None) -> bool:
        """Run the current level to its end (as :meth:`iterate` until the
        level changes), or at most ``max_iterations`` of it, in one compiled
        loop (:meth:`Descent.run`): the same iterations without their
        Python-level cost.  False, having run nothing, where that loop does
        not apply (see :meth:`Descent.run`)."""
        return self.stepper.run_level(max_iterations)

    def stop(self, status: int = 2) -> None:
        """End the current frame now (``status`` 2: stopped from outside)."""
        self.stepper.stop(status)

    def intermediate(self) -> Intermediate:
        """The state after the last iteration, as ``iter_callback`` gets it."""
        return Intermediate(self.surface, self.iteration, self.level, self.patches, float(self.motion))

    def _iterate_until_stopped(self, iter_callback=None, callback_every: int = 1) -> None:
        while self.status is None:
            if iter_callback is None:
                if not self.run_level():
                    self.iterate()
                continue
            if callback_every == 1 or not self.run_level(callback_every):
                self.iterate()
            try:
                iter_callback(self.intermediate())
            except StopIteration:
                self.stop(2)

    def run(self, iter_callback=None, *, callback_every: int = 1, report: bool = True,
            base_ring: bool = True) -> SegmentationResult:
        """Iterate until the current frame stops; ``iter_callback(intermediate)``
        is called after every iteration and may raise ``StopIteration``.
        With ``callback_every`` k > 1 it is called after every k-th iteration
        and at each level's end, and the iterations between run in the
        compiled loop (:meth:`run_level`): a viewer's stream of intermediate
        surfaces at the speed of a run without one.
        A frame whose base ring came out narrower than :meth:`base_ring_floor`
        runs its finest level again with the ring held open
        (:func:`spheroseg.frames.base_ring_points`); ``base_ring=False``
        skips that check, for a surface that something else keeps open (the
        epicardium, held outside an endocardium whose ring was checked).
        ``report``: as in :meth:`result`."""
        if not (isinstance(callback_every, (int, np.integer)) and callback_every >= 1):
            raise ValueError(f"callback_every must be a positive integer, got {callback_every!r}")
        self._iterate_until_stopped(iter_callback, int(callback_every))
        if base_ring and self.status in (0, 1) and self._widen_base_ring():
            self._iterate_until_stopped(iter_callback, int(callback_every))
        return self.result(report=report)

    def base_ring_floor(self) -> float:
        """The least radius (mm) of the base ring (:func:`spheroseg.frames.base_ring_floor`)."""
        return base_ring_floor(self.annulus)

    def _widen_base_ring(self) -> bool:
        """Hold the base ring open where it is narrower than
        :meth:`base_ring_floor` and continue the finest level; returns
        whether it did."""
        surface = self.surface
        ring = base_ring_points(surface, self.base_ring_floor())
        if ring is None:
            return False
        points, weights = self.stepper.held_points(surface.pose)
        weight = np.full(len(ring), self.options.landmark_weight)
        points = ring if points is None else np.concatenate([points, ring])
        weights = weight if weights is None else np.concatenate([weights, weight])
        self.stepper.resume(points, weights, level=len(self.levels) - 1)
        return True

    # frames ----------------------------------------------------------------

    def next_frame(self, volume, *, max_iterations: int | None = None, iter_callback=None,
                   callback_every: int = 1, follow_base: bool = False) -> SegmentationResult:
        """Segment a new frame, starting from the current surface.

        The finest level continues on ``volume``: same matrices and data
        term (its statistics measured again); the current surface is the
        start and the reference shape of the smoothing prior; at most
        ``max_iterations`` (default: the options') until the surface stops
        moving.  With ``follow_base``, the mitral plane first moves along the
        long axis with the annulus (:func:`spheroseg.frames.followed_base`)
        and the model is posed there.  With ``coarse_to_fine``, a frame
        whose stepped surface did not settle on the wall
        (:func:`spheroseg.frames.followed_the_wall`), or whose wall moved on
        the whole by more than half the local means' band
        (:func:`spheroseg.frames.wall_motion_mm`), is then segmented again
        from afar and the better segmentation kept
        (:func:`spheroseg.frames.keep_better_start`).  ``iter_callback``
        and ``callback_every`` as in :meth:`run`.
        """
        check_volume(volume)
        if max_iterations is not None and not (isinstance(max_iterations, (int, np.integer)) and max_iterations >= 1):
            raise ValueError(f"max_iterations must be a positive integer, got {max_iterations!r}")
        if self.status is None:
            self.run()  # the current frame first
        started = time.perf_counter()
        stepper = self.stepper
        stepper.count_threads()  # the machine's load, at each frame
        if follow_base:
            followed = followed_base(self.surface, self.volume, volume, apex=self.apex, annulus=self.annulus,
                                     options=self.options)
            if followed is not None:
                self.base, self.annulus, fitted = followed
                stepper.restart_from(fitted)
        start = self.surface
        stepper.start_frame(volume, self.options.max_iterations if max_iterations is None else int(max_iterations))
        stepper.seconds = time.perf_counter() - started
        self.run(iter_callback, callback_every=callback_every)
        if self.options.coarse_to_fine and self.status != 2:  # (not when stopped from outside)
            # settled, yet not followed: the wall was left behind; followed where the check looks (the basal
            # wall), yet moved by more than the local means can follow: maybe left behind where it does not
            followed = followed_the_wall(self)
            if not followed or wall_motion_mm(start, self.surface) > self.options.band / 2:
                keep_better_start(self, start, left_behind=not followed and self.status == 0)
        return self.result()

    def step(self, volume, *, max_iterations: int | None = None, iter_callback=None,
             follow_base: bool = False) -> SegmentationResult:
        """Deprecated alias of :meth:`next_frame` (``step`` is one iteration
        in scipy's solvers); it will be removed after 0.2."""
        warnings.warn("Tracker.step(volume) is deprecated: use Tracker.next_frame(volume)", DeprecationWarning,
                      stacklevel=2)
        return self.next_frame(volume, max_iterations=max_iterations, iter_callback=iter_callback,
                               follow_base=follow_base)

    def interface_levels(self) -> tuple[float, float]:
        """Scalar ``(c_in, c_out)`` (grey levels) about the finest level's
        interface: the medians of its fixed levels (the intensity
        interface's), else of the region means last measured."""
        return self.stepper.interface_levels()

    def set_landmarks(self, landmarks) -> None:
        """Replace the user's landmarks (world points ``(k, 3)``) and continue
        the finest level from the current surface (the viewer's edits)."""
        stepper = self.stepper
        stepper.landmarks = check_landmarks(self.volume, landmarks)
        stepper.count_threads()
        stepper.resume(*stepper.held_points(stepper.descent.model.pose),
                       level=len(self.levels) - 1 if self.status is not None else self.level)

    # the result ------------------------------------------------------------

    def result(self, *, report: bool = True) -> SegmentationResult:
        """The current frame's result; its ``quality`` None without
        ``report`` (a caller that judges the surface by its own measures, as
        :func:`spheroseg.epicardium.segment_epicardium` its wall's)."""
        stepper = self.stepper
        c_in, c_out = stepper.start_means if stepper.c_in is None else (stepper.c_in, stepper.c_out)
        parameters = self.options.as_parameters()
        if stepper.frame_cap is not None:
            parameters.update(max_iterations=stepper.frame_cap, coarse_to_fine=False)
        status = 2 if self.status is None else self.status
        surface = self.surface
        quality = None if not report else self._quality.report(
            surface, observed=stepper.last, converged=self.status == 0, landmarks=self.landmarks,
            no_speckle=stepper.no_speckle, beyond_wall=stepper.beyond_wall())
        return SegmentationResult(
            surface=surface, iterations=self.iteration, converged=stepper.converged,
            c_in=float(nanmedian(c_in)), c_out=float(nanmedian(c_out)), seconds=stepper.seconds,
            parameters=parameters, status=status, message=STATUS_MESSAGES[status], quality=quality,
            log_compression=stepper.log_compression())
