"""Bicubic Hermite functions on a periodic-by-interval grid (paper section 3).

A function ``f(v1, v2)`` on ``[0, 2 pi) x [v2_min, v2_max]`` is stored as
four coefficients per node (paper eqs. 11-12), in this order:

    k = 0: f,   k = 1: df/dv1,   k = 2: df/dv2,   k = 3: d2f/dv1dv2

with derivatives per unit of ``v1`` and ``v2`` (radians, or mm for the
cylindrical ``z``), not per local patch coordinate.  ``v1 = theta`` is
periodic: the grid has ``n1`` patches and ``n1`` node columns (node ``n1``
is node ``0``).  ``v2`` has ``n2`` patches and ``n2 + 1`` node rows.

Ends of the ``v2`` interval that are poles of the coordinate system (the
apex, ``mu = 0``) are constrained so the surface is well formed there:
one value ``c`` for the whole row, ``df/dv1 = 0`` and
``df/dv2 = p1 cos(theta) + p2 sin(theta)`` at the nodes (the surface of a
tilted tangent plane), with the matching cross derivative.  These
constraints are the linear map ``coefficients = constraints @ parameters``
(:meth:`HermiteGrid.constraints`); optimisers work on the parameters.

References
----------
.. [1] Duan Q, Angelini ED, Laine AF et al. Variational segmentation
   framework in prolate spheroidal coordinates for 3D real-time
   echocardiography. Proc. SPIE 6144, 61444A (2006). doi:10.1117/12.653692
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # SciPy is imported where a matrix is built: the package's import loads none
    import scipy.sparse as sp

__all__ = ["hermite_basis", "global_basis", "patch_dofs", "HermiteGrid", "basis_norms", "gauss_legendre"]


def hermite_basis(t: np.ndarray, derivative: int = 0) -> np.ndarray:
    """The four cubic Hermite basis functions of paper eq. 7 on ``[0, 1]``.

    Parameters
    ----------
    t : array
        Local coordinate ``V`` in ``[0, 1]``.
    derivative : {0, 1, 2}
        Order of the derivative with respect to ``V``.

    Returns
    -------
    array, shape ``(4,) + t.shape``
        ``psi_0^0, psi_0^1, psi_1^0, psi_1^1``: value and slope at the
        patch's first node, value and slope at its second node.
    """
    t = np.asarray(t, dtype=float)
    if derivative not in (0, 1, 2):
        raise ValueError(f"derivative must be 0, 1 or 2, got {derivative!r}")
    out = np.empty((4,) + t.shape)  # filled row by row: np.stack cost as much as the polynomials
    if derivative == 0:
        out[0], out[1], out[2], out[3] = 1 - 3 * t**2 + 2 * t**3, t * (t - 1) ** 2, t**2 * (3 - 2 * t), t**2 * (t - 1)
    elif derivative == 1:
        out[0], out[1], out[2], out[3] = 6 * t * (t - 1), (3 * t - 1) * (t - 1), 6 * t * (1 - t), t * (3 * t - 2)
    else:
        out[0], out[1], out[2], out[3] = 12 * t - 6, 6 * t - 4, 6 - 12 * t, 6 * t - 2
    return out


def global_basis(t: np.ndarray, width: float, derivative: int = 0) -> np.ndarray:
    """The Hermite basis of a patch ``width`` wide, in global units.

    A patch's degrees of freedom are values and slopes with respect to the
    coordinate ``v = v_node + width t``, so the slope dofs multiply
    ``width psi_a^1`` and each derivative in ``v`` divides by ``width``::

        phi = (psi_0^0, width psi_0^1, psi_1^0, width psi_1^1) / width^derivative

    Parameters
    ----------
    t : array
        Local coordinate in ``[0, 1]``.
    width : float
        The patch's extent in ``v`` (radians for ``v1``, the units of ``v2``).
    derivative : {0, 1, 2}
        Order of the derivative with respect to ``v``.

    Returns
    -------
    array, shape ``(4,) + t.shape``
        Ordered ``2 node + dof``, as :func:`hermite_basis`.
    """
    b = hermite_basis(t, derivative)
    scale = np.array([1.0, width, 1.0, width]) / width**derivative
    return b * scale.reshape((4,) + (1,) * np.ndim(t))


@lru_cache(maxsize=16)
def patch_dofs(n1: int, n2: int) -> np.ndarray:
    """Where each patch's 16 degrees of freedom lie in the flat coefficients.

    The coefficients are ``(n2 + 1, n1, 4)``: node row along ``v2``, node
    column along ``v1`` (periodic: the last patch's second column is column
    0) and dof ``e1 + 2 e2`` (``e`` = 0 value, 1 slope, along ``v1`` and
    ``v2``).  Returns the read-only integer array ``[i2, i1, 2 a1 + e1,
    2 a2 + e2]`` of flat indices, ``a1``, ``a2`` the patch's node along each
    direction, so that on a patch ``f = phi_1^T P phi_2`` with ``P =
    coefficients.ravel()[patch_dofs(n1, n2)[i2, i1]]`` and ``phi`` the
    :func:`global_basis` along each direction.
    """
    i2, i1, a1, e1, a2, e2 = np.ix_(range(n2), range(n1), range(2), range(2), range(2), range(2))
    flat = ((i2 + a2) * n1 + (i1 + a1) % n1) * 4 + e1 + 2 * e2
    out = np.ascontiguousarray(flat.reshape(n2, n1, 4, 4))
    out.flags.writeable = False
    return out


@lru_cache(maxsize=16)
def gauss_legendre(order: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Legendre points and weights on ``[0, 1]`` (read-only, computed
    once an order)."""
    x, w = np.polynomial.legendre.leggauss(order)
    t, w = (x + 1) / 2, w / 2
    t.flags.writeable = w.flags.writeable = False
    return t, w


