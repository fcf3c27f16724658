"""What a user waits for before any segmenting (issue 49): the package's
import, the command's --help, ``spheroseg.load`` against SimpleITK's own
read, and ``spheroseg segment`` as a whole process against a bare
SimpleITK read + write process.

Each figure is a median over fresh processes (or in-process repeats for
``load``), the versions side by side in one run, interleaved so that the
shared machine's load falls on both alike::

    git archive <before-commit> src | tar -x -C /tmp/before
    PYTHONPATH=src python benchmarks/startup.py --before /tmp/before/src

The load check also confirms that the sector padding found lazily is the
one the eager search found, on the devset and CETUS Patient 7 ED (made an
``.mha`` in a temporary folder, never kept). Results go to
``docs/startup.json``; ``--report`` prints the docs section.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
SHARED = ROOT.parent / "shared" if (ROOT.parent / "shared").is_dir() else Path("/work/shared")
CETUS = SHARED / "data" / "cetus"
DEVSET = SHARED / "data" / "devset"


def env_for(src: str) -> dict:
    return dict(os.environ, PYTHONPATH=src)


def wall(argv, env, repeats: int) -> list[float]:
    out = []
    for _ in range(repeats):
        t = time.perf_counter()
        run = subprocess.run(argv, env=env, capture_output=True, text=True)
        out.append(time.perf_counter() - t)
        if run.returncode not in (0, 3):
            raise RuntimeError(f"{argv}: {run.stderr.strip()[-500:]}")
    return out


def interleaved(commands: dict, repeats: int) -> dict:
    """``{name: median seconds}`` of ``{name: (argv, env)}``, run in turn ``repeats`` times."""
    times = {name: [] for name in commands}
    for _ in range(repeats):
        for name, (argv, env) in commands.items():
            times[name] += wall(argv, env, 1)
    return {name: statistics.median(t) for name, t in times.items()}


def loaded_modules(src: str) -> dict:
    code = ("import sys, json\nimport spheroseg\n"
            "print(json.dumps({m: m in sys.modules for m in ('numpy', 'scipy', 'scipy.ndimage', 'scipy.sparse', "
            "'scipy.optimize', 'SimpleITK', 'matplotlib', 'meshio', 'numba', 'tqdm')}))")
    run = subprocess.run([sys.executable, "-c", code], env=env_for(src), capture_output=True, text=True, check=True)
    return json.loads(run.stdout)


def import_time_tree(src: str) -> list:
    """The ten largest cumulative entries of ``python -X importtime -c 'import spheroseg'`` (microseconds)."""
    run = subprocess.run([sys.executable, "-X", "importtime", "-c", "import spheroseg"], env=env_for(src),
                         capture_output=True, text=True, check=True)
    rows = []
    for line in run.stderr.splitlines():
        if line.startswith("import time:") and "|" in line and "cumulative" not in line:
            _, cumulative, name = line.split("|")
            rows.append((int(cumulative), name.rstrip()))
    return [[c, n] for c, n in sorted(rows, reverse=True)[:10]]


def p7_case(folder: Path) -> dict:
    import SimpleITK as sitk

    info = json.loads((CETUS / "Patient7_points.json").read_text())
    array = np.load(CETUS / info["ED"]["file"])
    spacing = info["assumed_spacing_mm"]
    image = sitk.GetImageFromArray(array)
    image.SetSpacing((spacing,) * 3)
    path = folder / "p7_ed.mha"
    sitk.WriteImage(image, str(path))
    return {"path": str(path), "apex": (np.array(info["ED"]["apex_index"][::-1], float) * spacing).tolist(),
            "base": (np.array(info["ED"]["base_index"][::-1], float) * spacing).tolist()}


LOAD_CHILD = r"""
import json, statistics, sys, time
import numpy as np
import SimpleITK as sitk
import spheroseg
from spheroseg._compiled.raster import outside_sector

