"""Speed, side by side in one process: spheroseg's iteration and whole
segmentation at three image sizes, the time to load the image from disk,
the peers, tracking throughput, and a profile of one iteration.

    python benchmarks/speed.py           # about 10 minutes on 2 cores
    PYTHONPATH=<other code>/src python benchmarks/speed.py --default-mode before [--min]
    python benchmarks/speed.py --threads  # one thread against all cores, about 3 minutes

Writes docs/speed.json and regenerates docs/benchmarks.md.  With
``--default-mode LABEL`` it measures only the default mode (whole
segmentations of the unseen-style cases, the last stage's iteration, the
first segmentation of a process) with whatever spheroseg is importable and
keeps them under that label beside the full run's ('after'), so that two
versions of the code are compared on the same machine; ``--min`` keeps the
least of this run and the stored one (run the two versions in turn a few
times on a shared machine).  With ``--threads`` it measures the default
mode's segmentations and last-stage iteration, and the surface and the
samples of that iteration, on one thread and on each count up to the
cores (the ``threads`` option), side by side, and keeps them beside the
full run's.
"""

from __future__ import annotations

import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import PEER_PARAMS, machine, median_time, run_sitk, run_skimage, write_json  # noqa: E402
from report import write_markdown  # noqa: E402

import spheroseg  # noqa: E402
from spheroseg.descent.backends import compiled_available, kernel_thread_count, kernel_threads, usable_cores  # noqa: E402
from spheroseg._compiled._runtime import current_threads  # noqa: E402
from spheroseg.descent.dataterms import IntensityInterface, LocalMeans  # noqa: E402
from spheroseg.descent.stepper import freeze_samples  # noqa: E402
from spheroseg.descent.descent import Descent  # noqa: E402
from spheroseg.synthetic.phantom import FORMATIONS, make_phantom, make_sequence  # noqa: E402
from spheroseg.tracking.segment import segment as _segment, track  # noqa: E402
from spheroseg.surfaces.surface import Surface  # noqa: E402
from spheroseg.tracking.tracker import Tracker  # noqa: E402


def segment(*args, **kwargs):
    """The descent from the given points, without the check of those points
    against the located ventricle (``check=False``), which is measured by
    benchmarks/locate.py: this page times the method itself."""
    return _segment(*args, check=False, **kwargs)


def descent(apex, base, patches=(8, 8), backend="auto"):
    s = Surface.from_apex_base(apex, base, patches=patches)
    return Descent(s, s, order=8, step=1.0, landmarks=apex[None], landmark_weights=[1.0], nu=0.0, smoothness=1.0,
                   backend=backend)


def iteration_parts(d, volume, repeats=300) -> dict:
    """Median times (us) of the parts of one local-mode iteration."""
    p0 = d.p.copy()
    term = LocalMeans()
    state = term.start(np.array([0.0, 100.0]))
    obs = d.observe(volume, term.reads(state))

    def project():
        d.p = p0.copy()
        d.iterate(obs, term.force(obs, state))

    def whole():
        d.p = p0.copy()
        o = d.observe(volume, term.reads(state))
        d.iterate(o, term.force(o, state))

    backend, rows = d.backend, d.discretisation.band_rows
    out = {"sampling_us": 1e6 * median_time(lambda: d.observe(volume, term.reads(state)), repeats),
           "projection_us": 1e6 * median_time(project, repeats),
           "iteration_us": 1e6 * median_time(whole, repeats)}
    out["geometry_us"] = 1e6 * median_time(lambda: d.model.geometry(d.p), repeats) if backend.name == "numpy" else np.nan
    if backend.name == "compiled":  # the parts of the observation
        out["surface_and_samples_us"] = 1e6 * median_time(lambda: backend.observe(d.p, volume), repeats)
        out["band_samples_us"] = 2e6 * median_time(lambda: backend.mean_along(volume, obs, state.band_offsets, rows),
                                                   repeats)
        out["local_means_us"] = 1e6 * median_time(
            lambda: term.force(replace(obs, band_means=backend.band_means(obs)), state), repeats)
        out["image_samples"] = d.model.n_samples + 2 * len(rows) * len(state.band_offsets)
    d.p = p0
    return out


