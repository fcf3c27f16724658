"""Compiled kernels and their runtime, beneath everything else.

- :mod:`._kernels`: the iteration's hot loops (surface and image samples,
  cavity sums, the level loop), with the numpy reference path beside them in
  :mod:`spheroseg.descent.backends`.
- :mod:`._raster`: the exact rasteriser of a surface's cavity and the
  face-connected fill; :mod:`.raster` is its light service (what the layers
  above call).
- :mod:`._runtime`: whether the kernels can run, their threads and the lock
  around their parallel regions.

Nothing here imports a layer above it but :mod:`spheroseg.geometry` (the
Hermite basis).
"""

#: points this close (in voxels) outside the first or last voxel centre count
#: as on it: world -> index round-off must not lose the image's edge (the
#: compiled samplers and the numpy ones alike)
INDEX_TOLERANCE = 1e-6
