"""Manifests of cohorts: the studies to run, read from JSON or CSV and
checked before anything runs."""

from __future__ import annotations

import csv
import json
import os
import re
from dataclasses import asdict, dataclass
from io import StringIO
from pathlib import Path

import numpy as np

__all__ = ["Study", "ManifestError", "read_manifest", "select_shard", "as_study", "MANIFEST_KEYS"]

#: keys a manifest entry may have
MANIFEST_KEYS = ("id", "image", "apex", "base", "annulus", "landmarks", "points", "spacing", "track", "glob")
_SAFE_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")
#: names the cohort folder keeps for itself (write_summary's files), any case
_RESERVED_ID = re.compile(r"summary(-\d+-of-\d+)?\.(json|csv)", re.IGNORECASE)


class ManifestError(ValueError):
    """A manifest that cannot be run (nothing was started)."""


@dataclass(frozen=True)
class Study:
    """One study of a cohort (paths absolute; points world mm, LPS).

    Attributes
    ----------
    id : str
        Unique; the name of its output folder.
    image : str
        A volume or a sequence (file, folder of frames, glob, DICOM folder).
    apex, base : tuple of 3 floats, optional
        Needed unless ``points`` gives them (``base`` or ``annulus``).
    annulus : tuple of points
        Three or more points of the mitral annulus, instead of ``base``.
    landmarks : tuple of points
    points : str, optional
        A 3D Slicer markups file with points labelled apex, base, landmark...
    spacing : tuple of 3 floats, optional
        Voxel spacing, mm (needed for ``.npy``).
    track : bool, optional
        Track a sequence (True) or segment one volume (False); None: track a
        4D input.
    glob : bool
        ``image`` is a pattern whose matches are the frames (otherwise a
        name is a name, ``*?[`` included).
    """

    id: str
    image: str
    apex: tuple | None = None
    base: tuple | None = None
    annulus: tuple = ()
    landmarks: tuple = ()
    points: str | None = None
    spacing: tuple | None = None
    track: bool | None = None
    glob: bool = False

    def as_entry(self) -> dict:
        """The study as a manifest entry (JSON values; ``glob`` only when
        true, so that the checksums of earlier cohorts stay)."""
        return {k: (list(map(list, v)) if k in ("landmarks", "annulus") else list(v) if isinstance(v, tuple) else v)
                for k, v in asdict(self).items() if k != "glob" or v}


def _numbers(value, count: int | None, what: str) -> tuple:
    given = value  # the message quotes what the manifest says, not its split
    if isinstance(value, str):
        value = value.replace(",", " ").split()
    try:
        numbers = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be numbers, got {given!r}") from None
    if (count is not None and len(numbers) != count) or not all(np.isfinite(numbers)):
        raise ValueError(f"{what} must be {count} finite numbers (x y z), got {given!r}")
    return numbers


def _point_list(value, what: str) -> tuple:
    if value in (None, ""):
        return ()
    if isinstance(value, str):
        value = [part for part in value.split(";") if part.strip()]
    if not isinstance(value, (list, tuple)):
        raise ValueError(f"{what} must be a list of points, got {value!r}")
    return tuple(_numbers(p, 3, f"each point of {what}") for p in value)


def _flag(value, name: str = "track") -> bool | None:
    if value is None or isinstance(value, bool):
        return value
    text = str(value).strip().lower()
    if text == "":
        return None
    if text in ("true", "yes", "1"):
        return True
    if text in ("false", "no", "0"):
        return False
    raise ValueError(f"{name} must be true or false, got {value!r}")


