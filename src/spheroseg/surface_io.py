"""Surfaces to and from files: triangle meshes and the model as JSON.

Meshes are written through meshio (.vtk, .ply, .stl, .obj) in world mm, LPS
(ITK physical space); legacy ASCII VTK gets ``SPACE=LPS`` in its header
line so 3D Slicer places it on the image.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from .surface import Surface

__all__ = ["read_mesh", "write_mesh", "write_surface_json", "read_surface_json", "atomic_path"]


def atomic_path(path: str | os.PathLike):
    """Context manager giving a temporary path beside ``path`` that is
    renamed onto ``path`` when the block ends without error."""
    from contextlib import contextmanager

    @contextmanager
    def _ctx():
        target = Path(path)
        tmp = target.with_name(f".{target.stem}.tmp{os.getpid()}{''.join(target.suffixes)}")
        try:
            yield tmp
            os.replace(tmp, target)
        finally:
            if tmp.exists():
                tmp.unlink()

    return _ctx()


def _read_legacy_vtk_polydata(path: Path) -> tuple[np.ndarray, np.ndarray]:
    tokens = path.read_text().split()
    try:
        i = tokens.index("POINTS")
        n = int(tokens[i + 1])
        points = np.array(tokens[i + 3 : i + 3 + 3 * n], dtype=float).reshape(n, 3)
        j = tokens.index("POLYGONS")
        m, size = int(tokens[j + 1]), int(tokens[j + 2])
        cells = np.array(tokens[j + 3 : j + 3 + size], dtype=np.int64)
    except (ValueError, IndexError) as exc:
        raise ValueError(f"{path}: not a legacy VTK POLYDATA mesh with POINTS and POLYGONS") from exc
    faces, k = [], 0
    for _ in range(m):
        cnt = cells[k]
        poly = cells[k + 1 : k + 1 + cnt]
        faces += [[poly[0], poly[t], poly[t + 1]] for t in range(1, cnt - 1)]  # fan-split polygons
        k += cnt + 1
    return points, np.array(faces, dtype=np.int64)


def read_mesh(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle mesh: ``(points [n, 3], faces [m, 3])``.

    Anything meshio reads, plus legacy ASCII VTK POLYDATA (the CETUS
    reference meshes), which meshio does not.  Units are the file's.
    """
    import meshio

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such file")
    head = path.open("rb").read(256)
    if path.suffix.lower() == ".vtk" and b"POLYDATA" in head:
        return _read_legacy_vtk_polydata(path)
    try:
        mesh = meshio.read(path)
    except Exception as exc:  # meshio raises many types
        raise ValueError(f"{path}: cannot read mesh ({exc})") from exc
    tri = [c.data for c in mesh.cells if c.type == "triangle"]
    if not tri:
        raise ValueError(f"{path}: no triangles in mesh")
    return np.asarray(mesh.points, dtype=float), np.concatenate(tri).astype(np.int64)


def write_mesh(path: str | os.PathLike, points: np.ndarray, faces: np.ndarray) -> None:
    """Write a triangle mesh (world mm, LPS) with meshio, atomically.

    The format follows the suffix (.vtk, .ply, .stl, .obj); legacy VTK is
    binary with ``SPACE=LPS`` in its header line for 3D Slicer.
    """
    import meshio

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".vtk", ".ply", ".stl", ".obj"):
        raise ValueError(f"{path}: mesh format must be .vtk, .ply, .stl or .obj")
    mesh = meshio.Mesh(np.asarray(points, float), [("triangle", np.asarray(faces, np.int32))])
    with atomic_path(path) as tmp:
        if suffix == ".obj":
            meshio.write(tmp, mesh)
        else:
            meshio.write(tmp, mesh, binary=True)
        if suffix == ".vtk":
            head, rest = tmp.read_bytes().split(b"\n", 1)
            _, rest = rest.split(b"\n", 1)
            tmp.write_bytes(head + b"\nspheroseg cavity mesh, SPACE=LPS, units mm\n" + rest)


def write_surface_json(path: str | os.PathLike, surface: Surface, **extra) -> None:
    """The surface model (system, pose, Hermite coefficients) as JSON."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps({**surface.to_dict(), **extra}, indent=1))


def read_surface_json(path: str | os.PathLike) -> Surface:
    try:
        return Surface.from_dict(json.loads(Path(path).read_text()))
    except (OSError, KeyError, TypeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not a spheroseg surface file ({exc})") from exc
