"""Cohorts: many studies segmented or tracked on a process pool or a Dask
cluster, resumable, one bad study never stopping the rest.

A *manifest* lists the studies (:func:`read_manifest`); :func:`segment_many`
runs them, each in a worker that reads its own inputs (paths travel, not
arrays) and writes the ``segment``/``track`` outputs (:mod:`spheroseg.outputs`)
into a temporary folder ``DIR/.<id>.partial-*`` renamed ``DIR/<id>`` when
complete.  ``DIR/<id>/results.json`` records a checksum of the study's input
files and options (:func:`study_checksum`); a study whose checksum matches is
skipped, its files untouched.

Failures are per study: an exception in the worker, a study over its
``timeout`` (a :class:`StudyTimeout` raised in the worker's thread; a worker
stuck in compiled code past the timeout plus a grace period exits and is
replaced), or a worker that dies (the local pool is re-created; each study
in flight when it broke is run again alone, so the one that kills its worker
is the one reported).

This module supervises the processes and runs a study; the manifest is
:mod:`spheroseg.manifest`, the checksums and summaries
:mod:`spheroseg.records` (their names are importable from here too).
"""

from __future__ import annotations

import ctypes
import json
import math
import os
import re
import shutil
import sys
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Executor, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .manifest import MANIFEST_KEYS, ManifestError, Study, as_study, read_manifest, select_shard  # noqa: F401
from .records import SUMMARY_FIELDS, study_checksum, summary_row, write_summary  # the names batch had

__all__ = ["Study", "StudyOutcome", "StudyTimeout", "ManifestError", "read_manifest", "segment_many", "run_study",
           "study_checksum", "summary_row", "write_summary", "select_shard", "warm_up", "SUMMARY_FIELDS"]

#: options of a run beside :class:`spheroseg.SegmentOptions`'s (see :func:`run_study`)
RUN_OPTIONS = ("iterations_per_frame", "no_data_value", "mask_suffix", "stl", "report")
#: a worker stuck past its timeout exits after this many more seconds (or half the timeout, if longer)
HARD_TIMEOUT_GRACE = 10.0
#: the longest finite timeout, s (a year; the system's timers take no more than ~292 years)
MAX_TIMEOUT = 365 * 86400.0


class StudyTimeout(Exception):
    """Raised in a worker's thread when its study exceeds the timeout."""


@dataclass(frozen=True)
class StudyOutcome:
    """What :func:`segment_many` yields for each study.

    Attributes
    ----------
    row : dict
        The study's line of the summary (:data:`SUMMARY_FIELDS`).
    skipped : bool
        Already complete with the same checksum: nothing was run.
    """

    row: dict
    skipped: bool = False

    @property
    def id(self) -> str:
        return self.row["id"]

    @property
    def status(self) -> str:
        return self.row["status"]


# -- one study, in a worker --------------------------------------------------


def _die() -> None:
    """End this process at once, as a crash would (no cleanup, no exception)."""
    import signal

    os.kill(os.getpid(), signal.SIGKILL)


def _importing(frame) -> bool:
    """Whether a thread whose innermost frame is ``frame`` is importing a module."""
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib"):
            return True
        frame = frame.f_back
    return False


