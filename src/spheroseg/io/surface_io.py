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

from . import write_atomically
from ..surfaces.surface import Surface

__all__ = ["read_mesh", "write_mesh", "write_surface_json", "read_surface_json", "write_cmiss", "write_cmiss_heart"]


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
    binary with ``SPACE=LPS`` in its header line for 3D Slicer.  The same
    mesh gives the same bytes (meshio's dated PLY and OBJ comments are replaced).
    """
    import meshio

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".vtk", ".ply", ".stl", ".obj"):
        raise ValueError(f"{path}: mesh format must be .vtk, .ply, .stl or .obj")
    mesh = meshio.Mesh(np.asarray(points, float), [("triangle", np.asarray(faces, np.int32))])

    def write(tmp: Path) -> None:
        if suffix == ".obj":
            meshio.write(tmp, mesh)
        else:
            meshio.write(tmp, mesh, binary=True)
        if suffix == ".vtk":
            head, rest = tmp.read_bytes().split(b"\n", 1)
            _, rest = rest.split(b"\n", 1)
            tmp.write_bytes(head + b"\nspheroseg cavity mesh, SPACE=LPS, units mm\n" + rest)
        elif suffix == ".ply":
            data = tmp.read_bytes()
            start = data.index(b"\ncomment Created by meshio")
            end = data.index(b"\n", start + 1)
            tmp.write_bytes(data[:start] + b"\ncomment spheroseg cavity mesh, LPS, mm" + data[end:])
        elif suffix == ".obj":
            _, rest = tmp.read_bytes().split(b"\n", 1)
            tmp.write_bytes(b"# spheroseg cavity mesh, LPS, mm\n" + rest)

    write_atomically(path, write)


def write_surface_json(path: str | os.PathLike, surface: Surface, **extra) -> None:
    """The surface model (system, pose, Hermite coefficients) as JSON."""
    text = json.dumps({**surface.to_dict(), **extra}, indent=1)
    write_atomically(path, lambda tmp: tmp.write_text(text))


def read_surface_json(path: str | os.PathLike) -> Surface:
    try:
        return Surface.from_dict(json.loads(Path(path).read_text()))
    except (OSError, KeyError, TypeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not a spheroseg surface file ({exc})") from exc


def _cmiss_header(focus: float) -> str:
    return (
        f" #Fields=1\n"
        f" 1) coordinates, coordinate, prolate spheroidal, focus= {focus:.16e}, #Components=3\n"
    )


def write_cmiss(stem: str | os.PathLike, surface: Surface, *, group: str = "spheroseg") -> tuple[Path, Path]:
    """Write the surface as a CMISS/OpenCMISS ``.exnode``/``.exelem`` pair.

    The field ``coordinates`` is prolate spheroidal with ``focus=`` the
    focal length (mm), in the model's local frame (x along the long axis,
    ``mu = 0`` at the apex; the pose to world space is in the JSON output).
    ``lambda`` is ``c.Hermite*c.Hermite`` over ``xi1 = theta``,
    ``xi2 = mu``; ``mu`` and ``theta`` are ``l.Lagrange*l.Lagrange``.
    No scale factors are written, so nodal derivatives are per unit xi:
    the Hermite slopes times the element widths.  The theta seam has its
    own column of nodes at ``theta = 2 pi`` (same lambda parameters as
    ``theta = 0``), and every apex node has ``mu = 0``: a single point.

    Returns the two paths written.
    """
    return _write_cmiss(stem, surface, [surface.coefficients], group)


def write_cmiss_heart(stem: str | os.PathLike, endocardium: Surface, epicardium: Surface, *,
                      group: str = "spheroseg_heart") -> tuple[Path, Path]:
    """Write the myocardium as CMISS/OpenCMISS volume elements.

    As :func:`write_cmiss`, with a second layer of nodes on the epicardium
    and 3D elements between the layers (Hunter's prolate spheroidal heart
    models): ``lambda`` is ``c.Hermite*c.Hermite*l.Lagrange`` over
    ``xi1 = theta``, ``xi2 = mu``, ``xi3`` from the endocardium (0) to the
    epicardium (1); ``mu`` and ``theta`` are trilinear Lagrange.  The two
    surfaces must share the system, the pose and the Hermite grid.

    Returns the two paths written.
    """
    same = (endocardium.system == epicardium.system and endocardium.grid.shape == epicardium.grid.shape
            and tuple(endocardium.grid.v2_range) == tuple(epicardium.grid.v2_range)
            and np.allclose(endocardium.pose.origin, epicardium.pose.origin)
            and np.allclose(endocardium.pose.rotation, epicardium.pose.rotation))
    if not same:
        raise ValueError("the endocardium and the epicardium must share the coordinate system, the pose and the grid")
    return _write_cmiss(stem, endocardium, [endocardium.coefficients, epicardium.coefficients], group)


def _write_cmiss(stem, surface: Surface, layers: list, group: str) -> tuple[Path, Path]:
    """The exnode/exelem pair of one layer of nodes (2D elements) or two
    (3D elements, linear between them) on ``surface``'s grid."""
    from ..geometry.coords import ProlateSpheroidal

    if not isinstance(surface.system, ProlateSpheroidal):
        raise ValueError(f"CMISS export needs prolate spheroidal coordinates, not {surface.system.name}")
    stem = Path(stem)
    grid = surface.grid
    n1, n2 = grid.n1, grid.n2
    d_theta = 2 * np.pi / n1
    d_mu = (grid.v2_range[1] - grid.v2_range[0]) / n2
    scale = np.array([1.0, d_theta, d_mu, d_theta * d_mu])
    per_layer = (n2 + 1) * (n1 + 1)
    node_id = lambda r, j, k=0: k * per_layer + r * (n1 + 1) + j + 1  # noqa: E731

    lines = [f" Group name: {group}\n", _cmiss_header(surface.system.focal_length),
             "   lambda.  Value index= 1, #Derivatives= 3 (d/ds1,d/ds2,d2/ds1ds2)\n",
             "   mu.  Value index= 5, #Derivatives= 0\n",
             "   theta.  Value index= 6, #Derivatives= 0\n"]
    for k, c in enumerate(layers):
        for r, mu in enumerate(grid.node_v2):
            for j in range(n1 + 1):
                lam = c[r, j % n1] * scale
                lines.append(f" Node: {node_id(r, j, k)}\n")
                lines.append("  " + " ".join(f"{v: .16e}" for v in lam) + "\n")
                lines.append(f"  {mu: .16e}\n  {j * d_theta: .16e}\n")
    exnode = "".join(lines)

    dimension = 2 if len(layers) == 1 else 3
    count = 2**dimension
    across = "" if dimension == 2 else "*l.Lagrange"

    def component(name, basis, values):
        out = [f"   {name}.  {basis}, no modify, standard node based.\n", f"     #Nodes= {count}\n"]
        for k in range(1, count + 1):
            out.append(f"      {k}.  #Values={values}\n")
            out.append("       Value indices: " + " ".join(str(v + 1) for v in range(values)) + "\n")
            out.append("       Scale factor indices: " + " ".join("0" for _ in range(values)) + "\n")
        return "".join(out)

    lines = [f" Group name: {group}\n", f" Shape.  Dimension={dimension}\n", " #Scale factor sets= 0\n",
             f" #Nodes= {count}\n", _cmiss_header(surface.system.focal_length),
             component("lambda", "c.Hermite*c.Hermite" + across, 4),
             component("mu", "l.Lagrange*l.Lagrange" + across, 1),
             component("theta", "l.Lagrange*l.Lagrange" + across, 1)]
    element = 1
    for r in range(n2):
        for j in range(n1):
            nodes = [node_id(r + a, j + b, k) for k in range(len(layers)) for a in (0, 1) for b in (0, 1)]
            lines.append(f" Element: {element} 0 0\n   Nodes:\n    " + " ".join(map(str, nodes)) + "\n")
            element += 1
    exelem = "".join(lines)

    paths = (stem.with_suffix(".exnode"), stem.with_suffix(".exelem"))
    for path, text in zip(paths, (exnode, exelem)):
        write_atomically(path, lambda tmp, text=text: tmp.write_text(text))
    return paths
