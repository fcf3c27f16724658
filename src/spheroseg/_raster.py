"""Compiled rasterisation: the cavity's voxel mask and the sector padding.

Both are loops over voxels that numba compiles; they are imported only when
called (``import spheroseg`` does not load numba).

Cavity mask (:func:`cavity_mask`)
    The reference is :meth:`spheroseg.Surface.contains` at every voxel centre
    of the surface's bounding box: a voxel is inside when ``v2`` lies in the
    model's range and ``g = v0 - f(v1, v2) <= 0``.  Along each row of voxels
    (the image's ``i`` axis) the kernel evaluates ``g`` exactly, as the
    reference does, but skips the voxels that provably share the status of
    the one it evaluated, by *sphere tracing*: within a ball of radius
    ``delta`` (mm) around the point,

        |g(y) - g(x)| <= delta L(delta),
        L(delta) = 1 / min h0 + F1 / min h1 + F2 / min h2

    with ``h_i`` the scale factors (``|grad v_i| = 1 / h_i``), bounded below
    on the ball: ``h1`` is the distance to the long axis in every system,
    so ``min h1 = rho - delta``; prolate ``h0 = h2 = sqrt(r1 r2)`` with
    ``r1, r2`` the distances to the foci; spherical ``h2 = r``; the others
    are 1.  ``F1``, ``F2`` bound ``|df/dv1|``, ``|df/dv2|`` over the whole
    surface (sampled densely by the caller, with a margin).  So every voxel
    within ``delta`` with ``delta L(delta) < |g|`` shares the point's status;
    near the axis or the foci the bound grows and the step falls back to
    single voxels.  The boundary of the ``v2`` range is the base plane
    ``x1 = 0`` (prolate, spherical with ``v2_range = (0, pi/2)``) or the
    planes ``z = 0``, ``z = height`` (cylindrical): its distance is exact,
    and a segment that leaves that convex range does not come back.  Voxels
    within ``TIE`` of a decision are left to the caller, which decides them
    with the reference arithmetic.  The cost grows with the number of rows
    and the surface's area in voxels, not with the volume.
 Cost grows with
    the rows and the surface's area in voxels, not with the volume.

Sector padding (:func:`face_connected_zeros`)
    The exact zeros 6-connected to the image's faces: the zero runs at the
    ends of each row along x (most of a sector's padding) in one pass, then
    a span flood fill from the runs inside rows that touch them.
"""

from __future__ import annotations

import cmath
import math
import sys

import numpy as np
from numba import njit, prange

__all__ = ["cavity_mask", "face_connected_zeros", "compilations"]


_PROLATE, _SPHERICAL, _CYLINDRICAL = 0, 1, 2
_OUT, _IN, _TIE = 0, 1, 2
#: voxels this close to a decision (|g| or v2 to an end of its range, in the
#: units of v0 and v2) are decided by the caller in numpy, as the reference
#: does: the compiled arithmetic may round differently
TIE = 1e-9


@njit(cache=True, inline="always")
def _hermite(t, width, derivative):
    """Cubic Hermite basis (value and slope dofs in global units) at ``t``."""
    if derivative == 0:
        return (1 - 3 * t * t + 2 * t * t * t, width * (t * (t - 1) * (t - 1)), t * t * (3 - 2 * t),
                width * (t * t * (t - 1)))
    return (6 * t * (t - 1) / width, (3 * t - 1) * (t - 1), 6 * t * (1 - t) / width, t * (3 * t - 2))


