# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled hot path of an iteration (Cython, built with the package).

An iteration touches only what the model sets: the 4096 sample points of an
8 x 8-patch surface (8 x 8 Gauss-Legendre points a patch), their normals and
a few trilinear samples along each normal.  In numpy that is some hundred
array operations and sparse products on 4096-long arrays; as plain loops
compiled to C it is a tenth of that time (docs/benchmarks.md).  The readable
numpy backend (:class:`spheroseg.descent.backends.NumpyBackend`) stays the
reference: the tests check each kernel against it and whole segmentations
on both.  Where this extension is not built (a source tree on
``PYTHONPATH``), the numpy backend runs.

Each kernel does one job and writes into arrays the caller allocated once
per level:

- :func:`prolate_surface`: the surface at the sample points (``f``, the
  scale factor ``h0``, the unit normal in world space, ``A_K``, ...):
  paper eq. 1 (the coordinates) and eqs. 16-17 (tangents, ``A_K``);
- :func:`sample_along`: the mean of trilinear samples along normals;
  :func:`samples_at`: the samples themselves, trilinear or the nearest voxel;
  both, and :func:`cavity_sums`, sample a Cartesian image or a beam-space
  volume, whose arrays :func:`sampler` puts in one form (``beam`` None for
  a Cartesian image);
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
OpenMP ``prange`` loops over points or patches, on the threads of
:func:`spheroseg._compiled._runtime.kernel_threads`: each iteration writes
its own outputs and sums nothing across iterations, so a result is the same
to the last bit on any number of threads.  ``min`` and ``max`` are Python's
(:func:`_min`, :func:`_max`), and the build turns off fused multiply-adds,
so the arithmetic rounds as the Python source of each step would.

Equation numbers are those of Duan et al., Proc. SPIE 6144, 61444A (2006).

Only the prolate spheroidal system (the default) has a surface kernel.
"""

from collections import namedtuple

import numpy as np

from cython.parallel cimport prange
from libc.math cimport NAN, atan, exp, isfinite, isnan, log, log1p, rint, sqrt
from libc.stdint cimport int32_t, int64_t, uint64_t

from ._layout cimport node_offset, prolate_point

from spheroseg._compiled import INDEX_TOLERANCE
from spheroseg._compiled._runtime import current_threads as _current_threads

__all__ = ["AVAILABLE", "NO_BEAM", "sampler", "prolate_surface", "sample_along", "samples_at", "cavity_sums",
           "gather", "scatter", "normal_displacement", "csr_product", "descend"]

AVAILABLE = True
#: the ``beam`` argument of a Cartesian image (:func:`sampler`)
NO_BEAM = None

cdef double _EDGE = INDEX_TOLERANCE

ctypedef fused index_t:
    int32_t
    int64_t


cdef inline double _max(double a, double b) noexcept nogil:
    """Python's ``max(a, b)``: ``b`` only when it is greater."""
    return b if b > a else a


cdef inline double _min(double a, double b) noexcept nogil:
    """Python's ``min(a, b)``: ``b`` only when it is smaller."""
    return b if b < a else a


cdef struct Sampler:
    # the image's arguments (:func:`sampler`) as the kernels read them
    const float* image
    uint64_t sy, sz
    double upper[3]
    double to_index[9]
    double origin[3]
    bint beam
    double b[7]


cdef Sampler _sampler(const float[::1] image, const int64_t[::1] strides, const double[::1] upper,
                      const double[:, :] to_index, const double[::1] origin, beam) except *:
    cdef Sampler s
    cdef int i, j
    cdef const double[::1] b
    s.image = &image[0]
    s.sy, s.sz = <uint64_t>strides[1], <uint64_t>strides[2]
    for i in range(3):
        s.upper[i] = upper[i]
        s.origin[i] = origin[i]
        for j in range(3):
            s.to_index[3 * i + j] = to_index[i, j]
    s.beam = beam is not None
    if s.beam:
        b = beam
        for i in range(7):
            s.b[i] = b[i]
    return s


def _c_order(a):
    """``a`` as a C-order float64 array (itself when it is one)."""
    return np.ascontiguousarray(a, dtype=float)


cdef inline double _sample(const Sampler* s, double fi, double fj, double fk) noexcept nogil:
    """Trilinear sample of the flat image at the continuous voxel index
    ``(fi, fj, fk)`` (x, y, z), as :meth:`spheroseg.Volume.sample` (the
    reference; the arrays are those of :meth:`~spheroseg.Volume.sampling_view`): NaN
    outside the image and, through the image's NaN voxels, on no-data."""
    if not (fi >= -_EDGE and fj >= -_EDGE and fk >= -_EDGE
            and fi <= s.upper[0] + _EDGE and fj <= s.upper[1] + _EDGE and fk <= s.upper[2] + _EDGE):
        return NAN
    fi = _min(_max(fi, 0.0), s.upper[0])
    fj = _min(_max(fj, 0.0), s.upper[1])
    fk = _min(_max(fk, 0.0), s.upper[2])
    # the cell's lower corner; the last voxel belongs to the cell before it
    cdef int64_t i0 = min(<int64_t>fi, <int64_t>s.upper[0] - 1)
    cdef int64_t j0 = min(<int64_t>fj, <int64_t>s.upper[1] - 1)
    cdef int64_t k0 = min(<int64_t>fk, <int64_t>s.upper[2] - 1)
    cdef double ti = fi - i0, tj = fj - j0, tk = fk - k0
    cdef uint64_t sy = s.sy, sz = s.sz
    cdef uint64_t c = <uint64_t>i0 + <uint64_t>j0 * sy + <uint64_t>k0 * sz
    cdef const float* image = s.image
    # weights times float32 values: the products are double, as in numpy
    cdef double c00 = image[c] * (1.0 - ti) + image[c + 1] * ti
    cdef double c01 = image[c + sy] * (1.0 - ti) + image[c + sy + 1] * ti
    cdef double c10 = image[c + sz] * (1.0 - ti) + image[c + sz + 1] * ti
    cdef double c11 = image[c + sy + sz] * (1.0 - ti) + image[c + sy + sz + 1] * ti
    return (c00 * (1.0 - tj) + c01 * tj) * (1.0 - tk) + (c10 * (1.0 - tj) + c11 * tj) * tk


cdef inline double _beam_sample(const Sampler* s, double x, double y, double z) noexcept nogil:
    """Trilinear sample of a beam-space volume at the probe-frame point
    ``(x, y, z)``, as :meth:`spheroseg.beamspace.BeamVolume.sample` (the
    reference): the point in ``(r, e, a)`` index (one ``sqrt`` and two
    ``atan``, a second ``sqrt`` in the "sin" convention), then :func:`_sample`
    on the samples ``a`` fastest; NaN outside the sector and on no-data.
    ``b``: the separations and the index offset in ``(r, e, a)``, then 1
    for the "sin" convention (:func:`sampler`)."""
    # the sector lies in z > 0 in both conventions (half-angles under 90
    # degrees), where atan2(u, z) = atan(u / z), the cheaper call
    if not z > 0.0:
        return NAN
    cdef const double* b = s.b
    cdef double rho = sqrt(x * x + y * y + z * z)
    cdef double fr = (rho - b[3]) / b[0]
    if not (fr >= -_EDGE and fr <= s.upper[2] + _EDGE):  # off the range: no angles needed
        return NAN
    cdef double inv_z = 1.0 / z, alpha
    cdef double fe = (atan(y * inv_z) - b[4]) / b[1]
    if b[6] != 0.0:
        alpha = atan(x / sqrt(y * y + z * z))
    else:
        alpha = atan(x * inv_z)
    cdef double fa = (alpha - b[5]) / b[2]
    return _sample(s, fa, fe, fr)