class _Deadline:
    """Raise :class:`StudyTimeout` in this thread after ``seconds``; if the
    thread is still busy ``grace`` seconds later (stuck in compiled code),
    end the process so that the pool or the cluster replaces the worker.

    Use ``start()`` inside a ``try`` whose ``finally`` calls ``stop()``:
    the exception may arrive at any line, even within ``start`` (a timeout
    of a millisecond), and ``stop`` always ends the watch.  It is held back
    while the thread imports a module: raised there, it would leave a
    half-imported module (``matplotlib`` without its attributes) that fails
    every later study of the worker.
    """

    def __init__(self, seconds: float | None):
        self.seconds = seconds
        self.thread_id = threading.get_ident()
        self.done = threading.Event()
        self.lock = threading.Lock()
        self.watcher: threading.Thread | None = None

    def _watch(self):
        if self.done.wait(self.seconds):
            return
        while not self.done.is_set() and _importing(sys._current_frames().get(self.thread_id)):
            self.done.wait(0.01)
        with self.lock:
            if self.done.is_set():
                return
            ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(self.thread_id), ctypes.py_object(StudyTimeout))
        if not self.done.wait(max(HARD_TIMEOUT_GRACE, 0.5 * self.seconds)):
            _die()

    def start(self) -> None:
        if self.seconds is not None:
            self.watcher = threading.Thread(target=self._watch, daemon=True, name="spheroseg-deadline")
            self.watcher.start()

    def stop(self) -> None:
        """End the watch; no StudyTimeout arrives after this returns (one
        that arrives while it runs is raised once it is done)."""
        late = False
        while True:
            try:
                with self.lock:
                    self.done.set()
                break
            except StudyTimeout:
                late = True
        if self.watcher is not None:
            try:
                ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(self.thread_id), None)
                self.watcher.join()
            except StudyTimeout:  # sent just before the lock was taken
                late = True
                self.watcher.join()
        if late:
            raise StudyTimeout


def _one_line(exc: BaseException) -> str:
    text = re.sub(r"\(0x[0-9a-fA-F]+\)", "", " ".join(str(exc).split()))  # ITK's object addresses: not reproducible
    expected = isinstance(exc, (ValueError, OSError))  # the loaders' and the validation's messages say it all
    return text if text and expected else f"{type(exc).__name__}: {text}".rstrip(": ")


def _is_sequence(study: Study) -> bool:
    """Whether a study's input is 3D+t (a pattern, a folder of frames, a 4D
    or multi-component image, a 4D .npy)."""
    from ..io import IMAGE_SUFFIXES, image_format, is_sequence_file

    path = Path(study.image)
    if study.glob:
        return True
    if path.is_dir():
        return any(image_format(p) in IMAGE_SUFFIXES for p in path.iterdir())
    return is_sequence_file(path)


def _points(study: Study):
    """apex, base (or None), landmarks (or None), annulus (or None), as the CLI reads them."""
    from ..io.markups import points_with_markups

    apex, base, landmarks, annulus = points_with_markups(
        study.points, apex=study.apex, base=study.base, landmarks=[np.asarray(p, float) for p in study.landmarks],
        annulus=[np.asarray(p, float) for p in study.annulus])
    as_array = lambda points: np.array(points, dtype=float) if len(points) else None  # noqa: E731
    if apex is None and base is None and not annulus:
        return None, None, as_array(landmarks), None  # the ventricle is located
    if apex is None or (base is None and not annulus):
        raise ValueError("give the apex and the base (or the annulus)")
    return (np.asarray(apex, float), None if base is None else np.asarray(base, float), as_array(landmarks),
            as_array(annulus))


def _install(tmp: Path, final: Path) -> None:
    """Rename the complete folder ``tmp`` to ``final`` (replacing an older
    one all or nothing: :func:`spheroseg.atomic.replace_folder`)."""
    from ..io.atomic import replace_folder

    replace_folder(tmp, final)


def _failed_row(study_id: str, error: str, seconds: float | None = None) -> dict:
    row = dict.fromkeys(SUMMARY_FIELDS)
    row.update(id=study_id, status="failed", error=error, seconds=seconds)
    return row


