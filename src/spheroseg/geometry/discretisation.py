"""The discretisation of a Hermite grid: its fixed sample points and every
matrix that depends on the grid alone.

An iteration evaluates the surface at fixed sample points ``(v1_q, v2_q)``
(Gauss-Legendre, ``order`` x ``order`` a patch) with quadrature weights
``w_q``.  What it multiplies by is set by the grid, never by the pose, the
coordinate system or the image, so it is built once per
``(grid, order)`` and shared, read-only, by every segmentation at that
resolution (:func:`discretise` caches it):

- ``B``, ``B_1``, ``B_2``: ``f``, ``df/dv1``, ``df/dv2`` at the samples
  from the free parameters ``p`` (the coefficients are ``H = A p``,
  :attr:`HermiteGrid.constraints`);
- the mass matrix ``M = B^T W B`` (its diagonal is paper eq. 10's
  normalisation) and its inverse;
- the thin-plate matrix ``T`` of the smoothing prior and
  ``(M + T)^-1`` for each smoothness (:meth:`Discretisation.system_inverse`);
- the band rows: a quarter of the sample points (every other one in each
  direction of a patch) on which region means are taken;
- the per-patch basis tables of the compiled kernels.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # SciPy is imported where a matrix is built: the package's import loads none
    import scipy.sparse as sp

from . import hermite
from .array_cache import cached_arrays
from .hermite import HermiteGrid

__all__ = ["Discretisation", "discretise", "BAND_STRIDE", "ROUGHNESS_SCALE"]

#: band means are taken on every other sample point in each direction
BAND_STRIDE = 2
#: the thin-plate matrix relative to the mass matrix for smoothness = 1: its
#: eigenvalues grow as k^4 for angular wavenumber k; this makes
#: smoothness = 1 damp a k = 8 wave (patch scale at 8 x 8) by half per step
ROUGHNESS_SCALE = 8.0**4


@dataclass(frozen=True, eq=False)
class Discretisation:
    """Sample points and grid-only matrices of a :class:`HermiteGrid` (read-only).

    Build it with :func:`discretise`, which caches one per ``(grid, order)``.

    Attributes
    ----------
    grid : HermiteGrid
    order : int
        Gauss-Legendre points per patch and direction (paper: 8).
    v1, v2, weights : arrays (n,)
        Sample points and quadrature weights (``sum(weights)`` is the area
        of the ``(v1, v2)`` domain).
    constraints : sparse (coefficients, parameters)
        ``A``; ``constraints_t`` is its transpose.
    b_f, b_1, b_2 : sparse (n, parameters)
        ``f``, ``df/dv1``, ``df/dv2`` at the samples.
    mass, mass_inverse : arrays (parameters, parameters)
        ``M = B^T W B`` and ``M^-1``.
    roughness : sparse (parameters, parameters)
        The thin-plate matrix per unit area (``T`` for smoothness 1; 13 % of
        its entries are non-zero at 8 x 8 patches).
    band_rows : int array
        Sample points of the band means.
    band_weights : array
        Their quadrature weights, rescaled to the domain's area.
    band_transpose : sparse
        ``B^T`` restricted to the band rows.
    tables, band_tables : (array, array)
        Hermite basis values and first derivatives at the ``order`` positions
        of a patch along v1 and v2 (``(2, order, 4)`` each), and the same at
        the band rows' positions (:meth:`HermiteGrid.patch_tables`).
    trig : (cos v1, sin v1, cos v2, sin v2) at the samples
    """

    grid: HermiteGrid
    order: int
    v1: np.ndarray
    v2: np.ndarray
    weights: np.ndarray
    constraints: sp.csr_matrix
    constraints_t: sp.csr_matrix
    b_f: sp.csr_matrix
    b_1: sp.csr_matrix
    b_2: sp.csr_matrix
    mass: np.ndarray
    mass_inverse: np.ndarray
    roughness: sp.csr_matrix
    band_rows: np.ndarray
    band_weights: np.ndarray
    band_transpose: sp.csr_matrix
    tables: tuple
    band_tables: tuple
    trig: tuple
    _system_inverses: dict = field(default_factory=dict, repr=False)
    _smoothings: dict = field(default_factory=dict, repr=False)

    @property
    def n_samples(self) -> int:
        return len(self.weights)

    @property
    def n_parameters(self) -> int:
        return self.constraints.shape[1]

    @property
    def area(self) -> float:
        """Area of the ``(v1, v2)`` domain, ``sum(weights)``."""
        return float(self.weights.sum())

    def smoothing(self, smoothness: float) -> sp.csr_matrix:
        """``a T``: the thin-plate matrix scaled to the mass matrix (sparse;
        cached per smoothness, its values read-only: every new descent
        reads it, and scaling a sparse matrix costs more than the rest of it).

        ``T`` is per unit area and ``M`` is not, hence the domain's area."""
        key = float(smoothness)
        if key not in self._smoothings:
            matrix = (key * self.area / ROUGHNESS_SCALE) * self.roughness
            matrix.data.flags.writeable = False
            self._smoothings[key] = matrix
        return self._smoothings[key]

    def system_inverse(self, smoothness: float) -> np.ndarray:
        """``(M + a T)^-1`` (cached per smoothness, read-only)."""
        key = float(smoothness)
        if key not in self._system_inverses:
            inverse = cached_arrays("system-inverse", _key(self.grid, self.order) + (key,),
                                    lambda: {"inverse": spd_inverse(self.mass + self.smoothing(key).toarray())},
                                    sources=_SOURCES)["inverse"]
            inverse.flags.writeable = False
            self._system_inverses[key] = inverse
        return self._system_inverses[key]


