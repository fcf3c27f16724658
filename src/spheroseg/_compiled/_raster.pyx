# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled rasterisation: the cavity's voxel mask and the sector padding.

Both are loops over voxels, compiled (Cython) when the package is built;
they are imported only when called.

Cavity mask (:func:`cavity_mask`)
    The reference is :meth:`spheroseg.Surface.contains` at every voxel centre
    of the surface's bounding box: a voxel is inside when ``v2`` lies in the
    model's range and ``g = v0 - f(v1, v2) <= 0``.  The kernel splits the box
    into cubes of ``BLOCK`` voxels a side and evaluates ``g`` at a
    block's centre: when every voxel centre of the block lies within a ball
    on which ``g`` provably keeps its sign, the block takes the centre's
    status at once; otherwise it splits in eight, down to single voxels,
    whose ``g`` decides them as the reference does.  On a ball of radius
    ``delta`` (mm) around the point,

        |g(y) - g(x)| <= delta L(delta),
        L(delta)^2 = 1 / min h0^2 + F1^2 / min h1^2 + F2^2 / min h2^2

    (the gradient of ``g`` in orthogonal coordinates), with ``h_i`` the
    scale factors (``|grad v_i| = 1 / h_i``) bounded below on the ball:
    ``h1`` is the distance to the long axis in every system, so ``min h1 =
    rho - delta``; prolate ``h0 = h2 = sqrt(r1 r2)`` with ``r1, r2`` the
    distances to the foci; spherical ``h2 = r``; the others are 1.  ``F1``,
    ``F2`` bound ``|df/dv1|``, ``|df/dv2|`` over the patches that the ball
    reaches (``v2`` moves by at most ``delta / min h2`` on it, ``v1`` by at
    most ``delta / min h1``; each patch sampled densely, with a margin).
    A ball never reaches the axis or a focus, where the bound fails.  The
    boundary of the ``v2`` range is the base plane ``x1 = 0`` (prolate,
    spherical with ``v2_range = (0, pi/2)``) or the planes ``z = 0``,
    ``z = height`` (cylindrical): its distance is exact, and a segment that
    leaves that convex range does not come back.  The prolate coordinates come from the distances to the
    foci, without the complex logarithm of the reference; a point within
    ``FAST`` of a decision (far above their error) or near the focal
    segment is redone with the reference's arithmetic, and voxels within
    ``TIE`` of a decision are left to the caller, which decides them as the
    reference does.  Only blocks the surface passes near are split, so the
    cost grows with the surface's area in voxels, not with the volume.

