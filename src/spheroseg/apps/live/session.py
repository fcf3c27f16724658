"""The live tracker: frames tracked as they come, as :func:`spheroseg.track`
tracks a sequence, and the cardiac cycle found on the fly.

:class:`LiveTracker` makes the same calls as :func:`spheroseg.track` (the
first frame started by :func:`spheroseg.locate.initialise`, each later one
by :meth:`spheroseg.Tracker.next_frame` from the previous surface), so the
volumes of frames tracked without a gap equal ``track``'s.  A frame of
another geometry starts the tracking again.

:class:`VolumeCurve` holds the recent volume curve.  Its period is the lag
of the first peak of its autocorrelation (at heart rates of 30 to 200 beats
a minute, on the curve resampled at the frame rate the timestamps give);
end-diastole and end-systole are the frames of largest and smallest volume
over the last period, and over every frame held until a period is found.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

__all__ = ["LiveTracker", "LiveFrame", "VolumeCurve", "same_geometry"]

#: the autocorrelation a peak needs to be taken for the cycle's period
PERIOD_CORRELATION = 0.6
#: heart rates a period is looked for within, beats a minute
HEART_RATES_BPM = (30.0, 200.0)


def same_geometry(a, b, *, atol: float = 1e-6) -> bool:
    """Whether two :class:`spheroseg.ImageGrid` place the same voxels."""
    return (a.shape == b.shape and np.allclose(a.spacing, b.spacing, rtol=0, atol=atol)
            and np.allclose(a.origin, b.origin, rtol=0, atol=atol)
            and np.allclose(a.direction, b.direction, rtol=0, atol=atol))


class VolumeCurve:
    """The volume curve of the last ``max_frames`` frames tracked.

    Parameters
    ----------
    max_frames : int
        Frames held (memory stays bounded however long the stream).
    """

    def __init__(self, *, max_frames: int = 600):
        self.times = deque(maxlen=max_frames)
        self.indices = deque(maxlen=max_frames)
        self.volumes = deque(maxlen=max_frames)

    def clear(self) -> None:
        self.times.clear()
        self.indices.clear()
        self.volumes.clear()

    def add(self, timestamp: float, index: int, volume_ml: float) -> None:
        self.times.append(float(timestamp))
        self.indices.append(int(index))
        self.volumes.append(float(volume_ml))

    def period(self, frame_rate: float | None) -> float | None:
        """The cycle's period (s), or None when no peak of the
        autocorrelation reaches :data:`PERIOD_CORRELATION` (fewer than two
        cycles held, or no rhythm)."""
        if not frame_rate or len(self.volumes) < 4:
            return None
        t = np.asarray(self.times)
        if not np.all(np.diff(t) > 0):
            return None
        grid = np.arange(t[0], t[-1] + 0.5 / frame_rate, 1.0 / frame_rate)
        x = np.interp(grid, t, np.asarray(self.volumes))
        x = x - x.mean()
        lags = np.arange(max(1, int(np.ceil(60.0 / HEART_RATES_BPM[1] * frame_rate))),
                         min(len(x) // 2, int(60.0 / HEART_RATES_BPM[0] * frame_rate)) + 1)
        if len(lags) < 3:
            return None
        r = np.array([np.corrcoef(x[:-lag], x[lag:])[0, 1] if np.std(x[lag:]) > 0 and np.std(x[:-lag]) > 0
                      else 0.0 for lag in lags])
        peaks = np.flatnonzero((r[1:-1] >= r[:-2]) & (r[1:-1] > r[2:]) & (r[1:-1] >= PERIOD_CORRELATION)) + 1
        return None if not len(peaks) else float(lags[peaks[0]] / frame_rate)

    def last_cycle(self, frame_rate: float | None) -> dict:
        """``edv_ml``, ``esv_ml``, ``ef`` (percent), ``ed_index``,
        ``es_index`` over the last period (``cycle`` ``"detected"``) or every
        frame held (``"so far"``), and ``heart_rate_bpm`` (None until a period
        is found)."""
        if not self.volumes:
            return {}
        period = self.period(frame_rate)
        t, v, k = np.asarray(self.times), np.asarray(self.volumes), np.asarray(self.indices)
        window = np.ones(len(t), bool) if period is None else t > t[-1] - period + 0.5 / frame_rate
        ed, es = np.flatnonzero(window)[[np.argmax(v[window]), np.argmin(v[window])]]
        return {"edv_ml": float(v[ed]), "esv_ml": float(v[es]), "ef": float(100.0 * (v[ed] - v[es]) / v[ed]),
                "ed_index": int(k[ed]), "es_index": int(k[es]), "cycle": "so far" if period is None else "detected",
                "heart_rate_bpm": None if period is None else 60.0 / period}


@dataclass
class LiveFrame:
    """A frame tracked live: its result and what the stream is to be told."""

    index: int
    timestamp: float
    volume: object
    result: object
    restarted: bool
    metrics: dict = field(default_factory=dict)


class StartError(RuntimeError):
    """The ventricle could not be started on this frame (tried again on the next)."""


class LiveTracker:
    """Track frames one at a time, as they arrive.

    Parameters
    ----------
    apex, base, annulus, landmarks
        As :func:`spheroseg.track` (world LPS mm); neither apex nor base: the
        ventricle is located in the first frame (and in the next ones, until
        it is found).  After a change of geometry the tracking starts again
        from the points, or by locating the ventricle where they fail.
    iterations_per_frame, follow_base, check, myocardium, rv_insertion, epicardium_options, **options
        As :func:`spheroseg.track`.
    max_frames : int
        Frames the volume curve holds (:class:`VolumeCurve`).
    """

    def __init__(self, *, apex=None, base=None, annulus=None, landmarks=None, iterations_per_frame: int = 20,
                 follow_base: bool = True, check: bool = True, myocardium: bool = False, rv_insertion=None,
                 epicardium_options: dict | None = None, max_frames: int = 600, **options):
        from ...descent.options import SegmentOptions

        SegmentOptions(**options)  # bad options: an error now, not at the first frame
        if not (isinstance(iterations_per_frame, (int, np.integer)) and iterations_per_frame >= 1):
            raise ValueError(f"iterations_per_frame must be a positive integer, got {iterations_per_frame!r}")
        self.points = dict(apex=apex, base=base, annulus=annulus)
        self.landmarks = landmarks
        self.iterations_per_frame = int(iterations_per_frame)
        self.follow_base = follow_base
        self.check = check
        self.myocardium = myocardium
        self.rv_insertion = rv_insertion
        self.epicardium_options = dict(epicardium_options or {})
        self.options = options
        self.curve = VolumeCurve(max_frames=max_frames)
        self.tracker = None
        self.grid = None
        self._previous = None
        self._started = False

    def restart(self) -> None:
        """Start again from the points (or locating) at the next frame."""
        self.tracker = self.grid = self._previous = None
        self.curve.clear()

    def _start(self, volume):
        from ...tracking.locate import initialise
        from ...tracking.segment import add_checks
        from ...tracking.tracker import Tracker

        given = any(v is not None for v in self.points.values())
        # the points were given for the first geometry: on another, where they fail, the ventricle is located
        starts = [self.points] + ([dict(apex=None, base=None, annulus=None)] if given and self._started else [])
        for k, points in enumerate(starts):
            try:
                apex, base, initialisation, located = initialise(volume, points["apex"], points["base"],
                                                                 annulus=points["annulus"], check=self.check)
                tracker = Tracker(volume, apex, base, annulus=points["annulus"],
                                  landmarks=self.landmarks if points is self.points else None, **self.options)
                break
            except (ValueError, RuntimeError) as exc:  # NoVentricleError is a ValueError; points outside the image
                if k == len(starts) - 1:
                    raise StartError(f"cannot start on this frame: {' '.join(str(exc).split())}") from None
        result = tracker.run()
        add_checks(result, volume, initialisation, located)
        self.tracker, self.grid, self._started = tracker, volume.grid, True
        return result

    def process(self, volume, *, index: int, timestamp: float, frame_rate: float | None = None) -> LiveFrame:
        """Track ``volume``, the stream's frame ``index`` stamped
        ``timestamp`` (s); ``frame_rate`` (frames a second) for the cycle.
        Raises :class:`StartError` when the ventricle cannot be started."""
        from ...tracking.epicardium import add_epicardium

        restarted = self.tracker is not None and not same_geometry(volume.grid, self.grid)
        if restarted:
            self.restart()
        if self.tracker is None:
            result = self._start(volume)
        else:
            result = self.tracker.next_frame(volume, max_iterations=self.iterations_per_frame,
                                             follow_base=self.follow_base)
        if self.myocardium:
            add_epicardium(result, volume, rv_insertion=self.rv_insertion, previous=self._previous,
                           **self.epicardium_options)
        self._previous = result
        self.curve.add(timestamp, index, result.volume_ml)
        quality = result.quality or {}
        metrics = {"index": int(index), "timestamp": float(timestamp), "volume_ml": result.volume_ml,
                   **self.curve.last_cycle(frame_rate), "poor": bool(quality.get("poor", False)),
                   "warnings": list(quality.get("warnings", [])), "restarted": restarted,
                   "iterations": result.iterations}
        if self.myocardium:
            metrics["lv_mass_g"] = result.lv_mass_g
        return LiveFrame(int(index), float(timestamp), volume, result, restarted, metrics)
