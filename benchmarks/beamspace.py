"""Beam space: tracking a beam-space sequence directly vs scan-convert-then-track,
the per-sample cost of the beam-space kernel vs the Cartesian one, and the
agreement of the two routes on phantoms.

    python benchmarks/beamspace.py       # about 3 minutes on 2 cores

The agreement uses the phantom's echo formed in beam space
(``make_phantom(formation=..., beam_space=True)``) and the legacy phantom
resampled on a sector.  The speed figures use phantoms (``spheroseg.synthetic.phantom``, 1 mm voxels)
resampled on a sector from the phantom's probe with ``to_beam_space``
(150 samples of 1 mm x 57 x 57 beams 1 degree apart); "scan-converted" is
that sector resampled back on the Cartesian grid covering it
(``scan_convert``, default grid: the beams' spacing at mid depth, 1.4 mm).  Writes docs/beamspace.json and
regenerates docs/benchmarks.md.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import machine, write_json  # noqa: E402
from report import write_markdown  # noqa: E402

from spheroseg._compiled import _kernels  # noqa: E402
from spheroseg.volumes.beamspace import scan_convert, to_beam_space  # noqa: E402
from spheroseg.synthetic.phantom import FORMATIONS, make_phantom, make_sequence, probe_sector  # noqa: E402
from spheroseg.tracking.segment import segment, track  # noqa: E402

ITERATIONS_PER_FRAME = 5


def tracking(repeats: int) -> dict:
    seq = make_sequence(n_frames=10, seed=11, spacing=1.0)
    apex, base = seq.frames[0].apex, seq.frames[0].base
    geometry = probe_sector(seq.volumes[0])
    frames = [to_beam_space(v, geometry) for v in seq.volumes]
    grid = geometry.cartesian_grid()
    converted = [scan_convert(f, grid) for f in frames]
    run = lambda vols: track(vols, apex, base, iterations_per_frame=ITERATIONS_PER_FRAME)  # noqa: E731
    run(frames), run(converted)  # warm-up
    # the routes interleaved, repeat by repeat, so that a load from other
    # jobs falls on both; medians and the fastest runs
    times = {"direct": [], "convert": [], "track_converted": []}
    for _ in range(repeats):
        for name, fn in (("direct", lambda: run(frames)), ("convert", lambda: [scan_convert(f, grid) for f in frames]),
                         ("track_converted", lambda: run(converted))):
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
    med = {k: float(np.median(v)) for k, v in times.items()}
    best = {k: min(v) for k, v in times.items()}
    n = len(frames)
    return {"frames": n, "beam_shape": list(geometry.shape), "cartesian_shape": list(grid.shape),
            "cartesian_spacing_mm": float(grid.spacing[0]), "iterations_per_frame": ITERATIONS_PER_FRAME,
            "repeats": repeats,
            "direct_ms_per_frame": 1e3 * med["direct"] / n, "scan_convert_ms_per_frame": 1e3 * med["convert"] / n,
            "track_converted_ms_per_frame": 1e3 * med["track_converted"] / n,
            "direct_ms_per_frame_min": 1e3 * best["direct"] / n,
            "scan_convert_ms_per_frame_min": 1e3 * best["convert"] / n,
            "track_converted_ms_per_frame_min": 1e3 * best["track_converted"] / n,
            "direct_fps": n / med["direct"], "converted_fps": n / (med["convert"] + med["track_converted"]),
            "converted_fps_excluding_conversion": n / med["track_converted"]}


def per_sample(repeats: int) -> list[dict]:
    """ns per trilinear sample along normals: beam-space kernel (both
    conventions) vs the Cartesian kernel on the scan-converted sector."""
    ph = make_phantom(seed=3, spacing=1.0)
    rng = np.random.default_rng(0)
    n = 4096
    # points around the cavity, normals random: samples spread over the sector like a surface's
    world = (ph.base + (ph.apex - ph.base) * rng.uniform(0, 1, (n, 1)) + rng.normal(0, 15, (n, 3))).T.copy()
    normal = rng.normal(size=(3, n))
    normal /= np.linalg.norm(normal, axis=0)
    offsets = np.linspace(-4, 4, 9)
    rows = np.arange(n)
    mean, count = np.empty(n), np.empty(n, np.int64)
    out = []
    for convention in ("tan", "sin"):
        beam = to_beam_space(ph.volume, probe_sector(ph.volume, convention=convention))
        cart = scan_convert(beam)
        for name, volume in (("beam space", beam), ("Cartesian", cart)):
            view = _kernels.sampler(volume.sampling_view())
            _kernels.sample_along(*view, world, normal, rows, offsets, 0.0, mean, count)  # compile / load
            times = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                _kernels.sample_along(*view, world, normal, rows, offsets, 0.0, mean, count)
                times.append(time.perf_counter() - t0)
            # the median and the fastest run: on a loaded machine the longer
            # (beam-space) calls are preempted more often than the short ones
            out.append({"convention": convention, "kernel": name,
                        "ns_per_sample": 1e9 * float(np.median(times)) / (n * len(offsets)),
                        "ns_per_sample_min": 1e9 * min(times) / (n * len(offsets)),
                        "finite_fraction": float(count.sum() / (n * len(offsets)))})
    return out


def agreement(seeds=(1, 2, 3, 4)) -> list[dict]:
    """Each phantom segmented in beam space and after scan conversion (default
    grid), with the original Cartesian image and the truth for reference."""
    cases = []
    for seed in seeds:  # echo formed in beam space by the phantom, then its Cartesian image
        ph = make_phantom(seed=seed, spacing=1.5, formation=FORMATIONS["default"], beam_space=True)
        cases.append(("formed in beam space", "tan", seed, ph, ph.beam_volume))
    for convention in ("tan", "sin"):  # the legacy Cartesian phantom resampled on a sector
        for seed in seeds[:2]:
            ph = make_phantom(seed=seed, spacing=1.0)
            cases.append(("resampled from Cartesian", convention, seed, ph,
                          to_beam_space(ph.volume, probe_sector(ph.volume, convention=convention))))
    rows = []
    for data, convention, seed, ph, beam in cases:
        converted_volume = scan_convert(beam)
        direct = segment(beam, ph.apex, ph.base)
        converted = segment(converted_volume, ph.apex, ph.base)
        converted_1mm = segment(scan_convert(beam, beam.geometry.cartesian_grid(1.0)), ph.apex, ph.base)
        cartesian = segment(ph.volume, ph.apex, ph.base)
        a, b = direct.mesh()[0], converted.mesh()[0]
        msd = 0.5 * (cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean())
        rows.append({"data": data, "convention": convention, "seed": seed, "beam_shape": list(beam.shape),
                     "converted_spacing_mm": float(converted_volume.spacing[0]), "mean_distance_mm": msd,
                     "direct_ml": direct.volume_ml, "converted_ml": converted.volume_ml,
                     "converted_1mm_ml": converted_1mm.volume_ml,
                     "original_cartesian_ml": cartesian.volume_ml, "truth_ml": ph.truth_volume_ml,
                     "volume_difference_percent": 100 * (direct.volume_ml / converted.volume_ml - 1),
                     "volume_difference_1mm_percent": 100 * (direct.volume_ml / converted_1mm.volume_ml - 1)})
    return rows


def main(repeats: int = 5) -> None:
    t0 = time.perf_counter()
    data = {"command": "python benchmarks/beamspace.py", "machine": machine(), "tracking": tracking(7),
            "per_sample": per_sample(repeats * 20), "agreement": agreement()}
    data["wall_seconds"] = time.perf_counter() - t0
    print("wrote", write_json("beamspace.json", data))
    print("wrote", write_markdown())


if __name__ == "__main__":
    main()
