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

Test hook (for the test suite only): the environment variable
``SPHEROSEG_BATCH_TEST_HOOK="ID=exit,ID2=sleep:SECONDS"`` makes a worker
die abruptly (SIGKILL, as a crash) on study ``ID``, or spend ``SECONDS`` (in Python, so
that a timeout interrupts it) before study ``ID2``.
"""

from __future__ import annotations

import csv
import ctypes
import hashlib
import json
import os
import re
import shutil
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Executor, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass
from io import StringIO
from pathlib import Path

import numpy as np

__all__ = ["Study", "StudyOutcome", "StudyTimeout", "ManifestError", "read_manifest", "segment_many", "run_study",
           "study_checksum", "summary_row", "write_summary", "select_shard", "warm_up", "SUMMARY_FIELDS"]

#: columns of ``summary.json`` / ``summary.csv``
SUMMARY_FIELDS = ("id", "status", "kind", "volume_ml", "edv_ml", "esv_ml", "ef", "iterations", "descent_status",
                  "quality", "seconds", "error")
#: keys a manifest entry may have
MANIFEST_KEYS = ("id", "image", "apex", "base", "annulus", "landmarks", "points", "spacing", "track")
#: options of a run beside :class:`spheroseg.SegmentOptions`'s (see :func:`run_study`)
RUN_OPTIONS = ("iterations_per_frame", "no_data_value", "mask_suffix", "stl", "report")
#: a worker stuck past its timeout exits after this many more seconds (or half the timeout, if longer)
HARD_TIMEOUT_GRACE = 10.0
TEST_HOOK_VARIABLE = "SPHEROSEG_BATCH_TEST_HOOK"

_SAFE_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")


class ManifestError(ValueError):
    """A manifest that cannot be run (nothing was started)."""


class StudyTimeout(Exception):
    """Raised in a worker's thread when its study exceeds the timeout."""


@dataclass(frozen=True)
class Study:
    """One study of a cohort (paths absolute; points world mm, LPS).

    Attributes
    ----------
    id : str
        Unique; the name of its output folder.
    image : str
        A volume or a sequence (file, folder of frames, glob, DICOM folder).
    apex, base : tuple of 3 floats, optional
        Needed unless ``points`` gives them (``base`` or ``annulus``).
    annulus : tuple of points
        Three or more points of the mitral annulus, instead of ``base``.
    landmarks : tuple of points
    points : str, optional
        A 3D Slicer markups file with points labelled apex, base, landmark...
    spacing : tuple of 3 floats, optional
        Voxel spacing, mm (needed for ``.npy``).
    track : bool, optional
        Track a sequence (True) or segment one volume (False); None: track a
        4D input.
    """

    id: str
    image: str
    apex: tuple | None = None
    base: tuple | None = None
    annulus: tuple = ()
    landmarks: tuple = ()
    points: str | None = None
    spacing: tuple | None = None
    track: bool | None = None

    def as_entry(self) -> dict:
        """The study as a manifest entry (JSON values)."""
        return {k: (list(map(list, v)) if k in ("landmarks", "annulus") else list(v) if isinstance(v, tuple) else v)
                for k, v in asdict(self).items()}


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


# -- manifests ---------------------------------------------------------------


def _numbers(value, count: int | None, what: str) -> tuple:
    if isinstance(value, str):
        value = value.replace(",", " ").split()
    try:
        numbers = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be numbers, got {value!r}") from None
    if (count is not None and len(numbers) != count) or not all(np.isfinite(numbers)):
        raise ValueError(f"{what} must be {count} finite numbers (x y z), got {value!r}")
    return numbers


def _point_list(value, what: str) -> tuple:
    if value in (None, ""):
        return ()
    if isinstance(value, str):
        value = [part for part in value.split(";") if part.strip()]
    if not isinstance(value, (list, tuple)):
        raise ValueError(f"{what} must be a list of points, got {value!r}")
    return tuple(_numbers(p, 3, f"each point of {what}") for p in value)


def _flag(value) -> bool | None:
    if value is None or isinstance(value, bool):
        return value
    text = str(value).strip().lower()
    if text == "":
        return None
    if text in ("true", "yes", "1"):
        return True
    if text in ("false", "no", "0"):
        return False
    raise ValueError(f"track must be true or false, got {value!r}")