def run_study(study: Study, out: str | os.PathLike, *, options: dict | None = None, checksum: str | None = None,
              timeout: float | None = None) -> dict:
    """Segment or track one study into ``out/<id>/``; return its summary row.

    Runs in a worker.  Reads the study's inputs, writes every output into
    ``out/.<id>.partial-*`` and renames it ``out/<id>`` when complete.  Any
    error, or a run over ``timeout`` seconds, gives a ``failed`` row with a
    one-line reason (the partial folder removed).

    Parameters
    ----------
    study : Study
    out : path
        The cohort's output folder.
    options : dict, optional
        :func:`spheroseg.segment` options, plus ``iterations_per_frame``,
        ``no_data_value``, ``mask_suffix`` (None: the input's format),
        ``stl`` and ``report``.
    checksum : str, optional
        Recorded in ``results.json`` (:func:`study_checksum`).
    timeout : float, optional
        Seconds.
    """
    from ..io import load, load_sequence
    from ..io.outputs import default_mask_suffix, write_segmentation_outputs, write_tracking_outputs
    from ..tracking.segment import segment, track

    options = dict(options or {})
    no_data = options.pop("no_data_value", "auto")
    suffix = options.pop("mask_suffix", None) or default_mask_suffix(study.image)
    writer = {"stl": options.pop("stl", False), "report": options.pop("report", True)}
    per_frame = options.pop("iterations_per_frame", 20)
    out = Path(out)
    started = time.perf_counter()
    tmp = out / f".{study.id}.partial-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    deadline = _Deadline(timeout)
    try:
        try:
            deadline.start()
            apex, base, landmarks, annulus = _points(study)
            sequence = _is_sequence(study) if study.track is None else study.track
            common = dict(source=study.image, apex=apex, base=base, annulus=annulus, landmarks=landmarks,
                          mask_suffix=suffix, extra={"id": study.id, "checksum": checksum, "study": study.as_entry(),
                                 "options": {**options, "iterations_per_frame": per_frame, "no_data_value": no_data,
                                             "mask_suffix": suffix, **writer}}, **writer)
            t0 = time.perf_counter()
            if sequence:
                volumes = load_sequence(study.image, spacing=study.spacing, no_data_value=no_data, glob=study.glob)
                t_load = time.perf_counter() - t0
                result = track(volumes, apex, base, annulus=annulus, landmarks=landmarks,
                               iterations_per_frame=per_frame, **options)
                written = write_tracking_outputs(tmp, volumes, result, seconds={"load": t_load}, **common)
            else:
                try:
                    volume = load(study.image, spacing=study.spacing, no_data_value=no_data)
                except ValueError as exc:
                    if study.track is False and "3D+t" in str(exc):  # not the CLI's advice: the manifest's key
                        raise ValueError(f"{study.image}: a 3D+t image, and the manifest says track: false; set "
                                         "track to true (or leave it out)") from None
                    raise
                t_load = time.perf_counter() - t0
                result = segment(volume, apex, base, annulus=annulus, landmarks=landmarks, **options)
                written = write_segmentation_outputs(tmp, volume, result, seconds={"load": t_load}, **common)
        finally:
            deadline.stop()
        _install(tmp, out / study.id)
        return summary_row(written)
    except StudyTimeout:
        return _failed_row(study.id, f"timed out after {timeout:g} s", time.perf_counter() - started)
    except Exception as exc:  # one study's failure never stops the cohort
        return _failed_row(study.id, _one_line(exc), time.perf_counter() - started)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def warm_up() -> None:
    """Load the compiled kernels in this process (a tiny segmentation), so
    a worker pays for it once, not on its first study."""
    from ..synthetic.phantom import make_phantom
    from ..tracking.segment import segment

    phantom = make_phantom(seed=0, spacing=4.0)
    segment(phantom.volume, phantom.apex, phantom.base, max_iterations=2, check=False)


# -- many studies ------------------------------------------------------------


def _clean_partials(out: Path, ids: Iterable[str]) -> None:
    ids = set(ids)
    for kind in ("partial", "old"):
        for path in out.glob(f".*.{kind}-*"):
            if path.name[1:].rsplit(f".{kind}-", 1)[0] in ids:
                shutil.rmtree(path, ignore_errors=True)


def _complete(out: Path, study: Study, checksum: str) -> dict | None:
    try:
        results = json.loads((out / study.id / "results.json").read_text())
    except (OSError, ValueError):
        return None
    return results if isinstance(results, dict) and results.get("checksum") == checksum else None


def _pool_worker_init(threads: int | None, parent: int | None = None) -> None:
    import signal

    from .._compiled._runtime import die_with_parent

    if parent is not None:  # a worker dies with the command (kill -9 of it included), not under PID 1
        die_with_parent(parent)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's: running studies finish, then it stops
    if threads is not None:  # this (main) thread runs the studies; a study's own threads option still applies
        from .._compiled._runtime import set_default_threads

        set_default_threads(threads)
    warm_up()


