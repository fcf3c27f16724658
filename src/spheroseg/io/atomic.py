"""Files and folders written whole or not at all: a reader never sees half
a file, a failed run leaves no partial output set."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

__all__ = ["write_atomically", "write_folder_atomically"]


def write_atomically(target: str | os.PathLike, write) -> None:
    """Call ``write(tmp_path)`` on a path in a temporary folder beside
    ``target``, then move every file it made into ``target``'s folder
    (a MetaImage header and its .raw move together)."""
    target = Path(target)
    tmpdir = Path(tempfile.mkdtemp(prefix=".spheroseg-", dir=target.parent))
    try:
        write(tmpdir / target.name)
        for produced in tmpdir.iterdir():
            os.replace(produced, target.parent / produced.name)
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)


def write_folder_atomically(out: str | os.PathLike, write, *, replaces=()):
    """Call ``write(tmp_folder)`` on a hidden folder beside ``out``, then put
    everything it wrote into ``out``; return what ``write`` returned.

    A missing ``out`` is the hidden folder renamed (missing parents are made
    only then).  In an existing ``out`` the entries named in ``replaces``
    (files or folders: the whole output set of an earlier run) are moved
    aside, the new ones moved in, and the old ones deleted; other entries
    stay.  If ``write`` raises (or is interrupted) nothing is moved and the
    hidden folder is deleted: ``out`` is as it was, or still missing.
    """
    out = Path(os.path.abspath(out))
    anchor = out.parent
    while not anchor.exists() and anchor != anchor.parent:  # the hidden folder stays on out's file system
        anchor = anchor.parent
    tmpdir = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=anchor))
    old = None
    try:
        returned = write(tmpdir)
        if not out.exists():
            out.parent.mkdir(parents=True, exist_ok=True)
            os.replace(tmpdir, out)
            return returned
        old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
        for name in replaces:
            if (out / name).exists() or (out / name).is_symlink():
                os.replace(out / name, old / name)
        for produced in tmpdir.iterdir():
            os.replace(produced, out / produced.name)
        return returned
    finally:
        for folder in (tmpdir, old):
            if folder is not None:
                shutil.rmtree(folder, ignore_errors=True)
