"""The kernels' runtime: thread counts, the machine's load, the lock around
parallel regions."""

import threading

import numpy as np
import pytest

import spheroseg._compiled._runtime as runtime
from spheroseg._compiled._runtime import (current_threads, default_threads, idle_cores, kernel_thread_count,
                                          kernel_threads, set_default_threads)


def test_kernel_threads_sets_and_restores_the_count():
    before = current_threads()
    assert before == default_threads()
    with kernel_threads(None):
        assert current_threads() == before
    with kernel_threads(2):
        assert current_threads() == 2
        with kernel_threads(1):
            assert current_threads() == 1
        assert current_threads() == 2
        seen = []  # another Python thread (the viewer's HTTP thread) keeps its own count
        other = threading.Thread(target=lambda: seen.append(current_threads()))
        other.start()
        other.join()
        assert seen == [before]
    assert current_threads() == before
    with pytest.raises(RuntimeError), kernel_threads(3):  # restored on an exception too
        raise RuntimeError
    assert current_threads() == before


def test_the_default_count_is_the_usable_cores_unless_set(monkeypatch):
    monkeypatch.setattr(runtime, "_DEFAULT", [None])
    monkeypatch.setenv("OMP_NUM_THREADS", "1")  # BLAS's (spheroseg batch sets it), not the kernels'
    assert default_threads() == runtime.usable_cores()
    set_default_threads(1)
    assert default_threads() == current_threads() == 1
    with pytest.raises(ValueError, match="threads must be a positive integer, got 0"):
        set_default_threads(0)


BUSY = "import time\nprint('spinning', flush=True)\nend = time.monotonic() + 30\nwhile time.monotonic() < end: pass\n"


def test_idle_cores_leaves_out_a_busy_process():
    """A process spinning on a core takes that core from the count (this
    process's own threads do not: with nothing else running, every core)."""
    import os
    import subprocess
    import sys
    import time

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    assert 1 <= idle_cores() <= cores
    busy = subprocess.Popen([sys.executable, "-c", BUSY], stdout=subprocess.PIPE, text=True)
    try:
        assert busy.stdout.readline().strip() == "spinning"  # its interpreter started (however loaded the machine)
        time.sleep(0.05)
        counts = [idle_cores() for _ in range(20)]
    finally:
        busy.kill()
        busy.wait()
    # the spinner is runnable at nearly every instant: most samples see it
    assert np.median(counts) <= max(cores - 1, 1), counts


def test_idle_cores_reuses_a_sample_no_older_than_asked(monkeypatch):
    first = idle_cores()  # a fresh sample
    monkeypatch.setattr(runtime, "usable_cores", lambda: pytest.fail("the load was read"))
    assert idle_cores(max_age=60.0) == first
    with pytest.raises(pytest.fail.Exception, match="the load was read"):
        idle_cores()  # max_age 0: always a new one


def test_kernel_thread_count_defaults_to_the_idle_cores(monkeypatch):
    assert kernel_thread_count(3) == 3  # given: as given
    monkeypatch.setattr(runtime, "_DEFAULT", [2])
    monkeypatch.setattr(runtime, "idle_cores", lambda **_: 1)
    assert kernel_thread_count(None) == 1
    monkeypatch.setattr(runtime, "idle_cores", lambda **_: 64)
    assert kernel_thread_count(None) == 2  # never above the default
    set_default_threads(1)  # a batch worker's setting: kept without looking at the load
    monkeypatch.setattr(runtime, "idle_cores", lambda **_: pytest.fail("the load was read"))
    assert kernel_thread_count(None) == 1


CONCURRENT = """
import threading, time
import numpy as np
import spheroseg
from spheroseg.synthetic.phantom import make_phantom
ph = make_phantom(seed=0, spacing=2.0)
result = spheroseg.segment(ph.volume, ph.apex, ph.base)
expected = result.mask(ph.volume)
done, bad = threading.Event(), []
def masks():  # the viewer's HTTP thread saving a mask
    while not done.is_set():
        bad.append(not np.array_equal(result.mask(ph.volume), expected))
thread = threading.Thread(target=masks)
thread.start()
started = time.perf_counter()
while time.perf_counter() - started < 2:  # its worker thread segmenting
    again = spheroseg.segment(ph.volume, ph.apex, ph.base, threads=2)
    bad.append(not np.array_equal(again.surface.coefficients, result.surface.coefficients))
done.set()
thread.join()
print(len(bad), sum(bad))
"""


def test_two_threads_in_parallel_kernels_at_once():
    """The viewer's worker segmenting while its HTTP thread rasterises a
    mask, both in the kernels' parallel loops: the process runs on and
    both get what they get alone."""
    import os
    import subprocess
    import sys

    from conftest import SUBPROCESS_PATH

    pytest.importorskip("spheroseg._compiled._kernels", reason="the compiled kernels are not built")
    env = {**os.environ, "PYTHONPATH": SUBPROCESS_PATH, "PYTHONWARNINGS": "ignore"}
    run = subprocess.run([sys.executable, "-c", CONCURRENT], capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode == 0, run.stderr[-500:]
    runs, wrong = map(int, run.stdout.split())
    assert runs > 2 and wrong == 0
