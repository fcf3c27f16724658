"""Finding the ventricle without clicks (issue 29): located apex and base
against the truth, segmentation from them, the time it takes, CETUS.

    python benchmarks/locate.py [--cases 16] [--beam-cases 8]

Cases: seeded random phantoms (2 mm voxels), each with its own tilt
(0-25 degrees), long axis (60-100 mm), radius (0.26-0.38 of it), phase (ED,
or ES: radius 0.7 as large, wall 13.5 mm instead of 9) and image formation
(the 16 of the formation sweep in turn).  For each: ``locate`` (least time
of two after a first call, apex and base errors, confidence), then
``segment(volume)`` with no points (Dice against the true mask, volume
error, whether it was flagged poor).  The tilted mitral scenes (the plane at
0, 15 and 30 degrees to the long axis): the same.  Beam-space cases (seeded
likewise, every third formation): ``locate`` on the beam-space volume (time,
apex and base errors).  Ringed cases (seeded likewise): ``locate`` with the
dark pools ignored, so that every case goes by its ringed sections (the
fallback for a pool joined to the dark around it).  CETUS Patient 7 (0.9 mm
assumed): located against
the clicked points, and the volumes without points against the clicked ones.

Writes docs/locate.json and regenerates docs/benchmarks.md.
"""

import argparse
import importlib
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import machine, write_json  # noqa: E402
from report import write_markdown  # noqa: E402

from spheroseg import NoVentricleError, Volume  # noqa: E402
from spheroseg import locate, segment
from spheroseg.surfaces.metrics import dice  # noqa: E402
from spheroseg.synthetic.phantom import FORMATIONS, make_phantom, tilted_mitral_scene  # noqa: E402

CETUS = Path(__file__).resolve().parents[2] / "shared" / "data" / "cetus"
DEVSET = Path(__file__).resolve().parents[2] / "shared" / "data" / "devset"


def _timed(function, *args):
    """The least time (s) of two calls after a first, and the result."""
    function(*args)
    times = []
    for _ in range(2):
        t0 = time.perf_counter()
        result = function(*args)
        times.append(time.perf_counter() - t0)
    return min(times), result


def scenes(n: int, seed: int, *, every: int = 1):
    """Seeded random ventricles: ``(formation name, phase, make_phantom keywords)``,
    the formations taken ``every`` one of the sweep in turn."""
    rng = np.random.default_rng(seed)
    names = list(FORMATIONS)
    for k in range(n):
        tilt, length = rng.uniform(0, 25), rng.uniform(60, 100)
        radius = length * rng.uniform(0.26, 0.38)
        phase = "ES" if k % 2 else "ED"
        wall = 9.0
        if phase == "ES":
            radius, wall = 0.7 * radius, 13.5
        name = names[(every * k) % len(names)]
        yield name, phase, dict(seed=int(rng.integers(10_000)), spacing=2.0, tilt_deg=tilt, length=length,
                                radius=radius, wall=wall, formation=FORMATIONS[name])


def _without_points(row: dict, volume, apex, base, truth_mask, truth_ml, *, clicks=None) -> dict:
    """``row`` with ``locate(volume)`` against the true ``apex`` and
    ``base`` (time, errors, confidence, scores) and ``segment(volume)`` with
    no points against the truth (Dice, volume error, whether flagged poor),
    and, given ``clicks`` (apex, base), what checking them said; printed."""
    try:
        row["locate_s"], found = _timed(locate, volume)
    except NoVentricleError as error:
        row.update(refused=str(error))
        print(row, flush=True)
        return row
    row.update(apex_mm=float(np.linalg.norm(found.apex - apex)), base_mm=float(np.linalg.norm(found.base - base)),
               confidence=found.confidence, reason=found.reason, scores=found.scores, measures=found.measures)
    result = segment(volume)
    row.update(dice=float(dice(result.mask(volume), truth_mask)),
               volume_error_pct=100 * (result.volume_ml / truth_ml - 1), poor=result.quality["poor"],
               warnings=result.quality["warnings"])
    if clicks is not None:
        from spheroseg.locate import check_points

        row["clicks_flagged"] = (check_points(found, *clicks) if found.confidence >= 0.5 else
                                 ["not checked: low confidence"])
    print({k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()
           if k not in ("scores", "measures", "warnings")}, flush=True)
    return row


def phantom_cases(n: int, seed: int = 29) -> list[dict]:
    rows = []
    for name, phase, scene in scenes(n, seed):
        ph = make_phantom(**scene)
        row = {"formation": name, "phase": phase, "tilt_deg": scene["tilt_deg"], "truth_ml": ph.truth_volume_ml}
        rows.append(_without_points(row, ph.volume, ph.apex, ph.base, ph.truth_mask, ph.truth_volume_ml))
    return rows


def devset(directory: Path = DEVSET, *, every: int = 3):
    """The development set's volumes: ``(name, family, phase, image path,
    cavity truth path, case dict of the volume (true_landmarks, clicks,
    true_volume_ml))``: each single volume, and every ``every``-th frame of
    the sequence (None when ``directory`` lacks it)."""
    if not (directory / "index.json").is_file():
        return None
    out = []
    for folder in sorted(p for p in directory.iterdir() if (p / "case.json").is_file()):
        case = json.loads((folder / "case.json").read_text())
        if case["kind"] == "single":
            out.append((folder.name, case["family"], case["phase"], folder / case["files"]["image"],
                        folder / case["files"]["endocardium"], case))
        else:
            for frame in case["frames"][::every]:
                phase = {case["ed_frame"]: "ED", case["es_frame"]: "ES"}.get(frame["frame"],
                                                                             f"{frame['cycle_fraction']:.2f}")
                out.append((f"{folder.name}[{frame['frame']}]", case["family"], phase, folder / frame["files"]["image"],
                            folder / frame["files"]["endocardium"], frame))
    return out


