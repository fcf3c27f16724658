"""The myocardium (issue 33): the epicardium, LV mass and the 17 segments on
phantoms with exact truth.

    python benchmarks/myocardium.py [--quick]
    python benchmarks/myocardium.py --sequences  # the tracked cycles only
    python benchmarks/myocardium.py --figure     # docs/segments.png only

1. Across image formations (`spheroseg.synthetic.phantom.sweep_cases`, the upright
   and the tilted ventricle, 1 mm voxels): myocardial Dice against the
   phantom's wall below the mitral plane, LV mass error against its exact
   volume at 1.05 g/mL, and the wall time of `segment(..., myocardium=True)`
   over that of the endocardium alone (the same call without it; both
   without the points' check).
2. A tracked 10-frame cycle whose wall has a late region
   (`LateRegion`, 10 % of the cycle late): mass at ED and ES, the
   segmental volume curves' latest segment and the SDI against the truth
   (the truth's cavity voxels labelled by the same 17-segment definition in
   the frame of the true apex and base).

Writes docs/myocardium.json and regenerates docs/benchmarks.md; with
``--figure``, docs/segments.png: the segment convention.
"""

import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import DOCS, machine, write_json  # noqa: E402
from report import write_markdown  # noqa: E402

from spheroseg import Pose, track  # noqa: E402
from spheroseg import segment
from spheroseg.surfaces.metrics import dice  # noqa: E402
from spheroseg.surfaces.myocardium import segment_labels, systolic_dyssynchrony_index, times_to_minimum  # noqa: E402
from spheroseg.synthetic.phantom import FORMATIONS, LateRegion, make_phantom, make_sequence, sweep_cases  # noqa: E402

SWEEP = ("default", "psf_wide", "dr_40", "gain_+6", "tgc_over", "contrast_high", "contrast_low", "clutter_strong")


