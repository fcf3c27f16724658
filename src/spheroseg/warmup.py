"""Load the compiled kernels before anything is timed.

numba compiles spheroseg's kernels on their first call on a machine (about
10 s on 2 cores) and caches them on disk; every later process loads them
from that cache (a few hundred ms, most of it importing numba) and computes
the grid-only matrices of each resolution once.  :func:`load_kernels` pays
all of this up front on a tiny synthetic image, so that the timings a
command prints are those of the work itself, and tells whether the kernels
had to be compiled.
"""

from __future__ import annotations

import time

import numpy as np

__all__ = ["load_kernels", "KernelLoad", "compilations"]


class KernelLoad(dict):
    """``{"seconds": wall time of the loading, "compiled": whether numba
    compiled (rather than loaded) any kernel}``."""


def compilations(module) -> int:
    """Kernels of ``module`` that numba compiled in this process, i.e. that
    missed its on-disk cache (``Dispatcher.stats.cache_misses``)."""
    count = 0
    for value in vars(module).values():
        misses = getattr(getattr(value, "stats", None), "cache_misses", None)
        if misses:
            count += sum(misses.values()) if isinstance(misses, dict) else len(misses)
    return count


def load_kernels() -> KernelLoad:
    """Compile or load every kernel a segmentation, its mask and the sector
    padding use, and the grid-only matrices of the default resolutions, by
    running them once on a small synthetic ellipsoid (deterministic).

    Returns
    -------
    KernelLoad
        Seconds taken and whether anything was compiled (a first run).
    """
    t0 = time.perf_counter()
    from . import _kernels
    from .segment import segment
    from ._raster import compilations as raster_compilations
    from .volume import Volume, outside_sector

    shape = (24, 20, 20)
    k, j, i = np.indices(shape)
    # a dark ellipsoidal cavity in bright tissue, with Rayleigh speckle,
    # log-compressed as a scanner does, and a zero border as a sector's padding
    inside = ((i - 9.5) / 6) ** 2 + ((j - 9.5) / 6) ** 2 + ((k - 4) / 16) ** 2 <= 1
    speckle = np.random.default_rng(0).rayleigh(size=shape)
    image = (20 * np.log10(1 + 100 * np.where(inside, 0.1, 1.0) * speckle)).astype(np.float32)
    image[:, :, 0] = 0
    padding = outside_sector(image)
    volume = Volume(image, spacing=(2.0, 2.0, 2.0), no_data_mask=padding)
    result = segment(volume, apex=(19.0, 19.0, 38.0), base=(19.0, 19.0, 8.0), max_iterations=2)
    result.mask(volume)
    compiled = compilations(_kernels) + raster_compilations() > 0
    return KernelLoad(seconds=time.perf_counter() - t0, compiled=compiled)
