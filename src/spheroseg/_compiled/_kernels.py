"""Compiled hot path of an iteration (optional: numba).

An iteration touches only what the model sets: the 4096 sample points of an
8 x 8-patch surface (8 x 8 Gauss-Legendre points a patch), their normals and
a few trilinear samples along each normal.  In numpy that is some hundred
array operations and sparse products on 4096-long arrays; as plain loops
compiled by numba it is a tenth of that time (docs/benchmarks.md).  numba
compiles the loops from this Python source, so the readable numpy backend
(:class:`spheroseg.backends.NumpyBackend`) stays the reference, and the tests
check each kernel against it and whole segmentations on both to 1e-6.
Without numba the numpy backend runs.

Each kernel does one job and writes into arrays the caller allocated once
per level:

- :func:`prolate_surface`: the surface at the sample points (``f``, the
  scale factor ``h0``, the unit normal in world space, ``A_K``, ...):
  paper eq. 1 (the coordinates) and eqs. 16-17 (tangents, ``A_K``);
- :func:`sample_along`: the mean of trilinear samples along normals;
  :func:`samples_at`: the samples themselves, trilinear or the nearest voxel;
  both, and :func:`cavity_sums`, sample a Cartesian image or a beam-space
  volume, whose arrays :func:`sampler` puts in one form (the sampler is
  picked by the type of its beam parameters, None for a Cartesian image:
  one source, compiled and cached on disk once per geometry);
- :func:`cavity_sums`: samples along the rays inside the cavity, weighted by
  the volume element ``V = h0 h1 h2`` of eq. 19 (the global Chan-Vese mean);
- :func:`gather`, :func:`scatter`: ``B H`` and ``B^T v`` for the Hermite
  basis ``B`` at the sample points, from two small tables (the points are a
  tensor product of ``order`` positions per patch);
- :func:`normal_displacement`: the region force of eq. 22 as a ``v0``
  displacement;
- :func:`descend`: a whole level of the descent, the kernels above called
  in the order of an iteration, repeated until the surface stops moving.

The kernels over the sample points (not :func:`scatter`, which sums patches
into shared nodes, nor :func:`samples_at`, run once a segmentation) are
``prange`` loops over points or patches: each
iteration writes its own outputs and sums nothing across iterations, so a
result is the same to the last bit on any number of threads (numba's count,
the ``threads`` option).  Scratch arrays allocated in such a loop are
hoisted by numba to the start of each thread's share of it.

Equation numbers are those of Duan et al., Proc. SPIE 6144, 61444A (2006).

Only the prolate spheroidal system (the default) has a surface kernel.
"""

from __future__ import annotations

import math
import warnings
from typing import NamedTuple

import numpy as np

try:  # pragma: no cover - exercised when numba is installed
    from numba import njit, prange
    from numba.core import types
    from numba.core.errors import NumbaIRAssumptionWarning
    from numba.extending import overload

    # numba's internal check of the IR, on inlining _sample_at's choice of
    # sampler into a loop, names a variable it expected in scope; the code
    # compiled is right (the tests hold it equal to the reference)
    warnings.filterwarnings("ignore", message=".*_sample_at_typed", category=NumbaIRAssumptionWarning)
except ImportError:  # pragma: no cover
    njit, prange = None, range

from . import INDEX_TOLERANCE as _EDGE

__all__ = ["AVAILABLE", "NO_BEAM", "sampler", "prolate_surface", "sample_along", "samples_at", "cavity_sums",
           "gather", "scatter", "normal_displacement", "csr_product", "descend"]

AVAILABLE = njit is not None
_ZERO = np.zeros(3)
#: the ``beam`` argument of a Cartesian image (:func:`sampler`)
NO_BEAM = None


def _sample(image, strides, upper, fi, fj, fk):
    """Trilinear sample of the flat image at the continuous voxel index
    ``(fi, fj, fk)`` (x, y, z), as :meth:`spheroseg.Volume.sample` (the
    reference; the arrays are those of :meth:`~spheroseg.Volume.sampling_view`): NaN
    outside the image and, through the image's NaN voxels, on no-data."""
    # (plain comparisons: numba compiles a chained a <= x <= b to slower code)
    if not (fi >= -_EDGE and fj >= -_EDGE and fk >= -_EDGE
            and fi <= upper[0] + _EDGE and fj <= upper[1] + _EDGE and fk <= upper[2] + _EDGE):
        return np.nan
    fi = min(max(fi, 0.0), upper[0])
    fj = min(max(fj, 0.0), upper[1])
    fk = min(max(fk, 0.0), upper[2])
    # the cell's lower corner; the last voxel belongs to the cell before it
    i0 = min(int(fi), int(upper[0]) - 1)
    j0 = min(int(fj), int(upper[1]) - 1)
    k0 = min(int(fk), int(upper[2]) - 1)
    ti, tj, tk = fi - i0, fj - j0, fk - k0
    # unsigned offsets: numba then skips its negative-index wraparound
    sy, sz, one = np.uint64(strides[1]), np.uint64(strides[2]), np.uint64(1)
    c = np.uint64(i0) + np.uint64(j0) * sy + np.uint64(k0) * sz
    # weights times float32 values: the products are double, as in numpy
    c00 = image[c] * (1.0 - ti) + image[c + one] * ti
    c01 = image[c + sy] * (1.0 - ti) + image[c + sy + one] * ti
    c10 = image[c + sz] * (1.0 - ti) + image[c + sz + one] * ti
    c11 = image[c + sy + sz] * (1.0 - ti) + image[c + sy + sz + one] * ti
    return (c00 * (1.0 - tj) + c01 * tj) * (1.0 - tk) + (c10 * (1.0 - tj) + c11 * tj) * tk