cdef inline double _sample_at(const Sampler* s, double x, double y, double z) noexcept nogil:
    """The image at ``(x, y, z)`` of the sampler's frame: a Cartesian image's
    continuous voxel index or a beam-space volume's probe frame."""
    if s.beam:
        return _beam_sample(s, x, y, z)
    return _sample(s, x, y, z)


cdef inline double _nearest(const Sampler* s, double fi, double fj, double fk) noexcept nogil:
    """The voxel nearest the continuous index ``(fi, fj, fk)``, as
    :meth:`spheroseg.Volume.sample` with ``order=0`` (halves rounded to even,
    as ``np.rint``): NaN outside the image and on no-data."""
    if not (fi >= -_EDGE and fj >= -_EDGE and fk >= -_EDGE
            and fi <= s.upper[0] + _EDGE and fj <= s.upper[1] + _EDGE and fk <= s.upper[2] + _EDGE):
        return NAN
    cdef double i = rint(_min(_max(fi, 0.0), s.upper[0]))
    cdef double j = rint(_min(_max(fj, 0.0), s.upper[1]))
    cdef double k = rint(_min(_max(fk, 0.0), s.upper[2]))
    return s.image[<uint64_t>i + <uint64_t>j * s.sy + <uint64_t>k * s.sz]


cdef inline (double, double, double) _index(const double* m, double ox, double oy, double oz,
                                            double x, double y, double z) noexcept nogil:
    """``m @ ((x, y, z) - offset)``: a world point (or, with a zero offset,
    a direction) to the sampler's frame."""
    x, y, z = x - ox, y - oy, z - oz
    return (m[0] * x + m[1] * y + m[2] * z, m[3] * x + m[4] * y + m[5] * z, m[6] * x + m[7] * y + m[8] * z)


cdef inline void _patch(const double* coefficients, Py_ssize_t n1, Py_ssize_t i1, Py_ssize_t i2,
                        double* out) noexcept nogil:
    """The 16 coefficients of patch ``(i1, i2)`` from ``(n2+1, n1, 4)``
    (C order) as ``out[4 (2 a1 + e1) + 2 a2 + e2]`` (node ``a`` and
    derivative ``e`` along v1, v2), so that ``f = sum_jm basis1[a, j]
    out[j, m] basis2[b, m]``.  (Pointers, not memoryviews, in the loops'
    helpers: passing a memoryview counts a reference, atomically.)"""
    cdef int a1, e1, a2, e2
    for a1 in range(2):
        for e1 in range(2):
            for a2 in range(2):
                for e2 in range(2):
                    out[4 * (2 * a1 + e1) + 2 * a2 + e2] = coefficients[node_offset(n1, i1, i2, a1, a2, e1, e2)]


cdef inline void _contract(const double* patch, const double* basis, double* out) noexcept nogil:
    """``out[j] = sum_m patch[j, m] basis[m]``: the patch on one line of v2."""
    cdef int j
    for j in range(4):
        out[j] = (patch[4 * j] * basis[0] + patch[4 * j + 1] * basis[1] + patch[4 * j + 2] * basis[2]
                  + patch[4 * j + 3] * basis[3])


cdef inline double _dot4(const double* basis, const double* line) noexcept nogil:
    return basis[0] * line[0] + basis[1] * line[1] + basis[2] * line[2] + basis[3] * line[3]


# The sample points are a tensor product of ``order`` positions a patch in
# each direction, so the kernels below walk patch by patch, contract the
# 4 x 4 coefficients with the v2 table once per line of points and with the
# v1 table at each point (4 multiply-adds a point instead of 16).  The
# sample at local position (a, b) of patch (i1, i2) is number
# ((i2 order + b) n1 + i1) order + a (v2-major, as HermiteGrid.quadrature).


cdef void _gather_patch(const double* coefficients, Py_ssize_t n1, int order, const double* basis1,
                        const double* basis2, double* out, Py_ssize_t i1, Py_ssize_t i2) noexcept nogil:
    # basis[0, b, :] at basis + 4 b (tables (2, order, 4), C order)
    cdef double patch[16]
    cdef double line[4]
    cdef Py_ssize_t q
    cdef int a, b
    _patch(coefficients, n1, i1, i2, patch)
    for b in range(order):
        _contract(patch, basis2 + 4 * b, line)
        q = ((i2 * order + b) * n1 + i1) * order
        for a in range(order):
            out[q + a] = _dot4(basis1 + 4 * a, line)


