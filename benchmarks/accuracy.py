"""Accuracy against the exact truth of phantom families, for spheroseg's
data terms and the peers (scikit-image morphological Chan-Vese, SimpleITK
Chan-Vese dense level set), plus real CETUS Patient 7 (no truth).

    python benchmarks/accuracy.py            # about half an hour on 2 cores
    python benchmarks/accuracy.py --sweep    # the peers' parameter sweep
    python benchmarks/accuracy.py --quick    # 2 seeds, no peers: a smoke run

Writes docs/accuracy.json and regenerates docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import (  # noqa: E402
    DOCS, PEER_PARAMS, machine, mask_wall_mesh, run_sitk, run_skimage, score, write_json,
)
from report import write_markdown  # noqa: E402

from spheroseg.metrics import mask_volume_ml  # noqa: E402
from spheroseg.phantom import FAMILIES, make_phantom, make_sequence  # noqa: E402
from spheroseg.segment import segment, track  # noqa: E402
from spheroseg.volume import Volume  # noqa: E402

MODES = ("local", "chan-vese", "fast")
PEERS = {"skimage morphological_chan_vese": run_skimage, "SimpleITK ScalarChanAndVese": run_sitk}
PEER_KEY = {"skimage morphological_chan_vese": "skimage", "SimpleITK ScalarChanAndVese": "sitk"}


def spheroseg_case(volume, apex, base, mode):
    r = segment(volume, apex, base, mode=mode)
    return r, r.seconds


def run_case(ph, peers: bool) -> dict:
    out = {}
    for mode in MODES:
        r, seconds = spheroseg_case(ph.volume, ph.apex, ph.base, mode)
        out[f"spheroseg {mode}"] = {**score(r.mask(ph.volume), r.mesh(closed=False), r.volume_ml, ph), "seconds": seconds}
    if peers:
        for name, fn in PEERS.items():
            mask, seconds = fn(ph.volume, ph.apex, ph.base, **PEER_PARAMS[PEER_KEY[name]])
            ml = mask_volume_ml(mask, ph.volume.spacing)
            out[name] = {**score(mask, mask_wall_mesh(mask, ph.volume, ph.apex, ph.base), ml, ph), "seconds": seconds}
    return out


def run_cases(seeds, peers: bool) -> list:
    cases = []
    for family, seed in itertools.product(FAMILIES, seeds):
        ph = make_phantom(seed=seed, **FAMILIES[family])
        res = run_case(ph, peers)
        cases.append({"family": family, "seed": seed, "truth_ml": ph.truth_volume_ml, "results": res})
        print(family, seed, {k: round(v["dice"], 3) for k, v in res.items()}, flush=True)
    return cases


def sweep() -> dict:
    ph = make_phantom(seed=100, **FAMILIES["speckle"])
    results = {"skimage": [], "sitk": []}
    for sigma, n, smooth in itertools.product((0.0, 1.5), (30, 60), (1, 2, 3)):
        mask, t = run_skimage(ph.volume, ph.apex, ph.base, sigma_mm=sigma, num_iter=n, smoothing=smooth)
        d = score(mask, None, mask_volume_ml(mask, ph.volume.spacing), ph)["dice"]
        results["skimage"].append({"sigma_mm": sigma, "num_iter": n, "smoothing": smooth, "dice": d, "seconds": t})
        print("skimage", results["skimage"][-1], flush=True)
    for sigma, n, curv in itertools.product((0.0, 1.5, 3.0), (30, 60), (0.0, 0.2)):
        mask, t = run_sitk(ph.volume, ph.apex, ph.base, sigma_mm=sigma, num_iter=n, curvature=curv)
        d = score(mask, None, mask_volume_ml(mask, ph.volume.spacing), ph)["dice"]
        results["sitk"].append({"sigma_mm": sigma, "num_iter": n, "curvature": curv, "dice": d, "seconds": t})
        print("sitk", results["sitk"][-1], flush=True)
    return results


def cetus(peers: bool) -> dict | None:
    folder = Path(__file__).resolve().parents[2] / "shared" / "data" / "cetus"
    if not (folder / "Patient7_points.json").is_file():
        return None
    points = json.loads((folder / "Patient7_points.json").read_text())
    spacing = points["assumed_spacing_mm"]
    out = {"assumed_spacing_mm": spacing}
    for phase in ("ED", "ES"):
        vol = Volume(np.load(folder / points[phase]["file"]), spacing=(spacing,) * 3, no_data_value=0)
        apex = np.array(points[phase]["apex_index"][::-1], float) * spacing
        base = np.array(points[phase]["base_index"][::-1], float) * spacing
        for mode in MODES:
            r = segment(vol, apex, base, mode=mode)
            out.setdefault(f"spheroseg {mode}", {})[phase] = {"volume_ml": r.volume_ml, "seconds": r.seconds}
        if peers:
            for name, fn in PEERS.items():
                mask, seconds = fn(vol, apex, base, **PEER_PARAMS[PEER_KEY[name]])
                out.setdefault(name, {})[phase] = {"volume_ml": mask_volume_ml(mask, vol.spacing), "seconds": seconds}
    for phases in out.values():
        if isinstance(phases, dict) and "ED" in phases:
            ed, es = phases["ED"]["volume_ml"], phases["ES"]["volume_ml"]
            phases["ef_percent"] = 100 * (ed - es) / ed if ed > 0 else float("nan")
    return out


def sequences(seeds, peers: bool) -> list:
    rows = []
    for seed in seeds:
        seq = make_sequence(seed=seed, n_frames=10)
        first = seq.frames[0]
        t0 = time.perf_counter()
        tr = track(seq.volumes, first.apex, first.base)
        row = {"seed": seed, "truth_ef": seq.truth_ef,
               "spheroseg local (tracking)": {"ef": tr.ef, "seconds_per_frame": (time.perf_counter() - t0) / len(seq.frames)}}
        ed, es = int(np.argmax(seq.truth_volumes_ml)), int(np.argmin(seq.truth_volumes_ml))
        # the same question as the peers get: ED and ES segmented on their own
        # from the first frame's apex/base half-ellipsoid
        v = [segment(seq.frames[k].volume, first.apex, first.base).volume_ml for k in (ed, es)]
        row["spheroseg local (ED and ES frames)"] = {"ef": 100 * (v[0] - v[1]) / v[0]}
        if peers:
            for name, fn in PEERS.items():
                v = [mask_volume_ml(fn(seq.frames[k].volume, first.apex, first.base, **PEER_PARAMS[PEER_KEY[name]])[0],
                                    seq.frames[k].volume.spacing) for k in (ed, es)]
                row[f"{name} (ED and ES frames)"] = {"ef": 100 * (v[0] - v[1]) / v[0] if v[0] > 0 else float("nan")}
        rows.append(row)
        print("sequence", seed, {k: (v["ef"] if isinstance(v, dict) else v) for k, v in row.items()}, flush=True)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sweep", action="store_true", help="run the peers' parameter sweep on one case")
    ap.add_argument("--quick", action="store_true", help="2 seeds and no peers")
    ap.add_argument("--only", choices=["cases", "sequences", "cetus"],
                    help="recompute one part and keep the rest of docs/accuracy.json")
    args = ap.parse_args(argv)
    if args.only:
        data = json.loads((DOCS / "accuracy.json").read_text())
        peers = bool(data.get("peer_params"))
        seeds = sorted({c["seed"] for c in data["cases"]})
        if args.only == "cases":
            data["cases"] = run_cases(seeds, peers)
        elif args.only == "sequences":
            data["sequences"] = sequences(seeds, peers)
        else:
            data["cetus_patient7"] = cetus(peers)
        data["machine"] = machine()
        data["command"] = "python benchmarks/accuracy.py, then --only " + args.only
        print("wrote", write_json("accuracy.json", data))
        print("wrote", write_markdown())
        return
    if args.sweep:
        write_json("peer_sweep.json", {"machine": machine(), "case": "speckle seed 100", "results": sweep()})
        return
    seeds = (0, 1) if args.quick else (0, 1, 2, 3, 4)
    peers = not args.quick
    t0 = time.perf_counter()
    cases = run_cases(seeds, peers)
    data = {
        "command": "python benchmarks/accuracy.py" + (" --quick" if args.quick else ""),
        "machine": machine(), "peer_params": PEER_PARAMS, "cases": cases,
        "sequences": sequences(seeds, peers), "cetus_patient7": cetus(peers),
        "wall_seconds": time.perf_counter() - t0,
    }
    print("wrote", write_json("accuracy.json", data))
    print("wrote", write_markdown())


if __name__ == "__main__":
    main()
