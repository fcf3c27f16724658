"""Shared pieces of the benchmarks: the peers, scoring, the report writer.

The peers are the tools a researcher would otherwise use, set up the same
way as spheroseg: initialised from the half-ellipsoid that spheroseg starts
from (apex and base points), and closed at the same base plane.  Each peer
pipeline is: Gaussian smoothing of the image (sigma in mm, 0 = none), the
level set, the connected component that overlaps the initial ellipsoid,
the half-space on the apex side of the base plane.
"""

from __future__ import annotations

import datetime
import json
import platform
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

import spheroseg
from spheroseg.surfaces.metrics import dice, surface_distances
from spheroseg.surfaces.surface import Surface

DOCS = Path(__file__).resolve().parents[1] / "docs"

# Chosen by `python benchmarks/accuracy.py --peer-sweep` on one case (speckle
# family, seed 100), then fixed for every case: see docs/benchmarks.md.
PEER_PARAMS = {
    "skimage": {"sigma_mm": 0.0, "num_iter": 30, "smoothing": 2},
    "sitk": {"sigma_mm": 1.5, "num_iter": 30, "curvature": 0.0},
}


def base_half_space(volume, apex, base) -> np.ndarray:
    """Voxels on the apex side of the plane through ``base`` normal to the axis."""
    axis = (apex - base) / np.linalg.norm(apex - base)
    k, j, i = np.indices(volume.shape)
    world = volume.index_to_world(np.stack([i, j, k], -1).reshape(-1, 3))
    return (((world - base) @ axis) >= 0).reshape(volume.shape)


def _postprocess(mask, init, half_space):
    mask = mask & half_space
    labels, n = ndimage.label(mask)
    if n == 0:
        return mask
    overlap = np.bincount(labels[init & mask], minlength=n + 1)
    overlap[0] = 0
    return labels == np.argmax(overlap) if overlap.max() > 0 else np.zeros_like(mask)


def _smoothed(volume, sigma_mm):
    image = volume.array.astype(np.float32) / 255.0
    if sigma_mm > 0:
        image = ndimage.gaussian_filter(image, sigma=sigma_mm / volume.spacing[::-1])
    return image


def run_skimage(volume, apex, base, *, sigma_mm, num_iter, smoothing):
    from skimage.segmentation import morphological_chan_vese

    init = Surface.from_apex_base(apex, base).mask(volume.grid)
    half = base_half_space(volume, apex, base)
    t0 = time.perf_counter()
    image = _smoothed(volume, sigma_mm)
    level = morphological_chan_vese(image, num_iter=num_iter, init_level_set=init.astype(np.int8), smoothing=smoothing)
    mask = _postprocess(level.astype(bool), init, half)
    return mask, time.perf_counter() - t0


def run_sitk(volume, apex, base, *, sigma_mm, num_iter, curvature):
    import SimpleITK as sitk

    init = Surface.from_apex_base(apex, base).mask(volume.grid)
    half = base_half_space(volume, apex, base)
    t0 = time.perf_counter()
    image = sitk.GetImageFromArray(_smoothed(volume, sigma_mm))
    image.SetSpacing(tuple(float(s) for s in volume.spacing))
    seed = sitk.GetImageFromArray(init.astype(np.uint8))
    seed.SetSpacing(image.GetSpacing())
    phi = sitk.SignedMaurerDistanceMap(seed, insideIsPositive=False, useImageSpacing=True, squaredDistance=False)
    cv = sitk.ScalarChanAndVeseDenseLevelSetImageFilter()
    cv.SetNumberOfIterations(num_iter)
    cv.SetMaximumRMSError(0.0)
    cv.SetLambda1(1.0)
    cv.SetLambda2(1.0)
    cv.SetEpsilon(1.0)
    cv.SetCurvatureWeight(curvature)
    cv.SetUseImageSpacing(True)
    out = sitk.GetArrayFromImage(cv.Execute(sitk.Cast(phi, sitk.sitkFloat32), image)) > 0
    mask = _postprocess(out, init, half)
    return mask, time.perf_counter() - t0


def mask_wall_mesh(mask, volume, apex, base):
    """Marching-cubes surface of a mask in world mm, without the flat cap on
    the base plane (the references are open there)."""
    from skimage.measure import marching_cubes

    if mask.sum() < 10:
        return None
    verts, faces, _, _ = marching_cubes(np.pad(mask, 1).astype(np.float32), 0.5)
    verts = verts - 1.0
    world = volume.index_to_world(verts[:, ::-1])
    axis = (apex - base) / np.linalg.norm(apex - base)
    height = (world - base) @ axis
    # marching cubes puts the cap up to 1.5 voxels from the plane's last layer
    cap = np.all(height[faces] < 1.5 * volume.spacing.max(), axis=1)
    return world, faces[~cap]


def score(mask, wall_mesh, volume_ml, phantom) -> dict:
    out = {"dice": dice(mask, phantom.truth_mask), "volume_error_pct": 100 * (volume_ml / phantom.truth_volume_ml - 1)}
    if wall_mesh is None:
        out.update(msd_mm=np.nan, hausdorff_mm=np.nan)
    else:
        sd = surface_distances(wall_mesh, phantom.truth_mesh, spacing=0.5)
        out.update(msd_mm=sd["mean"], hausdorff_mm=sd["hausdorff"])
    return out


def machine() -> dict:
    import scipy
    import SimpleITK
    import skimage

    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "date": datetime.date.today().isoformat(), "cpu": cpu, "python": platform.python_version(),
        "spheroseg": spheroseg.__version__, "numpy": np.__version__, "scipy": scipy.__version__,
        "SimpleITK": SimpleITK.Version_VersionString(), "scikit-image": skimage.__version__,
    }


def write_json(name: str, data: dict) -> Path:
    path = DOCS / name
    path.parent.mkdir(exist_ok=True)
    path.write_text(json.dumps(data, indent=1, default=lambda v: v.tolist() if hasattr(v, "tolist") else str(v)))
    return path


def median_time(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))
