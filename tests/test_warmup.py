"""The numerical path loaded once a process (from two threads at once), and
an installed spheroseg segmenting in a fresh interpreter from its prebuilt
kernels: nothing compiled at run time, numba never imported."""

import json
import os
import subprocess
import sys
import time

import pytest
from conftest import SUBPROCESS_PATH



TWO_THREADS = """
import json, threading
import spheroseg.tracking.segment as module
from spheroseg.apps.warmup import load_kernels
calls, segment = [], module.segment
module.segment = lambda *args, **kwargs: (calls.append(1), segment(*args, **kwargs))[1]
results = []
threads = [threading.Thread(target=lambda: results.append(load_kernels())) for _ in range(2)]
for thread in threads:
    thread.start()
for thread in threads:
    thread.join()
print(json.dumps({"calls": len(calls), "results": results, "again": load_kernels()}))
"""


def test_load_kernels_loads_once_from_two_threads():
    """The viewer's worker and its command at once, in a fresh process: one
    segmentation runs, both calls return, and a later call only looks."""
    env = {**os.environ, "PYTHONPATH": SUBPROCESS_PATH, "PYTHONWARNINGS": "ignore"}
    run = subprocess.run([sys.executable, "-c", TWO_THREADS], capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    found = json.loads(run.stdout.strip().splitlines()[-1])
    assert found["calls"] == 1 and len(found["results"]) == 2
    assert all(set(r) == {"seconds"} and r["seconds"] >= 0 for r in found["results"])
    assert found["again"]["seconds"] < max(r["seconds"] for r in found["results"])


FRESH = """
import json, sys, time
from importlib.util import find_spec
t0 = time.perf_counter()
import spheroseg
from spheroseg.synthetic.phantom import make_phantom
ph = make_phantom(seed=0, spacing=3.0)
result = spheroseg.segment(ph.volume, ph.apex, ph.base)
result.mask(ph.volume)
ran = [sys.modules.get(f"spheroseg._compiled.{m}") for m in ("_kernels", "_raster")]  # imported when they run
print(json.dumps({"files": [getattr(m, "__file__", None) for m in ran],
                  "volume": result.volume_ml, "truth": ph.truth_volume_ml,
                  "loaded": sorted(m for m in ("numba", "llvmlite", "pyximport") if m in sys.modules),
                  "seconds": time.perf_counter() - t0}))
"""


def test_a_fresh_interpreter_segments_from_the_prebuilt_kernels():
    """A segmentation and its mask run the extension modules, shared objects
    built before this process started (an editable install's rebuild at
    import would write them anew), and neither numba nor pyximport is
    imported (SciPy imports Cython's version where it is installed)."""
    from importlib.util import find_spec

    if find_spec("spheroseg._compiled._kernels") is None:  # a source tree on PYTHONPATH
        if os.environ.get("CI"):
            pytest.fail("spheroseg is not built: its compiled kernels are missing")
        pytest.skip("the compiled kernels are not built (a source tree)")
    started = time.time()
    env = {**os.environ, "PYTHONPATH": SUBPROCESS_PATH, "PYTHONWARNINGS": "ignore"}
    run = subprocess.run([sys.executable, "-c", FRESH], capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    found = json.loads(run.stdout.strip().splitlines()[-1])
    for path in found["files"]:
        assert path is not None and path.endswith((".so", ".pyd")) and os.path.isfile(path), path
        assert os.path.getmtime(path) < started, f"{path} was compiled at run time"
    assert found["loaded"] == []
    assert abs(found["volume"] - found["truth"]) < 0.1 * found["truth"]
