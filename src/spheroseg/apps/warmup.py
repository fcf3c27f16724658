"""Run the numerical path once before anything is timed.

The kernels are compiled when the package is built; a process still pays,
on its first segmentation, for importing SciPy and the extension modules
and for the grid-only matrices of each resolution (computed once per
machine and cached on disk, :mod:`spheroseg.geometry.array_cache`, then
read).  :func:`load_kernels` pays all of this up front on a tiny synthetic
image, so that the timings a command prints are those of the work itself,
and the viewer's first click answers at once.
"""

from __future__ import annotations

import threading
import time

import numpy as np

__all__ = ["load_kernels", "KernelLoad"]


class KernelLoad(dict):
    """``{"seconds": wall time of the loading}``."""


def load_kernels() -> KernelLoad:
    """Run a segmentation, its mask and the sector padding once on a small
    synthetic ellipsoid (deterministic), loading what they use.

    Once a process: a later call, or one made meanwhile from another thread
    (the viewer's worker and the command that started it), waits for the
    first and reports its own wait as ``seconds``.
    """
    t0 = time.perf_counter()
    with _LOADING:
        if "first" not in _LOADED:
            _LOADED["first"] = _load()
            return KernelLoad(_LOADED["first"])
        return KernelLoad(_LOADED["first"], seconds=time.perf_counter() - t0)


_LOADING = threading.Lock()
_LOADED: dict[str, KernelLoad] = {}


def _load() -> KernelLoad:
    from .._compiled.raster import outside_sector, surface_mask
    from ..tracking.segment import segment

    t0 = time.perf_counter()
    image, volume, apex, base = _synthetic_case()
    result = segment(volume, apex=apex, base=base, max_iterations=2, check=False)
    surface_mask(result.surface, volume.grid)
    outside_sector(image)
    return KernelLoad(seconds=time.perf_counter() - t0)


def _synthetic_case():
    """A dark ellipsoidal cavity in bright tissue, with Rayleigh speckle,
    log-compressed as a scanner does, and a zero border as a sector's
    padding (deterministic): ``(image, volume, apex, base)``."""
    from ..volumes.volume import Volume

    shape = (24, 20, 20)
    k, j, i = np.indices(shape)
    inside = ((i - 9.5) / 6) ** 2 + ((j - 9.5) / 6) ** 2 + ((k - 4) / 16) ** 2 <= 1
    speckle = np.random.default_rng(0).rayleigh(size=shape)
    image = (20 * np.log10(1 + 100 * np.where(inside, 0.1, 1.0) * speckle)).astype(np.float32)
    image[:, :, 0] = 0  # the padding: every other voxel is positive
    volume = Volume(image, spacing=(2.0, 2.0, 2.0), no_data_mask=image == 0)
    return image, volume, (19.0, 19.0, 38.0), (19.0, 19.0, 8.0)
