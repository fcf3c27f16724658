"""The stepper: a surface model and its region statistics, advanced by
iterations and by frames.

A :class:`Tracker` holds what a segmentation carries from one iteration to
the next and advances by :meth:`~Tracker.iterate` (one iteration, as
scipy's ``OdeSolver.step``) or :meth:`~Tracker.next_frame` (a new frame of a
sequence); :func:`spheroseg.segment` and :func:`spheroseg.track` are short
loops over it, as :func:`scipy.integrate.solve_ivp` loops over its solver.
Its ``status`` is ``None`` while it runs, then says why it stopped.

It is the :class:`~spheroseg.descent.stepper.Stepper` of a frame's levels
(one object: the state and its steps) with what a sequence adds:
:mod:`~spheroseg.tracking.initial` builds the initial model (the points
checked, the pose, the start surface), the tracker decides each new frame
(the stepped surface kept, or the frame segmented again) by the plain
functions of :mod:`~spheroseg.tracking.frames`, and
:class:`~spheroseg.descent.quality.FrameQuality` reports how far a result
can be trusted.
"""

from __future__ import annotations

import time
import warnings
from functools import partial

import numpy as np

from .frames import (BASE_RING_MM, base_ring_floor, base_ring_points, followed_base, kept_candidate, left_behind,
                     wall_motion_mm, wall_offsets, wall_sides)
from .initial import check_landmarks, check_volume, fitted_start, initial_model
from ..descent.dataterms import nanmedian
from ..descent.options import SegmentOptions
from ..descent.quality import FrameQuality
from ..descent.results import Intermediate, SegmentationResult, STATUS_MESSAGES
from ..descent.stepper import Level, Stepper, schedule
from ..geometry.energy import data_energy
from ..surfaces.surface import Surface
from .._moved import MOVED_IN, REMOVED_IN

__all__ = ["Tracker", "Level", "schedule", "BASE_RING_MM"]