@njit(cache=True)
def _status(x1, x2, x3, kind, param, coef, lo, hi, standard_range, step, slope1, slope2):
    """Status of the local point (_OUT, _IN or _TIE: too close to call), and
    the number of further voxels along the row (``step`` mm apart) that
    share it."""
    # model coordinates, as CoordinateSystem.from_cartesian
    rho = math.hypot(x2, x3)
    if kind == _PROLATE:
        w = cmath.acosh(complex(x1, rho) / param)
        v0 = abs(w.real)
        v2 = abs(w.imag)
    elif kind == _SPHERICAL:
        v0 = math.hypot(x1, rho)
        v2 = math.atan2(rho, x1)
    else:
        v0 = rho
        v2 = x1
    # distance (mm) to the boundary of the v2 range, when it is a plane
    if standard_range:
        plane = min(abs(x1), abs(param - x1)) if kind == _CYLINDRICAL else abs(x1)
    else:
        plane = 0.0
    if abs(v2 - lo) < TIE or abs(v2 - hi) < TIE:
        return _TIE, 0
    if not (v2 >= lo and v2 <= hi):
        return _OUT, int(plane / step)
    v1 = math.atan2(x3, x2) % (2 * math.pi)
    # f at the point (its slopes are bounded over the whole surface by the caller)
    n2, n1 = coef.shape[0] - 1, coef.shape[1]
    w1 = 2 * math.pi / n1
    w2 = (hi - lo) / n2
    u1 = (v1 % (2 * math.pi)) * (n1 / (2 * math.pi))
    u2 = (v2 - lo) * (n2 / (hi - lo))
    i1 = min(max(int(math.floor(u1)), 0), n1 - 1)
    i2 = min(max(int(math.floor(u2)), 0), n2 - 1)
    t1 = u1 - i1
    t2 = u2 - i2
    b1 = _hermite(t1, w1, 0)
    b2 = _hermite(t2, w2, 0)
    f = 0.0
    for a1 in range(2):
        node1 = (i1 + a1) % n1
        for a2 in range(2):
            node2 = i2 + a2
            for e1 in range(2):
                for e2 in range(2):
                    f += b1[2 * a1 + e1] * b2[2 * a2 + e2] * coef[node2, node1, e1 + 2 * e2]
    g = v0 - f
    if abs(g) < TIE:
        return _TIE, 0
    inside = g <= 0
    # the largest ball on which g cannot reach 0 (module docstring)
    if kind == _PROLATE:
        r1 = math.sqrt((x1 - param) ** 2 + rho * rho)
        r2 = math.sqrt((x1 + param) ** 2 + rho * rho)
        near = min(rho, r1, r2)
    elif kind == _SPHERICAL:
        r1 = r2 = v0
        near = min(rho, v0)
    else:
        r1 = r2 = math.inf
        near = rho
    radius = 0.0
    delta = 0.0
    for _ in range(4):
        delta = min(delta, 0.999 * near)
        if kind == _PROLATE:
            m0 = math.sqrt((r1 - delta) * (r2 - delta))
            m2 = m0
        elif kind == _SPHERICAL:
            m0, m2 = 1.0, r1 - delta
        else:
            m0, m2 = 1.0, 1.0
        if not (m0 > 0 and m2 > 0 and rho - delta > 0):
            break
        bound = 1.0 / m0 + slope1 / (rho - delta) + slope2 / m2
        if delta > 0 and delta * bound < abs(g):
            radius = delta
            break
        # bound grows with delta: |g| / bound(delta_k) satisfies the test
        # with bound(delta_k) in place of bound(delta_{k+1})
        delta = abs(g) / bound
    radius = radius * (1.0 - 1e-9)
    if inside:
        radius = min(radius, plane)
    code = _IN if inside else _OUT
    if not radius < 1e30:  # inf or NaN
        return code, 0
    return code, int(radius / step)


@njit(cache=True, parallel=True)
def _cavity_rows(out, start, affine, offset, kind, param, coef, lo, hi, standard_range, step, slope1, slope2):
    nk, nj, ni = out.shape
    for row in prange(nk * nj):
        k = row // nj
        j = row % nj
        fj = start[1] + j
        fk = start[2] + k
        bx = offset[0] + affine[0, 1] * fj + affine[0, 2] * fk
        by = offset[1] + affine[1, 1] * fj + affine[1, 2] * fk
        bz = offset[2] + affine[2, 1] * fj + affine[2, 2] * fk
        i = 0
        while i < ni:
            fi = start[0] + i
            code, n = _status(bx + affine[0, 0] * fi, by + affine[1, 0] * fi, bz + affine[2, 0] * fi,
                                kind, param, coef, lo, hi, standard_range, step, slope1, slope2)
            stop = min(i + n + 1, ni)
            if code != _OUT:
                for m in range(i, stop):
                    out[k, j, m] = code
            i = stop


