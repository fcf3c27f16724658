"""load_kernels on a first run (an empty numba cache) and on later runs, from two threads at once."""

import json
import os
import subprocess
import sys

import pytest

pytest.importorskip("numba")

RUN = """
import json
import threading
from spheroseg._raster import compilations
from spheroseg.synthetic.phantom import make_phantom
from spheroseg.surface import Surface
from spheroseg.volume import outside_sector
from spheroseg.warmup import load_kernels
# two threads at once, as the viewer's worker and its command: one loads
said, results = [], []
threads = [threading.Thread(target=lambda: results.append(load_kernels(on_compile=lambda: said.append(1))))
           for _ in range(2)]
for thread in threads:
    thread.start()
for thread in threads:
    thread.join()
loaded = max(results, key=lambda r: r["seconds"])  # the one that loaded
# a mask and a padding search as a command makes them, after the loading
ph = make_phantom(seed=0, spacing=3.0)
Surface.from_apex_base(ph.apex, ph.base).mask(ph.volume.grid)
outside_sector(ph.volume.array)
print(json.dumps({**loaded, "raster_compiled": compilations(), "said": len(said),
                  "both_compiled": [r["compiled"] for r in results]}))
"""


def test_a_first_run_compiles_the_rasteriser_in_a_second_process(tmp_path):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba"), "PYTHONWARNINGS": "ignore"}
    runs = []
    for _ in range(2):
        proc = subprocess.run([sys.executable, "-c", RUN], capture_output=True, text=True, env=env, timeout=600)
        assert proc.returncode == 0, proc.stderr
        runs.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    first, later = runs
    # a first run is said once, and both callers learn it compiled
    assert first["compiled"] and first["said"] == 1 and first["both_compiled"] == [True, True]
    if (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()) >= 2:
        # the second process compiled the mask's and the padding's kernels
        # into the cache, with the signatures of a command's calls, while
        # this one compiled the segmentation's
        assert first["helper"] and first["raster_compiled"] == 0
    assert not later["compiled"] and not later["helper"] and later["raster_compiled"] == 0
    assert later["said"] == 0 and later["both_compiled"] == [False, False]


STEP = """
import json
import sys
from spheroseg import _kernels
from spheroseg.synthetic.phantom import make_phantom
from spheroseg.segment import segment
from spheroseg.warmup import load_step_kernels
if sys.argv[1] == "step":
    load_step_kernels()
else:
    ph = make_phantom(seed=0, spacing=3.0)
    segment(ph.volume, ph.apex, ph.base, max_iterations=2)
print(json.dumps({name: sum(getattr(_kernels, name).stats.cache_misses.values())
                  for name in ("gather", "scatter", "normal_displacement", "samples_at")}))
"""


def test_the_helpers_step_kernels_are_those_a_segmentation_calls(tmp_path):
    """What the second process of a first run compiles first: with an
    empty cache it compiles each of these kernels, and a segmentation after
    it compiles none of them (the signatures are a segmentation's)."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba"), "PYTHONWARNINGS": "ignore"}
    compiled = []
    for role in ("step", "segmentation"):
        proc = subprocess.run([sys.executable, "-c", STEP, role], capture_output=True, text=True, env=env,
                              timeout=600)
        assert proc.returncode == 0, proc.stderr
        compiled.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    step, segmentation = compiled
    assert all(count >= 1 for count in step.values()), step
    assert not any(segmentation.values()), segmentation