def devset_cases() -> list[dict] | None:
    from spheroseg.io import load

    cases = devset()
    if cases is None:
        return None
    rows = []
    for name, family, phase, image, endocardium, case in cases:
        volume = load(image)
        truth = np.asarray(load(endocardium, no_data_value=None).array) > 0.5
        landmarks, clicks = case["true_landmarks"], case["clicks"]
        row = {"case": name, "family": family, "phase": phase, "truth_ml": case["true_volume_ml"]}
        rows.append(_without_points(row, volume, np.array(landmarks["apex_mm"]), np.array(landmarks["base_mm"]), truth,
                                    case["true_volume_ml"],
                                    clicks=(np.array(clicks["apex_mm"]), np.array(clicks["base_mm"]))))
    return rows


def mitral_cases(tilts=(0.0, 15.0, 30.0)) -> list[dict]:
    rows = []
    for tilt in tilts:
        scene = tilted_mitral_scene(tilt)
        found = locate(scene.volume)
        result = segment(scene.volume)
        row = {"tilt_deg": tilt, "apex_mm": float(np.linalg.norm(found.apex - scene.apex)),
               "base_mm": float(np.linalg.norm(found.base - scene.base)), "confidence": found.confidence,
               "dice": float(dice(result.mask(scene.volume), scene.truth_mask)),
               "volume_error_pct": 100 * (result.volume_ml / scene.truth_ml - 1), "poor": result.quality["poor"]}
        rows.append(row)
        print({k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)
    return rows


def beam_cases(n: int, seed: int = 7) -> list[dict]:
    rows = []
    for name, phase, scene in scenes(n, seed, every=3):
        ph = make_phantom(**scene, beam_space=True)
        row = {"formation": name, "phase": phase, "tilt_deg": scene["tilt_deg"],
               "shape": list(ph.beam_volume.array.shape)}
        rows.append(_located(row, ph.beam_volume, ph, timed=True))
    return rows


def _located(row: dict, volume, phantom, *, timed: bool = False) -> dict:
    """``row`` with the located apex's and base's errors against
    ``phantom``'s and the confidence (and the time, ``timed``), or why
    ``volume`` was refused; printed."""
    try:
        if timed:
            row["locate_s"], found = _timed(locate, volume)
        else:
            found = locate(volume)
        row.update(apex_mm=float(np.linalg.norm(found.apex - phantom.apex)),
                   base_mm=float(np.linalg.norm(found.base - phantom.base)), confidence=found.confidence)
    except NoVentricleError as error:
        row["refused"] = str(error)
    print({k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)
    return row


def ringed_cases(n: int, seed: int = 41) -> list[dict]:
    """The random ventricles located by the ringed sections alone (the dark
    pools ignored, as if each had joined the dark around it): how the
    fallback for images whose pool is no ventricle does where the truth is
    known."""
    from unittest import mock

    module = importlib.import_module("spheroseg.locate")
    rows = []
    with mock.patch.object(module, "_pool", lambda *args, **kwargs: None):
        for name, phase, scene in scenes(n, seed):
            ph = make_phantom(**scene)
            rows.append(_located({"formation": name, "phase": phase, "tilt_deg": scene["tilt_deg"]}, ph.volume, ph))
    return rows


def patient7(directory: Path = CETUS) -> dict | None:
    """CETUS Patient 7 as ``{phase: (volume, apex, base)}`` (0.9 mm assumed,
    the clicked points in world mm), or None when ``directory`` lacks it."""
    points_file = directory / "Patient7_points.json"
    if not points_file.is_file():
        return None
    points = json.loads(points_file.read_text())
    spacing = points["assumed_spacing_mm"]
    out = {}
    for phase in ("ED", "ES"):
        p = points[phase]
        volume = Volume(np.load(directory / p["file"]), spacing=(spacing,) * 3, no_data_value=0)
        out[phase] = (volume, *(np.array(p[k][::-1], float) * spacing for k in ("apex_index", "base_index")))
    return out


def cetus() -> dict | None:
    cases = patient7()
    if cases is None:
        return None
    out = {}
    for phase, (volume, apex, base) in cases.items():
        clicked = segment(volume, apex, base, check=False).volume_ml
        row = {"clicked_ml": clicked}
        try:
            found = locate(volume)
            row.update(apex_mm=float(np.linalg.norm(found.apex - apex)),
                       base_mm=float(np.linalg.norm(found.base - base)), confidence=found.confidence,
                       reason=found.reason, located_ml=segment(volume).volume_ml)
        except NoVentricleError as error:
            row["refused"] = str(error)
        checked = segment(volume, apex, base)
        row["clicks_flagged"] = checked.quality["warnings"]
        out[phase] = row
        print(phase, row, flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=16)
    ap.add_argument("--beam-cases", type=int, default=8)
    args = ap.parse_args()
    segment(make_phantom(seed=0, spacing=3.0).volume)  # compile the kernels outside the timings
    data = {"command": f"python benchmarks/locate.py --cases {args.cases} --beam-cases {args.beam_cases}",
            "machine": machine(), "cases": phantom_cases(args.cases), "devset": devset_cases(),
            "mitral": mitral_cases(), "beam": beam_cases(args.beam_cases), "ringed": ringed_cases(args.cases),
            "cetus_patient7": cetus()}
    write_json("locate.json", data)
    print("wrote", write_markdown())


if __name__ == "__main__":
    main()
