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

__all__ = ["AVAILABLE", "prolate_observe"]

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


def _prolate_observe(coefficients, cols, wf, w1, w2, cos_th, sin_th, cos_mu, sin_mu, d, rotation, origin,
                     image, to_index, img_origin, upper, surface_offsets, band_offsets,
                     band_rows, out_f, out_h0, out_cos, out_u, out_in, out_out):
    """Fill, for every sample point: f, h0, cos(normal, dx/dlambda), the grey
    level u averaged over ``surface_offsets`` mm along the normal, and on the
    ``band_rows`` points the means over ``band_offsets`` mm inside and outside.
    Means skip missing samples (NaN when none)."""
    n = cols.shape[0]
    band_k = 0
    for q in range(n):
        f = 0.0
        f1 = 0.0
        f2 = 0.0
        for k in range(cols.shape[1]):
            c = coefficients[cols[q, k]]
            f += wf[q, k] * c
            f1 += w1[q, k] * c
            f2 += w2[q, k] * c
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
        n0, n1, n2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
        area = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        along = n0 * j00 + n1 * j01 + n2 * j02
        scale = 0.0
        if area > 0:
            scale = (1.0 if along > 0 else (-1.0 if along < 0 else 0.0)) / area
        n0, n1, n2 = n0 * scale, n1 * scale, n2 * scale
        h0 = d * math.sqrt(sh * sh + sm * sm)
        out_f[q] = f
        out_h0[q] = h0
        out_cos[q] = (n0 * j00 + n1 * j01 + n2 * j02) / h0
        wx = rotation[0, 0] * x0 + rotation[0, 1] * x1 + rotation[0, 2] * x2 + origin[0]
        wy = rotation[1, 0] * x0 + rotation[1, 1] * x1 + rotation[1, 2] * x2 + origin[1]
        wz = rotation[2, 0] * x0 + rotation[2, 1] * x1 + rotation[2, 2] * x2 + origin[2]
        nx = rotation[0, 0] * n0 + rotation[0, 1] * n1 + rotation[0, 2] * n2
        ny = rotation[1, 0] * n0 + rotation[1, 1] * n1 + rotation[1, 2] * n2
        nz = rotation[2, 0] * n0 + rotation[2, 1] * n1 + rotation[2, 2] * n2
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
    prolate_observe = njit(cache=True)(_prolate_observe)
else:  # pragma: no cover
    prolate_observe = None
