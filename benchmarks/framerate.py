"""Tracked EF at frame rates from 4 to 20 frames a cycle, and from
end-diastole to end-systole directly.

    python benchmarks/framerate.py               # about 15 min on 2 shared cores
    python benchmarks/framerate.py --seeds 0 1

Each seed's cycle (default formation, the annulus descending 10 mm at
end-systole) is made at 20 frames and tracked with every frame, every 2nd
(10 a cycle) and every 5th (4 a cycle), and as the pair ED, ES; a 6-frame
cycle of the same heart is made and tracked too.  ``spheroseg.track`` with
default options from the first frame's apex and base.  Writes
docs/framerate.json and regenerates docs/benchmarks.md.
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

from spheroseg.phantom import FORMATIONS, make_sequence  # noqa: E402
from spheroseg.segment import track  # noqa: E402

DESCENT_MM = 10.0


def tracked(frames) -> dict:
    t0 = time.perf_counter()
    tr = track([f.volume for f in frames], frames[0].apex, frames[0].base)
    truth = np.array([f.truth_volume_ml for f in frames])
    truth_ef = float((truth.max() - truth.min()) / truth.max() * 100)
    errors = 100 * (tr.volumes_ml / truth - 1)
    return {"frames": len(frames), "truth_ef": truth_ef, "tracked_ef": float(tr.ef),
            "ef_error": float(tr.ef - truth_ef), "esv_error_pct": float(errors[int(np.argmin(truth))]),
            "edv_error_pct": float(errors[int(np.argmax(truth))]),
            "poor_frames": int(sum(bool(f.quality["poor"]) for f in tr.frames)),
            "min_base_radius_mm": float(min(f.surface.base_radii().min() for f in tr.frames)),
            "seconds_per_frame": (time.perf_counter() - t0) / len(frames)}


def run(seeds) -> list:
    rows = []
    for seed in seeds:
        seq = make_sequence(seed=seed, n_frames=20, base_descent=DESCENT_MM, formation=FORMATIONS["default"])
        frames = seq.frames
        es = int(np.argmin(seq.truth_volumes_ml))
        for name, chosen in (("20 a cycle", frames), ("10 a cycle", frames[::2]), ("4 a cycle", frames[::5]),
                             ("ED to ES", [frames[0], frames[es]])):
            rows.append({"seed": seed, "sampling": name, **tracked(chosen)})
            print(rows[-1], flush=True)
        six = make_sequence(seed=seed, n_frames=6, base_descent=DESCENT_MM, formation=FORMATIONS["default"])
        rows.append({"seed": seed, "sampling": "6 a cycle", **tracked(six.frames)})
        print(rows[-1], flush=True)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    rows = run(args.seeds)
    command = "python benchmarks/framerate.py" + ("" if args.seeds == [0] else
                                                  " --seeds " + " ".join(map(str, args.seeds)))
    data = {"command": command, "machine": machine(), "base_descent_mm": DESCENT_MM, "rows": rows,
            "wall_seconds": time.perf_counter() - t0}
    print("wrote", write_json("framerate.json", data))
    print("wrote", write_markdown())


if __name__ == "__main__":
    main()
