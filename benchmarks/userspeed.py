"""What a user waits for: the whole ``spheroseg segment`` command, stage by stage.

    python benchmarks/userspeed.py --label before   # run on the code to compare against
    python benchmarks/userspeed.py --label after    # run on this code
    python benchmarks/userspeed.py --report         # the section in docs/benchmarks.md

Each label measures, with whatever ``spheroseg`` is importable (set
PYTHONPATH to choose the code), on two volumes written as MetaImage files:
CETUS Patient 7 ED (201 x 140 x 140, spacing 0.9 mm as its points file
assumes; skipped when /work/shared/data/cetus is absent) and the same volume
resampled to 256^3:

- the stages, each in a fresh interpreter (so ``import`` and the first call
  are what a command sees): import, loading the kernels (this branch's
  ``spheroseg.warmup``; before it, paid inside the first calls), SimpleITK's own read, spheroseg.load
  without the padding search, the padding search (``outside_sector``), the
  segmentation, the mask, the meshes and surface files, the mask and JSON
  writes, the PNG report;
- the wall time of ``python -m spheroseg segment`` with and without the
  report, on a first run (an empty matrix cache: ``SPHEROSEG_CACHE_DIR`` set to a
  new folder) and on later runs.

Medians over ``--repeats`` runs; results in docs/userspeed.json by label.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

DOCS = Path(__file__).resolve().parents[1] / "docs"
CETUS = Path(os.environ.get("SPHEROSEG_CETUS", "/work/shared/data/cetus"))
WORK = Path(tempfile.gettempdir()) / "spheroseg-userspeed"

STAGES = ["import", "kernels", "sitk_read", "read", "padding", "segment", "mask", "meshes", "writes", "report"]

# one fresh interpreter: every stage of the command, timed
CHILD = r"""
import json, sys, time
t = time.perf_counter(); import spheroseg, spheroseg.cli; s = {"import": time.perf_counter() - t}
from pathlib import Path
import numpy as np
import SimpleITK as sitk
from spheroseg.volumes.volume import Volume, outside_sector
from spheroseg.io.surface_io import write_mesh, write_surface_json, write_cmiss
from spheroseg.io import save_mask
path, out, apex, base = sys.argv[1], Path(sys.argv[2]), json.loads(sys.argv[3]), json.loads(sys.argv[4])
t = time.perf_counter()
try:  # after: the kernels and level matrices loaded up front, as the CLI does
    from spheroseg.apps.warmup import load_kernels
    load_kernels()
except ImportError:  # before: paid by the first call of each stage
    pass
s["kernels"] = time.perf_counter() - t
t = time.perf_counter(); img = sitk.ReadImage(path); a = sitk.GetArrayFromImage(img); s["sitk_read"] = time.perf_counter() - t
t = time.perf_counter(); v = spheroseg.load(path, no_data_value=None); s["read"] = time.perf_counter() - t
t = time.perf_counter(); pad = outside_sector(v.array); s["padding"] = time.perf_counter() - t
vol = Volume(v.array, spacing=v.spacing, origin=v.origin, direction=v.direction, no_data_mask=pad)
t = time.perf_counter(); r = spheroseg.segment(vol, apex, base); s["segment"] = time.perf_counter() - t
s["segment_inside"] = r.seconds
t = time.perf_counter(); m = r.mask(vol); s["mask"] = time.perf_counter() - t
t = time.perf_counter()
p, f = r.mesh()
for suffix in (".vtk", ".ply"):
    write_mesh(out / ("mesh" + suffix), p, f)