cdef void _gather(const double[:, :, :, ::1] coefficients, int order, const double[:, :, ::1] basis1,
                  const double[:, :, ::1] basis2, double[:, ::1] out, int threads) noexcept nogil:
    cdef Py_ssize_t n2 = coefficients.shape[1] - 1, n1 = coefficients.shape[2], i, k
    for i in prange(out.shape[0] * n2 * n1, schedule="static", num_threads=threads, use_threads_if=threads > 1):  # disjoint points
        k = i // (n2 * n1)
        _gather_patch(&coefficients[k, 0, 0, 0], n1, order, &basis1[0, 0, 0], &basis2[0, 0, 0], &out[k, 0], i % n1,
                      i // n1 % n2)


def gather(const double[:, :, :, ::1] coefficients, int order, const double[:, :, ::1] basis1,
           const double[:, :, ::1] basis2, double[:, ::1] out):
    """``out[k] = B coefficients[k]``: each field (coefficients
    ``(fields, n2+1, n1, 4)``) at every sample point."""
    cdef int threads = _current_threads()
    with nogil:
        _gather(coefficients, order, basis1, basis2, out, threads)


cdef void _scatter(const double[:, :] values, int order, const double[:, :, ::1] basis1,
                   const double[:, :, ::1] basis2, double[:, :, :, ::1] out) noexcept nogil:
    cdef Py_ssize_t n2 = out.shape[1] - 1, n1 = out.shape[2], k, i1, i2, q, node1
    cdef double patch[16]
    cdef double line[4]
    cdef int a, b, j, m, a1, e1, a2, e2
    out[...] = 0.0
    for k in range(values.shape[0]):
        for i2 in range(n2):
            for i1 in range(n1):
                for j in range(16):
                    patch[j] = 0.0
                for b in range(order):
                    q = ((i2 * order + b) * n1 + i1) * order
                    for j in range(4):
                        line[j] = 0.0
                    for a in range(order):
                        for j in range(4):
                            line[j] += basis1[0, a, j] * values[k, q + a]
                    for j in range(4):
                        for m in range(4):
                            patch[4 * j + m] += line[j] * basis2[0, b, m]
                for a1 in range(2):
                    node1 = i1 + a1 if i1 + a1 < n1 else 0
                    for e1 in range(2):
                        for a2 in range(2):
                            for e2 in range(2):
                                out[k, i2 + a2, node1, e1 + 2 * e2] += patch[4 * (2 * a1 + e1) + 2 * a2 + e2]


def scatter(const double[:, :] values, int order, const double[:, :, ::1] basis1, const double[:, :, ::1] basis2,
            double[:, :, :, ::1] out):
    """``out[k] = B^T values[k]`` on coefficients ``(fields, n2+1, n1, 4)``."""
    with nogil:
        _scatter(values, order, basis1, basis2, out)


cdef void _surface_patch(const double* coefficients, Py_ssize_t n1, int order, const double* basis1,
                         const double* basis2, Py_ssize_t i1, Py_ssize_t i2, double* out_f, double* out_h0,
                         double* out_cos, double* out_area) noexcept nogil:
    # basis[0, b, :] at basis + 4 b, basis[1, b, :] at basis + 4 (order + b)
    cdef double patch[16]
    cdef double line[4]
    cdef double line_mu[4]
    cdef Py_ssize_t q
    cdef int a, b
    _patch(coefficients, n1, i1, i2, patch)
    for b in range(order):
        _contract(patch, basis2 + 4 * b, line)
        _contract(patch, basis2 + 4 * (order + b), line_mu)
        q = ((i2 * order + b) * n1 + i1) * order
        for a in range(order):
            out_f[q + a] = _dot4(basis1 + 4 * a, line)
            out_h0[q + a] = _dot4(basis1 + 4 * (order + a), line)  # df/dtheta until the loop below
            out_cos[q + a] = _dot4(basis1 + 4 * a, line_mu)  # df/dmu until the loop below
            out_area[q + a] = exp(out_f[q + a])  # e^lambda until the loop below


cdef void _prolate_surface(const double[:, :, ::1] coefficients, int order, const double[:, :, ::1] basis1,
                           const double[:, :, ::1] basis2, const double[::1] cos_th, const double[::1] sin_th,
                           const double[::1] cos_mu, const double[::1] sin_mu, double d, const double[:, :] rotation,
                           const double[:] origin, double[::1] out_f, double[::1] out_h0, double[::1] out_cos,
                           double[::1] out_area, double[:, ::1] out_world, double[:, ::1] out_normal,
                           int threads) noexcept nogil:
    cdef Py_ssize_t n2 = coefficients.shape[0] - 1, n1 = coefficients.shape[1], i, q
    for i in prange(n2 * n1, schedule="static", num_threads=threads, use_threads_if=threads > 1):  # the patches write disjoint points
        _surface_patch(&coefficients[0, 0, 0], n1, order, &basis1[0, 0, 0], &basis2[0, 0, 0], i % n1, i // n1,
                       &out_f[0], &out_h0[0], &out_cos[0], &out_area[0])
    cdef double r00 = rotation[0, 0], r01 = rotation[0, 1], r02 = rotation[0, 2]
    cdef double r10 = rotation[1, 0], r11 = rotation[1, 1], r12 = rotation[1, 2]
    cdef double r20 = rotation[2, 0], r21 = rotation[2, 1], r22 = rotation[2, 2]
    cdef double o0 = origin[0], o1 = origin[1], o2 = origin[2]
    cdef double e, f1, f2, ch, sh, ct, st, cm, sm, x0, rho, x1, x2, j00, j01, j02, j10, j11, j12, j20, j21, j22
    cdef double a0, a1, a2, b0, b1, b2, m0, m1, m2, area, along, sign, scale, h0
    for q in prange(out_f.shape[0], schedule="static", num_threads=threads, use_threads_if=threads > 1):
        e, f1, f2 = out_area[q], out_h0[q], out_cos[q]
        ch, sh = 0.5 * (e + 1.0 / e), 0.5 * (e - 1.0 / e)
        ct, st, cm, sm = cos_th[q], sin_th[q], cos_mu[q], sin_mu[q]
        x0, x1, x2 = prolate_point(d, ch, sh, ct, st, cm, sm)
        # columns of the Jacobian: dx/dlambda, dx/dtheta, dx/dmu
        j00, j01, j02 = d * sh * cm, d * ch * sm * ct, d * ch * sm * st
        j10, j11, j12 = 0.0, -d * sh * sm * st, d * sh * sm * ct
        j20, j21, j22 = -d * ch * sm, d * sh * cm * ct, d * sh * cm * st
        # tangents x_theta = f1 J0 + J1, x_mu = f2 J0 + J2 and their cross product
        a0, a1, a2 = f1 * j00 + j10, f1 * j01 + j11, f1 * j02 + j12
        b0, b1, b2 = f2 * j00 + j20, f2 * j01 + j21, f2 * j02 + j22
        m0, m1, m2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
        area = sqrt(m0 * m0 + m1 * m1 + m2 * m2)
        # outwards: along +dx/dlambda
        along = m0 * j00 + m1 * j01 + m2 * j02
        sign = (1.0 if along > 0 else 0.0) - (1.0 if along < 0 else 0.0)
        scale = sign / area if area > 0 else 0.0
        m0, m1, m2 = m0 * scale, m1 * scale, m2 * scale
        h0 = d * sqrt(sh * sh + sm * sm)
        out_h0[q] = h0
        out_cos[q] = (m0 * j00 + m1 * j01 + m2 * j02) / h0
        out_area[q] = area
        out_world[0, q] = r00 * x0 + r01 * x1 + r02 * x2 + o0
        out_world[1, q] = r10 * x0 + r11 * x1 + r12 * x2 + o1
        out_world[2, q] = r20 * x0 + r21 * x1 + r22 * x2 + o2
        out_normal[0, q] = r00 * m0 + r01 * m1 + r02 * m2
        out_normal[1, q] = r10 * m0 + r11 * m1 + r12 * m2
        out_normal[2, q] = r20 * m0 + r21 * m1 + r22 * m2


def prolate_surface(const double[:, :, ::1] coefficients, int order, const double[:, :, ::1] basis1,
                    const double[:, :, ::1] basis2, const double[::1] cos_th, const double[::1] sin_th,
                    const double[::1] cos_mu, const double[::1] sin_mu, double d, const double[:, :] rotation,
                    const double[:] origin, double[::1] out_f, double[::1] out_h0, double[::1] out_cos,
                    double[::1] out_area, double[:, ::1] out_world, double[:, ::1] out_normal):
    """The surface ``lambda = f(theta, mu)`` at every sample point (eq. 1 for
    the point, eqs. 16-17 for the tangents and ``A_K``): ``f``, the
    scale factor ``h0`` (mm per unit lambda), the cosine between the outward
    normal and ``dx/dlambda``, ``A_K = |x_theta x x_mu|``, the world point
    and the unit outward normal (world), both ``(3, n)``, as
    :meth:`SampledSurface.geometry`."""
    cdef int threads = _current_threads()
    with nogil:
        _prolate_surface(coefficients, order, basis1, basis2, cos_th, sin_th, cos_mu, sin_mu, d, rotation, origin,
                         out_f, out_h0, out_cos, out_area, out_world, out_normal, threads)


cdef double _mean_along(const Sampler* s, const double* world, const double* normal, Py_ssize_t n, Py_ssize_t q,
                        const double* offsets, Py_ssize_t n_offsets, double exponent,
                        int64_t* count) noexcept nogil:
    # the point and the normal in the sampler's frame: the samples are a line there
    cdef double pi, pj, pk, ni, nj, nk, v, t, total = 0.0
    cdef int64_t found = 0
    cdef Py_ssize_t k
    pi, pj, pk = _index(s.to_index, s.origin[0], s.origin[1], s.origin[2], world[q], world[n + q], world[2 * n + q])
    ni, nj, nk = _index(s.to_index, 0.0, 0.0, 0.0, normal[q], normal[n + q], normal[2 * n + q])
    for k in range(n_offsets):
        t = offsets[k]
        v = _sample_at(s, pi + t * ni, pj + t * nj, pk + t * nk)
        if exponent != 0.0:
            v = exp(exponent * v)
        if not isnan(v):
            total += v
            found += 1
    count[0] = found
    return total / found if found else NAN


cdef double _one_along(const Sampler* s, const double* world, const double* normal, Py_ssize_t n, Py_ssize_t q,
                       double offset, double exponent) noexcept nogil:
    cdef double pi, pj, pk, ni, nj, nk, v
    pi, pj, pk = _index(s.to_index, s.origin[0], s.origin[1], s.origin[2], world[q], world[n + q], world[2 * n + q])
    ni, nj, nk = _index(s.to_index, 0.0, 0.0, 0.0, normal[q], normal[n + q], normal[2 * n + q])
    v = _sample_at(s, pi + offset * ni, pj + offset * nj, pk + offset * nk)
    if exponent != 0.0:
        v = exp(exponent * v)
    return v


cdef void _sample_along(const Sampler* s, const double[:, ::1] world, const double[:, ::1] normal,
                        const int64_t[::1] rows, const double[::1] offsets, double exponent, double[:] out_mean,
                        int64_t[:] out_count, int threads) noexcept nogil:
    """:func:`sample_along` on (3, n) C-order points and normals."""
    cdef Py_ssize_t r, n = world.shape[1], n_offsets = offsets.shape[0]
    cdef const double* w = &world[0, 0]
    cdef const double* m = &normal[0, 0]
    cdef const int64_t* q = &rows[0] if rows.shape[0] else NULL
    cdef const double* o = &offsets[0] if n_offsets else NULL
    cdef double offset, v
    if n_offsets == 1:
        # the surface's own samples, every iteration: a loop without an inner one
        offset = offsets[0]
        for r in prange(rows.shape[0], schedule="static", num_threads=threads, use_threads_if=threads > 1):
            v = _one_along(s, w, m, n, q[r], offset, exponent)
            out_mean[r] = v  # NaN: no finite sample
            out_count[r] = not isnan(v)
        return
    for r in prange(rows.shape[0], schedule="static", num_threads=threads, use_threads_if=threads > 1):
        out_mean[r] = _mean_along(s, w, m, n, q[r], o, n_offsets, exponent, &out_count[r])


def sample_along(const float[::1] image, const int64_t[::1] strides, const double[::1] upper,
                 const double[:, :] to_index, const double[::1] image_origin, beam, world, normal, rows, offsets,
                 double exponent, double[:] out_mean, int64_t[:] out_count):
    """For each ``q`` in ``rows``: the mean (NaN if none) and the number of the
    finite samples at ``world[:, q] + s normal[:, q]`` for ``s`` in
    ``offsets`` (mm); with a non-zero ``exponent`` ``a``, of ``exp(a v)`` for
    each sample ``v`` (log compression undone).  The image arguments are
    :func:`sampler`'s, of a Cartesian or a beam-space volume."""
    cdef Sampler s = _sampler(image, strides, upper, to_index, image_origin, beam)
    cdef int threads = _current_threads()
    cdef const double[:, ::1] w = _c_order(world), m = _c_order(normal)
    cdef const int64_t[::1] q = np.ascontiguousarray(rows, dtype=np.int64)
    cdef const double[::1] o = _c_order(offsets)
    if q.shape[0] > out_mean.shape[0] or q.shape[0] > out_count.shape[0]:
        raise ValueError("the outputs are shorter than the rows")
    with nogil:
        _sample_along(&s, w, m, q, o, exponent, out_mean, out_count, threads)


def samples_at(const float[::1] image, const int64_t[::1] strides, const double[::1] upper,
               const double[:, :] to_index, const double[::1] image_origin, beam, const double[:, :] world,
               const double[:, :] normal, const int64_t[:] rows, const double[:] offsets, bint nearest,
               double[:, :] out):
    """``out[r, k]``: the sample at ``world[:, q] + offsets[k] normal[:, q]``
    for ``q = rows[r]``, as :meth:`spheroseg.Volume.sample` (the reference):
    trilinear, or with ``nearest`` the nearest voxel (a Cartesian image's
    only); NaN off the data.  The image arguments are :func:`sampler`'s."""
    cdef Sampler sm = _sampler(image, strides, upper, to_index, image_origin, beam)
    cdef Sampler* s = &sm
    cdef Py_ssize_t r, k, q
    cdef double pi, pj, pk, ni, nj, nk, t
    with nogil:
        for r in range(rows.shape[0]):
            q = rows[r]
            pi, pj, pk = _index(s.to_index, s.origin[0], s.origin[1], s.origin[2], world[0, q], world[1, q],
                                world[2, q])
            ni, nj, nk = _index(s.to_index, 0.0, 0.0, 0.0, normal[0, q], normal[1, q], normal[2, q])
            for k in range(offsets.shape[0]):
                t = offsets[k]
                if nearest:
                    out[r, k] = _nearest(s, pi + t * ni, pj + t * nj, pk + t * nk)
                else:
                    out[r, k] = _sample_at(s, pi + t * ni, pj + t * nj, pk + t * nk)


cdef void _cavity_row(const Sampler* s, double fq, double ct, double st, double cm, double sm, double d,
                      const double* rotation, const double* origin, const double* fractions, Py_ssize_t n_fractions,
                      double* out_sum, double* out_weight) noexcept nogil:
    cdef double total = 0.0, weight = 0.0, e, sh, ch, x0, rho, x1, x2, wx, wy, wz, fi, fj, fk, v, volume
    cdef Py_ssize_t k
    for k in range(n_fractions):
        e = exp(fractions[k] * fq)
        sh, ch = 0.5 * (e - 1.0 / e), 0.5 * (e + 1.0 / e)
        x0, x1, x2 = prolate_point(d, ch, sh, ct, st, cm, sm)
        wx = rotation[0] * x0 + rotation[1] * x1 + rotation[2] * x2 + origin[0]
        wy = rotation[3] * x0 + rotation[4] * x1 + rotation[5] * x2 + origin[1]
        wz = rotation[6] * x0 + rotation[7] * x1 + rotation[8] * x2 + origin[2]
        fi, fj, fk = _index(s.to_index, s.origin[0], s.origin[1], s.origin[2], wx, wy, wz)
        v = _sample_at(s, fi, fj, fk)
        if not isnan(v):
            volume = d * (d * d) * (sh * sh + sm * sm) * sh * sm  # (d**3 as Python's d * (d * d))
            total += volume * v
            weight += volume
    out_sum[0] = total
    out_weight[0] = weight


cdef void _cavity_sums(const Sampler* s, const double[::1] f, const double[::1] cos_th, const double[::1] sin_th,
                       const double[::1] cos_mu, const double[::1] sin_mu, double d, const double[:, :] rotation,
                       const double[:] origin, const int64_t[::1] rows, const double[::1] fractions,
                       double[:] out_sum, double[:] out_weight, int threads) noexcept nogil:
    cdef Py_ssize_t r, q, i
    cdef double rot[9]
    cdef double o[3]
    for i in range(9):
        rot[i] = rotation[i // 3, i % 3]
    for i in range(3):
        o[i] = origin[i]
    cdef const double* fr = &fractions[0] if fractions.shape[0] else NULL
    for r in prange(rows.shape[0], schedule="static", num_threads=threads, use_threads_if=threads > 1):
        q = rows[r]
        _cavity_row(s, f[q], cos_th[q], sin_th[q], cos_mu[q], sin_mu[q], d, rot, o, fr, fractions.shape[0],
                    &out_sum[r], &out_weight[r])


def cavity_sums(const float[::1] image, const int64_t[::1] strides, const double[::1] upper,
                const double[:, :] to_index, const double[::1] image_origin, beam, f, cos_th, sin_th, cos_mu, sin_mu,
                double d, const double[:, :] rotation, const double[:] origin, rows, fractions, double[:] out_sum,
                double[:] out_weight):
    """For each ``q`` in ``rows``, samples at ``lambda = t f[q]`` for ``t`` in
    ``fractions``, weighted by the volume element ``V = h0 h1 h2``: the sums
    of ``V u`` and of ``V`` over the finite samples.  The image arguments
    are :func:`sampler`'s."""
    cdef Sampler s = _sampler(image, strides, upper, to_index, image_origin, beam)
    cdef int threads = _current_threads()
    cdef const double[::1] fv = _c_order(f), ct = _c_order(cos_th), st = _c_order(sin_th)
    cdef const double[::1] cm = _c_order(cos_mu), sm = _c_order(sin_mu), fr = _c_order(fractions)
    cdef const int64_t[::1] q = np.ascontiguousarray(rows, dtype=np.int64)
    if q.shape[0] > out_sum.shape[0] or q.shape[0] > out_weight.shape[0]:
        raise ValueError("the outputs are shorter than the rows")
    with nogil:
        _cavity_sums(&s, fv, ct, st, cm, sm, d, rotation, origin, q, fr, out_sum, out_weight, threads)


cdef void _csr(const index_t[::1] indptr, const index_t[::1] indices, const double[::1] data, const double[::1] x,
               double[::1] out) noexcept nogil:
    cdef Py_ssize_t i, k
    cdef double total
    for i in range(out.shape[0]):
        total = 0.0
        for k in range(indptr[i], indptr[i + 1]):
            total += data[k] * x[indices[k]]
        out[i] = total


def csr_product(const index_t[::1] indptr, const index_t[::1] indices, const double[::1] data, const double[::1] x,
                double[::1] out):
    """``out = A x`` for a CSR matrix ``A`` (``indptr, indices, data``), each
    row summed in the order of scipy's ``csr_matvec``, so equal to
    ``A @ x`` to the last bit; without scipy's per-call dispatch, which
    costs some ten times the product of the few-hundred-entry constraint
    matrices."""
    with nogil:
        _csr(indptr, indices, data, x, out)


cdef void _normal_displacement(const double[:] u, const double[:] c_in, const double[:] c_out, double scale,
                               double clip, const double[:] h0, const double[:] cos, double h0_floor,
                               double min_cos, double step, const double[:] weights, double[:] out) noexcept nogil:
    cdef Py_ssize_t q
    cdef double r, speed, normal_to_v0
    for q in range(u.shape[0]):
        r = (c_out[q] - c_in[q]) * (2.0 * u[q] - c_in[q] - c_out[q]) / scale
        if isfinite(r):
            speed = -_min(_max(r, -clip), clip)
        elif isfinite(u[q]):
            speed = 0.0
        else:  # off the data: pulled back in
            speed = -1.0
        normal_to_v0 = _max(h0[q] * _max(cos[q], min_cos), h0_floor)
        out[q] = weights[q] * step * speed / normal_to_v0


def normal_displacement(const double[:] u, const double[:] c_in, const double[:] c_out, double scale, double clip,
                        const double[:] h0, const double[:] cos, double h0_floor, double min_cos, double step,
                        const double[:] weights, double[:] out):
    """``out = weights * dv0``: the region force of eq. 22 as a displacement
    in ``v0`` per sample point, as :meth:`spheroseg.backends.NumpyBackend.displacement`
    (the reference, through :func:`spheroseg.energy.normal_speed`)."""
    with nogil:
        _normal_displacement(u, c_in, c_out, scale, clip, h0, cos, h0_floor, min_cos, step, weights, out)


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


cdef enum:
    _FIXED_MEANS = 0
    _GLOBAL_MEANS = 1
    _LOCAL_MEANS = 2
    _AT_CAP = 0
    _CONVERGED = 1
    _NO_BAND_DATA = 2

#: the data terms whose force :func:`descend` computes itself
FIXED_MEANS, GLOBAL_MEANS, LOCAL_MEANS = _FIXED_MEANS, _GLOBAL_MEANS, _LOCAL_MEANS

#: What :func:`descend` reads of the model, fixed for a grid and pose:
#: the constraints ``A`` and ``A^T`` as CSR ``(indptr, indices, data)``,
#: the coefficients' shape, the quadrature order and basis tables (of the
#: sample points and of the band rows), ``(cos theta, sin theta, cos mu,
#: sin mu)`` at the samples, the focal length, the pose, the quadrature
#: weights and the domain's area, the least cosine of the ``v0``
#: conversion, all rows and the band rows with their weights, and
#: ``M^-1``.
LoopSurface = namedtuple("LoopSurface", ["constraints", "constraints_t", "grid_shape", "order", "tables_1",
                                         "tables_2", "band_order", "band_tables_1", "band_tables_2", "trig",
                                         "focal_length", "rotation", "origin", "weights", "area", "min_cos",
                                         "all_rows", "band_rows", "band_weights", "mass_inverse"])
#: The least-squares problem's other rows: ``a T`` as CSR, the system's
#: (symmetric) inverse, the landmark rows ``L``, their ``v0`` and ``h0``,
#: and ``L^T Omega``.
LoopPrior = namedtuple("LoopPrior", ["smoothing", "inverse", "landmark_rows", "landmark_v0", "landmark_h0",
                                     "landmark_pull"])
#: The data term as :func:`descend` computes it: its ``kind``
#: (:data:`FIXED_MEANS`, :data:`GLOBAL_MEANS`, :data:`LOCAL_MEANS`), the
#: fixed means at every sample and their scale, the least scale, the
#: cavity fractions, the shell's and the bands' offsets (mm), and the
#: local means' polarity and boundary (:class:`spheroseg.dataterms.LocalMeans`).
LoopTerm = namedtuple("LoopTerm", ["kind", "fixed_in", "fixed_out", "fixed_scale", "min_scale", "fractions",
                                   "shell_offsets", "band_offsets", "polarity", "boundary_nepers"],
                      defaults=(1.0, np.inf))
#: The arrays an observation fills, as :class:`spheroseg.backends.Observation`.
LoopObservation = namedtuple("LoopObservation", ["f", "h0", "cos", "area", "world", "normal", "u", "inside",
                                                 "outside"])

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
AT_CAP, CONVERGED, NO_BAND_DATA = _AT_CAP, _CONVERGED, _NO_BAND_DATA

cdef struct State:
    double step, initial_step, h0_floor, adaptive, previous_squared, motion, iterations, c_in, c_out, scale

# The loop's own arithmetic is written as plain loops, its sums in the
# order of the Python source's: a level in the loop equals its iterations
# to rounding.


cdef struct CSR:
    const int64_t* indptr
    const int64_t* indices
    const double* data


cdef inline void _product(const CSR* a, const double* x, double* out, Py_ssize_t rows) noexcept nogil:
    """``out = A x`` for ``a`` CSR."""
    cdef Py_ssize_t i, k
    cdef double total
    for i in range(rows):
        total = 0.0
        for k in range(a.indptr[i], a.indptr[i + 1]):
            total += a.data[k] * x[a.indices[k]]
        out[i] = total


cdef inline void _symmetric_product(const double[:, ::1] matrix, const double* x, double* out) noexcept nogil:
    """``out = A x`` for a symmetric ``A``, as ``A^T x``: a row of ``A``
    times ``x[j]`` added to ``out`` for each ``j`` (contiguous, on SIMD
    lanes; a row-by-row dot product is a chain of dependent additions)."""
    cdef Py_ssize_t i, j, n = matrix.shape[0]
    cdef double xj
    for i in range(n):
        out[i] = 0.0
    for j in range(n):
        xj = x[j]
        for i in range(n):
            out[i] += matrix[j, i] * xj


cdef double _select(double* a, Py_ssize_t n, Py_ssize_t k) noexcept nogil:
    """The ``k``-th smallest of ``a[:n]`` (reordered in place: the ``k``
    smaller ones before it), by Hoare's selection."""
    cdef Py_ssize_t lo = 0, hi = n - 1, i, j
    cdef double pivot, t
    while lo < hi:
        pivot = a[(lo + hi) // 2]
        i, j = lo, hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while a[j] > pivot:
                j -= 1
            if i <= j:
                t = a[i]
                a[i] = a[j]
                a[j] = t
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    return a[k]


cdef double _median(const double* values, Py_ssize_t n, double* scratch) noexcept nogil:
    """The median of ``values[:n]`` (finite), as numpy's: the middle value or
    the mean of the two middle ones (a selection in ``scratch``)."""
    cdef Py_ssize_t i
    for i in range(n):
        scratch[i] = values[i]
    cdef double high = _select(scratch, n, n // 2)
    if n % 2:
        return high
    cdef double low = scratch[0]  # the largest of the lower half, which the selection left below
    for i in range(1, n // 2):
        low = _max(low, scratch[i])
    return (low + high) / 2


cdef inline double _logaddexp(double x, double y) noexcept nogil:
    """``np.logaddexp`` (numpy's npy_logaddexp)."""
    cdef double tmp
    if x == y:  # infinities of the same sign
        return x + 0.693147180559945309417232121458176568
    tmp = x - y
    if tmp > 0:
        return x + log1p(exp(-tmp))
    elif tmp <= 0:
        return y + log1p(exp(tmp))
    return tmp  # NaN


cdef inline double _interface_level(double dark, double bright, double nepers) noexcept nogil:
    """The level loop's twin of :func:`spheroseg.descent.dataterms.interface_level`
    (the definition; the tests hold the loop equal to it) on scalars."""
    return bright + nepers * (_logaddexp(dark / nepers, bright / nepers) - bright / nepers - log(2.0))


cdef void _local_force(const double* band_in, const double* band_out, Py_ssize_t n, double polarity,
                       double boundary_nepers, double* out_contrast, double* out_c_in,
                       double* out_c_out) noexcept nogil:
    """:meth:`spheroseg.dataterms.LocalMeans.force` from its band means: the
    contrast of the right polarity and the force's means."""
    cdef bint finite = isfinite(boundary_nepers)
    cdef Py_ssize_t q
    cdef double contrast, force_in, force_out, dark, bright, level
    for q in range(n):
        contrast = _max(polarity * (band_out[q] - band_in[q]), 0.0)
        out_contrast[q] = contrast
        force_in, force_out = band_in[q], band_in[q] + polarity * contrast
        if finite:
            if polarity > 0:
                dark, bright = force_in, force_out
            else:
                dark, bright = force_out, force_in
            level = _interface_level(dark, bright, boundary_nepers)
            force_in, force_out = level - polarity * contrast / 2, level + polarity * contrast / 2
        out_c_in[q], out_c_out[q] = force_in, force_out


cdef struct Loop:
    # what descend reads (the LoopSurface, LoopPrior and LoopTerm) and its scratch
    CSR constraints, constraints_t, smoothing
    Py_ssize_t n, nb, n_parameters, n_coefficients, n_landmarks
    int order, band_order, kind, threads
    double focal_length, area, min_cos, fixed_scale, min_scale, polarity, boundary_nepers


cdef bint _band_means(const Loop* L, const double[:, ::1] mass_inverse, const double[::1] band_weights,
                      const double[:, :, ::1] band_tables_1, const double[:, :, ::1] band_tables_2,
                      const double[:, :, ::1] tables_1, const double[:, :, ::1] tables_2, const double[::1] inside,
                      const double[::1] outside, double[:, ::1] fields, double[:, :, :, ::1] coefficients,
                      double[:, ::1] flat, double[::1] rhs, double[::1] smooth, double[:, ::1] means,
                      double[::1] out_c_in, double[::1] out_c_out) noexcept nogil:
    """:meth:`spheroseg.backends.NumpyBackend.band_means`: the band means
    (a missing one replaced by its band's mean) projected on the Hermite
    space, at every sample point; False when a band has no finite mean."""
    cdef Py_ssize_t nb = L.nb, r, q
    cdef int k, finite
    cdef double total
    cdef const double[::1] band
    for k in range(2):
        band = inside if k == 0 else outside
        total, finite = 0.0, 0
        for r in range(nb):
            if isfinite(band[r]):
                total += band[r]
                finite += 1
        if finite == 0:
            return False
        for r in range(nb):
            fields[k, r] = band_weights[r] * (band[r] if isfinite(band[r]) else total / finite)
    _scatter(fields, L.band_order, band_tables_1, band_tables_2, coefficients)
    for k in range(2):  # M^-1 B_b^T W_b m, then its coefficients
        _product(&L.constraints_t, &flat[k, 0], &rhs[0], L.n_parameters)
        _symmetric_product(mass_inverse, &rhs[0], &smooth[0])
        _product(&L.constraints, &smooth[0], &flat[k, 0], L.n_coefficients)
    _gather(coefficients, L.order, tables_1, tables_2, means, L.threads)
    for q in range(means.shape[1]):
        out_c_in[q], out_c_out[q] = means[0, q], means[1, q]
    return True


def _csr_arrays(matrix):
    indptr, indices, data = matrix
    return (np.ascontiguousarray(indptr, dtype=np.int64), np.ascontiguousarray(indices, dtype=np.int64),
            np.ascontiguousarray(data, dtype=float))


cdef CSR _csr_view(tuple arrays):
    cdef const int64_t[::1] indptr = arrays[0]
    cdef const int64_t[::1] indices = arrays[1]
    cdef const double[::1] data = arrays[2]
    cdef CSR a
    a.indptr = &indptr[0]
    a.indices = &indices[0] if indices.shape[0] else NULL
    a.data = &data[0] if data.shape[0] else NULL
    return a


def descend(double[::1] p, const double[::1] reference, int max_iterations, double tol, state, prior, surface,
            tuple image, term, obs, double[:, ::1] means, double[::1] previous):
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
    cdef Loop L
    cdef Sampler sm = _sampler(image[0], image[1], image[2], image[3], image[4], image[5])
    # the CSR matrices with int64 indices, held here for the call
    held = [_csr_arrays(m) for m in (surface.constraints, surface.constraints_t, prior.smoothing)]
    L.constraints, L.constraints_t, L.smoothing = _csr_view(held[0]), _csr_view(held[1]), _csr_view(held[2])
    grid_shape = tuple(surface.grid_shape)
    L.order, L.band_order = surface.order, surface.band_order
    L.focal_length, L.area, L.min_cos = surface.focal_length, surface.area, surface.min_cos
    L.kind, L.min_scale = term.kind, term.min_scale
    L.fixed_scale, L.polarity, L.boundary_nepers = term.fixed_scale, term.polarity, term.boundary_nepers
    L.threads = _current_threads()
    cdef const double[:, :, ::1] tables_1 = surface.tables_1, tables_2 = surface.tables_2
    cdef const double[:, :, ::1] band_tables_1 = surface.band_tables_1, band_tables_2 = surface.band_tables_2
    cdef const double[::1] cos_th = _c_order(surface.trig[0]), sin_th = _c_order(surface.trig[1])
    cdef const double[::1] cos_mu = _c_order(surface.trig[2]), sin_mu = _c_order(surface.trig[3])
    cdef const double[:, :] rotation = surface.rotation
    cdef const double[:] origin = surface.origin
    cdef const double[::1] weights = surface.weights, band_weights = surface.band_weights
    cdef const int64_t[::1] all_rows = np.ascontiguousarray(surface.all_rows, dtype=np.int64)
    cdef const int64_t[::1] band_rows = np.ascontiguousarray(surface.band_rows, dtype=np.int64)
    cdef const double[:, ::1] mass_inverse = surface.mass_inverse, inverse = prior.inverse
    cdef const double[:, ::1] lm_basis = np.ascontiguousarray(prior.landmark_rows, dtype=float).reshape(
        -1, p.shape[0])
    cdef const double[::1] lm_v0 = prior.landmark_v0, lm_h0 = prior.landmark_h0
    cdef const double[:, ::1] lm_pull = np.ascontiguousarray(prior.landmark_pull, dtype=float).reshape(
        p.shape[0], -1)
    cdef const double[::1] fixed_in = term.fixed_in, fixed_out = term.fixed_out
    cdef const double[::1] fractions = _c_order(term.fractions), shell_offsets = _c_order(term.shell_offsets)
    cdef const double[::1] band_offsets = _c_order(term.band_offsets)
    cdef double[::1] f = obs.f, h0 = obs.h0, cos = obs.cos, area_element = obs.area, u = obs.u
    cdef double[:, ::1] world = obs.world, normal = obs.normal
    cdef double[::1] inside = obs.inside, outside = obs.outside
    L.n, L.nb, L.n_parameters, L.n_landmarks = f.shape[0], band_rows.shape[0], p.shape[0], lm_v0.shape[0]
    L.n_coefficients = int(np.prod(grid_shape))
    # scratch, allocated once a level
    coefficient_array = np.empty((1,) + grid_shape)  # the surface's, then the step's
    cdef double[:, :, :, ::1] coefficients = coefficient_array
    cdef double[::1] coefficients_flat = coefficient_array.reshape(-1)
    band_array = np.empty((2,) + grid_shape)
    cdef double[:, :, :, ::1] band_coefficients = band_array
    cdef double[:, ::1] band_flat = band_array.reshape(2, -1)
    cdef int64_t[::1] counts = np.empty(L.n, np.int64), band_counts = np.empty(L.nb, np.int64)
    cdef double[::1] surface_offset = np.zeros(1), inner_offsets = -np.asarray(band_offsets)
    cdef double[:, ::1] displacement = np.empty((1, L.n)), motion = np.empty((1, L.n))
    cdef double[:, ::1] scratch = np.empty((3, L.n)), fields = np.empty((2, L.nb)), band_means = np.empty((2, L.n))
    cdef double[::1] rhs = np.empty(L.n_parameters), projected = np.empty(L.n_parameters)
    cdef double[::1] dp = np.empty(L.n_parameters), smooth = np.empty(L.n_parameters)
    cdef State s
    record = state[0]
    s.step, s.initial_step, s.h0_floor, s.adaptive = record["step"], record["initial_step"], record["h0_floor"], \
        record["adaptive"]
    s.previous_squared, s.motion, s.iterations = record["previous_squared"], record["motion"], record["iterations"]
    s.c_in, s.c_out, s.scale = record["c_in"], record["c_out"], record["scale"]
    cdef int status
    with nogil:
        status = _descend(&L, &sm, &s, p, reference, max_iterations, tol, tables_1, tables_2, band_tables_1,
                          band_tables_2, cos_th, sin_th, cos_mu, sin_mu, rotation, origin, weights, band_weights,
                          all_rows, band_rows, mass_inverse, inverse, lm_basis, lm_v0, lm_h0, lm_pull, fixed_in,
                          fixed_out, fractions, shell_offsets, band_offsets, inner_offsets, f, h0, cos, area_element,
                          u, world, normal, inside, outside, means, previous, coefficients, coefficients_flat,
                          band_coefficients, band_flat, counts, band_counts, surface_offset, displacement, motion,
                          scratch, fields, band_means, rhs, projected, dp, smooth)
    record["step"], record["initial_step"], record["h0_floor"], record["adaptive"] = s.step, s.initial_step, \
        s.h0_floor, s.adaptive
    record["previous_squared"], record["motion"], record["iterations"] = s.previous_squared, s.motion, s.iterations
    record["c_in"], record["c_out"], record["scale"] = s.c_in, s.c_out, s.scale
    return status


cdef int _descend(const Loop* L, const Sampler* image, State* s, double[::1] p, const double[::1] reference,
                  int max_iterations, double tol, const double[:, :, ::1] tables_1, const double[:, :, ::1] tables_2,
                  const double[:, :, ::1] band_tables_1, const double[:, :, ::1] band_tables_2,
                  const double[::1] cos_th, const double[::1] sin_th, const double[::1] cos_mu,
                  const double[::1] sin_mu, const double[:, :] rotation, const double[:] origin,
                  const double[::1] weights, const double[::1] band_weights, const int64_t[::1] all_rows,
                  const int64_t[::1] band_rows,
                  const double[:, ::1] mass_inverse, const double[:, ::1] inverse, const double[:, ::1] lm_basis,
                  const double[::1] lm_v0, const double[::1] lm_h0, const double[:, ::1] lm_pull,
                  const double[::1] fixed_in, const double[::1] fixed_out, const double[::1] fractions,
                  const double[::1] shell_offsets, const double[::1] band_offsets, const double[::1] inner_offsets,
                  double[::1] f, double[::1] h0, double[::1] cos, double[::1] area_element, double[::1] u,
                  double[:, ::1] world, double[:, ::1] normal, double[::1] inside, double[::1] outside,
                  double[:, ::1] means, double[::1] previous, double[:, :, :, ::1] coefficients,
                  double[::1] coefficients_flat, double[:, :, :, ::1] band_coefficients, double[:, ::1] band_flat,
                  int64_t[::1] counts, int64_t[::1] band_counts, const double[::1] surface_offset,
                  double[:, ::1] displacement, double[:, ::1] motion, double[:, ::1] scratch,
                  double[:, ::1] fields, double[:, ::1] band_means, double[::1] rhs, double[::1] projected,
                  double[::1] dp, double[::1] smooth) noexcept nogil:
    cdef Py_ssize_t n = L.n, nb = L.nb, n_parameters = L.n_parameters, q, r, i, k
    cdef int iteration, threads = L.threads
    cdef double measured_in, measured_out, scale, step, residual, squared, dot, norms, in_sum, in_weight
    cdef double out_sum, out_weight, w_in, w_out
    cdef double[::1] c_in = means[0], band_out = means[1], c_out = means[2], band_in = means[3]
    cdef double[::1] moved = motion[0]
    cdef double* cavity = &scratch[0, 0]
    cdef double* element = &scratch[1, 0]
    cdef double* shell = &scratch[2, 0]
    for iteration in range(max_iterations):
        # the observation (CompiledBackend.observe)
        _product(&L.constraints, &p[0], &coefficients_flat[0], L.n_coefficients)
        _prolate_surface(coefficients[0], L.order, tables_1, tables_2, cos_th, sin_th, cos_mu, sin_mu,
                         L.focal_length, rotation, origin, f, h0, cos, area_element, world, normal, threads)
        _sample_along(image, world, normal, all_rows, surface_offset, 0.0, u, counts, threads)
        # the force's means (the data term's force)
        if L.kind == _GLOBAL_MEANS:
            # NumpyBackend.region_means: the cavity's volume-weighted mean and
            # the shell's area-weighted mean (NaN without weight)
            _cavity_sums(image, f, cos_th, sin_th, cos_mu, sin_mu, L.focal_length, rotation, origin, band_rows,
                         fractions, scratch[0], scratch[1], threads)
            _sample_along(image, world, normal, band_rows, shell_offsets, 0.0, scratch[2], band_counts, threads)
            in_sum = in_weight = out_sum = out_weight = 0.0
            for r in range(nb):
                q = band_rows[r]
                w_in = weights[q] * f[q]
                in_sum += w_in * cavity[r]
                in_weight += w_in * element[r]
                w_out = weights[q] * area_element[q] * band_counts[r]
                if band_counts[r]:  # no sample, no weight
                    out_sum += w_out * shell[r]
                out_weight += w_out
            measured_in = in_sum / in_weight if in_weight > 0 else NAN
            measured_out = out_sum / out_weight if out_weight > 0 else NAN
            s.c_in, s.c_out = measured_in, measured_out
            measured_out = _max(measured_out, measured_in)  # blood dark: no force on the wrong polarity
            for q in range(n):
                c_in[q], c_out[q] = measured_in, measured_out
            scale = _max((measured_out - measured_in) * (measured_out - measured_in), L.min_scale)
        elif L.kind == _LOCAL_MEANS:
            _sample_along(image, world, normal, band_rows, inner_offsets, 0.0, inside, band_counts, threads)
            _sample_along(image, world, normal, band_rows, band_offsets, 0.0, outside, band_counts, threads)
            if not _band_means(L, mass_inverse, band_weights, band_tables_1, band_tables_2, tables_1, tables_2,
                               inside, outside, fields, band_coefficients, band_flat, rhs, smooth, band_means,
                               band_in, band_out):
                return _NO_BAND_DATA
            _local_force(&band_in[0], &band_out[0], n, L.polarity, L.boundary_nepers, &scratch[0, 0], &c_in[0],
                         &c_out[0])
            scale = _median(&scratch[0, 0], n, &scratch[1, 0])
            scale = _max(scale * scale, L.min_scale)
        else:
            for q in range(n):
                c_in[q], c_out[q] = fixed_in[q], fixed_out[q]
            scale = L.fixed_scale
        s.scale = scale
        # the step (Descent.iterate)
        if s.h0_floor < 0:  # fixed per level, on its first observation
            s.h0_floor = 0.3 * _median(&h0[0], n, &scratch[1, 0])
        step = s.step
        _normal_displacement(u, c_in, c_out, scale, 1.0, h0, cos, s.h0_floor, L.min_cos, step, weights,
                             displacement[0])
        _scatter(displacement, L.order, tables_1, tables_2, coefficients)
        _product(&L.constraints_t, &coefficients_flat[0], &rhs[0], n_parameters)
        for i in range(n_parameters):
            dp[i] = reference[i] - p[i]
        _product(&L.smoothing, &dp[0], &projected[0], n_parameters)
        for i in range(n_parameters):
            rhs[i] += projected[i]
        for k in range(L.n_landmarks):  # towards each landmark by at most a step
            dot = 0.0
            for i in range(n_parameters):
                dot += lm_basis[k, i] * p[i]
            residual = (lm_v0[k] - dot) * lm_h0[k]
            residual = _min(_max(residual, -step), step) / lm_h0[k]
            for i in range(n_parameters):
                rhs[i] += lm_pull[i, k] * residual
        _symmetric_product(inverse, &rhs[0], &dp[0])
        for i in range(n_parameters):
            p[i] += dp[i]
        _product(&L.constraints, &dp[0], &coefficients_flat[0], L.n_coefficients)
        _gather(coefficients, L.order, tables_1, tables_2, motion, threads)
        squared = dot = 0.0
        for q in range(n):
            moved[q] *= h0[q]
            squared += weights[q] * moved[q] * moved[q]
            dot += weights[q] * moved[q] * previous[q]
        if s.adaptive:  # Descent._adapt_step
            if s.previous_squared >= 0:
                norms = sqrt(squared * s.previous_squared)
                if norms > 0 and dot < -0.5 * norms:
                    s.step = _max(0.5 * step, s.initial_step / 8)
            for q in range(n):
                previous[q] = moved[q]
            s.previous_squared = squared
        s.motion = sqrt(squared / L.area)
        s.iterations += 1
        if s.motion < tol:
            return _CONVERGED
    return _AT_CAP
