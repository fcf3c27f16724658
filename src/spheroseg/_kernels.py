"""Compiled hot path of an iteration (optional: numba).

What one iteration reads from the image is set by the model: at each of the
4096 sample points of an 8 x 8-patch surface, the surface point, its normal
and a few trilinear samples along the normal.  In numpy that is some hundred
array operations on 4096-long arrays plus the gathers, about 2 ms; fused in
one compiled loop it is a few hundred microseconds.  numba compiles the loop
from Python source, so the readable numpy path in :mod:`spheroseg.segment`
stays the reference and the tests check that both agree to 1e-6.  Without
numba installed the numpy path runs.

Only the prolate spheroidal system (the default) has a kernel.
"""

from __future__ import annotations

import math

import numpy as np

try:  # pragma: no cover - exercised when numba is installed
    from numba import njit
except ImportError:  # pragma: no cover
    njit = None

__all__ = ["AVAILABLE", "prolate_observe", "scatter", "gather", "basis_tables"]

AVAILABLE = njit is not None
_EDGE = 1e-6  # as spheroseg.volume._EDGE


def _trilinear(image, to_index, img_origin, upper, px, py, pz):
    """Trilinear sample at world (px, py, pz); NaN outside the image (and,
    through the image's NaN voxels, on no-data)."""
    dx, dy, dz = px - img_origin[0], py - img_origin[1], pz - img_origin[2]
    fi = to_index[0, 0] * dx + to_index[0, 1] * dy + to_index[0, 2] * dz
    fj = to_index[1, 0] * dx + to_index[1, 1] * dy + to_index[1, 2] * dz
    fk = to_index[2, 0] * dx + to_index[2, 1] * dy + to_index[2, 2] * dz
    if not (-_EDGE <= fi <= upper[0] + _EDGE and -_EDGE <= fj <= upper[1] + _EDGE and -_EDGE <= fk <= upper[2] + _EDGE):
        return np.nan
    fi = min(max(fi, 0.0), upper[0])
    fj = min(max(fj, 0.0), upper[1])
    fk = min(max(fk, 0.0), upper[2])
    i0 = min(int(fi), max(int(upper[0]) - 1, 0))
    j0 = min(int(fj), max(int(upper[1]) - 1, 0))
    k0 = min(int(fk), max(int(upper[2]) - 1, 0))
    ti, tj, tk = fi - i0, fj - j0, fk - k0
    c00 = image[k0, j0, i0] * (1.0 - ti) + image[k0, j0, i0 + 1] * ti
    c01 = image[k0, j0 + 1, i0] * (1.0 - ti) + image[k0, j0 + 1, i0 + 1] * ti
    c10 = image[k0 + 1, j0, i0] * (1.0 - ti) + image[k0 + 1, j0, i0 + 1] * ti
    c11 = image[k0 + 1, j0 + 1, i0] * (1.0 - ti) + image[k0 + 1, j0 + 1, i0 + 1] * ti
    return (c00 * (1.0 - tj) + c01 * tj) * (1.0 - tk) + (c10 * (1.0 - tj) + c11 * tj) * tk


def _evaluate(coefficients, n1, basis1, basis2, i1, a, i2, b):
    """f, df/dv1, df/dv2 at the sample point at local position (a, b) of
    patch (i1, i2), from the coefficients (n2+1, n1, 4).

    The sample points are a tensor product of ``order`` local positions per
    patch, so the basis values come from two small tables (local position x
    [value dofs | slope dofs]) instead of a 16-entry sparse row per point."""
    f = 0.0
    f1 = 0.0
    f2 = 0.0
    for a1 in range(2):
        node1 = i1 + a1
        if node1 == n1:  # theta is periodic
            node1 = 0
        for a2 in range(2):
            for e1 in range(2):
                v1 = basis1[0, a, 2 * a1 + e1]
                d1 = basis1[1, a, 2 * a1 + e1]
                for e2 in range(2):
                    c = coefficients[i2 + a2, node1, e1 + 2 * e2]
                    v2 = basis2[0, b, 2 * a2 + e2]
                    f += c * v1 * v2
                    f1 += c * d1 * v2
                    f2 += c * v1 * basis2[1, b, 2 * a2 + e2]
    return f, f1, f2


def _scatter(values, n1, order, basis1, basis2, out):
    """out = B^T values, with B the map from coefficients (n2+1, n1, 4) to f
    at the sample points (ordered v2-major, as HermiteGrid.quadrature)."""
    out[:] = 0.0
    q = 0
    for i2 in range(out.shape[0] - 1):
        for b in range(order):
            for i1 in range(n1):
                for a in range(order):
                    value = values[q]
                    q += 1
                    for a1 in range(2):
                        node1 = i1 + a1
                        if node1 == n1:
                            node1 = 0
                        for a2 in range(2):
                            for e1 in range(2):
                                for e2 in range(2):
                                    out[i2 + a2, node1, e1 + 2 * e2] += (
                                        value * basis1[0, a, 2 * a1 + e1] * basis2[0, b, 2 * a2 + e2])


def _gather(coefficients, n1, order, basis1, basis2, out):
    """out = B coefficients: f at every sample point."""
    q = 0
    for i2 in range(coefficients.shape[0] - 1):
        for b in range(order):
            for i1 in range(n1):
                for a in range(order):
                    out[q] = _evaluate(coefficients, n1, basis1, basis2, i1, a, i2, b)[0]
                    q += 1


