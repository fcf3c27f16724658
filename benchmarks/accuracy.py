"""Accuracy against the exact truth of phantom families, for spheroseg's
data terms and the peers (scikit-image morphological Chan-Vese, SimpleITK
Chan-Vese dense level set), plus real CETUS Patient 7 (no truth).

    python benchmarks/accuracy.py                 # about half an hour on 2 cores
    python benchmarks/accuracy.py --peer-sweep    # the peers' parameter sweep
    python benchmarks/accuracy.py --quick         # 2 seeds, no peers: a smoke run
    python benchmarks/accuracy.py --sweep --label before   # image formations (a few minutes)
    python benchmarks/accuracy.py --sweep --label fitted-reference --smoothness-reference fitted

Writes docs/accuracy.json and regenerates docs/benchmarks.md.  ``--sweep``
segments the phantom scenes imaged by every named image formation
(``spheroseg.synthetic.phantom.FORMATIONS``) and tracks sequences with base descent,
with spheroseg's default options, and stores the run under ``--label`` in
docs/accuracy_sweep.json beside the runs already there (so 'before' and
'after' a change of method sit side by side); ``--smoothness-reference``
runs it with that option instead of the default.
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

from spheroseg.surfaces.metrics import mask_volume_ml  # noqa: E402
from spheroseg.synthetic.phantom import FAMILIES, FORMATIONS, make_phantom, make_sequence, sweep_cases  # noqa: E402
from spheroseg.descent.options import MODES as spheroseg_modes  # noqa: E402
from spheroseg.descent.options import SegmentOptions  # noqa: E402
from spheroseg.tracking.segment import segment, track  # noqa: E402
from spheroseg.volumes.volume import Volume  # noqa: E402

MODES = spheroseg_modes  # every data term, the default first
DEFAULT = SegmentOptions().mode
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


def formation_cases(**options) -> list:
    """spheroseg with default options (or ``options``) on scene families x image formations."""
    cases = []
    for family, name, kwargs in sweep_cases():
        ph = make_phantom(**kwargs)
        r = segment(ph.volume, ph.apex, ph.base, **options)
        row = {**score(r.mask(ph.volume), r.mesh(closed=False), r.volume_ml, ph),
               "volume_error_ml": r.volume_ml - ph.truth_volume_ml, "iterations": r.iterations,
               "converged": bool(r.converged), "seconds": r.seconds}
        cases.append({"family": family, "formation": name, "seed": kwargs["seed"], "truth_ml": ph.truth_volume_ml,
                      "result": row})
        print(family, name, {k: round(v, 3) if isinstance(v, float) else v for k, v in row.items()}, flush=True)
    return cases


#: (seed, base descent mm) of the tracked sequences of the formation sweep
SWEEP_SEQUENCES = ((0, 0.0), (1, 0.0), (2, 0.0), (0, 10.0), (1, 12.0), (2, 14.0))


def formation_sequences(**options) -> list:
    """Tracked EF on default-formation sequences, without and with base
    descent; and the end-systolic frame segmented on its own from its true
    apex and base (``fresh_esv_ml``)."""
    rows = []
    for seed, descent in SWEEP_SEQUENCES:
        seq = make_sequence(seed=seed, n_frames=10, base_descent=descent, formation=FORMATIONS["default"])
        first = seq.frames[0]
        tr = track(seq.volumes, first.apex, first.base, **options)
        truth = seq.truth_volumes_ml
        ed, es = int(np.argmax(truth)), int(np.argmin(truth))
        fresh = segment(seq.volumes[es], seq.frames[es].apex, seq.frames[es].base, **options)
        rows.append({"seed": seed, "base_descent_mm": descent, "truth_ef": seq.truth_ef, "tracked_ef": tr.ef,
                     "truth_edv_ml": truth[ed], "truth_esv_ml": truth[es], "tracked_edv_ml": tr.volumes_ml[ed],
                     "tracked_esv_ml": tr.volumes_ml[es], "fresh_esv_ml": fresh.volume_ml,
                     "seconds_per_frame": sum(f.seconds for f in tr.frames) / len(tr.frames)})
        print("sequence", {k: round(v, 2) for k, v in rows[-1].items()}, flush=True)
    return rows


def git_commit() -> str:
    import subprocess

    try:
        def git(*args):
            return subprocess.run(["git", *args], capture_output=True, text=True, check=True,
                                  cwd=Path(__file__).resolve().parent).stdout.strip()

        # the code measured is HEAD's only when neither the package nor the benchmarks have changes beside it
        changed = git("status", "--porcelain", "--untracked-files=no", "--", "../src", ".")
        return git("rev-parse", "--short", "HEAD") + (" with uncommitted changes" if changed else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def formation_sweep(label: str, smoothness_reference: str | None = None) -> None:
    path = DOCS / "accuracy_sweep.json"
    data = json.loads(path.read_text()) if path.is_file() else {"runs": {}}
    t0 = time.perf_counter()
    options = {} if smoothness_reference is None else {"smoothness_reference": smoothness_reference}
    command = f"python benchmarks/accuracy.py --sweep --label {label}" + "".join(
        f" --{k.replace('_', '-')} {v}" for k, v in options.items())
    run = {"command": command, "commit": git_commit(), "machine": machine(),
           "method": "spheroseg.segment / track with default options" + "".join(
               f", {k}={v!r}" for k, v in options.items()),
           "default_mode": SegmentOptions().mode, "options": options,
           "cases": formation_cases(**options), "sequences": formation_sequences(**options)}
    run["wall_seconds"] = time.perf_counter() - t0
    run["summary"] = summarise(run["cases"])
    data["runs"][label] = run
    data["formations"] = {name: vars(f) for name, f in FORMATIONS.items()}
    print("wrote", write_json("accuracy_sweep.json", data))
    print("wrote", write_markdown())


def summarise(cases) -> dict:
    """Medians and extremes per formation, per family and over all cases."""
    def stats(rows):
        r = [c["result"] for c in rows]
        ve = np.array([x["volume_error_pct"] for x in r])
        return {"n": len(r), "median_dice": float(np.median([x["dice"] for x in r])),
                "worst_dice": float(min(x["dice"] for x in r)),
                "median_msd_mm": float(np.nanmedian([x["msd_mm"] for x in r])),
                "median_volume_error_pct": float(np.median(ve)),
                "worst_volume_error_pct": float(ve[np.argmax(abs(ve))]),
                "median_volume_error_ml": float(np.median([x["volume_error_ml"] for x in r])),
                "median_iterations": float(np.median([x["iterations"] for x in r])),
                "median_seconds": float(np.median([x["seconds"] for x in r]))}

    def by(key):
        return {n: stats([c for c in cases if c[key] == n]) for n in dict.fromkeys(c[key] for c in cases)}

    return {"formation": by("formation"), "family": by("family"), "all": stats(cases)}


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
               f"spheroseg {DEFAULT} (tracking)": {"ef": tr.ef, "seconds_per_frame": (time.perf_counter() - t0) / len(seq.frames)}}
        ed, es = int(np.argmax(seq.truth_volumes_ml)), int(np.argmin(seq.truth_volumes_ml))
        # the same question as the peers get: ED and ES segmented on their own
        # from the first frame's apex/base half-ellipsoid
        v = [segment(seq.frames[k].volume, first.apex, first.base).volume_ml for k in (ed, es)]
        row[f"spheroseg {DEFAULT} (ED and ES frames)"] = {"ef": 100 * (v[0] - v[1]) / v[0]}
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
    ap.add_argument("--peer-sweep", action="store_true", help="run the peers' parameter sweep on one case")
    ap.add_argument("--sweep", action="store_true",
                    help="spheroseg (default options) across image formations and tracked sequences with base descent")
    ap.add_argument("--label", default="latest", help="name of the --sweep run in docs/accuracy_sweep.json")
    ap.add_argument("--smoothness-reference", choices=["start", "fitted"],
                    help="--sweep with this SegmentOptions.smoothness_reference (default: the default options)")
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
        formation_sweep(args.label, args.smoothness_reference)
        return
    if args.peer_sweep:
        write_json("peer_sweep.json", {"machine": machine(), "case": "speckle seed 100", "results": sweep()})
        return
    seeds = (0, 1) if args.quick else (0, 1, 2, 3, 4)
    peers = not args.quick
    t0 = time.perf_counter()
    cases = run_cases(seeds, peers)
    data = {
        "command": "python benchmarks/accuracy.py" + (" --quick" if args.quick else ""),
        "machine": machine(), "peer_params": PEER_PARAMS, "default_mode": DEFAULT, "cases": cases,
        "sequences": sequences(seeds, peers), "cetus_patient7": cetus(peers),
        "wall_seconds": time.perf_counter() - t0,
    }
    print("wrote", write_json("accuracy.json", data))
    print("wrote", write_markdown())


if __name__ == "__main__":
    main()