Sector padding (:func:`face_connected_zeros`)
    The exact zeros 6-connected to the image's faces: the zero runs at the
    ends of each row along x (most of a sector's padding) in one parallel
    pass over the image's values, then a span flood fill from the runs
    inside rows that touch them.
"""

import math
import mmap

import numpy as np

from cython.parallel cimport prange
from libc.math cimport INFINITY, asinh, atan2, copysign, fabs, floor, hypot, log, sqrt
from libc.stdint cimport int64_t, uint8_t
from libc.string cimport memset

from ._layout cimport node_offset

from spheroseg._compiled._runtime import PARALLEL_LOCK, current_threads
from spheroseg.geometry.hermite import global_basis, patch_dofs

__all__ = ["cavity_mask", "face_connected_zeros"]


_PROLATE, _SPHERICAL, _CYLINDRICAL = 0, 1, 2
_OUT, _IN, _TIE = 0, 1, 2
_REDO = 3  # (never written: the point is decided again with exact coordinates)
#: voxels this close to a decision (|g| or v2 to an end of its range, in the
#: units of v0 and v2) are decided by the caller in numpy, as the reference
#: does: the compiled arithmetic may round differently
TIE = 1e-9
#: decisions closer than this by the fast prolate coordinates are redone
#: with the reference's arithmetic
FAST = 1e-6
#: voxels across the largest blocks (a power of 2)
BLOCK = 8
#: the slopes of f bounded patch by patch: their largest over
#: (SLOPE_SAMPLES + 1)^2 points of a patch (its edges included), times
#: SLOPE_MARGIN (a derivative is at most cubic along an axis of a patch:
#: between samples 1/12 apart a cubic exceeds their largest by at most
#: 96 / (8 * 144) = 8 %, by Markov's inequality)
SLOPE_SAMPLES = 12
SLOPE_MARGIN = 1.25
#: outputs of this many bytes or more come from :func:`fresh_zeros`
FRESH_ZEROS_BYTES = 1 << 20


def fresh_zeros(shape, dtype) -> np.ndarray:
    """Zeros for a kernel's output, from an anonymous memory map when large.

    numpy advises Linux to back arrays of 4 MiB or more with transparent
    huge pages, and a huge page is zeroed whole when first written: 2 MiB
    for one voxel of the cavity.  An anonymous map's pages are zeros mapped
    4 KiB at a time as they are written (``docs/benchmarks.md``).  A page
    never written costs a fault when first read.  (Arrays the kernels read,
    such as the voxels, keep numpy's pages: copying the voxels to float32
    was slower in 4 KiB pages.)
    """
    dtype = np.dtype(dtype)
    size = int(np.prod(shape)) * dtype.itemsize
    if size < FRESH_ZEROS_BYTES:
        return np.zeros(shape, dtype=dtype)
    return np.frombuffer(mmap.mmap(-1, size), dtype=dtype).reshape(shape)


cdef enum:
    C_PROLATE = 0
    C_SPHERICAL = 1
    C_CYLINDRICAL = 2
    C_OUT = 0
    C_IN = 1
    C_TIE = 2
    C_REDO = 3

cdef double C_TIE_GAP = TIE
cdef double C_FAST = FAST
cdef double PI = math.pi


cdef inline double _max(double a, double b) noexcept nogil:
    """Python's ``max(a, b)``: ``b`` only when it is greater."""
    return b if b > a else a


cdef inline double _min(double a, double b) noexcept nogil:
    """Python's ``min(a, b)``: ``b`` only when it is smaller."""
    return b if b < a else a


cdef inline void _hermite_at(double t, double width, int derivative, double* out) noexcept nogil:
    if derivative == 0:
        out[0] = 1 - 3 * t * t + 2 * t * t * t
        out[1] = width * (t * (t - 1) * (t - 1))
        out[2] = t * t * (3 - 2 * t)
        out[3] = width * (t * t * (t - 1))
    else:
        out[0] = 6 * t * (t - 1) / width
        out[1] = (3 * t - 1) * (t - 1)
        out[2] = 6 * t * (1 - t) / width
        out[3] = t * (3 * t - 2)


def hermite_at(double t, double width, int derivative):
    """:func:`spheroseg.hermite.global_basis` at one point (``derivative``
    0 or 1), compiled."""
    cdef double out[4]
    _hermite_at(t, width, derivative, out)
    return out[0], out[1], out[2], out[3]


cdef inline (double, double, double, double) _prolate_fast(double x1, double rho, double param) noexcept nogil:
    """Prolate ``(v0, v2)`` and the distances ``r1, r2`` to the foci, without
    the complex logarithm: ``cosh v0 = (r1 + r2) / 2a``, ``tan v2 = rho
    cosh v0 / (x1 sinh v0)``.  Accurate to ~1e-10 except within ~1e-3 of the
    focal segment (``v0 -> 0``), where it returns ``v0 = -1`` to say so."""
    cdef double r1 = sqrt((x1 - param) * (x1 - param) + rho * rho)
    cdef double r2 = sqrt((x1 + param) * (x1 + param) + rho * rho)
    cdef double c = 0.5 * (r1 + r2) / param
    if c < 1.0 + 5e-7:
        return -1.0, 0.0, r1, r2
    cdef double s = sqrt((c - 1.0) * (c + 1.0))
    return log(c + s), atan2(rho * c, x1 * s), r1, r2


cdef inline (double, double) _csqrt(double a, double b) noexcept nogil:
    """The principal square root of ``a + ib``."""
    cdef double r = hypot(a, b), t
    if r == 0.0:
        return 0.0, b
    if a >= 0.0:
        t = sqrt(0.5 * (r + a))
        return t, b / (2.0 * t)
    t = sqrt(0.5 * (r - a))
    return fabs(b) / (2.0 * t), copysign(t, b)


cdef inline (double, double) _acosh(double x, double y) noexcept nogil:
    """``cmath.acosh(x + iy)`` by CPython's formula: ``asinh(Re(s1* s2))``
    and ``2 atan2(Im s1, Re s2)`` with ``s1 = sqrt(z - 1)``, ``s2 = sqrt(z + 1)``."""
    cdef double s1r, s1i, s2r, s2i
    s1r, s1i = _csqrt(x - 1.0, y)
    s2r, s2i = _csqrt(x + 1.0, y)
    return asinh(s1r * s2r + s1i * s2i), 2.0 * atan2(s1i, s2r)


cdef (int, bint) _status(double x1, double x2, double x3, int kind, double param, const double[:, :, ::1] coef,
                         double lo, double hi, bint standard_range, const double[:, :, ::1] slopes,
                         double reach) noexcept nogil:
    """Status of the local point (_OUT, _IN or _TIE: too close to call), and
    whether every point within ``reach`` (mm) provably shares it (always
    for ``reach = 0``; never for _TIE at ``reach > 0``)."""
    cdef double rho, v0, v2, r1, r2, tie
    cdef int code
    cdef bint shared
    if kind == C_PROLATE:
        # the fast coordinates decide only the points FAST clear of a
        # decision (their error is below 1e-10 there); the others, as the
        # reference computes them
        rho = sqrt(x2 * x2 + x3 * x3)
        v0, v2, r1, r2 = _prolate_fast(x1, rho, param)
        if v0 < 0.0:
            return _status_exact(x1, x2, x3, kind, param, coef, lo, hi, standard_range, slopes, reach)
        tie = C_FAST
    else:
        # as CoordinateSystem.from_cartesian
        rho = hypot(x2, x3)
        if kind == C_SPHERICAL:
            v0 = hypot(x1, rho)
            v2 = atan2(rho, x1)
            r1 = r2 = v0
        else:
            v0 = rho
            v2 = x1
            r1 = r2 = INFINITY
        tie = C_TIE_GAP
    code, shared = _classify(x1, x2, x3, rho, v0, v2, r1, r2, tie, kind, param, coef, lo, hi, standard_range,
                             slopes, reach)
    if code == C_REDO:
        return _status_exact(x1, x2, x3, kind, param, coef, lo, hi, standard_range, slopes, reach)
    return code, shared


def status(double x1, double x2, double x3, int kind, double param, const double[:, :, ::1] coef, double lo,
           double hi, bint standard_range, const double[:, :, ::1] slopes, double reach):
    """:func:`_status` from Python: ``(code, shared)``."""
    code, shared = _status(x1, x2, x3, kind, param, coef, lo, hi, standard_range, slopes, reach)
    return code, bool(shared)


cdef (int, bint) _status_exact(double x1, double x2, double x3, int kind, double param,
                               const double[:, :, ::1] coef, double lo, double hi, bint standard_range,
                               const double[:, :, ::1] slopes, double reach) noexcept nogil:
    """:func:`status` of a prolate point with its coordinates as the
    reference computes them (the complex arccosh)."""
    cdef double rho = hypot(x2, x3), wr, wi
    wr, wi = _acosh(x1 / param, rho / param)
    cdef double r1 = hypot(x1 - param, rho)
    cdef double r2 = hypot(x1 + param, rho)
    return _classify(x1, x2, x3, rho, fabs(wr), fabs(wi), r1, r2, C_TIE_GAP, kind, param, coef, lo, hi,
                     standard_range, slopes, reach)


cdef (int, bint) _classify(double x1, double x2, double x3, double rho, double v0, double v2, double r1, double r2,
                           double tie, int kind, double param, const double[:, :, ::1] coef, double lo, double hi,
                           bint standard_range, const double[:, :, ::1] slopes, double reach) noexcept nogil:
    """The status of a point from its model coordinates: too close to call
    within ``tie`` of a decision (_REDO with the fast prolate coordinates,
    to be redone exactly; _TIE with the exact ones, left to the caller)."""
    cdef double plane, f, v1, g, bound
    cdef int code
    # distance (mm) to the boundary of the v2 range, when it is a plane
    if standard_range:
        plane = _min(fabs(x1), fabs(param - x1)) if kind == C_CYLINDRICAL else fabs(x1)
    else:
        plane = 0.0
    if fabs(v2 - lo) < tie or fabs(v2 - hi) < tie:
        return (C_TIE if tie == C_TIE_GAP else C_REDO), reach == 0.0
    # shrunk by 1e-9: the distances are rounded
    if not (v2 >= lo and v2 <= hi):
        return C_OUT, reach == 0.0 or reach < plane * (1.0 - 1e-9)
    f, v1 = _surface(x2, x3, v2, coef, lo, hi)
    g = v0 - f
    if fabs(g) < tie:
        return (C_TIE if tie == C_TIE_GAP else C_REDO), reach == 0.0
    code = C_IN if g <= 0 else C_OUT
    if reach == 0.0:
        return code, True
    if not reach < 0.999 * _min(_min(rho, r1), r2) or (code == C_IN and not reach < plane * (1.0 - 1e-9)):
        return code, False
    bound = _gradient_bound(reach, kind, r1, r2, rho, v1, v2, lo, hi, slopes)
    return code, reach * bound < fabs(g) * (1.0 - 1e-9)


cdef inline (double, double) _surface(double x2, double x3, double v2, const double[:, :, ::1] coef, double lo,
                                      double hi) noexcept nogil:
    """``f(v1, v2)`` and ``v1 = atan2(x3, x2)``."""
    # as np.mod(arctan2, 2 pi) does for angles in [-pi, pi]
    cdef double v1 = atan2(x3, x2)
    if v1 < 0:
        v1 += 2 * PI
    cdef Py_ssize_t n2 = coef.shape[0] - 1, n1 = coef.shape[1]
    cdef double u1 = v1 * (n1 / (2 * PI))
    cdef double u2 = (v2 - lo) * (n2 / (hi - lo))
    cdef Py_ssize_t i1 = min(max(<Py_ssize_t>floor(u1), 0), n1 - 1)
    cdef Py_ssize_t i2 = min(max(<Py_ssize_t>floor(u2), 0), n2 - 1)
    cdef double b1[4]
    cdef double b2[4]
    _hermite_at(u1 - i1, 2 * PI / n1, 0, b1)
    _hermite_at(u2 - i2, (hi - lo) / n2, 0, b2)
    cdef double f = 0.0
    cdef int a1, a2, e1, e2
    cdef const double* nodes = &coef[0, 0, 0]
    for a1 in range(2):
        for a2 in range(2):
            for e1 in range(2):
                for e2 in range(2):
                    f += b1[2 * a1 + e1] * b2[2 * a2 + e2] * nodes[node_offset(n1, i1, i2, a1, a2, e1, e2)]
    return f, v1


cdef double _gradient_bound(double delta, int kind, double r1, double r2, double rho, double v1, double v2,
                            double lo, double hi, const double[:, :, ::1] slopes) noexcept nogil:
    cdef double m2, spread, m1, f1, f2, radial
    cdef Py_ssize_t n2 = slopes.shape[0], n1 = slopes.shape[1], first, last, left, right, row, column, c
    if kind == C_PROLATE:  # h0 = h2 >= sqrt((r1 - delta) (r2 - delta))
        m2 = sqrt((r1 - delta) * (r2 - delta))
    elif kind == C_SPHERICAL:  # h0 = 1, h2 = r >= r1 - delta
        m2 = r1 - delta
    else:
        m2 = 1.0
    # |grad v2| = 1 / h2: on the ball v2 stays within delta / m2 of the centre's
    spread = delta / m2
    first, last = 0, n2 - 1
    if spread < hi - lo:
        first = min(max(<Py_ssize_t>floor((v2 - spread - lo) * n2 / (hi - lo)), 0), n2 - 1)
        last = min(max(<Py_ssize_t>floor((v2 + spread - lo) * n2 / (hi - lo)), first), n2 - 1)
    m1 = rho - delta  # h1 = rho
    # |grad v1| = 1 / h1: v1 stays within delta / m1 of the centre's (it
    # wraps; 1e-9 more for its rounding)
    spread = delta / m1 + 1e-9
    left, right = 0, n1 - 1
    if spread < PI:
        left = <Py_ssize_t>floor((v1 - spread) * n1 / (2 * PI))
        right = <Py_ssize_t>floor((v1 + spread) * n1 / (2 * PI))
    f1 = 0.0
    f2 = 0.0
    for row in range(first, last + 1):
        for column in range(left, right + 1):
            c = column % n1
            if c < 0:
                c += n1
            f1 = _max(f1, slopes[row, c, 0])
            f2 = _max(f2, slopes[row, c, 1])
    if kind == C_PROLATE:
        radial = (1.0 + f2 * f2) / (m2 * m2)
    elif kind == C_SPHERICAL:
        radial = 1.0 + (f2 / m2) * (f2 / m2)
    else:
        radial = 1.0 + f2 * f2
    return sqrt(radial + (f1 / m1) * (f1 / m1))


def gradient_bound(double delta, int kind, double r1, double r2, double rho, double v1, double v2, double lo,
                   double hi, const double[:, :, ::1] slopes):
    """Upper bound of ``|grad g|`` on the ball of radius ``delta`` (mm)
    around a point at ``(v1, v2)``: the root sum of squares of the three
    terms (the coordinates are orthogonal), each with its scale factor
    bounded below on the ball, and the slopes of ``f`` bounded over the
    patches the ball reaches (``slopes[i2, i1]``: ``|df/dv1|``,
    ``|df/dv2|``)."""
    return _gradient_bound(delta, kind, r1, r2, rho, v1, v2, lo, hi, slopes)


cdef inline double _reach(const double* affine, double ei, double ej, double ek) noexcept nogil:
    """Largest distance (mm) from the centre of a block of voxel centres,
    ``ei x ej x ek`` voxel steps across, to its corners."""
    cdef double best = 0.0, sj, sk, dx, dy, dz
    cdef int a, b
    for a in range(2):
        sj = -1.0 if a == 0 else 1.0
        for b in range(2):
            sk = -1.0 if b == 0 else 1.0
            dx = 0.5 * (ei * affine[0] + sj * ej * affine[1] + sk * ek * affine[2])
            dy = 0.5 * (ei * affine[3] + sj * ej * affine[4] + sk * ek * affine[5])
            dz = 0.5 * (ei * affine[6] + sj * ej * affine[7] + sk * ek * affine[8])
            best = _max(best, sqrt(dx * dx + dy * dy + dz * dz))
    return best


cdef struct Box:
    # the box [start, stop) (x, y, z), the voxel index -> local point map
    int64_t start[3]
    int64_t stop[3]
    double affine[9]
    double offset[3]
    int kind
    double param, lo, hi
    bint standard_range
    int64_t size


cdef int64_t _fill_block(uint8_t[:, :, ::1] out, int64_t k_top, int64_t j_top, int64_t i_top, const Box* box,
                         const double[:, :, ::1] coef, const double[:, :, ::1] slopes) noexcept nogil:
    """One top block (box index of its corner): a block whose centre's ball
    (its status shared, :func:`status`) holds every voxel centre of the
    block takes that status at once; the others split in eight, down to
    single voxels.  Returns the number of voxels left too close to call."""
    cdef int64_t ni = box.stop[0] - box.start[0], nj = box.stop[1] - box.start[1], nk = box.stop[2] - box.start[2]
    cdef int64_t ties = 0, top = 1, k0, j0, i0, s, k1, j1, i1, h, k, j, i
    cdef int64_t stack[8 * 8 * 4]  # (k0, j0, i0, size): 7 a level deep
    cdef const double* a = box.affine
    cdef double ci, cj, ck, x1, x2, x3, reach
    cdef int code, dk, dj, di
    cdef bint single, shared
    stack[0], stack[1], stack[2], stack[3] = k_top, j_top, i_top, box.size
    while top > 0:
        top -= 1
        k0, j0, i0, s = stack[4 * top], stack[4 * top + 1], stack[4 * top + 2], stack[4 * top + 3]
        k1, j1, i1 = min(k0 + s, nk), min(j0 + s, nj), min(i0 + s, ni)
        if k1 <= k0 or j1 <= j0 or i1 <= i0:
            continue
        # the centre of the block's voxel centres, in the grid's index
        ci = box.start[0] + 0.5 * (i0 + i1 - 1)
        cj = box.start[1] + 0.5 * (j0 + j1 - 1)
        ck = box.start[2] + 0.5 * (k0 + k1 - 1)
        x1 = box.offset[0] + a[0] * ci + a[1] * cj + a[2] * ck
        x2 = box.offset[1] + a[3] * ci + a[4] * cj + a[5] * ck
        x3 = box.offset[2] + a[6] * ci + a[7] * cj + a[8] * ck
        single = k1 - k0 == 1 and j1 - j0 == 1 and i1 - i0 == 1
        reach = 0.0 if single else _reach(a, i1 - 1 - i0, j1 - 1 - j0, k1 - 1 - k0)
        code, shared = _status(x1, x2, x3, box.kind, box.param, coef, box.lo, box.hi, box.standard_range, slopes,
                               reach)
        if shared:
            if code == C_TIE:
                ties += 1
            if code != C_OUT:
                for k in range(box.start[2] + k0, box.start[2] + k1):
                    for j in range(box.start[1] + j0, box.start[1] + j1):
                        for i in range(box.start[0] + i0, box.start[0] + i1):
                            out[k, j, i] = code
            continue
        h = (s + 1) // 2
        for dk in range(2):
            for dj in range(2):
                for di in range(2):
                    stack[4 * top] = k0 + dk * h
                    stack[4 * top + 1] = j0 + dj * h
                    stack[4 * top + 2] = i0 + di * h
                    stack[4 * top + 3] = h
                    top += 1
    return ties


cdef void _cavity_blocks(uint8_t[:, :, ::1] out, const Box* box, const double[:, :, ::1] coef,
                         const double[:, :, ::1] slopes, int64_t[::1] ties, int threads) noexcept nogil:
    """Fill the box of ``out`` block by block (:func:`_fill_block`), the top
    blocks in parallel; ``ties[b]``: the voxels of top block ``b`` left too
    close to call."""
    cdef int64_t size = box.size
    cdef int64_t ni = box.stop[0] - box.start[0], nj = box.stop[1] - box.start[1], nk = box.stop[2] - box.start[2]
    cdef int64_t bk = (nk + size - 1) // size, bj = (nj + size - 1) // size, bi = (ni + size - 1) // size
    cdef Py_ssize_t block
    # dynamic: the blocks the surface crosses cost far more than the others
    for block in prange(bk * bj * bi, schedule="dynamic", num_threads=threads, use_threads_if=threads > 1):
        ties[block] = _fill_block(out, (block // (bj * bi)) * size, ((block // bi) % bj) * size, (block % bi) * size,
                                  box, coef, slopes)


def _positions(const uint8_t[:, :, ::1] out, const int64_t[::1] start, const int64_t[::1] stop, int64_t size,
               const int64_t[::1] ties):
    """The indices ``(k, j, i)`` of the _TIE voxels of the box ``[start,
    stop)``, from the top blocks that have them (``ties`` as
    :func:`_cavity_blocks` counts them)."""
    found_array = np.empty((int(np.sum(ties)), 3), dtype=np.int64)
    cdef int64_t[:, ::1] found = found_array
    cdef int64_t ni = stop[0] - start[0], nj = stop[1] - start[1]
    cdef int64_t bj = (nj + size - 1) // size, bi = (ni + size - 1) // size
    cdef int64_t n = 0, k0, j0, i0, k, j, i
    cdef Py_ssize_t block
    with nogil:
        for block in range(ties.shape[0]):
            if ties[block] == 0:
                continue
            k0 = start[2] + (block // (bj * bi)) * size
            j0 = start[1] + ((block // bi) % bj) * size
            i0 = start[0] + (block % bi) * size
            for k in range(k0, min(k0 + size, stop[2])):
                for j in range(j0, min(j0 + size, stop[1])):
                    for i in range(i0, min(i0 + size, stop[0])):
                        if out[k, j, i] == C_TIE:
                            found[n, 0], found[n, 1], found[n, 2] = k, j, i
                            n += 1
    return found_array


def patch_slopes(coefficients, lo, hi, samples):
    """The largest ``|df/dv1|``, ``|df/dv2|`` over ``samples + 1`` squared
    points of each patch (its edges included), ``[i2, i1, 2]``.  (numpy: it runs
    once a mask.)"""
    n2, n1 = coefficients.shape[0] - 1, coefficients.shape[1]
    t = np.arange(samples + 1) / samples
    (b1, d1), (b2, d2) = ((global_basis(t, width, 0).T, global_basis(t, width, 1).T)  # [sample, 2 node + dof]
                          for width in (2 * np.pi / n1, (hi - lo) / n2))
    # each patch's 16 dofs [i2, i1, 2 a2 + e2, 2 a1 + e1]
    dofs = np.asarray(coefficients, dtype=float).ravel()[patch_dofs(n1, n2)].swapaxes(2, 3)
    df1 = b2 @ dofs @ d1.T  # [i2, i1, sample along v2, sample along v1]
    df2 = d2 @ dofs @ b1.T
    return np.stack([np.abs(df1).max(axis=(2, 3)), np.abs(df2).max(axis=(2, 3))], axis=-1)


def cavity_mask(shape, start, stop, affine, offset, kind, param, coefficients, v2_range, standard_range):
    """Voxel status in the index box ``[start, stop)`` (x, y, z order) of a
    grid of ``shape`` ([z, y, x]): 0 outside the cavity (and outside the
    box), 1 inside, 2 too close to call (left to the caller, with their
    indices ``(k, j, i)``).  The local model point of index ``idx`` is
    ``affine @ idx + offset``; ``kind`` is ``"prolate"``, ``"spherical"`` or
    ``"cylindrical"`` and ``param`` its focal length or height;
    ``standard_range``: the ``v2`` range ends on the base plane (and for
    cylinders the plane ``z = height``).  The slopes of ``f`` are bounded
    patch by patch (:func:`patch_slopes`, :data:`SLOPE_SAMPLES`).

    Returns
    -------
    codes : array of uint8, ``shape``
    ties : array (n, 3) of int
    """
    start = np.asarray(start, dtype=np.int64)
    stop = np.asarray(stop, dtype=np.int64)
    codes = fresh_zeros(shape, np.uint8)
    blocks = int(np.prod(-(-(stop - start) // BLOCK)))
    ties = np.zeros(blocks, dtype=np.int64)
    coefficients = np.ascontiguousarray(coefficients, dtype=float)
    lo, hi = float(v2_range[0]), float(v2_range[1])
    # per patch, not per row of patches: a ball reaches one or two patches
    # around the axis, whose own slopes decide more blocks at once
    slopes = SLOPE_MARGIN * patch_slopes(coefficients, lo, hi, SLOPE_SAMPLES) + 1e-9
    affine = np.ascontiguousarray(affine, dtype=float)
    offset = np.asarray(offset, dtype=float)
    cdef Box box
    cdef int i
    for i in range(3):
        box.start[i], box.stop[i], box.offset[i] = start[i], stop[i], offset[i]
    for i in range(9):
        box.affine[i] = affine[i // 3, i % 3]
    box.kind = {"prolate": _PROLATE, "spherical": _SPHERICAL, "cylindrical": _CYLINDRICAL}[kind]
    box.param, box.lo, box.hi, box.standard_range, box.size = float(param), lo, hi, bool(standard_range), BLOCK
    cdef uint8_t[:, :, ::1] out = codes
    cdef const double[:, :, ::1] coef = coefficients, slope_view = slopes
    cdef int64_t[::1] tie_view = ties
    cdef int threads = current_threads()
    with nogil:
        _cavity_blocks(out, &box, coef, slope_view, tie_view, threads)
    return codes, _positions(codes, start, stop, BLOCK, ties)


cdef int64_t _row_ends(const float[:, :, ::1] values, uint8_t[:, :, ::1] out, int64_t[:, ::1] first,
                       int64_t[:, ::1] last, int64_t[:, ::1] inner, int64_t[::1] counts, int threads) noexcept nogil:
    """The zero runs at both ends of every row along x into ``out``, each
    row's first and last non-zero (``first = nx``, ``last = nx - 1`` for a
    row of zeros) and its number of zeros between them, and the number of
    voxels filled; rows in parallel (they are independent), so that the
    serial flood visits only the rows with zeros inside."""
    cdef Py_ssize_t nz = values.shape[0], ny = values.shape[1], nx = values.shape[2], k
    cdef int64_t total = 0
    for k in prange(nz, schedule="static", num_threads=threads, use_threads_if=threads > 1):
        counts[k] = _plane_ends(values, out, first, last, inner, k)
    for k in range(nz):
        total += counts[k]
    return total


cdef int64_t _plane_ends(const float[:, :, ::1] values, uint8_t[:, :, ::1] out, int64_t[:, ::1] first,
                         int64_t[:, ::1] last, int64_t[:, ::1] inner, Py_ssize_t k) noexcept nogil:
    cdef Py_ssize_t ny = values.shape[1], nx = values.shape[2], j
    cdef int64_t a, b, ends, count = 0
    for j in range(ny):
        a, b, inner[k, j] = _row_scan(&values[k, j, 0], nx)
        b = max(b, a - 1)
        memset(&out[k, j, 0], 1, a)
        memset(&out[k, j, 0] + b + 1, 1, nx - 1 - b)
        first[k, j] = a
        last[k, j] = b
        ends = a + nx - 1 - b
        inner[k, j] -= ends
        count += ends
    return count


cdef inline (int64_t, int64_t, int64_t) _row_scan(const float* row, Py_ssize_t nx) noexcept nogil:
    """A row's first and last non-zero (``nx`` and -1 for none) and its
    zeros: a loop without an exit or a branch (vectorised), where the scans
    that stopped at the ends' first non-zero took longer."""
    cdef int64_t a = nx, b = -1, zeros = 0, i
    cdef bint data
    for i in range(nx):
        data = row[i] != 0
        zeros += not data
        a = min(a, i if data else nx)
        b = max(b, i if data else -1)
    return a, b, zeros


cdef int64_t _flood_zeros(const float[:, :, ::1] values, uint8_t[:, :, ::1] out, int64_t[::1] stack,
                          int64_t[:, ::1] first, int64_t[:, ::1] last, int64_t[:, ::1] inner, int64_t[::1] counts,
                          int threads) noexcept nogil:
    """The zeros of ``values`` 6-connected to the faces, into ``out``;
    their count, or -1 if ``stack`` overflows.

    A sector's padding is mostly the zero runs at both ends of each row
    along x, which touch an x face: they are filled in one parallel pass
    that also finds the rows with zeros inside.  Those zero runs are
    padding when they lie on a y or z face or touch an end run of one of
    the four neighbouring rows: they seed a span flood fill (fill a run,
    then seed the runs of the neighbouring rows that touch it) through the
    remaining zeros."""
    cdef Py_ssize_t nz = values.shape[0], ny = values.shape[1], nx = values.shape[2], size = stack.shape[0]
    cdef int64_t count = _row_ends(values, out, first, last, inner, counts, threads)
    cdef int64_t top = 0, m, a, b, p, i, j, k, kk, jj
    cdef int n
    cdef bint face, seed
    cdef int64_t dks[4]
    cdef int64_t djs[4]
    dks[0], dks[1], dks[2], dks[3] = -1, 1, 0, 0
    djs[0], djs[1], djs[2], djs[3] = 0, 0, -1, 1
    for k in range(nz):
        for j in range(ny):
            if inner[k, j] == 0:
                continue
            face = k == 0 or k == nz - 1 or j == 0 or j == ny - 1
            m = first[k, j] + 1
            while m < last[k, j]:
                if values[k, j, m] != 0:
                    m += 1
                    continue
                a = m
                while values[k, j, m] == 0:  # ends at the row's last non-zero
                    m += 1
                seed = face
                for n in range(4):
                    if seed:
                        break
                    kk, jj = k + dks[n], j + djs[n]
                    if 0 <= kk < nz and 0 <= jj < ny:  # [a, m) meets the end runs of row (kk, jj)
                        seed = a < first[kk, jj] or m - 1 > last[kk, jj]
                if seed:
                    if top == size:
                        return -1
                    stack[top] = (k * ny + j) * nx + a
                    top += 1
    while top > 0:
        top -= 1
        p = stack[top]
        i = p % nx
        j = (p // nx) % ny
        k = p // (nx * ny)
        if out[k, j, i]:
            continue
        a = i
        while a > 0 and values[k, j, a - 1] == 0 and not out[k, j, a - 1]:
            a -= 1
        b = i
        while b < nx - 1 and values[k, j, b + 1] == 0 and not out[k, j, b + 1]:
            b += 1
        for m in range(a, b + 1):
            out[k, j, m] = 1
        count += b - a + 1
        inner[k, j] -= b - a + 1
        for n in range(4):
            kk, jj = k + dks[n], j + djs[n]
            if kk < 0 or kk >= nz or jj < 0 or jj >= ny or inner[kk, jj] == 0:  # nothing left to fill there
                continue
            m = a
            while m <= b:
                if values[kk, jj, m] == 0 and not out[kk, jj, m]:
                    if top == size:
                        return -1  # the caller retries with a larger stack
                    stack[top] = (kk * ny + jj) * nx + m
                    top += 1
                    while m <= b and values[kk, jj, m] == 0 and not out[kk, jj, m]:
                        m += 1
                else:
                    m += 1
    return count


def face_connected_zeros(array) -> tuple:
    """The exact zeros 6-connected to the faces of a 3D array, and their count."""
    array = np.asarray(array)
    # the kernel reads float32 (a volume's voxels) in place; other types as
    # their non-zeros, exactly (float64's tiny values would round to 0)
    if array.dtype == np.float32:
        values_array = np.ascontiguousarray(array)
    else:
        values_array = np.not_equal(array, 0, out=np.empty(array.shape, dtype=np.float32))
    cdef const float[:, :, ::1] values = values_array
    nz, ny = values_array.shape[:2]
    cdef int64_t[:, ::1] first = np.empty((nz, ny), dtype=np.int64)  # the row's first and last non-zero
    cdef int64_t[:, ::1] last = np.empty((nz, ny), dtype=np.int64)
    cdef int64_t[:, ::1] inner = np.empty((nz, ny), dtype=np.int64)  # its zeros between them, unfilled
    cdef int64_t[::1] counts = np.empty(nz, dtype=np.int64)
    cdef uint8_t[:, :, ::1] out_view
    cdef int64_t[::1] stack
    cdef int64_t count
    cdef int threads = current_threads()
    # seeds (one a run), then run starts: a voxel can be pushed from each of
    # its four neighbouring rows before it is filled, so in the worst case 5
    # a voxel (a sector's padding needs a few hundred); a stack that
    # overflows makes the kernel return -1
    size = 4096
    while True:
        out = fresh_zeros(values_array.shape, bool)
        out_view = out.view(np.uint8)
        stack = np.empty(size, dtype=np.int64)
        with PARALLEL_LOCK:  # its row pass is a parallel kernel
            with nogil:
                count = _flood_zeros(values, out_view, stack, first, last, inner, counts, threads)
        if count >= 0:
            return out, int(count)
        size = min(8 * size, 5 * values_array.size + 16)
