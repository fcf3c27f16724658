"""Speed, side by side in one process: spheroseg's iteration and whole
segmentation at three image sizes, the time to load the image from disk,
the peers, tracking throughput, and a profile of one iteration.

    python benchmarks/speed.py           # about 10 minutes on 2 cores

Writes docs/speed.json and regenerates docs/benchmarks.md.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import PEER_PARAMS, machine, median_time, run_sitk, run_skimage, write_json  # noqa: E402
from report import write_markdown  # noqa: E402

import spheroseg  # noqa: E402
from spheroseg import _kernels  # noqa: E402
from spheroseg.phantom import make_phantom, make_sequence  # noqa: E402
from spheroseg.segment import _SURFACE_OFFSETS, _Descent, segment, track  # noqa: E402
from spheroseg.surface import Surface  # noqa: E402


def descent(volume, apex, base, patches=(8, 8), compiled=True):
    s = Surface.from_apex_base(apex, base, patches=patches)
    return _Descent(volume, s, s, order=8, step=1.0, band=8.0, band_out=15.0, landmarks=apex[None],
                    landmark_weights=[1.0], nu=0.0, smoothness=1.0, compiled=compiled)


def iteration_parts(d, repeats=300) -> dict:
    """Median times (us) of the parts of one local-mode iteration."""
    p0 = d.p.copy()
    obs = d.observe(True)
    c_in, c_out = d.local_means(obs)

    def project():
        d.p = p0.copy()
        cin, cout = d.local_means(obs)
        d.iterate(obs, cin, cout, 100.0)

    def whole():
        d.p = p0.copy()
        o = d.observe(True)
        cin, cout = d.local_means(o)
        d.iterate(o, cin, cout, 100.0)

    out = {"sampling_us": 1e6 * median_time(lambda: d.observe(True), repeats),
           "projection_us": 1e6 * median_time(project, repeats),
           "iteration_us": 1e6 * median_time(whole, repeats)}
    out["geometry_us"] = 1e6 * median_time(lambda: d.model.geometry(d.p), repeats) if not d.kernel else np.nan
    if d.kernel:  # the compiled parts of the observation
        m, b = d.model, d._buffers
        coefficients = (m.constraints @ d.p).reshape(m.grid.shape)
        out["surface_us"] = 1e6 * median_time(lambda: _kernels.prolate_surface(
            coefficients, m.order, *d.level.tables, *d.level.trig, m.system.focal_length, m.pose.rotation,
            m.pose.origin, b["f"], b["h0"], b["cos"], b["area"], b["world"], b["normal"]), repeats)
        counts = np.empty(m.n_samples, np.int64)
        out["surface_samples_us"] = 1e6 * median_time(lambda: _kernels.sample_along(
            *d._image(), b["world"], b["normal"], d._all_rows, _SURFACE_OFFSETS, b["u"], counts), repeats)
        out["band_samples_us"] = 2e6 * median_time(lambda: _kernels.sample_along(
            *d._image(), b["world"], b["normal"], d.band_rows, d._band, b["inside"], counts), repeats)
        out["local_means_us"] = 1e6 * median_time(lambda: d.local_means(obs), repeats)
        out["image_samples"] = m.n_samples + 2 * len(d.band_rows) * len(d._band)
    d.p = p0
    return out


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
    """Bytes of what a level holds beyond the image: its buffers, and the
    matrices it shares with every level of the same resolution."""
    m = d.model  # its dense mass matrix is the level's
    shared = [m.b_f, m.b_1, m.b_2, m.constraints, m.v1, m.v2, m.weights]
    return int(_nbytes(vars(d)) + _nbytes(vars(d.level)) + _nbytes(shared))


def main():
    # the first segmentation in a process pays for loading the compiled
    # kernels from numba's cache and for the per-resolution matrices
    ph = make_phantom(seed=0)
    started = time.perf_counter()
    segment(ph.volume, ph.apex, ph.base)
    first_ms = 1000 * (time.perf_counter() - started)
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
            d = descent(vol, ph.apex, ph.base)
            parts = iteration_parts(d)
            seg_s = median_time(lambda: segment(vol, ph.apex, ph.base), 10)
            res = segment(vol, ph.apex, ph.base)
            row = {"spacing_mm": spacing, "shape": "x".join(map(str, vol.shape)), "voxels": int(np.prod(vol.shape)),
                   "load_ms": 1000 * load_s, "load_auto_ms": 1000 * load_auto_s, "iteration_us": parts["iteration_us"], "segment_ms": 1000 * seg_s,
                   "iterations": res.iterations}
            for name, fn in (("skimage", run_skimage), ("sitk", run_sitk)):
                _, seconds = fn(vol, ph.apex, ph.base, **PEER_PARAMS[name])
                row[f"{name}_ms"] = 1000 * seconds
            rows.append(row)
            print(row, flush=True)

    ph = make_phantom(seed=0)
    profile = []
    for patches in ((4, 4), (8, 8), (16, 16)):
        d = descent(ph.volume, ph.apex, ph.base, patches)
        parts = iteration_parts(d)
        ref = iteration_parts(descent(ph.volume, ph.apex, ph.base, patches, compiled=False), repeats=50)
        profile.append({"patches": f"{patches[0]} x {patches[1]}", "samples": d.model.n_samples, **parts,
                        "numpy_iteration_us": ref["iteration_us"], "numpy_geometry_us": ref["geometry_us"],
                        "memory_kb": memory_bytes(d) / 1024})
        print(profile[-1], flush=True)

    seq = make_sequence(seed=0, n_frames=10)
    first = seq.frames[0]
    state = {}  # as spheroseg.track keeps it: the model and statistics of the first frame
    start = segment(seq.volumes[0], first.apex, first.base, _state=state)
    tracking = {}
    for ipf in (3, 5, 20):
        def follow():
            prev = start.surface
            for vol in seq.volumes[1:]:
                prev = segment(vol, first.apex, first.base, init=prev, max_iterations=ipf, coarse_to_fine=False,
                               _state=state).surface
        seconds = median_time(follow, 5)
        tracking[ipf] = (len(seq.volumes) - 1) / seconds
    full = median_time(lambda: track(seq.volumes, first.apex, first.base), 3)

    notes = [
        f"numba {'is' if _kernels.AVAILABLE else 'is NOT'} installed: the compiled path "
        f"{'ran' if _kernels.AVAILABLE else 'did not run'} (the numpy path is the reference; tests check both agree "
        "to 1e-6).",
        f"Whole tracking of the 10-frame sequence (first frame from apex and base, then up to 20 iterations per "
        f"frame): {1000 * full:.0f} ms, {len(seq.volumes) / full:.0f} volumes per second.",
    ]
    data = {"command": "python benchmarks/speed.py", "machine": machine(), "sizes": rows, "profile": profile,
            "tracking": {"iterations_per_frame": 5, "volumes_per_second": tracking[5],
                         "volumes_per_second_3": tracking[3], "volumes_per_second_20": tracking[20]},
            "first_segmentation_ms": first_ms,
            "notes": notes}
    print("wrote", write_json("speed.json", data))
    print("wrote", write_markdown())


if __name__ == "__main__":
    main()
