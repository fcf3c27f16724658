"""Tracked EF at frame rates from 4 to 20 frames a cycle, and from
end-diastole to end-systole directly.

    python benchmarks/framerate.py               # about 15 min on 2 shared cores
    python benchmarks/framerate.py --seeds 0 1
    python benchmarks/framerate.py --speed       # the tracking speed only (a minute)
    python benchmarks/framerate.py --pairs       # ED-ES pairs of every formation (5 min)
    python benchmarks/framerate.py --formations  # 4, 5 and 6 frames a cycle of every formation (12 min)

Each seed's cycle (default formation, the annulus descending 10 mm at
end-systole) is made at 20 frames and tracked with every frame, every 2nd
(10 a cycle) and every 5th (4 a cycle), and as the pair ED, ES; a 6-frame
cycle of the same heart is made and tracked too.  ``spheroseg.track`` with
default options from the first frame's apex and base.  ``--speed``: the
throughput of tracking the legacy 10-frame cycle (as benchmarks/speed.py
measures it) with every frame segmented again (the default) and with none,
interleaved.  ``--pairs``: the pair ED, ES alone (1.5 mm voxels, seeds 0,
1 and 3) of every named formation and of the default one post-processed
as a scanner exports it (the export grids aside), tracked.
``--formations``: the seed-3 cycle of every named formation at 4 and 5
frames a cycle (every 5th and 4th of 20) and made at 6, tracked.
Writes docs/framerate.json and regenerates docs/benchmarks.md.
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

from spheroseg.synthetic.phantom import FORMATIONS, POSTPROCESSINGS, make_sequence  # noqa: E402
from spheroseg.tracking.segment import track  # noqa: E402
from spheroseg.tracking.tracker import Tracker  # noqa: E402

SEGMENTED_AGAIN = []  # the frames the tracker segmented again, counted through its call


def _counting(segment_again):
    def counted(tracker, start, **options):
        SEGMENTED_AGAIN.append(1)
        return segment_again(tracker, start, **options)
    return counted


Tracker.segment_again = _counting(Tracker.segment_again)

DESCENT_MM = 10.0


def tracked(frames) -> dict:
    t0 = time.perf_counter()
    SEGMENTED_AGAIN.clear()
    tr = track([f.volume for f in frames], frames[0].apex, frames[0].base)
    truth = np.array([f.truth_volume_ml for f in frames])
    truth_ef = float((truth.max() - truth.min()) / truth.max() * 100)
    errors = 100 * (tr.volumes_ml / truth - 1)
    return {"frames": len(frames), "truth_ef": truth_ef, "tracked_ef": float(tr.ef),
            "ef_error": float(tr.ef - truth_ef), "esv_error_pct": float(errors[int(np.argmin(truth))]),
            "edv_error_pct": float(errors[int(np.argmax(truth))]),
            "poor_frames": int(sum(bool(f.quality["poor"]) for f in tr.frames)),
            "min_base_radius_mm": float(min(f.surface.base_radii().min() for f in tr.frames)),
            "segmented_again": len(SEGMENTED_AGAIN),
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


PAIR_SEEDS = (0, 1, 3)


def pairs() -> list:
    """End-diastole to end-systole directly, tracked, for every formation
    and post-processing (:data:`PAIR_SEEDS`, 1.5 mm voxels)."""
    settings = [(name, {"formation": formation}) for name, formation in FORMATIONS.items()]
    settings += [(f"default, {name}", {"formation": FORMATIONS["default"], **extra})
                 for name, extra in POSTPROCESSINGS.items() if name != "raw" and "spacing" not in extra]
    rows = []
    for name, kwargs in settings:
        for seed in PAIR_SEEDS:
            seq = make_sequence(seed=seed, n_frames=2, spacing=1.5, base_descent=DESCENT_MM, **kwargs)
            rows.append({"setting": name, "seed": seed, **tracked(seq.frames)})
            print(rows[-1], flush=True)
    return rows


FORMATION_SEED = 3


def formations() -> list:
    """The cycle of every formation at 4, 5 and 6 frames a cycle
    (:data:`FORMATION_SEED`, the default voxels)."""
    rows = []
    for name, formation in FORMATIONS.items():
        seq = make_sequence(seed=FORMATION_SEED, n_frames=20, base_descent=DESCENT_MM, formation=formation)
        six = make_sequence(seed=FORMATION_SEED, n_frames=6, base_descent=DESCENT_MM, formation=formation)
        for sampling, frames in (("4 a cycle", seq.frames[::5]), ("5 a cycle", seq.frames[::4]),
                                 ("6 a cycle", six.frames)):
            rows.append({"setting": name, "sampling": sampling, **tracked(frames)})
            print(rows[-1], flush=True)
    return rows


def speed(repeats: int = 3) -> dict:
    """Volumes per second stepping the legacy 10-frame cycle at 5 iterations
    a frame, with the frames whose wall was left behind or moved far
    segmented again (the default), with every frame and with none (the tracker's options
    without ``coarse_to_fine`` after the first frame, which the
    re-segmentation needs); and whole ``track`` runs."""
    import os
    from dataclasses import replace

    seq = make_sequence(seed=0, n_frames=10)
    first = seq.frames[0]
    times = {"where the wall was left behind or moved far (the default)": [], "every frame": [], "none": []}
    load = os.getloadavg()[0]
    followed_the_wall = Tracker.followed_the_wall
    for _ in range(repeats):
        for name, rows in times.items():
            tracker = Tracker(seq.volumes[0], first.apex, first.base)
            tracker.run()
            if name == "none":
                tracker.options = replace(tracker.options, coarse_to_fine=False)
            Tracker.followed_the_wall = (lambda tracker: False) if name == "every frame" else followed_the_wall
            t0 = time.perf_counter()
            steps = [tracker.next_frame(volume, max_iterations=5) for volume in seq.volumes[1:]]
            seconds = time.perf_counter() - t0
            Tracker.followed_the_wall = followed_the_wall
            volumes = np.array([s.volume_ml for s in steps])
            rows.append((seconds, volumes))
    t0 = time.perf_counter()
    whole = track(seq.volumes, first.apex, first.base)
    out = {name: {"volumes_per_second_5": (len(seq.volumes) - 1) / float(np.median([r[0] for r in rows])),
                  "esv_ml": float(rows[0][1].min())} for name, rows in times.items()}
    return {"policies": out, "track_volumes_per_second": len(seq.volumes) / (time.perf_counter() - t0),
            "ef": whole.ef, "truth_ef": seq.truth_ef, "truth_esv_ml": float(seq.truth_volumes_ml.min()),
            "load_start": load, "load_end": os.getloadavg()[0], "date": time.strftime("%Y-%m-%d %H:%M")}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--speed", action="store_true", help="measure the tracking speed only")
    ap.add_argument("--pairs", action="store_true", help="the ED-ES pairs of every formation only")
    ap.add_argument("--formations", action="store_true", help="4, 5 and 6 frames a cycle of every formation only")
    args = ap.parse_args(argv)
    if args.speed or args.pairs or args.formations:
        import json

        path = Path(__file__).resolve().parents[1] / "docs" / "framerate.json"
        data = json.loads(path.read_text()) if path.is_file() else {}
        if args.speed:
            data["speed"] = speed()
            print(data["speed"], flush=True)
        else:
            t0 = time.perf_counter()
            name = "pairs" if args.pairs else "formations"
            data[name] = {"command": f"python benchmarks/framerate.py --{name}", "machine": machine(),
                          "rows": (pairs if args.pairs else formations)(), "wall_seconds": time.perf_counter() - t0}
        print("wrote", write_json("framerate.json", data))
        print("wrote", write_markdown())
        return
    t0 = time.perf_counter()
    rows = run(args.seeds)
    command = "python benchmarks/framerate.py" + ("" if args.seeds == [0] else
                                                  " --seeds " + " ".join(map(str, args.seeds)))
    data = {"command": command, "machine": machine(), "base_descent_mm": DESCENT_MM, "rows": rows,
            "wall_seconds": time.perf_counter() - t0}
    previous = Path(__file__).resolve().parents[1] / "docs" / "framerate.json"
    if previous.is_file():  # the speed of --speed, measured on its own
        import json

        data.update({k: v for k, v in json.loads(previous.read_text()).items() if k in ("speed", "pairs", "formations")})
    print("wrote", write_json("framerate.json", data))
    print("wrote", write_markdown())


if __name__ == "__main__":
    main()
