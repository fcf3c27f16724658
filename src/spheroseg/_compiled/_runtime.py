"""The compiled kernels' runtime: whether they can run (the package was
built), how many threads their OpenMP loops get, and the lock around their
parallel regions.

Nothing here imports the kernels: ``import spheroseg`` stays light.
"""

from __future__ import annotations

import os
import threading
import time
from contextlib import contextmanager
from typing import Iterator

import numpy as np

__all__ = ["die_with_parent", "PARALLEL_LOCK", "compiled_available", "usable_cores", "idle_cores", "default_threads",
           "set_default_threads", "current_threads", "kernel_thread_count", "kernel_threads", "LOAD_MAX_AGE"]

#: held by a caller of a parallel kernel (the iteration's and the
#: rasteriser's): the kernels release the GIL, and two Python threads (the
#: viewer's worker and its HTTP thread, a mask on save) each opening an
#: OpenMP team of the cores' size would put two threads on every core,
#: where a parallel region waits for its slowest thread
PARALLEL_LOCK = threading.Lock()
# a segmentation or a frame reads the machine's load when the last reading
# is older than this (s): a back-to-back series (a cohort, a sequence)
# need not read it at every frame
LOAD_MAX_AGE = 0.1
_LOAD_SAMPLE = (-np.inf, 1)  # (time.monotonic(), idle cores) of the last reading
_LOCAL = threading.local()  # .threads: kernel_threads' count in this Python thread
_DEFAULT = [None]  # default_threads, once read


def compiled_available() -> bool:
    """Whether the compiled kernels can run: the package was built (its
    extension modules are beside this one), not run from a source tree."""
    from importlib.util import find_spec

    return find_spec("spheroseg._compiled._kernels") is not None


def usable_cores() -> int:
    """Cores this process may run on (its affinity; elsewhere than Linux, the machine's)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        return os.cpu_count() or 1


def idle_cores(*, max_age: float = 0.0) -> int:
    """Cores this process may run on that no other process is using now
    (at least 1).

    The cores of its affinity less the tasks of other processes that are
    running or ready to run at this instant: on Linux the runnable count of
    ``/proc/loadavg`` less this process's own running threads; elsewhere the
    1-minute load average less one (this process).  A sample of an instant:
    a busy process is runnable at almost every one.

    ``max_age`` (s): the last sample when it is at most that old (taking
    one reads this process's threads one by one)."""
    global _LOAD_SAMPLE
    sampled, count = _LOAD_SAMPLE
    now = time.monotonic()
    if now - sampled > max_age:
        count = _sample_idle_cores()
        _LOAD_SAMPLE = (now, count)  # one assignment: atomic for the viewer's threads
    return count


def _sample_idle_cores() -> int:
    cores = usable_cores()
    try:
        with open("/proc/loadavg") as f:
            runnable = int(f.read().split()[3].split("/")[0])
        # this thread is one of them: alone, no other (and no need to read
        # this process's threads)
        others = 0 if runnable <= 1 else runnable - _own_running_threads()
    except (OSError, ValueError, IndexError):  # pragma: no cover - not on Linux
        try:
            others = round(os.getloadavg()[0]) - 1
        except (AttributeError, OSError):
            others = 0
    return max(1, min(cores, cores - others))


def _own_running_threads() -> int:
    """Threads of this process running or ready to run (at least this one)."""
    running = 0
    for task in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{task}/stat") as f:
                stat = f.read()
        except OSError:  # the thread ended meanwhile
            continue
        running += stat[stat.rindex(")") + 2] == "R"  # the state follows the command's name
    return max(running, 1)


def default_threads() -> int:
    """The kernels' thread count outside :func:`kernel_threads`: that of
    :func:`set_default_threads`, else the :func:`usable_cores`
    (``OMP_NUM_THREADS``, which ``spheroseg batch`` sets to 1 for BLAS,
    does not apply)."""
    if _DEFAULT[0] is None:
        _DEFAULT[0] = usable_cores()
    return _DEFAULT[0]


def set_default_threads(threads: int) -> None:
    """Set :func:`default_threads` for the process (a batch worker's one
    thread)."""
    if int(threads) < 1:
        raise ValueError(f"threads must be a positive integer, got {threads!r}")
    _DEFAULT[0] = int(threads)


def current_threads() -> int:
    """The thread count the kernels run on now, in this Python thread:
    :func:`kernel_threads`' inside one, else :func:`default_threads`."""
    return getattr(_LOCAL, "threads", None) or default_threads()


def kernel_thread_count(threads: int | None) -> int:
    """The compiled kernels' thread count for a segmentation or a frame.

    ``threads`` when given; otherwise the current count
    (:func:`current_threads`), reduced to the :func:`idle_cores` (a reading
    at most ``LOAD_MAX_AGE`` s old): a parallel region waits for its slowest
    thread, and a thread that shares its core with another process's work
    made whole segmentations 2 to 90 times slower than on one thread
    (measured beside one busy process on 2 cores)."""
    if threads is not None:
        return threads
    count = current_threads()
    return count if count == 1 else min(count, idle_cores(max_age=LOAD_MAX_AGE))


@contextmanager
def kernel_threads(threads: int | None) -> Iterator[None]:
    """Run the compiled kernels inside on ``threads`` threads, then restore
    the count before (also on an exception); None changes nothing.  The
    count belongs to the calling Python thread, so two threads (the
    viewer's worker and its HTTP thread) do not change each other's."""
    if threads is None:
        yield
        return
    previous = getattr(_LOCAL, "threads", None)
    _LOCAL.threads = max(1, int(threads))
    try:
        yield
    finally:
        _LOCAL.threads = previous


#: Linux's prctl option that sends the calling process a signal when its
#: parent ends
_PR_SET_PDEATHSIG = 1


def die_with_parent(parent_pid: int) -> None:
    """End this process (SIGKILL) when its parent ends, however it ends
    (``kill -9`` included): for the command's helper processes (batch
    workers, the report worker), which otherwise run on under PID 1.

    On Linux the kernel does it (``prctl(PR_SET_PDEATHSIG)``); if the parent
    is already gone when this runs, the process exits now.  Elsewhere a
    daemon thread polls the parent's id.
    """
    import signal
    import sys

    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            if libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0:
                if os.getppid() != parent_pid:  # it ended before the call
                    os._exit(1)
                return
        except (OSError, AttributeError):
            pass

    def watch():
        while os.getppid() == parent_pid:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, daemon=True, name="spheroseg-parent-watch").start()
