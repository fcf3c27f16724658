"""Files and folders written whole or not at all: a reader never sees half
a file, a failed or killed run leaves no partial output set, and no output
ever lands on an input."""

from __future__ import annotations

import ctypes
import os
import shutil
import sys
import tempfile
from pathlib import Path

__all__ = ["write_atomically", "write_folder_atomically", "replace_folder", "refuse_overwriting_inputs",
           "shared_mode"]


def refuse_overwriting_inputs(targets, inputs, *, hint: str = "choose another --out") -> None:
    """Raise ``ValueError`` when writing, moving aside or replacing any of
    ``targets`` would touch one of ``inputs``: the same file or folder
    (links followed), an input inside a target folder (replaced whole), or
    a target inside an input folder (a folder of frames gaining files).

    The one check every writer runs (``segment``, ``track``, ``batch``,
    ``scan-convert``) before anything is read or created.
    """
    resolved = []
    for path in inputs:
        path = Path(path)
        if path.exists() or path.is_symlink():
            resolved.append((path.resolve(), path.is_dir()))
    for target in targets:
        where = Path(target).resolve()
        for source, folder in resolved:
            if where == source or where in source.parents or (folder and source in where.parents):
                raise ValueError(f"output {where} would overwrite an input ({source}); {hint}")


def shared_mode(folder: Path, like: Path | None = None) -> None:
    """Give a folder made by ``mkdtemp`` (0700) the mode of ``like`` or, without
    it, the one ``mkdir`` gives (0777 less the umask): an output folder is as
    readable as any other the user makes."""
    if like is not None and like.is_dir():
        shutil.copymode(like, folder)
        return
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(folder, 0o777 & ~umask)


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


#: renameat2's flag that swaps two paths in one step (Linux 3.15)
_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def _exchange(a: Path, b: Path) -> bool:
    """Swap the folders ``a`` and ``b`` in one system call (Linux's
    ``renameat2(RENAME_EXCHANGE)``); False where that is not available."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        call = libc.renameat2
    except (OSError, AttributeError):
        return False
    call.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if call(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    errno = ctypes.get_errno()
    if errno in (22, 38, 95):  # EINVAL, ENOSYS, EOPNOTSUPP: a file system or kernel without it
        return False
    raise OSError(errno, os.strerror(errno), str(b))


def replace_folder(new: Path, final: Path) -> None:
    """Put the complete folder ``new`` at ``final``, replacing the folder
    there, all or nothing even under ``kill -9``: one exchange of the two
    names (the old set is then at ``new``'s name, deleted after).  Where
    the exchange is not available, two renames: killed between them,
    ``final`` is missing and the complete new set is at ``new``."""
    if not (final.exists() or final.is_symlink()):
        os.replace(new, final)
        return
    if _exchange(new, final):
        shutil.rmtree(new, ignore_errors=True)
        return
    old = final.parent / f".{final.name}.old-{os.getpid()}-{os.urandom(4).hex()}"
    os.replace(final, old)
    os.replace(new, final)
    shutil.rmtree(old, ignore_errors=True)


def _link_tree(source: Path, target: Path) -> None:
    """``target`` as a copy of ``source`` made of hard links (a copy where
    links are refused); symbolic links stay links."""
    if source.is_symlink():
        os.symlink(os.readlink(source), target)
    elif source.is_dir():
        target.mkdir()
        shutil.copystat(source, target)
        for entry in source.iterdir():
            _link_tree(entry, target / entry.name)
    else:
        try:
            os.link(source, target)
        except OSError:
            shutil.copy2(source, target)


def _moves_in_place(out: Path) -> bool:
    """Whether ``out`` must keep its identity (entries moved one by one)
    rather than be exchanged for the new folder: it holds folders of the
    user's own (hard-linking a tree is not cheap), or it is this process's
    working folder or above it (a shell there would be left in a deleted
    folder)."""
    cwd = Path.cwd()
    return out == cwd or out in cwd.parents


def write_folder_atomically(out: str | os.PathLike, write, *, replaces=()):
    """Call ``write(tmp_folder)`` on a hidden folder beside ``out``, then put
    it at ``out``; return what ``write`` returned.

    A missing ``out`` is the hidden folder renamed (missing parents are made
    only then).  An existing ``out`` is replaced by the hidden folder once
    it holds the new set and, as hard links, every file of ``out`` not named
    in ``replaces`` (the user's own files stay; the earlier run's set goes
    whole, stale frames included): one exchange of the two folders
    (:func:`replace_folder`), so that ``kill -9`` at any point leaves
    ``out`` with the old set or the new one, complete, and at most a hidden
    ``.<out>.partial-*`` folder beside it.  When ``out`` holds folders not
    in ``replaces``, or is the working folder, the entries are moved one
    by one instead (old set aside, new set in, ``results.json`` last): a
    kill in between leaves the set without its ``results.json``.  If
    ``write`` raises (or is interrupted) ``out`` is as it was, or still
    missing, and the hidden folder is deleted.
    """
    out = Path(os.path.realpath(out) if os.path.islink(out) else os.path.abspath(out))
    anchor = out.parent
    while not anchor.exists() and anchor != anchor.parent:  # the hidden folder stays on out's file system
        anchor = anchor.parent
    # its name UTF-8 whatever out's bytes: the image writers open files in it
    name = os.fsencode(out.name).decode("utf-8", "replace").replace("\ufffd", "_")
    tmpdir = Path(tempfile.mkdtemp(prefix=f".{name}.partial-", dir=anchor))
    old = None
    try:
        shared_mode(tmpdir, out)
        returned = write(tmpdir)
        if not out.exists():
            out.parent.mkdir(parents=True, exist_ok=True)
            os.replace(tmpdir, out)
            return returned
        keep = [e for e in out.iterdir() if e.name not in replaces and not (tmpdir / e.name).exists()]
        if not _moves_in_place(out) and not any(e.is_dir() and not e.is_symlink() for e in keep):
            for entry in keep:
                _link_tree(entry, tmpdir / entry.name)
            replace_folder(tmpdir, out)
            return returned
        old = Path(tempfile.mkdtemp(prefix=f".{name}.old-", dir=out.parent))
        last = "results.json"
        for entry in sorted(replaces, key=lambda n: n != last):  # the old set's results.json first
            if (out / entry).exists() or (out / entry).is_symlink():
                os.replace(out / entry, old / entry)
        for produced in sorted(tmpdir.iterdir(), key=lambda p: p.name == last):  # the new one's last
            os.replace(produced, out / produced.name)
        return returned
    finally:
        for folder in (tmpdir, old):
            if folder is not None:
                shutil.rmtree(folder, ignore_errors=True)