def _local_pool(workers: int) -> ProcessPoolExecutor:
    import multiprocessing

    # spawn: the parent holds threads (progress bar, timers), which fork must not copy;
    # several workers share the cores: one kernel thread each, or they only contend
    return ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_pool_worker_init, initargs=(1 if workers > 1 else None, os.getpid()))


def _crash_message(exc: BaseException) -> str:
    return f"worker process died ({type(exc).__name__}: {' '.join(str(exc).split())[:160]})".replace(": )", ")")


def _run_local(jobs: list, workers: int, call: Callable) -> Iterator[tuple]:
    """Run ``call(study, checksum)`` for each job on a spawned process pool of
    ``workers``; yield ``(study, row)``.  When a worker dies the pool is
    re-created and each study then in flight runs again alone: one that
    breaks its pool alone is failed, the others go on."""
    queue = deque(jobs)
    pool = _local_pool(workers)
    try:
        while True:
            running = {}
            broken = []
            while queue or running:
                while queue and len(running) < workers and not broken:
                    job = queue.popleft()
                    running[pool.submit(call, *job)] = job
                if not running:
                    break
                done, _ = wait(running, return_when=FIRST_COMPLETED)
                for future in done:
                    job = running.pop(future)
                    try:
                        row = future.result()
                    except BrokenProcessPool:
                        broken.append(job)
                        continue
                    except Exception as exc:
                        row = _failed_row(job[0].id, _one_line(exc))
                    yield job[0], row
                if broken and not running:
                    break
            pool.shutdown(wait=True, cancel_futures=True)
            if not broken:
                break
            for job in broken:  # alone, so that a crash names its study
                alone = _local_pool(1)
                try:
                    row = alone.submit(call, *job).result()
                except BrokenProcessPool as exc:
                    row = _failed_row(job[0].id, _crash_message(exc))
                finally:
                    alone.shutdown(wait=True, cancel_futures=True)
                yield job[0], row
            if queue:
                pool = _local_pool(workers)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _run_executor(jobs: list, executor: Executor, call: Callable) -> Iterator[tuple]:
    """Run the jobs on any ``concurrent.futures.Executor``; yield ``(study, row)``
    as they finish.  An error raised by the executor itself (a lost worker,
    Dask's ``KilledWorker``) fails that study only."""
    from concurrent.futures import as_completed

    futures = {executor.submit(call, *job): job for job in jobs}
    try:
        for future in as_completed(futures):
            study = futures[future][0]
            try:
                row = future.result()
            except Exception as exc:
                row = _failed_row(study.id, _crash_message(exc))
            yield study, row
    finally:
        for future in futures:
            future.cancel()


