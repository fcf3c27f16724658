"""One study in the viewer: its frames, the user's points, the segmentations
run on them, and the events the page is sent while they run.

Nothing here knows HTTP: :mod:`spheroseg.viewer.server` turns requests into
calls of :class:`Session` and its events into Server-Sent Events.

Coordinates: every point the session receives, stores, segments with,
sends and saves is LPS millimetres (ITK's, the files', the rest of the
package's); the page alone converts to the frame NiiVue draws in.
"""

from __future__ import annotations

import base64
import collections
import contextlib
import os
import queue
import shutil
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from ...io.atomic import shared_mode
from ...volumes.beamspace import BeamVolume, scan_convert
from ...io import save_volume, write_markups
from ...descent.options import SegmentOptions
from ...descent.results import TrackingResult
from ...tracking.segment import add_checks, tracking_order
from ...surfaces.surface import Surface
from ...tracking.tracker import Tracker
from ...volumes.volume import Volume

from ...tracking.locate import NoVentricleError, annotate, initialise, locate

#: the display mesh's resolution (around the axis, from apex to base): fixed,
#: so the page builds its mesh once and only moves the vertices
MESH_RESOLUTION = (48, 24)
#: the least time between two intermediate surfaces sent while a descent runs
#: (s): the final one is always sent; each costs a mesh, its encoding and the
#: page's drawing, CPU the descent would otherwise have
STREAM_INTERVAL = 0.1
#: iterations between two looks at the stream (a newer job stops the descent
#: there); those between run in the compiled loop, at a plain run's speed
STREAM_EVERY = 8


def _encode(array, dtype) -> str:
    return base64.b64encode(np.ascontiguousarray(array, dtype=dtype).tobytes()).decode("ascii")


@dataclass(frozen=True)
class Points:
    """What the user placed, LPS mm: ``apex``, ``base`` (None until given),
    ``landmarks`` (k, 3) and ``annulus`` (k, 3; from a markups file)."""

    apex: np.ndarray | None = None
    base: np.ndarray | None = None
    landmarks: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    annulus: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    @classmethod
    def from_json(cls, data: dict) -> "Points":
        """Points as the page sends them (LPS mm), checked: one-line
        ``ValueError`` on anything else."""
        if not isinstance(data, dict):
            raise ValueError("points must be a JSON object with apex, base and landmarks")

        def point(value, name):
            if value is None:
                return None
            numbers = isinstance(value, list) and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
            p = np.asarray(value, dtype=float) if numbers else None
            if p is None or p.shape != (3,) or not np.all(np.isfinite(p)):
                raise ValueError(f"{name} must be 3 finite numbers (mm), got {value!r}"[:200])
            return p

        def points(value, name):
            value = [] if value is None else value
            if not isinstance(value, list) or len(value) > 64:
                raise ValueError(f"{name} must be a list of at most 64 points")
            return np.array([point(v, f"{name}[{k}]") for k, v in enumerate(value)]).reshape(-1, 3)

        return cls(point(data.get("apex"), "apex"), point(data.get("base"), "base"),
                   points(data.get("landmarks"), "landmarks"), points(data.get("annulus"), "annulus"))

    def as_json(self) -> dict:
        def listed(p):
            return None if p is None else np.asarray(p, dtype=float).tolist()

        return {"apex": listed(self.apex), "base": listed(self.base),
                "landmarks": [listed(p) for p in self.landmarks], "annulus": [listed(p) for p in self.annulus]}

    def named(self):
        """``(name, point)`` for every point placed, named as in messages."""
        if self.apex is not None:
            yield "the apex", self.apex
        if self.base is not None:
            yield "the base", self.base
        for k, p in enumerate(self.landmarks):
            yield f"landmark {k}", p
        for k, p in enumerate(self.annulus):
            yield f"annulus point {k}", p

    @property
    def complete(self) -> bool:
        return self.apex is not None and (self.base is not None or len(self.annulus) >= 3)

    def keywords(self) -> dict:
        """``apex``, ``base``, ``annulus`` and ``landmarks`` for :class:`Tracker`."""
        return {"apex": self.apex, "base": self.base, "annulus": self.annulus if len(self.annulus) else None,
                "landmarks": self.landmarks if len(self.landmarks) else None}

    def same(self, other: "Points") -> bool:
        def eq(a, b):
            return (a is None) == (b is None) and (a is None or (np.shape(a) == np.shape(b) and np.array_equal(a, b)))

        return all(eq(getattr(self, k), getattr(other, k)) for k in ("apex", "base", "landmarks", "annulus"))


