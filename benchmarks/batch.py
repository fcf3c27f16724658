"""Cohort throughput: ``spheroseg batch`` on the local pool (1 and 2 workers)
and on a Dask LocalCluster (1 and 2 worker processes), against a shell loop
of ``spheroseg segment`` calls, on the same phantom studies with the default
outputs (mask, meshes, surface, CMISS, report, results.json).

    python benchmarks/batch.py [--studies 8] [--repeats 3]   # about 10 minutes on 2 cores

Every configuration runs the whole cohort into a fresh folder, timed from
the command's start to its exit (interpreter start, workers' start and
kernel loading included); the Dask cluster is started once beforehand (a
cluster outlives its jobs) and its start is timed apart.  Writes
docs/batch.json and its own section of docs/benchmarks.md (the rest of the
page is left as it is; ``--section-only`` rewrites the section from the JSON).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import SimpleITK as sitk

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import DOCS, machine, write_json  # noqa: E402
from report import batch_section  # noqa: E402

from spheroseg.synthetic.phantom import make_phantom  # noqa: E402

SPACING = 1.5  # mm: volumes of about 90 x 60 x 60 voxels


def make_cohort(folder: Path, n: int) -> list[dict]:
    studies = []
    for k in range(n):
        ph = make_phantom(seed=300 + k, spacing=SPACING)
        image = sitk.GetImageFromArray(ph.volume.array.astype(np.uint8))
        image.SetSpacing(tuple(ph.volume.spacing))
        sitk.WriteImage(image, str(folder / f"p{k:02d}.mha"))
        studies.append({"id": f"p{k:02d}", "image": f"p{k:02d}.mha", "apex": [float(x) for x in ph.apex],
                        "base": [float(x) for x in ph.base]})
    (folder / "cohort.json").write_text(json.dumps(studies))
    return studies


def timed(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {proc.stderr[-500:]}")
    return wall


def batch_run(folder: Path, out: Path, *extra) -> tuple[float, list[dict]]:
    wall = timed([sys.executable, "-m", "spheroseg", "batch", str(folder / "cohort.json"), "--out", str(out), "--quiet",
                  *map(str, extra)])
    return wall, json.loads((out / "summary.json").read_text())


def shell_loop(folder: Path, out: Path, studies: list[dict]) -> tuple[float, list[float]]:
    t0 = time.perf_counter()
    seconds = []
    for s in studies:
        timed([sys.executable, "-m", "spheroseg", "segment", str(folder / s["image"]), "--apex", *map(str, s["apex"]),
               "--base", *map(str, s["base"]), "--out", str(out / s["id"]), "--quiet"])
        results = json.loads((out / s["id"] / "results.json").read_text())
        seconds.append(results["seconds"]["load"] + results["seconds"]["segment"])
    return time.perf_counter() - t0, seconds


def write_section() -> Path:
    """Replace (or append) this benchmark's section of docs/benchmarks.md."""
    section = "\n".join(batch_section(json.loads((DOCS / "batch.json").read_text())))
    path = DOCS / "benchmarks.md"
    text = path.read_text()
    title = section.splitlines()[0]
    if title in text:
        start = text.index(title)
        end = text.find("\n## ", start + len(title))
        text = text[:start] + section + ("\n" + text[end:] if end >= 0 else "\n")
    else:
        text = text.rstrip("\n") + "\n\n" + section + "\n"
    path.write_text(text)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--studies", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--section-only", action="store_true", help="rewrite the section from docs/batch.json")
    args = parser.parse_args()
    if args.section_only:
        print("wrote", write_section())
        return
    os.environ.setdefault("OMP_NUM_THREADS", "1")  # as spheroseg batch and Dask set for their workers
    started, load = time.perf_counter(), os.getloadavg()
    work = Path(tempfile.mkdtemp(prefix="spheroseg-batch-bench-"))
    try:
        studies = make_cohort(work, args.studies)
        configs = {}

        def record(name, walls, seconds, workers, note):
            walls = np.array(walls)
            wall = float(np.median(walls))
            study_seconds = float(np.mean(seconds))
            configs[name] = {
                "workers": workers, "wall_seconds": walls.tolist(), "median_wall_seconds": wall,
                "studies_per_second": args.studies / wall, "mean_study_seconds": study_seconds,
                # what a study costs beyond loading and segmenting it, in worker-seconds
                "overhead_seconds_per_study": wall * workers / args.studies - study_seconds, "note": note}
            print(f"{name:>22}: {args.studies / wall:5.2f} studies/s (median wall {wall:.1f} s of {walls.round(1)}), "
                  f"overhead {configs[name]['overhead_seconds_per_study']:.2f} s/study", flush=True)

        walls, seconds = [], []
        for r in range(args.repeats):
            wall, secs = shell_loop(work, work / f"loop{r}", studies)
            walls.append(wall)
            seconds += secs
        record("shell loop", walls, seconds, 1, "for s in studies: spheroseg segment ...")
        for workers in (1, 2):
            walls, seconds = [], []
            for r in range(args.repeats):
                wall, rows = batch_run(work, work / f"pool{workers}-{r}", "--workers", workers)
                walls.append(wall)
                seconds += [row["seconds"] for row in rows]
            record(f"local pool, {workers} worker{'s' * (workers > 1)}", walls, seconds, workers,
                   f"spheroseg batch --workers {workers}")
        resume = [batch_run(work, work / "pool2-0", "--workers", 2)[0] for _ in range(args.repeats)]
        dask_start = {}
        try:
            from distributed import LocalCluster
        except ImportError:
            print("dask.distributed missing: pip install 'spheroseg[dask]'; Dask rows skipped")
        else:
            for workers in (1, 2):
                t0 = time.perf_counter()
                with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
                    dask_start[workers] = time.perf_counter() - t0
                    walls, seconds = [], []
                    for r in range(args.repeats):
                        wall, rows = batch_run(work, work / f"dask{workers}-{r}", "--scheduler",
                                               cluster.scheduler_address)
                        walls.append(wall)
                        seconds += [row["seconds"] for row in rows]
                record(f"Dask LocalCluster, {workers} worker{'s' * (workers > 1)}", walls, seconds, workers,
                       "spheroseg batch --scheduler ADDRESS")
        data = {"command": "python benchmarks/batch.py " + " ".join(sys.argv[1:]), "machine": machine(),
                "studies": args.studies, "repeats": args.repeats, "spacing_mm": SPACING,
                "volume_shape": list(make_phantom(seed=300, spacing=SPACING).volume.shape),
                "configs": configs, "resume_all_done_seconds": resume,
                "dask_cluster_start_seconds": dask_start, "wall_seconds": time.perf_counter() - started,
                "load": [load[0], os.getloadavg()[0]]}
        print("wrote", write_json("batch.json", data))
        print("wrote", write_section())
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
