"""load_kernels on a first run (an empty numba cache) and on later runs, from two threads at once,
and what a first run of the command says."""

import json
import os
import subprocess
import sys

import pytest
from conftest import numba_cache_without

from spheroseg.io import save_volume
from spheroseg.synthetic.phantom import make_phantom

pytest.importorskip("numba")


def test_a_first_run_compiles_the_rasteriser_in_a_second_process(first_run):
    """``conftest.RUN`` in an empty numba cache, then again in that cache."""
    _, (first, later) = first_run
    # a first run is said once, and both callers learn it compiled
    assert first["compiled"] and first["said"] == 1 and first["both_compiled"] == [True, True]
    if (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()) >= 2:
        # the second process compiled the mask's and the padding's kernels
        # into the cache, with the signatures of a command's calls, while
        # this one compiled the segmentation's
        assert first["helper"] and first["raster_compiled"] == 0
    assert not later["compiled"] and not later["helper"] and later["raster_compiled"] == 0
    assert later["said"] == 0 and later["both_compiled"] == [False, False]


STEP_KERNELS = ("gather", "scatter", "normal_displacement", "samples_at")
STEP = """
import json
import sys
from spheroseg._compiled import _kernels
from spheroseg.synthetic.phantom import make_phantom
from spheroseg.tracking.segment import segment
from spheroseg.apps.warmup import load_step_kernels
if sys.argv[1] == "step":
    load_step_kernels()
else:
    ph = make_phantom(seed=0, spacing=3.0)
    segment(ph.volume, ph.apex, ph.base, max_iterations=2)
print(json.dumps({name: sum(getattr(_kernels, name).stats.cache_misses.values())
                  for name in sys.argv[2:]}))
"""


def test_the_helpers_step_kernels_are_those_a_segmentation_calls(first_run, tmp_path):
    """What the second process of a first run compiles first: with none of
    these kernels in the cache it compiles each of them, and a segmentation
    after it compiles none of them (the signatures are a segmentation's).
    The cache is the first run's less these kernels' files, so that the
    segmentation finds the rest of its kernels compiled."""
    cache = numba_cache_without(first_run, tmp_path / "numba", [f"_kernels.{name}-*" for name in STEP_KERNELS])
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "PYTHONWARNINGS": "ignore"}
    compiled = []
    for role in ("step", "segmentation"):
        proc = subprocess.run([sys.executable, "-c", STEP, role, *STEP_KERNELS], capture_output=True, text=True,
                              env=env, timeout=600)
        assert proc.returncode == 0, proc.stderr
        compiled.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    step, segmentation = compiled
    assert all(count >= 1 for count in step.values()), step
    assert not any(segmentation.values()), segmentation


TRACK = """
import json
from spheroseg._compiled import _kernels
from spheroseg.tracking.segment import track
from spheroseg.synthetic.phantom import make_sequence
seq = make_sequence(seed=0, n_frames=4, spacing=3.0)
first = seq.frames[0]
track(seq.volumes, first.apex, first.base)
print(json.dumps({name: sum(kernel.stats.cache_misses.values()) for name, kernel in vars(_kernels).items()
                  if hasattr(kernel, "stats")}))
"""


def test_tracking_compiles_nothing_a_first_run_left_out(first_run, tmp_path):
    """After a first run (:func:`spheroseg.warmup.load_kernels` in an empty
    cache), tracking a sequence finds every kernel it calls compiled: a
    frame's checks call them with a segmentation's signatures (a writable
    row index, where a segmentation's are read-only, compiled another
    specialisation on every first tracking)."""
    cache = numba_cache_without(first_run, tmp_path / "numba", [])
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "PYTHONWARNINGS": "ignore"}
    proc = subprocess.run([sys.executable, "-c", TRACK], capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr
    compiled = json.loads(proc.stdout.strip().splitlines()[-1])
    assert compiled and not any(compiled.values()), compiled


def test_first_run_says_once_that_it_compiles(first_run, tmp_path):
    """``spheroseg segment`` twice: the first run says once, in one line,
    that it compiles, and the second nothing.  A cache without the
    rasteriser's kernels is a first run (as an empty one on a new machine:
    the first test above); the rest of a command's kernels are the first
    run's, so a kernel that load_kernels misses is compiled in the segment
    stage, as it would be from nothing."""
    ph = make_phantom(seed=41, spacing=1.5)
    path = tmp_path / "first.mha"
    save_volume(path, ph.volume)
    args = ["segment", path, "--apex", *ph.apex, "--base", *ph.base, "--no-report", "--force"]
    cache = numba_cache_without(first_run, tmp_path / "numba", ["_raster.*"])
    env = {**os.environ, "PYTHONWARNINGS": "ignore", "NUMBA_CACHE_DIR": str(cache)}
    runs = [subprocess.run([sys.executable, "-m", "spheroseg", *map(str, args), "--out", tmp_path / f"out{k}"],
                           capture_output=True, text=True, env=env, timeout=600) for k in range(2)]
    assert all(r.returncode == 0 for r in runs), runs[0].stderr
    first = runs[0].stderr.strip().splitlines()
    assert len(first) == 1 and first[0].startswith("spheroseg: compiling the numerical kernels"), first
    assert runs[1].stderr == ""
    seconds = [json.loads((tmp_path / f"out{k}" / "results.json").read_text())["seconds"] for k in range(2)]
    said = float(first[0].split("): ")[1].split(" s")[0])
    assert said == pytest.approx(seconds[0]["kernels"], abs=0.051)
    # compiling is in the kernels stage, not in the segmentation
    assert seconds[0]["kernels"] > seconds[1]["kernels"]
    assert seconds[0]["segment"] < seconds[0]["kernels"]