class EventStream:
    """One page's pending events.  When more than ``capacity`` wait (a page
    too slow to read them), the oldest intermediate surface goes: the final
    surfaces and the other events are kept."""

    def __init__(self, capacity: int = 64):
        self.capacity = capacity
        self._events: collections.deque = collections.deque()
        self._ready = threading.Condition()

    def put(self, kind: str, data: dict) -> None:
        with self._ready:
            if len(self._events) >= self.capacity:
                stale = next((e for e in self._events if e[0] == "surface" and not e[1].get("final")), None)
                if stale is not None:
                    self._events.remove(stale)
            self._events.append((kind, data))
            self._ready.notify()

    def get(self, timeout: float) -> tuple[str, dict]:
        """The next event; ``queue.Empty`` after ``timeout`` seconds without one."""
        with self._ready:
            if not self._ready.wait_for(lambda: self._events, timeout):
                raise queue.Empty
            return self._events.popleft()


class Broadcaster:
    """Events to every open page, each with its own :class:`EventStream`."""

    def __init__(self, *, capacity: int = 64):
        self._subscribers: list[EventStream] = []
        self._lock = threading.Lock()
        self.capacity = capacity
        self.closed = False

    def subscribe(self) -> EventStream:
        stream = EventStream(self.capacity)
        with self._lock:
            self._subscribers.append(stream)
        return stream

    def unsubscribe(self, stream: EventStream) -> None:
        with self._lock:
            if stream in self._subscribers:
                self._subscribers.remove(stream)

    def publish(self, kind: str, data: dict) -> None:
        data = {**data, "sent": time.time()}
        with self._lock:
            for stream in self._subscribers:
                stream.put(kind, data)

    def close(self) -> None:
        self.closed = True
        self.publish("close", {})