def _study(entry, folder: Path) -> Study:
    if not isinstance(entry, dict):
        raise ValueError(f"a study must be an object with keys {', '.join(MANIFEST_KEYS)}, got {type(entry).__name__}")
    unknown = sorted(set(entry) - set(MANIFEST_KEYS))
    if unknown:
        raise ValueError(f"unknown key(s) {', '.join(unknown)} (known: {', '.join(MANIFEST_KEYS)})")
    ident = str(entry.get("id") or "").strip()
    if not _SAFE_ID.fullmatch(ident):
        raise ValueError(f"id must be a safe folder name (letters, digits, . _ -; not starting with . _ -), got {ident!r}")
    image = str(entry.get("image") or "").strip()
    if not image:
        raise ValueError("no image")
    points = str(entry.get("points") or "").strip() or None
    apex = None if entry.get("apex") in (None, "") else _numbers(entry["apex"], 3, "apex")
    base = None if entry.get("base") in (None, "") else _numbers(entry["base"], 3, "base")
    annulus = _point_list(entry.get("annulus"), "annulus")
    if annulus and len(annulus) < 3:
        raise ValueError(f"annulus needs 3 or more points, got {len(annulus)}")
    if points is None and (base is not None or annulus) and apex is None:
        raise ValueError("give apex and base (x y z, mm) or apex and annulus, or points (a markups file), or none "
                         "(the ventricle is located)")
    if points is None and apex is not None and base is None and not annulus:
        raise ValueError("give apex and base (x y z, mm) or apex and annulus, not the apex alone")
    spacing = None if entry.get("spacing") in (None, "") else _numbers(entry["spacing"], 3, "spacing")
    if spacing is not None and min(spacing) <= 0:
        raise ValueError(f"spacing must be positive, got {spacing}")
    resolve = lambda p: str(p if Path(p).is_absolute() else folder / p)  # noqa: E731
    return Study(id=ident, image=resolve(image), apex=apex, base=base, annulus=annulus,
                 landmarks=_point_list(entry.get("landmarks"), "landmarks"),
                 points=None if points is None else resolve(points), spacing=spacing, track=_flag(entry.get("track")))


