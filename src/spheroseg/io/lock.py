"""A run owns its output folder: a lock file beside ``--out`` held for the
whole run, so that a second run on the same folder is refused, naming the
run that holds it, instead of the two deleting each other's files.

The lock is ``fcntl.flock`` on ``.<out>.lock`` in ``--out``'s parent (the
nearest existing folder above a missing one; ``--out/.spheroseg.lock``
when only ``--out`` is writable): the system drops it when its
process ends, however it ends, so a lock left by a killed run is simply
taken over.  The file names the holder (process id, host, command, start
time) for the message.  Without ``fcntl`` (Windows) runs are not locked.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import time
from pathlib import Path

__all__ = ["OutputInUse", "hold_output"]


class OutputInUse(OSError):
    """Another running process holds the output folder."""


def _lock_path(out: Path) -> Path | None:
    """Beside ``out`` (in the nearest existing folder above it); inside it
    when only it is writable (a cohort folder in a read-only share); None
    when neither is (the run fails on its own writes)."""
    out = Path(os.path.abspath(out))
    parent = out.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if os.access(parent, os.W_OK):
        return parent / f".{out.name}.lock"
    if out.is_dir() and os.access(out, os.W_OK):
        return out / ".spheroseg.lock"
    return None


def _holder(path: Path) -> str:
    try:
        info = json.loads(path.read_text())
        return (f"process {info['pid']} on {info['host']} ({info['command']}, started "
                f"{time.strftime('%Y-%m-%d %H:%M:%S', time.localtime(info['started']))})")
    except (OSError, ValueError, KeyError, TypeError):
        return "another process"


@contextlib.contextmanager
def hold_output(out: str | os.PathLike, command: str):
    """Hold ``out``'s lock for the ``with`` block; raise :class:`OutputInUse`
    (naming the holder) when a live process holds it."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    path = _lock_path(Path(out))
    if path is None:
        yield
        return
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise OutputInUse(f"output folder {Path(os.path.abspath(out))} is in use by {_holder(path)}; wait for "
                              f"it to end (its lock: {path})") from None
        except OSError:  # a file system without locks: not locked
            os.close(fd)
            yield
            return
        try:  # the file may have been removed by its holder between open and lock: lock the one at the path
            same = os.path.samestat(os.fstat(fd), os.stat(path))
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        info = {"pid": os.getpid(), "host": socket.gethostname(), "command": command, "started": time.time()}
        os.ftruncate(fd, 0)
        os.write(fd, json.dumps(info).encode())
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(path)
        os.close(fd)