def _beam_sample(image, strides, upper, beam, x, y, z):
    """Trilinear sample of a beam-space volume at the probe-frame point
    ``(x, y, z)``, as :meth:`spheroseg.beamspace.BeamVolume.sample` (the
    reference): the point in ``(r, e, a)`` index (one ``sqrt`` and two
    ``atan``, a second ``sqrt`` in the "sin" convention), then :func:`_sample`
    on the samples ``a`` fastest; NaN outside the sector and on no-data.
    ``beam``: the separations and the index offset in ``(r, e, a)``, then 1
    for the "sin" convention (:func:`sampler`)."""
    # the sector lies in z > 0 in both conventions (half-angles under 90
    # degrees), where atan2(u, z) = atan(u / z), the cheaper call
    if not z > 0.0:
        return np.nan
    rho = math.sqrt(x * x + y * y + z * z)
    fr = (rho - beam[3]) / beam[0]
    if not (fr >= -_EDGE and fr <= upper[2] + _EDGE):  # off the range: no angles needed
        return np.nan
    inv_z = 1.0 / z
    fe = (math.atan(y * inv_z) - beam[4]) / beam[1]
    if beam[6] != 0.0:
        alpha = math.atan(x / math.sqrt(y * y + z * z))
    else:
        alpha = math.atan(x * inv_z)
    fa = (alpha - beam[5]) / beam[2]
    return _sample(image, strides, upper, fa, fe, fr)


def _sample_at(image, strides, upper, beam, x, y, z):
    """The image at ``(x, y, z)`` of the sampler's frame: a Cartesian image's
    continuous voxel index (``beam`` None) or a beam-space volume's probe
    frame (:func:`sampler`).  Compiled, the choice is made by ``beam``'s
    type (:func:`_sample_at_typed`): a Cartesian kernel holds no beam code."""
    if beam is None:
        return _sample(image, strides, upper, x, y, z)
    return _beam_sample(image, strides, upper, beam, x, y, z)


def _sample_at_typed(image, strides, upper, beam, x, y, z):
    """:func:`_sample_at` for numba: the sampler of ``beam``'s type."""
    if isinstance(beam, types.NoneType):
        def cartesian(image, strides, upper, beam, x, y, z):
            return _sample(image, strides, upper, x, y, z)
        return cartesian

    def beam_space(image, strides, upper, beam, x, y, z):
        return _beam_sample(image, strides, upper, beam, x, y, z)
    return beam_space


def sampler(view) -> tuple:
    """The image arguments of :func:`sample_along` and :func:`cavity_sums`
    (``image, strides, upper, to_frame, frame_origin, beam``) for a
    :meth:`spheroseg.Volume.sampling_view` or a
    :meth:`spheroseg.beamspace.BeamVolume.sampling_view`.

    A world point ``w`` is sampled at ``to_frame @ (w - frame_origin)``: a
    Cartesian image's voxel index (``beam`` None), or a beam-space volume's
    probe frame (``to_frame`` the probe's rotation transposed, the origin its
    apex; ``beam`` its separations, index offset and convention), whose
    samples are then read ``a`` fastest, as a Cartesian image's ``x``."""
    if len(view) == 5:
        return (*view, NO_BEAM)
    values, strides, upper, rotation, apex, separations, index_offset, sin_convention = view
    beam = np.array([*separations, *index_offset, 1.0 if sin_convention else 0.0])
    return (values, np.array([1, strides[1], strides[0]], dtype=np.int64), np.ascontiguousarray(upper[::-1]),
            np.ascontiguousarray(rotation.T), np.asarray(apex, dtype=float), beam)


def _nearest(image, strides, upper, fi, fj, fk):
    """The voxel nearest the continuous index ``(fi, fj, fk)``, as
    :meth:`spheroseg.Volume.sample` with ``order=0`` (halves rounded to even,
    as ``np.rint``): NaN outside the image and on no-data."""
    if not (fi >= -_EDGE and fj >= -_EDGE and fk >= -_EDGE
            and fi <= upper[0] + _EDGE and fj <= upper[1] + _EDGE and fk <= upper[2] + _EDGE):
        return np.nan
    i = np.rint(min(max(fi, 0.0), upper[0]))
    j = np.rint(min(max(fj, 0.0), upper[1]))
    k = np.rint(min(max(fk, 0.0), upper[2]))
    return float(image[np.uint64(i) + np.uint64(j) * np.uint64(strides[1]) + np.uint64(k) * np.uint64(strides[2])])


def _index(matrix, offset, x, y, z):
    """``matrix @ ((x, y, z) - offset)``: a world point (or, with a zero
    offset, a direction) to voxel index, with the image's ``to_index`` and
    origin."""
    x, y, z = x - offset[0], y - offset[1], z - offset[2]
    return (matrix[0, 0] * x + matrix[0, 1] * y + matrix[0, 2] * z,
            matrix[1, 0] * x + matrix[1, 1] * y + matrix[1, 2] * z,
            matrix[2, 0] * x + matrix[2, 1] * y + matrix[2, 2] * z)


