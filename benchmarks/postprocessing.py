"""Accuracy on echo post-processed as a scanner exports it, with and
without the intensity interface's model of the smoothing.

    python benchmarks/postprocessing.py                 # about 30 min on 2 cores
    python benchmarks/postprocessing.py --seeds 0       # a smoke run

Every setting of ``spheroseg.synthetic.phantom.POSTPROCESSINGS`` (and the raw
formations with the strongest contrasts, where the contrast bound binds,
and the narrow and wide point-spread functions, whose blurred edge the
band means' correction reads from the speckle) images the
scenes ``speckle`` and ``tilted`` of the formation sweep; each is segmented
with default options, and again with the smoothing's estimate held at 0
and no blur of the wall read from the speckle (the contrast bound alone, as
before).  Writes docs/postprocessing.json and
regenerates docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import machine, write_json  # noqa: E402
from report import write_markdown  # noqa: E402

from spheroseg.descent import speckle  # noqa: E402
from spheroseg.descent.dataterms import IntensityInterface  # noqa: E402
from spheroseg.surfaces.metrics import dice  # noqa: E402
from spheroseg.synthetic.phantom import FAMILIES, FORMATIONS, POSTPROCESSINGS, make_phantom  # noqa: E402
from spheroseg.tracking.segment import segment  # noqa: E402

#: raw formations with the most contrast (43 and 42 dB), where the contrast bound binds,
#: and the point-spread functions narrower and wider than the edge model's
RAW = ("blood_low", "contrast_high", "psf_narrow", "psf_wide")
#: the variants compared: the contrast bound alone (the smoothing's estimate held at 0), and now
VARIANTS = ("bound", "edge")


def settings():
    for name, options in POSTPROCESSINGS.items():
        yield name, dict(formation=FORMATIONS["default"], **options)
    for name in RAW:
        yield name, dict(formation=FORMATIONS[name])


def run(seeds) -> list:
    rows = []
    estimate = IntensityInterface.estimate_blur
    smoothing = {}

    def recorded(samples):
        smoothing["mm"], blur = estimate(samples)
        # the point-spread function's blur of the wall read from the speckle: the widest, along the image's axes
        smoothing["blur_mm"] = float(np.sqrt(np.max(np.diag(blur)))) if blur is not None else 0.0
        return (smoothing["mm"], blur) if smoothing["variant"] == "edge" else (0.0, None)

    IntensityInterface.estimate_blur = staticmethod(recorded)
    try:
        for name, options in settings():
            for k, family in enumerate(("speckle", "tilted")):
                for seed in seeds:
                    ph = make_phantom(seed=seed + 10 * k, **FAMILIES[family], **options)
                    row = {"setting": name, "family": family, "seed": seed + 10 * k, "truth_ml": ph.truth_volume_ml}
                    for variant in VARIANTS:
                        smoothing["variant"] = variant
                        r = segment(ph.volume, ph.apex, ph.base)
                        row[variant] = {"dice": dice(r.mask(ph.volume), ph.truth_mask),
                                        "volume_error_pct": 100 * (r.volume_ml / ph.truth_volume_ml - 1)}
                    row["smoothing_mm"] = smoothing["mm"]
                    row["edge_blur_mm"] = smoothing["blur_mm"]
                    rows.append(row)
                    print(name, family, seed + 10 * k, round(row["smoothing_mm"], 2),
                          {v: round(row[v]["volume_error_pct"], 2) for v in VARIANTS}, flush=True)
    finally:
        IntensityInterface.estimate_blur = staticmethod(estimate)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1], help="scene seeds (each family adds 10 per family)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    rows = run(args.seeds)
    command = "python benchmarks/postprocessing.py" + ("" if args.seeds == [0, 1] else
                                                       " --seeds " + " ".join(map(str, args.seeds)))
    data = {"command": command, "machine": machine(), "variants": list(VARIANTS),
            "max_contrast_db": speckle.MAX_CONTRAST_DB, "edge_psf_mm": speckle.EDGE_PSF_MM, "cases": rows,
            "wall_seconds": time.perf_counter() - t0}
    print("wrote", write_json("postprocessing.json", data))
    print("wrote", write_markdown())


if __name__ == "__main__":
    main()
