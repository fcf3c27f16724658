"""The numba runtime: whether the compiled kernels can run, how many
threads they get, the lock around their parallel regions, and what numba
compiled rather than loaded from its on-disk cache.

Nothing here imports numba at module level: ``import spheroseg`` stays light.
"""

from __future__ import annotations

import os
import threading
import time
from contextlib import contextmanager
from typing import Iterator

import numpy as np

__all__ = ["die_with_parent", "PARALLEL_LOCK", "compiled_available", "compilations", "usable_cores", "idle_cores",
           "kernel_thread_count", "kernel_threads", "LOAD_MAX_AGE"]

#: held by a caller of a parallel kernel (the iteration's and the
#: rasteriser's): numba releases the GIL in a parallel region, and its
#: fallback threading layer (workqueue, where neither TBB nor an OpenMP
#: runtime is installed) aborts the process when two Python threads enter
#: one at once, as the viewer's worker and its HTTP thread (a mask on save)
#: could
PARALLEL_LOCK = threading.Lock()
# a segmentation or a frame reads the machine's load when the last reading
# is older than this (s): a back-to-back series (a cohort, a sequence)
# need not read it at every frame
LOAD_MAX_AGE = 0.1
_LOAD_SAMPLE = (-np.inf, 1)  # (time.monotonic(), idle cores) of the last reading


def compilations(module) -> int:
    """Kernels of ``module`` that numba compiled in this process, i.e. that
    missed its on-disk cache (``Dispatcher.stats.cache_misses``)."""
    count = 0
    for value in vars(module).values():
        misses = getattr(getattr(value, "stats", None), "cache_misses", None)
        if misses:
            count += sum(misses.values()) if isinstance(misses, dict) else len(misses)
    return count


def compiled_available() -> bool:
    """Whether the compiled kernels can run (numba is installed)."""
    from importlib.util import find_spec

    return find_spec("numba") is not None


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


def kernel_thread_count(threads: int | None) -> int | None:
    """The compiled kernels' thread count for a segmentation or a frame.

    ``threads`` when given; otherwise numba's count, reduced to the
    :func:`idle_cores` (a reading at most ``LOAD_MAX_AGE`` s old): a
    parallel region waits for its slowest thread, and a thread that shares
    its core with another process's work made whole segmentations 2 to 90
    times slower than on one thread (measured beside one busy process on 2
    cores).  None without numba."""
    if threads is not None:
        return threads
    try:
        import numba
    except ImportError:  # pragma: no cover - numba is a dependency
        return None
    count = numba.get_num_threads()
    return count if count == 1 else min(count, idle_cores(max_age=LOAD_MAX_AGE))


@contextmanager
def kernel_threads(threads: int | None) -> Iterator[None]:
    """Run the compiled kernels inside on ``threads`` threads, then restore
    numba's count (also on an exception); None, or without numba, changes
    nothing.  numba's count belongs to the calling Python thread, so two
    threads (the viewer's worker and its HTTP thread) do not change each
    other's.  A count above ``NUMBA_NUM_THREADS`` is capped at it."""
    try:
        import numba
    except ImportError:
        numba = None
    if threads is None or numba is None:
        yield
        return
    previous, wanted = numba.get_num_threads(), min(int(threads), numba.config.NUMBA_NUM_THREADS)
    if wanted == previous:  # nested (a run's iterations): nothing to set
        yield
        return
    numba.set_num_threads(wanted)
    try:
        yield
    finally:
        numba.set_num_threads(previous)


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