def segment_many(studies: Iterable, *, out: str | os.PathLike, executor: Executor | None = None,
                 workers: int | None = None, timeout: float | None = None,
                 options: dict | None = None, protect=()) -> Iterator[StudyOutcome]:
    """Segment or track many studies; yield each one's outcome as it finishes.

    Parameters
    ----------
    studies : iterable of Study or dict
        Dicts are manifest entries (:func:`read_manifest`; relative paths
        relative to the working folder).
    out : path
        The cohort's folder: ``out/<id>/`` per study.
    executor : concurrent.futures.Executor, optional
        Where the studies run: any executor (e.g. a Dask
        ``client.get_executor()``).  Default: a process pool of ``workers``
        (one per core), each worker loading the compiled kernels once.
    workers : int, optional
        Size of the default pool.  Its workers inherit the environment:
        ``spheroseg batch`` sets ``OMP_NUM_THREADS=1`` (and OpenBLAS's, MKL's)
        unless given, as Dask does for its workers, so that the two give the
        same numbers to the last bit.  With more than one worker each runs
        the compiled kernels on one thread
        (:func:`spheroseg._compiled._runtime.set_default_threads`; the option
        ``threads`` overrides it), so that the workers do not contend for
        the cores; a single worker uses all of them.  A Dask cluster's
        workers do not get this: give them ``threads=1`` in ``options``.
    timeout : float, optional
        Seconds a study may take; over it the study fails.
    options : dict, optional
        As :func:`run_study`.
    protect : paths, optional
        Files besides the studies' inputs that no study folder may replace
        (``spheroseg batch`` gives its manifest).

    Returns
    -------
    iterator of StudyOutcome
        Skipped studies (complete, same checksum) first, then the others in
        the order they finish.  Closing it early (or Ctrl-C) cancels the
        studies not started and lets the running ones finish.

    Examples
    --------
    >>> from dask.distributed import Client                   # doctest: +SKIP
    >>> rows = [o.row for o in segment_many(studies, out="cohort", executor=Client().get_executor())]  # doctest: +SKIP
    """
    from ..descent.options import SegmentOptions

    studies = [as_study(s, Path.cwd()) for s in studies]
    ids = [s.id.lower() for s in studies]
    if len(set(ids)) != len(ids):
        raise ValueError("study ids must be unique")
    if timeout is not None and not (isinstance(timeout, (int, float)) and timeout > 0):
        raise ValueError(f"timeout must be positive seconds, got {timeout!r}")
    if timeout is not None and math.isinf(timeout):
        timeout = None  # no limit
    if timeout is not None and timeout > MAX_TIMEOUT:
        raise ValueError(f"timeout must be at most {MAX_TIMEOUT:g} s (or inf: no limit), got {timeout:g}")
    if workers is not None and not (isinstance(workers, int) and workers >= 1):
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    options = dict(options or {})
    unknown = sorted(set(options) - set(SegmentOptions.names()) - set(RUN_OPTIONS))
    if unknown:
        raise ValueError(f"unknown option(s) {', '.join(unknown)}")
    SegmentOptions(**{k: v for k, v in options.items() if k not in RUN_OPTIONS})  # raises on a bad value
    check_study_folders(studies, Path(out), protect)
    return _outcomes(studies, Path(out), executor, workers, timeout, options)


def check_study_folders(studies, out: Path, protect=()) -> None:
    """Refuse a cohort where a study's folder ``out/<id>`` (replaced whole
    when it runs) is or holds an input of any study, or one of ``protect``
    (an id ``p1.mha`` with ``--out`` the images' folder)."""
    from ..io.atomic import refuse_overwriting_inputs
    from ..io import image_files

    inputs = [Path(p) for p in protect]
    for study in studies:
        inputs += [Path(study.image), *image_files(study.image, glob=study.glob)]
        inputs += [Path(study.points)] if study.points else []
    for study in studies:
        try:
            refuse_overwriting_inputs([out / study.id], inputs, hint="choose another id or --out")
        except ValueError as exc:
            raise ValueError(f"study {study.id}: {exc}") from None


def _outcomes(studies, out: Path, executor, workers, timeout, options) -> Iterator[StudyOutcome]:
    from functools import partial

    out.mkdir(parents=True, exist_ok=True)
    _clean_partials(out, [s.id for s in studies])
    jobs = []
    for study in studies:
        checksum = study_checksum(study, options)
        results = _complete(out, study, checksum)
        if results is None:
            jobs.append((study, checksum))
        else:
            yield StudyOutcome(summary_row(results), skipped=True)
    if not jobs:
        return
    call = partial(_call, out=str(out), options=options, timeout=timeout)
    if executor is None:
        runner = _run_local(jobs, max(1, min(workers or os.cpu_count() or 1, len(jobs))), call)
    else:
        runner = _run_executor(jobs, executor, call)
    try:
        for _, row in runner:
            yield StudyOutcome(row)
    finally:
        runner.close()
        _clean_partials(out, [job[0].id for job in jobs])


def _call(study: Study, checksum: str, *, out: str, options: dict, timeout: float | None) -> dict:
    return run_study(study, out, options=options, checksum=checksum, timeout=timeout)


