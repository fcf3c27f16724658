"""How well 4 x 4, 8 x 8 and 16 x 16 Hermite patches represent real ventricles:
least-squares fits to the CETUS Patient 1 expert meshes (read from ../shared).

    python benchmarks/fit.py

Writes docs/fit.json and regenerates docs/benchmarks.md.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import machine, write_json  # noqa: E402
from report import write_markdown  # noqa: E402

from spheroseg.fit import apex_base_of_open_mesh, fit_surface, point_to_surface_distance, surface_sample  # noqa: E402
from spheroseg.surface import Surface  # noqa: E402
from spheroseg.surface_io import read_mesh  # noqa: E402

CETUS = Path(__file__).resolve().parents[2] / "shared" / "data" / "cetus"


def main():
    rows = []
    for phase in ("ED", "ES"):
        path = CETUS / f"Patient1_{phase}_truth.vtk"
        if not path.is_file():
            print(f"{path} not available")
            return
        points, faces = read_mesh(path)
        points = points * 1000.0
        apex, base = apex_base_of_open_mesh(points, faces)
        init = Surface.from_apex_base(apex, base)
        target = surface_sample(points, faces, spacing=1.0)
        for patches in ((4, 4), (8, 8), (16, 16)):
            fitted = fit_surface(target, system=init.system, pose=init.pose, patches=patches)
            d = point_to_surface_distance(points, fitted)
            _, _, v2 = fitted.model_coordinates(points)
            inside = v2 <= fitted.grid.v2_range[1]
            rows.append({"phase": phase, "patches": f"{patches[0]} x {patches[1]}", "mean_mm": float(d.mean()),
                         "max_mm": float(d.max()), "max_in_range_mm": float(d[inside].max()),
                         "volume_ml": fitted.volume_ml()})
            print(rows[-1])
    write_json("fit.json", {"command": "python benchmarks/fit.py", "machine": machine(), "rows": rows})
    print("wrote", write_markdown())


if __name__ == "__main__":
    main()