def _patch(coefficients, i1, i2, out):
    """The 16 coefficients of patch ``(i1, i2)`` from ``(n2+1, n1, 4)`` as
    ``out[2 a1 + e1, 2 a2 + e2]`` (node ``a`` and derivative ``e`` along v1,
    v2), so that ``f = sum_jm basis1[a, j] out[j, m] basis2[b, m]``."""
    n1 = coefficients.shape[1]
    for a1 in range(2):
        node1 = i1 + a1 if i1 + a1 < n1 else 0  # theta is periodic
        for e1 in range(2):
            for a2 in range(2):
                for e2 in range(2):
                    out[2 * a1 + e1, 2 * a2 + e2] = coefficients[i2 + a2, node1, e1 + 2 * e2]


def _contract(patch, basis, out):
    """``out[j] = sum_m patch[j, m] basis[m]``: the patch on one line of v2."""
    for j in range(4):
        out[j] = patch[j, 0] * basis[0] + patch[j, 1] * basis[1] + patch[j, 2] * basis[2] + patch[j, 3] * basis[3]


def _dot4(basis, line):
    return basis[0] * line[0] + basis[1] * line[1] + basis[2] * line[2] + basis[3] * line[3]


# The sample points are a tensor product of ``order`` positions a patch in
# each direction, so the kernels below walk patch by patch, contract the
# 4 x 4 coefficients with the v2 table once per line of points and with the
# v1 table at each point (4 multiply-adds a point instead of 16).  The
# sample at local position (a, b) of patch (i1, i2) is number
# ((i2 order + b) n1 + i1) order + a (v2-major, as HermiteGrid.quadrature).


def gather(coefficients, order, basis1, basis2, out):
    """``out[k] = B coefficients[k]``: each field (coefficients
    ``(fields, n2+1, n1, 4)``) at every sample point."""
    n2, n1 = coefficients.shape[1] - 1, coefficients.shape[2]
    for i in prange(out.shape[0] * n2 * n1):  # the patches write disjoint points
        k, i2, i1 = i // (n2 * n1), i // n1 % n2, i % n1
        patch, line = np.empty((4, 4)), np.empty(4)
        _patch(coefficients[k], i1, i2, patch)
        for b in range(order):
            _contract(patch, basis2[0, b], line)
            q = ((i2 * order + b) * n1 + i1) * order
            for a in range(order):
                out[k, q + a] = _dot4(basis1[0, a], line)


def scatter(values, order, basis1, basis2, out):
    """``out[k] = B^T values[k]`` on coefficients ``(fields, n2+1, n1, 4)``."""
    n2, n1 = out.shape[1] - 1, out.shape[2]
    patch, line = np.empty((4, 4)), np.empty(4)
    out[:] = 0.0
    for k in range(values.shape[0]):
        for i2 in range(n2):
            for i1 in range(n1):
                patch[:] = 0.0
                for b in range(order):
                    q = ((i2 * order + b) * n1 + i1) * order
                    line[:] = 0.0
                    for a in range(order):
                        for j in range(4):
                            line[j] += basis1[0, a, j] * values[k, q + a]
                    for j in range(4):
                        for m in range(4):
                            patch[j, m] += line[j] * basis2[0, b, m]
                for a1 in range(2):
                    node1 = i1 + a1 if i1 + a1 < n1 else 0
                    for e1 in range(2):
                        for a2 in range(2):
                            for e2 in range(2):
                                out[k, i2 + a2, node1, e1 + 2 * e2] += patch[2 * a1 + e1, 2 * a2 + e2]


