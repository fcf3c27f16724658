"""Rasterisation: a surface's cavity as a voxel mask, the padding around a
scan-converted sector, and an image's means over blocks of voxels.

A service beside :class:`~spheroseg.Surface` and
:class:`~spheroseg.Volume`, which stay numpy types: the loops over voxels
are compiled (:mod:`spheroseg._compiled._raster`), imported only when called, and run
under the runtime's lock on parallel regions.  Nothing here imports the
surface or the volume modules: the surface and the grid are read through
their attributes.
"""

from __future__ import annotations

import numpy as np

__all__ = ["surface_mask", "outside_sector", "block_means"]


def surface_mask(surface, grid) -> np.ndarray:
    """Boolean mask ``[z, y, x]`` of the voxel centres of ``grid`` inside the
    closed cavity of ``surface``.

    Only the voxels in the surface's bounding box are tested, each as
    :meth:`Surface.contains <spheroseg.Surface.contains>` does (``v2`` in
    range and ``v0 <= f(v1, v2)``).  The compiled rasteriser decides whole
    blocks of voxels from one evaluation where the surface is provably far,
    and single voxels only near it, so its cost grows with the surface's
    area in voxels, not with the grid; without the built extension every voxel of the box
    is converted.

    Parameters
    ----------
    surface : Surface
    grid : ImageGrid
        The voxel grid (``shape`` ``[z, y, x]``, world mm).
    """
    lo, hi = surface.bounding_box()
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    idx = grid.world_to_index(corners)
    start = np.clip(np.floor(idx.min(0)).astype(int), 0, np.array(grid.shape[::-1]))
    stop = np.clip(np.ceil(idx.max(0)).astype(int) + 1, 0, np.array(grid.shape[::-1]))
    if np.any(stop <= start):
        return np.zeros(grid.shape, dtype=bool)
    try:
        from ._raster import cavity_mask
    except ImportError:  # not built (a source tree): the reference
        k, j, i = np.meshgrid(*(np.arange(a, b) for a, b in zip(start[::-1], stop[::-1])), indexing="ij")
        world = grid.index_to_world(np.stack([i, j, k], axis=-1).reshape(-1, 3))
        out = np.zeros(grid.shape, dtype=bool)
        out[start[2] : stop[2], start[1] : stop[1], start[0] : stop[0]] = surface.contains(world).reshape(i.shape)
        return out
    from ._runtime import PARALLEL_LOCK

    # local model point of a voxel index: R^T (D diag(spacing) idx + origin - pose origin)
    rotation_t = surface.pose.rotation.T
    affine = rotation_t @ grid.direction @ np.diag(grid.spacing)
    offset = rotation_t @ (grid.origin - surface.pose.origin)
    v2_lo, v2_hi = surface.grid.v2_range
    name = surface.system.name
    if name == "cylindrical":
        param = surface.system.height
        planar = v2_lo == 0 and abs(v2_hi - param) < 1e-12
    else:
        param = getattr(surface.system, "focal_length", 1.0)
        planar = v2_lo == 0 and abs(v2_hi - np.pi / 2) < 1e-12
    with PARALLEL_LOCK:
        codes, ties = cavity_mask(grid.shape, start, stop, affine, offset, name, param, surface.coefficients,
                                  (v2_lo, v2_hi), planar)
    if len(ties):
        codes[tuple(ties.T)] = surface.contains(grid.index_to_world(ties[:, ::-1]))
    return codes.view(bool)  # 0 and 1 only


def outside_sector(array: np.ndarray, *, min_fraction: float = 0.01) -> np.ndarray | None:
    """Voxels of the black padding around a scan-converted echo sector: the
    exact zeros connected to the faces of the image (6-connectivity).

    Zeros inside the anatomy (a noise-free blood pool) are not connected to
    the faces and stay data.

    Parameters
    ----------
    array : array (nz, ny, nx)
        The image's values.
    min_fraction : float, optional
        Least fraction of the image the padding must cover.

    Returns
    -------
    array of bool (nz, ny, nx) or None
        The padding, or ``None`` when it is under ``min_fraction`` of the
        image.
    """
    array = np.asarray(array)
    if array.ndim != 3:
        raise ValueError(f"expected a 3D array [z, y, x], got {array.ndim}D with shape {array.shape}")
    n = array.size
    # (no count of the zeros first: the padding is some of them, so too
    # few zeros means too little padding, and the search is no dearer)
    try:
        from ._raster import face_connected_zeros
    except ImportError:  # not built (a source tree): the reference
        from scipy import ndimage

        labels, _ = ndimage.label(array == 0)
        faces = np.concatenate([labels[[0, -1]].ravel(), labels[:, [0, -1]].ravel(), labels[:, :, [0, -1]].ravel()])
        mask = np.isin(labels, np.unique(faces[faces > 0]))
        count = int(np.count_nonzero(mask))
    else:
        mask, count = face_connected_zeros(array)
    return mask if count > 0 and count >= min_fraction * n else None


def block_means(array: np.ndarray, missing: np.ndarray, factor) -> np.ndarray:
    """Means of ``array`` over blocks of ``factor`` samples along its axes,
    over the samples not ``missing`` (a bool array of its shape): NaN where
    half a block or more is missing; what lies past the last whole block is
    left out.  Computed in the array's floating type (float32 at least, so
    that 8-bit grey levels do not overflow)."""
    factor = np.asarray(factor, int)
    shape = np.array(array.shape) // factor
    ok = ~np.asarray(missing, bool)
    values = np.where(ok, array, 0).astype(np.result_type(array.dtype, np.float32), copy=False)
    total, count = _block_sums(values, factor, shape), _block_sums(ok.astype(np.int32), factor, shape)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0.5 * factor.prod(), total / count, np.nan)


def _block_sums(array: np.ndarray, factor, shape) -> np.ndarray:
    # along each axis in turn the factor strided slices added: long inner
    # loops, where a sum over a reshaped block's short axes is slow
    for axis, (f, n) in enumerate(zip(factor, shape)):
        def part(i, axis=axis, f=f, n=n):
            return array[(slice(None),) * axis + (slice(i, n * f, f),)]
        total = part(0)
        for i in range(1, f):
            total = total + part(i)
        array = total
    return array
