"""Compose docs/benchmarks.md from the JSON the benchmarks wrote.

    python benchmarks/report.py
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import DOCS  # noqa: E402


def _load(name):
    path = DOCS / name
    return json.loads(path.read_text()) if path.is_file() else None


def _fmt(v, digits=2):
    return "n/a" if v is None or (isinstance(v, float) and not np.isfinite(v)) else f"{v:.{digits}f}"


def _tried(rows) -> list[str]:
    """A table of what was tried: (tried, what it gave, kept? / why) a row."""
    return (["| tried | what it gave | kept? / why |", "| --- | --- | --- |"]
            + [f"| {a} | {b} | {c} |" for a, b, c in rows])


def _machine(m):
    return (f"{m['date']}, {m['cpu']}, Python {m['python']}, spheroseg {m['spheroseg']}, numpy {m['numpy']}, "
            f"scipy {m['scipy']}, SimpleITK {m['SimpleITK']}, scikit-image {m['scikit-image']}")


def _accuracy(acc) -> list[str]:
    out = ["## Accuracy on phantoms", "",
           f"Command: `{acc['command']}` ({acc['wall_seconds'] / 60:.0f} min). Machine: {_machine(acc['machine'])}.", "",
           "Synthetic apical 3D echo volumes (`spheroseg.synthetic.phantom`, 1 mm voxels) with exact truth; every method starts "
           "from the same half-ellipsoid placed by the true apex and base points and is closed at the same base plane. "
           "Dice on the voxel grid; mean surface distance (MSD, the average of the two directed means) and Hausdorff "
           "distance (HD) between the wall surfaces, open at the mitral plane as in CETUS; volume error relative to the "
           "exact volume; time per volume on one process. Median (worst) over seeds.", ""]
    methods = list(acc["cases"][0]["results"])
    families = list(dict.fromkeys(c["family"] for c in acc["cases"]))
    out += ["| family | method | Dice | MSD mm | HD mm | volume error % | seconds |",
            "| --- | --- | --- | --- | --- | --- | --- |"]
    summary = {}
    for fam in families:
        for m in methods:
            rows = [c["results"][m] for c in acc["cases"] if c["family"] == fam]
            d = np.array([r["dice"] for r in rows])
            msd = np.array([r["msd_mm"] for r in rows])
            hd = np.array([r["hausdorff_mm"] for r in rows])
            ve = np.array([r["volume_error_pct"] for r in rows])
            t = np.array([r["seconds"] for r in rows])
            summary.setdefault(m, []).extend(rows)
            out.append(f"| {fam} | {m} | {_fmt(np.median(d), 3)} ({_fmt(d.min(), 3)}) | {_fmt(np.nanmedian(msd))} "
                       f"({_fmt(np.nanmax(msd))}) | {_fmt(np.nanmedian(hd), 1)} ({_fmt(np.nanmax(hd), 1)}) | "
                       f"{_fmt(np.median(ve), 1)} ({_fmt(ve[np.argmax(np.abs(ve))], 1)}) | {_fmt(np.median(t), 3)} |")
    out += ["", "All families together:", "", "| method | median Dice | worst Dice | median MSD mm | median seconds |",
            "| --- | --- | --- | --- | --- |"]
    for m, rows in summary.items():
        d = np.array([r["dice"] for r in rows])
        out.append(f"| {m} | {_fmt(np.median(d), 3)} | {_fmt(d.min(), 3)} | "
                   f"{_fmt(np.nanmedian([r['msd_mm'] for r in rows]))} | {_fmt(np.median([r['seconds'] for r in rows]), 3)} |")
    if acc.get("peer_params"):
        out += ["", f"Peer parameters (fixed after a sweep on one case, `--peer-sweep`, see docs/peer_sweep.json): "
                f"`{json.dumps(acc['peer_params'])}`. Each peer smooths the image with a Gaussian of `sigma_mm`, runs "
                "the level set, keeps the component that overlaps the initial ellipsoid and the apex side of the base plane."]
    seqs = acc.get("sequences") or []
    if seqs:
        out += ["", "## Ejection fraction on phantom sequences", "",
                "10 frames per cycle from end-diastole. 'tracking': spheroseg follows every frame, each starting from "
                "the previous one. 'ED and ES frames': the true ED and ES frames segmented on their own from the same "
                "half-ellipsoid (the first frame's apex and base, base radius 0.3 of their distance), which at "
                "end-systole lies across the wall: a test of robustness to a poor start that global level sets fail "
                "by leaking outwards. EF error in points (median, worst absolute).", "",
                "| method | median abs EF error | worst abs EF error |", "| --- | --- | --- |"]
        names = [k for k in seqs[0] if k not in ("seed", "truth_ef")]
        for name in names:
            err = np.array([abs(r[name]["ef"] - r["truth_ef"]) for r in seqs])
            out.append(f"| {name} | {_fmt(np.median(err), 1)} | {_fmt(err.max(), 1)} |")
    p7 = acc.get("cetus_patient7")
    if p7:
        out += ["", "## Real echo: CETUS Patient 7 (no ground truth)", "",
                f"ED and ES volumes of CETUS Patient 7 (CC BY-NC-SA 4.0, Bernard et al. 2016; read from ../shared, not "
                f"shipped). The voxel spacing was not stored with these arrays: {p7['assumed_spacing_mm']} mm isotropic is "
                "assumed, so volumes in mL carry that assumption (EF does not).", "",
                "| method | EDV mL | ESV mL | EF % | seconds per volume |", "| --- | --- | --- | --- | --- |"]
        for name, v in p7.items():
            if isinstance(v, dict) and "ED" in v:
                out.append(f"| {name} | {_fmt(v['ED']['volume_ml'], 1)} | {_fmt(v['ES']['volume_ml'], 1)} | "
                           f"{_fmt(v['ef_percent'], 1)} | {_fmt((v['ED']['seconds'] + v['ES']['seconds']) / 2, 3)} |")
        out += ["", "![CETUS Patient 7](cetus_patient7.png)"]
    return out


#: issue 11's targets across the image-formation sweep
SWEEP_TARGETS = dict(median_dice=0.94, median_msd_mm=1.0, median_volume_error_pct=5.0, worst_dice=0.85, ef_points=3.0)


def _sweep_targets(sweep) -> list[tuple[str, str, bool]]:
    """(target, measured, met) for the latest run of the formation sweep."""
    if not sweep or not sweep.get("runs"):
        return []
    # the latest run with the default options (a run with options of its own is a comparison)
    label, run = [(lab, r) for lab, r in sweep["runs"].items() if not r.get("options")][-1]
    a, t = run["summary"]["all"], SWEEP_TARGETS
    ef = max((abs(r["tracked_ef"] - r["truth_ef"]) for r in run["sequences"] if r["base_descent_mm"] > 0),
             default=float("nan"))
    return [
        (f"median Dice >= {t['median_dice']} across the image-formation sweep ('{label}')",
         f"{a['median_dice']:.3f}", a["median_dice"] >= t["median_dice"]),
        (f"worst Dice >= {t['worst_dice']} across the sweep ('{label}')", f"{a['worst_dice']:.3f}",
         a["worst_dice"] >= t["worst_dice"]),
        (f"median mean surface distance <= {t['median_msd_mm']} mm across the sweep ('{label}')",
         f"{a['median_msd_mm']:.2f} mm", a["median_msd_mm"] <= t["median_msd_mm"]),
        (f"median volume error within +-{t['median_volume_error_pct']:.0f} % across the sweep ('{label}')",
         f"{a['median_volume_error_pct']:+.1f} %", abs(a["median_volume_error_pct"]) <= t["median_volume_error_pct"]),
        (f"tracked EF within {t['ef_points']:.0f} points with base descent (worst, '{label}')", f"{ef:.1f} points",
         ef <= t["ef_points"]),
    ]


def _formation_sweep(sweep) -> list[str]:
    # runs with options of their own have a section of their own (_option_runs)
    runs = {label: run for label, run in sweep["runs"].items() if not run.get("options")}
    labels = list(runs)
    first = runs[labels[0]]
    out = ["## Accuracy across image formations (issue 11)", ""]
    for label, run in runs.items():
        mode = f", default mode '{run['default_mode']}'" if run.get("default_mode") else ""
        out.append(f"Run '{label}': `{run['command']}` on commit {run['commit']}{mode} "
                   f"({run['wall_seconds'] / 60:.0f} min, phantom generation included). Machine: {_machine(run['machine'])}; a shared machine under load "
                   "from other jobs, so seconds are indicative only.")
        out.append("")
    n_fam = len(first["summary"]["family"])
    out += [f"The scenes of `spheroseg.synthetic.phantom` ({', '.join(first['summary']['family'])}; 1 mm voxels, exact truth) "
            "imaged by each named image formation of `spheroseg.synthetic.phantom.FORMATIONS` "
            f"({len(first['summary']['formation'])} settings, {n_fam} scenes each, the same scenes for every setting): beam-space speckle with a "
            "point-spread function widening with depth, attenuation, noise, TGC, log compression and scan conversion "
            "(`spheroseg.synthetic.echo`). 'default' resembles an adult apical scan (axial PSF 0.8 mm, lateral 3 mm at 80 mm, "
            "55 dB); every other setting changes one thing (see docs/accuracy_sweep.json for all parameters). "
            "`spheroseg.segment` with its default options from the true apex and base points. Per setting: median "
            "Dice (worst), median mean surface distance, median volume error in % and mL (the bias), median "
            "iterations.", ""]
    head = "| formation | " + " | ".join(f"{lab}: Dice | {lab}: MSD mm | {lab}: volume error % | {lab}: mL | "
                                          f"{lab}: iterations" for lab in labels) + " |"
    out += [head, "| --- |" + " --- |" * (5 * len(labels))]

    def cells(st):
        return (f"{_fmt(st['median_dice'], 3)} ({_fmt(st['worst_dice'], 3)}) | {_fmt(st['median_msd_mm'])} | "
                f"{st['median_volume_error_pct']:+.1f} | {st['median_volume_error_ml']:+.1f} | "
                f"{st['median_iterations']:.0f}")

    for group in ("formation", "family"):
        for name in first["summary"][group]:
            row = [cells(runs[lab]["summary"][group][name]) if name in runs[lab]["summary"][group] else
                   " | ".join(["n/a"] * 5) for lab in labels]
            out.append(f"| {'' if group == 'formation' else 'scene: '}{name} | " + " | ".join(row) + " |")
    out.append("| all cases | " + " | ".join(cells(runs[lab]["summary"]["all"]) for lab in labels) + " |")
    out += ["", "Tracked sequences (default formation, 10 frames, `spheroseg.track` with default options from the "
            "first frame's apex and base): the mitral annulus descends towards the apex by the given distance at "
            "end-systole, the long axis shortening by as much. EDV and ESV at the true ED and ES frames.", "",
            "| run | seed | base descent mm | true EF % | tracked EF % | EF error points | EDV error % | ESV error % |",
            "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for label, run in runs.items():
        for r in run["sequences"]:
            out.append(f"| {label} | {r['seed']} | {r['base_descent_mm']:.0f} | {r['truth_ef']:.1f} | "
                       f"{r['tracked_ef']:.1f} | {r['tracked_ef'] - r['truth_ef']:+.1f} | "
                       f"{100 * (r['tracked_edv_ml'] / r['truth_edv_ml'] - 1):+.1f} | "
                       f"{100 * (r['tracked_esv_ml'] / r['truth_esv_ml'] - 1):+.1f} |")
    out += ["", "contrast_low's myocardium is 5 dB darker than the tissue around the heart, where every other "
            "setting's is brighter (`epicardium.check_wall_polarity`: the wall's median grey level minus that of the "
            "8 mm beyond it, -0.11 of the blood-wall contrast on both scenes; +0.09 to +0.26 on every other "
            "formation, the nine post-processings and the trabecular rim (one scene each); CETUS Patient 7 +0.93 "
            "and +0.35). The intensity interface takes the myocardium's grey level from the band means 2-8 mm "
            "outside the local means' wall. The phantom's wall, measured along the normal, is 4-5 mm thick towards "
            "the apex, so there the band's far half reads the brighter tissue beyond. Read as the wall's level, it "
            "put the apical half of the surface 2-3.4 mm outside the truth (speckle seed 0; within 1 mm at the mid "
            "wall): +9.5 / +10.2 %, Dice 0.948, flagged. The interface now reads the outer band's median at each "
            "of its four offsets, the blurred edge's deficit there removed (`band_contamination`); where the far "
            "half reads above the near half, the excess over the near half comes off the wall's level "
            "(`dataterms.beyond_wall_excess`, `quality['beyond_wall']`): all of it where the last step is three "
            "quarters of the first or more, none where it is half or less, in proportion between (a dark wall then "
            "flagged). A "
            "blurred edge alone rises across the band too, but by shrinking steps (the normal distribution "
            "function is log-concave; about the local means' wall the last step is under half the first for "
            "blurs up to 3 mm, standard deviation, at 15-40 dB, and under three quarters up to 4 mm: tests check "
            "it), so a smoothed bright wall whose edge width cannot be read from its speckle is left alone "
            "(gaussian_2mm: its far half 0.09 of the contrast above its near half, its last step falling). In "
            "this sweep it took 0.065 / 0.069 of the "
            "contrast off contrast_low's scenes and nothing anywhere else (of the other formations, the "
            "post-processings and the rim, only the rim's tilted scene reads higher in its far half, by 0.011, "
            "and its last step falls): contrast_low +3.6 / +3.5 %, Dice 0.966 / 0.968 (the table's 'after'), "
            "unflagged; every other result unchanged. A dark wall is still flagged where not all was taken off. "
            "Measured besides, with this code against the last (volume errors):", ""]
    out += _tried([
        ("contrast_low after the post-processings (speckle seed 0)", "gaussian_1mm +11.0 to +3.7 %, median_1mm "
         "+11.8 to +4.0, diffusion +14.2 to +6.9, persistence_3 +14.3 to +7.1, grid_0.7mm +10.2 to +3.3, "
         "grid_1.5mm +10.4 to +3.5; median_2mm +8.8 to +4.6, part of the rise taken (flagged); gaussian_2mm +10.8 "
         "unchanged and flagged (the wall and the tissue beyond blurred into one rise whose steps shrink)",
         "kept"),
        ("the wall 25 dB above blood (contrast_low's) on other scenes (speckle 1, tilted 11, speckle 2)",
         "+5.5 / +8.8 / +11.2 to +1.8 / +3.6 / +4.1 %", "kept"),
        ("... 28 dB, 2 dB below the tissue", "+3.1 / +5.0 / +6.1 to +1.6 / +3.3 / +5.8 % (the last two with "
         "part of the rise taken, flagged)", "kept"),
        ("tracked 10-frame cycles of contrast_low (seeds 0, 1)", "volumes at ED +10.4 / +5.0 to +4.4 / +1.2 %, "
         "at mid-systole up to +19.6 / +9.4 to +8.9 / +3.8 % (thicker walls); EF -3.7 / -1.9 to -2.0 / -1.2 "
         "points", "kept"),
        ("the tests' confocal speckle shells with dark walls, -3 and -6 dB (white speckle under a blurred "
         "intensity: an image of another making whose blur cannot be read from its speckle)", "blurred by 0.5 mm "
         "+4.9 to +5.7 % (were +5.8 to +6.2); by 1 and 2 mm unchanged (-0.6 to -1.0 %, -12.1 to -13.3 %: "
         "the steps shrink)", "kept"),
        ("all of the rise or none at a last step of half the first", "28 dB: +1.6 / +3.2 / +3.3 %; but one "
         "dark shell blurred by 1 mm from -0.8 to -3.4 %, and a level that jumps by the whole rise where a "
         "profile crosses the bound (a sequence's frames, a mildly dark wall)", "no: in proportion between "
         "half and three quarters"),
        ("the outer band's near half (2 and 4 mm, the blurred edge's deficit removed) always", "contrast_low "
         "+3.6 / +3.6 %, but default Dice 0.970 / 0.972 (was 0.979 / 0.979), psf_wide 0.955 / 0.954 (was "
         "0.971 / 0.970): two offsets' means vary more over the surface", "no: only where the far half reads "
         "beyond the wall"),
        ("... the far half taken for the tissue beyond wherever it reads 0.05 of the contrast above the near "
         "half", "the sweep as kept, but the tests' confocal shells blurred by 2 mm read 0.15-0.20 above, "
         "climbing the unread blurred edge, and fell from -12.1 to -13.8 % to -19.2 to -20.2 %", "no: the "
         "last step's test"),
        ("the 2 mm offset alone (the deficit removed)", "contrast_low +0.9 / +1.2 %, but default Dice 0.961 / "
         "0.966, psf_wide +4.4 / -3.9 %, the rim -9.9 / -9.6 %", "no"),
        ("the rule kept, and the near half's level also where the far half reads below it (darker tissue "
         "beyond a bright wall)", "contrast_high -0.2 / -0.3 % (was -2.7 / -2.2), but default +2.2 / +1.8 % (was +0.4 / +0.7), "
         "psf_narrow +4.0 / +4.1 %, psf_wide +3.3 / -1.5 %, blood_high +2.6 %, clutter_strong +3.5 %: on bright "
         "walls the darker tissue beyond offsets the interface's outward bias on a sharp edge", "no"),
        ("... with that outward bias modelled too: the trilinear sampler averages the log edge over a voxel "
         "(over a random sub-voxel phase, a hat of variance h^2 / 6 along the normal), its drop at the interface, "
         "with the smoothing's, taken off the level (`smoothed_edge_drop` across the edge's blur as read from the "
         "speckle)", "every case of this sweep within +-3 % (contrast_low +1.0 / +0.9, psf_narrow +1.8 / +1.8, "
         "contrast_high -1.8 / -2.4, psf_wide +2.7 / -2.5, tgc_over -2.2 / -2.4, default +0.6 / -0.1), the "
         "post-processings within 2.2 %, the papillary muscles -0.7 / -1.0 %; but the rim -7.4 / -7.8 % (was "
         "-5.9 / -5.7), and on the tests' confocal speckle shells, whose speckle does not show their blur (read "
         "as 0.15 mm), 12 dB bright walls blurred by 2 mm -29.0 % (was -13.8) and by 1 mm -14.1 % (was -2.1)",
         "no: it trusts the blur read from the speckle for the whole level, and an image whose speckle does not "
         "show it fails badly"),
        ("... the sampler's drop alone", "default -1.0 / -0.9 %, psf_narrow +0.2 / +0.4 %, but contrast_high "
         "-4.0 / -3.9 %, the rim -7.4 / -7.8 %", "no"),
    ])
    out += ["", "Tried before, measured before the wall's blur was removed from the band means (the "
            "post-processing section), on both scenes of 8 formations (default, contrast_low and _high, psf_wide "
            "and _narrow, blood_low and _high, clutter_strong), volume errors upright / tilted:", ""]
    out += _tried([
        ("the myocardium's level from the outer band's 2 and 4 mm only", "contrast_low +2.9 / +3.3 % (was "
         "+9.5 / +10.2); default Dice 0.970 / 0.972 (was 0.979 / 0.979); psf_wide -5.9 / -5.3 % (was -3.5 / -3.2)",
         "no: it costs Dice on every setting"),
        ("... from 2, 3, 4 and 5 mm", "contrast_low +4.8 / +5.1 %; default Dice 0.974, +0.8 / +1.3 %; psf_narrow "
         "+3.6 / +3.9 %, psf_wide -4.0 / -3.7 %", "no"),
        ("... from 3, 4, 5 and 6 mm", "contrast_low +8.5 / +9.2 %; default +2.3 / +2.7 %", "no"),
        ("the lesser of the band's level and the 2-4 mm one", "contrast_low +2.7 / +3.1 %; default -1.6 / -1.0 %, "
         "contrast_high -5.1 / -4.0 %, psf_wide -7.1 / -6.6 %", "no"),
        ("the 2-4 mm level only where the outer band still rises at its far end (its median at 8 mm above those "
         "at 4 and 6 mm: the band reached tissue brighter than the wall), decided once", "contrast_low +2.9 / "
         "+3.3 %, Dice 0.971 / 0.971 (its far end 0.09 / 0.07 of the contrast above the middle); no other "
         "formation, post-processing or the rim changed (0.04-0.14 below); but on the tests' confocal speckle "
         "shells blurred by 2 mm (sigma, 1.5 mm voxels) a wall 6-12 dB brighter than what lies beyond reads as "
         "rising too (up to 0.02 above: the band still climbing a wide blurred edge), and its volume falls from "
         "-13.2 to -19.6 %; their dark walls (-6 dB, 6-9 mm thick) fall from -12.6 to -19.6 % too", "no: the near "
         "half helps only past a thin wall, and a band that rises at its end may be climbing a wide edge"),
        ("the band means read again about the interface's own wall, then its levels frozen anew for one more "
         "stage (the prior's reference still the start): the wall's level without the blurred edge the local "
         "means' wall leaves in the band", "psf_wide -0.7 / -0.3 % (was -3.5 / -3.2), contrast_high -2.0 / -1.8 %, "
         "default +0.9 / +1.2 %, Dice 0.977-0.982 on these (was 0.964-0.979); the 3 mm trabecular rim -4.4 / "
         "-3.9 % (was -6.5 / -5.9); but the 2 mm Gaussian +3.3 / +3.6 % (was +1.4 / +1.9), and contrast_low "
         "creeps through its wall: +21.3 / +20.9 %, Dice 0.90 (the stage moves its wall 1 mm, the others' "
         "0.1-0.3 mm)", "no: the creep the freezing prevents returns, and the smoothing's correction was made "
         "for the first reading"),
        ("... with the first reading's log compression and smoothing kept, and the first reading's levels kept "
         "where the second reading's band rises at its far end (a dark wall: its far end 0.03-0.04 of the "
         "contrast above its middle on contrast_low, 0.07-0.15 on the tests' dark speckle shells; 0.05-0.39 "
         "below on every bright wall here and there)", "psf_wide -0.9 / -0.9 %, the rim -4.5 / -4.5 %, Dice up "
         "to 0.014 higher (gaussian_2mm's unchanged); on the tests' confocal speckle shells (an image of another "
         "making: isotropic Gaussian blur, 1.5 mm voxels), 12 dB bright walls blurred by 2 mm -7.8 / -7.3 % "
         "(were -13.8 / -13.2) and by 0.5 mm +2.6 / +2.6 % (were +4.5 / +4.7), but with a 2 mm Gaussian after a "
         "1 mm blur +1.0 to +3.6 % (were -0.8 to +0.9); here gaussian_2mm +3.8 / +4.2 % "
         "(was +1.4 / +1.9), clutter_strong +3.3 / +3.2 % (was +1.9 / +2.5), default +0.9 / +0.9 %, and one "
         "more stage in every segmentation (the 5 ms target's margin is 0.3 ms)", "no: as many settings beyond "
         "+-3 % as before, and slower; the smoothing's correction would have to be made again for it"),
    ])
    out += ["", "Whether the band reaches past the wall depends on the phantom's apical wall thickness: any "
            "shorter reach would be a constant tuned to this phantom, so the band is kept and its profile read."]
    return out + [""] + _option_runs(sweep)


def _option_runs(sweep) -> list[str]:
    """The sweep run with an option of its own against the default run
    ('after'): per setting and over all cases, and the sequences' volumes."""
    base = sweep["runs"].get("after")
    others = {label: run for label, run in sweep["runs"].items() if run.get("options")}
    if base is None or not others:
        return []
    out = []
    for label, run in others.items():
        option = ", ".join(f"`{k}={v!r}`" for k, v in run["options"].items())
        out += [f"### The sweep with {option}", "",
                f"`{run['command']}` on commit {run['commit']}, against the run 'after' (default options). "
                "The smoothing prior (`smoothness`) measures the surface's departure from a reference shape: by "
                "default the initial half-ellipsoid posed by the clicks, at every level; with "
                "`smoothness_reference='fitted'` the finest patches measure it from that half-ellipsoid widened "
                "or narrowed to hold the volume the coarse levels ended on (`initial.fitted_start`: the same pose "
                "and apex height, base radius `sqrt(3 V / (2 pi h))`). Per setting: median Dice, median mean "
                "surface distance (mm), median volume error (%).", "",
                f"| formation | default: Dice | default: MSD | default: volume % | {label}: Dice | {label}: MSD | "
                f"{label}: volume % |", "| --- | --- | --- | --- | --- | --- | --- |"]

        def cells(st):
            return f"{st['median_dice']:.3f} | {st['median_msd_mm']:.2f} | {st['median_volume_error_pct']:+.1f}"

        for name, st in base["summary"]["formation"].items():
            if name in run["summary"]["formation"]:
                out.append(f"| {name} | {cells(st)} | {cells(run['summary']['formation'][name])} |")
        out.append(f"| all cases | {cells(base['summary']['all'])} | {cells(run['summary']['all'])} |")
        errors = {lab: np.array([c["result"]["volume_error_pct"] for c in r["cases"]])
                  for lab, r in (("default", base), (label, run))}
        closer = sum(b["result"]["dice"] > a["result"]["dice"] for a, b in zip(base["cases"], run["cases"]))
        out += ["", f"Dice higher on {closer} of {len(run['cases'])} cases; volume error over the cases, median "
                "of its size and root mean square: "
                + "; ".join(f"{lab} {np.median(np.abs(e)):.1f} % and {np.sqrt(np.mean(e ** 2)):.1f} %"
                            for lab, e in errors.items()) + ".", "",
                "The default formation's sequences (10 frames; as above): EDV and ESV tracked, and the "
                "end-systolic frame segmented on its own from its true apex and base (fresh ESV).", "",
                "| seed | base descent mm | run | EF error points | EDV error % | ESV error % | fresh ESV error % |",
                "| --- | --- | --- | --- | --- | --- | --- |"]
        for a, b in zip(base["sequences"], run["sequences"]):
            for lab, r in (("default", a), (label, b)):
                fresh = (f"{100 * (r['fresh_esv_ml'] / r['truth_esv_ml'] - 1):+.1f}" if "fresh_esv_ml" in r
                         else "n/a")
                out.append(f"| {r['seed']} | {r['base_descent_mm']:.0f} | {lab} | "
                           f"{r['tracked_ef'] - r['truth_ef']:+.1f} | "
                           f"{100 * (r['tracked_edv_ml'] / r['truth_edv_ml'] - 1):+.1f} | "
                           f"{100 * (r['tracked_esv_ml'] / r['truth_esv_ml'] - 1):+.1f} | {fresh} |")
        out += ["", "The default stays the start. The fitted shape fits every case closer and pulls a small, "
                "end-systolic cavity out less (the fresh ESV: +0.9 to +3.2 % against +4.0 to +10.4), but it leaves "
                "the volumes "
                "1-2 % lower (all cases +0.5 to -1.0 %), nearer the data terms' own inward bias, which the clicked "
                "shape's pull (its base radius 0.3 of the long axis, the phantoms' end-diastoles fit 0.27) offsets "
                "on these phantoms' end-diastoles: contrast_high -3.8 % (start -2.4), psf_wide -2.4 %, tracked EFs "
                "0.2-0.6 points further low (the tracked end-diastoles lower, the end-systoles as large), and the "
                "rim further in. Where the clicked shape's constant sets the volume, a default tuned to it is not "
                "made. "
                "What it gives a user who segments end-diastole and end-systole apart:", "",
                "| measured (this code, `segment` with each reference) | start | fitted |",
                "| --- | --- | --- |",
                "| the end-systole (32 mL) of a 20-frame cycle whose annulus descends 10 mm (seed 3), segmented on its "
                "own from its true points, volume error %: default, contrast_low, clutter_strong, default then "
                "gaussian_2mm, psf_narrow, psf_wide | +7.7, +12.7, +12.6, +10.5, +10.3, +6.6 | "
                "+3.1, +4.6, +2.3, +7.2, +4.4, +1.4 |",
                "| ... its end-diastole (82 mL) | +0.8, +4.5, +2.3, +3.3, +3.2, -0.1 | -0.6, +1.3, -1.2, +2.0, +1.3, "
                "-1.8 |",
                "| ... EF from the two segmented apart, error in points | -2.7, -3.0, -3.9, -2.7, -2.7, -2.6 | "
                "-1.4, -1.3, -1.4, -2.0, -1.2, -1.3 |",
                "| ... EF tracked from end-diastole to end-systole directly | -2.4, -3.2, -3.9, -3.2, -2.5, -0.8 | "
                "-1.8, -1.5, -3.4, -2.9, -1.5, +0.2 |",
                "| the papillary muscles (speckle, tilted; the anatomy section's scenes) | -0.3 / +0.2 % | "
                "-1.4 / -0.7 % |",
                "| the 3 mm trabecular rim | -5.9 / -5.3 % | -7.2 / -6.3 % |",
                "| the nine post-processings (speckle, tilted) | -2.2 to +1.9 %, Dice 0.973-0.979 | "
                "-3.7 to +0.5 %, Dice 0.980-0.988 |",
                "| CETUS Patient 7 (no ground truth), end-diastole / end-systole mL, native grid; resampled to 256^3 "
                "(nearest voxel, as a scanner's export might be) | 193.6 / 137.0; 195.3 / 139.4 | 183.1 / 133.4; "
                "185.2 / 136.1 (none flagged) |",
                "| echo of another making (the simulators section's scenes, seed 0), walls blurred by 1, 1.5, 2, 2.5 "
                "and 3 mm: bright walls (tissue 12 dB darker); walls as bright as the tissue | -0.3, -0.5, -3.3, "
                "-4.3, -7.1 %; +1.9, +2.1, +0.8, +2.8, -7.2 % (flagged) | -1.6, -2.9, -5.4, -1.3, -6.7 %; -0.4, "
                "-1.7, -4.5 (flagged), +5.6, -14.8 % (unflagged) |", "",
                "The fitted shape follows the coarse levels' own error: where the wall's blur is wide and its "
                "speckle does not show it, the coarse surface errs by several percent and the reference with it; "
                "the clicked shape knows nothing of the image. That, too, keeps the default.", "",
                "The end-systole's excess from the clicked shape lies in the apical third (default: +1.4 of its "
                "+2.5 mL at 0.7-0.9 of the way from base to apex): its clicked base radius, 0.3 of the long axis, "
                "is the end-diastole's proportion, and the fitted one reads 0.21 there (0.27 at end-diastole).", "",
                "| tried | what it gave | kept? / why |", "| --- | --- | --- |",
                "| `smoothness_reference='coarse'`, the finest patches smoothed from the surface the coarse levels "
                "ended on (replaced by 'fitted') | the sweep: Dice 0.984 (32 cases higher than the start's), volume "
                "-0.5 % (contrast_high -3.3, contrast_low +1.4, psf_wide -1.9 %); fresh end-systoles +2.2 to +4.9 %; "
                "the seed-3 end-systole +3.9, +7.0, +3.9, +8.3, +5.8 % (the formations above); the rim -6.6 / -6.1 %; "
                "but Patient 7's end-diastole on 256^3 224.7 mL, flagged as a bulge (native 194.1), its "
                "end-systole 147.8 mL: the coarse surface's own bulges are kept, where a half-ellipsoid holds a weak "
                "wall | no: 'fitted' |",
                "| the held apex let go (`apex_weight=0`, start reference) | that end-systole +4.4 % (+7.7 with it), "
                "its end-diastole +0.7 %, Patient 7 189.1 / 139.7 mL native, 191.2 / 141.9 on 256^3, none flagged; "
                "but clutter_strong's cycle collapses (-40.5 / -50.6 % at end-diastole / end-systole, flagged); at a "
                "weight of 3 its end-systole +12.1 % | no: the apex holds against near-field clutter |",
                "| a lighter smoothing (`smoothness=0.5`) | that end-systole +5.0 %, but Patient 7's end-diastole on "
                "256^3 212.5 mL | no |",
                "| the fitted shape as the default, with the wall's level read from the outer band's near half also "
                "where its far half reads below it (darker tissue beyond a bright wall; the formation sweep's tried "
                "rows), that read left out where the band's own profile gave the blur | every formation within "
                "+-3 % (psf_wide +0.9 / -2.6, psf_narrow +2.3 / +2.4, contrast_high -1.6 / -1.2, contrast_low "
                "+0.8 / +1.2 %), Dice 0.978-0.988; the papillary muscles +0.0 / +0.6 %; but the rim -7.2 / -6.3 %, "
                "median_2mm -3.6 %, and the simulators' scenes as the fitted shape's row above | no: the fitted "
                "shape's errors on images of another making |", ""]
    return out


