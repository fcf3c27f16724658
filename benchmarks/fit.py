"""How well 4 x 4, 8 x 8 and 16 x 16 Hermite patches represent real ventricles:
least-squares fits to the CETUS Patient 1 expert meshes (read from ../shared),
with the model posed by the apex-base line (before) and by the mitral plane
(after, `Surface.from_annulus`).

    python benchmarks/fit.py

Writes docs/fit.json and regenerates docs/benchmarks.md.
"""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import machine, write_json  # noqa: E402
from report import write_markdown  # noqa: E402

from spheroseg.geometry.coords import annulus_plane  # noqa: E402
from spheroseg.surfaces.fit import (annulus_of_open_mesh, apex_base_of_open_mesh, fit_surface,  # noqa: E402
                          point_to_surface_distance)
from spheroseg.surfaces.surface import Surface  # noqa: E402
from spheroseg.io.surface_io import read_mesh  # noqa: E402

CETUS = Path(__file__).resolve().parents[2] / "shared" / "data" / "cetus"
HELD_OUT = 0.2  # fraction of the vertices left out of the fit and measured


def main():
    rows, geometry = [], []
    for phase in ("ED", "ES"):
        path = CETUS / f"Patient1_{phase}_truth.vtk"
        if not path.is_file():
            print(f"{path} not available")
            return
        points, faces = read_mesh(path)
        points = points * 1000.0
        apex, base = apex_base_of_open_mesh(points, faces)
        ring = annulus_of_open_mesh(points, faces)
        centre, normal = annulus_plane(ring)
        line = (apex - base) / np.linalg.norm(apex - base)
        height = abs((apex - centre) @ normal)
        geometry.append({
            "phase": phase, "vertices": len(points), "ring_vertices": len(ring),
            "ring_rms_off_plane_mm": float(np.sqrt(np.mean(((ring - centre) @ normal) ** 2))),
            "axis_angle_deg": float(np.degrees(np.arccos(abs(line @ normal)))),
            "apex_height_mm": float(height),
            "apex_off_axis_mm": float(np.sqrt(np.sum((apex - centre) ** 2) - height**2))})
        print(geometry[-1])
        held = np.random.default_rng(0).random(len(points)) < HELD_OUT
        poses = {"apex-base line": Surface.from_apex_base(apex, base), "mitral plane": Surface.from_annulus(apex, ring)}
        for pose_name, init in poses.items():
            for patches in ((4, 4), (8, 8), (16, 16)):
                fitted = fit_surface(points, system=init.system, pose=init.pose, patches=patches)
                d = point_to_surface_distance(points, fitted)
                inside = fitted.pose.to_local(points)[:, 0] >= -0.01  # on the apex side of the base plane
                part = fit_surface(points[~held], system=init.system, pose=init.pose, patches=patches)
                dh = point_to_surface_distance(points[held], part)
                rows.append({"phase": phase, "pose": pose_name, "patches": f"{patches[0]} x {patches[1]}",
                             "mean_mm": float(d.mean()), "max_mm": float(d.max()),
                             "max_in_range_mm": float(d[inside].max()), "beyond_base_plane": int((~inside).sum()),
                             "held_out_mean_mm": float(dh.mean()), "held_out_max_mm": float(dh.max()),
                             "volume_ml": fitted.volume_ml()})
                print(rows[-1])
    write_json("fit.json", {"command": "python benchmarks/fit.py", "machine": machine(), "held_out": HELD_OUT,
                            "geometry": geometry, "rows": rows})
    print("wrote", write_markdown())


if __name__ == "__main__":
    main()