paths, repeats = json.loads(sys.argv[1]), int(sys.argv[2])
outside_sector(np.zeros((4, 4, 4), np.float32))  # the kernel loaded (or compiled) before any timing
out = {}
for path in paths:
    t_read, t_array, t_load, t_first = [], [], [], []
    for _ in range(repeats):
        t = time.perf_counter(); image = sitk.ReadImage(path); t_read.append(time.perf_counter() - t)
        t = time.perf_counter(); sitk.GetArrayFromImage(sitk.ReadImage(path)); t_array.append(time.perf_counter() - t)
        t = time.perf_counter(); volume = spheroseg.load(path); t_load.append(time.perf_counter() - t)
        t = time.perf_counter(); mask = volume.no_data_mask; t_first.append(time.perf_counter() - t)
    eager = outside_sector(np.ascontiguousarray(sitk.GetArrayFromImage(sitk.ReadImage(path)), dtype=np.float32))
    same = (mask is None and eager is None) or (mask is not None and eager is not None and np.array_equal(mask, eager))
    out[path] = {"ReadImage": statistics.median(t_read), "ReadImage+array": statistics.median(t_array),
                 "load": statistics.median(t_load), "sector": statistics.median(t_first),
                 "padding_fraction": 0.0 if mask is None else float(mask.mean()), "same_sector": bool(same)}