class Tracker(Stepper):
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
    surface : Surface
        The current surface; the rest of the state as a
        :class:`~spheroseg.descent.stepper.Stepper`'s.

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
        super().__init__(volume, model.surface, levels=model.levels, options=opts, apex=model.apex,
                         landmarks=model.landmarks, fitted_start=family)
        self._quality = FrameQuality(model.surface, model.apex)
        self.seconds = time.perf_counter() - started

    @property
    def stepper(self) -> Tracker:
        """Deprecated: the tracker is its stepper since 0.2.0."""
        warnings.warn(f"Tracker.stepper is the tracker itself since spheroseg {MOVED_IN}; it goes in {REMOVED_IN}",
                      DeprecationWarning, stacklevel=2)
        return self

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
        points, weights = self.held_points(surface.pose)
        weight = np.full(len(ring), self.options.landmark_weight)
        points = ring if points is None else np.concatenate([points, ring])
        weights = weight if weights is None else np.concatenate([weights, weight])
        self.resume(points, weights, level=len(self.levels) - 1)
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
        (:meth:`followed_the_wall`), or whose wall moved on the whole by
        more than half the local means' band
        (:func:`spheroseg.tracking.frames.wall_motion_mm`), is then
        segmented again from afar and the better segmentation kept
        (:meth:`segment_again`).  ``iter_callback`` and ``callback_every``
        as in :meth:`run`.
        """
        check_volume(volume)
        if max_iterations is not None and not (isinstance(max_iterations, (int, np.integer)) and max_iterations >= 1):
            raise ValueError(f"max_iterations must be a positive integer, got {max_iterations!r}")
        if self.status is None:
            self.run()  # the current frame first
        started = time.perf_counter()
        self.count_threads()  # the machine's load, at each frame
        if follow_base:
            followed = followed_base(self.surface, self.volume, volume, apex=self.apex, annulus=self.annulus,
                                     options=self.options)
            if followed is not None:
                self.base, self.annulus, fitted = followed
                self.restart_from(fitted)
        start = self.surface
        self.start_frame(volume, self.options.max_iterations if max_iterations is None else int(max_iterations))
        self.seconds = time.perf_counter() - started
        self.run(iter_callback, callback_every=callback_every)
        if self.options.coarse_to_fine and self.status != 2:  # (not when stopped from outside)
            # settled, yet not followed: the wall was left behind; followed where the check looks (the basal
            # wall), yet moved by more than the local means can follow: maybe left behind where it does not
            followed = self.followed_the_wall()
            if not followed or wall_motion_mm(start, self.surface) > self.options.band / 2:
                self.segment_again(start, left_behind=not followed and self.status == 0)
        return self.result()

    def followed_the_wall(self) -> bool:
        """Whether the stepped frame settled on the wall: its finest level
        converged, and in every sector of the wall the band just inside the
        surface (half the local means' band, ``options.band / 2`` mm)
        reads as blood and the band just outside as wall, on the
        interface's levels (:func:`~spheroseg.tracking.frames.left_behind`).
        Only where it did not is the frame segmented again
        (:meth:`segment_again`: two more segmentations and their energies).
        """
        if self.status != 0:
            return False
        offsets = wall_offsets(self.options.band / 2)
        model = self.descent.model
        with np.errstate(invalid="ignore", divide="ignore"):  # a sector without image data: NaN, not left behind
            sides = wall_sides(self.samples_along_normals(offsets), offsets, model.v1, model.v2, model.grid.v2_range,
                               self.interface_levels())
        return not left_behind(sides)

    def segment_again(self, start: Surface, *, left_behind: bool = False) -> None:
        """Segment the current frame again through the coarse data term,
        from ``start`` (the frame's start surface) and from the initial
        shape posed at the current apex and base (coarse to fine, smoothed
        on the finest patches towards that shape fitted to the coarse
        levels' volume: ``smoothness_reference="fitted"``), and continue
        from the segmentation :func:`~spheroseg.tracking.frames.kept_candidate`
        keeps by their data energies: the stepped one unless another is
        lower by more than ``RESEGMENT_MARGIN`` of it; where the stepped
        surface ``left_behind`` the wall (:meth:`followed_the_wall`), the
        one of lowest energy among those on the wall.

        A wall that moved between frames by more than the finest levels'
        bands can follow leaves the stepped surface where the local means
        balance on the wrong side of it (a long time step: few frames a
        cycle, or end-diastole to end-systole directly), while the global
        means bring the surface to the walls from afar.  The surfaces share
        the pose and the grid; all are scored by the Chan-Vese data energy
        (paper eq. 14) with the same scalar levels, the mean of the
        segmentations' interface levels: ``int_cavity (u - c_in)^2 - (u -
        c_out)^2 dV``, lowest when the cavity holds every voxel darker than
        the interface and none brighter.
        """
        started = time.perf_counter()
        options = {name: getattr(self.options, name) for name in SegmentOptions.names()}
        place = dict(annulus=self.annulus, landmarks=self.landmarks if len(self.landmarks) else None)
        # the clicked shape's proportions are the first frame's; a frame far from it (an end-systole reached from
        # end-diastole) is smoothed towards the shape holding what the coarse levels found in it
        fresh = Tracker(self.volume, self.apex, self.base, **place, **{**options, "smoothness_reference": "fitted"})
        coarse, finest = schedule(self.options)[0], schedule(self.options, coarse_to_fine=False)
        again_levels = (Level(finest[0].patches, coarse.data_term, coarse.max_iterations, coarse.tol), *finest)
        again = Tracker(self.volume, self.apex, self.base, init=start, levels=again_levels, **place, **options)
        candidates = [self]
        for candidate in (again, fresh):
            candidate.run()
            if candidate.patches == self.patches:
                candidates.append(candidate)
        model = self.descent.model
        levels = np.mean([candidate.interface_levels() for candidate in candidates], axis=0)

        def sample(world):  # no data weighs nothing
            return self.volume.sample(world, fill_value=float(levels.mean()))

        energies = [data_energy(model, model.parameters(candidate.surface.coefficients), sample, *levels)
                    for candidate in candidates]
        on_wall = [k for k, candidate in enumerate(candidates) if k and candidate.followed_the_wall()] \
            if left_behind else []
        kept = kept_candidate(energies, on_wall)
        if kept:
            self.adopt(candidates[kept])
        self.seconds += time.perf_counter() - started

    def step(self, volume, *, max_iterations: int | None = None, iter_callback=None,
             follow_base: bool = False) -> SegmentationResult:
        """Deprecated alias of :meth:`next_frame` (``step`` is one iteration
        in scipy's solvers); it will be removed after 0.2."""
        warnings.warn("Tracker.step(volume) is deprecated: use Tracker.next_frame(volume)", DeprecationWarning,
                      stacklevel=2)
        return self.next_frame(volume, max_iterations=max_iterations, iter_callback=iter_callback,
                               follow_base=follow_base)

    def set_landmarks(self, landmarks) -> None:
        """Replace the user's landmarks (world points ``(k, 3)``) and continue
        the finest level from the current surface (the viewer's edits)."""
        self.landmarks = check_landmarks(self.volume, landmarks)
        self.count_threads()
        self.resume(*self.held_points(self.descent.model.pose),
                    level=len(self.levels) - 1 if self.status is not None else self.level)

    # the result ------------------------------------------------------------

    def result(self, *, report: bool = True) -> SegmentationResult:
        """The current frame's result; its ``quality`` None without
        ``report`` (a caller that judges the surface by its own measures, as
        :func:`spheroseg.epicardium.segment_epicardium` its wall's)."""
        c_in, c_out = self.start_means if self.c_in is None else (self.c_in, self.c_out)
        parameters = self.options.as_parameters()
        if self.frame_cap is not None:
            parameters.update(max_iterations=self.frame_cap, coarse_to_fine=False)
        status = 2 if self.status is None else self.status
        surface = self.surface
        quality = None if not report else self._quality.report(
            surface, observed=self.last, converged=self.status == 0, landmarks=self.landmarks,
            no_speckle=self.no_speckle, beyond_wall=self.beyond_wall())
        return SegmentationResult(
            surface=surface, iterations=self.iteration, converged=self.converged,
            c_in=float(nanmedian(c_in)), c_out=float(nanmedian(c_out)), seconds=self.seconds,
            parameters=parameters, status=status, message=STATUS_MESSAGES[status], quality=quality,
            log_compression=self.log_compression())