def sweep_rows(formations):
    rows = []
    for family, name, kwargs in sweep_cases(formations=formations):
        ph = make_phantom(epicardium=True, **kwargs)
        # wall time of the calls without the points' check (the same locate()
        # in both), the least of 5 each, interleaved after a warm-up: the machine is shared
        segment(ph.volume, ph.apex, ph.base, check=False)
        endo, myo = [], []
        for _ in range(5):
            for times, myocardium in ((endo, False), (myo, True)):
                started = time.perf_counter()
                res = segment(ph.volume, ph.apex, ph.base, check=False, myocardium=myocardium)
                times.append(time.perf_counter() - started)
        res = segment(ph.volume, ph.apex, ph.base, myocardium=True)
        mass_error = 100 * (res.lv_mass_g / ph.truth_lv_mass_g - 1)
        row = {"family": family, "formation": name, "seed": kwargs["seed"],
               "dice": dice(res.myocardium_mask(ph.volume), ph.truth_myocardium_mask),
               "mass_g": res.lv_mass_g, "truth_mass_g": ph.truth_lv_mass_g, "mass_error_pct": mass_error,
               "cavity_error_pct": 100 * (res.volume_ml / ph.truth_volume_ml - 1),
               "endo_seconds": min(endo), "myo_seconds": min(myo),
               "polarity": res.parameters["epicardium"]["polarity"], "poor": bool(res.quality["poor"]),
               "thickness_median_mm": res.quality["epicardium"]["thickness_median_mm"]}
        rows.append(row)
        print({k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)
    return rows


def truth_curves(seq) -> np.ndarray:
    """Cavity volume per segment at every frame from the truth masks."""
    curves = []
    for ph in seq.frames:
        pose = Pose.from_apex_base(ph.apex, ph.base)
        k, j, i = np.nonzero(ph.truth_mask)
        local = pose.to_local(ph.volume.index_to_world(np.stack([i, j, k], -1).astype(float)))
        labels = segment_labels(local, length=float(np.linalg.norm(ph.apex - ph.base)))
        curves.append(np.bincount(labels, minlength=18)[1:] * np.prod(ph.volume.spacing) / 1000)
    return np.array(curves)


def sequence_row(seed: int):
    seq = make_sequence(n_frames=10, seed=seed, formation=FORMATIONS["default"], epicardium=True,
                        late_region=LateRegion(theta=1.0, half_width=np.pi / 3, delay=0.1))
    started = time.perf_counter()
    tracked = track(seq.volumes, seq.frames[0].apex, seq.frames[0].base, myocardium=True)
    seconds = time.perf_counter() - started
    truth = truth_curves(seq)
    masses, truth_masses = tracked.masses_g, np.array([f.truth_lv_mass_g for f in seq.frames])
    ed, es = 0, int(np.argmin(tracked.volumes_ml))
    times, truth_times = tracked.times_to_minimum, times_to_minimum(truth[:, :16])
    return {"seed": seed, "seconds": seconds, "masses_g": masses.tolist(), "truth_masses_g": truth_masses.tolist(),
            "ed_es_mass_difference_pct": 100 * abs(masses[es] - masses[ed]) / masses[ed],
            "truth_ed_es_mass_difference_pct": 100 * abs(truth_masses[es] - truth_masses[ed]) / truth_masses[ed],
            "times_to_minimum": times.tolist(), "truth_times_to_minimum": truth_times.tolist(),
            "late_segment": int(np.argmax(times)) + 1, "truth_late_segment": int(np.argmax(truth_times)) + 1,
            "sdi": tracked.sdi, "truth_sdi": systolic_dyssynchrony_index(truth),
            "ef": tracked.ef, "truth_ef": seq.truth_ef}


def convention_figure(path):
    """The segments' convention: a basal short-axis section in the model's
    frame seen from the apex, and the bull's-eye."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from spheroseg.io.report import draw_bullseye

    theta0 = np.radians(40.0)
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4.8))
    for k in range(6):
        edge = theta0 + np.radians(-60.0 + 60.0 * k)
        left.plot([1.0 * np.cos(edge), 1.6 * np.cos(edge)], [1.0 * np.sin(edge), 1.6 * np.sin(edge)], "k-", lw=1)
        mid = edge + np.radians(30.0)
        left.text(1.3 * np.cos(mid), 1.3 * np.sin(mid), str(k + 1), ha="center", va="center")
    ring = np.linspace(0, 2 * np.pi, 200)
    for r in (1.0, 1.6):
        left.plot(r * np.cos(ring), r * np.sin(ring), "k-", lw=1)
    septum = theta0 + np.radians(np.linspace(0, 120, 60))
    left.fill(np.r_[1.7 * np.cos(septum), 2.6 * np.cos(septum[::-1])],
              np.r_[1.7 * np.sin(septum), 2.6 * np.sin(septum[::-1])], color="0.85")
    left.text(2.2 * np.cos(theta0 + np.radians(60)), 2.2 * np.sin(theta0 + np.radians(60)), "RV", ha="center")
    left.annotate("", (1.9, 0), (0, 0), arrowprops=dict(arrowstyle="->"))
    left.text(1.95, -0.15, "x2 (theta = 0)")
    left.annotate("", (0, 1.9), (0, 0), arrowprops=dict(arrowstyle="->"))
    left.text(0.05, 1.95, "x3")
    left.plot([0, 2.7 * np.cos(theta0)], [0, 2.7 * np.sin(theta0)], "r--", lw=1)
    left.text(2.75 * np.cos(theta0), 2.75 * np.sin(theta0), "rv_insertion\n(psi = 0)", color="r", fontsize=8)
    arc = theta0 + np.radians(np.linspace(5, 55, 20))
    left.plot(0.75 * np.cos(arc), 0.75 * np.sin(arc), "b-")
    left.annotate("", (0.75 * np.cos(arc[-1]), 0.75 * np.sin(arc[-1])), (0.75 * np.cos(arc[-2]), 0.75 * np.sin(arc[-2])),
                  arrowprops=dict(arrowstyle="->", color="b"))
    left.text(0.1, 0.35, "psi (direction +1)", color="b", fontsize=8)
    left.set_title("basal section in the model's frame, seen from the apex\n(x1 towards the viewer)", fontsize=9)
    left.set_aspect("equal")
    left.set_xlim(-3, 3.4)
    left.set_ylim(-3, 3.4)
    left.axis("off")
    draw_bullseye(right)
    right.set_title("bull's-eye: anterior up, septum left", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main():
    if "--figure" in sys.argv:
        convention_figure(DOCS / "segments.png")
        print("wrote", DOCS / "segments.png")
        return
    quick = "--quick" in sys.argv
    started = time.perf_counter()
    if "--sequences" in sys.argv:  # the tracked cycles again, the sweep kept from the last run
        data = json.loads((DOCS / "myocardium.json").read_text())
        data["sequences"] = [sequence_row(seed) for seed in (0, 1)]
        data["sequences_command"] = "python benchmarks/myocardium.py --sequences"
        data["sequences_machine"] = machine()
        write_json("myocardium.json", data)
        print(data["sequences"])
        print("wrote", write_markdown())
        return
    rows = sweep_rows(SWEEP[:2] if quick else SWEEP)
    sequences = [sequence_row(seed) for seed in ((0,) if quick else (0, 1))]
    for s in sequences:
        print({k: v for k, v in s.items() if not isinstance(v, list)}, flush=True)
    command = "python benchmarks/myocardium.py" + (" --quick" if quick else "")
    write_json("myocardium.json", {"command": command, "machine": machine(),
                                   "wall_seconds": time.perf_counter() - started, "cases": rows,
                                   "sequences": sequences, "sequences_command": command})
    print("wrote", write_markdown())


if __name__ == "__main__":
    main()