write_surface_json(out / "surface.json", r.surface, volume_ml=r.volume_ml)
write_cmiss(out / "surface", r.surface)
s["meshes"] = time.perf_counter() - t
t = time.perf_counter(); save_mask(out / "mask.mha", m, vol); (out / "r.json").write_text(json.dumps({"v": r.volume_ml})); s["writes"] = time.perf_counter() - t
t = time.perf_counter()
from spheroseg.io.report import save_report
save_report(out / "report.png", vol, r.surface, mask=m, title="x"); s["report"] = time.perf_counter() - t
s["volume_ml"], s["iterations"], s["poor"] = r.volume_ml, r.iterations, r.quality["poor"]
print(json.dumps(s))
"""


def cases() -> list[dict]:
    """The two volumes as .mha files (made once) with their apex and base."""
    import SimpleITK as sitk

    WORK.mkdir(exist_ok=True)
    info = json.loads((CETUS / "Patient7_points.json").read_text())
    array = np.load(CETUS / info["ED"]["file"])
    spacing = info["assumed_spacing_mm"]
    apex = np.array(info["ED"]["apex_index"][::-1], float) * spacing
    base = np.array(info["ED"]["base_index"][::-1], float) * spacing
    out = []
    # the mask target is for 7 million voxels: the same volume at 250 x 172 x 163
    for name, shape in (("cetus", array.shape), ("7m", (250, 172, 163)), ("256", (256, 256, 256))):
        path = WORK / f"p7_{name}.mha"
        scale = np.array(array.shape, float) / np.array(shape)  # old voxels per new voxel, z y x
        sp = spacing * scale[::-1]
        if not path.is_file():
            from scipy import ndimage

            a = array if shape == array.shape else ndimage.zoom(array, np.array(shape) / array.shape, order=0)
            image = sitk.GetImageFromArray(a)
            image.SetSpacing(tuple(float(x) for x in sp))
            sitk.WriteImage(image, str(path))
        out.append({"name": f"{'x'.join(map(str, shape))}", "path": str(path), "apex": apex.tolist(),
                    "base": base.tolist()})
    return out


def stages(case: dict, env: dict) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        run = subprocess.run([sys.executable, "-c", CHILD, case["path"], tmp, json.dumps(case["apex"]),
                              json.dumps(case["base"])], capture_output=True, text=True, env=env)
    if run.returncode:
        raise RuntimeError(run.stderr)
    return json.loads(run.stdout.strip().splitlines()[-1])


def command(case: dict, env: dict, report: bool, extra=()) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "spheroseg", "segment", case["path"], "--apex", *map(str, case["apex"]),
               "--base", *map(str, case["base"]), "--out", tmp, "--force", "--quiet", *extra]
        if not report:
            cmd.append("--no-report")
        t = time.perf_counter()
        run = subprocess.run(cmd, capture_output=True, text=True, env=env)
        wall = time.perf_counter() - t
    if run.returncode:
        raise RuntimeError(run.stderr)
    return wall


def demo(env: dict) -> dict:
    """``spheroseg demo`` in a new folder: its wall time and its own timings
    (``seconds`` of its results.json: the synthetic sequence, the kernels,
    the segmentation of its frames)."""
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        run = subprocess.run([sys.executable, "-m", "spheroseg", "demo", "--quiet"], capture_output=True, text=True,
                             env=env, cwd=tmp)
        wall = time.perf_counter() - t
        if run.returncode:
            raise RuntimeError(run.stderr)
        seconds = json.loads(next(Path(tmp).glob("spheroseg-demo*/results.json")).read_text())["seconds"]
    return {"wall": wall, **seconds}


def measure_demo(repeats: int) -> dict:
    """The README's first command after its install: a first run (empty
    matrix cache), then later runs (medians)."""
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, SPHEROSEG_CACHE_DIR=cache)
        first = demo(env)
        later = [demo(env) for _ in range(repeats)]
    return {"first_run": first, "later": {k: float(np.median([r[k] for r in later])) for k in later[0]}}


def measure(repeats: int) -> dict:
    results = {}
    with tempfile.TemporaryDirectory() as warm:
        env_warm = dict(os.environ, SPHEROSEG_CACHE_DIR=warm)
        for case in cases():
            entry = {}
            first = []
            for _ in range(max(1, repeats // 2)):
                with tempfile.TemporaryDirectory() as cold:
                    first.append(command(case, dict(os.environ, SPHEROSEG_CACHE_DIR=cold), report=False))
            entry["first_run_no_report"] = float(np.median(first))
            command(case, env_warm, report=True)  # fills the warm cache
            runs = [stages(case, env_warm) for _ in range(repeats)]
            entry["stages"] = {k: float(np.median([r[k] for r in runs])) for k in runs[0]}
            entry["later_no_report"] = float(np.median([command(case, env_warm, False) for _ in range(repeats)]))
            entry["later_report"] = float(np.median([command(case, env_warm, True) for _ in range(repeats)]))
            results[case["name"]] = entry
            print(case["name"], json.dumps(entry, indent=1), flush=True)
    return results


def cpu_name() -> str:
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
        return next(line.split(":", 1)[1].strip() for line in lines if line.startswith("model name"))
    except (OSError, StopIteration):  # pragma: no cover
        return platform.processor() or "?"


def git_commit() -> str:
    try:
        import spheroseg

        src = Path(spheroseg.__file__).resolve().parents[2]
        return subprocess.run(["git", "-C", str(src), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True).stdout.strip()
    except Exception:  # pragma: no cover
        return "?"


def report_section(data: dict) -> str:
    labels = [k for k in ("before", "after") if k in data]
    lines = ["## The whole command, stage by stage (issue 15)", "",
             "Command: `PYTHONPATH=<code>/src python benchmarks/userspeed.py --label before|after --repeats 3`, "
             "then `--report`.  `before` is main when issue 15 was filed, `after` its latest round (its changes: "
             "the table at the end of this section); "
             + ", ".join(f"{k}: {data[k]['commit']} on {data[k]['date']}"
                         + (f" ({data[k]['machine']})" if data[k].get("machine") else "") for k in labels) + ".  "
             "Medians over 3 runs on a 2-core machine, each stage in a fresh interpreter, as in a command (the "
             "report stage draws in that process); the labels ran in different sessions, on virtual machines of one "
             "type whose import times vary by a third from run to run (their load averages above). Volumes: CETUS "
             "Patient 7 ED (201 x 140 x 140, 0.9 mm assumed), resampled (nearest voxel) to 250 x 172 x 163 (7.0 M "
             "voxels, the issue's mask target; after only) and to 256^3, as MetaImage files.  Milliseconds.", ""]
    names = list(dict.fromkeys(n for lab in labels for n in data[lab]["results"]))
    names.sort(key=lambda n: np.prod([int(k) for k in n.split("x")]))

    def entry(lab, n):  # a volume a label did not measure: no cells
        return data[lab]["results"].get(n)

    rows = [("import spheroseg + cli", "import"),
            ("load the kernels and level matrices (after only; before: inside the first calls)", "kernels"),
            ("SimpleITK's own read", "sitk_read"),
            ("spheroseg.load, no padding search", "read"), ("padding search (outside_sector)", "padding"),
            ("segment (before: first call in the process)", "segment"), ("  of which the descent (result.seconds)",
                                                                   "segment_inside"),
            ("mask", "mask"), ("meshes and surface files", "meshes"), ("mask and JSON writes", "writes"),
            ("report (PNG)", "report")]
    head = "| stage | " + " | ".join(f"{n} {lab}" for n in names for lab in labels) + " |"
    lines += [head, "| --- |" + " ---: |" * (len(names) * len(labels))]
    for title, key in rows:
        cells = [f"{1000 * entry(lab, n)['stages'].get(key, 0.0):.0f}" if entry(lab, n) else "-"
                 for n in names for lab in labels]
        lines.append(f"| {title} | " + " | ".join(cells) + " |")
    # what was timed: a collapsed segmentation is quick and wrong (the 256^3 case until this round)
    for title, key, form in (("cavity volume segmented (mL)", "volume_ml", "{:.1f}"),
                             ("iterations", "iterations", "{:.0f}")):
        cells = [form.format(entry(lab, n)["stages"][key]) if entry(lab, n) and key in entry(lab, n)["stages"]
                 else "-" for n in names for lab in labels]
        lines.append(f"| {title} | " + " | ".join(cells) + " |")
    for title, key in (("`spheroseg segment`, first run (empty matrix cache), no report", "first_run_no_report"),
                       ("`spheroseg segment`, later runs, no report", "later_no_report"),
                       ("`spheroseg segment`, later runs, with report", "later_report")):
        cells = [f"{1000 * entry(lab, n)[key]:.0f}" if entry(lab, n) else "-" for n in names for lab in labels]
        lines.append(f"| {title} | " + " | ".join(cells) + " |")
    demos = {lab: data[lab]["demo"] for lab in labels if "demo" in data[lab]}
    if demos:
        lines += ["", "`spheroseg demo` (the README's first command after its install; `--quiet`, in a new folder), "
                  "seconds: a first run with an empty matrix cache, then the median of later runs.  Its own "
                  "`seconds` in results.json: making the synthetic 10-frame sequence, loading (or compiling) the "
                  "kernels, segmenting its frames; the rest of the wall time is starting Python and importing, "
                  "the Dice and distance checks against the truth, the report and the files.", "",
                  "| run | label | wall | synthetic sequence | kernels | segmentation of the 10 frames |",
                  "| --- | --- | ---: | ---: | ---: | ---: |"]
        for lab, d in demos.items():
            for run in ("first_run", "later"):
                r = d[run]
                lines.append(f"| {run.replace('_', ' ')} | {lab} ({data[lab]['commit']}) | {r['wall']:.1f} | "
                             f"{r['make_phantom']:.1f} | {r['kernels']:.1f} | {r['segment_all_frames']:.2f} |")
    if "after" in labels:  # what the rounds of issue 15 changed, in order
        lines += ["", "What `after` changed, round by round:", "",
                  "| tried | what it gave | kept? / why |", "| --- | --- | --- |"]
        lines += [f"| {a} | {b} | kept |" for a, b in (
            ("the mask compiled, by blocks", "no separate figure"),
            ("the report drawn in a second process while a core is free", "no separate figure"),
            ("the command ending without the interpreter's teardown", "no separate figure"),
            ("kernels on OpenMP threads", "no separate figure"),
            ("the padding search on the float32 voxels in place", "no separate figure"),
            ("the mask's slopes bounded patch by patch only", "no separate figure"),
            ("the global means' blood-dark polarity", "without it the 256^3 case collapsed (see its volume)"),
            ("the surface's samples on SIMD lanes", "one more parallel loop for a first run to compile, some 1.5 s"),
            ("the mask's and the padding's outputs zeroed in an anonymous memory map instead of numpy's huge pages",
             "the 256^3 mask 50 to 20-25 ms"),
            ("on a first run, a second process compiling the mask's and the padding's kernels while the command "
             "compiles the segmentation's", "a first run 20 to 11 s"),
            ("the demo's synthetic sequence made frame by frame in threads", "7 to 4 s"),
            ("each level of the descent in one compiled loop", "the segmentation 21 to 15 ms at CETUS size, 46 to 35 "
             "at 256^3; a first run 3 s longer, 14 s, after the second process took on the step's plain kernels "
             "too"))]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--label", choices=["before", "after"])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--report", action="store_true", help="print the docs section from docs/userspeed.json")
    args = parser.parse_args()
    path = DOCS / "userspeed.json"
    data = json.loads(path.read_text()) if path.is_file() else {}
    if args.label:
        load = os.getloadavg()[0]
        results = measure(args.repeats)
        data[args.label] = {"commit": git_commit(), "date": time.strftime("%Y-%m-%d %H:%M"),
                            "python": platform.python_version(), "results": results,
                            "demo": measure_demo(args.repeats),
                            "machine": f"{cpu_name()}, load average {load:.1f} at the start, "
                                       f"{os.getloadavg()[0]:.1f} at the end"}
        path.write_text(json.dumps(data, indent=1) + "\n")
    if args.report:
        print(report_section(data))


if __name__ == "__main__":
    main()