def read_manifest(path: str | os.PathLike) -> list[Study]:
    """Read the studies of a JSON or CSV manifest.

    JSON: a list of objects.  CSV: a header row and one row a study, a point
    written ``x y z``, landmarks ``x y z; x y z``.  Keys: ``id`` (unique, a
    safe folder name), ``image``, ``apex`` and ``base`` (mm, LPS), optional
    ``landmarks``, ``points`` (a markups file instead of apex/base),
    ``spacing``, ``track`` and ``annulus`` (3 or more points of the mitral
    annulus instead of ``base``).  Relative paths are relative to the manifest's
    folder.  Input files are not opened here (a missing image fails its
    study, not the manifest).

    Raises
    ------
    ManifestError
        With the file, the entry and the reason.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise ManifestError(f"{path}: cannot read manifest ({exc.strerror})") from None
    except UnicodeDecodeError:
        raise ManifestError(f"{path}: a manifest must be UTF-8 text (JSON or CSV)") from None
    if path.suffix.lower() == ".json":
        try:
            entries = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ManifestError(f"{path}: not JSON ({exc.msg}, line {exc.lineno})") from None
        if not isinstance(entries, list):
            raise ManifestError(f"{path}: a JSON manifest must be a list of studies")
        where = lambda k: f"study {k + 1}"  # noqa: E731
    elif path.suffix.lower() == ".csv":
        reader = csv.DictReader(StringIO(text))
        if reader.fieldnames is None:
            raise ManifestError(f"{path}: empty CSV manifest (expected a header: {','.join(MANIFEST_KEYS)})")
        entries = [{k.strip(): (v or "").strip() for k, v in row.items() if k is not None and (v or "").strip()}
                   for row in reader]
        where = lambda k: f"row {k + 2}"  # noqa: E731
    else:
        raise ManifestError(f"{path}: a manifest is .json or .csv, got {path.suffix or 'no suffix'}")
    if not entries:
        raise ManifestError(f"{path}: no studies")
    studies, seen = [], set()
    for k, entry in enumerate(entries):
        try:
            study = _study(entry, path.parent.resolve())
        except ValueError as exc:
            name = entry.get("id") if isinstance(entry, dict) else None
            raise ManifestError(f"{path}: {where(k)}{f' ({name})' if name else ''}: {exc}") from None
        if study.id.lower() in seen:
            raise ManifestError(f"{path}: {where(k)}: id {study.id!r} appears twice")
        seen.add(study.id.lower())
        studies.append(study)
    return studies


def select_shard(studies: list, shard: tuple[int, int] | None) -> list:
    """Studies ``i - 1, i - 1 + n, ...`` of shard ``(i, n)`` (1 <= i <= n); all if None."""
    if shard is None:
        return list(studies)
    i, n = shard
    if not (1 <= i <= n):
        raise ValueError(f"shard must be I/N with 1 <= I <= N, got {i}/{n}")
    return list(studies[i - 1::n])


# -- checksums ---------------------------------------------------------------


def _header_data_file(path: Path) -> Path | None:
    """The data file a MetaImage (.mhd) or detached NRRD (.nhdr) header names."""
    key = {".mhd": "elementdatafile", ".nhdr": "data file"}.get(path.suffix.lower())
    if key is None:
        return None
    try:
        with open(path, encoding="latin-1") as handle:
            for line in handle:
                name, sep, value = line.partition("=" if key == "elementdatafile" else ":")
                if sep and name.strip().lower() == key:
                    value = value.strip()
                    return None if value.upper() in ("LOCAL", "") else path.parent / value
    except OSError:
        return None
    return None


def _input_files(image: str) -> list[Path]:
    if any(ch in image for ch in "*?["):
        import glob

        files = [Path(f) for f in sorted(glob.glob(image))]
    elif Path(image).is_dir():
        files = sorted(p for p in Path(image).rglob("*") if p.is_file())
    else:
        files = [Path(image)]
    for f in list(files):
        data = _header_data_file(f)
        if data is not None and data not in files:
            files.append(data)
    return files


def study_checksum(study: Study, options: dict) -> str:
    """SHA-256 of the study's entry, the options and the bytes of every input
    file (an image's data file, a folder's files, the markups); a missing
    file counts as missing, so the study runs and fails with its reason.
    The thread count is left out: it changes no result."""
    digest = hashlib.sha256()
    options = {k: v for k, v in options.items() if k != "threads"}
    digest.update(json.dumps({"study": study.as_entry(), "options": options}, sort_keys=True).encode())
    for path in _input_files(study.image) + ([Path(study.points)] if study.points else []):
        digest.update(f"\0{path.name}\0".encode())
        try:
            with open(path, "rb") as handle:
                for block in iter(lambda: handle.read(1 << 20), b""):
                    digest.update(block)
        except OSError:
            digest.update(b"\0missing\0")
    return digest.hexdigest()


# -- one study, in a worker --------------------------------------------------


def _die() -> None:
    """End this process at once, as a crash would (no cleanup, no exception)."""
    import signal

    os.kill(os.getpid(), signal.SIGKILL)


def _test_hook(study_id: str) -> None:
    spec = os.environ.get(TEST_HOOK_VARIABLE)
    if not spec:
        return
    for item in spec.split(","):
        name, _, action = item.partition("=")
        if name.strip() != study_id:
            continue
        if action == "exit":
            _die()
        if action.startswith("sleep:"):  # in small steps, as a long computation: a timeout interrupts it
            end = time.monotonic() + float(action.split(":", 1)[1])
            while time.monotonic() < end:
                time.sleep(0.02)


class _Deadline:
    """Raise :class:`StudyTimeout` in this thread after ``seconds``; if the
    thread is still busy ``grace`` seconds later (stuck in compiled code),
    end the process so that the pool or the cluster replaces the worker."""

    def __init__(self, seconds: float | None):
        self.seconds = seconds
        self.thread_id = threading.get_ident()
        self.done = threading.Event()
        self.timers: list[threading.Timer] = []

    def _raise(self):
        if not self.done.is_set():
            ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(self.thread_id), ctypes.py_object(StudyTimeout))

    def _exit(self):
        if not self.done.is_set():
            _die()

    def __enter__(self):
        if self.seconds is not None:
            grace = max(HARD_TIMEOUT_GRACE, 0.5 * self.seconds)
            self.timers = [threading.Timer(self.seconds, self._raise), threading.Timer(self.seconds + grace, self._exit)]
            for timer in self.timers:
                timer.daemon = True
                timer.start()
        return self

    def __exit__(self, *exc):
        self.done.set()
        for timer in self.timers:
            timer.cancel()
            timer.join()
        if self.timers:  # a StudyTimeout sent just as the study ended must not land after it
            ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(self.thread_id), None)
        return False


def _one_line(exc: BaseException) -> str:
    text = re.sub(r"\(0x[0-9a-fA-F]+\)", "", " ".join(str(exc).split()))  # ITK's object addresses: not reproducible
    expected = isinstance(exc, (ValueError, OSError))  # the loaders' and the validation's messages say it all
    return text if text and expected else f"{type(exc).__name__}: {text}".rstrip(": ")


def _is_sequence(image: str) -> bool:
    """Whether an input is 3D+t (folder of frames, glob, 4D or multi-component image, 4D .npy)."""
    from .io import IMAGE_SUFFIXES, image_format

    path = Path(image)
    if any(ch in image for ch in "*?["):
        return True
    if path.is_dir():
        return any(image_format(p) in IMAGE_SUFFIXES for p in path.iterdir())
    try:
        if image_format(path) == ".npy":
            return np.load(path, mmap_mode="r", allow_pickle=False).ndim == 4
        import SimpleITK as sitk

        reader = sitk.ImageFileReader()
        reader.SetFileName(str(path))
        reader.ReadImageInformation()
        return reader.GetDimension() == 4 or reader.GetNumberOfComponents() > 1
    except (OSError, ValueError, RuntimeError):
        return False  # the loader reports why


def _points(study: Study):
    """apex, base (or None), landmarks (or None), annulus (or None), as the CLI reads them."""
    apex, base, landmarks, annulus = study.apex, study.base, list(study.landmarks), list(study.annulus)
    if study.points:
        from .io import read_markups

        marks = read_markups(study.points)
        apex = marks["apex"] if apex is None else apex
        base = marks["base"] if base is None else base
        landmarks += [tuple(p) for p in marks["landmarks"]]
        annulus = annulus or [tuple(p) for p in marks.get("annulus", [])]
    as_array = lambda points: np.array(points, dtype=float) if points else None  # noqa: E731
    if apex is None and base is None and not annulus and not study.points:
        return None, None, as_array(landmarks), None  # the ventricle is located
    if apex is None or (base is None and not annulus):
        raise ValueError(f"{study.points}: no points labelled apex and base (or annulus)")
    return (np.asarray(apex, float), None if base is None else np.asarray(base, float), as_array(landmarks),
            as_array(annulus))


def _install(tmp: Path, final: Path) -> None:
    """Rename the complete folder ``tmp`` to ``final`` (replacing an older one)."""
    old = None
    if final.exists():
        old = final.parent / f".{final.name}.old-{uuid.uuid4().hex[:8]}"
        os.replace(final, old)
    os.replace(tmp, final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def summary_row(results: dict) -> dict:
    """A study's summary line from its ``results.json`` content."""
    tracked = "edv_ml" in results
    iterations = results.get("iterations")
    seconds = results.get("seconds", {})
    return {
        "id": results.get("id"), "status": "ok", "kind": "track" if tracked else "segment",
        "volume_ml": None if tracked else results.get("volume_ml"),
        "edv_ml": results.get("edv_ml"), "esv_ml": results.get("esv_ml"), "ef": results.get("ef_percent"),
        "iterations": int(np.sum(iterations)) if iterations is not None else None,
        # why the descent stopped (0 converged, 1 iteration cap, ...), when the result records it
        "descent_status": results.get("status"), "quality": results.get("quality"),
        "seconds": float(seconds.get("load", 0.0) + np.sum(seconds.get("segment", 0.0))),
        "error": None,
    }


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
    from .io import load, load_sequence
    from .outputs import default_mask_suffix, write_segmentation_outputs, write_tracking_outputs
    from .segment import segment, track

    options = dict(options or {})
    no_data = options.pop("no_data_value", "auto")
    suffix = options.pop("mask_suffix", None) or default_mask_suffix(study.image)
    writer = {"stl": options.pop("stl", False), "report": options.pop("report", True)}
    per_frame = options.pop("iterations_per_frame", 20)
    out = Path(out)
    started = time.perf_counter()
    tmp = out / f".{study.id}.partial-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    try:
        with _Deadline(timeout):
            _test_hook(study.id)
            apex, base, landmarks, annulus = _points(study)
            sequence = _is_sequence(study.image) if study.track is None else study.track
            common = dict(source=study.image, apex=apex, base=base, annulus=annulus, landmarks=landmarks,
                          mask_suffix=suffix, extra={"id": study.id, "checksum": checksum, "study": study.as_entry(),
                                 "options": {**options, "iterations_per_frame": per_frame, "no_data_value": no_data,
                                             "mask_suffix": suffix, **writer}}, **writer)
            t0 = time.perf_counter()
            if sequence:
                volumes = load_sequence(study.image, spacing=study.spacing, no_data_value=no_data)
                t_load = time.perf_counter() - t0
                result = track(volumes, apex, base, annulus=annulus, landmarks=landmarks,
                               iterations_per_frame=per_frame, **options)
                written = write_tracking_outputs(tmp, volumes, result, seconds={"load": t_load}, **common)
            else:
                volume = load(study.image, spacing=study.spacing, no_data_value=no_data)
                t_load = time.perf_counter() - t0
                result = segment(volume, apex, base, annulus=annulus, landmarks=landmarks, **options)
                written = write_segmentation_outputs(tmp, volume, result, seconds={"load": t_load}, **common)
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
    from .phantom import make_phantom
    from .segment import segment

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


