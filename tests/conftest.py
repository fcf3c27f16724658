from pathlib import Path

import numpy as np
import pytest

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
CETUS = SHARED / "data" / "cetus"


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
