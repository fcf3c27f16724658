"""Accuracy on echo of another making: speckle that does not show the blur
of its walls.

    python benchmarks/simulators.py          # about 2 min on 2 cores

Many simulators blur the scene's mean intensity and multiply it by speckle
independent from voxel to voxel (`spheroseg.synthetic.echo.multiplicative_speckle`);
a scanner's speckle is the point-spread function's own size, and the
phantom's (`spheroseg.synthetic.echo.form_image`) too.  The scene: a half
ellipsoidal cavity (semi-axes 22, 22 and 70 mm, closed at the base plane;
blood 30 dB below the myocardium), an 8 mm wall, and tissue beyond it 12 dB
darker than the wall, as bright, or 6 dB brighter; 1 mm voxels, blurred by
an isotropic Gaussian of 0.5-3 mm (standard deviation).  Each is segmented
with default options from the true apex and base ('profile', now), and
again with the wall's blur read from the speckle alone ('speckle', as
before: `spheroseg.descent.speckle.profile_blur_mm` giving the speckle's back).
Writes docs/simulators.json and regenerates docs/benchmarks.md.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import machine, write_json  # noqa: E402
from report import write_markdown  # noqa: E402

from spheroseg import Volume  # noqa: E402
from spheroseg.descent import dataterms, speckle
from spheroseg import segment
from spheroseg.descent.dataterms import IntensityInterface  # noqa: E402
from spheroseg.tracking.epicardium import DARK_WALL  # noqa: E402
from spheroseg.synthetic.echo import multiplicative_speckle  # noqa: E402

BLURS_MM = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0)
#: the tissue beyond the wall, dB relative to the wall
TISSUE_DB = (-12.0, 0.0, 6.0)
SEEDS = (0, 1)
VARIANTS = ("speckle", "profile")
SHAPE, CENTRE, AXES, WALL_MM = (110, 80, 80), np.array([40.0, 40.0, 90.0]), np.array([22.0, 22.0, 70.0]), 8.0


def scene(blur_mm: float, tissue_db: float, seed: int):
    """The image (x, y, z world mm = voxel index), the apex and base points, the true cavity volume (mL)."""
    k, j, i = np.mgrid[:SHAPE[0], :SHAPE[1], :SHAPE[2]].astype(float)
    offset = np.stack([i, j, k], axis=-1) - CENTRE

    def within(axes):
        return (offset**2 / axes**2).sum(axis=-1) <= 1

    below = k <= CENTRE[2]
    cavity = within(AXES) & below
    wall = within(AXES + WALL_MM) & below & ~cavity
    echogenicity = np.where(cavity, 1e-3, np.where(wall, 1.0, 10 ** (tissue_db / 10)))
    grey = multiplicative_speckle(echogenicity, blur_mm=blur_mm, spacing=1.0, seed=seed)
    truth_ml = 2 / 3 * np.pi * AXES.prod() / 1000
    return Volume(grey), CENTRE - [0, 0, AXES[2]], CENTRE.copy(), truth_ml


def run() -> list:
    rows, read = [], {}
    unblurred = IntensityInterface.unblurred_levels

    def recorded(*args, **kwargs):
        levels = unblurred(*args, **kwargs)
        read["mm"] = levels[3]  # the wall's blur removed
        return levels

    profile_blur = dataterms.profile_blur_mm
    IntensityInterface.unblurred_levels = staticmethod(recorded)
    try:
        for blur in BLURS_MM:
            for tissue_db in TISSUE_DB:
                for seed in SEEDS:
                    volume, apex, base, truth_ml = scene(blur, tissue_db, seed)
                    row = {"blur_mm": blur, "tissue_db": tissue_db, "seed": seed}
                    for variant in VARIANTS:
                        dataterms.profile_blur_mm = (profile_blur if variant == "profile"
                                                     else lambda profile, *, sigma_mm, **_: sigma_mm)
                        r = segment(volume, apex, base)
                        row[variant] = {"volume_error_pct": 100 * (r.volume_ml / truth_ml - 1),
                                        "blur_read_mm": read["mm"], "poor": bool(r.quality["poor"]),
                                        "dark_wall": DARK_WALL in r.quality["warnings"]}
                    rows.append(row)
                    print(blur, tissue_db, seed, {v: round(row[v]["volume_error_pct"], 2) for v in VARIANTS},
                          round(row["profile"]["blur_read_mm"], 2), flush=True)
    finally:
        dataterms.profile_blur_mm = profile_blur
        IntensityInterface.unblurred_levels = staticmethod(unblurred)
    return rows


def main() -> None:
    t0 = time.perf_counter()
    rows = run()
    data = {"command": "python benchmarks/simulators.py", "machine": machine(), "variants": list(VARIANTS),
            "max_edge_blur_mm": speckle.MAX_EDGE_BLUR_MM, "rows": rows, "wall_seconds": time.perf_counter() - t0}
    print("wrote", write_json("simulators.json", data))
    print("wrote", write_markdown())


if __name__ == "__main__":
    main()
