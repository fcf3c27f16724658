"""The numba runtime: thread counts, the machine's load, the lock around
parallel regions."""

import numpy as np
import pytest

import spheroseg._compiled._runtime as runtime
from spheroseg._compiled._runtime import idle_cores, kernel_thread_count, kernel_threads


def test_kernel_threads_sets_and_restores_the_count():
    numba = pytest.importorskip("numba")
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one core: nothing to change")
    before = numba.get_num_threads()
    numba.set_num_threads(2)
    with kernel_threads(None):
        assert numba.get_num_threads() == 2
    with pytest.raises(RuntimeError):
        with kernel_threads(1):
            assert numba.get_num_threads() == 1
            with kernel_threads(1):  # nested: the same count
                assert numba.get_num_threads() == 1
            raise RuntimeError
    assert numba.get_num_threads() == 2
    with kernel_threads(10_000):  # capped at numba's NUMBA_NUM_THREADS
        assert numba.get_num_threads() == numba.config.NUMBA_NUM_THREADS
    numba.set_num_threads(before)


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
    numba = pytest.importorskip("numba")
    assert kernel_thread_count(3) == 3  # given: as given
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
        monkeypatch.setattr(runtime, "idle_cores", lambda **_: 1)
        assert kernel_thread_count(None) == 1
        monkeypatch.setattr(runtime, "idle_cores", lambda **_: 64)
        assert kernel_thread_count(None) == numba.get_num_threads()  # never above numba's count
        numba.set_num_threads(1)  # a batch worker's setting: kept without looking at the load
        monkeypatch.setattr(runtime, "idle_cores", lambda **_: pytest.fail("the load was read"))
        assert kernel_thread_count(None) == 1
    finally:
        numba.set_num_threads(before)


CONCURRENT = """
import threading, time
import spheroseg
from spheroseg.synthetic.phantom import make_phantom
ph = make_phantom(seed=0, spacing=2.0)
result = spheroseg.segment(ph.volume, ph.apex, ph.base)
done = threading.Event()
def masks():  # the viewer's HTTP thread saving a mask
    while not done.is_set():
        result.mask(ph.volume)
thread = threading.Thread(target=masks)
thread.start()
started = time.perf_counter()
while time.perf_counter() - started < 2:  # its worker thread segmenting
    spheroseg.segment(ph.volume, ph.apex, ph.base, threads=2)
done.set()
thread.join()
import numba
print(numba.threading_layer())
"""


def test_two_threads_in_parallel_kernels_under_the_workqueue_layer():
    """numba's fallback threading layer aborts the process when two Python
    threads are in parallel regions at once (numba releases the GIL there):
    without the lock the kernels' callers hold, this run aborts within a
    second."""
    import os
    import subprocess
    import sys

    pytest.importorskip("numba")
    env = {**os.environ, "NUMBA_THREADING_LAYER": "workqueue", "PYTHONWARNINGS": "ignore"}
    run = subprocess.run([sys.executable, "-c", CONCURRENT], capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode == 0, run.stderr[-500:]
    assert run.stdout.split() == ["workqueue"]