def prolate_surface(coefficients, order, basis1, basis2, cos_th, sin_th, cos_mu, sin_mu, d, rotation, origin,
                    out_f, out_h0, out_cos, out_area, out_world, out_normal):
    """The surface ``lambda = f(theta, mu)`` at every sample point (eq. 1 for
    the point, eqs. 16-17 for the tangents and ``A_K``): ``f``, the
    scale factor ``h0`` (mm per unit lambda), the cosine between the outward
    normal and ``dx/dlambda``, ``A_K = |x_theta x x_mu|``, the world point
    and the unit outward normal (world), both ``(3, n)``, as
    :meth:`SampledSurface.geometry`."""
    n2, n1 = coefficients.shape[0] - 1, coefficients.shape[1]
    for i in prange(n2 * n1):  # the patches write disjoint points
        i2, i1 = i // n1, i % n1
        patch, line, line_mu = np.empty((4, 4)), np.empty(4), np.empty(4)
        _patch(coefficients, i1, i2, patch)
        for b in range(order):
            _contract(patch, basis2[0, b], line)
            _contract(patch, basis2[1, b], line_mu)
            q = ((i2 * order + b) * n1 + i1) * order
            for a in range(order):
                out_f[q + a] = _dot4(basis1[0, a], line)
                out_h0[q + a] = _dot4(basis1[1, a], line)  # df/dtheta until the loop below
                out_cos[q + a] = _dot4(basis1[0, a], line_mu)  # df/dmu until the loop below
                out_area[q + a] = math.exp(out_f[q + a])  # e^lambda until the loop below
    # this loop calls no function and writes contiguous arrays: it runs on
    # SIMD lanes (with the world points and normals as (3, n) it does,
    # as (n, 3) or with exp inside it does not: four times slower)
    r00, r01, r02 = rotation[0, 0], rotation[0, 1], rotation[0, 2]
    r10, r11, r12 = rotation[1, 0], rotation[1, 1], rotation[1, 2]
    r20, r21, r22 = rotation[2, 0], rotation[2, 1], rotation[2, 2]
    for q in prange(out_f.shape[0]):
        e, f1, f2 = out_area[q], out_h0[q], out_cos[q]
        ch, sh = 0.5 * (e + 1.0 / e), 0.5 * (e - 1.0 / e)
        ct, st, cm, sm = cos_th[q], sin_th[q], cos_mu[q], sin_mu[q]
        x0, rho = d * ch * cm, d * sh * sm
        x1, x2 = rho * ct, rho * st
        # columns of the Jacobian: dx/dlambda, dx/dtheta, dx/dmu
        j00, j01, j02 = d * sh * cm, d * ch * sm * ct, d * ch * sm * st
        j10, j11, j12 = 0.0, -d * sh * sm * st, d * sh * sm * ct
        j20, j21, j22 = -d * ch * sm, d * sh * cm * ct, d * sh * cm * st
        # tangents x_theta = f1 J0 + J1, x_mu = f2 J0 + J2 and their cross product
        a0, a1, a2 = f1 * j00 + j10, f1 * j01 + j11, f1 * j02 + j12
        b0, b1, b2 = f2 * j00 + j20, f2 * j01 + j21, f2 * j02 + j22
        m0, m1, m2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
        area = math.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
        # outwards: along +dx/dlambda
        along = m0 * j00 + m1 * j01 + m2 * j02
        sign = (1.0 if along > 0 else 0.0) - (1.0 if along < 0 else 0.0)
        scale = sign / area if area > 0 else 0.0
        m0, m1, m2 = m0 * scale, m1 * scale, m2 * scale
        h0 = d * math.sqrt(sh * sh + sm * sm)
        out_h0[q] = h0
        out_cos[q] = (m0 * j00 + m1 * j01 + m2 * j02) / h0
        out_area[q] = area
        out_world[0, q] = r00 * x0 + r01 * x1 + r02 * x2 + origin[0]
        out_world[1, q] = r10 * x0 + r11 * x1 + r12 * x2 + origin[1]
        out_world[2, q] = r20 * x0 + r21 * x1 + r22 * x2 + origin[2]
        out_normal[0, q] = r00 * m0 + r01 * m1 + r02 * m2
        out_normal[1, q] = r10 * m0 + r11 * m1 + r12 * m2
        out_normal[2, q] = r20 * m0 + r21 * m1 + r22 * m2


def sample_along(image, strides, upper, to_index, image_origin, beam, world, normal, rows, offsets, exponent,
                 out_mean, out_count):
    """For each ``q`` in ``rows``: the mean (NaN if none) and the number of the
    finite samples at ``world[:, q] + s normal[:, q]`` for ``s`` in
    ``offsets`` (mm); with a non-zero ``exponent`` ``a``, of ``exp(a v)`` for
    each sample ``v`` (log compression undone).  The image arguments are
    :func:`sampler`'s, of a Cartesian or a beam-space volume."""
    if offsets.shape[0] == 1:
        # the surface's own samples, every iteration: a parallel loop whose
        # body has no inner loop runs on SIMD lanes (a loop an offset, the
        # sums carried in the outputs, would cost more in launches than it
        # saves on the few hundred rows of the global means' shell)
        offset = offsets[0]
        for r in prange(rows.shape[0]):
            q = rows[r]
            pi, pj, pk = _index(to_index, image_origin, world[0, q], world[1, q], world[2, q])
            ni, nj, nk = _index(to_index, _ZERO, normal[0, q], normal[1, q], normal[2, q])
            v = _sample_at(image, strides, upper, beam, pi + offset * ni, pj + offset * nj, pk + offset * nk)
            if exponent != 0.0:
                v = math.exp(exponent * v)
            out_mean[r] = v  # NaN: no finite sample
            out_count[r] = not math.isnan(v)
        return
    for r in prange(rows.shape[0]):
        q = rows[r]
        # the point and the normal in the sampler's frame: the samples are a line there
        pi, pj, pk = _index(to_index, image_origin, world[0, q], world[1, q], world[2, q])
        ni, nj, nk = _index(to_index, _ZERO, normal[0, q], normal[1, q], normal[2, q])
        total, count = 0.0, 0
        for s in offsets:
            v = _sample_at(image, strides, upper, beam, pi + s * ni, pj + s * nj, pk + s * nk)
            if exponent != 0.0:
                v = math.exp(exponent * v)
            if not math.isnan(v):
                total += v
                count += 1
        out_mean[r] = total / count if count else np.nan
        out_count[r] = count


def samples_at(image, strides, upper, to_index, image_origin, beam, world, normal, rows, offsets, nearest, out):
    """``out[r, k]``: the sample at ``world[:, q] + offsets[k] normal[:, q]``
    for ``q = rows[r]``, as :meth:`spheroseg.Volume.sample` (the reference):
    trilinear, or with ``nearest`` the nearest voxel (a Cartesian image's
    only); NaN off the data.  The image arguments are :func:`sampler`'s."""
    for r in range(rows.shape[0]):
        q = rows[r]
        pi, pj, pk = _index(to_index, image_origin, world[0, q], world[1, q], world[2, q])
        ni, nj, nk = _index(to_index, _ZERO, normal[0, q], normal[1, q], normal[2, q])
        for k in range(offsets.shape[0]):
            s = offsets[k]
            if nearest:
                out[r, k] = _nearest(image, strides, upper, pi + s * ni, pj + s * nj, pk + s * nk)
            else:
                out[r, k] = _sample_at(image, strides, upper, beam, pi + s * ni, pj + s * nj, pk + s * nk)