def _speed(sp) -> list[str]:
    threads = sp.get("kernel_threads", 1)  # runs before the threads option: one
    out = ["## Speed", "", f"Command: `{sp['command']}`. Machine: {_machine(sp['machine'])}. "
           f"Medians over repeats, one process, {'one thread' if threads == 1 else f'{threads} threads'} for "
           "spheroseg's compiled kernels (the threads section below compares the counts).", ""]
    out += ["Phantoms of one shape at three voxel sizes (2.5, 1.25, 0.625 mm). 'read' is reading the .mha into a "
            "Volume (the yardstick); 'load' adds the default search for the sector padding. Peers: one run each.", "",
            "| image | voxels | read ms | load ms | local-mode iteration us | default-mode iteration us | "
            "spheroseg segmentation ms (iterations) | skimage ms | SimpleITK ms |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for row in sp["sizes"]:
        out.append(f"| {row['shape']} | {row['voxels']} | {_fmt(row['load_ms'], 1)} | {_fmt(row.get('load_auto_ms'), 1)} | "
                   f"{_fmt(row['iteration_us'], 0)} | {_fmt(row.get('intensity_iteration_us'), 0)} | "
                   f"{_fmt(row['segment_ms'], 1)} ({row['iterations']}) | "
                   f"{_fmt(row.get('skimage_ms'), 0)} | {_fmt(row.get('sitk_ms'), 0)} |")
    modes = sp.get("default_mode") or ({"after": {"unseen": sp["unseen"], "first_calls": sp["first_calls"]}}
                                       if sp.get("unseen") else {})
    labels = [k for k in ("before", "after") if k in modes]
    if labels:
        out += ["", "The default mode on the accuracy sweep's image formations ('default' and the wider point-spread "
                "function 'psf_wide', 1 mm phantoms, seeds 0-2): the whole segmentation (median of 10, iterations "
                "in brackets) and one iteration of its last stage (the intensity interface on 8 x 8 patches, its "
                "region means frozen: observe, force, update; after: inside the compiled level loop)"
                + (", before and after issue 15's changes, measured on the same machine in turn "
                   f"(`--default-mode before --min`, last on {modes['before'].get('date', '?')}, the least of "
                   f"{modes['before'].get('runs', 1)} runs; after: the least of {modes['after'].get('runs', 1)}, "
                   f"last on {modes['after'].get('date', '?')})" if len(labels) == 2 else "") + ".", "",
                "| formation | seed | image | " + " | ".join(f"{lab}: segmentation ms" for lab in labels) + " | "
                + " | ".join(f"{lab}: last-stage iteration us" for lab in labels) + " |",
                "| --- | --- | --- |" + " --- |" * (2 * len(labels))]
        for k, row in enumerate(modes[labels[-1]]["unseen"]):
            rows = [modes[lab]["unseen"][k] for lab in labels]
            out.append(f"| {row['formation']} | {row['seed']} | {row['shape']} | "
                       + " | ".join(f"{r['segment_ms']:.1f} ({r['iterations']})" for r in rows) + " | "
                       + " | ".join(f"{r['intensity_iteration_us']:.0f}" for r in rows) + " |")
        for lab in labels:
            fc = modes[lab]["first_calls"]
            out += ["", f"The first segmentation of a fresh process ({lab}; median over 5 interpreters, 2 mm "
                    f"phantom): {fc['fresh_ms']:.0f} ms when it also loads numba and the compiled kernels (on "
                    f"6 x 6 patches), then {fc['first_default_ms']:.1f} ms for the first on the default grids against "
                    f"{fc['again_ms']:.1f} ms for the next one"
                    + (" (their matrices read from the on-disk cache beside numba's)." if lab == "after" else
                       " (their matrices computed).")]
    out += _threads(sp.get("threads"))
    tr = sp["tracking"]
    out += ["", f"Tracking: {_fmt(tr['volumes_per_second'], 0)} volumes per second at "
            f"{tr['iterations_per_frame']} iterations per frame"
            + (f", {_fmt(tr['volumes_per_second_3'], 0)} at 3" if "volumes_per_second_3" in tr else "")
            + " (excluding file reading).", ""]
    if sp.get("profile"):
        out += ["Profile of one local-mode iteration at each patch count (8 x 8 sample points per patch, 1 mm "
                "phantom): the compiled surface evaluation and image samples, the projection (band means smoothed "
                "over the surface, the force, the least-squares update), the whole iteration, the same with the numpy "
                "reference path, and the memory the level precomputes beyond the image.", "",
                "| patches | sample points | surface + samples us | projection us | iteration us | numpy iteration us "
                "| memory kB |", "| --- | --- | --- | --- | --- | --- | --- |"]
        for row in sp["profile"]:
            out.append(f"| {row['patches']} | {row['samples']} | {_fmt(row['sampling_us'], 0)} | "
                       f"{_fmt(row['projection_us'], 0)} | {_fmt(row['iteration_us'], 0)} | "
                       f"{_fmt(row['numpy_iteration_us'], 0)} | {_fmt(row['memory_kb'], 0)} |")
    if sp.get("notes"):
        out += [""] + sp["notes"]
    prof = next((r for r in sp.get("profile", []) if r["patches"] == "8 x 8"), None)
    if prof and "surface_and_samples_us" in prof:
        unseen = (sp.get("default_mode") or {}).get("after", {}).get("unseen") or sp.get("unseen") or []
        it_default = float(np.median([r["intensity_iteration_us"] for r in unseen])) if unseen else float("nan")
        seg_unseen = [r["segment_ms"] for r in unseen] or [float("nan")]
        its_unseen = [r["iterations"] for r in unseen] or [0]
        stage_text = _stage_text([r["stages_ms"] for r in unseen if "stages_ms" in r])
        out += ["", "### Where the time goes, and what it would take", "",
                "The default mode runs four stages: the global means on 2 x 2 and 4 x 4 patches, the local means on "
                "8 x 8, then the intensity interface on 8 x 8, which is handed the local means' last band means and "
                "freezes its levels; each level runs in one compiled loop (`_kernels.descend`, called by "
                f"`Tracker.run_level`). A whole default segmentation of the unseen-style cases takes "
                f"{min(seg_unseen):.1f} to {max(seg_unseen):.1f} ms (target 5 ms: "
                f"{'met' if max(seg_unseen) <= 5 else 'missed'}), in {min(its_unseen)} to {max(its_unseen)} "
                f"iterations. {stage_text}".rstrip(),
                "",
                f"An iteration of the last stage at 8 x 8 patches takes {it_default:.0f} us (median over the "
                f"unseen-style cases above, {sp.get('kernel_threads', 1)} kernel threads, inside the compiled loop "
                "that runs a level: 11 iterations less 1, over 10): the surface at the "
                f"{prof['samples']} sample points and their grey levels ({prof['surface_and_samples_us']:.0f} us "
                "alone, from Python), then the force, B^T v, the thin-plate and constraint products, the product "
                "with the 259 x 259 system inverse and the motion B dp. The local-mode iteration of the profile "
                f"above adds the band means: {prof['band_samples_us']:.0f} us of samples "
                f"({1000 * prof['band_samples_us'] / (prof['image_samples'] - prof['samples']):.0f} ns each) and "
                "their projection on the surface. The kernels of the sample points (surface, samples, cavity sums, "
                "B p) split the points among numba's threads; a batch of several workers runs one thread in each, "
                "where threads would only contend.",
                "",
                "What is left is some 2.6 ms of arithmetic in the loops (the local means' iterations the dearest: "
                "their band samples, their projection and the median of their contrast) and some 2 ms of Python "
                "around them: the set-up 0.7 ms (the initial surface, the start's statistics, the first level's "
                "matrices and landmark rows), each change of level 0.15-0.2 ms (the new level's landmark rows, 80 us "
                "for the one apex point, all of it numpy's cost per call, and their Woodbury update), the hand-over "
                "0.2 ms and the result 0.35-0.5 ms (its quality report). The worst case (the wide point-spread "
                "function, seed 0: 24 iterations) is within a few tenths of a millisecond of the target, which a "
                "slower day of this virtual machine would take: one case takes 6.5 ms in one minute and 10 in the "
                "next, whichever the code (the tables keep the least of several runs).",
                "",
                "Below, issue 15's rounds in order, then what was tried on what is left. The schedule's changes "
                "were judged on CETUS Patient 7: on its end-systolic volume the local means' last iterations slide "
                "one region inwards (139 to 126 mL "
                "over 20 iterations, the median point moving 0.005 mm an iteration and the fastest 0.5-0.9) and the "
                "interface moves it back (140.6 mL), so where the interface stage starts sets that volume within "
                "some 3 %.",
                ""]
        out += _tried([
            ("the last stage sampling no bands (nor its first observation, since the hand-over)",
             "two thirds of its samples fewer", "kept"),
            ("a stage on the same grid, and a tracked frame, continuing the descent",
             "no rebuilt matrices and landmark rows", "kept"),
            ("a volume or a mesh without a sparse basis matrix", "no separate figure", "kept"),
            ("what depends only on the grid (mass and smoothing systems, their inverses, basis tables) cached on disk",
             "built once per machine, read by a new process (the first segmentation above)", "kept"),
            ("the step solved for directly", "one dense product a step instead of two; the thin-plate matrix sparse",
             "kept"),
            ("the medians a result reports taken once, at its end", "no separate figure", "kept"),
            ("raw samples (the speckle's, the start's) from a compiled kernel", "no separate figure", "kept"),
            ("the set-up and the quality report on tensor grids, the initial surface once per tracker, the apex as "
             "one point", "no separate figure", "kept"),
            ("the local means' two band fields in one product with the mass inverse, times the constraints in "
             "compiled code", "scipy's dispatch of a sparse product had cost more than the product", "kept"),
            ("a wall's distances from the axis measured in the model's frame", "no separate figure", "kept"),
            ("the surface's own samples (one a point) in a loop of their own: the Hermite basis patch by patch, "
             "then exp, normal and scale factor on SIMD lanes", "no separate figure", "kept"),
            ("the image samples in a parallel loop whose body has no inner loop", "no separate figure", "kept"),
            ("the product with the system inverse a row added per parameter",
             "SIMD lanes instead of a chain of dependent additions", "kept"),
            ("the hand-over's speckle estimate binning its rays by their patch's number", "no sort", "kept"),
            ("the coarse levels stopping at twice `tol` (`coarse_tol`), the interface (starting at the wall) taking "
             "twice the step when the local means settled", "32 sweep cases: 824 to 641 iterations, median Dice "
             "0.971 to 0.978", "kept: checked across the image formations"),
            ("each level in one compiled loop", "from Python an iteration had been a dozen kernel calls and their "
             "numpy glue: 60-100 us on the coarse levels, some 50 us on the fine ones", "kept"),
            ("the loop's sums with numba's dot products, medians and array expressions",
             "12.7 s to compile the loop and its kernels, 7.1 s with plain loops",
             "no: plain loops (a level equals its iterations from Python to rounding, not to the last bit; tested)"),
            ("the machine's load read at most ten times a second",
             "a reading had cost 0.1 ms back to back (the kernels' threads still running, read one by one)", "kept"),
            ("a tensor grid's Hermite basis kept for the last parameters",
             "the quality report's axis distances (twice a result) 80 to 46 us", "kept"),
            ("the initial surface's profile in one call, its frame without `np.cross`'s checks", "130 to 100 us",
             "kept"),
            ("the hand-over's speckle estimate binning by the patch labels themselves (no `np.unique`)", "30 us",
             "kept"),
            ("the last four rows together, alternating in one process with the code before them (3113c3a)",
             "the six cases' median 4.43 to 4.11 ms, worst 4.87 to 4.68 (2 threads)", "kept: equal to the last bit "
             "(24 segmentations, four modes on the six cases); 3113c3a had read 5.6-6.6 ms two days earlier, on a "
             "slower day: that gain is the machine's"),
            ("fewer sample points (`order=6`: 36 a patch instead of 64)", "about 1.2 ms saved; the sweep's worst "
             "Dice 0.935 against 0.946, worst volume error 13.3 % against 10.6 %", "no: a worse worst case"),
            ("a step that grows while successive motions agree",
             "overshot on the coarse levels: 144 iterations against 143 on the six cases", "no"),
            ("the interface started from the 4 x 4 global means' wall, without the local means",
             "Patient 7's end-systolic volume changed by 11 %", "no"),
            ("the local means on the 4 x 4 patches instead of the 8 x 8", "0.9 ms saved, the sweep's median Dice "
             "0.9780 against 0.9782; Patient 7's end-systolic volume moved 2.4 %",
             "no: and a tracked frame (the finest patches only) would lack them"),
            ("the local means stopping at `coarse_tol`", "0.6 ms saved; that volume moved 2.6 %", "no"),
            ("starting at 4 x 4, without the 2 x 2 level", "0.4 ms saved; Patient 7's end-diastolic volume moved "
             "5 %", "no")])
    return out


def _stage_text(stages: list[dict]) -> str:
    """A sentence on the medians over the cases of :func:`speed.stage_ms`."""
    if not stages:
        return ""

    def median(key):
        return float(np.median([s.get(key, 0.0) for s in stages]))

    levels = [k for k in stages[0] if k.startswith("level") and not k.endswith("iterations")]
    names = {"GlobalMeans": "global means", "LocalMeans": "local means, with the hand-over: the log-compression "
             "estimate and the interface's frozen levels", "IntensityInterface": "interface"}
    parts = [f"{k.split(': ')[0]} ({names.get(k.split(': ')[1], k)}) {median(k):.1f} ms "
             f"({median(k + ' iterations'):.0f} iterations)" for k in levels]
    return (f"Medians over the cases, stage by stage (`stage_ms`; a level's time includes building the next "
            f"level's descent): the tracker's set-up {median('setup'):.1f} ms, " + ", ".join(parts)
            + f", and the result {median('result'):.1f} ms (its quality report). ")


def _threads(th) -> list[str]:
    """The thread counts side by side (``speed.py --threads``)."""
    if not th:
        return []
    counts = [str(n) for n in th["counts"]]
    names = {"1": "1 thread"} | {n: f"{n} threads" for n in counts[1:]}
    rows = th["unseen"]
    med = {n: {k: float(np.median([r[n][k] for r in rows])) for k in rows[0][n]} for n in counts}
    out = ["", "### Threads", "",
           f"Command: `python benchmarks/speed.py --threads` ({th['date']}, numba's threading layer "
           f"'{th['threading_layer']}'; the 1-minute load average of the 2 cores {th['load'][0]:.1f} before the run and "
           f"{th['load'][1]:.1f} at its end, the run's own included). The compiled kernels split their sample points among numba's threads (the "
           "`threads` option; the coefficients are equal to the last bit whatever the count, checked here on "
           "every case). The counts alternate in 5 turns on each case, so that load weighs on all alike. The "
           "default mode on the unseen-style cases: the whole segmentation (median of 10) and one iteration of its "
           "last stage in the compiled loop (a tenth of the median of 100 runs of ten), as above.", "",
           "| formation | seed | " + " | ".join(f"segmentation ms, {names[n]}" for n in counts) + " | "
           + " | ".join(f"last-stage iteration us, {names[n]}" for n in counts) + " |",
           "| --- | --- |" + " --- |" * (2 * len(counts))]
    for r in rows:
        out.append(f"| {r['formation']} | {r['seed']} | " + " | ".join(f"{r[n]['segment_ms']:.1f}" for n in counts)
                   + " | " + " | ".join(f"{r[n]['intensity_iteration_us']:.0f}" for n in counts) + " |")
    iteration = " against ".join(f"{med[n]['intensity_iteration_us']:.0f}" for n in counts)
    segmentation = " against ".join(f"{med[n]['segment_ms']:.1f}" for n in counts)
    out += ["", "Medians over the cases, " + " against ".join(names[n] for n in counts) + ": the whole iteration "
            f"{iteration} us, a segmentation {segmentation} ms; within the iteration, "
            + "; ".join(f"{names[n]}: the surface and its grey levels at the 4096 sample points "
                        f"{med[n]['surface_and_samples_us']:.0f} us, of which the samples alone "
                        f"{med[n]['samples_us']:.0f} us (the rest, "
                        f"{med[n]['surface_and_samples_us'] - med[n]['samples_us']:.0f} us, the surface with the "
                        "product of the constraints and the calls)" for n in counts) + "."]
    busy = th.get("busy")
    if busy:
        d, f = busy["default"], busy["forced"]
        out += ["", f"Beside a busy process (another process spinning on one core, started by the run): the same "
                f"segmentations, {busy['segmentations']} with each setting in turn. The default (numba's count reduced "
                f"at each segmentation to the cores no other process is running on, read at most ten times a second"
                + (f", {busy['default_threads']} thread{'' if busy['default_threads'] == 1 else 's'} when checked"
                   if "default_threads" in busy else "")
                + ") took "
                f"{d['median_ms']:.1f} ms (median; worst {d['worst_ms']:.1f}); {busy['forced_threads']} threads forced "
                f"took {f['median_ms']:.1f} ms (worst {f['worst_ms']:.1f}): a parallel step waits for its slowest "
                "thread, and one of them shares its core with the other process."]
    return out


def _beamspace(bs) -> list[str]:
    tr = bs["tracking"]
    out = ["## Beam space: segmenting without scan conversion", "",
           f"Command: `{bs['command']}` ({bs['wall_seconds']:.0f} s). Machine: {_machine(bs['machine'])}; a shared "
           "machine under load from other jobs, so absolute times vary by tens of percent between runs; the "
           "routes were timed side by side in one process. Medians over repeats, one thread.", "",
           f"Tracking a {tr['frames']}-frame phantom cycle at {tr['iterations_per_frame']} iterations per frame. "
           f"Beam space: {' x '.join(map(str, tr['beam_shape']))} samples [r, e, a] (1 mm x 1 deg x 1 deg); "
           f"scan-converted: the Cartesian grid covering the sector, "
           f"{' x '.join(map(str, tr['cartesian_shape']))} voxels of {tr['cartesian_spacing_mm']:g} mm.", "",
           "Medians over the repeats (the fastest run in brackets), the routes interleaved repeat by repeat.", "",
           "| route | scan conversion ms/frame | tracking ms/frame | frames per second |", "| --- | --- | --- | --- |",
           f"| beam space, sampled directly | - | {_fmt(tr['direct_ms_per_frame'], 1)} "
           f"({_fmt(tr.get('direct_ms_per_frame_min'), 1)}) | {_fmt(tr['direct_fps'], 0)} |",
           f"| scan-convert, then track | {_fmt(tr['scan_convert_ms_per_frame'], 1)} "
           f"({_fmt(tr.get('scan_convert_ms_per_frame_min'), 1)}) | {_fmt(tr['track_converted_ms_per_frame'], 1)} "
           f"({_fmt(tr.get('track_converted_ms_per_frame_min'), 1)}) | {_fmt(tr['converted_fps'], 1)} "
           f"({_fmt(tr['converted_fps_excluding_conversion'], 0)} without the conversion) |", "",
           "Per trilinear sample (4096 points around the cavity, 9 samples along each normal, "
           "`sample_along` kernels; the Cartesian kernel reads the scan-converted sector):", "",
           "| convention | kernel | ns per sample, median | fastest run | samples in the data |",
           "| --- | --- | --- | --- | --- |"]
    for row in bs["per_sample"]:
        out.append(f"| {row['convention']} | {row['kernel']} | {_fmt(row['ns_per_sample'], 1)} | "
                   f"{_fmt(row.get('ns_per_sample_min'), 1)} | {_fmt(100 * row['finite_fraction'], 0)} % |")
    out += ["", "The same phantom segmented in beam space and after scan conversion (default options; the default "
            "Cartesian grid, the beams' spacing at mid depth; mean distance: the symmetric mean over the two meshes' "
            "vertices), with the phantom's own Cartesian image and the truth for reference. 'formed in beam space': "
            "the phantom's echo formed on its beams (`make_phantom(formation=FORMATIONS['default'], "
            "beam_space=True)`, 1.5 mm Cartesian image); 'resampled': the legacy 1 mm phantom resampled on the "
            "1 mm x 1 deg sector above, so that both routes interpolate it once more than the original.", "",
            "| data | convention | seed | mean distance mm | beam space mL | scan-converted mL | difference % | "
            "converted to 1 mm: mL | difference % | phantom's Cartesian mL | truth mL |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for row in bs["agreement"]:
        out.append(f"| {row.get('data', 'resampled')} | {row['convention']} | {row['seed']} | "
                   f"{_fmt(row['mean_distance_mm'])} | {_fmt(row['direct_ml'], 1)} | {_fmt(row['converted_ml'], 1)} | "
                   f"{_fmt(row['volume_difference_percent'], 1)} | {_fmt(row.get('converted_1mm_ml'), 1)} | "
                   f"{_fmt(row.get('volume_difference_1mm_percent'), 1)} | {_fmt(row['original_cartesian_ml'], 1)} | "
                   f"{_fmt(row['truth_ml'], 1)} |")
    return out


def _fit(fit) -> list[str]:
    out = ["## How well Hermite surfaces represent a real ventricle", "",
           f"Command: `{fit['command']}`. Least-squares fits (`spheroseg.fit.fit_surface`, default smoothness) to the "
           "vertices of the CETUS Patient 1 expert meshes (metres in the file, mm here). Two poses of the same "
           "prolate spheroidal Hermite family: the **apex-base line** (`Surface.from_apex_base`: the base plane "
           "through the mitral ring's centre, perpendicular to the line to the apex, the round-1 pose) and the "
           "**mitral plane** (`Surface.from_annulus`: the long axis along the normal of the mesh's mitral ring "
           "(its open boundary), through the ring's centre, the apex off the axis). Distances from the reference "
           "vertices to the fitted wall (`point_to_surface_distance`, exact to ~1e-6 mm): from all vertices "
           f"(fitted to all), and from {100 * fit.get('held_out', 0.2):.0f} % of them left out of the fit "
           "(seeded).", ""]
    geometry = fit.get("geometry", [])
    if geometry:
        out += ["| phase | vertices | ring vertices | ring off its plane, RMS mm | apex-base line vs ring normal | "
                "apex height mm | apex off the ring's axis mm |", "| --- | --- | --- | --- | --- | --- | --- |"]
        for g in geometry:
            out.append(f"| {g['phase']} | {g['vertices']} | {g['ring_vertices']} | {g['ring_rms_off_plane_mm']:.4f} | "
                       f"{g['axis_angle_deg']:.1f} deg | {g['apex_height_mm']:.1f} | {g['apex_off_axis_mm']:.1f} |")
        out += [""]
    out += ["| phase | pose | patches | mean mm | max mm | max below the base plane mm | vertices beyond it | "
            "held-out mean mm | held-out max mm | volume mL |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in fit["rows"]:
        out.append(f"| {r['phase']} | {r.get('pose', 'apex-base line')} | {r['patches']} | {r['mean_mm']:.3f} | "
                   f"{r['max_mm']:.2f} | {r['max_in_range_mm']:.2f} | {r.get('beyond_base_plane', '')} | "
                   f"{r['held_out_mean_mm']:.3f} | {r['held_out_max_mm']:.2f} | {r['volume_ml']:.1f} |"
                   if "held_out_mean_mm" in r else
                   f"| {r['phase']} | {r.get('pose', 'apex-base line')} | {r['patches']} | {r['mean_mm']:.3f} | "
                   f"{r['max_mm']:.2f} | {r['max_in_range_mm']:.2f} | | | | {r['volume_ml']:.1f} |")
    out += ["", "The mesh's mitral ring is planar (RMS 0.0003 mm off its plane) but not perpendicular to the "
            "apex-base line: posed by that line, the base plane cuts the ring at a slant and the vertices beyond it "
            "are not represented (the overall maximum, 4-5 mm); posed by the mitral plane, no vertex lies beyond "
            "the base plane, and 8 x 8 patches represent the ventricle to 0.017-0.023 mm mean and 0.15-0.42 mm max "
            "on held-out vertices, 4 x 4 patches to about 0.1 mm mean. 16 x 16 patches gain on ES but not on ED "
            "held-out vertices (0.026 mm mean, 1.48 mm max: 3000 vertices do not pin 1088 parameters everywhere).",
            ""]
    out += _tried([
        ("fitting area samples of the triangles, the distance to the nearest of wall samples 0.25 mm apart "
         "(the table before this round)",
         "ED 8 x 8 mitral plane 0.115 mm mean: 0.08 from the sampled distance (exact: 0.038), 0.02 from the "
         "flat facets, which lie inside a smooth wall (0.017 fitted to the vertices); apex-base pose 0.19 / "
         "0.16 mm mean at 8 x 8 (ED / ES)",
         "no: the vertices and the exact distance")])
    return out


def _mitral(data) -> list[str]:
    modes = data["modes"]
    poses = ("apex-base line", "mitral plane")

    def cells(rows):
        out = []
        for mode in modes:
            for pose in poses:
                r = [row[f"{pose}, {mode}"] for row in rows]
                d, v = np.array([x["dice"] for x in r]), np.array([x["volume_error_pct"] for x in r])
                out.append(f"{np.median(d):.3f} ({d.min():.3f}), {np.median(v):+.1f} %")
        return " | ".join(out)

    head = " | ".join(f"{pose}, {mode}" for mode in modes for pose in poses)
    rule = "| --- " * (1 + 2 * len(modes)) + "|"
    out = ["## Posing by the mitral plane", "",
           f"Command: `{data['command']}`. Segmentation posed by the apex-base line (`segment(volume, apex, base)`) "
           "and by the mitral plane (`segment(volume, apex, annulus=points)`), default options but the data term "
           "(`mode`). Cells: median Dice (worst), median volume error.", "",
           f"The phantom's `tilted` family ({len(data['phantom_tilted'])} seeds, 1 mm voxels; annulus: 6 points of "
           "the true mitral ring). The phantom tilts the whole ventricle from the beam: its mitral plane stays "
           "perpendicular to its apex-base line, so it has nothing to gain here, and the two poses differ only "
           "by the ring's centre (the centroid of the 6 points, not the phantom's base point).", "",
           f"| family | {head} |", rule,
           f"| tilted | {cells(data['phantom_tilted'])} |", "",
           "A scene with a mitral plane tilted from the apex-base line (`spheroseg.synthetic.phantom.tilted_mitral_scene`: an "
           "ellipsoid cut by a tilted plane through its centre, a dark atrium beyond, Gaussian noise, not "
           "log-compressed speckle; 3 seeds per tilt; annulus: 8 points of the true ring). Posed by the apex-base "
           "line the cavity is closed on the wrong plane: a wedge of atrium in, a wedge of ventricle out (the "
           "volumes nearly cancel, Dice shows it).", "",
           f"| mitral plane tilt | {head} |", rule]
    for tilt in sorted({r["tilt_deg"] for r in data["tilted_mitral_scene"]}):
        rows = [r for r in data["tilted_mitral_scene"] if r["tilt_deg"] == tilt]
        out.append(f"| {tilt:.0f} deg | {cells(rows)} |")
    out += ["", f"Machine: {_machine(data['machine'])}; a shared machine under load."]
    return out


def _landmarks(data) -> list[str]:
    rows = data["rows"]
    out = ["## Landmarks on and off the wall", "",
           f"Command: `{data['command']}`. Phantoms of the formations {', '.join(data['formations'])} (seeds "
           f"{', '.join(map(str, data['seeds']))}, 1.5 mm voxels), one landmark on the true wall at mid-height or "
           "8, 15, 30 mm out from it (a misclick), at the default `landmark_weight` 1 and held ten times harder. "
           "Cells: median (largest) distance from the landmark to the final surface, how many of the cases "
           "`quality` flags for that landmark (over 2 mm), median (worst) Dice, median volume error.", "",
           "| landmark | weight | residual, mm | flagged | Dice | volume error |", "| --- | --- | --- | --- | --- | --- |"]
    for offset in sorted({r["offset_mm"] for r in rows}):
        for weight in sorted({r["weight"] for r in rows}):
            sel = [r for r in rows if r["offset_mm"] == offset and r["weight"] == weight]
            res, d = np.array([r["residual_mm"] for r in sel]), np.array([r["dice"] for r in sel])
            v = np.array([r["volume_error_pct"] for r in sel])
            where = "on the wall" if offset == 0 else f"{offset:.0f} mm out"
            out.append(f"| {where} | {weight:g} | {np.median(res):.1f} ({res.max():.1f}) | "
                       f"{sum(r['flagged'] for r in sel)}/{len(sel)} | {np.median(d):.3f} ({d.min():.3f}) | "
                       f"{np.median(v):+.1f} % |")
    out += ["", "A landmark on the wall is reached within 0.1 mm either way. Off the wall, the surface follows a "
            "landmark at weight 1 to within 1-2 mm up to 15 mm out (the landmark is the user's word for where the "
            "wall is); where the data resists, 30 mm out, it stops short and the residual is flagged. Holding it "
            "harder (weight 10, or a hard constraint) always reaches it, and costs off the wall: lower Dice at every "
            "offset and a volume error up to +57 % at 30 mm, with no landmark warning (the bulge check flags some "
            "of those). So spheroseg reports the residual "
            "per landmark (`quality[\"landmark_residuals_mm\"]`, a warning above 2 mm) and does not force it.",
            "", f"Machine: {_machine(data['machine'])}; a shared machine under load."]
    return out


def _targets(acc, sp, sweep=None, user=None) -> list[str]:
    """Each target of the issues, met or missed, from the measured numbers."""
    rows = []

    def add(target, value, met):
        rows.append(f"| {target} | {value} | {'met' if met else '**missed**'} |")

    if acc:
        ours_key = f"spheroseg {acc.get('default_mode', 'local')}"
        speckle = [c["results"][ours_key] for c in acc["cases"] if c["family"] == "speckle"]
        d = np.median([r["dice"] for r in speckle])
        msd = np.median([r["msd_mm"] for r in speckle])
        add("median Dice >= 0.92 on standard speckle", f"{d:.3f}", d >= 0.92)
        add("median mean surface distance <= 1.5 mm on standard speckle", f"{msd:.2f} mm", msd <= 1.5)
        if acc.get("sequences"):
            err = max(abs(r[f"{ours_key} (tracking)"]["ef"] - r["truth_ef"]) for r in acc["sequences"])
            add("EF within 5 points on phantom sequences (worst)", f"{err:.1f} points", err <= 5)
        peers = [m for m in acc["cases"][0]["results"] if not m.startswith("spheroseg")]
        if peers:
            ours = [c["results"][ours_key] for c in acc["cases"]]
            t_ours = np.median([r["seconds"] for r in ours])
            d_ours = np.median([r["dice"] for r in ours])
            best = min(peers, key=lambda m: np.median([c["results"][m]["seconds"] for c in acc["cases"]]))
            t_peer = np.median([c["results"][best]["seconds"] for c in acc["cases"]])
            d_peer = np.median([c["results"][best]["dice"] for c in acc["cases"]])
            add(f"100x faster than the fastest peer ({best}) at equal or better median Dice",
                f"{t_peer / t_ours:.0f}x, Dice {d_ours:.3f} vs {d_peer:.3f}", t_peer / t_ours >= 100 and d_ours >= d_peer)
    if sp:
        sizes = sp["sizes"]
        for row in sizes:
            add(f"segmentation faster than loading the image ({row['shape']})",
                f"{row['segment_ms']:.1f} ms vs {row['load_ms']:.1f} ms", row["segment_ms"] < row["load_ms"])
        it = [r["iteration_us"] for r in sizes]
        seg = [r["segment_ms"] for r in sizes]
        add("time per iteration within 20 % from the smallest to the largest image",
            f"{min(it):.0f} to {max(it):.0f} us", max(it) <= 1.2 * min(it))
        add("whole segmentation within 20 % from the smallest to the largest image",
            f"{min(seg):.1f} to {max(seg):.1f} ms", max(seg) <= 1.2 * min(seg))
        unseen = (sp.get("default_mode") or {}).get("after", {}).get("unseen") or sp.get("unseen")
        if unseen:  # the default mode (issue 15): its last stage, and whole segmentations
            it_default = float(np.median([r["intensity_iteration_us"] for r in unseen]))
            worst, median = max(r["segment_ms"] for r in unseen), np.median([r["segment_ms"] for r in unseen])
            threads, cores = sp.get("threads"), ""
            if threads:  # the most threads, when measured (speed.py --threads)
                n = str(threads["counts"][-1])
                cases = [r[n] for r in threads["unseen"]]
                it_default = float(np.median([r["intensity_iteration_us"] for r in cases]))
                worst, median = max(r["segment_ms"] for r in cases), np.median([r["segment_ms"] for r in cases])
                cores = f" on {n} threads"
            add("<= 200 us per iteration at 8 x 8 patches, default mode (median over the unseen-style cases)",
                f"{it_default:.0f} us{cores}", it_default <= 200)
            add("<= 5 ms per whole segmentation on the unseen-style cases (default and wide PSF; worst)",
                f"{worst:.1f} ms (median {median:.1f}){cores}", worst <= 5)
        else:
            default = next(r for r in sp["profile"] if r["patches"] == "8 x 8")
            add("<= 200 us per iteration at 8 x 8 patches, 8 x 8 samples", f"{default['iteration_us']:.0f} us",
                default["iteration_us"] <= 200)
        mid = sizes[len(sizes) // 2]
        add(f"whole segmentation <= 10 ms ({mid['shape']})", f"{mid['segment_ms']:.1f} ms", mid["segment_ms"] <= 10)
        vps = sp["tracking"]["volumes_per_second"]
        add("tracking >= 200 volumes per second at 5 iterations per frame", f"{vps:.0f}", vps >= 200)
    for target, value, met in _sweep_targets(sweep):
        add(target, value, met)
    after = (user or {}).get("after", {}).get("results", {})
    for name, entry in after.items():  # the whole command (issue 15), a fresh interpreter per stage
        st = entry["stages"]
        voxels = int(np.prod([int(n) for n in name.split("x")]))
        add(f"mask < 20 ms ({name}, {voxels / 1e6:.1f} M voxels)", f"{1000 * st['mask']:.0f} ms", st["mask"] < 0.020)
        load = st["read"] + st["padding"]
        add(f"load (with the padding search) within 3 x SimpleITK's own read ({name})",
            f"{1000 * load:.0f} ms vs {1000 * st['sitk_read']:.0f} ms", load <= 3 * st["sitk_read"])
        add(f"`spheroseg segment` within 1 s without the report, 1.5 s with it ({name}, later runs)",
            f"{entry['later_no_report']:.2f} s, {entry['later_report']:.2f} s",
            entry["later_no_report"] <= 1.0 and entry["later_report"] <= 1.5)
    if not rows:
        return []
    return ["## Targets", "", "| target | measured | |", "| --- | --- | --- |"] + rows


def batch_section(b) -> list[str]:
    out = ["## Cohorts: spheroseg batch", "",
           f"Command: `{b['command']}` ({b['wall_seconds'] / 60:.0f} min). Machine: {_machine(b['machine'])}; "
           f"shared with other jobs (load average {b['load'][0]:.1f} at the start, {b['load'][1]:.1f} at the end, on 2 cores), so the figures are "
           "indicative.", "",
           f"{b['studies']} phantom volumes ({' x '.join(map(str, b['volume_shape']))} voxels, {b['spacing_mm']} mm) "
           "as .mha, default outputs (mask, meshes, surface JSON, CMISS, report PNG, results.json). Wall time from "
           f"the command's start to its exit, median of {b['repeats']} runs into fresh folders. Overhead: the "
           "worker-seconds a study costs beyond loading and segmenting it (outputs, interpreter and worker start, "
           "kernel loading, scheduling): wall x workers / studies - mean(load + segment). The Dask rows run on a "
           "`LocalCluster(n_workers=N, threads_per_worker=1, processes=True)` started beforehand.", "",
           "| how | studies/s | median wall s | load + segment s a study | overhead s a study |",
           "| --- | --- | --- | --- | --- |"]
    for name, c in b["configs"].items():
        out.append(f"| {name} (`{c['note']}`) | {_fmt(c['studies_per_second'])} | {_fmt(c['median_wall_seconds'], 1)} "
                   f"| {_fmt(c['mean_study_seconds'], 3)} | {_fmt(c['overhead_seconds_per_study'])} |")
    out += ["", f"A rerun with every study done (nothing to do but read and hash the inputs): median "
                f"{_fmt(float(np.median(b['resume_all_done_seconds'])), 1)} s for the cohort."]
    if b.get("dask_cluster_start_seconds"):
        out.append("Starting the Dask LocalCluster (not in the times above): " + ", ".join(
            f"{_fmt(v, 1)} s with {k} worker(s)" for k, v in b["dask_cluster_start_seconds"].items()) + ".")
    out += ["", "In the shell loop every study's segmentation is the first of its process, so its time includes "
            "loading the compiled kernels (about 0.2 s unloaded); the workers load them once. On a machine this "
            "loaded the second worker seldom finds a free core (the load + segment time of a study grows with it), "
            "so 1 against 2 workers is not measured here; what stands is the shell loop against any of the batch "
            "runs."]
    return out


def _userspeed(data) -> list[str]:
    from userspeed import report_section  # benchmarks/ is on the path of every script here

    return report_section(data).splitlines()


def _viewer(v) -> list[str]:
    m = v["medians_ms"]
    n = len(v["runs_ms"]["drag_to_final_ms_cetus" if "drag_to_final_ms_cetus" in m else "drag_to_final_ms"])
    lines = ["## The viewer's latency", "",
             f"Command: `{v['command']}` ({v['date']}; {v['machine']}, page {v['viewport'][0]} x {v['viewport'][1]}). "
             "A study served by `spheroseg view`'s server, driven by Playwright as a user: medians of "
             f"{n} repeats, milliseconds, measured in the page from the click's handler. *Contour drawn*: the "
             "final surface's contour on the slices, after a one-pixel `readPixels` (the slices under it are on "
             "screen); *3D drawn*: the 3D view after it (the page draws it once nothing has moved for 600 ms); "
             "*received*: when the page had the surface's event; *segmentation*: the descent on the server.", ""]
    rows = [("CETUS Patient 7 ED (0.9 mm assumed), 3D view on: click on the base", "base", "_cetus", "400"),
            ("CETUS Patient 7 ED: landmark dragged (release)", "drag", "_cetus", "300"),
            ("demo phantom, 3D view on: click on the base", "base", "", ""),
            ("demo phantom, 3D view off: click on the base", "base", "_slices_only", ""),
            ("demo phantom: landmark dragged (release)", "drag", "", "")]
    lines += ["| step | contour drawn | target | 3D drawn | received | segmentation |",
              "| --- | ---: | ---: | ---: | ---: | ---: |"]
    for label, kind, suffix, target in rows:
        if f"{kind}_to_final_ms{suffix}" not in m:
            continue
        segment = m.get(("segment_ms" if kind == "base" else "drag_segment_ms") + suffix)
        three = m.get(f"base_to_3d_ms{suffix}") if kind == "base" else None
        lines.append(f"| {label} | {m[f'{kind}_to_final_ms{suffix}']:.0f} | {target or '-'} | "
                     f"{'-' if three is None else f'{three:.0f}'} | {m[f'{kind}_to_final_received_ms{suffix}']:.0f} | "
                     f"{'-' if segment is None else f'{segment:.0f}'} |")
    software = ("No graphics card here: WebGL runs on SwiftShader, where the slices take about a hundred ms to draw "
                "and the 3D view of a large echo seconds; a placing click leaves the slices where they are and a new "
                "surface redraws only the contour (a 2D canvas), so nothing waits for WebGL before the contour.")
    if "base_to_final_ms_cetus" in m:
        met = [f"{what} {m[key]:.0f} ms against {target} ({'met' if m[key] <= target else 'missed'})"
               for what, key, target in (("base click", "base_to_final_ms_cetus", 400),
                                         ("landmark release", "drag_to_final_ms_cetus", 300))]
        lines += ["", f"Targets on CETUS Patient 7 with the 3D view on: {'; '.join(met)}. The page's own part is "
                      "the difference between *contour drawn* and *received*; the rest is the server's: the "
                      "descent, its intermediate surfaces and the event stream, on a machine shared by other jobs "
                      + (f"(load average {v['load_average_1min']:.1f} on its 2 cores at the end of the run)"
                         if "load_average_1min" in v else "") + ". " + software]
    else:
        lines += ["", software]
    if v.get("page_ready_s") is not None:
        lines += ["", f"The demo's page was ready {v['page_ready_s']:.1f} s after it was opened."]
    lines += ["", "Screenshots: `docs/viewer-1-loaded.png` (the demo, probe at the top), `-2-segmented`, "
                  "`-3-landmark`, `-4-tracked` (the sequence at end-systole), `-5-cetus` (CETUS Patient 7 "
                  "segmented, 3D view on; the echo is CETUS data, CC BY-NC-SA 4.0, Bernard et al. 2016, shown, not "
                  "shipped), `-6-help` (the shortcuts, on `?`)."]
    return lines


def _postprocessing(data) -> list[str]:
    cases = data["cases"]
    seeds = sorted({c["seed"] for c in cases})
    out = ["## Accuracy on post-processed echo (issue 30)", "",
           f"`{data['command']}` ({data['wall_seconds'] / 60:.0f} min, phantom generation included). Machine: "
           f"{_machine(data['machine'])}.", "",
           "The scenes `speckle` and `tilted` (seeds " + ", ".join(map(str, seeds)) + ") of the default formation "
           "post-processed as a scanner exports them (`echo.postprocess`: a Gaussian of sigma 1 and 2 mm, a median "
           "of half width 1 and 2 mm, 10 Perona-Malik iterations, persistence over 3 images, the Cartesian export "
           "at 0.7 and 1.5 mm instead of 1), and four raw formations (the most contrast, `blood_low` 43 dB and "
           "`contrast_high` 42 dB; `psf_narrow` and `psf_wide`, 2 and 4.5 mm FWHM laterally at 80 mm); "
           "`spheroseg.segment`, default options. 'bound' (the code before the smoothing's model and the wall's "
           "blur): the interface's log compression `k` is the speckle's spread bounded below by the region means' "
           "contrast taken at most "
           f"{data['max_contrast_db']:g} dB (`interface_nepers`). 'edge' (now): its level also lowered by the "
           "smoothing estimated from the speckle, across a "
           f"{data['edge_psf_mm']:g} mm FWHM point-spread function (`speckle_smoothing_mm`, `smoothed_edge_drop`); "
           "it also removes from the band means the deficit of the wall's blurred edge where the speckle is "
           "as formed (`edge_blur_mm`, `band_contamination`, below). Cells: median Dice, median (worst) volume "
           "error, median smoothing estimated (mm, sigma), median blur of the wall read from the speckle's "
           "correlation (mm, sigma, the widest image axis; used only under 0.75 mm of smoothing).", "",
           "| setting | bound: Dice | bound: volume error % | edge: Dice | edge: volume error % | smoothing mm | "
           "wall blur mm |",
           "| --- | --- | --- | --- | --- | --- | --- |"]
    for name in dict.fromkeys(c["setting"] for c in cases):
        rows = [c for c in cases if c["setting"] == name]
        cells = []
        for variant in data["variants"]:
            ve = np.array([c[variant]["volume_error_pct"] for c in rows])
            cells.append(f"{np.median([c[variant]['dice'] for c in rows]):.3f} | {np.median(ve):+.1f} "
                         f"({ve[np.argmax(abs(ve))]:+.1f})")
        blur = [c["edge_blur_mm"] for c in rows if "edge_blur_mm" in c]
        out.append(f"| {name} | " + " | ".join(cells) + f" | {np.median([c['smoothing_mm'] for c in rows]):.2f} | "
                   + (f"{np.median(blur):.2f} |" if blur else " |"))
    out += ["", "Smoothing narrows the speckle's spread and leaves the region means: the spread alone gives `k` "
            "2-3.5 times low, and the contrast bound holds it (14-16 grey levels per neper). What the bound "
            "leaves is the edge: across the wall the mean grey level is `c_out + k ln(eps + (1 - eps) "
            "Phi(x / sigma))` (a point-spread function of standard deviation `sigma`), concave at the interface, "
            "so a Gaussian smoothing of standard deviation `s` lowers its level there (by 0.30 `k` at "
            "`s = sigma`, 0.98 `k` at `s = 2 sigma`, 35 dB) and the level crossing moves outwards. The smoothing "
            "is the speckle's correlation between neighbouring voxels, the least over the image axes (along the "
            "beam raw speckle hardly correlates): 0.4 mm on the raw export, 1.4 after the 1 mm Gaussian, 1.9 "
            "after the 2 mm one, 0.5 after persistence (which averages independent speckle). The level is lowered "
            "by the smoothed edge's drop across a nominal 3 mm FWHM point-spread function (an adult apical 3D "
            "scan's at 80 mm).", "",
            "The band means themselves are read about the local means' wall, which lies about two widths of the "
            "point-spread function inside the interface: across a wide one the outer band's near offsets are still "
            "in the blurred edge, `c_out` reads low and the wall goes inwards (psf_wide was -3.5 / -3.2 % in the "
            "formation sweep; the tests' speckle cavity, an image of another making without scan conversion, "
            "-5.3 % at 2 mm of amplitude spread and -8.6 % at 2.5 mm). Where the speckle is as formed (smoothed by "
            "less than 0.75 mm, `FORMED_SPECKLE_SMOOTHING_MM`: 0.3-0.5 mm on every raw setting here, 1.0-1.9 after "
            "the filters), the same correlation between neighbouring voxels gives the point-spread function along "
            "each image axis (the log's correlation is `(6 / pi^2) Li2` of the intensity's; `edge_blur_mm`, "
            "checked on simulated speckle to 3 %), and the band means lose the deficit the model of the blurred "
            "edge predicts about the local means' wall (`band_contamination`, checked against a numerically "
            "blurred edge). The raw settings above then read (formation sweep, upright / tilted): psf_wide "
            "+0.5 / -1.8 %, default +0.4 / +0.7 %, psf_narrow unchanged; the speckle cavity -1.7 % at 2 mm and +0.2 % "
            "at 2.5 mm. "
            "The filtered settings are unchanged.", ""]
    out += _tried([
        ("the histogram's shape as the measure of smoothing (log speckle's skewness and excess kurtosis shrink "
         "by sqrt(N) and N under averaging)", "fully developed: -1.14 and 2.4; the raw export: -0.32 and 0.22",
         "no: no usable N"),
        ("fitting the log edge (position, PSF width, smoothing) to the mean profile across the wall",
         "the PSF width at its bound, the position 1.2 mm off on the raw export",
         "no: averaged over the wall's orientations the profile is a blurred step whatever the smoothing"),
        ("the speckle's spread ratio to the bound as the measure of smoothing",
         "persistence 0.66 (no edge blur), the median 0.5 (little)", "no: would over-correct both"),
        ("the nominal PSF width, 1.0 or 1.6 mm sigma instead of 1.27",
         "the 2 mm Gaussian's median +0.1 or +3.5 % instead of +2.1 % (four cases, before the estimate read the "
         "band's 8 mm offset too)", "1.27 kept: the model's one constant"),
        ("the wall's blur read from the speckle everywhere, the point-spread function's width then also in "
         "the smoothing's edge drop (one model of the blurred, smoothed edge)",
         "raw settings as now or better (psf_narrow +1.9 / +1.9 %), but the filtered ones read a point-spread "
         "function of 0.1-3.2 mm (a voxel apart their speckle correlates by 0.8-0.97 along every axis): the 2 mm "
         "median -10.0 / -6.6 %, the 2 mm Gaussian -5.2 / +2.3 %", "no: the gate on the smoothing kept"),
        ("... gated on the speckle's spread having set `k` (above the contrast bound) instead",
         "the 1 mm Gaussian's upright scene passed the gate (the raw default is only 2 % above the bound): "
         "+2.8 %", "no"),
        ("... and the trilinear sampler's smoothing (a voxel's triangle, `h^2 / 6` along the normal) in the "
         "edge drop", "psf_narrow +0.3 / +0.4 % (was +2.1 / +3.0), default -0.8 / -0.7 %; but the speckle cavity "
         "with 0.5 mm of spread -2.7 % (was +4.3): its point-spread function is alike along every axis, and what "
         "all axes share is taken for the export's interpolation", "no"),
        ("... with the sampler's interpolation, and the blur read without removing what the axes share",
         "the speckle cavity at 0.5 mm +1.0 % (was +4.3), psf_narrow +2.0 / +2.1 %; but psf_wide +2.9 / -0.1 % "
         "and default +0.9 / +0.8 % (now +0.5 / -1.8 and +0.4 / +0.7); the speckle cavity at 2 mm -1.5 %",
         "no: not better across the settings; the sampler's share of the sharp edges' outward bias is the "
         "lead it leaves")])
    return out


def _simulators(data) -> list[str]:
    rows = data["rows"]
    before, now = data["variants"]
    out = ["## Echo of another making: speckle that does not show the blur (issue 30)", "",
           f"`{data['command']}` ({data['wall_seconds']:.0f} s). Machine: {_machine(data['machine'])}.", "",
           "Many simulators blur the scene's mean intensity and multiply it by speckle independent from voxel to "
           "voxel (`synthetic.echo.multiplicative_speckle`); a scanner's speckle, and the phantom's, is the "
           "point-spread function's own size. The scene: a half ellipsoidal cavity (semi-axes 22, 22 and 70 mm, "
           "71 mL; blood 30 dB below the myocardium), an 8 mm wall, tissue beyond it 12 dB darker, as bright or "
           "6 dB brighter; 1 mm voxels blurred by an isotropic Gaussian (standard deviation), seeds "
           + ", ".join(str(s) for s in sorted({r["seed"] for r in rows})) + ". `spheroseg.segment`, default "
           f"options. '{before}': the wall's blur read from the speckle alone (as before); '{now}' (now): also "
           "from the outer band's profile (`dataterms.profile_blur_mm`). Cells: median (worst) volume error, "
           "median blur read (mm), cases flagged with a dark wall.", "",
           f"| blur mm | tissue beyond the wall dB | {before}: volume error % | {now}: volume error % | "
           "blur read mm | flagged dark |", "| --- | --- | --- | --- | --- | --- |"]
    for blur in dict.fromkeys(r["blur_mm"] for r in rows):
        for tissue in dict.fromkeys(r["tissue_db"] for r in rows):
            chosen = [r for r in rows if r["blur_mm"] == blur and r["tissue_db"] == tissue]
            cells = []
            for variant in (before, now):
                ve = np.array([r[variant]["volume_error_pct"] for r in chosen])
                cells.append(f"{np.median(ve):+.1f} ({ve[np.argmax(abs(ve))]:+.1f})")
            read = np.median([r[now]["blur_read_mm"] for r in chosen])
            dark = sum(r[now]["dark_wall"] for r in chosen)
            out.append(f"| {blur:g} | {tissue:+g} | " + " | ".join(cells) + f" | {read:.2f} | {dark} of {len(chosen)} |")
    out += ["", "The intensity interface removes from its band means the deficit the wall's blurred edge leaves "
            "in them, the blur read from the speckle's correlation (`edge_blur_mm`, the post-processing section). "
            "Speckle independent from voxel to voxel reads none (0.2-0.3 mm here), the outer band's near offsets "
            "stay in the edge and the wall goes in: 10-12 % at 2 mm, a quarter of the volume at 3 mm. The outer "
            "band's profile shows the blur still (its median at each of its offsets, 2-8 mm beyond the local "
            "means' wall): less the speckle's deficits, its far half still reads above its near half, by "
            "shrinking steps. `profile_blur_mm` reads the blur whose deficits leave no such rise, at most "
            f"{data['max_edge_blur_mm']:g} mm (beyond it the band, too short to see the edge's foot, reads blurs "
            "alike whose deficits are not), in proportion to the part of the rise `beyond_wall_excess` leaves to "
            "the edge. Past a dark wall blurred as widely as the band is long, the band's rise is also the "
            "brighter tissue's: the offsets as far again past the band (10-16 mm), less the read blur's deficits, "
            "then read above the plateau the blur implies (by 0.14-0.19 of the blood-wall contrast here; -0.01 "
            "to +0.02 where the tissue is as bright as the wall, -0.15 to -0.35 where darker), and the blur read "
            "falls back to the speckle's in proportion, none kept where that excess is as large as the read "
            "raised the plateau (those offsets are read only when the band's profile gave a blur). The phantom's "
            "formations, post-processings, rim and papillary muscles and CETUS Patient 7 are unchanged: with "
            "their speckle's blur removed their profiles do not rise. What is left at 0.5 mm (+2.7 to +3.8 %) is "
            "the trilinear sampler's averaging of a sharp log edge (the post-processing section's lead). A wall is "
            "flagged dark (`DARK_WALL`) where it reads darker than the 8 mm beyond it by more than 3 % of the "
            "blood-wall contrast (`epicardium.DARK_WALL_MARGIN`: tissue 1 dB brighter at 30 dB, read as the wall's "
            "level, moves the volume by about 2 %); before, by any amount, and half the walls as bright as the "
            "tissue beyond them (-0.5 to -2 grey levels of about 100: the blurred edge leaves the wall a little "
            "darker) were flagged. At 3 mm the edge leaves it darker than that.", ""]
    out += _tried([
        ("the blur read from the band without the fall-back past it", "dark walls (tissue +6 dB) at 1.5-2.5 mm "
         "+5.3 to +18.8 % (the speckle's blur alone: -2.7 to -15.4 %); the tests' confocal shells with 6 dB darker "
         "walls blurred by 2 mm +13.9 to +17.1 % (were -12.1 to -12.6)", "no: fall back where the rise goes on"),
        ("the blur read up to 4 mm", "the tests' confocal shells blurred by 3 mm +8.6 to +9.3 % (at 3 mm: -11.3 "
         "to -12.3 %; the speckle's alone: -30 %)", "no: 3 mm, where the step rule holds"),
        ("sampling the surface's grey level in intensity (the log of the trilinear mean of `exp(v / k)`) "
         "against the sampler's outward bias at sharp edges", "the tests' confocal shells blurred by 0.5 mm "
         "+4.5 to -3.4 %, but by 1 and 2 mm -0.9 to -7.3 and -2.7 to -11.5 %: the log of a mean of independent "
         "speckle reads high between voxel centres", "no"),
        ("the finest levels' tolerance 0.01 mm instead of 0.05", "the cavity blurred by 2 mm (the tests' white "
         "speckle cavity, 24 x 24 x 40 mm) -5.0 to -0.8 % in 76 iterations instead of 41: across a wide edge the "
         "intensity stage's force is weak and it stops short; the phantom's formations move by 0.1-0.4 points",
         "no: noted"),
        ("the intensity stage's step scaled by the blur read over 1.27 mm", "that cavity -5.0 to -4.0 %",
         "no"),
        ("the trilinear sampler's drop at the interface (a hat of variance `h^2 / 6` along the normal, with the "
         "export's smoothing, across the blur read, the band's before its fall-back), and the near half's level "
         "where the far half reads below it (the formation sweep's tried rows, with this blur)",
         "every formation within 3 % (contrast_low +1.0 / +0.9, psf_narrow +1.8 / +1.8, psf_wide +2.7 / -2.5, "
         "tgc_over -2.2 / -2.4, contrast_high -1.8 / -2.4 %), the post-processings within 2.2 %, this section's "
         "0.5 mm blur -0.3 to -0.7 % (now +2.8 to +3.7); but the rim -7.4 / -6.7 % (now -5.9 / -5.3), a dark "
         "wall here at 1 mm -7.6 % (now -1.3; its blur unread: the band's rise went to the tissue beyond, the "
         "speckle shows 0.3 mm), walls as bright as the tissue at 2.5 mm +5.9 % (now +3.1)",
         "no: the drop needs the edge's blur, which speckle of this making hides"),
        ("measured besides, the open gap: a scanner's smoothing on a point-spread function other than the "
         "nominal one (the formation sweep's scenes, one pair each, this code)", "psf_narrow then gaussian_1mm "
         "+3.0 / +3.3 %, gaussian_2mm +6.4 / +6.4 %, median_2mm +1.5 / +2.2 %; psf_wide then gaussian_1mm "
         "-4.4 / -3.7 %, gaussian_2mm -5.1 / -4.2 %, median_2mm -6.2 / -5.2 % (default: -0.1 to +1.9 %); this "
         "section's scenes smoothed by a Gaussian of 1 and 2 mm: blurred by 0.5 mm +7.5 to +16.1 %, by 2 mm -8.0 "
         "to -10.1 %, none flagged. Smoothed speckle hides the point-spread function, and the smoothing's drop "
         "is modelled across the nominal 3 mm FWHM one (`EDGE_PSF_MM`)", "left open"),
        ("the edge's blur read from the band in smoothed images too (at least the smoothing's, its deficits "
         "removed, the smoothing's drop across the rest of it instead of the nominal point-spread function)",
         "this section's scenes smoothed: blurred by 0.5-1 mm unchanged (the band shows no blur that small), by "
         "2 mm -0.1 to -15.3 % (were -8.0 to -10.1)", "no")])
    return out


def _framerate(data) -> list[str]:
    out = ["## Tracking at any frame rate (issue 30)", "",
           f"`{data['command']}` ({data['wall_seconds'] / 60:.0f} min). Machine: {_machine(data['machine'])}.", "",
           "Cycles of the default formation whose annulus descends "
           f"{data['base_descent_mm']:g} mm at end-systole, made at 20 frames a cycle and tracked with every "
           "frame, every 2nd and every 5th, and as the pair end-diastole, end-systole; a cycle made at 6 frames. "
           "`spheroseg.track` with default options: each frame is stepped from the previous surface, and some are "
           "segmented again (below). Poor: frames whose quality report warns; least base radius over the frames; "
           "frames segmented again (of those after the first). Seconds per frame on a shared machine.",
           "", "| seed | frames | true EF % | tracked EF % | EF error points | EDV error % | ESV error % | poor frames | "
           "least base radius mm | segmented again | s per frame |", "| --- |" + " --- |" * 10]
    for r in data["rows"]:
        out.append(f"| {r['seed']} | {r['sampling']} | {r['truth_ef']:.1f} | {r['tracked_ef']:.1f} | "
                   f"{r['ef_error']:+.1f} | {r['edv_error_pct']:+.1f} | {r['esv_error_pct']:+.1f} | "
                   f"{r['poor_frames']} | {r['min_base_radius_mm']:.1f} | {r.get('segmented_again', '')} | "
                   f"{r['seconds_per_frame']:.2f} |")
    samplings = dict.fromkeys(r["sampling"] for r in data["rows"])
    worst = {s: max((r["ef_error"] for r in data["rows"] if r["sampling"] == s), key=abs) for s in samplings}
    out += ["", "Worst EF error over the seeds: " + ", ".join(f"{s} {e:+.1f}" for s, e in worst.items()) + " points.",
            "", "A frame is segmented again through the coarse data term (from its start surface, and from the "
            "initial shape, smoothed on the finest patches towards that shape fitted to the volume its coarse "
            "levels found: `smoothness_reference='fitted'`, the accuracy sweep's section), the stepped one kept "
            "unless another's data energy is lower by 1 %, when its stepped "
            "descent did not converge (capped before it settled, as at the descent reference's 5 iterations a "
            "frame: its wall was still moving) or left the wall behind (`frames.followed_the_wall`: in some sector "
            "of the mid or basal wall the 4 mm just inside the surface read more than a quarter of the way from the "
            "blood's grey level to the wall's, or the 4 mm just outside less). The apical half is not read: "
            "near-field clutter (`clutter_strong`) raises the inner band there to 0.48 on followed frames, and the "
            "apex barely moves over a cycle. What it cannot see is bounded by how far the wall moved on the whole "
            "(`frames.wall_motion_mm`: the volume's change over the mean area of the two walls): a frame whose wall "
            "moved by more than half the local means' band (4 mm), which the finest levels cannot be trusted to "
            "follow, is segmented again too. The stepped walls moved 0.2-1.5 mm a frame at 20 frames a cycle, up to "
            "2.9 at 10, 4.0 at 4 (seed 0) and 4.5 at 6 (seed 1, 1.5 mm voxels); from end-diastole to end-systole "
            "directly 5.1-5.5 (default, seeds 0 and 3; the check found those left behind) and 6.5-6.8 mm under "
            "`clutter_strong`, whose stepped "
            "end-systoles followed the basal wall and kept the apical one (ESV +21 / +14 %, EF 7.1 / 4.3 points low "
            "before). Where the stepped surface settled yet left the wall behind, the same "
            "check judges the candidates, and the one of lowest energy among those on the wall replaces it (by "
            "energy alone where none is): the energy's scalar levels preferred the stepped surfaces of tgc_under's "
            "pairs, whose basal wall the weak time-gain compensation left dark inside them (ESV +35 to +49 %, EF "
            "12-23 points low, unflagged; now the pairs' table below). The tracked EFs above, and those of the legacy "
            "cycles and of the "
            "descent reference's, are the ones segmenting every frame again gave. The levels, over the 12 sectors "
            "of the basal wall:", "",
            "| frames | largest inner-band level | least outer-band level |", "| --- | --- | --- |",
            "| followed by the stepped descent: these cycles, the legacy 10- and 6-frame cycles, the descent "
            "reference's 4-frame cycle, 10- and 5-frame cycles of each of the 16 formations (seed 3) | -0.37 to "
            "0.11 | 0.44 to 0.59 |",
            "| the same under `dropout` (the wall without echo reads dark outside; two frames segmented again, to "
            "no change) | | 0.23-0.35 |",
            "| end-systoles reached from end-diastole directly (where the annulus descends) | 0.57 to 0.70 | |",
            "| the 9 post-processings of the smoothing sweep (10-frame cycles, seed 3), followed frames (none "
            "segmented again) | -0.02 to 0.11 | |",
            "| the same, their ED-ES pairs (every pair segmented again) | 0.52 to 0.58 | |"]
    pairs = data.get("pairs")
    if pairs:
        settings = list(dict.fromkeys(r["setting"] for r in pairs["rows"]))
        seeds = sorted({r["seed"] for r in pairs["rows"]})
        out += ["", f"End-diastole to end-systole directly, every formation (`{pairs['command']}`, "
                f"{pairs['wall_seconds'] / 60:.0f} min; {pairs['machine']['date']}): the pair alone (1.5 mm voxels, "
                f"the annulus descending {data['base_descent_mm']:g} mm) of each named formation and of the default "
                "one post-processed as a scanner exports it (the export grids aside), tracked with default options. "
                "Cells: EF error in points (poor frames), seeds " + ", ".join(map(str, seeds)) + ".", "",
                "| setting | " + " | ".join(f"seed {s}" for s in seeds) + " |", "| --- |" + " --- |" * len(seeds)]
        for name in settings:
            cells = {r["seed"]: f"{r['ef_error']:+.1f}" + (f" ({r['poor_frames']})" if r["poor_frames"] else "")
                     for r in pairs["rows"] if r["setting"] == name}
            out.append(f"| {name} | " + " | ".join(cells.get(s, "") for s in seeds) + " |")
        errors = np.array([r["ef_error"] for r in pairs["rows"]])
        beyond = [r for r in pairs["rows"] if abs(r["ef_error"]) > 3]
        out += ["", f"Within 3 points: {int(np.sum(np.abs(errors) <= 3))} of {len(errors)} pairs; median "
                f"{np.median(errors):+.1f} points."
                + ("" if not beyond else " Beyond: " + ", ".join(
                    f"{r['setting']} seed {r['seed']} (ESV {r['esv_error_pct']:+.0f} %, segmented again "
                    f"{r['segmented_again']})" for r in beyond)
                   + ".")]
    every = data.get("formations")
    if every:
        samplings = list(dict.fromkeys(r["sampling"] for r in every["rows"]))
        out += ["", f"Low frame rates, every formation (`{every['command']}`, {every['wall_seconds'] / 60:.0f} min; "
                f"{every['machine']['date']}): the seed-3 cycle of each named formation at 4 and 5 frames a cycle "
                "(every 5th and 4th of 20) and made at 6, tracked with default options. Cells: EF error in points "
                "(poor frames; frames segmented again).", "",
                "| formation | " + " | ".join(samplings) + " |", "| --- |" + " --- |" * len(samplings)]
        for name in dict.fromkeys(r["setting"] for r in every["rows"]):
            cells = {r["sampling"]: f"{r['ef_error']:+.1f}" + (f" ({r['poor_frames']}; {r['segmented_again']})"
                                                              if r["poor_frames"] or r["segmented_again"] else "")
                     for r in every["rows"] if r["setting"] == name}
            out.append(f"| {name} | " + " | ".join(cells.get(s, "") for s in samplings) + " |")
        errors = np.array([r["ef_error"] for r in every["rows"]])
        out += ["", f"Within 3 points: {int(np.sum(np.abs(errors) <= 3))} of {len(errors)} cycles; median "
                f"{np.median(errors):+.1f}, worst {errors[np.argmax(np.abs(errors))]:+.1f} points."]
    sp = data.get("speed")
    if sp:
        out += ["", "Tracking speed (`python benchmarks/framerate.py --speed`, " + sp["date"] + ", load average "
                f"{sp['load_start']:.1f} at the start and {sp['load_end']:.1f} at the end: on a busy machine the "
                "ratio holds, not the rates): the legacy 10-frame cycle of benchmarks/speed.py's tracking line at 5 "
                "iterations a frame, segmenting again the frames whose wall was left behind or moved far (the default), every "
                "frame, or none; interleaved, medians of 3; the least volume over the stepped frames against the "
                f"true ESV {sp['truth_esv_ml']:.1f} mL.", "",
                "| frames segmented again | volumes per second at 5 iterations a frame | least volume mL |",
                "| --- | --- | --- |"]
        for name, row in sp["policies"].items():
            out.append(f"| {name} | {row['volumes_per_second_5']:.1f} | {row['esv_ml']:.1f} |")
        out += ["", f"The whole `spheroseg.track` of the cycle: {sp['track_volumes_per_second']:.1f} volumes per "
                f"second, EF {sp['ef']:.1f} % (true {sp['truth_ef']:.1f} %)."]
    out += [""] + _tried([
        ("the stepped surface alone (seed 0, end-diastole to end-systole)",
         "stays near the end-diastolic wall: ESV +48 %, EF about 19 points low", "no"),
        ("a fresh start kept by energy, the annulus searched +-8 mm while it descends 10 (seed 0, the same pair)",
         "-4.0 points", "no"),
        ("the initial shape's segmentation smoothed towards the clicked shape itself (the default `segment`), "
         "whose proportions are the first frame's (base radius 0.3 of the long axis; an end-systole reads 0.21)",
         "end-diastole to end-systole: seeds 0-2 -2.4, -2.1, -2.6 points (ESV +6.9, +5.1, +8.2 %; now -0.9, -1.4, "
         "-1.6 and +3.1, +3.4, +5.6); the seed-3 cycle, start -> fitted: default -2.4 -> -1.2, contrast_low -3.2 "
         "-> -0.3, psf_narrow -2.5 -> -0.8, default then gaussian_2mm -3.2 -> -2.3, psf_wide -0.8 -> +0.9, "
         "clutter_strong -3.9 either way (its stepped surface kept: ESV +12.6 %)", "no: fitted"),
        ("the apical sectors read too, against what the first frame's surface read there (near-field clutter "
         "does not move with the heart): `clutter_strong` seed 0 end-diastole to end-systole, the sectors 0.17-0.33 "
         "of the way from the apex", "the first frame's inner band 0.48-0.59, the stepped end-systole's (left "
         "behind) 0.49-0.67, the candidate segmented afresh (on the wall) 0.26-0.38 on its own levels: the haze "
         "reads as high as a wall left behind", "no: the wall's motion instead"),
        ("the code before, on the legacy image's 6-frame cycles (seeds 0-2, 1.5 mm), end-diastole to end-systole",
         "-16.7, -24.8, -11.7 points (now -3.0, -2.3, -2.8); their 6-frame tracking unchanged (-2.0, -1.6, -1.7)",
         "no: replaced by the present check"),
        ("segmenting a frame again only when its stepped surface holds the frame's blood (the Chan-Vese data "
         "energy over the cavity's volume and the squared contrast) less well than a fraction of the first frame's",
         "frames no candidate replaced 0.92-1.00 (legacy 4- and 6-frame cycles); end-systoles reached from "
         "end-diastole directly 0.73-0.81; the descent reference's 4-frame end-systole (seed 7, 2 mm, "
         "`mode='local'`, base kept still), which a candidate replaced (EF 55.3 % against 50.3 without, true "
         "55.0), 0.895", "no: too thin a margin (that frame's descent had not converged, which the present check "
         "reads)")])
    return out


def _anatomy(data) -> list[str]:
    rows = data["rows"]
    out = ["## Papillary muscles and trabeculae (issue 30)", "",
           f"`{data['command']}` ({data['wall_seconds'] / 60:.0f} min). Machine: {_machine(data['machine'])}.", "",
           "The scenes `speckle` and `tilted` (4 hearts) of the default formation, plain, with two papillary "
           "muscles standing in the cavity, and with the muscles and a 3 mm rim of trabecular ridges inside the "
           "compact wall; the truth follows the compact wall (muscles and trabeculae are cavity, the CETUS and "
           "ASE convention). `spheroseg.segment` with default options: median Dice, median (worst) volume "
           "error in %.", "", "| anatomy | Dice | volume error % |", "| --- | --- | --- |"]
    for name in dict.fromkeys(r["anatomy"] for r in rows):
        chosen = [r for r in rows if r["anatomy"] == name]
        ve = np.array([r["volume_error_pct"] for r in chosen])
        out.append(f"| {name} | {np.median([r['dice'] for r in chosen]):.3f} | {np.median(ve):+.1f} "
                   f"({ve[np.argmax(abs(ve))]:+.1f}) |")
    out += ["", "The muscles keep the bias within the +-3 % target. The trabecular rim does not. Where the surface "
            "ends, read along its normals against the truth (speckle seed 0, the rim without the muscles, -5.5 %): "
            "at the apex, where the rim is 3 mm deep, on the compact wall (within 0.1 mm); along the mid and basal "
            "wall, where the rim thins to 1.3-2.5 mm, under the point-spread function's width, 0.6-1.0 mm inside "
            "it, half way into the rim, whose 40 % of tissue merges there into the wall's blurred edge. The local "
            "means lose as much (with the muscles: -23.8 % with the rim, -16.1 % without; the interface -6.5 % and "
            "-0.7 %): the bias is the image's, not the interface level's. Raising the level towards the wall's would move every plain wall out: not done "
            "(it would be tuned to this phantom's rim)."]
    out += [""] + _tried([
        ("the interface level raised by a fraction of the blood-wall contrast (speckle / tilted, 2026-11-27)",
         "0.04: plain +3.8 / +3.7 %, the muscles and rim -2.2 / -2.1 %; 0.08: +8.3 / +7.9 and +2.7 / +2.4 %; "
         "0.12: +16.1 / +15.4 and +11.3 / +9.7 %: the rim stays 4.8-6.2 points below the plain wall at every level",
         "no: the rim must be told from a plain wall first"),
        ("telling them apart by the median grey-level profile along the normals of the mid and basal wall "
         "(0.1-0.6 of the way from base to apex, speckle scenes, the profile scaled from blood to wall)",
         "the rim shows as a foot on the blood side, +0.05 to +0.10 of the contrast 2-4 mm inside the surface, the "
         "rise's 20-80 % width 2.9-3.0 mm against 2.5-2.6 on the plain wall, the muscles, clutter_strong and "
         "contrast_high (wall blur read 0.62-0.69 mm on all); but psf_wide (blur read 1.17 mm) 3.2 mm with a foot "
         "of 0.13-0.32, psf_narrow (0.41 mm) 1.9 mm, gaussian_2mm 3.6 mm: the width varies with the point-spread "
         "function more than the rim widens it, and the blur read from the speckle (the median over the normals) "
         "does not predict the width closely enough to leave the rim's 0.4 mm", "no"),
        ("... against a model of the edge along each normal: the median of the blurred log edges of standard "
         "deviation `sqrt(n C n)` (`C` the speckle's covariance, `edge_blur_covariance`), the same 20-80 % width",
         "measured less modelled: plain walls 0.57-1.24 mm over 7 formations and the muscles (speckle and tilted "
         "scenes), the rim 1.40 / 1.43 mm", "no: the rim's 0.2-0.4 mm lies within the plain walls' spread"),
        ("... by the grey level's variation around the wall: on rings of the surface 0.2-0.5 of the way from base "
         "to apex (360 points each), the variance around the ring, a 60-degree moving average removed, of the mean "
         "grey level 0.5-2.5 mm inside the surface, over that of the tissue 3-5 mm outside (log speckle's variance "
         "does not depend on its mean), median over the rings",
         "the rim 3.8 / 4.1 (without the muscles 3.1 / 3.7); every plain wall 0.71-2.08: the muscles 1.5, the eight "
         "formations measured 0.95-2.08 (contrast_high the most), gaussian_2mm, median_2mm and diffusion 0.71-1.86 "
         "(speckle / tilted scenes)", "the lead left: the ridges (a 7.7 mm period at the mid wall, resolved "
         "laterally) show; where they do, the compact wall is the outer end of the modulated zone, to be read "
         "along each normal. The margin (2.1 against 3.1) is this phantom's: real trabeculae are irregular, so "
         "the test wants real echo with expert contours first"),
        ("... the same variance read at each offset along the normals (rings of 240 points, a 60-degree moving "
         "average removed, the grey levels averaged over +-0.5 mm along the normal), over the tissue's at 4-6 mm, "
         "speckle seed 0, the surfaces the default segmented (2026-11-27)",
         "the rim alone (-5.0 %), on five rings of the wall: 3.6-5.3 at 1.5-2.5 mm inside the surface, 0.9-2.2 "
         "at +0.5 mm, 1.0 at +2.5 mm; it falls to twice the tissue's 0.5-2.4 mm inside the truth (which lies "
         "+0.25 to +1.25 mm out); the papillary muscles alone (-0.3 %), on the rings they "
         "stand on: 6.8-7.9 at 3 mm inside, 2.6 / 1.5 at the surface, 1.7 / 1.3 at +0.5 mm, the truth at +0.25 to "
         "+0.75 mm; the plain wall 0.6-1.6 everywhere", "no: the muscles, cavity too and already segmented right, "
         "modulate the grey level as the rim does, and their modulation ends 0.5 mm nearer the surface; where the rim's"
         " ends does not place its compact wall either"),
        ("a tangential low quantile: at every offset along the normals the grey level replaced by a low quantile "
         "of its neighbours on the same offset surface (0.25 in 4 mm; 0.1 of means over 1.5 mm discs in 5 mm; 0.1 "
         "of 2.5 mm means in 6 mm), less the quantile's own deficit in the cavity (log speckle is a location "
         "family: a region's quantile lies a fixed step below its mean), so that blood between ridges pulls the "
         "wall out while a wall constant along the surface stays", "the level's crossing on the mid wall moves "
         "out 0.1-0.3 mm on the rim and 0.05-0.25 mm on the plain wall (speckle seed 0); the rim's truth lies 0.3-"
         "0.6 mm beyond the unmoved crossing", "no: across the rim's thin mid wall the point-spread function "
         "leaves the gaps too little contrast against the speckle"),
    ])
    return out


def _located_summary(rows) -> dict:
    """The figures of one set of located cases (:func:`_locate`'s table)."""
    found = [r for r in rows if "refused" not in r]
    confident = [r for r in found if r["confidence"] >= 0.5]
    apex, base = np.array([r["apex_mm"] for r in found]), np.array([r["base_mm"] for r in found])
    worst = max((max(r["apex_mm"], r["base_mm"]) for r in confident), default=float("nan"))
    d, v = np.array([r["dice"] for r in found]), np.array([r["volume_error_pct"] for r in found])
    good = [r for r in found if r["dice"] >= 0.90]
    t = np.array([r["locate_s"] for r in found])
    flags = [r["clicks_flagged"] for r in found if "clicks_flagged" in r]
    return {"located": f"{len(found)} / {len(rows) - len(found)}",
            "apex": f"{np.median(apex):.1f} mm ({apex.max():.1f})",
            "base": f"{np.median(base):.1f} mm ({base.max():.1f})",
            "trusted": f"{worst:.1f} mm ({len(confident)} of {len(found)})",
            "untrusted": f"{sum(r['confidence'] < 0.5 and max(r['apex_mm'], r['base_mm']) < 6.0 for r in found)}",
            "dice": f"{np.median(d):.3f} ({d.min():.3f})",
            "good_poor": f"{sum(r['poor'] for r in good)} of {len(good)}",
            "bad": f"{sum(r['dice'] < 0.85 and not r['poor'] for r in found)}",
            "volume": f"{np.median(v):+.1f} %", "time": f"{1000 * np.median(t):.0f} ms ({1000 * t.max():.0f})",
            "clicks": (f"{sum(bool(f) and not f[0].startswith('not checked') for f in flags)} "
                       f"({sum(bool(f) and f[0].startswith('not checked') for f in flags)} not checked)"
                       if flags else "")}


def _locate(data) -> list[str]:
    rows = data["cases"]
    dev = data.get("devset") or []
    sets = [_located_summary(rows)] + ([_located_summary(dev)] if dev else [])
    labels = [("located", "cases located / refused", "all located"),
              ("apex", "apex error, median (worst)", "6 (10) mm"), ("base", "base error, median (worst)", "6 (10) mm"),
              ("trusted", "worst error with confidence >= 0.5", "10 mm"),
              ("untrusted", "within 6 mm yet confidence < 0.5", "few"),
              ("dice", "Dice without points, median (worst)", "0.94"),
              ("good_poor", "Dice >= 0.90 flagged poor", "1 in 10"),
              ("bad", "Dice < 0.85 not flagged poor", "0"),
              ("volume", "volume error, median", "within 5 %"), ("time", "locate time, median (worst)", "300 ms"),
              ("clicks", "user-like clicks flagged wrong", "0 (the not checked said so)")]
    out = ["## Finding the ventricle without clicks (issues 29, 48)", "",
           f"Command: `{data['command']}`. The phantom sweep: seeded random phantoms (2 mm voxels): tilt 0-25 "
           "degrees, long axis 60-100 mm, radius 0.26-0.38 of it, ED or ES (radius 0.7 as large, wall 13.5 mm), "
           "each imaged by the next formation of the sweep. The devset (`../shared/data/devset`, another "
           "simulator: its 8 volumes and every third frame of its sequence, exact truth): the same, and its "
           "user-like clicks checked against the location. `locate(volume)` (its time the least of two calls "
           "after a first), then `segment(volume)` with no points.", "",
           "| measure | phantom sweep | devset | target |" if dev else "| measure | phantom sweep | target |",
           "| --- | --- | --- | --- |" if dev else "| --- | --- | --- |"]
    for key, label, target in labels:
        if key == "clicks" and not dev:
            continue
        out.append(f"| {label} | " + " | ".join(s[key] or "-" for s in sets) + f" | {target} |")
    out += ["", "| formation | phase | tilt | truth mL | apex mm | base mm | confidence | Dice | volume error | poor |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        if "refused" in r:
            out.append(f"| {r['formation']} | {r['phase']} | {r['tilt_deg']:.0f} | {r['truth_ml']:.0f} | refused: "
                       f"{r['refused']} | | | | | |")
        else:
            out.append(f"| {r['formation']} | {r['phase']} | {r['tilt_deg']:.0f} | {r['truth_ml']:.0f} | "
                       f"{r['apex_mm']:.1f} | {r['base_mm']:.1f} | {r['confidence']:.2f} | {r['dice']:.3f} | "
                       f"{r['volume_error_pct']:+.1f} % | {r['poor']} |")
    if dev:
        out += ["", "| devset case | family | phase | truth mL | apex mm | base mm | confidence | Dice | volume error "
                "| poor | clicks flagged |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
        for r in dev:
            head = f"| {r['case']} | {r['family']} | {r['phase']} | {r['truth_ml']:.0f} |"
            out.append(f"{head} refused: {r['refused']} | | | | | | |" if "refused" in r else
                       f"{head} {r['apex_mm']:.1f} | {r['base_mm']:.1f} | {r['confidence']:.2f} | {r['dice']:.3f} | "
                       f"{r['volume_error_pct']:+.1f} % | {r['poor']} | {'; '.join(r['clicks_flagged']) or 'no'} |")
    out += ["", "Small end-systolic cavities (15-38 mL) now count as ventricles (they were scored 0.4 on size under "
            "30 mL and flagged though right); the haze case (`clutter_strong`) is still the worst apex, its pool a "
            "stump hardly longer than wide (elongation 1.0-1.3 against 1.4-2.8), so low in confidence and flagged."]
    mitral = data.get("mitral")
    if mitral:
        out += ["", "The tilted mitral scenes (`tilted_mitral_scene`: an 80 x 26 mm half-ellipsoid cut by a plane "
                "at the angle given to the long axis, a dark atrium beyond, 1 mm voxels, no sector):", "",
                "| plane tilt | apex mm | base mm | confidence | Dice | volume error | poor |",
                "| --- | --- | --- | --- | --- | --- | --- |"]
        out += [f"| {r['tilt_deg']:.0f} | {r['apex_mm']:.1f} | {r['base_mm']:.1f} | {r['confidence']:.2f} | "
                f"{r['dice']:.3f} | {r['volume_error_pct']:+.1f} % | {r['poor']} |" for r in mitral]
        out += ["", "At 30 degrees the atrium meets the cavity across the whole tilted plane and the pool has no "
                "waist: the base is put at the far end of the atrium (low confidence, flagged poor; not addressed). "
                "At 0 and 15 degrees the base is within 1-2 mm, yet the volumes without points are 8-10 % large. "
                "That is not the location: from the true apex and base the default mode gives +6.9 and +6.8 %, and "
                "the local means +0.5 % at 0 degrees. The scene's noise is Gaussian, not log-compressed speckle: "
                "the intensity interface reads its spread as speckle's (11.6 grey levels per neper) and moves the "
                "wall out. Left alone: the scene tests the mitral plane, and echo has speckle."]
    beam = data.get("beam")
    if beam:
        ok = [r for r in beam if "refused" not in r]
        bt = np.array([r["locate_s"] for r in ok])
        out += ["", f"Beam-space volumes ({len(beam)} seeded phantoms imaged in beam space, every third formation "
                "of the sweep; `locate(beam_volume)` in the beam geometry, its time the least of two calls after a "
                "first): located "
                f"{len(ok)} / {len(beam)}, time median {1000 * np.median(bt):.0f} ms, worst {1000 * bt.max():.0f} ms "
                "(target 300 ms).", "",
                "| formation | phase | tilt | beams (r, e, a) | time ms | apex mm | base mm | confidence |",
                "| --- | --- | --- | --- | --- | --- | --- | --- |"]
        for r in beam:
            shape = " x ".join(str(n) for n in r["shape"])
            head = f"| {r['formation']} | {r['phase']} | {r['tilt_deg']:.0f} | {shape} |"
            out.append(f"{head} refused: {r['refused']} | | | |" if "refused" in r else
                       f"{head} {1000 * r['locate_s']:.0f} | {r['apex_mm']:.1f} | {r['base_mm']:.1f} | "
                       f"{r['confidence']:.2f} |")
    ringed = data.get("ringed")
    if ringed:
        ok = [r for r in ringed if "refused" not in r]
        out += ["", f"The ringed sections alone ({len(ringed)} seeded phantoms drawn as above; `locate` with the dark "
                "pools ignored, as if each had joined the dark around it, so that every case goes by the fallback "
                f"that located Patient 7 below): located {len(ok)} / {len(ringed)}; every location it gives has a "
                "confidence of at most 0.3.", "",
                "| formation | phase | tilt | apex mm | base mm |", "| --- | --- | --- | --- | --- |"]
        for r in ringed:
            head = f"| {r['formation']} | {r['phase']} | {r['tilt_deg']:.0f} |"
            out.append(f"{head} refused | |" if "refused" in r else
                       f"{head} {r['apex_mm']:.1f} | {r['base_mm']:.1f} |")
    cetus = data.get("cetus_patient7")
    if cetus:
        out += ["", "CETUS Patient 7 (0.9 mm assumed), against the clicked points of `Patient7_points.json`:", "",
                "| phase | clicked mL | located | clicks flagged |", "| --- | --- | --- | --- |"]
        for phase, r in cetus.items():
            where = (f"refused ({r['refused']})" if "refused" in r else
                     f"apex {r['apex_mm']:.0f} mm, base {r['base_mm']:.0f} mm off, confidence {r['confidence']:.2f}, "
                     f"{r['located_ml']:.0f} mL")
            out.append(f"| {phase} | {r['clicked_ml']:.0f} | {where} | {'; '.join(r['clicks_flagged']) or 'no'} |")
    out += ["", "How `locate` works: a 3 mm copy of the image, each coarse voxel the mean of its nearest voxels at "
            "27 points fixed in mm, so that its cost and its result do not depend on the image's resolution (at "
            "most 96 coarse voxels along an axis; a beam-space volume: 4 mm, inside the sector only), each 6 mm "
            "shell of depth levelled to its brighter quartile; Otsu's threshold of its smoothed grey levels, "
            "refused when the classes' means lie under 1.4 speckle spreads apart (the median grey-level standard "
            "deviation within a coarse voxel: log-compressed speckle's does not depend on the tissue, so that the "
            "measure holds across gains, compressions and simulators); the dark pools "
            "after an opening of 1 (then 2, 3) voxels, one along the sector (a long axis within 45 degrees of its "
            "centre line); the long axis by PCA, turned towards the probe; the base at the pool's waist (the "
            "narrowest section against the widest on both sides), moved onto the mitral plane where the mean grey "
            "level over a disc across the axis (0.9 of the cavity's coarse radius), read at full resolution 12 mm "
            "either side, crosses half-way from the blood's level to its peak (the annulus, the closed leaflets or "
            "the narrower orifice); the apex where the full-resolution axial profile meets the wall. Haze over the "
            "apex (`clutter_strong`) starts the pool 29-38 mm deep: not fixed, but the stump it leaves (its length "
            "under 1.35 times its width; scored from 1.25) takes the confidence under 0.5. The confidence is "
            "the product of the scores (contrast, waist, size, length, wall, elongation); under 0.5 a location is "
            "not trusted: a segmentation from it is flagged, and clicks are not checked against it, which the "
            "result says (`the clicked points could not be checked: ...`) instead of passing them.", "",
            "CETUS Patient 7's cavity is one dark pool with the dark tissue beyond a faint wall near the base "
            "(openings of up to 9 mm do not cut it), so no pool is a ventricle. Its sections across the sector "
            "are still dark discs ringed by the wall where the wall is clear (111-138 mm deep at ED). Such an "
            "image is now located along those sections (`_along_ringed_sections`, only where no pool is a "
            "ventricle). The ringed sections are dark regions of the coarse image about the sector's centre "
            "line, on planes across it every 3 mm, closed all round by tissue 1 pooled deviation brighter (not "
            "by the sector's edge). The longest series of neighbouring ones is the cavity, cut at its waist (a "
            "section 5 % smaller in area than the widest on both sides: an open mitral valve joins the atrium's "
            "sections on). The long axis is the line through their centres when they span 40 mm or more, and "
            "otherwise the line from the probe through them (an apical view looks down it from over the apex). "
            "Along it, the full-resolution grey level (a 3 mm disc) crosses half way from "
            "the blood's to the brightest level within 12 mm of a first half-way crossing: the apex towards the "
            "probe; the base away from it, within 30 mm of the last ringed section, or at the waist moved onto the "
            "mitral plane. Both rises "
            "must be half the image's tissue-blood contrast. The confidence is at most 0.3 (`JOINED_POOL`), "
            "with the reason, so a segmentation from it is flagged poor. On the 2.7 mm copy of before (whole "
            "0.9 mm voxels) Patient 7 was found within 4 mm (apex) and 10 mm (base) of the clicks; how it is "
            "found depends on the coarse spacing (the table of choices below: 2.5-3.5 mm give 3-66 mm off, or "
            "a refusal), never with confidence: on the 3 mm copy its clicks are now said to be unchecked "
            "(above) rather than passed.", "",
            "Each choice below was measured on the formation sweep's scenes, the legacy families, the tilted "
            "mitral scenes and CETUS Patient 7; those for Patient 7 on its ED and ES volumes, the 16-case sweep "
            "and the bright-blood phantom, which must be refused.", ""]
    out += _tried([
        ("the apex of the coarse pool alone", "4-8 mm short on every case (the opening and the 3 mm voxels round "
         "the tip off)", "no: the full-resolution axial profile, about 2 mm"),
        ("a 2 mm slab of voxels around the base, on a grid slightly tilted to the axis",
         "a strip to one side: the base 14-17 mm off laterally on upright phantoms", "no: whole voxel layers"),
        ("Otsu's between-class variance ratio to refuse tissue",
         "0.63 for any single Gaussian class, 0.69-0.86 on phantoms",
         "no: cannot refuse; the classes' distance in pooled deviations can (2.6 on speckled tissue, 4.7-5.7 on "
         "the sweep; 3.2 on a phantom whose blood is as bright as its wall, refused as no dark pool lies along "
         "the sector)"),
        ("the widest section first, then the waist", "the base at the far end of the atrium when the atrium was "
         "wider than the ventricle's base", "no: the narrowest section against the widest on both sides"),
        ("no levelling in depth, under under-compensated attenuation (`tgc_under`)",
         "Otsu's dark class is the depth, not the blood: classes 2.0 deviations apart on an end-systolic case, "
         "refused", "no: 6 mm shells levelled: 5.1, every phantom 4.9-6.3, the legacy `clutter` apex 11 to "
         "3.5 mm"),
        ("Patient 7: scipy's `watershed_ift` to split the pools", "its basins leak (it cuts a symmetric two-basin "
         "profile off-centre); an ES result 7 mm off at the base came from that", "no"),
        ("Patient 7: splitting the pools where they narrow, once the openings find no ventricle (a merge tree of "
         "the distance to the pool's edge; two parts kept apart at a ridge narrower than a ratio of the narrower "
         "part's widest point)", "ratio 0.3-0.4: joined; 0.5: ES 21 mm (apex) and 25 mm (base) off the clicks; "
         "0.6: ED 53 / 68 mm off, and the bright-blood phantom given a ventricle", "no: wrong locations"),
        ("Patient 7: only the pools inside a cone about the sector's centre line, once the whole sector has no "
         "ventricle", "half-angle 15-25 degrees: both phases 10-19 mm off at the apex, 9-37 mm at the base, "
         "confidence 0-0.11; 30 degrees: both refused", "no: wrong locations"),
        ("a straight line fitted to the depth drift instead of the shells (gain errors are linear in dB, so in "
         "log-compressed grey)", "no false pool from the bright near field 25 mm above Patient 7's clicked apex; "
         "the sweep about as it was (apex median 1.6 mm, base 2.8 mm, Dice 0.951, volume +5.5 %); Patient 7 not "
         "located on its own", "no"),
        ("the base left at the coarse pool's narrowest section", "1-4 mm beyond the mitral plane (the 3-4 mm "
         "voxels, the atrium widening past the orifice): volumes without points 5-9 % large",
         "no: moved onto the plane"),
        ("the base at the steepest fall of the pool's section before its waist", "1.6-6.8 mm short of the plane "
         "(median 3.2 mm; the ventricle itself narrows towards its base)", "no"),
        ("the disc's radius 0.5 of the cavity's", "the disc stays inside the orifice: up to 15 mm off", "no"),
        ("the disc's radius 0.8", "sweep 0.6-1.7 mm; tilted mitral scenes 3.0-4.7 mm (their atrium 0.85 of the "
         "cavity's radius)", "no"),
        ("the disc's radius 0.9", "sweep 0.6-2.0 mm; mitral scenes 0.9-2.1 mm", "kept"),
        ("the disc's radius 1.0", "one mitral scene 3.3 mm off", "no"),
        ("a beam-space volume's coarse copy interpolated over the whole box around the sector (three times the "
         "sector: 650,000 coarse voxels at 3 mm for a 75-degree sector)", "0.55-1.8 s (the first pass)",
         "no: read only inside the sector, the distances from the probe from the grid's axes"),
        ("a beam-space volume searched at 3 mm", "8 beam-space cases, side by side under heavy load: median "
         "0.38 s (worst 0.51), apex median 1.7 mm, base 0.9 mm", "no"),
        ("... at 4 mm (as a 2 mm Cartesian image already is)", "0.19 s (0.28), apex 1.8 mm, base 1.0 mm", "kept"),
        ("Patient 7: lower thresholds, Otsu's minus 0.25-1.5 pooled deviations", "ED joined at every one; ES "
         "10-28 mm off at the apex, 13-14 mm at the base, at 1.25-1.5", "no"),
        ("Patient 7: the core of ringed sections alone, with a cylinder about the line from the probe through it "
         "(1.0-1.6 times its radius)", "apex 29-33 mm off, into the bright near field; base 19-60 mm", "no"),
        ("Patient 7: the ringed core with the straight-line depth drift", "the core vanishes (0.2-2 mL)", "no"),
        ("for images otherwise refused, the cavity followed section by section from the ringed core (a section "
         "running out through the wall, over 1.3 times the previous one, cut to the previous), ending at a "
         "quarter of the widest section, the apex left to the axial profile", "Patient 7 located, not within the "
         "targets: ED apex and base 10 mm off, 288 mL without points against 196 clicked; ES 7 and 16 mm, "
         "153 mL against 141; confidence 0.001-0.05", "removed (below)"),
        ("... ending at 0.15 of the widest section", "the ED apex 29 mm up into the near field", "no"),
        ("... a growth limit of 1.1 or 1.2", "ES as it was, ED 9-13 mm off", "no"),
        ("... on a synthetic half-ellipsoid whose wall opens over 20 mm into dark surroundings (refused before)",
         "a confident wrong pose: apex 18 mm, base 27 mm off, confidence 0.91",
         "removed: a refusal is better; Patient 7 stays refused"),
        ("the ringed sections (above): the long axis by PCA of their centres", "Patient 7 ED apex 11.3, base 13.1 "
         "mm off (the series spans 27 mm); ES as with the probe's line", "no: the line from the probe"),
        ("... the line from the probe always", "with the pools ignored on 16 random phantoms: located 13, the apex "
         "14-23 mm off beyond 15 degrees of tilt (the line misses a tilted apex)", "no: PCA of the centres when "
         "they span 40 mm or more (Patient 7: 27 mm, unchanged): located 12, apex and base within 3.6 mm but "
         "under haze (apex 38 mm) and dropout (6.8 mm)"),
        ("... the ends where the profile crosses half way to its brightest level on either side",
         "the apex 9-10 mm short, half way to the near field's ringing 30 mm from the probe: volumes +13 and "
         "+22 %", "no: half way to the brightest within 12 mm of that first crossing (3.5 mm)"),
        ("... then the pool path's refinements (`_endocardial_apex`, `_mitral_plane`)", "ED apex 5.4 mm, ES 8.2 mm; "
         "ES volume +17.7 %", "no: the crossing is read at full resolution already"),
        ("... without the waist", "the 16-case sweep's 21 mL end-systole (refused before) located with its atrium: "
         "base 39 mm off, Dice 0.61, flagged poor", "no: with it, base 1.6 mm, Dice 0.943"),
        ("... the waist at a dip of 10 % (the pool path's)", "a 10-degree phantom's sections dip 9.7 % at the orifice: "
         "base 40 mm off, in the atrium (refused with the 30 mm reach below)", "no: 5 % (the sections, 3 mm "
         "apart, are smooth): base 1.1 mm; Patient 7 unchanged"),
        ("... the base within 60 mm beyond the last ringed section", "with the pools ignored, 4 of 12 random phantoms "
         "(tilts 10-25 degrees) given a base 18-41 mm off, through the open valve to the atrium's far wall",
         "no: 30 mm (Patient 7's unringed basal wall is 12-19 mm); those 4 refused, the rest unchanged"),
        ("... on a stress case: `dropout` phantoms (seeds 0-5, 1.5 mm) with everything beside the heart on the "
         "apex's side of the mitral plane as dark as blood", "upright: refused (Otsu's classes too close); tilted "
         "20 degrees: 3 of 6 went this way, 7-9 mm off at the apex and 18-24 mm at the base at confidence "
         "0.16-0.19 with the base's 60 mm reach, refused with 30 mm (only sections near the apex are ringed, "
         "too short a series to tilt the axis); the pool path took the other 3, 38-48 mm off at the base, "
         "confidence 0.06-0.09", "kept: low confidence, flagged; a "
         "tilted ventricle with a faint wall is not located within 10 mm"),
        ("(issue 48) Otsu's classes' distance in their own pooled spread, refused under 2.8", "the sweep 4.1-5.4; "
         "the devset 2.4-3.0, 5 of 12 refused and the rest at confidence 0-0.26; uniform speckle 2.6", "no: the "
         "pooled spread holds the tissue's own variety (chambers, lung, heterogeneous tissue), another "
         "simulator's more than the phantom's"),
        ("(48) the classes' distance in the speckle's spread (median standard deviation within a coarse voxel), "
         "refused under 1.4", "the sweep 5.0-7.3; the devset 1.87-8.2 (lowcontrast 1.87); uniform speckle in a "
         "sector 0.12-0.60 (point-spread 0.5-3 mm laterally), 0.95 at 5 mm; the textured-tissue test 1.06; "
         "blood as bright as the wall 1.09", "kept"),
        ("(48) ... no refusal by it (the pools' wall alone)", "uniform speckle given a ventricle (confidence up "
         "to 0.64)", "no"),
        ("(48) the taper (the section 10 mm from the apex, scored under 0.65 of the widest)", "the devset's "
         "blunt (super-ellipsoidal) apices 0.46-0.86: 6 right locations at confidence 0; haze 0.84", "no: the "
         "elongation"),
        ("(48) the elongation (length over the widest section's diameter) scored from 1.1 to 1.3", "right: "
         "1.42-2.84 (two sweeps, seeds 29 and 30), 1.28-2.29 (devset: `lowcontrast` 1.28, its pool joined to a "
         "neighbour across); haze 1.01 (seed 29) and 1.29 (seed 30: apex 36 mm off at confidence 0.93)", "no"),
        ("(48) ... the width from the pool's narrower spread across the axis (a disc's diameter is sqrt(20) of "
         "it), scored from 1.2 to 1.4", "right: 1.43-2.93 (sweeps), 1.49-2.33 (devset); haze 1.00 and 1.25 "
         "(scores 0 and 0.24), but `clutter_strong` seed 0 at 1.5 mm 1.30 (confidence 0.51, apex 32 mm off: "
         "its right clicks called wrong)", "no"),
        ("(48) ... scored from 1.25 to 1.45 (a half at 1.35)", "haze 0.99-1.30 (seeds 0-5 at 1.5 and 2 mm, and "
         "the sweeps'): confidence 0-0.25; every right location still trusted", "kept"),
        ("(48) a pool as long one way as another across (second principal spread over 0.9 of the first): the "
         "direction in their plane nearest the sector's centre line as its axis, not the first", "devset "
         "`lowcontrast` (0.97; its axis 57 degrees off the sector's, refused as no apical view, then found along "
         "its ringed sections at confidence 0.28) located by its pool: apex 2.2, base 2.0 mm, confidence 0.94; "
         "every other case unchanged", "kept"),
        ("(48) the waist scored as its dip over 0.2", "devset `papillary_es` (ES, atrium taken in, no clear "
         "orifice): dip 0.13, confidence 0.66, base 39 mm off", "no: (dip - 0.1) / 0.1 (0.32 there; right cases "
         "0.22-0.87 score 1)"),
        ("(48) pools of 20-30 mL scored 0.4 on size", "4 right end-systolic sweep cases (17-28 mL pools) flagged",
         "no: 15 mL up counts (a small heart's end-systole)"),
        ("(48) the coarse copy at whole voxels (a 2 mm image at 4 mm, 0.9 mm at 2.7 mm)", "cost and result "
         "depend on the resolution", "no: 3 mm of 27 points fixed in mm (a 2x finer copy of a volume: the same "
         "check)"),
        ("(48) ... Patient 7 at coarse spacings of 2.5-3.5 mm", "ED located at 2.5-2.7 and 3.0 mm (base 10 mm off "
         "the clicks, confidence 0.30), 13-66 mm off at 2.9 and 3.1-3.5 mm (confidence 0-0.11); ES within 10 mm "
         "at 5 of 8, refused at 2.6, 3.0 and 3.5 mm", "the ringed-section fallback is fragile: its clicks are "
         "now said to be unchecked")])
    out += ["", f"Machine: {_machine(data['machine'])}; a shared machine under load (six developers on 2 cores)."]
    return out


def _myocardium(data) -> list[str]:
    cases, seqs = data["cases"], data["sequences"]
    d = np.array([c["dice"] for c in cases])
    err = np.array([c["mass_error_pct"] for c in cases])
    ratio = np.array([c["myo_seconds"] / c["endo_seconds"] for c in cases])
    out = ["## The myocardium: epicardium, LV mass, segments (issue 33)", "",
           f"Command: `{data['command']}` ({data['wall_seconds'] / 60:.0f} min). Machine: {_machine(data['machine'])}.",
           "",
           "`segment(volume, apex, base, myocardium=True)` on phantoms imaged by the formations named (1 mm voxels, "
           "seed 0 upright, seed 10 tilted 25 degrees): Dice of `myocardium_mask` against the phantom's wall below the "
           "mitral plane, LV mass error against its exact volume at 1.05 g/mL, the cavity's volume error, and the wall "
           "time of the call over that of the endocardium alone (the same call without `myocardium`, both with "
           "`check=False`: the points' check costs the same in both; least of 5 each, interleaved, after a warm-up). "
           f"Median Dice {np.median(d):.3f} (target 0.85: {'met' if np.median(d) >= 0.85 else 'missed'}), worst "
           f"{d.min():.3f}; median |mass error| {np.median(np.abs(err)):.1f} % (target 8 %: "
           f"{'met' if np.median(np.abs(err)) <= 8 else 'missed'}); median time ratio {np.median(ratio):.2f}, worst "
           f"{ratio.max():.2f} (target 2: {'met' if ratio.max() <= 2 else 'missed'}).", "",
           "| family | formation | Dice | mass error % | cavity error % | time ratio | polarity | flagged |",
           "|---|---|---|---|---|---|---|---|"]
    for c in cases:
        out.append(f"| {c['family']} | {c['formation']} | {c['dice']:.3f} | {c['mass_error_pct']:+.1f} | "
                   f"{c['cavity_error_pct']:+.1f} | {c['myo_seconds'] / c['endo_seconds']:.2f} | {c['polarity']} | "
                   f"{'yes' if c['poor'] else ''} |")
    out += ["", "A bright wall's epicardium lies where the echo intensity is half way between the wall's and what lies "
            "beyond it (`epicardium.wall_term`: the local means with the wall inside, `LocalMeans.polarity = -1`, and "
            "`boundary_nepers`, `k` the image's log compression as the endocardium's intensity interface estimated it, "
            "`SegmentationResult.log_compression`; in the compiled level loop). A median thickness below 4 mm is "
            "flagged (`quality.WALL_LIMITS`), and so is an epicardium still moving at its cap of 30 iterations "
            "(`epicardium.MAX_ITERATIONS`; the bright walls of this sweep settle in 5-12). At contrast_low the "
            "phantom's wall is darker than the tissue outside it: its outer edge is weak (5 dB), and the local means "
            "about it lean on the cavity's darker blood and draw the epicardium in, with no boundary to settle on "
            "(its median thickness falls by about 0.1 mm an iteration: 6.1-6.5 mm at 10 iterations, 4.6-4.8 at "
            "30); it is flagged wherever it stops, and stops at 15 iterations (`epicardium.DARK_MAX_ITERATIONS`, "
            "half the bright wall's cap: a boundary that cannot be found costs no more time than one that can), "
            "its median thickness 5.3-5.9 mm, the mass 7-9 % low. Measured besides on all 16 formations and "
            "the 9 post-processings (upright and tilted, one scene each, `segment(..., myocardium=True)`): every "
            "bright wall's Dice 0.883-0.939 and mass error -8.5 to +4.7 % (psf_narrow tilted the lowest, "
            "gaussian_2mm the highest). Its cavity is now within 3.6 % (the intensity interface "
            "reads past the thin dark wall, the formation sweep's section), so the endocardium's dark-wall flag no "
            "longer fires there; the epicardium of a dark wall carries a flag of its own "
            "(`epicardium.DARK_EPICARDIUM`). Where the time goes (default formation, upright, least of 20 "
            "calls each, nothing else running, as for the ratios above): the endocardium's whole `segment` 6.9 ms, "
            "the epicardium 6.8 ms: its level 3.5 ms (8 iterations at 0.44 ms, on 8 x 8 patches, 4096 sample "
            "points, the local means' bands read at every iteration), the `Tracker` set-up 0.7 ms, the thickness "
            "floor and the wall report 0.7 ms, the polarity 0.5 ms, the start 0.3 ms.", ""]
    out += _tried([
        ("the grey levels' midpoint (the local means) for a bright wall", "outside, on the dim side of the blurred "
         "edge: median mass error +9.1 %, +17 % at contrast_high", "no"),
        ("the crop as linear intensity under the local means", "inside: -14 % and -22 % on default (the outer "
         "band's mean intensity follows what lies beyond the wall)", "no"),
        ("the log compression from the endocardium's estimate, not a second reading of the wall's speckle",
         "changes the results: before, median absolute mass error 4.4 %, Dice 0.915", "kept"),
        ("a bright wall stopping at 0.1 mm of RMS motion, the coarse levels' tolerance",
         "8 iterations instead of 10 on this case", "kept"),
        ("the thickness floor checked where the wall report reads it", "one thickness grid instead of two", "kept"),
        ("no quality report of the endocardium's kind for the epicardium's descent",
         "it had been made and discarded", "kept"),
        ("the start's region means measured only when a result needs them", "the endocardium gains this too",
         "kept"),
        ("the polarity read on 16 x 16 cells instead of 24 x 24, its samples by the compiled sampler",
         "no separate figure", "kept"),
        ("the last six rows together", "the time ratio from 2.8-3.1 to about 2 (the previous table: median 3.11 "
         "under a load of about 10; 2.82 with nothing else running)", "kept"),
        ("the dark walls' epicardium on fixed levels (`mode='fast'`, the interface half way in intensity between "
         "the mean grey levels of the start's wall and of the 8 mm beyond it), contrast_low", "the mass +7.6 / "
         "+8.4 % (was -15.0 / -15.8), Dice 0.860 / 0.856 (was 0.880 / 0.871): the start's 8 mm wall holds "
         "tissue beyond a 5-6 mm wall, and its level reads high", "no: flagged instead"),
        ("the dark walls (contrast_low) stopping at 0.1 mm too", "the collapsing wall stopped above the 4 mm flag: "
         "median thickness 4.1 and 4.5 mm, mass -22 and -17 % unflagged (measured again with this code)",
         "no: their plain local means keep the endocardium's 0.05 mm (3.1-3.2 times)"),
        ("the epicardium capped at 30 iterations instead of 60, a wall still moving then flagged",
         "the bright walls unchanged (5-12 iterations); the dark walls stop at 30, flagged as still moving, "
         "their time ratio 3.1-3.2 to 2.4-2.6", "kept"),
        ("the dark walls' epicardium capped at 15 iterations (contrast_low; measured with the table's code)",
         "the time ratio 2.43 / 2.29 to 1.92 / 1.97, the mass -15.0 / -15.8 to -7.4 / -9.3 %, Dice 0.880 / 0.871 "
         "to 0.873 / 0.882; at 20: 2.07 / 1.97, -12.0 / -14.4 %; at 10: 1.62 / 1.84, +1.2 / +1.0 % (the prior "
         "thickness's), Dice 0.858 / 0.862", "kept: 15, flagged as before"),
        ("the local means' force computed on numba's threads", "no gain measured", "no"),
        ("the quadrature order 6 instead of 8", "Dice -0.01, mass error 1-3 points worse on 8 cases", "no"),
        ("a step twice as long", "7-10 iterations instead of 6-12 on 6 cases, the mass up to 2 % lower", "no"),
        ("no base ring check after the epicardium's descent (`Tracker.run(base_ring=False)`: the thickness floor "
         "holds it outside an endocardium whose ring was checked)", "0.1-0.8 ms less of 9-12 ms (the tilted default, "
         "tgc_over, dr_40; medians of 15 interleaved calls); the table's ratios move by as much from run to run "
         "on this shared machine", "kept"),
        ("a second stage as the endocardium's: the wall's local means until it moves less than twice the "
         "tolerance (0.2 mm), then their band means frozen (no bands read) down to 0.1 mm; the 16 cases above",
         "frozen at 0.2 mm: 8 iterations as before on the default, 0.1-0.7 ms less in interleaved calls, Dice "
         "within 0.003, the mass up to 1.3 points higher; frozen at 0.4 mm: 6-7 iterations, but the mass +7 to "
         "+11 % on 8 cases (Dice down to 0.86)", "no: the frozen levels must be read about the wall the descent "
         "settles on, and by then most of its iterations have run")])
    out += ["", f"Command: `{data.get('sequences_command', data['command'])}`. "
            "A tracked 10-frame cycle (`track(..., myocardium=True)`, default formation) whose wall has a region "
            "10 % of the cycle late (`phantom.LateRegion(theta=1, half_width=pi/3, delay=0.1)`): the mass at ED and "
            "ES (the truth's differs by the phantom's wall model; every frame's epicardium after the first starts from "
            "the previous frame's wall with its myocardial volume, `epicardium.conserving_start`), the segment whose "
            "volume is smallest last, and "
            "the SDI (standard deviation of the 16 segments' times to minimum, % of the cycle), against the truth's "
            "cavity voxels labelled by the same definition.", "",
            "| seed | ED-ES mass difference % (truth) | late segment (truth) | SDI % (truth) | EF % (truth) |",
            "|---|---|---|---|---|"]
    for q in seqs:
        out.append(f"| {q['seed']} | {q['ed_es_mass_difference_pct']:.1f} ({q['truth_ed_es_mass_difference_pct']:.1f}) "
                   f"| {q['late_segment']} ({q['truth_late_segment']}) | {q['sdi']:.1f} ({q['truth_sdi']:.1f}) | "
                   f"{q['ef']:.1f} ({q['truth_ef']:.1f}) |")
    return out


def _pulse_echo(data) -> list[str]:
    def stats(values):
        v = np.asarray(values, float)
        return f"{np.median(v):+.1f} ({v[np.argmax(abs(v))]:+.1f})"

    out = ["## Echo formed by an array (issue 53)", "",
           f"`benchmarks/pulse_echo.py`, one command a row (below). Machine: {_machine(data['machine'])}.", "",
           "The phantom's anatomy and echogenicity (ED and ES of `make_sequence(n_frames=2)`: at ES the radius "
           "0.67 of ED's, the wall 1.5 times as thick), imaged not by convolution but as a 3D probe does: a 32 x 32 "
           "matrix array (half-wavelength pitch, 2.5 MHz, 60 % bandwidth, no apodisation) fires 5 diverging waves "
           "(virtual source behind the centre, tilts 0 and +-15 degrees in azimuth and elevation), delay-and-sum "
           "on receive, coherent compounding, envelope, the phantom's attenuation, TGC and noise, 55 dB log "
           "compression, scan conversion (no clutter: the side lobes are the haze). The point-target checks "
           "(`--check`, tests/test_pulse_echo.py): per-element echoes arrive at the geometric delay (pymust "
           "`simus3`, 16 x 16 elements of the same pitch, the same delays, a scatterer at (5, 3, 40) mm: within "
           "0.045 us of it, a pulse envelope's std being 0.25 us); DAS of "
           "one scatterer at 60 mm, 4.16 degrees FWHM (amplitude), the volumes' far-field kernel 4.12 (1 "
           "untilted wave: 4.31, the aperture's 1.207 lambda / D). `pymust.simus3` itself takes 24 s for 500 "
           "scatterers on 1024 elements, one transmit (a volume needs 10^6): the volumes use the kernel.", "",
           "Segmented with `spheroseg.segment` defaults from the true apex and base, 1 mm voxels unless said. "
           "Cells: median (worst) volume error %, EF error points of each seed's ED/ES pair, Dice median, "
           "flagged of all, log compression read (grey levels per neper; true 20.06 at 55 dB), and at ES the "
           "median signed distance (mm, + outside) of the segmented wall from the true one, over walls facing "
           "the beam / along it, and the contrast (dB) between the cavity's core and the 2-5 mm outside it.", "",
           "| run | ED volume % | ES volume % | EF points | Dice ED / ES | flagged | log compression | ES wall mm "
           "facing / along | contrast dB ED / ES |",
           "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for name, run in data["runs"].items():
        rows = run["rows"]
        ed = {r["seed"]: r for r in rows if r["phase"] == "ED"}
        es = {r["seed"]: r for r in rows if r["phase"] == "ES"}
        seeds = sorted(set(ed) & set(es))
        ef_err = [100 * ((ed[s]["ml"] - es[s]["ml"]) / ed[s]["ml"] - (ed[s]["truth_ml"] - es[s]["truth_ml"])
                         / ed[s]["truth_ml"]) for s in seeds]
        flagged = sum(bool(r["flags"]) for r in rows)
        out.append(
            f"| {name} | {stats([ed[s]['error_pct'] for s in seeds])} | {stats([es[s]['error_pct'] for s in seeds])} "
            f"| {stats(ef_err)} | {np.median([ed[s]['dice'] for s in seeds]):.3f} / "
            f"{np.median([es[s]['dice'] for s in seeds]):.3f} | {flagged} of {len(rows)} | "
            f"{np.median([r['log_compression'] for r in rows]):.1f} | "
            f"{np.median([es[s]['offset_facing_mm'] for s in seeds]):+.1f} / "
            f"{np.median([es[s]['offset_along_mm'] for s in seeds]):+.1f} | "
            f"{np.median([ed[s]['contrast_db'] for s in seeds]):.0f} / {np.median([es[s]['contrast_db'] for s in seeds]):.0f} |")
    out += ["", "Commands: " + "; ".join(f"{name}: `{run['command']}`" for name, run in data["runs"].items()) + "."]
    out += ["", "What the rows show (seeds 0-2; the figures in this paragraph from the table unless said):", "",
            "- **Formed by the array alone, the issue's end-systolic excess does not appear**: ED -4.0 % (worst "
            "-4.6), ES -0.6 % (-2.0), EF -1.7 points (-1.9), none flagged: within the issue's targets. The same "
            "anatomy by convolution reads ES +9.1 % (+10.9), the fresh end-systole's excess of the image-formation "
            "section.",
            "- **Log compression** (the speckle's spread): read 15.7 on the array, 16.0 on the convolution, 20.06 "
            "true; at 40 and 70 dB 21.3 and 12.3 for 27.6 and 15.8. About 22 % low whatever forms the image "
            "(scan conversion's interpolation narrows the spread): not what differs between the two.",
            "- **Side-lobe haze**: the cavity's core 5-10 dB brighter on the array (the core-to-wall contrast 22-25 "
            "dB for 34), more at ES than ED (17 grey levels), yet the walls go in, not out. Without the side lobes "
            "(a Gaussian of the same main lobe) ED -4.7 %, ES +0.8 %: the haze does not move the ES wall; ED's "
            "deficit is the main lobe's lateral width (Hann apodisation, a main lobe 1.6 times as wide: ED -10.2 "
            "%, ES -7.2 %; 16 x 16 elements, 8.6 degrees: ED -9.9 %).",
            "- **Anisotropic lateral blur**: at ES the walls along the beam sit 0.4 mm inside the truth on the "
            "array (median), 0.3 mm outside by convolution: inwards.",
            "- **Brightness that depends on the wall's angle to the beam** (`--anisotropy 12`: tissue 12 dB "
            "weaker where its boundary runs along the beam, read over 2 mm: the wall's layer next to the blood): "
            "this gives the issue's pattern, on the array (ED +1.1 %, ES +16.6 % (+21.4), EF -6.9 (-8.1), Dice "
            "0.979 / 0.920, none flagged) and by convolution alike (ES +26.1 %), the wall outside where it runs "
            "along the beam (+0.9 and +1.4 mm median there, +0.2 and +0.3 where it faces it). Why, from the "
            "intensity interface's frozen levels (seed 0, ES; `IntensityInterface.freeze` wrapped to log them): "
            "the outer band's profile (its median at each of the 4 offsets) rises, 152 to 167 grey levels "
            "(convolution; 142 to 156 on the array), where the plain convolution's is flat (195-203); "
            "`profile_blur_mm` reads the rise as a blurred edge, 1.42 and 1.80 mm for 0.83, the band means lose "
            "that blur's deficits, `c_out` and `g*` rise and the wall settles in the wall. Not the start: from a "
            "start of base radius 0.2 of the long axis instead of 0.3, ES +16.5 % for +16.6 (seed 0). With the "
            "whole wall dimmed (read over 6 mm: the profile no longer rises) ES +8.0 % (+8.3), and the dark-wall "
            "warning flags 4 of 6.",
            "- **How much is `profile_blur_mm`'s** (`--no-profile-blur`: the blur the speckle's correlation "
            "gives, never more; the rows ending 'no profile blur'): with the angular brightness ES +7.9 to +12.7 "
            "% for +13.2 to +21.4, ED -0.1 to +1.1; about half the excess; the other half is not accounted for "
            "here (the levels the band means give about a dimmed layer, presumably). On the plain array ED -4.9 to -5.1 % and ES -1.0 to -3.5 "
            "for -3.4 to -4.6 and -0.4 to -2.0 (the profile reading engages a little there too); on the "
            "convolution rows nothing changes (the same volumes to 0.1 %, a run by an equivalent script).",
            "- **The quality flag does not see it**: of the report's numbers none separates those ES (+13 to +21 "
            "%) from the good cases (`wall_contrast` 11-13 there, 11-14 at their ED, +1 to +3 %; `bulge` "
            "1.1-1.3 throughout).",
            "- **Flagged failures**: the ES of seed 0 with papillary muscles, 1.5 mm voxels, 1 transmit, 3.5 MHz, 40 dB or blood "
            "+8 dB stays where it started (+134 to +141 %; the report's contrast 0, 88-90 % of the surface "
            "without): the clicked half-ellipsoid lies across the 13.5 mm wall and the hazy pool, and the first "
            "level's means do not tell them apart. Flagged, but lost.",
            "",
            "Not done: the data term is unchanged (so the convolution sweep and the devset are too). The fix the "
            "rows point to is in `profile_blur_mm`'s reading of a rising outer band: a wall whose layer next to "
            "the blood is dimmer than its middle rises as a blurred edge does; to tell them apart the profile "
            "would be read per region of the surface (walls along the beam against walls facing it) or bounded "
            "by the blur the speckle's correlation gives along the normal (`edge_blur_mm`, 0.8-0.9 mm across "
            "the beam here). A flag for it: the outer band's rise by region. Whether a real probe's angular "
            "brightness is layered like this is not known here."]
    return out


RESULTS = [
    "## Results", "",
    "What spheroseg achieves, each with the command that measures it (the sections of the notebook below give the "
    "cases, the machine and what was tried):", "",
    "| | measured | command |", "| --- | --- | --- |",
    "| against the level-set peers (scikit-image morphological Chan-Vese, SimpleITK ScalarChanAndVese), phantoms | "
    "median Dice 0.978 against 0.789 for the fastest peer, at 710 times its speed | `python benchmarks/accuracy.py`, "
    "`python benchmarks/speed.py` |",
    "| 16 image formations of the project's phantom (PSF, dynamic range, gain, TGC, blood level, contrast, clutter, "
    "dropout) | median Dice 0.978, volume error +0.5 % | `python benchmarks/accuracy.py --sweep --label after` |",
    "| without clicks (`locate`), the phantom sweep and another simulator (the development set) | every volume "
    "located; apex 1.8 mm, base 1.0 / 2.7 mm (median); median Dice 0.962 / 0.963; confidence under 0.5 only where "
    "the location is wrong | `python benchmarks/locate.py --cases 16 --beam-cases 8` |",
    "| tracked sequences, the phantom's cycles | EF within 1.7 points (worst); every 2nd to 4th frame and ED to ES: the notebook | `python benchmarks/accuracy.py`, `python benchmarks/framerate.py --seeds 0 1 2` |",
    "| echo formed by a matrix array (pulse-echo, the phantom's anatomy) | ED -4.0 %, ES -0.6 %, EF -1.7 points; a "
    "wall dimmer along the beam: ES +16.6 %, not flagged (a known miss) | `python benchmarks/pulse_echo.py` |",
    "| starting up | `import spheroseg` 127 ms (`python -c pass` 103 ms), `load` within 1.2 x SimpleITK's read on "
    "the development set | `python benchmarks/startup.py` |",
    "| live over OpenIGTLink, loopback | volumes and EF equal `track`; latency targets missed on the shared machine "
    "(see the section) | `python benchmarks/live.py` |", "",
    "Known misses: a deep trabecular rim reads about 6 % small (accepted, documented); the myocardium's mass and "
    "tracking over large steps on unseen echo (issue 48) are measured in their sections and not yet within their "
    "targets.", "",
    "## Lab notebook", "",
    "Every measurement and what was tried, as the benchmarks wrote them (the numbers are also in the JSON files beside "
    "this page; targets that are missed say so). Sections written by hand, without a JSON of their own, are kept "
    "from one composition to the next.", ""]


def _demoted(lines: list[str]) -> list[str]:
    """The notebook's sections one heading level down, under ``## Lab notebook``."""
    return ["#" + line if line.startswith("## ") else line for line in lines]


def _hand_sections(path: Path, composed: list[str]) -> list[str]:
    """The notebook's sections of ``path`` (``### ...``) that this script did
    not compose: written by hand, kept as they stand."""
    if not path.exists():
        return []
    made = {line for line in composed if line.startswith("### ")}
    kept, keep = [], False
    for line in path.read_text().split("\n"):
        if line.startswith("## ") or line.startswith("### "):
            keep = line.startswith("### ") and line not in made
        if keep:
            kept.append(line)
    return kept


def write_markdown() -> Path:
    parts = ["# Benchmarks", "",
             "Generated by the scripts in `benchmarks/` (`python benchmarks/report.py` composes this page from the "
             "JSON they wrote).", ""] + RESULTS
    notebook = _targets(_load("accuracy.json"), _load("speed.json"), _load("accuracy_sweep.json"),
                        _load("userspeed.json")) + [""]
    for name, fn in (("fit.json", _fit), ("mitral.json", _mitral), ("landmarks.json", _landmarks),
                     ("accuracy.json", _accuracy),
                     ("accuracy_sweep.json", _formation_sweep), ("speed.json", _speed), ("beamspace.json", _beamspace),
                     ("postprocessing.json", _postprocessing), ("simulators.json", _simulators),
                     ("framerate.json", _framerate),
                     ("anatomy.json", _anatomy), ("locate.json", _locate), ("myocardium.json", _myocardium),
                     ("pulse_echo.json", _pulse_echo),
                     ("batch.json", batch_section), ("userspeed.json", _userspeed), ("viewer.json", _viewer)):
        data = _load(name)
        if data:
            notebook += fn(data) + [""]
    path = DOCS / "benchmarks.md"
    notebook = _demoted(notebook)
    notebook += _hand_sections(path, notebook)
    path.write_text("\n".join(parts + notebook))
    return path


if __name__ == "__main__":
    print("wrote", write_markdown())
