"""Compiled sampling of beam-space volumes (optional: numba).

The same jobs as :func:`spheroseg._kernels.sample_along` and
:func:`spheroseg._kernels.cavity_sums`, with the same trailing arguments,
for a :class:`spheroseg.beamspace.BeamVolume`: the image arguments are those
of :meth:`BeamVolume.sampling_view` (flat samples, strides, last index,
the probe's rotation and apex, the index step and offset, the convention)
instead of a Cartesian image's.  Each sample is taken in the probe frame
(a point and a normal are rotated once per row; along the normal the probe
frame is still linear) and then costs one ``sqrt`` and two ``atan`` (a
second ``sqrt`` in the "sin" convention) before the trilinear interpolation
in ``[r, e, a]``.  :meth:`BeamVolume.sample` is the reference; the tests
require equal values.
"""

from __future__ import annotations

import math

import numpy as np

try:  # pragma: no cover - exercised when numba is installed
    from numba import njit
except ImportError:  # pragma: no cover
    njit = None

from .volume import INDEX_TOLERANCE as _EDGE

__all__ = ["AVAILABLE", "sample_along", "cavity_sums"]

AVAILABLE = njit is not None


def _sample(values, strides, upper, separations, index_offset, sin_convention, x, y, z):
    """Trilinear sample in ``[r, e, a]`` at the probe-frame point ``(x, y, z)``,
    as :meth:`spheroseg.beamspace.BeamVolume.sample`: NaN outside the
    sector (which lies in z > 0) and on no-data."""
    # the sector lies in z > 0 in both conventions (half-angles under 90
    # degrees), where atan2(u, z) = atan(u / z), the cheaper call
    if not z > 0.0:
        return np.nan
    rho = math.sqrt(x * x + y * y + z * z)
    fr = (rho - index_offset[0]) / separations[0]
    if not (fr >= -_EDGE and fr <= upper[0] + _EDGE):  # off the range: no angles needed
        return np.nan
    inv_z = 1.0 / z
    beta = math.atan(y * inv_z)
    if sin_convention:
        alpha = math.atan(x / math.sqrt(y * y + z * z))
    else:
        alpha = math.atan(x * inv_z)
    fe = (beta - index_offset[1]) / separations[1]
    fa = (alpha - index_offset[2]) / separations[2]
    if not (fe >= -_EDGE and fa >= -_EDGE and fe <= upper[1] + _EDGE and fa <= upper[2] + _EDGE):
        return np.nan
    fr = min(max(fr, 0.0), upper[0])
    fe = min(max(fe, 0.0), upper[1])
    fa = min(max(fa, 0.0), upper[2])
    r0 = min(int(fr), int(upper[0]) - 1)
    e0 = min(int(fe), int(upper[1]) - 1)
    a0 = min(int(fa), int(upper[2]) - 1)
    tr, te, ta = fr - r0, fe - e0, fa - a0
    sr, se, one = np.uint64(strides[0]), np.uint64(strides[1]), np.uint64(1)
    c = np.uint64(r0) * sr + np.uint64(e0) * se + np.uint64(a0)
    c00 = values[c] * (1.0 - ta) + values[c + one] * ta
    c01 = values[c + se] * (1.0 - ta) + values[c + se + one] * ta
    c10 = values[c + sr] * (1.0 - ta) + values[c + sr + one] * ta
    c11 = values[c + sr + se] * (1.0 - ta) + values[c + sr + se + one] * ta
    return (c00 * (1.0 - te) + c01 * te) * (1.0 - tr) + (c10 * (1.0 - te) + c11 * te) * tr


def _to_probe(rotation, apex, x, y, z):
    """``rotation^T ((x, y, z) - apex)``: a world point (or, with a zero apex,
    a direction) in the probe frame."""
    x, y, z = x - apex[0], y - apex[1], z - apex[2]
    return (rotation[0, 0] * x + rotation[1, 0] * y + rotation[2, 0] * z,
            rotation[0, 1] * x + rotation[1, 1] * y + rotation[2, 1] * z,
            rotation[0, 2] * x + rotation[1, 2] * y + rotation[2, 2] * z)


def sample_along(values, strides, upper, rotation, apex, separations, index_offset, sin_convention, world, normal,
                 rows, offsets, exponent, out_mean, out_count):
    """For each ``q`` in ``rows``: the mean (NaN if none) and the number of
    the finite samples at ``world[:, q] + s normal[:, q]`` for ``s`` in
    ``offsets`` (mm), of ``exp(exponent v)`` if ``exponent`` is not 0, as
    :func:`spheroseg._kernels.sample_along`."""
    zero = np.zeros(3)
    for r in range(rows.shape[0]):
        q = rows[r]
        px, py, pz = _to_probe(rotation, apex, world[0, q], world[1, q], world[2, q])
        nx, ny, nz = _to_probe(rotation, zero, normal[0, q], normal[1, q], normal[2, q])
        total, count = 0.0, 0
        for s in offsets:
            v = _sample(values, strides, upper, separations, index_offset, sin_convention,
                        px + s * nx, py + s * ny, pz + s * nz)
            if exponent != 0.0:
                v = math.exp(exponent * v)
            if not math.isnan(v):
                total += v
                count += 1
        out_mean[r] = total / count if count else np.nan
        out_count[r] = count


def cavity_sums(values, strides, upper, rotation, apex, separations, index_offset, sin_convention, f, cos_th, sin_th,
                cos_mu, sin_mu, d, model_rotation, model_origin, rows, fractions, out_sum, out_weight):
    """For each ``q`` in ``rows``, samples at ``lambda = t f[q]`` for ``t`` in
    ``fractions``, weighted by the prolate volume element ``V = h0 h1 h2``:
    the sums of ``V u`` and of ``V`` over the finite samples, as
    :func:`spheroseg._kernels.cavity_sums`."""
    # the model's frame straight into the probe's: R_probe^T R_model, and
    # the model origin in the probe frame
    m = rotation.T @ model_rotation
    o0, o1, o2 = _to_probe(rotation, apex, model_origin[0], model_origin[1], model_origin[2])
    for r in range(rows.shape[0]):
        q = rows[r]
        ct, st, cm, sm = cos_th[q], sin_th[q], cos_mu[q], sin_mu[q]
        total = weight = 0.0
        for t in fractions:
            e = math.exp(t * f[q])
            sh, ch = 0.5 * (e - 1.0 / e), 0.5 * (e + 1.0 / e)
            x0, rho = d * ch * cm, d * sh * sm
            x1, x2 = rho * ct, rho * st
            px = m[0, 0] * x0 + m[0, 1] * x1 + m[0, 2] * x2 + o0
            py = m[1, 0] * x0 + m[1, 1] * x1 + m[1, 2] * x2 + o1
            pz = m[2, 0] * x0 + m[2, 1] * x1 + m[2, 2] * x2 + o2
            v = _sample(values, strides, upper, separations, index_offset, sin_convention, px, py, pz)
            if not math.isnan(v):
                volume = d**3 * (sh * sh + sm * sm) * sh * sm
                total += volume * v
                weight += volume
        out_sum[r] = total
        out_weight[r] = weight


if AVAILABLE:
    _compile = njit(cache=True, error_model="numpy")
    _inline = njit(cache=True, error_model="numpy", inline="always")
    _sample = _inline(_sample)
    _to_probe = _inline(_to_probe)
    sample_along = _compile(sample_along)
    cavity_sums = _compile(cavity_sums)