def cavity_sums(image, strides, upper, to_index, image_origin, beam, f, cos_th, sin_th, cos_mu, sin_mu, d, rotation,
                origin, rows, fractions, out_sum, out_weight):
    """For each ``q`` in ``rows``, samples at ``lambda = t f[q]`` for ``t`` in
    ``fractions``, weighted by the volume element ``V = h0 h1 h2``: the sums
    of ``V u`` and of ``V`` over the finite samples.  The image arguments
    are :func:`sampler`'s."""
    for r in prange(rows.shape[0]):
        q = rows[r]
        ct, st, cm, sm = cos_th[q], sin_th[q], cos_mu[q], sin_mu[q]
        total = weight = 0.0
        for t in fractions:
            e = math.exp(t * f[q])
            sh, ch = 0.5 * (e - 1.0 / e), 0.5 * (e + 1.0 / e)
            x0, rho = d * ch * cm, d * sh * sm
            x1, x2 = rho * ct, rho * st
            wx = rotation[0, 0] * x0 + rotation[0, 1] * x1 + rotation[0, 2] * x2 + origin[0]
            wy = rotation[1, 0] * x0 + rotation[1, 1] * x1 + rotation[1, 2] * x2 + origin[1]
            wz = rotation[2, 0] * x0 + rotation[2, 1] * x1 + rotation[2, 2] * x2 + origin[2]
            fi, fj, fk = _index(to_index, image_origin, wx, wy, wz)
            v = _sample_at(image, strides, upper, beam, fi, fj, fk)
            if not math.isnan(v):
                volume = d**3 * (sh * sh + sm * sm) * sh * sm
                total += volume * v
                weight += volume
        out_sum[r] = total
        out_weight[r] = weight


def csr_product(indptr, indices, data, x, out):
    """``out = A x`` for a CSR matrix ``A`` (``indptr, indices, data``), each
    row summed in the order of scipy's ``csr_matvec``, so equal to
    ``A @ x`` to the last bit; without scipy's per-call dispatch, which
    costs some ten times the product of the few-hundred-entry constraint
    matrices."""
    for i in range(out.shape[0]):
        total = 0.0
        for k in range(indptr[i], indptr[i + 1]):
            total += data[k] * x[indices[k]]
        out[i] = total


def normal_displacement(u, c_in, c_out, scale, clip, h0, cos, h0_floor, min_cos, step, weights, out):
    """``out = weights * dv0``: the region force of eq. 22 as a displacement
    in ``v0`` per sample point, as :meth:`spheroseg.backends.NumpyBackend.displacement`
    (the reference, through :func:`spheroseg.energy.normal_speed`)."""
    for q in range(u.shape[0]):
        r = (c_out[q] - c_in[q]) * (2.0 * u[q] - c_in[q] - c_out[q]) / scale
        if math.isfinite(r):
            speed = -min(max(r, -clip), clip)
        elif math.isfinite(u[q]):
            speed = 0.0
        else:  # off the data: pulled back in
            speed = -1.0
        normal_to_v0 = max(h0[q] * max(cos[q], min_cos), h0_floor)
        out[q] = weights[q] * step * speed / normal_to_v0


#: the data terms whose force :func:`descend` computes itself
FIXED_MEANS, GLOBAL_MEANS, LOCAL_MEANS = 0, 1, 2


class LoopSurface(NamedTuple):
    """What :func:`descend` reads of the model, fixed for a grid and pose:
    the constraints ``A`` and ``A^T`` as CSR ``(indptr, indices, data)``,
    the coefficients' shape, the quadrature order and basis tables (of the
    sample points and of the band rows), ``(cos theta, sin theta, cos mu,
    sin mu)`` at the samples, the focal length, the pose, the quadrature
    weights and the domain's area, the least cosine of the ``v0``
    conversion, all rows and the band rows with their weights, and
    ``M^-1``."""

    constraints: tuple
    constraints_t: tuple
    grid_shape: tuple
    order: int
    tables_1: np.ndarray
    tables_2: np.ndarray
    band_order: int
    band_tables_1: np.ndarray
    band_tables_2: np.ndarray
    trig: tuple
    focal_length: float
    rotation: np.ndarray
    origin: np.ndarray
    weights: np.ndarray
    area: float
    min_cos: float
    all_rows: np.ndarray
    band_rows: np.ndarray
    band_weights: np.ndarray
    mass_inverse: np.ndarray


class LoopPrior(NamedTuple):
    """The least-squares problem's other rows: ``a T`` as CSR, the system's
    (symmetric) inverse, the landmark rows ``L``, their ``v0`` and ``h0``,
    and ``L^T Omega``."""

    smoothing: tuple
    inverse: np.ndarray
    landmark_rows: np.ndarray
    landmark_v0: np.ndarray
    landmark_h0: np.ndarray
    landmark_pull: np.ndarray