def last_stage(volume, apex, base):
    """The default mode's last stage (the intensity interface on 8 x 8
    patches, its region means frozen) from the surface a segmentation ends
    on: the descent, its data term and its start parameters."""
    s = segment(volume, apex, base).surface
    d = Descent(s, s, order=8, step=1.0, landmarks=apex[None], landmark_weights=[10.0], nu=0.0, smoothness=1.0)
    probe = d.backend.observe(d.p, volume)
    term = IntensityInterface()
    state = term.start(probe.u[np.isfinite(probe.u)])
    obs = d.observe(volume, term.reads(state))
    # measures and freezes the region means
    state = term.freeze(state, obs, *obs.band_means, freeze_samples(d.backend, volume, obs, term.freeze_reads(state)))
    return d, term, state, d.p.copy()


def intensity_iteration_us(volume, apex, base, repeats=300) -> float:
    """Median time (us) of one iteration of the default mode's last stage
    (:func:`last_stage`), as the tracker runs it: in the compiled level
    loop (``Descent.run``), the difference between 11 iterations and 1
    over 10 (the loop's call left out)."""
    d, term, state, p0 = last_stage(volume, apex, base)

    def run(iterations):
        d.p = p0.copy()
        d.reset_step(1.0)
        d.run(volume, term, state, tol=0.0, max_iterations=iterations)

    return 1e6 * (median_time(lambda: run(11), repeats) - median_time(lambda: run(1), repeats)) / 10


# the first segmentation of a fresh process: everything, and after the
# kernels were loaded on another grid (what is left: the grid matrices)
FIRST_CALL = r"""
import json, time
import spheroseg
from spheroseg.synthetic.phantom import make_phantom
ph = make_phantom(seed=0, spacing=2.0)
t = time.perf_counter(); spheroseg.segment(ph.volume, ph.apex, ph.base, patches=(6, 6), check=False); fresh = time.perf_counter() - t
t = time.perf_counter(); spheroseg.segment(ph.volume, ph.apex, ph.base, check=False); first = time.perf_counter() - t
t = time.perf_counter(); spheroseg.segment(ph.volume, ph.apex, ph.base, check=False); again = time.perf_counter() - t
print(json.dumps({"fresh_ms": 1000 * fresh, "first_default_ms": 1000 * first, "again_ms": 1000 * again}))
"""


def first_calls(repeats=5) -> dict:
    """Medians over fresh interpreters of :data:`FIRST_CALL`'s timings."""
    import json
    import subprocess

    runs = [json.loads(subprocess.run([sys.executable, "-c", FIRST_CALL], capture_output=True, text=True,
                                      check=True).stdout.strip().splitlines()[-1]) for _ in range(repeats)]
    return {k: float(np.median([r[k] for r in runs])) for k in runs[0]}


def stage_ms(volume, apex, base, repeats=10) -> dict:
    """Median times (ms) of a default segmentation's stages, stepping a
    :class:`Tracker` by hand as :func:`segment` does (a level in one
    compiled loop, else an iteration): the set-up (``Tracker()``), each
    level's iterations (a level's end builds the next level's descent:
    counted in it), and the result (with its quality report)."""
    runs = []
    for _ in range(repeats + 1):
        t0 = time.perf_counter()
        tracker = Tracker(volume, apex, base)
        row = {"setup": time.perf_counter() - t0}
        while tracker.status is None:
            level = f"level {tracker.level}: {type(tracker.levels[tracker.level].data_term).__name__}"
            t0, done = time.perf_counter(), tracker.iteration
            if not tracker.run_level():
                tracker.iterate()
            row[level] = row.get(level, 0.0) + time.perf_counter() - t0
            row[level + " iterations"] = row.get(level + " iterations", 0) + tracker.iteration - done
        t0 = time.perf_counter()
        tracker.result()
        row["result"] = time.perf_counter() - t0
        runs.append(row)
    runs = runs[1:]  # the first one warms the caches
    return {key: float(np.median([r.get(key, 0.0) for r in runs])) * (1 if key.endswith("iterations") else 1000)
            for key in runs[0]}


def unseen_cases(seeds=(0, 1, 2)) -> list[dict]:
    """Whole default segmentations of the accuracy sweep's image formations
    ('default' and the wider point-spread function), 1 mm phantoms."""
    rows = []
    for name in ("default", "psf_wide"):
        for seed in seeds:
            ph = make_phantom(seed=seed, formation=FORMATIONS[name])
            res = segment(ph.volume, ph.apex, ph.base)
            # ten more before timing: in the first few hundred ms after a
            # phantom is made, segmentations here took 3-4 ms more (the
            # system's work on the freed and new pages, not ours)
            median_time(lambda: segment(ph.volume, ph.apex, ph.base), 10)
            stages = stage_ms(ph.volume, ph.apex, ph.base)
            iteration = intensity_iteration_us(ph.volume, ph.apex, ph.base)
            rows.append({"formation": name, "seed": seed, "shape": "x".join(map(str, ph.volume.shape)),
                         "segment_ms": 1000 * median_time(lambda: segment(ph.volume, ph.apex, ph.base), 10),
                         "iterations": res.iterations, "intensity_iteration_us": iteration, "stages_ms": stages})
            print(rows[-1], flush=True)
    return rows