def _read_only(*arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    for a in arrays:
        a.flags.writeable = False
    return arrays


def basis_norms(n1: int, n2: int, v2_range: tuple[float, float]) -> np.ndarray:
    """L2 norms of the global basis functions ``f_i^{d1,d2}`` (paper eq. 10).

    In local patch units ``|f^0|^2 = 26/35`` and ``|f^1|^2 = 2/105`` over the
    two patches around an interior node; a slope basis function carries the
    patch width ``h`` (it is ``h psi^1``) and ``dv = h dV``, so in global
    units ``|f^0|^2 = 26/35 h`` and ``|f^1|^2 = 2/105 h^3``.  Nodes on the
    ends of the ``v2`` interval have one patch, hence half of this.

    Returns
    -------
    array, shape ``(n2 + 1, n1, 4)``
    """
    h1 = 2 * np.pi / n1
    h2 = (v2_range[1] - v2_range[0]) / n2
    one1 = np.array([26 / 35 * h1, 2 / 105 * h1**3])
    one2 = np.array([26 / 35 * h2, 2 / 105 * h2**3])
    rows = np.ones(n2 + 1)
    rows[[0, -1]] = 0.5
    sq = np.empty((n2 + 1, n1, 4))
    for k in range(4):
        sq[:, :, k] = (rows * one2[k // 2])[:, None] * one1[k % 2]
    return np.sqrt(sq)


@dataclass(frozen=True)
class HermiteGrid:
    """Node grid and basis of a bicubic Hermite function.

    Parameters
    ----------
    n1, n2 : int
        Patches along ``v1`` (periodic theta) and ``v2``; at least 2 each.
    v2_range : (float, float)
        Interval of ``v2``.
    poles : tuple of float
        Values of ``v2`` where the coordinate system has a pole; ends of
        ``v2_range`` equal to one of them are constrained (module docstring).
    """

    n1: int = 8
    n2: int = 8
    v2_range: tuple[float, float] = (0.0, np.pi / 2)
    poles: tuple[float, ...] = (0.0, np.pi)

    def __post_init__(self):
        for name in ("n1", "n2"):
            n = getattr(self, name)
            if not isinstance(n, (int, np.integer)) or n < 2:
                raise ValueError(f"{name} (number of patches) must be an integer >= 2, got {n!r}")
        lo, hi = (float(v) for v in self.v2_range)
        if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
            raise ValueError(f"v2_range must be an increasing finite interval, got {self.v2_range!r}")
        object.__setattr__(self, "v2_range", (lo, hi))
        object.__setattr__(self, "poles", tuple(float(p) for p in self.poles))

    @property
    def n_coefficients(self) -> int:
        return (self.n2 + 1) * self.n1 * 4

    @property
    def shape(self) -> tuple[int, int, int]:
        """Shape of the coefficient array: (v2 nodes, v1 nodes, 4)."""
        return (self.n2 + 1, self.n1, 4)

    @property
    def node_v1(self) -> np.ndarray:
        return np.arange(self.n1) * (2 * np.pi / self.n1)

    @property
    def node_v2(self) -> np.ndarray:
        return np.linspace(*self.v2_range, self.n2 + 1)

    @property
    def pole_rows(self) -> tuple[int, ...]:
        """Node rows (0 and/or n2) that lie on a pole."""
        rows = []
        for row, v in ((0, self.v2_range[0]), (self.n2, self.v2_range[1])):
            if any(abs(v - p) < 1e-12 for p in self.poles):
                rows.append(row)
        return tuple(rows)

    def refined(self) -> "HermiteGrid":
        """The grid with every patch split in two (2 n1 x 2 n2)."""
        return HermiteGrid(2 * self.n1, 2 * self.n2, self.v2_range, self.poles)

    # -- evaluation -------------------------------------------------------

    def _locate(self, v1, v2):
        v1 = np.mod(np.asarray(v1, dtype=float), 2 * np.pi)
        lo, hi = self.v2_range
        u1 = v1 * (self.n1 / (2 * np.pi))
        u2 = (np.asarray(v2, dtype=float) - lo) * (self.n2 / (hi - lo))
        # np.minimum(np.maximum()): np.clip's checks cost more than clipping a few points
        i1 = np.minimum(np.maximum(np.floor(u1).astype(np.int64), 0), self.n1 - 1)
        i2 = np.minimum(np.maximum(np.floor(u2).astype(np.int64), 0), self.n2 - 1)
        return i1, u1 - i1, i2, u2 - i2

    def _terms(self, v1, v2, d1: int = 0, d2: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """The 16 terms of ``f`` at each point: coefficient indices and basis
        values, ``(16,) + shape`` each (``shape`` the points', ``v1`` and
        ``v2`` broadcast), ordered ``(a2, a1, e2, e1)`` (node along v2, node
        along v1, dof along v2, dof along v1), the order in which
        :meth:`evaluate` sums them.

        The basis along each direction is computed on ``v1``'s and ``v2``'s
        own shapes: a tensor grid given as a row and a column costs a row's
        and a column's, not the grid's."""
        v1, v2 = np.asarray(v1, dtype=float), np.asarray(v2, dtype=float)
        i1, t1, i2, t2 = self._locate(v1, v2)
        # the points' axes, broadcast after (a2, a1, e2, e1)
        ndim = max(v1.ndim, v2.ndim)
        shape1, shape2 = ((1,) * (ndim - v.ndim) + v.shape for v in (v1, v2))
        b1 = global_basis(t1, 2 * np.pi / self.n1, d1).reshape((1, 2, 1, 2) + shape1)
        b2 = global_basis(t2, (self.v2_range[1] - self.v2_range[0]) / self.n2, d2).reshape((2, 1, 2, 1) + shape2)
        node1 = np.stack([i1, (i1 + 1) % self.n1]).reshape((1, 2) + shape1)
        node2 = np.stack([i2, i2 + 1]).reshape((2, 1) + shape2)
        corner = (node2 * self.n1 + node1) * 4  # [a2, a1, ...]
        dof = np.array([[0, 1], [2, 3]]).reshape((1, 1, 2, 2) + (1,) * ndim)  # [e2, e1] -> e1 + 2 e2
        index = corner.reshape(corner.shape[:2] + (1, 1) + corner.shape[2:]) + dof
        values = b1 * b2
        return index.reshape((16,) + index.shape[4:]), values.reshape((16,) + values.shape[4:])

    def basis_matrix(self, v1, v2, d1: int = 0, d2: int = 0) -> sp.csr_matrix:
        """Sparse matrix ``B`` with ``B @ coefficients.ravel()`` the
        ``(d1, d2)``-th partial derivative of ``f`` at the points.

        ``v1`` is wrapped into ``[0, 2 pi)``; ``v2`` outside the range is
        extrapolated from the end patch.
        """
        import scipy.sparse as sp
        index, values = self._terms(np.ravel(v1), np.ravel(v2), d1, d2)
        n = index.shape[1]
        # 16 distinct columns a row: built as CSR directly (COO's conversion
        # dominates for a few points), columns sorted as COO's would be
        matrix = sp.csr_matrix((values.T.ravel(), index.T.ravel(), np.arange(0, 16 * n + 1, 16)),
                               shape=(n, self.n_coefficients))
        matrix.sort_indices()
        return matrix

    def parameter_rows(self, v1, v2) -> np.ndarray:
        """``basis_matrix(v1, v2) @ constraints`` as a dense array: ``f`` at a
        few points from the parameters (a landmark, the apex).  A sparse
        product costs several times more for a handful of points; the
        transposed product sums each entry in the same order, so the two
        are equal to the last bit."""
        index, values = self._terms(np.ravel(v1), np.ravel(v2))
        rows = np.zeros((index.shape[1], self.n_coefficients))
        rows[np.arange(index.shape[1]), index] = values
        return (self._constraints_t @ rows.T).T

    def evaluate(self, coefficients, v1, v2, d1: int = 0, d2: int = 0) -> np.ndarray:
        """``d^(d1+d2) f / dv1^d1 dv2^d2`` at the points (``v1`` and ``v2``
        broadcast; a row of ``v1`` and a column of ``v2`` evaluate a tensor
        grid for the price of its row and column's basis)."""
        # the 16 terms a point summed directly: building the sparse matrix
        # cost several times the sum (a mesh evaluates 33 rings)
        index, values = self._terms(v1, v2, d1, d2)
        c = np.asarray(coefficients, dtype=float).reshape(-1)
        return (values * c[index]).sum(axis=0)

    def evaluate_grid(self, coefficients, v1, v2) -> np.ndarray:
        """``f`` on the tensor grid of the ``v2`` values (rows) by the ``v1``
        values (columns): two matrix products ``B2 C B1^T``, ``C`` the
        coefficients as a matrix of (v2 node, v2 dof) by (v1 node, v1 dof)
        and ``B1``, ``B2`` the basis along each direction.  A fraction of
        the time of :meth:`evaluate` at every point (equal to rounding).
        ``B1`` and ``B2`` are kept for the last few parameters (the quality
        report's, each segmentation): then the products are the whole cost."""
        v1, v2 = np.ravel(np.asarray(v1, dtype=float)), np.ravel(np.asarray(v2, dtype=float))
        m2, m1 = self._grid_basis(v1.tobytes(), v2.tobytes())
        # c[row, column, e1 + 2 e2] -> C[(row, e2), (column, e1)]
        c = np.asarray(coefficients, dtype=float).reshape(self.n2 + 1, self.n1, 2, 2).transpose(0, 2, 1, 3)
        return m2 @ c.reshape(2 * (self.n2 + 1), 2 * self.n1) @ m1.T

    @lru_cache(maxsize=16)
    def _grid_basis(self, v1_bytes: bytes, v2_bytes: bytes) -> tuple[np.ndarray, np.ndarray]:
        # keyed by the parameters' bytes: arrays are not hashable
        v1, v2 = np.frombuffer(v1_bytes), np.frombuffer(v2_bytes)
        i1, t1, i2, t2 = self._locate(v1, v2)
        b1 = global_basis(t1, 2 * np.pi / self.n1)  # [2 a1 + e1, point]
        b2 = global_basis(t2, (self.v2_range[1] - self.v2_range[0]) / self.n2)
        m1, m2 = np.zeros((v1.size, self.n1, 2)), np.zeros((v2.size, self.n2 + 1, 2))
        for a in (0, 1):
            m1[np.arange(v1.size), (i1 + a) % self.n1] = b1[2 * a : 2 * a + 2].T
            m2[np.arange(v2.size), i2 + a] = b2[2 * a : 2 * a + 2].T
        return _read_only(m2.reshape(v2.size, -1), m1.reshape(v1.size, -1))

    # -- quadrature -------------------------------------------------------

    @lru_cache(maxsize=16)
    def quadrature(self, order: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Gauss-Legendre points per patch: ``(v1, v2, weights)``, flat
        (read-only: cached by value, as the matrices below).

        ``sum(weights * g(v1, v2))`` integrates ``g dv1 dv2`` over the whole
        domain, exactly for piecewise polynomials of degree < 2 order.
        """
        if order < 1:
            raise ValueError(f"quadrature order must be >= 1, got {order!r}")
        t, w = gauss_legendre(order)
        w1 = 2 * np.pi / self.n1
        lo, hi = self.v2_range
        w2 = (hi - lo) / self.n2
        q1 = (np.arange(self.n1)[:, None] + t[None, :]).ravel() * w1
        q2 = lo + (np.arange(self.n2)[:, None] + t[None, :]).ravel() * w2
        wq1 = np.tile(w, self.n1) * w1
        wq2 = np.tile(w, self.n2) * w2
        v2, v1 = np.meshgrid(q2, q1, indexing="ij")
        return _read_only(v1.ravel(), v2.ravel(), np.outer(wq2, wq1).ravel())

    def quadrature_values(self, coefficients, order: int = 8) -> np.ndarray:
        """``f`` at the points of :meth:`quadrature` (same order), as
        :meth:`evaluate` there: ``f = T1 P T2^T`` patch by patch, with ``P``
        the patch's 4 x 4 coefficients and ``T1``, ``T2`` the tables of
        :meth:`patch_tables` (a tenth of the time of the sparse basis)."""
        c = np.asarray(coefficients, dtype=float).reshape(self.shape)
        table1, table2 = self.patch_tables(order)
        patch = c.ravel()[patch_dofs(self.n1, self.n2)]  # [i2, i1, 2 a1 + e1, 2 a2 + e2]
        f = table1[0] @ patch @ table2[0].T  # [i2, i1, a, b]
        return f.transpose(0, 3, 1, 2).ravel()

    @lru_cache(maxsize=16)
    def patch_tables(self, order: int = 8) -> tuple[np.ndarray, np.ndarray]:
        """Hermite basis values and first derivatives, in global units, at the
        ``order`` Gauss-Legendre positions of a patch: ``(2, order, 4)`` for
        v1 and for v2 (``[derivative, position, 2 node + dof]``).

        The sample points of :meth:`quadrature` are their tensor product, so
        the compiled kernels evaluate ``f`` patch by patch from these two
        small tables instead of a sparse matrix."""
        t, _ = gauss_legendre(order)
        lo, hi = self.v2_range
        tables = []
        for width in (2 * np.pi / self.n1, (hi - lo) / self.n2):
            tables.append(np.stack([global_basis(t, width, 0).T, global_basis(t, width, 1).T]))
        return _read_only(*tables)

    # -- pole constraints -------------------------------------------------

    # the matrices below depend on the grid's values only: cached by value
    # (a grid is frozen and hashable), so equal grids built anew (every
    # segmentation, every refinement) share them.  They are read-only.

    @property
    @lru_cache(maxsize=16)
    def constraints(self) -> sp.csr_matrix:
        """Matrix ``A`` (coefficients x parameters) with
        ``coefficients = A @ parameters`` for every well-formed surface.

        Free nodes keep their four coefficients as parameters; each pole row
        is replaced by three parameters ``(c, p1, p2)`` (module docstring).
        """
        import scipy.sparse as sp
        idx = np.arange(self.n_coefficients).reshape(self.shape)
        rows, cols, vals = [], [], []
        n_param = 0
        pole_rows = self.pole_rows
        for r in range(self.n2 + 1):
            if r in pole_rows:
                th = self.node_v1
                c, p1, p2 = n_param, n_param + 1, n_param + 2
                n_param += 3
                rows += list(idx[r, :, 0]) + list(idx[r, :, 2]) * 2 + list(idx[r, :, 3]) * 2
                cols += [c] * self.n1 + [p1] * self.n1 + [p2] * self.n1 + [p1] * self.n1 + [p2] * self.n1
                vals += [1.0] * self.n1 + list(np.cos(th)) + list(np.sin(th)) + list(-np.sin(th)) + list(np.cos(th))
            else:
                k = idx[r].ravel()
                rows += list(k)
                cols += list(range(n_param, n_param + k.size))
                vals += [1.0] * k.size
                n_param += k.size
        return sp.csr_matrix((vals, (rows, cols)), shape=(self.n_coefficients, n_param))

    @property
    @lru_cache(maxsize=16)
    def _constraints_t(self) -> sp.csr_matrix:
        return self.constraints.T.tocsr()

    @property
    @lru_cache(maxsize=16)
    def _constraint_pinv(self) -> sp.csr_matrix:
        # the columns of A are mutually orthogonal, so pinv(A) = diag(1/|a_j|^2) A^T
        import scipy.sparse as sp
        a = self.constraints
        norms = np.asarray(a.multiply(a).sum(axis=0)).ravel()
        return (sp.diags(1.0 / norms) @ a.T).tocsr()

    def parameters(self, coefficients) -> np.ndarray:
        """Least-squares parameters of (possibly unconstrained) coefficients."""
        return self._constraint_pinv @ np.asarray(coefficients, dtype=float).reshape(-1)

    def constrain(self, coefficients) -> np.ndarray:
        """Nearest well-formed coefficients (exact for well-formed input)."""
        return (self.constraints @ self.parameters(coefficients)).reshape(self.shape)

    @lru_cache(maxsize=16)
    def roughness_matrix(self, order: int = 4) -> sp.csr_matrix:
        """Thin-plate energy in the parameters: ``p^T T p = int f_11^2 +
        2 f_12^2 + f_22^2 dv1 dv2 / area``, zero for constant ``f``."""
        import scipy.sparse as sp
        q1, q2, w = self.quadrature(order)
        w = w / w.sum()
        a = self.constraints
        t = sp.csr_matrix((a.shape[1], a.shape[1]))
        for d1, d2, m in ((2, 0, 1.0), (1, 1, 2.0), (0, 2, 1.0)):
            d = self.basis_matrix(q1, q2, d1, d2) @ a
            t = t + m * (d.T @ d.multiply(w[:, None]))
        return t.tocsr()

    # -- refinement -------------------------------------------------------

    def refine(self, coefficients) -> tuple["HermiteGrid", np.ndarray]:
        """Exact representation on the grid with twice the patches.

        The bicubic Hermite space on ``n`` patches is a subspace of that on
        ``2 n`` patches, so the values, slopes and cross derivatives of the
        surface at the new nodes define the same function.
        """
        fine = self.refined()
        c = self._refinement_matrix @ np.asarray(coefficients, dtype=float).reshape(-1)
        return fine, c.reshape(fine.shape)

    @property
    @lru_cache(maxsize=16)
    def _refinement_matrix(self) -> sp.csr_matrix:
        # row (node, k) of the fine grid: the k-th derivative of the coarse basis there
        import scipy.sparse as sp
        fine = self.refined()
        v2, v1 = np.meshgrid(fine.node_v2, fine.node_v1, indexing="ij")
        parts = [self.basis_matrix(v1, v2, d1, d2) for d1, d2 in ((0, 0), (1, 0), (0, 1), (1, 1))]
        rows = sp.vstack(parts).tocsr()
        n = v1.size
        order = (np.arange(n)[:, None] + n * np.arange(4)[None, :]).ravel()  # node-major, k fastest
        return rows[order]