class LoopTerm(NamedTuple):
    """The data term as :func:`descend` computes it: its ``kind``
    (:data:`FIXED_MEANS`, :data:`GLOBAL_MEANS`, :data:`LOCAL_MEANS`), the
    fixed means at every sample and their scale, the least scale, the
    cavity fractions, the shell's and the bands' offsets (mm), and the
    local means' polarity and boundary (:class:`spheroseg.dataterms.LocalMeans`)."""

    kind: int
    fixed_in: np.ndarray
    fixed_out: np.ndarray
    fixed_scale: float
    min_scale: float
    fractions: np.ndarray
    shell_offsets: np.ndarray
    band_offsets: np.ndarray
    polarity: float = 1.0
    boundary_nepers: float = np.inf


class LoopObservation(NamedTuple):
    """The arrays an observation fills, as :class:`spheroseg.backends.Observation`."""

    f: np.ndarray
    h0: np.ndarray
    cos: np.ndarray
    area: np.ndarray
    world: np.ndarray
    normal: np.ndarray
    u: np.ndarray
    inside: np.ndarray
    outside: np.ndarray


#: the descent's state, read and written by :func:`descend` (one record):
#: the step and the level's first one (mm), the scale-factor floor (< 0:
#: not set yet), whether the step adapts (0 or 1), the previous motion's
#: weighted sum of squares (< 0: none), the last RMS motion (mm), the
#: iterations run, the global means measured last and the force's scale
LOOP_STATE = np.dtype([("step", float), ("initial_step", float), ("h0_floor", float), ("adaptive", float),
                       ("previous_squared", float), ("motion", float), ("iterations", float), ("c_in", float),
                       ("c_out", float), ("scale", float)])
#: how :func:`descend` ended: at its iteration cap, below the tolerance, or
#: with no image data around the surface (the local means)
AT_CAP, CONVERGED, NO_BAND_DATA = 0, 1, 2

# The loop's own arithmetic is written as plain loops: numba's np.dot, @,
# nanmedian, array expressions and slice assignments (their shape checks'
# messages) nearly double the loop's compilation.  Its sums are not BLAS's nor numpy's
# pairwise ones: a level in the loop equals its iterations to rounding.


def _product(matrix, x, out):
    """``out = A x`` for ``matrix`` ``(indptr, indices, data)``."""
    csr_product(matrix[0], matrix[1], matrix[2], x, out)


def _symmetric_product(matrix, x, out):
    """``out = A x`` for a symmetric ``A``, as ``A^T x``: a row of ``A``
    times ``x[j]`` added to ``out`` for each ``j`` (contiguous, on SIMD
    lanes; a row-by-row dot product is a chain of dependent additions)."""
    out[:] = 0.0
    for j in range(x.shape[0]):
        xj = x[j]
        for i in range(out.shape[0]):
            out[i] += matrix[j, i] * xj


def _dot(a, b):
    total = 0.0
    for i in range(a.shape[0]):
        total += a[i] * b[i]
    return total


