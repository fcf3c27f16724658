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
# numba.  Unless given, it is kept beside pytest's own cache, so that a clone
# starts with it empty (as CI) and later runs load from it.
NUMBA_CACHE = Path(os.environ.setdefault("NUMBA_CACHE_DIR",
                                         str(Path(__file__).resolve().parents[1] / ".pytest_cache" / "numba")))


def pytest_collection_modifyitems(items):
    """The tests of a first run first: when the session's numba cache is
    empty, :func:`first_run` compiles into it (once a session, not twice)."""
    items.sort(key=lambda item: "first_run" not in getattr(item, "fixturenames", ()))


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
    from spheroseg import warmup
    from spheroseg.cli import main as cli_main

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


@pytest.fixture(scope="session")
def first_run(tmp_path_factory):
    """``RUN`` twice in one numba cache, empty at first: the cache (every
    kernel of a command, compiled) and the two runs' reports.  The session's
    one compilation from nothing (``tests/test_warmup.py``); tests of a
    first run elsewhere start from this cache less the kernels they need
    compiled (:func:`numba_cache_without`)."""
    pytest.importorskip("numba")
    folder = tmp_path_factory.mktemp("first-run")
    cache = folder / "numba"
    # the session's cache when nothing is in it yet (a clone's first run, as
    # CI's): the session then loads these kernels rather than compile them
    # again, and the returned cache is a copy taken after the two runs
    session = not NUMBA_CACHE.exists() or not any(path.is_file() for path in NUMBA_CACHE.rglob("*"))
    env = {**os.environ, "NUMBA_CACHE_DIR": str(NUMBA_CACHE if session else cache), "PYTHONWARNINGS": "ignore"}
    runs = []
    for _ in range(2):
        proc = subprocess.run([sys.executable, "-c", RUN], capture_output=True, text=True, env=env, timeout=600)
        assert proc.returncode == 0, proc.stderr
        runs.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    if session:
        shutil.copytree(NUMBA_CACHE, cache)
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