def thread_medians(fn, counts, repeats: int, rounds: int = 5) -> dict:
    """Median time (s) of ``fn()`` with the kernels' thread count at each of
    ``counts``, in ``rounds`` turns of ``repeats / rounds`` calls at each
    count, so that a change of the machine's load weighs on all alike (the
    count is set before each turn: a call pays nothing for it)."""
    times = {n: [] for n in counts}
    fn()  # warm-up
    for _ in range(rounds):
        for n in counts:
            with kernel_threads(n):
                for _ in range(max(1, repeats // rounds)):
                    t0 = time.perf_counter()
                    fn()
                    times[n].append(time.perf_counter() - t0)
    return {n: float(np.median(t)) for n, t in times.items()}


def thread_counts(seeds=(0, 1, 2)) -> dict:
    """One thread against 2..cores for the compiled kernels (the ``threads``
    option), side by side in this process, on
    the unseen-style cases of :func:`unseen_cases`: the whole default
    segmentation, its last-stage iteration (8 x 8 patches), and in that
    iteration the surface with its samples at the 4096 points and the
    samples alone."""
    import os

    counts = list(range(1, usable_cores() + 1))
    load_start = os.getloadavg()[0]
    rows = []
    for name in ("default", "psf_wide"):
        for seed in seeds:
            ph = make_phantom(seed=seed, formation=FORMATIONS[name])
            vol, apex, base = ph.volume, ph.apex, ph.base
            results = [segment(vol, apex, base, threads=n) for n in counts]
            assert all(np.array_equal(r.surface.coefficients, results[0].surface.coefficients) for r in results)
            d, term, p0 = last_stage(vol, apex, base)
            rows_all = np.arange(d.model.n_samples)
            obs = d.backend.observe(p0, vol)
            at_surface = np.array([0.0])

            def iteration():  # ten, in the compiled loop as the tracker runs them (a tenth of this below)
                d.p = p0.copy()
                d.reset_step(1.0)
                d.run(vol, term, tol=0.0, max_iterations=10)

            # the count set, not the default's idle cores (a busy moment would lower it)
            seg = thread_medians(lambda: segment(vol, apex, base, threads=current_threads()), counts, 10)
            it = thread_medians(iteration, counts, 100)
            observe = thread_medians(lambda: d.backend.observe(p0, vol), counts, 500)
            samples = thread_medians(lambda: d.backend.mean_along(vol, obs, at_surface, rows_all), counts, 500)
            d.p = p0
            row = {"formation": name, "seed": seed, "shape": "x".join(map(str, vol.shape)),
                   "iterations": results[0].iterations}
            for n in counts:
                row[str(n)] = {"segment_ms": 1000 * seg[n], "intensity_iteration_us": 1e5 * it[n],
                               "surface_and_samples_us": 1e6 * observe[n], "samples_us": 1e6 * samples[n]}
            rows.append(row)
            print(row, flush=True)
    load_end = os.getloadavg()[0]
    busy = beside_a_busy_process(seeds)
    print("beside a busy process", busy, flush=True)
    return {"counts": counts, "unseen": rows, "threading_layer": "openmp",
            "load": [load_start, load_end], "busy": busy, "machine": machine(), "date": time.strftime("%Y-%m-%d %H:%M")}


SPIN = "import time\nend = time.monotonic() + 600\nwhile time.monotonic() < end: pass\n"


def beside_a_busy_process(seeds=(0, 1, 2), repeats=20) -> dict:
    """Whole default segmentations of the unseen-style cases while another
    process spins on one core: the default thread count (the cores, reduced to
    the idle cores) against the whole count forced, call by call in
    turn; the median and the worst of each."""
    import subprocess

    forced = usable_cores()
    spinner = subprocess.Popen([sys.executable, "-c", SPIN])
    times = {"default": [], "forced": []}
    try:
        time.sleep(0.5)
        chosen = kernel_thread_count(None)  # what the default picks beside the spinner
        for name in ("default", "psf_wide"):
            for seed in seeds:
                ph = make_phantom(seed=seed, formation=FORMATIONS[name])
                segment(ph.volume, ph.apex, ph.base, threads=forced)
                for _ in range(repeats):
                    for key, threads in (("default", None), ("forced", forced)):
                        t0 = time.perf_counter()
                        segment(ph.volume, ph.apex, ph.base, threads=threads)
                        times[key].append(1000 * (time.perf_counter() - t0))
    finally:
        spinner.kill()
        spinner.wait()
    return {"forced_threads": forced, "default_threads": chosen, "segmentations": len(times["default"]),
            **{key: {"median_ms": float(np.median(t)), "worst_ms": float(np.max(t))} for key, t in times.items()}}


def _kernel_threads() -> int:
    """The compiled kernels' thread count (1 where they are not built)."""
    return current_threads() if compiled_available() else 1


def _previous(key: str) -> dict:
    """``key`` of the speed.json on disk (kept across full runs)."""
    import json

    path = Path(__file__).resolve().parents[1] / "docs" / "speed.json"
    return json.loads(path.read_text()).get(key, {}) if path.is_file() else {}


def _nbytes(value) -> int:
    if isinstance(value, np.ndarray):
        return value.nbytes
    if hasattr(value, "data") and hasattr(value, "indices"):  # sparse
        return value.data.nbytes + value.indices.nbytes + value.indptr.nbytes
    if isinstance(value, (list, tuple)):
        return sum(_nbytes(v) for v in value)
    if isinstance(value, dict):
        return sum(_nbytes(v) for v in value.values())
    return 0


def memory_bytes(d) -> int:
    """Bytes of what a level holds beyond the image: its own arrays and its
    backend's buffers, and the discretisation it shares with every level of
    the same resolution (with one smoothing's inverse)."""
    shared = _nbytes(vars(d.discretisation)) + _nbytes(d.discretisation.system_inverse(1.0))
    # the backend keeps the last image's sampling views: the image itself
    backend = {k: v for k, v in vars(d.backend).items() if k != "_sampling_arrays"}
    return int(_nbytes(vars(d)) + _nbytes(backend) + shared)


def default_mode(label: str, minimum: bool = False) -> None:
    """Only the default mode's measurements, stored under ``label`` (with
    ``minimum``, the least of this run and the one stored)."""
    import json

    path = Path(__file__).resolve().parents[1] / "docs" / "speed.json"
    data = json.loads(path.read_text()) if path.is_file() else {}
    entry = {"first_calls": first_calls(), "unseen": unseen_cases(), "machine": machine(),
             "date": time.strftime("%Y-%m-%d %H:%M"), "runs": 1}
    previous = data.setdefault("default_mode", {}).get(label)
    if minimum and previous:  # the least of repeated runs: what load on a shared machine added is left out
        entry["runs"] = previous.get("runs", 1) + 1
        entry["first_calls"] = {k: min(v, previous["first_calls"][k]) for k, v in entry["first_calls"].items()}
        for row, old in zip(entry["unseen"], previous["unseen"]):
            for key in ("segment_ms", "intensity_iteration_us"):
                row[key] = min(row[key], old[key])
    data["default_mode"][label] = entry
    print("wrote", write_json("speed.json", data))


def main():
    if sys.argv[1:] and sys.argv[1] not in ("--default-mode", "--threads"):  # -h, --help, a typo: not a 10-minute run
        print(__doc__)
        return
    if len(sys.argv) >= 3 and sys.argv[1] == "--default-mode":
        return default_mode(sys.argv[2], minimum="--min" in sys.argv[3:])
    if sys.argv[1:] == ["--threads"]:
        import json

        path = Path(__file__).resolve().parents[1] / "docs" / "speed.json"
        data = json.loads(path.read_text()) if path.is_file() else {}
        data["threads"] = thread_counts()
        print("wrote", write_json("speed.json", data))
        print("wrote", write_markdown())
        return
    import os

    load_start = os.getloadavg()[0]
    # the first segmentation in a process pays for loading the compiled
    # kernels and SciPy, and for reading the per-resolution matrices
    ph = make_phantom(seed=0)
    started = time.perf_counter()
    segment(ph.volume, ph.apex, ph.base)
    first_ms = 1000 * (time.perf_counter() - started)
    first_call = first_calls()
    print("first calls", first_call, flush=True)
    unseen = unseen_cases()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        import SimpleITK as sitk

        for spacing in (2.5, 1.25, 0.625):
            ph = make_phantom(seed=0, spacing=spacing)
            vol = ph.volume
            path = Path(tmp) / f"case_{spacing}.mha"
            image = sitk.GetImageFromArray(vol.array.astype(np.uint8))
            image.SetSpacing((spacing,) * 3)
            sitk.WriteImage(image, str(path))
            # the yardstick: reading the file into a Volume, nothing else (the
            # default load also finds the sector padding, which costs more)
            load_s = median_time(lambda: spheroseg.load(path, no_data_value=None), 5)
            load_auto_s = median_time(lambda: spheroseg.load(path), 3)
            d = descent(ph.apex, ph.base)
            parts = iteration_parts(d, vol)
            parts["intensity_iteration_us"] = intensity_iteration_us(vol, ph.apex, ph.base)
            seg_s = median_time(lambda: segment(vol, ph.apex, ph.base), 10)
            res = segment(vol, ph.apex, ph.base)
            row = {"spacing_mm": spacing, "shape": "x".join(map(str, vol.shape)), "voxels": int(np.prod(vol.shape)),
                   "load_ms": 1000 * load_s, "load_auto_ms": 1000 * load_auto_s, "iteration_us": parts["iteration_us"],
                   "intensity_iteration_us": parts["intensity_iteration_us"], "segment_ms": 1000 * seg_s,
                   "iterations": res.iterations}
            for name, fn in (("skimage", run_skimage), ("sitk", run_sitk)):
                _, seconds = fn(vol, ph.apex, ph.base, **PEER_PARAMS[name])
                row[f"{name}_ms"] = 1000 * seconds
            rows.append(row)
            print(row, flush=True)

    ph = make_phantom(seed=0)
    profile = []
    for patches in ((4, 4), (8, 8), (16, 16)):
        d = descent(ph.apex, ph.base, patches)
        parts = iteration_parts(d, ph.volume)
        ref = iteration_parts(descent(ph.apex, ph.base, patches, backend="numpy"), ph.volume, repeats=50)
        profile.append({"patches": f"{patches[0]} x {patches[1]}", "samples": d.model.n_samples, **parts,
                        "numpy_iteration_us": ref["iteration_us"], "numpy_geometry_us": ref["geometry_us"],
                        "memory_kb": memory_bytes(d) / 1024})
        print(profile[-1], flush=True)

    seq = make_sequence(seed=0, n_frames=10)
    first = seq.frames[0]
    tracker = Tracker(seq.volumes[0], first.apex, first.base)
    tracker.run()
    tracking = {}
    for ipf in (3, 5, 20):
        # frames after the first, as track() steps them (the cycle again and
        # again: each repeat continues from where the last one ended)
        def follow():
            for vol in seq.volumes[1:]:
                tracker.next_frame(vol, max_iterations=ipf)
        seconds = median_time(follow, 5)
        tracking[ipf] = (len(seq.volumes) - 1) / seconds
    full = median_time(lambda: track(seq.volumes, first.apex, first.base), 3)

    notes = [
        f"The compiled kernels {'are' if compiled_available() else 'are NOT'} built: the compiled backend "
        f"{'ran' if compiled_available() else 'did not run'} (the numpy backend is the reference; tests check both agree "
        "to 1e-6).",
        f"Whole tracking of the 10-frame sequence (first frame from apex and base, then up to 20 iterations per "
        f"frame): {1000 * full:.0f} ms, {len(seq.volumes) / full:.0f} volumes per second.",
        f"Load average {load_start:.1f} at the start of this run, {os.getloadavg()[0]:.1f} at its end (a shared "
        "2-core machine: other jobs slow it).",
    ]
    data = {"command": "python benchmarks/speed.py", "machine": machine(), "sizes": rows, "profile": profile,
            "tracking": {"iterations_per_frame": 5, "volumes_per_second": tracking[5],
                         "volumes_per_second_3": tracking[3], "volumes_per_second_20": tracking[20]},
            "first_segmentation_ms": first_ms, "first_calls": first_call, "unseen": unseen,
            "default_mode": {**_previous("default_mode"), "after": {"first_calls": first_call, "unseen": unseen,
                                                                    "machine": machine(),
                                                                    "date": time.strftime("%Y-%m-%d %H:%M")}},
            "threads": _previous("threads"), "kernel_threads": _kernel_threads(), "notes": notes}
    print("wrote", write_json("speed.json", data))
    print("wrote", write_markdown())


if __name__ == "__main__":
    main()
