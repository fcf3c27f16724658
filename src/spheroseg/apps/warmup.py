"""Load the compiled kernels before anything is timed.

numba compiles spheroseg's kernels on their first call on a machine and
caches them on disk; every later process loads them from that cache (most
of it importing numba) and computes the grid-only matrices of each
resolution once.  :func:`load_kernels` pays
all of this up front on a tiny synthetic image, so that the timings a
command prints are those of the work itself, and tells whether the kernels
had to be compiled.

numba compiles one kernel at a time in a process.  On a first run with two
cores or more, a second process compiles the kernels of a descent's step
that sample no image and evaluate no surface, then the rasteriser's (the
mask and the sector padding), while this one compiles the rest of the
segmentation's (the surface, the samples and the compiled level loop).
This one loads the step's kernels from the cache when it reaches them, and
waits for the rasteriser's: a first run's loading takes about half as long
on 2 cores as in one process on one core (``docs/benchmarks.md``).
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from typing import Callable

import numpy as np

from .._compiled._runtime import compilations, usable_cores

__all__ = ["load_kernels", "load_raster_kernels", "load_step_kernels", "KernelLoad", "compilations"]


class KernelLoad(dict):
    """``{"seconds": wall time of the loading, "compiled": whether numba
    compiled (rather than loaded) any kernel, "helper": whether a second
    process compiled some}``."""


def load_kernels(*, on_compile: Callable[[], None] | None = None) -> KernelLoad:
    """Compile or load every kernel a segmentation, its mask and the sector
    padding use, and the grid-only matrices of the default resolutions, by
    running them once on a small synthetic ellipsoid (deterministic).

    Once a process: a later call, or one made meanwhile from another thread
    (the viewer's worker and the command that started it), waits for the
    first and reports its ``compiled`` with its own wait as ``seconds``.

    Parameters
    ----------
    on_compile : callable, optional
        Called before compiling when the rasteriser's kernels are not in
        numba's cache (a first run), so that a command can say so at once.

    Returns
    -------
    KernelLoad
        Seconds taken and whether anything was compiled (a first run);
        ``"helper"``: whether a second process compiled the step's and the
        rasteriser's kernels meanwhile.
    """
    t0 = time.perf_counter()
    with _LOADING:
        if "first" not in _LOADED:
            _LOADED["first"] = _load(on_compile)
            return KernelLoad(_LOADED["first"])
        return KernelLoad(_LOADED["first"], seconds=time.perf_counter() - t0)


_LOADING = threading.Lock()
_LOADED: dict[str, KernelLoad] = {}


def _load(on_compile) -> KernelLoad:
    t0 = time.perf_counter()
    from .._compiled import _kernels
    from .._compiled._raster import cached as raster_cached
    from .._compiled._raster import compilations as raster_compilations
    from ..tracking.segment import segment

    helper = None
    if not raster_cached():
        if on_compile is not None:
            on_compile()
        helper = _start_helper()
    image, volume, apex, base = _synthetic_case()
    result = segment(volume, apex=apex, base=base, max_iterations=2, check=False)
    if helper is not None:
        try:
            helper.wait(timeout=600)  # its kernels are in the cache now (had it failed, they compile below)
        except subprocess.TimeoutExpired:  # pragma: no cover
            helper.kill()
    load_raster_kernels(image, volume, result.surface)
    compiled = helper is not None or compilations(_kernels) + raster_compilations() > 0
    return KernelLoad(seconds=time.perf_counter() - t0, compiled=compiled, helper=helper is not None)


def load_raster_kernels(image=None, volume=None, surface=None) -> None:
    """Compile or load the rasteriser's kernels: the cavity mask of
    ``surface`` on ``volume``'s grid and the sector padding of ``image``
    (by default those of the synthetic case and its initial surface)."""
    from .._compiled.raster import outside_sector, surface_mask
    from ..surfaces.surface import Surface

    if surface is None:
        image, volume, apex, base = _synthetic_case()
        surface = Surface.from_apex_base(apex, base)
    surface_mask(surface, volume.grid)
    outside_sector(image)


def load_step_kernels() -> None:
    """Compile or load the kernels of a descent's step that sample no image
    and evaluate no surface (``B H``, ``B^T v``, the force's displacement,
    the samples along the normals), called as a segmentation calls them,
    on the synthetic case's initial surface, without computing that
    surface (a first run's second process compiles these while the first
    compiles the surface's and the samples')."""
    from ..descent.backends import Observation, select_backend
    from ..geometry.energy import SampledSurface
    from ..surfaces.surface import Surface

    image, volume, apex, base = _synthetic_case()
    surface = Surface.from_apex_base(apex, base)
    backend = select_backend(SampledSurface(surface.system, surface.pose, surface.grid, 8))
    d, n = backend.discretisation, backend.model.n_samples
    p = backend.model.parameters(surface.coefficients)
    backend.gather(p)
    backend.gather(np.zeros((len(p), 2)))
    backend.scatter(np.zeros(n))
    backend.scatter(np.zeros((2, len(d.band_rows))), band=True)
    world, normal = np.zeros((3, n)), np.zeros((3, n))  # any points: what is compiled is the calls' types
    world[0], normal[0] = 19.0, 1.0
    obs = Observation(*(np.ones(n) for _ in range(4)), world, normal, np.ones(n))
    backend.displacement(obs, 0.0, 1.0, 1.0, step=1.0, h0_floor=1.0)
    backend.samples_along(volume, obs, np.ones(4), d.band_rows)


def _start_helper():
    """A second process that compiles the step's and the rasteriser's
    kernels into numba's cache, when this process may run on two cores or
    more (else None)."""
    if usable_cores() < 2 or not sys.executable or getattr(sys, "frozen", False):  # (a frozen app is no Python)
        return None
    try:  # the same interpreter and environment (NUMBA_CACHE_DIR): the same cache
        return subprocess.Popen([sys.executable, "-c", "from spheroseg.warmup import load_raster_kernels, "
                                 "load_step_kernels; load_step_kernels(); load_raster_kernels()"],
                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    except OSError:  # pragma: no cover - this process compiles them
        return None


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
