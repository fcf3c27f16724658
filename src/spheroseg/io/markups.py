"""3D Slicer markups files (``.mrk.json``): the points a segmentation
starts from (apex, base, mitral annulus, landmarks), in LPS millimetres."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .atomic import write_atomically
from .images import ImageFileError

__all__ = ["read_markups", "write_markups", "points_with_markups", "MARKUPS_UNITS"]


#: millimetres per unit of a markups file's ``coordinateUnits``
MARKUPS_UNITS = {"mm": 1.0, "um": 1e-3, "\u00b5m": 1e-3, "\u03bcm": 1e-3, "cm": 10.0, "m": 1000.0}


def _markups_scale(markup, path) -> float:
    """Millimetres per unit of one markup's ``coordinateUnits`` (mm when absent)."""
    units = markup.get("coordinateUnits", "mm")
    names = {str(u).strip().lower() for u in (units if isinstance(units, list) else [units])}
    if len(names) != 1 or next(iter(names)) not in MARKUPS_UNITS:
        raise ImageFileError(f"{path}: coordinateUnits must be one of {', '.join(MARKUPS_UNITS)}, got {units!r}")
    return MARKUPS_UNITS[names.pop()]


def read_markups(path: str | os.PathLike) -> dict:
    """Points from a 3D Slicer markups file (``.mrk.json``), in LPS mm.

    Control points labelled ``apex`` and ``base`` (any case) give those;
    every label starting with ``annulus`` is a point of the mitral annulus
    (three or more define the mitral plane), every label starting with
    ``landmark`` a landmark.  RAS files are converted to LPS, and
    ``coordinateUnits`` (``um``, ``mm``, ``cm``, ``m``; mm when absent) to
    millimetres; another ``coordinateSystem`` (``IJK``) is refused, as is
    a used point whose ``positionStatus`` is not ``defined``.

    Returns
    -------
    dict
        ``{"apex": array or None, "base": array or None, "annulus": array (k, 3),
        "landmarks": array (k, 3), "labels": every control point's label}``

    Raises
    ------
    ValueError
        For a file that is not markups, unknown units, ``apex`` or ``base``
        labelled twice, or a point spheroseg uses whose ``positionStatus``
        is ``"undefined"`` (listed in Slicer but never placed: its position
        is meaningless).
    """
    import json

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    try:
        doc = json.loads(path.read_text(encoding="utf-8-sig"))  # a byte-order mark, as manifests
        out = {"apex": None, "base": None, "annulus": [], "landmarks": [], "labels": []}
        for markup in doc["markups"]:
            system = str(markup.get("coordinateSystem", "LPS")).strip().upper()
            if system not in ("LPS", "RAS"):
                raise ImageFileError(f"{path}: coordinateSystem must be LPS or RAS, got "
                                     f"{markup.get('coordinateSystem')!r}")
            ras = system == "RAS"
            scale = _markups_scale(markup, path)
            for point in markup.get("controlPoints", []):
                label = str(point.get("label", "")).strip().lower()
                out["labels"].append(str(point.get("label", "")))
                used = label in ("apex", "base") or label.startswith(("annulus", "landmark"))
                if not used:
                    continue
                status = str(point.get("positionStatus", "defined")).strip().lower()
                if status == "undefined":
                    raise ImageFileError(f"{path}: control point {label!r} has positionStatus 'undefined' (never "
                                         "placed); place it in Slicer or delete it")
                if status != "defined":  # "preview": being placed, not placed
                    raise ImageFileError(f"{path}: control point {label!r} has positionStatus "
                                         f"{point.get('positionStatus')!r}, not 'defined'; place it in Slicer")
                position = scale * np.asarray(point["position"], dtype=float).reshape(3)
                if ras:
                    position = position * [-1.0, -1.0, 1.0]
                if label in ("apex", "base"):
                    if out[label] is not None:
                        raise ImageFileError(f"{path}: two control points labelled {label!r}; keep one")
                    out[label] = position
                elif label.startswith("annulus"):
                    out["annulus"].append(position)
                else:
                    out["landmarks"].append(position)
    except ImageFileError:
        raise
    except OSError as exc:
        raise ValueError(f"{path}: cannot read markups ({exc.strerror})") from None
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise ValueError(f"{path}: not a 3D Slicer markups file with control points ({type(exc).__name__}: {exc})") from None
    out["landmarks"] = np.array(out["landmarks"]).reshape(-1, 3)
    out["annulus"] = np.array(out["annulus"]).reshape(-1, 3)
    return out


def points_with_markups(points_file=None, *, apex=None, base=None, landmarks=(), annulus=()):
    """The starting points of a segmentation: those given, completed from a
    markups file (given points win; the file's landmarks are added).

    A markups file is given for its points: one that leaves the apex, or
    both the base and the annulus, unknown (Slicer's default labels ``F-1``,
    ``F-2``, a misspelt label, no control points) is refused with the
    labels it has, never read as "no points" (the ventricle would be
    located instead, silently).  The one place ``segment``, ``track`` and
    ``batch`` read their points file.

    Returns
    -------
    apex, base : array or None
    landmarks, annulus : list of arrays
    """
    landmarks, annulus = list(landmarks), list(annulus)
    if points_file is None:
        return apex, base, landmarks, annulus
    marks = read_markups(points_file)
    apex = marks["apex"] if apex is None else apex
    base = marks["base"] if base is None else base
    landmarks += list(marks["landmarks"])
    annulus = annulus or list(marks["annulus"])
    if apex is None or (base is None and len(annulus) == 0):
        labels = ", ".join(repr(label) for label in marks["labels"][:6]) + (", ..." if len(marks["labels"]) > 6 else "")
        has = f"its labels are {labels}" if labels else "it has no control points"
        raise ImageFileError(f"{points_file}: no control points labelled apex and base (or annulus...); {has}: "
                             "label the points apex and base in Slicer")
    return apex, base, landmarks, annulus


def write_markups(path: str | os.PathLike, *, apex=None, base=None, annulus=None, landmarks=None) -> None:
    """Write points as a 3D Slicer markups file (``.mrk.json``, LPS mm) that
    :func:`read_markups` reads back: control points labelled ``apex``,
    ``base``, ``annulus`` (each annulus point) and ``landmark-1``, ...

    Parameters
    ----------
    path : str or Path
    apex, base : (x, y, z), optional
    annulus, landmarks : array (k, 3), optional
    """
    import json

    named = [("apex", apex), ("base", base)]
    named += [("annulus", p) for p in ([] if annulus is None else annulus)]
    named += [(f"landmark-{k + 1}", p) for k, p in enumerate([] if landmarks is None else landmarks)]
    points = []
    for label, position in named:
        if position is None:
            continue
        position = np.asarray(position, dtype=float)
        if position.shape != (3,) or not np.all(np.isfinite(position)):
            raise ValueError(f"{label} must be 3 finite numbers (x, y, z in mm), got {position.tolist()!r}")
        points.append({"id": str(len(points) + 1), "label": label, "position": position.tolist(),
                       "positionStatus": "defined"})
    doc = {"@schema": "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/Resources/"
                      "Schema/markups-schema-v1.0.3.json#",
           "markups": [{"type": "Fiducial", "coordinateSystem": "LPS", "coordinateUnits": "mm",
                        "controlPoints": points}]}
    write_atomically(path, lambda tmp: Path(tmp).write_text(json.dumps(doc, indent=1)))
