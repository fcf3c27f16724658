"""The level state machine: one frame's descent through the coarse-to-fine
schedule.

The schedule is data (:func:`schedule`): a tuple of :class:`Level`
(patches, data term, iteration cap, tolerance).  A :class:`Stepper` runs it
on one frame: each level starts from the previous one's surface refined
exactly (a Hermite surface on ``N`` patches is one on ``2N``), or on the
same grid hands the data term's band means over to the next stage.  It
keeps what a result reports (the region means, the last observation) and
the kernels' thread count the machine's load leaves it.  It knows nothing of
how the model was built nor of the frames before; :class:`spheroseg.Tracker`
puts those parts together.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, fields, replace

import numpy as np

from .._compiled._runtime import kernel_thread_count, kernel_threads
from .dataterms import (DataTerm, FreezeSamples, GlobalMeans, IntensityInterface, LocalMeans, NoSpeckleError,
                        band_offsets, nanmedian, patch_of_rows, shell_offsets)
from .descent import Descent
from .options import SegmentOptions
from .._moved import MOVED_IN, REMOVED_IN
from .results import STATUS_MESSAGES
from ..surfaces.surface import Surface

__all__ = ["Level", "schedule", "Stepper", "held_points", "freeze_samples"]


@dataclass(frozen=True)
class Level:
    """One level of the coarse-to-fine schedule: it stops when the RMS
    motion of an iteration falls below ``tol`` mm, or after
    ``max_iterations``; ``data_term`` is a
    :class:`~spheroseg.descent.dataterms.DataTerm` object."""

    patches: tuple[int, int]
    data_term: DataTerm
    max_iterations: int
    tol: float

    def __post_init__(self):
        if isinstance(self.data_term, type) and issubclass(self.data_term, DataTerm):  # 0.1 took the class
            warnings.warn(f"Level takes a DataTerm object since spheroseg {MOVED_IN}: pass "
                          f"{self.data_term.__name__}(), not the class (which it takes until {REMOVED_IN})",
                          DeprecationWarning, stacklevel=3)
            object.__setattr__(self, "data_term", self.data_term())


def schedule(options: SegmentOptions, *, coarse_to_fine: bool | None = None) -> tuple[Level, ...]:
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
    coarse = GlobalMeans() if isinstance(term, LocalMeans) else term
    finest = len(patches) - 1
    coarse_tol = 2.0 * options.tol if options.coarse_tol is None else options.coarse_tol
    levels = [Level(p, term if k == finest else coarse, options.max_iterations,
                    options.tol if k == finest else coarse_tol)
              for k, p in enumerate(patches)]
    if isinstance(term, IntensityInterface):  # found by the local means first, then moved to the interface
        levels.insert(-1, Level(levels[-1].patches, LocalMeans(), options.max_iterations, options.tol))
    return tuple(levels)


def held_points(pose, landmarks: np.ndarray, apex: np.ndarray, options: SegmentOptions):
    """The points the descent holds the surface through, with their weights:
    the landmarks on the cavity's side of ``pose``'s base plane (a followed
    annulus can leave one beyond it) and, when it has a weight, the clicked
    apex, a point of the endocardium the user gave (near-field clutter would
    otherwise push it down).  ``(None, None)`` when there are none."""
    points, weights = landmarks, np.full(len(landmarks), options.landmark_weight)
    if len(points):
        inside = pose.to_local(points)[:, 0] >= 0
        points, weights = points[inside], weights[inside]
    if options.apex_weight > 0:
        points = np.concatenate([points, apex[None]])
        weights = np.concatenate([weights, [options.apex_weight]])
    return (points, weights) if len(points) else (None, None)


def freeze_samples(backend, volume, obs, reads: dict) -> FreezeSamples:
    """What a data term's :meth:`~spheroseg.descent.dataterms.DataTerm.freeze`
    reads about the surface of ``obs`` (``reads``: its ``freeze_reads``):
    the outer band's median profile at its ``offsets`` and those
    ``beyond`` it, and where its ``estimates`` are still to be made, the
    band's grey levels at voxel centres with their patches, and those of
    the next voxel along each image axis (none in beam space)."""
    d = backend.discretisation
    rows = d.band_rows

    def medians(offsets):  # the outer band's median grey level at each offset
        outer = backend.samples_along(volume, obs, offsets, rows)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # an offset off the data everywhere: NaN
            return np.nanmedian(outer, axis=0)

    offsets = reads["offsets"]
    profile, beyond = medians(offsets), medians(reads["beyond"])
    if not reads["estimates"]:
        return FreezeSamples(profile, beyond)
    outer = backend.samples_along(volume, obs, offsets, rows, order=0)  # (rows, offsets), at voxel centres
    patch = patch_of_rows(d.grid, d.order, rows)
    if not hasattr(volume, "direction"):  # beam space: axes of angles
        return FreezeSamples(profile, beyond, outer, patch)
    direction = np.asarray(volume.direction, float)
    spacing = np.asarray(volume.spacing, float)
    steps = direction * spacing  # columns: one voxel
    neighbours = np.stack([backend.samples_along(volume, replace(obs, world=obs.world + step[:, None]), offsets, rows,
                                                 order=0) for step in steps.T])
    return FreezeSamples(profile, beyond, outer, patch, neighbours, spacing, direction)


class Stepper:
    """A frame's descent through the levels of a schedule.

    Parameters
    ----------
    volume : Volume
        The frame.
    surface : Surface
        The start, on the first level's patches or refining to them; also
        the first reference shape of the smoothing prior.
    levels : sequence of Level
        The schedule.
    options : SegmentOptions
    apex : array (3,)
        The clicked apex (world mm), held with ``options.apex_weight``.
    landmarks : array (k, 3)
        The user's landmarks (world mm), held with ``options.landmark_weight``.
    fitted_start : callable, optional
        ``fitted_start(volume_ml, patches=...)``: the start's shape holding
        that volume, or None (:func:`spheroseg.initial.fitted_start`); the
        finest patches' reference under ``smoothness_reference="fitted"``.
        Not given (a start that is not the clicked shape): the start.

    Attributes
    ----------
    level : int
        Index of the current level in :attr:`levels`.
    status : int or None
        ``None`` while iterating; then as :attr:`SegmentationResult.status`.
    iteration, level_iterations : int
        Iterations run in the frame, and in the current level.
    motion : float
        RMS motion of the last iteration (mm).
    frame_cap : int or None
        The iteration cap of the finest levels on a frame after the first
        (:meth:`start_frame`); None on the first.
    c_in, c_out : array or None
        The grey levels the last iteration's force kept (None before one).
    seconds : float
        The time spent on the frame.
    """

    def __init__(self, volume, surface: Surface, *, levels, options: SegmentOptions, apex: np.ndarray,
                 landmarks: np.ndarray, fitted_start: Callable[..., Surface | None] | None = None):
        started = time.perf_counter()
        self.volume, self.options, self.levels = volume, options, tuple(levels)
        self.fitted_start = fitted_start
        self.apex, self.landmarks = apex, landmarks
        self.level, self.frame_cap = 0, None
        self.descent = self.new_descent(surface, surface)
        self.threads = kernel_thread_count(options.threads)
        with kernel_threads(self.threads):
            self.states = self._start_terms()
        self.band_fields = None  # the band means the last local-means level measured
        self.iteration, self.level_iterations, self.motion, self.status = 0, 0, np.nan, None
        self.converged = False
        self.no_speckle = False  # this frame fell back to the local means' wall
        self.c_in = self.c_out = None
        self.last = None  # (u, force, spread) of the last iteration, for the quality report
        self.observation = None  # valid until the next observation (a stage's hand-over reads it)
        self.seconds = time.perf_counter() - started
        self._skip_empty_levels()

    # construction ----------------------------------------------------------

    def held_points(self, pose):
        """:func:`held_points` of this stepper's landmarks and apex."""
        return held_points(pose, self.landmarks, self.apex, self.options)

    def new_descent(self, surface: Surface, reference: Surface) -> Descent:
        """A descent on the current level's patches from ``surface``, pulled
        towards ``reference`` (both refined to the level's grid)."""
        patches = self.levels[self.level].patches
        while (surface.grid.n1, surface.grid.n2) != patches:
            if surface.grid.n1 >= patches[0] or surface.grid.n2 >= patches[1]:
                raise ValueError(f"the start surface has {surface.grid.n1} x {surface.grid.n2} patches: it must be "
                                 f"{patches[0]} x {patches[1]} or refine to it")
            surface, reference = surface.refine(), reference.refine()
        self.reference = reference
        points, weights = self.held_points(surface.pose)
        opts = self.options
        return Descent(surface, reference, order=opts.order, step=self.stage_step(), smoothness=opts.smoothness,
                       nu=opts.nu, landmarks=points, landmark_weights=weights, backend=opts.backend,
                       adaptive_step=opts.adaptive_step)

    def stage_step(self, *, settled: bool = True) -> float:
        """The step (mm) of the current level: the option's, times its data
        term's ``step_factor`` when the stage starts where the previous one
        ``settled`` (a stage that hit its cap left the surface moving: a
        larger step would carry that motion further)."""
        return self.options.step * (self.levels[self.level].data_term.step_factor if settled else 1.0)

    def _start_terms(self) -> dict:
        """The states of the schedule's data terms (``{term: TermState}``),
        from the grey levels around the initial surface: a check that there
        is something to segment, the scale of the contrast, the fast mode's
        levels."""
        d, opts = self.descent, self.options
        obs = d.backend.observe(d.p, self.volume)
        shell = shell_offsets(opts.band_out)
        # its region means, should a result need them: the compiled backend's
        # next observation writes over its arrays
        start = replace(obs, **{f.name: getattr(obs, f.name).copy() for f in fields(obs)
                                if isinstance(getattr(obs, f.name), np.ndarray)})
        self._start = (d.backend, self.volume, start, shell)
        self._start_means = None
        # the inner band's samples, then the shell's, in one call
        inner = band_offsets(opts.band)
        along = d.backend.samples_along(self.volume, obs, np.concatenate([-inner, shell]),
                                        d.discretisation.band_rows)
        samples = np.concatenate([along[:, :len(inner)].ravel(), along[:, len(inner):].ravel()])
        samples = samples[np.isfinite(samples)]
        if samples.size < 10 or np.ptp(samples) <= 1e-6 * max(np.abs(samples).max(), 1.0):
            raise ValueError("the image is constant (or empty) around the initial surface: nothing to segment")
        states = {}
        # and the coarse levels' term, for a frame segmented again from it
        for level in self.levels + schedule(self.options)[:1]:
            if level.data_term not in states:
                states[level.data_term] = level.data_term.start(samples, band=opts.band, band_out=opts.band_out)
        return states

    @property
    def start_means(self) -> tuple[float, float]:
        """The region means about the initial surface (the cavity's and the
        shell's): a result's levels before any iteration has measured any."""
        if self._start_means is None:
            backend, volume, obs, shell = self._start
            self._start_means = backend.region_means(volume, obs, shell)
        return self._start_means

    # the levels ------------------------------------------------------------

    @property
    def surface(self) -> Surface:
        """The current surface."""
        return self.descent.surface

    @property
    def patches(self) -> tuple[int, int]:
        """The current level's patches."""
        return self.levels[self.level].patches

    @property
    def message(self) -> str:
        """Why the frame stopped (empty while running)."""
        return "" if self.status is None else STATUS_MESSAGES[self.status]

    def max_iterations(self, level: int | None = None) -> int:
        """The iteration cap of ``level`` (default: the current one): the
        schedule's, or on the finest patches the frame's (:attr:`frame_cap`)."""
        lv = self.levels[self.level if level is None else level]
        if self.frame_cap is not None and lv.patches == self.levels[-1].patches:
            return self.frame_cap
        return lv.max_iterations

    def _check_running(self) -> None:
        if self.status is not None:
            raise RuntimeError(f"the tracker has stopped ({self.message}); next_frame(volume) starts a new frame")

    def iterate(self) -> float:
        """Run one iteration; at the end of a level, move to the next.
        Returns the RMS motion of the surface in the iteration (mm)."""
        self._check_running()
        started = time.perf_counter()
        term = self.levels[self.level].data_term
        with kernel_threads(self.threads):
            obs = self.descent.observe(self.volume, term.reads(self.states[term]))
            if term.starts_from_bands and not self.states[term].frozen:  # no band means handed over: its own
                self._freeze(term, obs, *obs.band_means)
            force = term.force(obs, self.states[term])
            motion = self.descent.iterate(obs, force)
        self._advance(term, obs, force, motion, 1)
        self.seconds += time.perf_counter() - started
        return self.motion

    def run_level(self, max_iterations: int | None = None) -> bool:
        """Run the current level to its end (as :meth:`iterate` until the
        level changes), or at most ``max_iterations`` of it, in one compiled
        loop (:meth:`Descent.run`).  False, having run nothing, where that
        loop does not apply."""
        self._check_running()
        started = time.perf_counter()
        level = self.levels[self.level]
        term = level.data_term
        remaining = self.max_iterations() - self.level_iterations
        if max_iterations is not None:
            remaining = min(remaining, max_iterations)
        with kernel_threads(self.threads):
            run = self.descent.run(self.volume, term, self.states[term], tol=level.tol, max_iterations=remaining)
        if run is None:
            return False
        self._advance(term, run.observation, run.force, run.motion, run.iterations)
        self.seconds += time.perf_counter() - started
        return True

    def _advance(self, term, obs, force, motion: float, iterations: int) -> None:
        """Keep what ``iterations`` (the last of which observed ``obs``
        and moved by ``motion``) leave for a result, and end the level when
        its last one converged or the level reached its cap."""
        self.c_in, self.c_out = force.grey_means
        if term.hands_over_bands:
            self.band_fields = force.measured  # what the next stage may start from
        self.last = (obs.u, force, self.states[term].spread)
        self.observation = obs
        self.motion = motion
        self.iteration += iterations
        self.level_iterations += iterations
        if self.motion < self.levels[self.level].tol:
            self._end_level(converged=True)
        elif self.level_iterations >= self.max_iterations():
            self._end_level(converged=False)

    def _end_level(self, *, converged: bool) -> None:
        self.converged = converged
        if self.level + 1 < len(self.levels):
            self.level += 1
            self.level_iterations = 0
            self._start_term()
            if self.levels[self.level].patches == self.levels[self.level - 1].patches:
                try:
                    self._hand_over()
                except NoSpeckleError:  # nothing to undo the log compression with: the local means' wall stands
                    self.level -= 1
                    self.no_speckle = True
                    self.status = 0 if converged else 1
                    return
                # the intensity stage: same grid, same landmarks
                self.descent.restart(self.stage_step(settled=converged))
            else:
                surface = self.descent.surface
                if self.levels[self.level].patches == self.levels[-1].patches:
                    self.reference = self._finest_reference(surface)
                self.descent = self.new_descent(surface, self.reference)
            self._skip_empty_levels()
        else:
            self.status = 0 if converged else 1

    def _finest_reference(self, surface: Surface) -> Surface:
        """The shape the finest patches smooth the wall's departure from
        (:attr:`SegmentOptions.smoothness_reference`): the clicked one, or
        its half-ellipsoid holding what ``surface``, the coarse levels'
        end, holds (where the stepper was given the clicked shape's family,
        ``fitted_start``)."""
        if self.options.smoothness_reference == "fitted" and self.fitted_start is not None:
            fitted = self.fitted_start(surface.volume_ml(), patches=(surface.grid.n1, surface.grid.n2))
            if fitted is not None:
                return fitted
        return self.reference

    def _start_term(self) -> None:
        """The current level's data term forgets what it measured before
        (a new level or frame), and so do the band means it hands over."""
        term = self.levels[self.level].data_term
        self.states[term] = term.reset(self.states[term])
        if term.hands_over_bands:
            self.band_fields = None

    def _hand_over(self) -> None:
        """The intensity interface starts from the local means' last band
        means, about the wall where they stopped (when they ran in this frame)."""
        term = self.levels[self.level].data_term
        if self.band_fields is not None and term.starts_from_bands:
            with kernel_threads(self.threads):
                self._freeze(term, self.observation, *self.band_fields)

    def _freeze(self, term: DataTerm, obs, c_in, c_out) -> None:
        """The term's levels set from the band means ``c_in``, ``c_out``
        about the surface of ``obs``, with the samples it asks for."""
        state = self.states[term]
        samples = freeze_samples(self.descent.backend, self.volume, obs, term.freeze_reads(state))
        self.states[term] = term.freeze(state, obs, c_in, c_out, samples)

    def _skip_empty_levels(self) -> None:
        if self.status is None and self.max_iterations() == 0:
            self._end_level(converged=False)

    def stop(self, status: int = 2) -> None:
        """End the frame now (``status`` 2: stopped from outside)."""
        self.status = status
        self.converged = False

    def samples_along_normals(self, offsets: np.ndarray) -> np.ndarray:
        """The frame's grey levels at ``offsets`` (mm along the outward
        normals, negative inside) at the current surface's sample points,
        ``(n, len(offsets))``, trilinear (NaN off the data)."""
        backend = self.descent.backend
        return backend.samples_along(self.volume, backend.observe(self.descent.p, self.volume), offsets)

    def interface_levels(self) -> tuple[float, float]:
        """Scalar ``(c_in, c_out)`` (grey levels) about the finest level's
        interface: the medians of its fixed levels (the intensity
        interface's), else of the region means last measured."""
        term = self.levels[-1].data_term
        state = self.states[term]
        if term.loop_kind(state) == "fixed":
            fixed = term.fixed_force(state)
            c_in, c_out = fixed.c_in, fixed.c_out
        else:
            c_in, c_out = self.c_in, self.c_out
        return float(nanmedian(c_in)), float(nanmedian(c_out))

    def log_compression(self) -> float | None:
        """Grey levels per neper of echo intensity, as the finest level's
        intensity interface estimated them from the wall's speckle
        (``TermState.nepers``); None before that, or with another data term."""
        term = self.levels[-1].data_term
        nepers = self.states[term].nepers
        return float(nepers) if isinstance(term, IntensityInterface) and nepers is not None else None

    def beyond_wall(self) -> tuple[float, float]:
        """Grey levels the finest level's intensity interface took off the
        myocardium's level for what its outer band read beyond a thin wall,
        and the fraction of that band's rise they are
        (``TermState.beyond_wall``, ``beyond_wall_fraction``); ``(0, 0)``
        with another data term or before its levels were set."""
        term = self.levels[-1].data_term
        state = self.states[term]
        if isinstance(term, IntensityInterface) and state.frozen:
            return float(state.beyond_wall), float(state.beyond_wall_fraction)
        return 0.0, 0.0

    # what changes between runs -----------------------------------------------

    def count_threads(self) -> None:
        """Count again the cores the machine's load leaves the kernels."""
        self.threads = kernel_thread_count(self.options.threads)

    def resume(self, points, weights, *, level: int) -> None:
        """Hold the surface through ``points`` (with ``weights``; None: no
        points) and continue the frame at ``level`` with a fresh step."""
        self.descent.set_landmarks(points, weights)
        self.level = level
        self.descent.reset_step(self.stage_step())
        self.level_iterations, self.status = 0, None

    def restart_from(self, surface: Surface) -> None:
        """A new descent on the current level from ``surface``, also the
        smoothing prior's reference (the model posed anew)."""
        self.descent = self.new_descent(surface, surface)

    def start_frame(self, volume, max_iterations: int) -> None:
        """Continue on a new frame from the current surface: the levels on
        the finest patches run again (for the intensity mode the local
        means, then the interface measured where they end), each capped at
        ``max_iterations``, with the current surface as the start and the
        reference shape of the smoothing prior; same matrices, the data
        terms' statistics measured again."""
        surface = self.surface
        finest = [k for k, level in enumerate(self.levels) if level.patches == self.levels[-1].patches]
        self.frame_cap = max_iterations
        self.volume = volume
        self.reference = surface
        if self.level != finest[0]:
            same_grid = self.patches == self.levels[finest[0]].patches
            self.level = finest[0]
            if same_grid:  # as a new descent on this grid and pose
                self.descent.restart(self.stage_step())
                self.descent.set_reference(surface)
            else:  # stopped on a coarser level
                self.descent = self.new_descent(surface, surface)
        else:
            self.descent.set_surface(surface)
            self.descent.set_reference(surface)
            self.descent.reset_step(self.stage_step())
        self._start_term()
        self.iteration, self.level_iterations, self.status, self.converged = 0, 0, None, False
        self.no_speckle = False
        self.seconds = 0.0

    def adopt(self, other: Stepper) -> None:
        """Continue from ``other``'s end instead of this one's (the same
        frame segmented again, on the same grid and pose): its descent, data
        terms and what they measured; the frame's iterations count both."""
        self.descent, self.states, self.band_fields, self.reference = (other.descent, other.states, other.band_fields,
                                                                       other.reference)
        for name in ("c_in", "c_out", "last", "observation"):
            if getattr(other, name) is not None:
                setattr(self, name, getattr(other, name))
        self.motion, self.converged, self.status = other.motion, other.converged, other.status
        self.level = len(self.levels) - 1  # every candidate ends on its finest level
        self.iteration += other.iteration
