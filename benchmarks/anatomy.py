"""Volume bias with papillary muscles and a trabecular rim in the cavity.

    python benchmarks/anatomy.py            # about 8 min on 2 shared cores

The scenes ``speckle`` and ``tilted`` (seeds 0, 1 and 10, 11) of the
default formation, plain, with papillary muscles, and with the muscles and
a 3 mm trabecular rim (``make_phantom(papillary=True, trabecular_mm=3)``;
the truth follows the compact wall).  ``spheroseg.segment`` with default
options.  Writes docs/anatomy.json and regenerates docs/benchmarks.md.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import machine, write_json  # noqa: E402
from report import write_markdown  # noqa: E402

from spheroseg.surfaces.metrics import dice  # noqa: E402
from spheroseg.synthetic.phantom import FAMILIES, FORMATIONS, make_phantom  # noqa: E402
from spheroseg.tracking.segment import segment  # noqa: E402

ANATOMY = {"plain": {}, "papillary muscles": dict(papillary=True),
           "muscles and 3 mm trabeculae": dict(papillary=True, trabecular_mm=3.0)}


def main() -> None:
    t0 = time.perf_counter()
    rows = []
    for k, family in enumerate(("speckle", "tilted")):
        for seed in (0, 1):
            for name, options in ANATOMY.items():
                ph = make_phantom(seed=seed + 10 * k, formation=FORMATIONS["default"], **FAMILIES[family], **options)
                r = segment(ph.volume, ph.apex, ph.base)
                rows.append({"anatomy": name, "family": family, "seed": seed + 10 * k,
                             "dice": dice(r.mask(ph.volume), ph.truth_mask),
                             "volume_error_pct": 100 * (r.volume_ml / ph.truth_volume_ml - 1)})
                print(rows[-1], flush=True)
    data = {"command": "python benchmarks/anatomy.py", "machine": machine(), "rows": rows,
            "wall_seconds": time.perf_counter() - t0}
    print("wrote", write_json("anatomy.json", data))
    print("wrote", write_markdown())


if __name__ == "__main__":
    main()