class Session:
    """A study open in the viewer.

    Parameters
    ----------
    frames : list of Volume or BeamVolume
        One 3D image, or the frames of a 3D+t sequence.
    source : str or Path
        Where they came from (recorded in the saved results).
    save_root : Path
        The only folder under which :meth:`save` writes.
    points : Points, optional
        Points to start from (a markups file): the frame is segmented at once.
    spacing_assumed : bool
        The voxel spacing was given by the user, not read from the file: the
        LV mass (and every volume) rests on it, and the page says so.
    **options
        :class:`spheroseg.SegmentOptions`.

    Notes
    -----
    One worker thread runs the jobs, newest first: a new request stops the
    running descent at its next iteration (``StopIteration`` from the
    callback), so dragging a landmark never queues stale work.  Every
    segmentation starts from the points alone, so what the page shows is
    what :func:`spheroseg.segment` gives for the same points, and what a
    saved markups file reproduces from the command line.
    """

    def __init__(self, frames, *, source, save_root, points: Points | None = None, iterations_per_frame: int = 20,
                 spacing_assumed: bool = False, **options):
        self.frames = list(frames)
        if not self.frames:
            raise ValueError("no frames to show")
        self.source = Path(source)
        self.save_root = Path(save_root).resolve()
        self.options = SegmentOptions(**options)
        self.iterations_per_frame = int(iterations_per_frame)
        self.spacing_assumed = bool(spacing_assumed)
        self.display = [scan_convert(f) if isinstance(f, BeamVolume) else f for f in self.frames]
        self.points = Points()
        # frame -> (the points it was segmented from, its result)
        self.results: dict[int, tuple[Points, object]] = {}
        self.tracking: TrackingResult | None = None
        self.tracked_points: Points | None = None
        self.events = Broadcaster()
        self._lock = threading.Lock()
        self._generation = 0
        self._jobs: queue.Queue = queue.Queue()
        self._nifti: bytes | None = None
        self._faces = None
        # frame -> what locate() found there (or the NoVentricleError it raised)
        self._located: dict[int, object] = {}
        # frame -> the points Find placed there: segmented from them, the
        # result is checked as spheroseg.segment checks a located one
        self._found: dict[int, Points] = {}
        # frame -> (the result, its epicardium): computed when the page asks
        self._epicardia: dict[int, tuple] = {}
        self._grey_range: tuple[float, float] | None = None  # the displayed grey levels' range
        self._worker = threading.Thread(target=self._work, name="spheroseg-viewer-worker", daemon=True)
        self._worker.start()
        if points is not None and points.complete:
            self.set_points(points, frame=0)
        elif points is not None:
            self.points = points

    # what the page reads ------------------------------------------------------

    def nifti(self) -> bytes:
        """The frames as one NIfTI file (4D for a sequence), 8-bit: the
        grey levels scaled linearly from the frames' range to 0-255 (no-data
        voxels 0), on the display grid (a beam-space study scan-converted)."""
        with self._lock:
            if self._nifti is None:
                self._nifti = _display_nifti(self.display)
            return self._nifti

    def faces(self) -> np.ndarray:
        """Triangles of the display mesh: the same for every surface of this
        study (the grid's poles decide them)."""
        if self._faces is None:
            surface = Surface.from_apex_base((0.0, 0.0, 80.0), (0.0, 0.0, 0.0), system=self.options.system,
                                             patches=self.options.patches)
            self._faces = surface.mesh(*MESH_RESOLUTION)[1]
        return self._faces

    def describe(self) -> dict:
        grid = self.display[0].grid
        return {
            "source": self.source.name, "frames": len(self.frames), "shape": list(grid.shape[::-1]),
            "spacing": grid.spacing.tolist(), "faces": _encode(self.faces(), "<u4"),
            "options": self.options.as_parameters(), "points": self.points.as_json(),
            "job": self._generation,
            "tracking": self._tracking_summary(),
            "save_root": str(self.save_root),
            "spacing_assumed": self.spacing_assumed,
            "state": self.state(),
        }

    def state(self) -> dict:
        """What the study's results are made from, as the server holds it:
        the points (LPS mm), the options, the newest job's number and, when
        the sequence was tracked with these points, the frame tracking
        started from.  Every answer to the page carries it, and the page
        shows, lists and saves what it says."""
        with self._lock:
            points, job = self.points, self._generation
            tracked = self.tracking is not None and self.tracked_points is not None and points.same(self.tracked_points)
            start = self.tracking.start_frame if tracked else None
        return {"points": points.as_json(), "options": self.options.as_parameters(), "job": job,
                "tracked": tracked, "start_frame": start}

    def surface_event(self, frame: int) -> dict | None:
        result = self._frame_result(frame)
        if result is None:
            return None
        return self._surface_data(frame, result.surface, final=True, result=result, job=self._generation,
                                  points=self.points)

    def epicardium_event(self, frame: int) -> dict | None:
        """The epicardium of ``frame``'s result for the current points
        (:func:`spheroseg.epicardium.segment_epicardium` with the result's
        log compression, as ``segment(..., myocardium=True)``; once a result):
        its display mesh's vertices, the LV mass (g); None before the frame
        is segmented.  Asked for by the page only when it draws the
        myocardium, so that the endocardium's latency stays the same."""
        from ...tracking.epicardium import segment_epicardium
        from ...surfaces.myocardium import lv_mass_g, myocardial_volume_ml

        result = self._frame_result(frame)
        if result is None:
            return None
        with self._lock:
            cached = self._epicardia.get(frame)
        if cached is None or cached[0] is not result:
            cached = (result, segment_epicardium(self.frames[frame], result.surface,
                                                 nepers=result.log_compression).surface)
            with self._lock:
                self._epicardia[frame] = cached
        epicardium = cached[1]
        vertices = _encode(epicardium.mesh(*MESH_RESOLUTION)[0], "<f4")
        caveats = ["myocardium validated on phantoms only"]
        if self.spacing_assumed:
            caveats.insert(0, "voxel spacing assumed, not read from the file")
        return {"frame": frame, "job": self._generation, "vertices": vertices,
                "lv_mass_g": lv_mass_g(myocardial_volume_ml(result.surface, epicardium)), "caveats": caveats}

    def views_event(self, frame: int) -> dict | None:
        """The standard views (:func:`.views.standard_views`) of ``frame``'s
        result for the current points: each plane, its image (uint8,
        base64, rows x cols, scaled as the displayed volume) and the
        surface's contour on it (pixel segments); None before the frame is
        segmented."""
        from .views import contour, sample, standard_views

        result = self._frame_result(frame)
        if result is None:
            return None
        with self._lock:
            if self._grey_range is None:
                arrays = [v.array if v.no_data_mask is None else v.array[~v.no_data_mask] for v in self.display]
                self._grey_range = (min(float(a.min()) for a in arrays), max(float(a.max()) for a in arrays))
            lo, hi = self._grey_range
        vertices, faces = result.surface.mesh(*MESH_RESOLUTION)
        shown = self.display[frame]
        views = [{**view.as_json(), "image": _encode(sample(shown, view, lo=lo, hi=hi), "u1"),
                  "contour": contour(vertices, faces, view).ravel().tolist()}
                 for view in standard_views(result.surface)]
        return {"frame": frame, "job": self._generation, "views": views}

    # what the page asks for ---------------------------------------------------

    def set_points(self, points: Points, *, frame: int) -> int:
        """Segment ``frame`` from ``points`` (in the background); the
        running job stops.  Returns the job's number (its events carry it)."""
        frame = self.check_frame(frame)
        self._check_inside(points, frame)
        if points.complete:
            Tracker(self.frames[frame], **points.keywords(), **self.options.as_parameters())  # checks, one line each
        with self._lock:
            self.points = points
            self._generation += 1
            job = self._generation
        if points.complete:
            self._jobs.put(("segment", job, frame, points))
        else:
            self.events.publish("cleared", {"job": job, "frame": frame})
            if points.apex is not None:  # locate while the user places the base: its click check is then ready
                self._jobs.put(("locate", job, frame, None))
        return job

    def find(self, *, frame: int) -> dict:
        """Place apex and base where :func:`spheroseg.locate.locate` finds
        the ventricle on ``frame``, and segment from them (landmarks and
        annulus points are dropped).  Returns the job's number, the points
        (LPS mm), the locator's ``confidence`` (0-1) and its ``reason``; a
        one-line ``ValueError`` when no ventricle is found."""
        frame = self.check_frame(frame)
        with self._lock:
            self._located.pop(frame, None)
        found = self._locate(self.frames[frame], frame)
        points = Points(apex=np.asarray(found.apex, dtype=float), base=np.asarray(found.base, dtype=float))
        with self._lock:
            self._found[frame] = points
        job = self.set_points(points, frame=frame)
        # what spheroseg.segment says of a location it starts from, said at once
        said = SimpleNamespace(quality={"warnings": [], "poor": False})
        annotate(said, {"method": "located", **points.as_json(), "located": found.as_dict()}, found)
        return {"job": job, **points.as_json(), "confidence": float(found.confidence), "reason": str(found.reason),
                "poor": bool(said.quality["poor"]), "warnings": list(said.quality["warnings"])}

    def track(self, *, frame: int) -> int:
        """Track every frame from ``frame`` (forwards to the last, then
        backwards to the first) with the current points."""
        frame = self.check_frame(frame)
        if len(self.frames) < 2:
            raise ValueError("tracking needs a 3D+t sequence; this study has one frame")
        with self._lock:
            points = self.points
            if not points.complete:
                raise ValueError("place the apex and the base first")
            self._generation += 1
            job = self._generation
        self._jobs.put(("track", job, frame, points))
        return job

    def save(self, name: str, *, frame: int, report: bool = True) -> dict:
        """Write the outputs of the command line (and ``points.mrk.json``)
        into a new folder ``save_root / name``: the tracked sequence if it was
        tracked with the current points, otherwise ``frame``'s segmentation.
        The folder is written beside its final place and renamed into it;
        an existing folder is never written into."""
        from ...io.outputs import default_mask_suffix, write_segmentation_outputs, write_tracking_outputs

        frame = self.check_frame(frame)
        target = self._save_target(name)
        with self._lock:
            points = self.points
            tracked = self.tracking is not None and self.tracked_points is not None and points.same(self.tracked_points)
            tracking = self.tracking if tracked else None
        result = self._frame_result(frame)
        if tracking is None and result is None:
            raise ValueError(f"nothing to save for frame {frame} yet: place the apex and the base, and let the "
                             "segmentation finish")
        suffix = default_mask_suffix(self.source)  # the input's type, as the command line
        keywords = points.keywords()
        staging = Path(tempfile.mkdtemp(prefix=".spheroseg-save-", dir=target.parent))
        try:
            shared_mode(staging)  # as mkdir makes a folder, not mkdtemp's 0700
            if tracking is not None:
                written = write_tracking_outputs(staging, self.frames, tracking, source=self.source, report=report,
                                                 mask_suffix=suffix, **keywords)
            else:
                written = write_segmentation_outputs(staging, self.frames[frame], result, source=self.source,
                                                     report=report, mask_suffix=suffix, extra={"frame": frame},
                                                     **keywords)
            write_markups(staging / "points.mrk.json", **keywords)
            os.rename(staging, target)  # fails if the target appeared meanwhile: never merged into
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
        files = sorted(str(p.relative_to(target)) for p in target.rglob("*") if p.is_file())
        return {"folder": str(target), "files": files, "tracked": tracking is not None,
                "volume_ml": written.get("volume_ml"), "ef_percent": written.get("ef_percent")}

    def close(self) -> None:
        """Stop the running job and the worker; end the event streams; wait
        for the worker to return (a process that exits while its worker thread
        is inside a kernel's parallel region can abort in the OpenMP runtime's
        teardown)."""
        with self._lock:
            self._generation += 1
        self._jobs.put(None)
        self.events.close()
        if threading.current_thread() is not self._worker:
            self._worker.join()

    # inside -------------------------------------------------------------------

    def check_frame(self, frame) -> int:
        """``frame`` if it is a frame of this study; else a one-line ``ValueError``."""
        if not isinstance(frame, int) or isinstance(frame, bool) or not 0 <= frame < len(self.frames):
            raise ValueError(f"frame must be an integer from 0 to {len(self.frames) - 1}, got {frame!r}"[:200])
        return frame

    def _check_inside(self, points: Points, frame: int) -> None:
        """A one-line ``ValueError`` for a point outside the displayed image
        or in its no-data region (the padding around an echo sector): a
        surface pulled there can only fit noise."""
        shown = self.display[frame]
        for name, p in points.named():
            where = ", ".join(f"{v:.1f}" for v in p)
            if not shown.contains(p):
                raise ValueError(f"{name} ({where} LPS mm) is outside the image: place it on the heart")
            if shown.no_data_mask is not None:
                index = tuple(np.clip(np.rint(shown.world_to_index(p)).astype(int), 0,
                                      np.array(shown.shape[::-1]) - 1)[::-1])
                if shown.no_data_mask[index]:
                    raise ValueError(f"{name} ({where} LPS mm) is outside the echo's data (the padding around "
                                     "the sector): place it inside the sector")

    def _save_target(self, name) -> Path:
        if not isinstance(name, str) or not name.strip():
            raise ValueError("name the folder to save into")
        relative = Path(name.strip())
        if relative.is_absolute() or any(part in ("..", "") for part in relative.parts) or len(name) > 200:
            raise ValueError(f"the folder must be a relative path inside {self.save_root}, got {name!r}"[:300])
        target = (self.save_root / relative).resolve()
        if self.save_root not in target.parents:
            raise ValueError(f"the folder must be inside {self.save_root}")
        if target.exists():
            raise ValueError(f"{target} exists already: choose a new folder name")
        target.parent.mkdir(parents=True, exist_ok=True)
        return target

    def _frame_result(self, frame: int):
        """``frame``'s result for the current points (tracked or segmented), or None."""
        with self._lock:
            if self.tracking is not None and self.tracked_points is not None and self.points.same(self.tracked_points):
                return self.tracking.frames[frame]
            points, result = self.results.get(frame, (None, None))
            return result if points is not None and points.same(self.points) else None

    def _tracking_summary(self) -> dict | None:
        with self._lock:
            tracking = self.tracking if self.tracked_points is not None and self.points.same(self.tracked_points) \
                else None
        if tracking is None:
            return None
        return {"volumes_ml": tracking.volumes_ml.tolist(), "ed_frame": tracking.ed_frame,
                "es_frame": tracking.es_frame, "edv_ml": tracking.edv_ml, "esv_ml": tracking.esv_ml,
                "ef_percent": tracking.ef, "start_frame": tracking.start_frame}

    def _surface_data(self, frame, surface, *, final, result=None, job=None, iteration=0, level=0,
                      points: Points | None = None) -> dict:
        vertices = surface.mesh(*MESH_RESOLUTION)[0]
        data = {"job": job, "frame": frame, "final": final, "iteration": iteration, "level": level,
                "vertices": _encode(vertices, "<f4"), "volume_ml": surface.volume_ml()}
        if points is not None:  # what the surface was made from: the page lists these
            data["points"] = points.as_json()
        if result is not None:
            quality = result.quality or {}
            data.update(status=result.status, message=result.message, iterations=result.iterations,
                        seconds=result.seconds, warnings=list(quality.get("warnings", [])) + list(quality.get("notes", [])),
                        poor=bool(quality.get("poor", False)))
        return data

    def _current(self, job: int) -> bool:
        return job == self._generation

    def _work(self) -> None:
        from ..warmup import load_kernels

        load_kernels()  # before the first click, not after it
        while True:
            item = self._jobs.get()
            if item is None:
                return
            kind, job, frame, points = item
            if not self._current(job):
                continue
            try:
                if kind == "segment":
                    self._segment(job, frame, points)
                elif kind == "track":
                    self._track(job, frame, points)
                else:
                    with contextlib.suppress(NoVentricleError):  # refused: the click check says nothing
                        self._locate(self.frames[frame], frame)
            except Exception as exc:  # reported to the page; the worker goes on
                message = " ".join(str(exc).split()) or type(exc).__name__
                self.events.publish("failure", {"job": job, "message": message})

    def _stream(self, job: int, frame: int):
        """An ``iter_callback`` that sends intermediate surfaces (at most one
        per :data:`STREAM_INTERVAL`) and stops the descent when a newer job
        arrives."""
        last = [time.perf_counter()]

        def callback(step):
            if not self._current(job):
                raise StopIteration
            now = time.perf_counter()
            if now - last[0] >= STREAM_INTERVAL:
                last[0] = now
                self.events.publish("surface", self._surface_data(frame, step.surface, final=False, job=job,
                                                                  iteration=step.iteration, level=step.level))

        return callback

    def _locate(self, volume, frame: int):
        """:func:`spheroseg.locate.locate` on ``frame``, once a frame (the
        clicks are checked against it after every segmentation)."""
        with self._lock:
            found = self._located.get(frame)
        if found is None:
            try:
                found = locate(volume)
            except NoVentricleError as error:
                found = error
            with self._lock:
                self._located[frame] = found
        if isinstance(found, NoVentricleError):
            raise found
        return found

    def _check_points(self, result, frame: int, points: Points) -> None:
        """Check the clicked points against the located ventricle and say so
        in ``result.quality``, as :func:`spheroseg.segment` does
        (:func:`spheroseg.segment.add_checks`)."""
        keywords = points.keywords()
        with self._lock:
            found = self._found.get(frame)
        if found is not None and found.same(points):  # Find's points, unmoved: checked as located ones
            _, _, initialisation, located = initialise(self.frames[frame], None, None,
                                                       locator=lambda volume: self._locate(volume, frame))
        else:
            _, _, initialisation, located = initialise(
                self.frames[frame], keywords["apex"], keywords["base"], annulus=keywords["annulus"],
                locator=lambda volume: self._locate(volume, frame))
        add_checks(result, self.frames[frame], initialisation, located)

    def _segment(self, job: int, frame: int, points: Points) -> None:
        tracker = Tracker(self.frames[frame], **points.keywords(), **self.options.as_parameters())
        self.events.publish("surface", self._surface_data(frame, tracker.surface, final=False, job=job))
        result = tracker.run(self._stream(job, frame), callback_every=STREAM_EVERY)
        if not self._current(job):
            return
        self._check_points(result, frame, points)
        with self._lock:
            self.results[frame] = (points, result)
        self.events.publish("surface", self._surface_data(frame, result.surface, final=True, result=result, job=job,
                                                          points=points))

    def _track(self, job: int, frame: int, points: Points) -> None:
        n = len(self.frames)
        order = tracking_order(n, frame)  # as spheroseg track --start-frame
        results: dict[int, object] = {}
        tracker = None
        for done, t in enumerate(order, 1):
            if not self._current(job):
                return
            if t == frame or t == frame - 1:  # each direction starts from the clicked frame
                tracker = Tracker(self.frames[frame], **points.keywords(), **self.options.as_parameters())
                if t == frame:
                    results[t] = tracker.run(self._stream(job, t), callback_every=STREAM_EVERY)
                    self._check_points(results[t], t, points)
                    self._publish_frame(job, t, results[t], done, n, points)
                    continue
                tracker.run()
            results[t] = tracker.next_frame(self.frames[t], max_iterations=self.iterations_per_frame,
                                            iter_callback=self._stream(job, t), callback_every=STREAM_EVERY,
                                            follow_base=True)
            self._publish_frame(job, t, results[t], done, n, points)
        if not self._current(job):
            return
        tracking = TrackingResult([results[t] for t in range(n)], start_frame=frame)
        with self._lock:
            self.tracking, self.tracked_points = tracking, points
        self.events.publish("tracked", {"job": job, **self._tracking_summary(), "state": self.state()})

    def _publish_frame(self, job, t, result, done, total, points) -> None:
        if self._current(job):
            self.events.publish("progress", {"job": job, "done": done, "total": total})
            self.events.publish("surface", self._surface_data(t, result.surface, final=True, result=result, job=job,
                                                              points=points))


def _display_nifti(volumes) -> bytes:
    arrays = [np.where(v.no_data_mask, np.float32(np.nan), v.array) if v.no_data_mask is not None else v.array
              for v in volumes]
    lo = min(float(np.nanmin(a)) for a in arrays)
    hi = max(float(np.nanmax(a)) for a in arrays)
    scale = 255.0 / (hi - lo) if hi > lo else 1.0
    grid = volumes[0].grid
    scaled = [Volume(np.rint(np.nan_to_num((a - lo) * scale, nan=0.0)), spacing=grid.spacing, origin=grid.origin,
                     direction=grid.direction) for a in arrays]
    with tempfile.TemporaryDirectory(prefix="spheroseg-view-") as folder:
        path = Path(folder) / "study.nii"
        save_volume(path, scaled if len(scaled) > 1 else scaled[0], dtype=np.uint8)
        return path.read_bytes()