def cavity_mask(start, stop, affine, offset, kind, param, coefficients, v2_range, standard_range, slopes):
    """Voxel status in the index box ``[start, stop)`` (x, y, z order) of a
    grid: 0 outside the cavity, 1 inside, 2 too close to call (left to the
    caller); shape ``stop - start`` reversed ([z, y, x]).  The local model
    point of index ``idx`` is ``affine @ idx + offset``; ``kind`` is
    ``"prolate"``, ``"spherical"`` or ``"cylindrical"`` and ``param`` its
    focal length or height; ``standard_range``: the ``v2`` range ends on the
    base plane (and for cylinders the plane ``z = height``); ``slopes``:
    upper bounds of ``|df/dv1|`` and ``|df/dv2|`` over the surface."""
    start = np.asarray(start, dtype=np.int64)
    stop = np.asarray(stop, dtype=np.int64)
    box = np.zeros(tuple((stop - start)[::-1]), dtype=np.uint8)
    step = float(np.linalg.norm(affine[:, 0]))
    kind = {"prolate": _PROLATE, "spherical": _SPHERICAL, "cylindrical": _CYLINDRICAL}[kind]
    _cavity_rows(box, start, np.ascontiguousarray(affine, dtype=float), np.asarray(offset, dtype=float), kind,
                 float(param), np.ascontiguousarray(coefficients, dtype=float), float(v2_range[0]),
                 float(v2_range[1]), bool(standard_range), step, float(slopes[0]), float(slopes[1]))
    return box


@njit(cache=True)
def _flood_zeros(zero, out, stack):
    """The zeros of ``zero`` (bool) 6-connected to the faces, into ``out``;
    their count, or -1 if ``stack`` overflows.

    A sector's padding is mostly the zero runs at both ends of each row
    along x, which touch an x face: they are filled in one pass that reads
    nothing else.  The zeros left (runs inside rows) are padding when they
    lie on a y or z face or touch padding in one of the four neighbouring
    rows: those runs seed a span flood fill (fill a run, then seed the runs
    of the neighbouring rows that touch it) through the remaining zeros."""
    nz, ny, nx = zero.shape
    first = np.empty((nz, ny), dtype=np.int64)  # the row's first and last non-zero
    last = np.empty((nz, ny), dtype=np.int64)
    count = 0
    for k in range(nz):
        for j in range(ny):
            a = 0
            while a < nx and zero[k, j, a]:
                out[k, j, a] = True
                a += 1
            count += a
            first[k, j] = a
            last[k, j] = a - 1
            if a == nx:
                continue
            b = nx - 1
            while zero[k, j, b]:
                out[k, j, b] = True
                b -= 1
            count += nx - 1 - b
            last[k, j] = b
    top = 0
    for k in range(nz):
        for j in range(ny):
            face = k == 0 or k == nz - 1 or j == 0 or j == ny - 1
            m = first[k, j] + 1
            while m < last[k, j]:
                if not zero[k, j, m]:
                    m += 1
                    continue
                a = m
                while zero[k, j, m]:  # ends at the row's last non-zero
                    m += 1
                seed = face
                for dk, dj in ((-1, 0), (1, 0), (0, -1), (0, 1)):
                    if seed:
                        break
                    kk, jj = k + dk, j + dj
                    if 0 <= kk < nz and 0 <= jj < ny:
                        for q in range(a, m):
                            if out[kk, jj, q]:
                                seed = True
                                break
                if seed:
                    if top == len(stack):
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
        while a > 0 and zero[k, j, a - 1] and not out[k, j, a - 1]:
            a -= 1
        b = i
        while b < nx - 1 and zero[k, j, b + 1] and not out[k, j, b + 1]:
            b += 1
        for m in range(a, b + 1):
            out[k, j, m] = True
        count += b - a + 1
        for dk, dj in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            kk, jj = k + dk, j + dj
            if kk < 0 or kk >= nz or jj < 0 or jj >= ny:
                continue
            m = a
            while m <= b:
                if zero[kk, jj, m] and not out[kk, jj, m]:
                    if top == len(stack):
                        return -1  # the caller retries with a larger stack
                    stack[top] = (kk * ny + jj) * nx + m
                    top += 1
                    while m <= b and zero[kk, jj, m] and not out[kk, jj, m]:
                        m += 1
                else:
                    m += 1
    return count


def face_connected_zeros(array: np.ndarray) -> tuple[np.ndarray, int]:
    """The exact zeros 6-connected to the faces of a 3D array, and their count."""
    zero = np.ascontiguousarray(array) == 0  # one kernel signature for every dtype
    # seeds (one a run), then run starts: a voxel can be pushed from each of
    # its four neighbouring rows before it is filled, so in the worst case 5
    # a voxel (a sector's padding needs a few hundred); a stack that
    # overflows makes the kernel return -1
    size = 4096
    while True:
        out = np.zeros(zero.shape, dtype=bool)
        count = _flood_zeros(zero, out, np.empty(size, dtype=np.int64))
        if count >= 0:
            return out, int(count)
        size = min(8 * size, 5 * zero.size + 16)


def compilations() -> int:
    """Kernels of this module numba compiled in this process (missed its cache)."""
    from .warmup import compilations as count

    return count(sys.modules[__name__])
