"""The stepper: a surface model and its region statistics, advanced by
iterations and by frames.

A :class:`Tracker` holds what a segmentation carries from one iteration to
the next (the Hermite parameters, the level's matrices, the data term and
its statistics) and advances by :meth:`~Tracker.iterate` (one iteration)
or :meth:`~Tracker.step` (a new frame of a sequence); :func:`spheroseg.segment`
and :func:`spheroseg.track` are short loops over it, as
:func:`scipy.integrate.solve_ivp` loops over ``OdeSolver.step``.  Its
``status`` is ``None`` while it runs, then says why it stopped.

The coarse-to-fine schedule is data (:func:`schedule`): a list of
:class:`Level` (patches, data term, iteration cap).  Each level starts
from the previous one's surface refined exactly (a Hermite surface on
``N`` patches is one on ``2N``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ._runtime import kernel_thread_count, kernel_threads
from .coords import Pose, annulus_plane
from .dataterms import DataTerm, GlobalMeans, IntensityInterface, LocalMeans, NoSpeckleError, band_offsets, nanmedian
from .descent import Descent
from .energy import data_energy
from .options import SegmentOptions, format_point
from .quality import axis_distances, landmark_residuals, quality_report, wall_bulge
from .results import STATUS_MESSAGES, Intermediate, SegmentationResult
from .surface import Surface

__all__ = ["Tracker", "Level", "schedule", "BASE_RING_MM"]

#: plausible radii of the mitral annulus in adults, mm (the base ring's range)
BASE_RING_MM = (10.0, 20.0)
#: a frame segmented again replaces the stepped one when its data energy is
#: lower by more than this fraction of the stepped one's: below it the
#: candidates differ by the descent's own noise (0.0001-0.3 % on phantom
#: cycles of 4-20 frames), a stepped wall left behind by 3 % and more
RESEGMENT_MARGIN = 0.01


@dataclass(frozen=True)
class Level:
    """One level of the coarse-to-fine schedule: it stops when the RMS
    motion of an iteration falls below ``tol`` mm, or after
    ``max_iterations``."""

    patches: tuple[int, int]
    data_term: type[DataTerm]
    max_iterations: int
    tol: float


def schedule(options: SegmentOptions, *, coarse_to_fine: bool | None = None) -> list[Level]:
    """The levels of a segmentation: ``options.patches`` halved while both
    stay even and at least 2 (coarse to fine, unless disabled), each capped
    at ``options.max_iterations``.  The local data terms run on the finest
    patches only; the coarser ones use the global means, which bring the
    surface to the walls from afar, and stop at ``options.coarse_tol``
    (default twice ``tol``).  :class:`IntensityInterface` runs after
    :class:`LocalMeans` on the finest patches (it measures its statistics
    where the local means put the wall)."""
    coarse_to_fine = options.coarse_to_fine if coarse_to_fine is None else coarse_to_fine
    patches = [tuple(options.patches)]
    while coarse_to_fine and min(patches[0]) >= 4 and patches[0][0] % 2 == 0 and patches[0][1] % 2 == 0:
        patches.insert(0, (patches[0][0] // 2, patches[0][1] // 2))
    term = options.data_term
    coarse = GlobalMeans if issubclass(term, LocalMeans) else term
    finest = len(patches) - 1
    coarse_tol = 2.0 * options.tol if options.coarse_tol is None else options.coarse_tol
    levels = [Level(p, term if k == finest else coarse, options.max_iterations,
                    options.tol if k == finest else coarse_tol)
              for k, p in enumerate(patches)]
    if term is IntensityInterface:  # found by the local means first, then moved to the interface
        levels.insert(-1, Level(levels[-1].patches, LocalMeans, options.max_iterations, options.tol))
    return levels


def _check_volume(volume) -> None:
    if not (callable(getattr(volume, "sample", None)) and hasattr(volume, "contains") and hasattr(volume, "grid")):
        raise TypeError(f"volume must be a spheroseg.Volume, got {type(volume).__name__}")


def _check_point(volume, point, name: str) -> np.ndarray:
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


def _check_annulus(volume, annulus) -> np.ndarray:
    annulus_plane(annulus)  # its points' form: (k >= 3, 3), finite, not on a line
    points = np.asarray(annulus, dtype=float)
    for k, point in enumerate(points):
        _check_point(volume, point, f"annulus point {k}")
    return points


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

    Examples
    --------
    >>> from spheroseg import Tracker
    >>> from spheroseg.phantom import make_phantom
    >>> ph = make_phantom(seed=1, spacing=2.0)
    >>> tracker = Tracker(ph.volume, ph.apex, ph.base)
    >>> while tracker.status is None:
    ...     motion = tracker.iterate()
    >>> result = tracker.result()
    >>> bool(abs(result.volume_ml - ph.truth_volume_ml) < 0.2 * ph.truth_volume_ml)
    True
    """

    def __init__(self, volume, apex, base=None, *, annulus=None, landmarks=None, init: Surface | None = None,
                 **options):
        started = time.perf_counter()
        self.options = opts = SegmentOptions(**options)
        _check_volume(volume)
        self.apex = _check_point(volume, apex, "apex")
        self.annulus = None if annulus is None else _check_annulus(volume, annulus)
        if base is None and self.annulus is None:
            raise ValueError("give the base point (the centre of the mitral plane) or the annulus "
                             "(3 or more points of the mitral ring)")
        given_base = None if base is None else _check_point(volume, base, "base")
        if self.annulus is None:
            self.base = given_base
            if np.linalg.norm(self.apex - self.base) < 1e-6:
                raise ValueError("apex and base must be distinct points")
        else:
            self.base = Pose.from_annulus(self.apex, self.annulus, base=given_base).origin
        if init is not None and not isinstance(init, Surface):
            raise TypeError(f"init must be a spheroseg.Surface, got {type(init).__name__}")
        self.volume = volume
        self.landmarks = self._check_landmarks(landmarks)
        self.levels = schedule(opts, coarse_to_fine=opts.coarse_to_fine and init is None)
        if init is None and self.annulus is not None:
            surface = Surface.from_annulus(self.apex, self.annulus, base=given_base, system=opts.system,
                                           patches=self.levels[0].patches, radius_ratio=opts.radius_ratio)
        elif init is None:
            surface = Surface.from_apex_base(self.apex, self.base, system=opts.system, patches=self.levels[0].patches,
                                             radius_ratio=opts.radius_ratio)
        else:
            surface = init
        self.level = 0
        self._descent = self._new_descent(surface, surface)
        self._threads = kernel_thread_count(opts.threads)
        with kernel_threads(self._threads):
            self._terms = self._prepare_terms()
            self._band_fields = None  # the band means the last local-means level measured
        self.iteration, self.motion, self.status = 0, np.nan, None
        self._level_iterations = 0
        self._converged = False
        self._initial_volume = surface.volume_ml()
        self._initial = surface  # the quality report's reference shape
        self._bulge_reference = None
        self._no_speckle = False  # this frame fell back to the local means' wall
        self._seconds = time.perf_counter() - started
        self._skip_empty_levels()

    # construction ----------------------------------------------------------

    def _check_landmarks(self, landmarks) -> np.ndarray:
        if landmarks is None:
            return np.empty((0, 3))
        try:
            points = np.asarray(landmarks, dtype=float).reshape(-1, 3)
        except (TypeError, ValueError):
            raise ValueError(f"landmarks must be points (x, y, z in mm), got {landmarks!r}") from None
        for k, point in enumerate(points):
            _check_point(self.volume, point, f"landmark {k}")
        return points

    def _held_points(self, pose):
        """The landmarks on the cavity's side of ``pose``'s base plane (a
        followed annulus can leave one beyond it) and, when it has a weight,
        the clicked apex: a point of the endocardium the user gave
        (near-field clutter would otherwise push it down)."""
        opts = self.options
        points, weights = self.landmarks, np.full(len(self.landmarks), opts.landmark_weight)
        if len(points):
            inside = pose.to_local(points)[:, 0] >= 0
            points, weights = points[inside], weights[inside]
        if opts.apex_weight > 0:
            points = np.concatenate([points, self.apex[None]])
            weights = np.concatenate([weights, [opts.apex_weight]])
        return (points, weights) if len(points) else (None, None)

    def _new_descent(self, surface: Surface, reference: Surface) -> Descent:
        patches = self.levels[self.level].patches
        while (surface.grid.n1, surface.grid.n2) != patches:
            if surface.grid.n1 >= patches[0] or surface.grid.n2 >= patches[1]:
                raise ValueError(f"the start surface has {surface.grid.n1} x {surface.grid.n2} patches: it must be "
                                 f"{patches[0]} x {patches[1]} or refine to it")
            surface, reference = surface.refine(), reference.refine()
        self._reference = reference
        points, weights = self._held_points(surface.pose)
        opts = self.options
        return Descent(surface, reference, order=opts.order, step=self._stage_step(), smoothness=opts.smoothness,
                       nu=opts.nu, landmarks=points, landmark_weights=weights, backend=opts.backend,
                       adaptive_step=opts.adaptive_step)

    def _stage_step(self, *, settled: bool = True) -> float:
        """The step (mm) of the current level: the option's, times its data
        term's ``step_factor`` when the stage starts where the previous one
        ``settled`` (a stage that hit its cap left the surface moving: a
        larger step would carry that motion further)."""
        return self.options.step * (self.levels[self.level].data_term.step_factor if settled else 1.0)

    def _prepare_terms(self) -> dict:
        """The data terms of the schedule, from the grey levels around the
        initial surface: a check that there is something to segment, the
        scale of the contrast, the fast mode's levels."""
        d, opts = self._descent, self.options
        obs = d.backend.observe(d.p, self.volume)
        probe = GlobalMeans(np.zeros(1), band=opts.band, band_out=opts.band_out)
        self._start_means = probe.global_means(d.backend, self.volume, obs)
        # the inner band's samples, then the shell's (one call: a sampling costs 50 us before its first point)
        inner = band_offsets(opts.band)
        along = d.backend.samples_along(self.volume, obs, np.concatenate([-inner, probe.shell_offsets]),
                                        d.discretisation.band_rows)
        samples = np.concatenate([along[:, :len(inner)].ravel(), along[:, len(inner):].ravel()])
        samples = samples[np.isfinite(samples)]
        if samples.size < 10 or np.ptp(samples) <= 1e-6 * max(np.abs(samples).max(), 1.0):
            raise ValueError("the image is constant (or empty) around the initial surface: nothing to segment")
        terms = {}
        # and the coarse levels' term, for a frame segmented again from it (_keep_better_start)
        for level in self.levels + schedule(self.options)[:1]:
            if level.data_term not in terms:
                terms[level.data_term] = level.data_term(samples, band=opts.band, band_out=opts.band_out,
                                                         interface=opts.interface)
        return terms

    # stepping --------------------------------------------------------------

    @property
    def surface(self) -> Surface:
        """The current surface."""
        return self._descent.surface

    @property
    def patches(self) -> tuple[int, int]:
        return self.levels[self.level].patches

    def iterate(self) -> float:
        """Run one iteration; at the end of a level, move to the next.

        Returns
        -------
        float
            RMS motion of the surface in the iteration (mm).
        """
        if self.status is not None:
            raise RuntimeError(f"the tracker has stopped ({self.message}); step(volume) starts a new frame")
        started = time.perf_counter()
        term = self._terms[self.levels[self.level].data_term]
        with kernel_threads(self._threads):
            obs = self._descent.observe(self.volume, term)
            force = term.force(self._descent.backend, self.volume, obs)
            motion = self._descent.iterate(obs, force)
        self._advance(term, obs, force, motion, 1)
        self._seconds += time.perf_counter() - started
        return self.motion

    def run_level(self) -> bool:
        """Run the current level to its end (as :meth:`iterate` until the
        level changes) in one compiled loop (:meth:`Descent.run`): the
        same iterations without their Python-level cost.  False, having run
        nothing, where that loop does not apply (see :meth:`Descent.run`)."""
        if self.status is not None:
            raise RuntimeError(f"the tracker has stopped ({self.message}); step(volume) starts a new frame")
        started = time.perf_counter()
        level = self.levels[self.level]
        term = self._terms[level.data_term]
        with kernel_threads(self._threads):
            run = self._descent.run(self.volume, term, tol=level.tol,
                                    max_iterations=level.max_iterations - self._level_iterations)
        if run is None:
            return False
        self._advance(term, run.observation, run.force, run.motion, run.iterations)
        self._seconds += time.perf_counter() - started
        return True

    def _advance(self, term, obs, force, motion: float, iterations: int) -> None:
        """Keep what ``iterations`` (the last of which observed ``obs``
        and moved by ``motion``) leave for a result, and end the level when
        its last one converged or the level reached its cap."""
        self.c_in, self.c_out = force.grey_means
        if term.hands_over_bands:
            self._band_fields = force.measured  # what the next stage may start from
        self._last = (obs.u, force, term.spread)  # for the quality report, read when a result is made
        self._observation = obs  # valid until the next observation (a stage's hand-over reads it)
        self.motion = motion
        self.iteration += iterations
        self._level_iterations += iterations
        if self.motion < self.levels[self.level].tol:
            self._end_level(converged=True)
        elif self._level_iterations >= self.levels[self.level].max_iterations:
            self._end_level(converged=False)

    def _end_level(self, *, converged: bool) -> None:
        self._converged = converged
        if self.level + 1 < len(self.levels):
            self.level += 1
            self._level_iterations = 0
            self._start_term()
            if self.levels[self.level].patches == self.levels[self.level - 1].patches:
                try:
                    self._hand_over()
                except NoSpeckleError:  # nothing to undo the log compression with: the local means' wall stands
                    self.level -= 1
                    self._no_speckle = True
                    self.status = 0 if converged else 1
                    return
                # the intensity stage: same grid, same landmarks
                self._descent.restart(self._stage_step(settled=converged))
            else:
                self._descent = self._new_descent(self._descent.surface, self._reference)
            self._skip_empty_levels()
        else:
            self.status = 0 if converged else 1

    def _start_term(self) -> None:
        """The current level's data term forgets what it measured before
        (a new level or frame), and so do the band means it hands over."""
        term = self._terms[self.levels[self.level].data_term]
        term.reset()
        if term.hands_over_bands:
            self._band_fields = None

    def _hand_over(self) -> None:
        """The intensity interface starts from the local means' last band
        means, about the wall where they stopped (when they ran in this frame)."""
        term = self._terms[self.levels[self.level].data_term]
        if self._band_fields is not None and term.starts_from_bands:
            with kernel_threads(self._threads):
                term.freeze(self._descent.backend, self.volume, self._observation, *self._band_fields)

    def _skip_empty_levels(self) -> None:
        if self.status is None and self.levels[self.level].max_iterations == 0:
            self._end_level(converged=False)

    def stop(self, status: int = 2) -> None:
        """End the current frame now (``status`` 2: stopped from outside)."""
        self.status = status
        self._converged = False

    @property
    def message(self) -> str:
        """Why the current frame stopped (empty while running)."""
        return "" if self.status is None else STATUS_MESSAGES[self.status]

    def intermediate(self) -> Intermediate:
        """The state after the last iteration, as ``iter_callback`` gets it."""
        return Intermediate(self.surface, self.iteration, self.level, self.patches, float(self.motion))

    def run(self, iter_callback=None) -> SegmentationResult:
        """Iterate until the current frame stops; ``iter_callback(intermediate)``
        is called after every iteration and may raise ``StopIteration``.
        A frame whose base ring came out narrower than an annulus runs its
        finest level again with the ring held open (:meth:`_widen_base_ring`)."""
        self._iterate_until_stopped(iter_callback)
        if self.status in (0, 1) and self._widen_base_ring():
            self._iterate_until_stopped(iter_callback)
        return self.result()

    def base_ring_floor(self) -> float:
        """The least radius (mm) of the base ring: :data:`BASE_RING_MM`'s
        lower end, or with a clicked annulus three quarters of its points'
        mean distance from their centre."""
        if self.annulus is None:
            return BASE_RING_MM[0]
        return 0.75 * float(np.mean(np.linalg.norm(self.annulus - self.annulus.mean(axis=0), axis=1)))

    def _widen_base_ring(self, n: int = 32) -> bool:
        """Hold the base ring open where it is narrower than
        :meth:`base_ring_floor`: landmarks on the base plane at that radius,
        at the angles where it is narrower, then the finest level runs again.

        The mitral annulus is a ring (10-20 mm in radius in adults); in low
        contrast at the base nothing stops the smoothing prior and the bright
        mitral apparatus from closing the cavity into a cusp about the base
        point.  Returns whether it held it (the frame then continues)."""
        surface = self.surface
        floor = self.base_ring_floor()
        narrow = surface.base_radii(n) < floor
        if not narrow.any():
            return False
        v1 = np.linspace(0, 2 * np.pi, n, endpoint=False)[narrow]
        direction = surface.system.to_cartesian(np.ones_like(v1), v1, np.full_like(v1, surface.base_v2))
        direction[:, 0] = 0.0  # in the base plane, away from the axis
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        ring = surface.pose.to_world(floor * direction)
        points, weights = self._held_points(surface.pose)
        weight = np.full(len(ring), self.options.landmark_weight)
        points = ring if points is None else np.concatenate([points, ring])
        weights = weight if weights is None else np.concatenate([weights, weight])
        self._descent.set_landmarks(points, weights)
        self.level = len(self.levels) - 1
        self._descent.reset_step(self._stage_step())
        self._level_iterations, self.status = 0, None
        return True

    def _iterate_until_stopped(self, iter_callback=None) -> None:
        while self.status is None:
            if iter_callback is None and self.run_level():
                continue
            self.iterate()
            if iter_callback is not None:
                try:
                    iter_callback(self.intermediate())
                except StopIteration:
                    self.stop(2)

    def step(self, volume, *, max_iterations: int | None = None, iter_callback=None,
             follow_base: bool = False) -> SegmentationResult:
        """Segment a new frame, starting from the current surface.

        The finest level continues on ``volume``: same matrices and data
        term (its statistics measured again); the current surface is the
        start and the reference shape of the smoothing prior; at most
        ``max_iterations`` (default: the options') until the surface stops
        moving.  With ``follow_base``, the mitral plane first moves along the
        long axis with the annulus (:func:`spheroseg.annulus.annulus_shift`)
        and the model is posed there.
        """
        _check_volume(volume)
        if max_iterations is not None and not (isinstance(max_iterations, (int, np.integer)) and max_iterations >= 1):
            raise ValueError(f"max_iterations must be a positive integer, got {max_iterations!r}")
        if self.status is None:
            self.run()  # the current frame first
        started = time.perf_counter()
        self._threads = kernel_thread_count(self.options.threads)  # the machine's load, at each frame
        if follow_base:
            self._follow_base(volume)
        surface = self.surface
        cap = self.options.max_iterations if max_iterations is None else int(max_iterations)
        # the levels on the finest patches run again (for the intensity mode:
        # the local means, then the interface measured where they end)
        finest = [k for k, level in enumerate(self.levels) if level.patches == self.levels[-1].patches]
        for k in finest:
            self.levels[k] = Level(self.levels[k].patches, self.levels[k].data_term, cap, self.levels[k].tol)
        self.volume = volume
        self._reference = surface
        if self.level != finest[0]:
            same_grid = self.patches == self.levels[finest[0]].patches
            self.level = finest[0]
            if same_grid:  # as a new descent on this grid and pose
                self._descent.restart(self._stage_step())
                self._descent.set_reference(surface)
            else:  # stopped on a coarser level
                self._descent = self._new_descent(surface, surface)
        else:
            self._descent.set_surface(surface)
            self._descent.set_reference(surface)
            self._descent.reset_step(self._stage_step())
        self._start_term()
        self.iteration, self._level_iterations, self.status, self._converged = 0, 0, None, False
        self._no_speckle = False
        self._seconds = time.perf_counter() - started
        self._frame_options = {"max_iterations": cap, "coarse_to_fine": False}
        self.run(iter_callback)
        if self.options.coarse_to_fine and self.status != 2:  # not when stopped from outside
            self._keep_better_start(surface)
        return self.result()

    def _keep_better_start(self, start: Surface) -> None:
        """Segment the current frame again through the coarse data term, from
        ``start`` (the frame's start surface) and from the initial shape
        posed at the current apex and base (coarse to fine), and keep the
        segmentation of the lowest data energy (the stepped one unless
        another is lower by more than :data:`RESEGMENT_MARGIN` of it).

        A wall that moved between frames by more than the finest levels'
        bands can follow leaves the stepped surface where the local means
        balance on the wrong side of it (a long time step: few frames a
        cycle, or end-diastole to end-systole directly), while the global
        means bring the surface to the walls from afar.  The surfaces share
        the pose and the grid; all are scored by the Chan-Vese data energy
        (paper eq. 14) with the same scalar levels, the mean of the
        segmentations' interface levels: ``int_cavity (u - c_in)^2 -
        (u - c_out)^2 dV``, lowest when the cavity holds every voxel darker
        than the interface and none brighter.
        """
        started = time.perf_counter()
        options = {name: getattr(self.options, name) for name in SegmentOptions.names()}
        place = dict(annulus=self.annulus, landmarks=self.landmarks if len(self.landmarks) else None)
        fresh = Tracker(self.volume, self.apex, self.base, **place, **options)
        again = Tracker(self.volume, self.apex, self.base, init=start, **place, **options)
        coarse = schedule(self.options)[0]
        again.levels.insert(0, Level(again.patches, coarse.data_term, coarse.max_iterations, coarse.tol))
        candidates = [self]
        for tracker in (again, fresh):
            tracker.run()
            if tracker.patches == self.patches:
                candidates.append(tracker)
        model = self._descent.model
        levels = np.mean([tracker.interface_levels() for tracker in candidates], axis=0)

        def sample(world):  # no data weighs nothing
            return self.volume.sample(world, fill_value=float(levels.mean()))

        energies = [data_energy(model, model.parameters(tracker.surface.coefficients), sample, *levels)
                    for tracker in candidates]
        best = candidates[int(np.argmin(energies))]
        if energies[0] - min(energies) > RESEGMENT_MARGIN * abs(energies[0]):
            kept = ("_descent", "_terms", "_band_fields", "_reference", "c_in", "c_out", "_last", "_observation",
                    "motion", "_converged", "status")
            self.__dict__.update({name: best.__dict__[name] for name in kept if name in best.__dict__})
            self.level = len(self.levels) - 1  # every candidate ended on its finest level
            self.iteration += best.iteration
        self._seconds += time.perf_counter() - started

    def interface_levels(self) -> tuple[float, float]:
        """Scalar ``(c_in, c_out)`` (grey levels) about the finest level's
        interface: the medians of its fixed levels (the intensity
        interface's), else of the region means last measured."""
        term = self._terms[self.levels[-1].data_term]
        if term.loop_kind == "fixed":
            fixed = term.fixed_force()
            c_in, c_out = fixed.c_in, fixed.c_out
        else:
            c_in, c_out = self.c_in, self.c_out
        return float(nanmedian(c_in)), float(nanmedian(c_out))

    def _follow_base(self, volume) -> None:
        """Move the base plane with the annulus from the current frame to
        ``volume``, and pose the model there: the plane keeps its
        orientation, the apex stays; the current surface is fitted in the
        new model (its points, extended a little beyond the old plane)."""
        from .annulus import annulus_shift
        from .fit import fit_surface

        surface = self.surface
        pose, grid = surface.pose, surface.grid
        axis = pose.rotation[:, 0]  # from the base towards the apex
        lo, hi = grid.v2_range
        v1 = np.linspace(0, 2 * np.pi, 64, endpoint=False)
        ring = surface.points(v1, np.full_like(v1, hi))
        radius = float(np.mean(np.linalg.norm(ring - pose.origin, axis=1)))
        shift = annulus_shift(self.volume, volume, pose.origin, axis, radius)
        if abs(shift) < 0.1:
            return
        opts, patches = self.options, (grid.n1, grid.n2)
        self.base = pose.origin + shift * axis
        if self.annulus is not None:
            self.annulus = self.annulus + shift * axis
            start = Surface.from_annulus(self.apex, self.annulus, base=self.base, system=opts.system,
                                         patches=patches, radius_ratio=opts.radius_ratio)
        else:
            start = Surface.from_apex_base(self.apex, self.base, system=opts.system, patches=patches,
                                           radius_ratio=opts.radius_ratio)
        # the old surface, extrapolated a little past its plane (diastole
        # moves the plane away from the apex, where it had no points)
        v1, v2 = np.meshgrid(np.linspace(0, 2 * np.pi, 96, endpoint=False), np.linspace(lo, hi + 0.25 * (hi - lo), 48))
        fitted = fit_surface(surface.points(v1.ravel(), v2.ravel()), system=start.system, pose=start.pose,
                             patches=patches, v2_range=start.grid.v2_range, smoothness=1e-5)
        self._descent = self._new_descent(fitted, fitted)

    def set_landmarks(self, landmarks) -> None:
        """Replace the user's landmarks (world points ``(k, 3)``) and continue
        the finest level from the current surface (the viewer's edits)."""
        points = self._check_landmarks(landmarks)
        self.landmarks = points
        self._descent.set_landmarks(*self._held_points(self._descent.model.pose))
        self.level = len(self.levels) - 1 if self.status is not None else self.level
        self._descent.reset_step(self._stage_step())
        self._threads = kernel_thread_count(self.options.threads)
        self._level_iterations, self.status = 0, None

    def result(self) -> SegmentationResult:
        """The current frame's result."""
        c_in, c_out = getattr(self, "c_in", self._start_means[0]), getattr(self, "c_out", self._start_means[1])
        parameters = {**self.options.as_parameters(), **getattr(self, "_frame_options", {})}
        status = 2 if self.status is None else self.status
        surface = self.surface
        return SegmentationResult(
            surface=surface, iterations=self.iteration, converged=self._converged,
            c_in=float(nanmedian(c_in)), c_out=float(nanmedian(c_out)), seconds=self._seconds,
            parameters=parameters, status=status, message=STATUS_MESSAGES[status], quality=self._quality(surface))

    def _quality(self, surface: Surface) -> dict:
        if hasattr(self, "_last"):
            u, force, spread = self._last
            no_data, contrast = float(np.mean(~np.isfinite(u))), np.asarray(force.c_out - force.c_in, float)
        else:
            no_data, contrast, spread = np.nan, np.full(1, np.nan), np.nan
        if self._bulge_reference is None:  # the initial surface's: once for every frame
            self._bulge_reference = axis_distances(self._initial, self._initial)
        with np.errstate(invalid="ignore", divide="ignore"):
            report = quality_report(
                contrast=float(nanmedian(contrast) / spread), no_data_fraction=no_data,
                low_contrast_fraction=float(np.mean(np.broadcast_to(contrast, (1,) + np.shape(contrast)) < 0.1 * spread)),
                converged=self.status == 0, apex_shift_mm=float(np.linalg.norm(surface.tip() - self.apex)),
                volume_ratio=surface.volume_ml() / self._initial_volume,
                bulge=wall_bulge(surface, self._initial, reference=self._bulge_reference),
                landmark_residuals_mm=landmark_residuals(surface, self.landmarks))
        if self._no_speckle:
            report["warnings"].append("no speckle around the surface to undo the log compression with (a noise-free "
                                      "or smoothed image?): the wall is the local means' (mode='local')")
            report["poor"] = True
        return report
