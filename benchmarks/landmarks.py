"""How far the surface ends from a landmark put on the wall or off it, and
what holding the landmark harder would cost.

    python benchmarks/landmarks.py

A landmark is a point of the wall the surface is drawn to with a weight
(``landmark_weight``, 1 by default); ``quality["landmark_residuals_mm"]``
reports the distance from each to the final surface, and more than 2 mm is
a warning.  For phantoms of several image formations (2 seeds each, 1.5 mm
voxels), one landmark on the true wall at mid-height (a point a user would
click) and 8, 15 and 30 mm out from it along the outward radial direction
(a misclick): the residual, whether it is flagged, Dice and volume error, at
the default weight and held ten times harder (weight 10; 100 gives the same).

Writes docs/landmarks.json and regenerates docs/benchmarks.md.
"""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import machine, write_json  # noqa: E402
from report import write_markdown  # noqa: E402

from spheroseg import segment  # noqa: E402
from spheroseg.surfaces.metrics import dice  # noqa: E402
from spheroseg.synthetic.phantom import FORMATIONS, make_phantom  # noqa: E402

FORMATION_NAMES = ("default", "clutter_strong", "contrast_low", "dropout", "psf_wide")
SEEDS = (1, 2)
OFFSETS_MM = (0.0, 8.0, 15.0, 30.0)
WEIGHTS = (1.0, 10.0)


def wall_point(ph, seed):
    """A point of the true wall at mid-height, at an angle set by the seed,
    and the outward radial direction there."""
    axis = (ph.base - ph.apex) / np.linalg.norm(ph.base - ph.apex)
    points = ph.truth_mesh[0]
    rel = points - ph.apex
    height = rel @ axis
    radial = rel - np.outer(height, axis)
    angle = np.arctan2(radial @ np.cross(axis, [1.0, 0, 0]), radial @ [1.0, 0, 0])
    k = np.argmin(np.abs(height - 0.5 * height.max()) + 20 * np.abs(np.angle(np.exp(1j * (angle - 2.0 * seed)))))
    return points[k], radial[k] / np.linalg.norm(radial[k])


def main():
    rows = []
    for name in FORMATION_NAMES:
        for seed in SEEDS:
            ph = make_phantom(seed=seed, spacing=1.5, formation=FORMATIONS[name])
            wall, outward = wall_point(ph, seed)
            for offset in OFFSETS_MM:
                for weight in WEIGHTS:
                    r = segment(ph.volume, ph.apex, ph.base, landmarks=[wall + offset * outward],
                                landmark_weight=weight)
                    row = {"formation": name, "seed": seed, "offset_mm": offset, "weight": weight,
                           "residual_mm": r.quality["landmark_residuals_mm"][0],
                           "flagged": any("misses landmark" in w for w in r.quality["warnings"]),
                           "poor": r.quality["poor"], "dice": dice(r.mask(ph.volume), ph.truth_mask),
                           "volume_error_pct": 100 * (r.volume_ml / ph.truth_volume_ml - 1)}
                    rows.append(row)
                    print(row)
    write_json("landmarks.json", {"command": "python benchmarks/landmarks.py", "machine": machine(),
                                  "formations": list(FORMATION_NAMES), "seeds": list(SEEDS), "rows": rows})
    print("wrote", write_markdown())


if __name__ == "__main__":
    main()
