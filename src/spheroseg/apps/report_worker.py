"""Draw the PNG report in a second process started with the command.

Importing matplotlib and drawing a report take about as long as the
command's own work of loading the numerical path and segmenting on one core
(docs/benchmarks.md).  When a core is free, :class:`ReportWorker` starts
a process that imports matplotlib at once and later draws the report
(:func:`spheroseg.report.save_parts`) from the few arrays it shows, so
neither lies on the command's path.  On Linux the process is forked as the
command starts (before SciPy and the kernels are loaded), so it needs no imports but
matplotlib's; elsewhere it is spawned.  Without a free core, or when the
process cannot start or dies, the report is drawn in this process.
"""

from __future__ import annotations

import multiprocessing
import os
import pickle
import signal
import sys

from .._compiled._runtime import die_with_parent, idle_cores
from ..io.report import save_parts

__all__ = ["ReportWorker"]


def _serve(connection, parent: int | None = None) -> None:
    """The worker: import what drawing needs, then draw what is sent."""
    if parent is not None:  # it dies with the command, kill -9 included
        die_with_parent(parent)
    # Ctrl-C reaches the whole process group: the command stops this process
    # itself, without a traceback from it
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot  # noqa: F401
    import mpl_toolkits.mplot3d  # noqa: F401

    while True:
        try:
            job = connection.recv()
        except EOFError:  # the command ended
            return
        if job is None:
            return
        try:
            save_parts(*job)
            connection.send(None)
        except Exception as exc:  # sent back, raised by the command
            try:
                connection.send(pickle.loads(pickle.dumps(exc)))
            except Exception:
                connection.send(RuntimeError(f"report: {exc}"))


def _free_core() -> bool:
    """Whether a second process would find a core to itself: one besides
    this process's, with no other process's work on it now."""
    return idle_cores() >= 2


class ReportWorker:
    """A process that draws reports, or this one when that does not pay.

    Use as a context manager around the command: :meth:`save` starts a
    report and returns a function that waits for it (and raises what drawing
    raised).  Leaving the context stops the process; after an error, at once.

    Parameters
    ----------
    parallel : bool, optional
        Draw in a second process; default: when a core is free (two or more
        cores, a load average under ``cores - 0.5``).
    """

    def __init__(self, *, parallel: bool | None = None) -> None:
        self._process = self._connection = None
        if parallel is None:
            parallel = _free_core()
        if parallel:
            context = multiprocessing.get_context("fork" if sys.platform == "linux" else "spawn")
            self._connection, child = context.Pipe()
            try:
                self._process = context.Process(target=_serve, args=(child, os.getpid()), daemon=True,
                                                name="spheroseg-report")
                self._process.start()
            except OSError:  # pragma: no cover - no processes here
                self._process = self._connection = None
            child.close()

    @property
    def parallel(self) -> bool:
        """Whether reports are drawn in the second process."""
        return self._process is not None

    def save(self, path, parts: dict):
        """Start writing the report of ``parts`` (:func:`spheroseg.report.report_parts`)
        to ``path``; returns the function that waits for it."""
        if self._process is not None:
            try:
                self._connection.send((path, parts))
                return lambda: self._wait(path, parts)
            except (OSError, ValueError):  # the process is gone
                self._stop(now=True)
        return lambda: save_parts(path, parts)

    def _wait(self, path, parts) -> None:
        try:
            failure = self._connection.recv()
        except (EOFError, OSError):  # the process died: draw here
            self._stop(now=True)
            save_parts(path, parts)
            return
        if failure is not None:
            raise failure

    def _stop(self, *, now: bool) -> None:
        process, self._process = self._process, None
        if process is None:
            return
        if now:
            process.terminate()
        else:
            try:
                self._connection.send(None)
            except (OSError, ValueError):
                process.terminate()
        process.join(timeout=10)
        self._connection.close()

    def close(self) -> None:
        """Stop the process (it finishes the report it is drawing)."""
        self._stop(now=False)

    def __enter__(self) -> ReportWorker:
        return self

    def __exit__(self, kind, value, traceback) -> None:
        self._stop(now=kind is not None)