def spd_inverse(matrix: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive definite matrix (through Cholesky).

    An iteration applies the inverses as mat-vecs: at a few hundred
    unknowns a dense product is cheaper than a triangular solve."""
    import scipy.linalg

    factor = scipy.linalg.cho_factor(matrix)
    inverse = scipy.linalg.cho_solve(factor, np.eye(len(matrix)))
    return (inverse + inverse.T) / 2


@lru_cache(maxsize=16)
def discretise(grid: HermiteGrid, order: int = 8) -> Discretisation:
    """The :class:`Discretisation` of ``grid`` at ``order`` sample points per
    patch and direction (cached by value: equal grids share it; and on disk,
    :mod:`spheroseg.array_cache`: a new process reads it instead of
    computing it again)."""
    if not (isinstance(order, (int, np.integer)) and order >= 1):
        raise ValueError(f"order must be a positive integer, got {order!r}")
    arrays = cached_arrays("discretisation", _key(grid, order), lambda: _matrices(grid, int(order)), sources=_SOURCES)
    # C order whether computed or read: the kernels' compiled signatures depend on it
    arrays = {name: np.ascontiguousarray(value) for name, value in arrays.items()}
    a = grid.constraints
    result = Discretisation(
        grid=grid, order=int(order), v1=arrays["v1"], v2=arrays["v2"], weights=arrays["weights"], constraints=a,
        constraints_t=a.T.tocsr(), b_f=_unpack(arrays, "b_f"), b_1=_unpack(arrays, "b_1"), b_2=_unpack(arrays, "b_2"),
        mass=arrays["mass"], mass_inverse=arrays["mass_inverse"], roughness=_unpack(arrays, "roughness"),
        band_rows=arrays["band_rows"], band_weights=arrays["band_weights"],
        band_transpose=_unpack(arrays, "band_transpose"), tables=(arrays["tables_1"], arrays["tables_2"]),
        band_tables=(arrays["band_tables_1"], arrays["band_tables_2"]),
        trig=tuple(arrays[f"trig_{k}"] for k in range(4)))
    for value in vars(result).values():
        for array in value if isinstance(value, tuple) else (value,):
            if isinstance(array, np.ndarray):
                array.flags.writeable = False
    return result


# the code that computes the cached arrays: editing it invalidates the files
_SOURCES = (__file__, hermite.__file__)


def _key(grid: HermiteGrid, order: int) -> tuple:
    return (grid.n1, grid.n2, grid.v2_range, grid.poles, int(order))


def _matrices(grid: HermiteGrid, order: int) -> dict:
    """Every array of the :class:`Discretisation` but the constraints (flat,
    sparse matrices as their CSR parts)."""
    v1, v2, weights = grid.quadrature(order)
    a = grid.constraints
    b_f = (grid.basis_matrix(v1, v2) @ a).tocsr()
    b_1 = (grid.basis_matrix(v1, v2, 1, 0) @ a).tocsr()
    b_2 = (grid.basis_matrix(v1, v2, 0, 1) @ a).tocsr()
    mass = (b_f.T @ b_f.multiply(weights[:, None])).toarray()
    total = float(weights.sum())
    # band means on every other sample position of a patch in each direction
    # (a quarter of the points): they are smoothed over the surface anyway
    local = np.arange(order) % BAND_STRIDE == 0
    n_row = grid.n1 * order
    q = np.arange(len(weights))
    band_rows = np.flatnonzero(local[(q % n_row) % order] & local[(q // n_row) % order])
    band_weights = weights[band_rows] * (total / weights[band_rows].sum())
    tables = grid.patch_tables(order)
    arrays = dict(v1=v1, v2=v2, weights=weights, mass=mass, mass_inverse=spd_inverse(mass),
                  band_rows=band_rows, band_weights=band_weights,
                  tables_1=tables[0], tables_2=tables[1], band_tables_1=np.ascontiguousarray(tables[0][:, local]),
                  band_tables_2=np.ascontiguousarray(tables[1][:, local]))
    arrays.update({f"trig_{k}": f(v) for k, (f, v) in enumerate(((np.cos, v1), (np.sin, v1), (np.cos, v2), (np.sin, v2)))})
    for name, matrix in (("b_f", b_f), ("b_1", b_1), ("b_2", b_2), ("band_transpose", b_f[band_rows].T.tocsr()),
                         ("roughness", grid.roughness_matrix().tocsr())):
        arrays.update({f"{name}_data": matrix.data, f"{name}_indices": matrix.indices,
                       f"{name}_indptr": matrix.indptr, f"{name}_shape": np.array(matrix.shape)})
    return arrays


def _unpack(arrays: dict, name: str) -> sp.csr_matrix:
    import scipy.sparse as sp
    return sp.csr_matrix((arrays[f"{name}_data"], arrays[f"{name}_indices"], arrays[f"{name}_indptr"]),
                         shape=tuple(arrays[f"{name}_shape"]))