print(json.dumps(out))
"""

SITK_PROCESS = ("import sys, SimpleITK as sitk\n"
                "sitk.WriteImage(sitk.ReadImage(sys.argv[1]) > 0, sys.argv[2])")


def segment_process(src: str, case: dict, out: Path, *, report: bool) -> tuple:
    argv = [sys.executable, "-m", "spheroseg", "segment", case["path"], "--apex", *map(str, case["apex"]),
            "--base", *map(str, case["base"]), "--out", str(out), "--force", "--allow-poor"]
    return argv + ([] if report else ["--no-report"]), env_for(src)


def measure(before: str, repeats: int) -> dict:
    after = str(ROOT / "src")
    versions = {"before": before, "after": after}
    result = {"modules": {v: loaded_modules(s) for v, s in versions.items()},
              "importtime": {v: import_time_tree(s) for v, s in versions.items()}}
    py = [sys.executable]
    commands = {"python -c pass": (py + ["-c", "pass"], env_for(after)),
                "python -c 'import numpy'": (py + ["-c", "import numpy"], env_for(after))}
    for v, s in versions.items():
        commands[f"import spheroseg ({v})"] = (py + ["-c", "import spheroseg"], env_for(s))
        commands[f"spheroseg --help ({v})"] = (py + ["-m", "spheroseg", "--help"], env_for(s))
        commands[f"spheroseg segment --help ({v})"] = (py + ["-m", "spheroseg", "segment", "--help"], env_for(s))
    result["startup"] = interleaved(commands, 3 * repeats)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        case = p7_case(tmp) if CETUS.is_dir() else None
        paths = ([case["path"]] if case else []) + sorted(str(p) for p in DEVSET.glob("dev_*/image.mha"))
        result["load"] = {}
        for v, s in versions.items():
            run = subprocess.run([sys.executable, "-c", LOAD_CHILD, json.dumps(paths), str(10 * repeats)],
                                 env=env_for(s), capture_output=True, text=True, check=True)
            result["load"][v] = {Path(p).parent.name if "devset" in p else "cetus_p7_ed": r
                                 for p, r in json.loads(run.stdout.strip().splitlines()[-1]).items()}
        if case:
            commands = {"SimpleITK read + write": (py + ["-c", SITK_PROCESS, case["path"], str(tmp / "m.mha")],
                                                   env_for(after))}
            for v, s in versions.items():
                commands[f"segment ({v})"] = segment_process(s, case, tmp / f"o-{v}", report=True)
                commands[f"segment --no-report ({v})"] = segment_process(s, case, tmp / f"n-{v}", report=False)
            wall(commands["segment (after)"][0], commands["segment (after)"][1], 1)  # numba caches warm
            wall(commands["segment (before)"][0], commands["segment (before)"][1], 1)
            result["segment"] = interleaved(commands, repeats)
            result["volume_ml"] = {v: json.loads((tmp / f"o-{v}" / "results.json").read_text())["volume_ml"]
                                   for v in versions}
            argv = commands["segment (after)"][0] + ["--profile"]
            run = subprocess.run(argv, env=env_for(after), capture_output=True, text=True)
            result["profile_after"] = run.stderr.strip().splitlines()
    return result


def report_section(data: dict) -> str:
    r = data["results"]
    s = r["startup"]
    base = s["python -c pass"]
    lines = [f"Measured {data['date']} on {data['machine']}, Python {data['python']}; commits: before "
             f"{data['before']}, after {data['commit']}.", "",
             "| fresh process (median) | before | after | before / after |", "|---|---:|---:|---:|",
             f"| `python -c pass` | {1000 * base:.0f} ms | | |"]
    numpy_only = s.get("python -c 'import numpy'")
    if numpy_only is not None:
        lines.append(f"| `python -c 'import numpy'` | {1000 * numpy_only:.0f} ms | | |")
    for what in ("import spheroseg", "spheroseg --help", "spheroseg segment --help"):
        b, a = s[f"{what} ({'before'})"], s[f"{what} ({'after'})"]
        lines.append(f"| `{what}` | {1000 * b:.0f} ms | {1000 * a:.0f} ms | {b / a:.1f}x |")
    heavy = [m for m, on in r["modules"]["before"].items() if on and not r["modules"]["after"][m]]
    lines += ["", f"`import spheroseg` no longer loads: {', '.join(heavy)} (after: "
                  f"{', '.join(m for m, on in r['modules']['after'].items() if on) or 'none of them'}).", "",
              "| `spheroseg.load` (median, in process) | ReadImage | ReadImage + array | load before | load after "
              "| after / ReadImage | sector found later | same sector |", "|---|---:|---:|---:|---:|---:|---:|---|"]
    for name, after in r["load"]["after"].items():
        before = r["load"]["before"][name]
        lines.append(f"| {name} ({100 * after['padding_fraction']:.0f}% padding) | {1000 * after['ReadImage']:.1f} ms | "
                     f"{1000 * after['ReadImage+array']:.1f} ms | {1000 * before['load']:.1f} ms | "
                     f"{1000 * after['load']:.1f} ms | {after['load'] / after['ReadImage']:.1f}x | "
                     f"{1000 * after['sector']:.1f} ms | {'yes' if after['same_sector'] else 'NO'} |")
    if "segment" in r:
        g = r["segment"]
        bare = g["SimpleITK read + write"]
        lines += ["", "| whole process on CETUS P7 ED (median) | seconds | / bare SimpleITK read + write |",
                  "|---|---:|---:|", f"| SimpleITK read + write | {bare:.2f} | 1.0x |"]
        for k in ("segment (before)", "segment (after)", "segment --no-report (before)", "segment --no-report (after)"):
            lines.append(f"| `spheroseg {k.replace('segment ', 'segment ').replace('(', '').replace(')', '')}` | "
                         f"{g[k]:.2f} | {g[k] / bare:.1f}x |")
        lines += ["", f"Cavity volume before {r['volume_ml']['before']:.1f} mL, after {r['volume_ml']['after']:.1f} mL.",
                  "", "After, `--profile`:", "", "    " + "\n    ".join(r.get("profile_after", []))]
    return "\n".join(lines)


def git_commit(path=ROOT) -> str:
    run = subprocess.run(["git", "-C", str(path), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    return run.stdout.strip() or "unknown"


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", help="the src folder of the version to compare with")
    parser.add_argument("--before-commit", default="", help="its commit, for the record")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--report", action="store_true", help="print the docs section from docs/startup.json")
    args = parser.parse_args()
    path = DOCS / "startup.json"
    if args.before:
        load = os.getloadavg()[0]
        results = measure(args.before, args.repeats)
        data = {"commit": git_commit(), "before": args.before_commit, "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                "python": platform.python_version(), "results": results,
                "machine": f"{os.cpu_count()} cores shared, load average {load:.1f} at the start, "
                           f"{os.getloadavg()[0]:.1f} at the end"}
        path.write_text(json.dumps(data, indent=1) + "\n")
    if args.report:
        print(report_section(json.loads(path.read_text())))


if __name__ == "__main__":
    main()