def _study(entry, folder: Path) -> Study:
    if not isinstance(entry, dict):
        raise ValueError(f"a study must be an object with keys {', '.join(MANIFEST_KEYS)}, got {type(entry).__name__}")
    unknown = sorted(set(entry) - set(MANIFEST_KEYS))
    if unknown:
        raise ValueError(f"unknown key(s) {', '.join(unknown)} (known: {', '.join(MANIFEST_KEYS)})")
    ident = str(entry.get("id") or "").strip()
    if not _SAFE_ID.fullmatch(ident):
        raise ValueError(f"id must be a safe folder name (letters, digits, . _ -; not starting with . _ -), got {ident!r}")
    if _RESERVED_ID.fullmatch(ident):
        raise ValueError(f"id {ident!r} is the name of the cohort's summary; choose another")
    image = str(entry.get("image") or "").strip()
    if not image:
        raise ValueError("no image")
    points = str(entry.get("points") or "").strip() or None
    apex = None if entry.get("apex") in (None, "") else _numbers(entry["apex"], 3, "apex")
    base = None if entry.get("base") in (None, "") else _numbers(entry["base"], 3, "base")
    annulus = _point_list(entry.get("annulus"), "annulus")
    if annulus and len(annulus) < 3:
        raise ValueError(f"annulus needs 3 or more points, got {len(annulus)}")
    if points is None and (base is not None or annulus) and apex is None:
        raise ValueError("give apex and base (x y z, mm) or apex and annulus, or points (a markups file), or none "
                         "(the ventricle is located)")
    if points is None and apex is not None and base is None and not annulus:
        raise ValueError("give apex and base (x y z, mm) or apex and annulus, not the apex alone")
    spacing = None if entry.get("spacing") in (None, "") else _numbers(entry["spacing"], 3, "spacing")
    if spacing is not None and min(spacing) <= 0:
        raise ValueError(f"spacing must be positive, got {spacing}")
    resolve = lambda p: str(p if Path(p).is_absolute() else folder / p)  # noqa: E731
    return Study(id=ident, image=resolve(image), apex=apex, base=base, annulus=annulus,
                 landmarks=_point_list(entry.get("landmarks"), "landmarks"),
                 points=None if points is None else resolve(points), spacing=spacing, track=_flag(entry.get("track")),
                 glob=bool(_flag(entry.get("glob"), "glob")))


def read_manifest(path: str | os.PathLike) -> list[Study]:
    """Read the studies of a JSON or CSV manifest.

    JSON: a list of objects.  CSV: a header row and one row a study, a point
    written ``x y z``, landmarks ``x y z; x y z``.  Keys: ``id`` (unique, a
    safe folder name), ``image``, ``apex`` and ``base`` (mm, LPS), optional
    ``landmarks``, ``points`` (a markups file instead of apex/base),
    ``spacing``, ``track``, ``glob`` (``image`` is a pattern) and
    ``annulus`` (3 or more points of the mitral annulus instead of ``base``).  Relative paths are relative to the manifest's
    folder.  Input files are not opened here (a missing image fails its
    study, not the manifest).

    Raises
    ------
    ManifestError
        With the file, the entry and the reason.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise ManifestError(f"{path}: cannot read manifest ({exc.strerror})") from None
    except UnicodeDecodeError:
        raise ManifestError(f"{path}: a manifest must be UTF-8 text (JSON or CSV)") from None
    if path.suffix.lower() == ".json":
        try:
            entries = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ManifestError(f"{path}: not JSON ({exc.msg}, line {exc.lineno})") from None
        if not isinstance(entries, list):
            raise ManifestError(f"{path}: a JSON manifest must be a list of studies")
        where = lambda k: f"study {k + 1}"  # noqa: E731
    elif path.suffix.lower() == ".csv":
        reader = csv.DictReader(StringIO(text))
        if reader.fieldnames is None:
            raise ManifestError(f"{path}: empty CSV manifest (expected a header: {','.join(MANIFEST_KEYS)})")
        names = [name.strip() for name in reader.fieldnames]
        twice = sorted({name for name in names if names.count(name) > 1})
        if twice:  # the last would win silently
            raise ManifestError(f"{path}: column(s) {', '.join(twice)} appear twice in the header")
        entries = [{k.strip(): (v or "").strip() for k, v in row.items() if k is not None and (v or "").strip()}
                   for row in reader]
        where = lambda k: f"row {k + 2}"  # noqa: E731
    else:
        raise ManifestError(f"{path}: a manifest is .json or .csv, got {path.suffix or 'no suffix'}")
    if not entries:
        raise ManifestError(f"{path}: no studies")
    studies, seen = [], set()
    for k, entry in enumerate(entries):
        try:
            study = _study(entry, path.parent.resolve())
        except ValueError as exc:
            name = entry.get("id") if isinstance(entry, dict) else None
            raise ManifestError(f"{path}: {where(k)}{f' ({name})' if name else ''}: {exc}") from None
        if study.id.lower() in seen:
            raise ManifestError(f"{path}: {where(k)}: id {study.id!r} appears twice")
        seen.add(study.id.lower())
        studies.append(study)
    return studies


def select_shard(studies: list, shard: tuple[int, int] | None) -> list:
    """Studies ``i - 1, i - 1 + n, ...`` of shard ``(i, n)`` (1 <= i <= n); all if None."""
    if shard is None:
        return list(studies)
    i, n = shard
    if not (1 <= i <= n):
        raise ValueError(f"shard must be I/N with 1 <= I <= N, got {i}/{n}")
    return list(studies[i - 1::n])



def as_study(item, folder: Path) -> Study:
    """``item`` as a :class:`Study`: itself, or a manifest entry (relative
    paths from ``folder``)."""
    return item if isinstance(item, Study) else _study(item, folder)
