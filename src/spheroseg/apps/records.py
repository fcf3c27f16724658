"""The records of a cohort: each study's checksum (what its results were
made from), its summary row, and the cohort's summary files."""

from __future__ import annotations

import csv
import hashlib
import json
import os
from io import StringIO
from pathlib import Path

import numpy as np

from .manifest import Study

__all__ = ["study_checksum", "summary_row", "write_summary", "SUMMARY_FIELDS"]

#: columns of ``summary.json`` / ``summary.csv``
SUMMARY_FIELDS = ("id", "status", "kind", "volume_ml", "edv_ml", "esv_ml", "ef", "iterations", "descent_status",
                  "poor", "quality", "seconds", "error")

def study_checksum(study: Study, options: dict) -> str:
    """SHA-256 of the study's entry, the options and the bytes of every input
    file (an image's data file, a folder's files, the markups); a missing
    file counts as missing, so the study runs and fails with its reason.
    The thread count is left out: it changes no result."""
    from ..io import image_files

    digest = hashlib.sha256()
    options = {k: v for k, v in options.items() if k != "threads"}
    digest.update(json.dumps({"study": study.as_entry(), "options": options}, sort_keys=True).encode())
    for path in image_files(study.image, glob=study.glob) + ([Path(study.points)] if study.points else []):
        digest.update(f"\0{path.name}\0".encode())
        try:
            with open(path, "rb") as handle:
                for block in iter(lambda: handle.read(1 << 20), b""):
                    digest.update(block)
        except OSError:
            digest.update(b"\0missing\0")
    return digest.hexdigest()


def summary_row(results: dict) -> dict:
    """A study's summary line from its ``results.json`` content."""
    tracked = "edv_ml" in results
    iterations = results.get("iterations")
    seconds = results.get("seconds", {})
    return {
        "id": results.get("id"), "status": "ok", "kind": "track" if tracked else "segment",
        "volume_ml": None if tracked else results.get("volume_ml"),
        "edv_ml": results.get("edv_ml"), "esv_ml": results.get("esv_ml"), "ef": results.get("ef_percent"),
        "iterations": int(np.sum(iterations)) if iterations is not None else None,
        # why the descent stopped (0 converged, 1 iteration cap, ...), when the result records it
        "descent_status": results.get("status"), "poor": (results.get("quality") or {}).get("poor"),
        "quality": results.get("quality"),
        "seconds": float(seconds.get("load", 0.0) + np.sum(seconds.get("segment", 0.0))),
        "error": None,
    }



def write_summary(out: str | os.PathLike, rows: list[dict], *, name: str = "summary") -> tuple[Path, Path]:
    """Write ``out/<name>.json`` (a list of rows) and ``out/<name>.csv``
    (``quality`` as JSON text), each atomically."""
    from ..io import write_atomically
    from ..io.outputs import write_json

    out = Path(out)
    rows = [{k: row.get(k) for k in SUMMARY_FIELDS} for row in rows]
    write_json(out / f"{name}.json", rows)
    text = StringIO()
    writer = csv.DictWriter(text, fieldnames=SUMMARY_FIELDS, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: ("" if v is None else json.dumps(v) if isinstance(v, (dict, list)) else v)
                         for k, v in row.items()})
    write_atomically(out / f"{name}.csv", lambda tmp: tmp.write_text(text.getvalue()))
    return out / f"{name}.json", out / f"{name}.csv"
