import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
CETUS = SHARED / "data" / "cetus"

# numba's cache of this session and of every command a test starts (they
# inherit the environment): one folder, set before any test module imports
# numba, shared by the session's workers (pytest-xdist; numba writes a file
# under a name of its own and renames it).  Unless given, it is kept beside
# pytest's own cache, so that a clone starts with it empty (as CI) and later
# runs load from it.
NUMBA_CACHE = Path(os.environ.setdefault("NUMBA_CACHE_DIR",
                                         str(Path(__file__).resolve().parents[1] / ".pytest_cache" / "numba")))


def pytest_xdist_auto_num_workers(config):
    """``-n auto``: a worker per core this process may run on
    (:func:`spheroseg._runtime.usable_cores`, its affinity; not the host's
    count, which a container's may be far below), at most 4: each worker
    compiles the kernels it calls, and past 4 the longest test file sets
    the time."""
    from spheroseg._compiled._runtime import usable_cores

    return max(1, min(usable_cores(), 4))


def pytest_collection_modifyitems(items):
    """The test files in the order the workers take them (``--dist
    loadfile --no-loadscope-reorder``): the one with the tests of a first
    run first, whose compilation from nothing is the suite's longest
    fixture, then the others by their number of tests, most first (as
    xdist's own order), so that no long file starts last; in a file, the
    first run's tests first."""
    def first_run(item):
        return "first_run" in getattr(item, "fixturenames", ())

    files = {}
    for item in items:
        files.setdefault(item.path, []).append(item)
    ordered = sorted(files.values(), key=lambda tests: (not any(map(first_run, tests)), -len(tests)))
    items[:] = [item for tests in ordered for item in sorted(tests, key=lambda item: not first_run(item))]


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


def cetus_file(name: str) -> Path:
    """A CETUS file from ../shared (never copied into the project); skip when absent."""
    path = CETUS / name
    if not path.is_file():
        pytest.skip(f"{path} not available")
    return path


def interruptible() -> None:
    """``preexec_fn`` of a command a test stops with Ctrl-C (SIGINT): its
    default disposition back.  A shell starts a background job with SIGINT
    ignored, children inherit that, and Python then installs no
    KeyboardInterrupt: the command would not stop."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)


def cli(capfd, *args):
    """``spheroseg ARGS`` in this process: what a subprocess would return
    (exit status, stdout, stderr as ``subprocess.run``; ``capfd``: the lines C++
    readers write on the file descriptors too)."""
    from spheroseg.apps import warmup
    from spheroseg.apps.cli import main as cli_main

    # the kernels loaded before the command, as a later process finds them
    # in numba's cache: load_kernels reports whether this process compiled
    # anything, and other tests have (a first run's line is tested in a
    # subprocess: tests/test_cli.py, tests/test_warmup.py)
    load = warmup.load_kernels
    load()
    warmup.load_kernels = lambda **kwargs: warmup.KernelLoad(load(**kwargs), compiled=False)
    capfd.readouterr()
    argv = [str(a) for a in args]
    try:
        code = cli_main(argv)
    except SystemExit as exc:  # argparse's errors and --help
        code = exc.code
    finally:
        warmup.load_kernels = load
    captured = capfd.readouterr()
    return subprocess.CompletedProcess(argv, code, captured.out, captured.err)


RUN = """
import json
import threading
from spheroseg._compiled._raster import compilations
from spheroseg.synthetic.phantom import make_phantom
from spheroseg.surfaces.surface import Surface
from spheroseg.volumes.volume import outside_sector
from spheroseg.apps.warmup import load_kernels
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


@pytest.fixture(scope="session")
def first_run(tmp_path_factory):
    """``RUN`` twice in one numba cache, empty at first: the cache (every
    kernel of a command, compiled) and the two runs' reports.  The one
    compilation from nothing of a test process (``tests/test_warmup.py``);
    tests of a first run start from this cache less the kernels they need
    compiled (:func:`numba_cache_without`)."""
    pytest.importorskip("numba")
    cache = tmp_path_factory.mktemp("first-run") / "numba"
    # a cache of its own, never the session's: the suite's other worker
    # (pytest-xdist) writes into that one meanwhile, and a first run must
    # start from nothing
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "PYTHONWARNINGS": "ignore"}
    runs = []
    for _ in range(2):
        proc = subprocess.run([sys.executable, "-c", RUN], capture_output=True, text=True, env=env, timeout=600)
        assert proc.returncode == 0, proc.stderr
        runs.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    return cache, runs


def numba_cache_without(first_run, folder: Path, patterns) -> Path:
    """A copy in ``folder`` of the first run's numba cache less the files
    matching each glob of ``patterns`` (``"_kernels.gather-*"``): a cache
    in which just those kernels are compiled again, the rest loaded.  Each
    pattern must match, so that a renamed kernel cannot leave the cache
    whole."""
    shutil.copytree(first_run[0], folder)
    for pattern in patterns:
        files = list(folder.rglob(pattern))
        assert files, f"no {pattern} in the first run's cache"
        for path in files:
            path.unlink()
    return folder
