"""Arrays computed once per machine: cached on disk.

A segmentation's first call in a process builds the matrices of each grid
it uses (:func:`spheroseg.geometry.discretisation.discretise`: for the
default 2 x 2, 4 x 4 and 8 x 8 patches, longer than the segmentation).
They depend on the grid and the code only, so they are written once to an
``.npz`` file and read back by every later process.

The files live in ``$SPHEROSEG_CACHE_DIR`` when set, else the package's
``__pycache__``.  A file's name hashes the
key, spheroseg's version and the size and modification time of the source
files that compute the arrays, so an edited formula is never read from an
old file.  Writes are atomic (a temporary file renamed); a file that cannot
be read, or a directory that cannot be written, costs only the computation.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import tempfile
from pathlib import Path
from typing import Callable

import numpy as np

__all__ = ["cache_directory", "cached_arrays"]

_SUBDIRECTORY = "spheroseg-arrays"


def cache_directory() -> Path:
    """The directory of the cached arrays (it may not exist yet)."""
    chosen = os.environ.get("SPHEROSEG_CACHE_DIR")
    root = Path(chosen) if chosen else Path(__file__).resolve().parent / "__pycache__"
    return root / _SUBDIRECTORY


def _file_name(name: str, key: tuple, sources: tuple) -> str:
    from .._version import __version__

    stamps = []
    for source in sources:
        try:
            stat = os.stat(source)
            stamps.append((str(source), stat.st_size, stat.st_mtime_ns))
        except OSError:
            stamps.append((str(source), None, None))
    digest = hashlib.sha256(repr((name, key, __version__, stamps)).encode()).hexdigest()[:24]
    return f"{name}-{digest}.npz"


def cached_arrays(name: str, key: tuple, compute: Callable[[], dict], *, sources=()) -> dict:
    """``compute()``'s arrays, read from the cache when a file for ``key``
    exists, else computed and written there.

    Parameters
    ----------
    name : str
        What the arrays are (the file name's prefix).
    key : tuple
        Everything the arrays depend on besides the code (its ``repr`` is hashed).
    compute : callable
        Returns ``{name: numpy array}`` (numeric, no objects).
    sources : sequence of path
        The source files of ``compute``: editing one invalidates the file.

    Returns
    -------
    dict
        The arrays (read from the file or just computed).
    """
    path = cache_directory() / _file_name(name, key, tuple(sources))
    try:
        with np.load(path, allow_pickle=False) as stored:
            return {k: stored[k] for k in stored.files}
    except Exception:  # missing, truncated, corrupted: compute (the file is rewritten)
        pass
    arrays = compute()
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.stem, suffix=".tmp")
        with os.fdopen(handle, "wb") as file:
            np.savez(file, **arrays)
        os.replace(tmp, path)  # atomic: a reader sees no file or the whole file
    except OSError:  # read-only or full: the arrays stay in memory only
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
    return arrays