def _prolate_observe(coefficients, n1, order, basis1, basis2, cos_th, sin_th, cos_mu, sin_mu, d, rotation, origin,
                     image, to_index, img_origin, upper, surface_offsets, band_offsets,
                     band_rows, out_f, out_h0, out_cos, out_u, out_in, out_out):
    """Fill, for every sample point: f, h0, cos(normal, dx/dlambda), the grey
    level u averaged over ``surface_offsets`` mm along the normal, and on the
    ``band_rows`` points the means over ``band_offsets`` mm inside and outside.
    Means skip missing samples (NaN when none)."""
    band_k = 0
    i1 = a = i2 = b = 0  # patch and local position of q, walked without divisions
    for q in range(out_f.shape[0]):
        f, f1, f2 = _evaluate(coefficients, n1, basis1, basis2, i1, a, i2, b)
        a += 1
        if a == order:
            a = 0
            i1 += 1
            if i1 == n1:
                i1 = 0
                b += 1
                if b == order:
                    b = 0
                    i2 += 1
        e = math.exp(f)
        ch, sh = 0.5 * (e + 1.0 / e), 0.5 * (e - 1.0 / e)
        ct, st, cm, sm = cos_th[q], sin_th[q], cos_mu[q], sin_mu[q]
        x0, rho = d * ch * cm, d * sh * sm
        x1, x2 = rho * ct, rho * st
        j00, j01, j02 = d * sh * cm, d * ch * sm * ct, d * ch * sm * st
        j10, j11, j12 = 0.0, -d * sh * sm * st, d * sh * sm * ct
        j20, j21, j22 = -d * ch * sm, d * sh * cm * ct, d * sh * cm * st
        a0, a1, a2 = f1 * j00 + j10, f1 * j01 + j11, f1 * j02 + j12
        b0, b1, b2 = f2 * j00 + j20, f2 * j01 + j21, f2 * j02 + j22
        m0, m1, m2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
        area = math.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
        along = m0 * j00 + m1 * j01 + m2 * j02
        scale = 0.0
        if area > 0:
            scale = (1.0 if along > 0 else (-1.0 if along < 0 else 0.0)) / area
        m0, m1, m2 = m0 * scale, m1 * scale, m2 * scale
        h0 = d * math.sqrt(sh * sh + sm * sm)
        out_f[q] = f
        out_h0[q] = h0
        out_cos[q] = (m0 * j00 + m1 * j01 + m2 * j02) / h0
        wx = rotation[0, 0] * x0 + rotation[0, 1] * x1 + rotation[0, 2] * x2 + origin[0]
        wy = rotation[1, 0] * x0 + rotation[1, 1] * x1 + rotation[1, 2] * x2 + origin[1]
        wz = rotation[2, 0] * x0 + rotation[2, 1] * x1 + rotation[2, 2] * x2 + origin[2]
        nx = rotation[0, 0] * m0 + rotation[0, 1] * m1 + rotation[0, 2] * m2
        ny = rotation[1, 0] * m0 + rotation[1, 1] * m1 + rotation[1, 2] * m2
        nz = rotation[2, 0] * m0 + rotation[2, 1] * m1 + rotation[2, 2] * m2
        total, count = 0.0, 0
        for s in surface_offsets:
            v = _trilinear(image, to_index, img_origin, upper, wx + s * nx, wy + s * ny, wz + s * nz)
            if not math.isnan(v):
                total += v
                count += 1
        out_u[q] = total / count if count else np.nan
        if band_rows[q]:
            out_in[band_k] = _band_mean(image, to_index, img_origin, upper, band_offsets, -1.0,
                                        wx, wy, wz, nx, ny, nz)
            out_out[band_k] = _band_mean(image, to_index, img_origin, upper, band_offsets, 1.0,
                                         wx, wy, wz, nx, ny, nz)
            band_k += 1


def _band_mean(image, to_index, img_origin, upper, offsets, sign, wx, wy, wz, nx, ny, nz):
    total, count = 0.0, 0
    for s in offsets:
        t = sign * s
        v = _trilinear(image, to_index, img_origin, upper, wx + t * nx, wy + t * ny, wz + t * nz)
        if not math.isnan(v):
            total += v
            count += 1
    return total / count if count else np.nan

if AVAILABLE:
    _trilinear = njit(cache=True, inline="always")(_trilinear)
    _band_mean = njit(cache=True)(_band_mean)
    _evaluate = njit(cache=True, inline="always")(_evaluate)
    prolate_observe = njit(cache=True)(_prolate_observe)
    scatter = njit(cache=True)(_scatter)
    gather = njit(cache=True)(_gather)
else:  # pragma: no cover
    prolate_observe = scatter = gather = None


def basis_tables(grid, order: int) -> tuple[np.ndarray, np.ndarray]:
    """Hermite basis values and first derivatives, in global units, at the
    ``order`` Gauss-Legendre positions of a patch: two arrays
    ``(2, order, 4)`` for v1 and v2 (as :meth:`HermiteGrid._factors`)."""
    from .hermite import hermite_basis

    x, _ = np.polynomial.legendre.leggauss(order)
    t = (x + 1) / 2
    out = []
    for width in (2 * np.pi / grid.n1, (grid.v2_range[1] - grid.v2_range[0]) / grid.n2):
        scale = np.array([1.0, width, 1.0, width])
        out.append(np.stack([hermite_basis(t, 0).T * scale, hermite_basis(t, 1).T * scale / width]))
    return out[0], out[1]