def _pool_worker_init(threads: int | None) -> None:
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's: running studies finish, then it stops
    if threads is not None:
        try:
            import numba
        except ImportError:
            pass
        else:  # this (main) thread runs the studies; a study's own threads option still applies
            numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    warm_up()


def _local_pool(workers: int) -> ProcessPoolExecutor:
    import multiprocessing

    # spawn: the parent holds threads (progress bar, timers), which fork must not copy;
    # several workers share the cores: one kernel thread each, or they only contend
    return ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_pool_worker_init, initargs=(1 if workers > 1 else None,))


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


def _as_study(item, folder: Path) -> Study:
    return item if isinstance(item, Study) else _study(item, folder)


def segment_many(studies: Iterable, *, out: str | os.PathLike, executor: Executor | None = None,
                 workers: int | None = None, timeout: float | None = None,
                 options: dict | None = None) -> Iterator[StudyOutcome]:
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
        the compiled kernels on one thread (numba's ``set_num_threads(1)``;
        the option ``threads`` overrides it), so that the workers do not
        contend for the cores; a single worker uses all of them.  A Dask
        cluster's workers do not get this: give them ``NUMBA_NUM_THREADS=1``
        in their environment, or ``threads=1`` in ``options``.
    timeout : float, optional
        Seconds a study may take; over it the study fails.
    options : dict, optional
        As :func:`run_study`.

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
    from .options import SegmentOptions

    studies = [_as_study(s, Path.cwd()) for s in studies]
    ids = [s.id.lower() for s in studies]
    if len(set(ids)) != len(ids):
        raise ValueError("study ids must be unique")
    if timeout is not None and not (isinstance(timeout, (int, float)) and timeout > 0):
        raise ValueError(f"timeout must be positive seconds, got {timeout!r}")
    if workers is not None and not (isinstance(workers, int) and workers >= 1):
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    options = dict(options or {})
    unknown = sorted(set(options) - set(SegmentOptions.names()) - set(RUN_OPTIONS))
    if unknown:
        raise ValueError(f"unknown option(s) {', '.join(unknown)}")
    SegmentOptions(**{k: v for k, v in options.items() if k not in RUN_OPTIONS})  # raises on a bad value
    return _outcomes(studies, Path(out), executor, workers, timeout, options)


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


def write_summary(out: str | os.PathLike, rows: list[dict], *, name: str = "summary") -> tuple[Path, Path]:
    """Write ``out/<name>.json`` (a list of rows) and ``out/<name>.csv``
    (``quality`` as JSON text), each atomically."""
    from .io import write_atomically
    from .outputs import write_json

    out = Path(out)
    rows = [{k: row.get(k) for k in SUMMARY_FIELDS} for row in rows]
    write_json(out / f"{name}.json", rows)
    text = StringIO()
    writer = csv.DictWriter(text, fieldnames=SUMMARY_FIELDS, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: ("" if v is None else json.dumps(v) if isinstance(v, (dict, list)) else v)
                         for k, v in row.items()})
    write_atomically(out / f"{name}.csv", lambda tmp: tmp.write_text(text.getvalue()))
    return out / f"{name}.json", out / f"{name}.csv"
