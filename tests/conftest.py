import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
CETUS = SHARED / "data" / "cetus"

# the cached grid matrices (spheroseg.geometry.array_cache) of this session
# and of every command a test starts (they inherit the environment): one
# folder beside pytest's own cache, not the installed package's, shared by
# the session's workers (a file is written under a name of its own and
# renamed)
os.environ.setdefault("SPHEROSEG_CACHE_DIR", str(Path(__file__).resolve().parents[1] / ".pytest_cache" / "spheroseg"))
#: the PYTHONPATH of a command a test starts: this process's sys.path, so
#: that it imports the spheroseg under test (the installed one, with its
#: compiled kernels), never a source tree beside it
SUBPROCESS_PATH = os.pathsep.join(p for p in sys.path if p)


def pytest_xdist_auto_num_workers(config):
    """``-n auto``: a worker per core this process may run on
    (:func:`spheroseg._runtime.usable_cores`, its affinity; not the host's
    count, which a container's may be far below), at most 4: past 4 the
    longest test file sets the time."""
    from spheroseg._compiled._runtime import usable_cores

    return max(1, min(usable_cores(), 4))


def pytest_collection_modifyitems(items):
    """The test files in the order the workers take them (``--dist
    loadfile --no-loadscope-reorder``): by their number of tests, most
    first (as xdist's own order), so that no long file starts last."""
    files = {}
    for item in items:
        files.setdefault(item.path, []).append(item)
    ordered = sorted(files.values(), key=lambda tests: -len(tests))
    items[:] = [item for tests in ordered for item in tests]


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
    from spheroseg.apps.cli import main as cli_main

    capfd.readouterr()
    argv = [str(a) for a in args]
    try:
        code = cli_main(argv)
    except SystemExit as exc:  # argparse's errors and --help
        code = exc.code
    captured = capfd.readouterr()
    return subprocess.CompletedProcess(argv, code, captured.out, captured.err)