def _median(values, scratch):
    """The median of ``values`` (finite), as numpy's: the middle value or
    the mean of the two middle ones (a selection in ``scratch``)."""
    n = values.shape[0]
    for i in range(n):
        scratch[i] = values[i]
    high = _select(scratch[:n], n // 2)
    if n % 2:
        return high
    low = scratch[0]  # the largest of the lower half, which the selection left below
    for i in range(1, n // 2):
        low = max(low, scratch[i])
    return (low + high) / 2


def _select(a, k):
    """The ``k``-th smallest of ``a`` (reordered in place: the ``k``
    smaller ones before it), by Hoare's selection."""
    lo, hi = 0, a.shape[0] - 1
    while lo < hi:
        pivot = a[(lo + hi) // 2]
        i, j = lo, hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while a[j] > pivot:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    return a[k]


def _global_means(image, f, area_element, world, normal, trig, focal_length, rotation, origin, weights, band_rows,
                  fractions, shell_offsets, scratch):
    """:meth:`spheroseg.backends.NumpyBackend.region_means`: the cavity's
    volume-weighted mean and the shell's area-weighted mean (NaN without
    weight); ``scratch``: three rows at least as long as the band rows."""
    nb = band_rows.shape[0]
    cavity, element, shell = scratch[0], scratch[1], scratch[2]
    count = np.empty(nb, np.int64)
    cavity_sums(*image, f, *trig, focal_length, rotation, origin, band_rows, fractions, cavity, element)
    sample_along(*image, world, normal, band_rows, shell_offsets, 0.0, shell, count)
    in_sum = in_weight = out_sum = out_weight = 0.0
    for r in range(nb):
        q = band_rows[r]
        w_in = weights[q] * f[q]
        in_sum += w_in * cavity[r]
        in_weight += w_in * element[r]
        w_out = weights[q] * area_element[q] * count[r]
        if count[r]:  # no sample, no weight
            out_sum += w_out * shell[r]
        out_weight += w_out
    return (in_sum / in_weight if in_weight > 0 else np.nan), (out_sum / out_weight if out_weight > 0 else np.nan)


def _band_means(inside, outside, surface, out_c_in, out_c_out):
    """:meth:`spheroseg.backends.NumpyBackend.band_means`: the band means
    (a missing one replaced by its band's mean) projected on the Hermite
    space, at every sample point; False when a band has no finite mean."""
    band_weights, mass_inverse = surface.band_weights, surface.mass_inverse
    nb, n_parameters = inside.shape[0], mass_inverse.shape[0]
    fields = np.empty((2, nb))
    for k in range(2):
        band = inside if k == 0 else outside
        total, finite = 0.0, 0
        for r in range(nb):
            if math.isfinite(band[r]):
                total += band[r]
                finite += 1
        if finite == 0:
            return False
        for r in range(nb):
            fields[k, r] = band_weights[r] * (band[r] if math.isfinite(band[r]) else total / finite)
    coefficients = np.empty((2,) + surface.grid_shape)
    scatter(fields, surface.band_order, surface.band_tables_1, surface.band_tables_2, coefficients)
    rhs, smooth = np.empty(n_parameters), np.empty(n_parameters)
    for k in range(2):  # M^-1 B_b^T W_b m, then its coefficients
        _product(surface.constraints_t, coefficients[k].ravel(), rhs)
        _symmetric_product(mass_inverse, rhs, smooth)
        _product(surface.constraints, smooth, coefficients[k].ravel())
    means = np.empty((2, out_c_in.shape[0]))
    gather(coefficients, surface.order, surface.tables_1, surface.tables_2, means)
    for q in range(means.shape[1]):
        out_c_in[q], out_c_out[q] = means[0, q], means[1, q]
    return True


def _interface_level(dark, bright, nepers):
    """The level loop's twin of :func:`spheroseg.descent.dataterms.interface_level`
    (the definition; the tests hold the loop equal to it) on scalars."""
    return bright + nepers * (np.logaddexp(dark / nepers, bright / nepers) - bright / nepers - np.log(2.0))


def _local_force(band_in, band_out, polarity, boundary_nepers, out_contrast, out_c_in, out_c_out):
    """:meth:`spheroseg.dataterms.LocalMeans.force` from its band means: the
    contrast of the right polarity and the force's means."""
    finite = math.isfinite(boundary_nepers)
    for q in range(band_in.shape[0]):
        contrast = max(polarity * (band_out[q] - band_in[q]), 0.0)
        out_contrast[q] = contrast
        force_in, force_out = band_in[q], band_in[q] + polarity * contrast
        if finite:
            dark, bright = (force_in, force_out) if polarity > 0 else (force_out, force_in)
            level = _interface_level(dark, bright, boundary_nepers)
            force_in, force_out = level - polarity * contrast / 2, level + polarity * contrast / 2
        out_c_in[q], out_c_out[q] = force_in, force_out


def descend(p, reference, max_iterations, tol, state, prior, surface, image, term, obs, means, previous):
    """A whole level of the descent in one call: the data term's force and
    :meth:`spheroseg.descent.Descent.iterate`, repeated until the RMS motion
    falls below ``tol`` (mm) or ``max_iterations`` have run.

    From Python an iteration is a dozen kernel calls and their numpy glue;
    here it is their arithmetic alone.  The reference is that method with
    the data terms of :mod:`spheroseg.dataterms`, whose steps this takes in
    their order; the tests require equal iterations and parameters equal
    to rounding.

    Parameters
    ----------
    p : array
        The parameters (updated in place).
    reference : array
        The prior's shape.
    state : array of :data:`LOOP_STATE`, one record
        The descent's state, read and updated.
    prior : LoopPrior
    surface : LoopSurface
    image : tuple
        :func:`sampler` of :meth:`spheroseg.Volume.sampling_view`.
    term : LoopTerm
    obs : LoopObservation
        Filled with the last observation.
    means : array (4, n)
        The force's ``c_in``, the band means' ``c_out``, the force's
        ``c_out`` and the band means' ``c_in``, as the last iteration saw
        them.
    previous : array (n,)
        The previous motion at the sample points (read and updated).

    Returns
    -------
    int
        :data:`CONVERGED`, :data:`AT_CAP` or :data:`NO_BAND_DATA`.
    """
    s = state[0]
    constraints, constraints_t, grid_shape, order = surface.constraints, surface.constraints_t, surface.grid_shape, \
        surface.order
    tables_1, tables_2, trig, focal_length = surface.tables_1, surface.tables_2, surface.trig, surface.focal_length
    rotation, origin, weights, area = surface.rotation, surface.origin, surface.weights, surface.area
    min_cos, all_rows, band_rows = surface.min_cos, surface.all_rows, surface.band_rows
    lm_basis, lm_v0, lm_h0, lm_pull = prior.landmark_rows, prior.landmark_v0, prior.landmark_h0, prior.landmark_pull
    kind, min_scale, fractions = term.kind, term.min_scale, term.fractions
    shell_offsets, band_offsets = term.shell_offsets, term.band_offsets
    f, h0, cos, area_element, world, normal, u = obs.f, obs.h0, obs.cos, obs.area, obs.world, obs.normal, obs.u
    inside, outside = obs.inside, obs.outside
    c_in, band_out, c_out, band_in = means[0], means[1], means[2], means[3]
    n, n_parameters, n_landmarks = f.shape[0], p.shape[0], lm_v0.shape[0]
    coefficients = np.empty((1,) + grid_shape)  # the surface's, then the step's
    counts, band_counts = np.empty(n, np.int64), np.empty(band_rows.shape[0], np.int64)
    surface_offset, inner_offsets = np.zeros(1), np.empty(band_offsets.shape[0])
    for k in range(band_offsets.shape[0]):
        inner_offsets[k] = -band_offsets[k]
    displacement, motion, scratch = np.empty((1, n)), np.empty((1, n)), np.empty((3, n))
    rhs, projected, dp = np.empty(n_parameters), np.empty(n_parameters), np.empty(n_parameters)
    for _ in range(max_iterations):
        # the observation (CompiledBackend.observe)
        _product(constraints, p, coefficients[0].ravel())
        prolate_surface(coefficients[0], order, tables_1, tables_2, *trig, focal_length, rotation, origin, f, h0,
                        cos, area_element, world, normal)
        sample_along(*image, world, normal, all_rows, surface_offset, 0.0, u, counts)
        # the force's means (the data term's force)
        if kind == GLOBAL_MEANS:
            measured_in, measured_out = _global_means(image, f, area_element, world, normal, trig, focal_length,
                                                      rotation, origin, weights, band_rows, fractions, shell_offsets,
                                                      scratch)
            s.c_in, s.c_out = measured_in, measured_out
            measured_out = max(measured_out, measured_in)  # blood dark: no force on the wrong polarity
            for q in range(n):
                c_in[q], c_out[q] = measured_in, measured_out
            scale = max((measured_out - measured_in) ** 2, min_scale)
        elif kind == LOCAL_MEANS:
            sample_along(*image, world, normal, band_rows, inner_offsets, 0.0, inside, band_counts)
            sample_along(*image, world, normal, band_rows, band_offsets, 0.0, outside, band_counts)
            if not _band_means(inside, outside, surface, band_in, band_out):
                return NO_BAND_DATA
            contrast = scratch[0]
            _local_force(band_in, band_out, term.polarity, term.boundary_nepers, contrast, c_in, c_out)
            scale = max(_median(contrast, scratch[1]) ** 2, min_scale)
        else:
            for q in range(n):
                c_in[q], c_out[q] = term.fixed_in[q], term.fixed_out[q]
            scale = term.fixed_scale
        s.scale = scale
        # the step (Descent.iterate)
        if s.h0_floor < 0:  # fixed per level, on its first observation
            s.h0_floor = 0.3 * _median(h0, scratch[1])
        step = s.step
        normal_displacement(u, c_in, c_out, scale, 1.0, h0, cos, s.h0_floor, min_cos, step, weights,
                            displacement[0])
        scatter(displacement, order, tables_1, tables_2, coefficients)
        _product(constraints_t, coefficients[0].ravel(), rhs)
        for i in range(n_parameters):
            dp[i] = reference[i] - p[i]
        _product(prior.smoothing, dp, projected)
        for i in range(n_parameters):
            rhs[i] += projected[i]
        for k in range(n_landmarks):  # towards each landmark by at most a step
            residual = (lm_v0[k] - _dot(lm_basis[k], p)) * lm_h0[k]
            residual = min(max(residual, -step), step) / lm_h0[k]
            for i in range(n_parameters):
                rhs[i] += lm_pull[i, k] * residual
        _symmetric_product(prior.inverse, rhs, dp)
        for i in range(n_parameters):
            p[i] += dp[i]
        _product(constraints, dp, coefficients[0].ravel())
        gather(coefficients, order, tables_1, tables_2, motion)
        moved = motion[0]
        squared = dot = 0.0
        for q in range(n):
            moved[q] *= h0[q]
            squared += weights[q] * moved[q] * moved[q]
            dot += weights[q] * moved[q] * previous[q]
        if s.adaptive:  # Descent._adapt_step
            if s.previous_squared >= 0:
                norms = math.sqrt(squared * s.previous_squared)
                if norms > 0 and dot < -0.5 * norms:
                    s.step = max(0.5 * step, s.initial_step / 8)
            for q in range(n):
                previous[q] = moved[q]
            s.previous_squared = squared
        s.motion = math.sqrt(squared / area)
        s.iterations += 1
        if s.motion < tol:
            return CONVERGED
    return AT_CAP


if AVAILABLE:
    _compile = njit(cache=True, error_model="numpy")
    _parallel = njit(cache=True, error_model="numpy", parallel=True)
    _inline = njit(cache=True, error_model="numpy", inline="always")
    _sample = _inline(_sample)
    _beam_sample = _inline(_beam_sample)
    overload(_sample_at, inline="always")(_sample_at_typed)
    _nearest = _inline(_nearest)
    _index = _inline(_index)
    _patch = _inline(_patch)
    _contract = _inline(_contract)
    _dot4 = _inline(_dot4)
    gather = _parallel(gather)
    scatter = _compile(scatter)
    prolate_surface = _parallel(prolate_surface)
    sample_along = _parallel(sample_along)
    samples_at = _compile(samples_at)  # serial: its few thousand samples do not repay a parallel compile
    cavity_sums = _parallel(cavity_sums)
    normal_displacement = _compile(normal_displacement)
    csr_product = _compile(csr_product)
    _product = _inline(_product)
    _symmetric_product = _inline(_symmetric_product)
    _dot = _inline(_dot)
    _select = _compile(_select)
    _median = _compile(_median)
    _global_means = _compile(_global_means)
    _band_means = _compile(_band_means)
    _interface_level = _inline(_interface_level)
    _local_force = _compile(_local_force)
    descend = _compile(descend)
