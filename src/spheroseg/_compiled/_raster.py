"""Compiled rasterisation: the cavity's voxel mask and the sector padding.

Both are loops over voxels that numba compiles; they are imported only when
called (``import spheroseg`` does not load numba).

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

from __future__ import annotations

import cmath
import math
import mmap
import sys

import numpy as np
from numba import njit, prange

from ._runtime import PARALLEL_LOCK
from ._runtime import compilations as _compilations
from ..geometry.hermite import global_basis, patch_dofs

__all__ = ["cavity_mask", "face_connected_zeros", "cached", "compilations"]


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


@njit(cache=True, inline="always", error_model="numpy")
def hermite_at(t, width, derivative):
    """:func:`spheroseg.hermite.global_basis` at one point (``derivative``
    0 or 1), compiled."""
    if derivative == 0:
        return (1 - 3 * t * t + 2 * t * t * t, width * (t * (t - 1) * (t - 1)), t * t * (3 - 2 * t),
                width * (t * t * (t - 1)))
    return (6 * t * (t - 1) / width, (3 * t - 1) * (t - 1), 6 * t * (1 - t) / width, t * (3 * t - 2))


@njit(cache=True, inline="always", error_model="numpy")
def _prolate_fast(x1, rho, param):
    """Prolate ``(v0, v2)`` and the distances ``r1, r2`` to the foci, without
    the complex logarithm: ``cosh v0 = (r1 + r2) / 2a``, ``tan v2 = rho
    cosh v0 / (x1 sinh v0)``.  Accurate to ~1e-10 except within ~1e-3 of the
    focal segment (``v0 -> 0``), where it returns ``v0 = -1`` to say so."""
    r1 = math.sqrt((x1 - param) * (x1 - param) + rho * rho)
    r2 = math.sqrt((x1 + param) * (x1 + param) + rho * rho)
    c = 0.5 * (r1 + r2) / param
    if c < 1.0 + 5e-7:
        return -1.0, 0.0, r1, r2
    s = math.sqrt((c - 1.0) * (c + 1.0))
    return math.log(c + s), math.atan2(rho * c, x1 * s), r1, r2


@njit(cache=True, error_model="numpy")
def status(x1, x2, x3, kind, param, coef, lo, hi, standard_range, slopes, reach):
    """Status of the local point (_OUT, _IN or _TIE: too close to call), and
    whether every point within ``reach`` (mm) provably shares it (always
    for ``reach = 0``; never for _TIE at ``reach > 0``)."""
    if kind == _PROLATE:
        # the fast coordinates decide only the points FAST clear of a
        # decision (their error is below 1e-10 there); the others, as the
        # reference computes them
        rho = math.sqrt(x2 * x2 + x3 * x3)
        v0, v2, r1, r2 = _prolate_fast(x1, rho, param)
        if v0 < 0.0:
            return _status_exact(x1, x2, x3, kind, param, coef, lo, hi, standard_range, slopes, reach)
        tie = FAST
    else:
        # as CoordinateSystem.from_cartesian
        rho = math.hypot(x2, x3)
        if kind == _SPHERICAL:
            v0 = math.hypot(x1, rho)
            v2 = math.atan2(rho, x1)
            r1 = r2 = v0
        else:
            v0 = rho
            v2 = x1
            r1 = r2 = math.inf
        tie = TIE
    code, shared = _classify(x1, x2, x3, rho, v0, v2, r1, r2, tie, kind, param, coef, lo, hi, standard_range,
                             slopes, reach)
    if code == _REDO:
        return _status_exact(x1, x2, x3, kind, param, coef, lo, hi, standard_range, slopes, reach)
    return code, shared


@njit(cache=True, error_model="numpy")
def _status_exact(x1, x2, x3, kind, param, coef, lo, hi, standard_range, slopes, reach):
    """:func:`status` of a prolate point with its coordinates as the
    reference computes them (the complex arccosh)."""
    rho = math.hypot(x2, x3)
    w = cmath.acosh(complex(x1, rho) / param)
    r1 = math.hypot(x1 - param, rho)
    r2 = math.hypot(x1 + param, rho)
    return _classify(x1, x2, x3, rho, abs(w.real), abs(w.imag), r1, r2, TIE, kind, param, coef, lo, hi,
                     standard_range, slopes, reach)


@njit(cache=True, error_model="numpy")
def _classify(x1, x2, x3, rho, v0, v2, r1, r2, tie, kind, param, coef, lo, hi, standard_range, slopes, reach):
    """The status of a point from its model coordinates: too close to call
    within ``tie`` of a decision (_REDO with the fast prolate coordinates,
    to be redone exactly; _TIE with the exact ones, left to the caller)."""
    # distance (mm) to the boundary of the v2 range, when it is a plane
    if standard_range:
        plane = min(abs(x1), abs(param - x1)) if kind == _CYLINDRICAL else abs(x1)
    else:
        plane = 0.0
    if abs(v2 - lo) < tie or abs(v2 - hi) < tie:
        return (_TIE if tie == TIE else _REDO), reach == 0.0
    # shrunk by 1e-9: the distances are rounded
    if not (v2 >= lo and v2 <= hi):
        return _OUT, reach == 0.0 or reach < plane * (1.0 - 1e-9)
    f, v1 = _surface(x2, x3, v2, coef, lo, hi)
    g = v0 - f
    if abs(g) < tie:
        return (_TIE if tie == TIE else _REDO), reach == 0.0
    code = _IN if g <= 0 else _OUT
    if reach == 0.0:
        return code, True
    if not reach < 0.999 * min(rho, r1, r2) or (code == _IN and not reach < plane * (1.0 - 1e-9)):
        return code, False
    bound = gradient_bound(reach, kind, r1, r2, rho, v1, v2, lo, hi, slopes)
    return code, reach * bound < abs(g) * (1.0 - 1e-9)


@njit(cache=True, inline="always", error_model="numpy")
def _surface(x2, x3, v2, coef, lo, hi):
    """``f(v1, v2)`` and ``v1 = atan2(x3, x2)``."""
    # as np.mod(arctan2, 2 pi) does for angles in [-pi, pi]
    v1 = math.atan2(x3, x2)
    if v1 < 0:
        v1 += 2 * math.pi
    n2, n1 = coef.shape[0] - 1, coef.shape[1]
    u1 = v1 * (n1 / (2 * math.pi))
    u2 = (v2 - lo) * (n2 / (hi - lo))
    i1 = min(max(int(math.floor(u1)), 0), n1 - 1)
    i2 = min(max(int(math.floor(u2)), 0), n2 - 1)
    b1 = hermite_at(u1 - i1, 2 * math.pi / n1, 0)
    b2 = hermite_at(u2 - i2, (hi - lo) / n2, 0)
    f = 0.0
    for a1 in range(2):
        node1 = i1 + a1 if i1 + a1 < n1 else 0
        for a2 in range(2):
            for e1 in range(2):
                for e2 in range(2):
                    f += b1[2 * a1 + e1] * b2[2 * a2 + e2] * coef[i2 + a2, node1, e1 + 2 * e2]
    return f, v1


@njit(cache=True, inline="always", error_model="numpy")
def gradient_bound(delta, kind, r1, r2, rho, v1, v2, lo, hi, slopes):
    """Upper bound of ``|grad g|`` on the ball of radius ``delta`` (mm)
    around a point at ``(v1, v2)``: the root sum of squares of the three
    terms (the coordinates are orthogonal), each with its scale factor
    bounded below on the ball, and the slopes of ``f`` bounded over the
    patches the ball reaches (``slopes[i2, i1]``: ``|df/dv1|``,
    ``|df/dv2|``)."""
    if kind == _PROLATE:  # h0 = h2 >= sqrt((r1 - delta) (r2 - delta))
        m2 = math.sqrt((r1 - delta) * (r2 - delta))
    elif kind == _SPHERICAL:  # h0 = 1, h2 = r >= r1 - delta
        m2 = r1 - delta
    else:
        m2 = 1.0
    # |grad v2| = 1 / h2: on the ball v2 stays within delta / m2 of the centre's
    n2, n1 = slopes.shape[0], slopes.shape[1]
    spread = delta / m2
    first, last = 0, n2 - 1
    if spread < hi - lo:
        first = min(max(int(math.floor((v2 - spread - lo) * n2 / (hi - lo))), 0), n2 - 1)
        last = min(max(int(math.floor((v2 + spread - lo) * n2 / (hi - lo))), first), n2 - 1)
    m1 = rho - delta  # h1 = rho
    # |grad v1| = 1 / h1: v1 stays within delta / m1 of the centre's (it
    # wraps; 1e-9 more for its rounding)
    spread = delta / m1 + 1e-9
    left, right = 0, n1 - 1
    if spread < math.pi:
        left = int(math.floor((v1 - spread) * n1 / (2 * math.pi)))
        right = int(math.floor((v1 + spread) * n1 / (2 * math.pi)))
    f1 = 0.0
    f2 = 0.0
    for row in range(first, last + 1):
        for column in range(left, right + 1):
            c = column % n1
            if c < 0:
                c += n1
            f1 = max(f1, slopes[row, c, 0])
            f2 = max(f2, slopes[row, c, 1])
    if kind == _PROLATE:
        radial = (1.0 + f2 * f2) / (m2 * m2)
    elif kind == _SPHERICAL:
        radial = 1.0 + (f2 / m2) ** 2
    else:
        radial = 1.0 + f2 * f2
    return math.sqrt(radial + (f1 / m1) ** 2)


@njit(cache=True, inline="always", error_model="numpy")
def _reach(affine, ei, ej, ek):
    """Largest distance (mm) from the centre of a block of voxel centres,
    ``ei x ej x ek`` voxel steps across, to its corners."""
    best = 0.0
    for sj in (-1.0, 1.0):
        for sk in (-1.0, 1.0):
            dx = 0.5 * (ei * affine[0, 0] + sj * ej * affine[0, 1] + sk * ek * affine[0, 2])
            dy = 0.5 * (ei * affine[1, 0] + sj * ej * affine[1, 1] + sk * ek * affine[1, 2])
            dz = 0.5 * (ei * affine[2, 0] + sj * ej * affine[2, 1] + sk * ek * affine[2, 2])
            best = max(best, math.sqrt(dx * dx + dy * dy + dz * dz))
    return best


@njit(cache=True, parallel=True)
def _cavity_blocks(out, start, stop, affine, offset, kind, param, coef, lo, hi, standard_range, slopes, size, ties):
    """Fill the box ``[start, stop)`` of ``out`` block by block
    (:func:`_fill_block`), the top blocks in parallel; ``ties[b]``: the
    voxels of top block ``b`` left too close to call."""
    ni, nj, nk = stop[0] - start[0], stop[1] - start[1], stop[2] - start[2]
    bk, bj, bi = -(-nk // size), -(-nj // size), -(-ni // size)
    for block in prange(bk * bj * bi):
        ties[block] = _fill_block(out, (block // (bj * bi)) * size, ((block // bi) % bj) * size, (block % bi) * size,
                                  start, stop, affine, offset, kind, param, coef, lo, hi, standard_range, slopes, size)


@njit(cache=True, error_model="numpy")
def _fill_block(out, k_top, j_top, i_top, start, stop, affine, offset, kind, param, coef, lo, hi, standard_range,
                slopes, size):
    """One top block (box index of its corner): a block whose centre's ball
    (its status shared, :func:`status`) holds every voxel centre of the
    block takes that status at once; the others split in eight, down to
    single voxels.  Returns the number of voxels left too close to call.
    (A function of its own: numba compiles a parallel loop's body slowly.)"""
    ni, nj, nk = stop[0] - start[0], stop[1] - start[1], stop[2] - start[2]
    ties = 0
    stack = np.empty((8 * 8, 4), dtype=np.int64)  # (k0, j0, i0, size): 7 a level deep
    stack[0, 0], stack[0, 1], stack[0, 2], stack[0, 3] = k_top, j_top, i_top, size
    top = 1
    while top > 0:
        top -= 1
        k0, j0, i0, s = stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3]
        k1, j1, i1 = min(k0 + s, nk), min(j0 + s, nj), min(i0 + s, ni)
        if k1 <= k0 or j1 <= j0 or i1 <= i0:
            continue
        # the centre of the block's voxel centres, in the grid's index
        ci = start[0] + 0.5 * (i0 + i1 - 1)
        cj = start[1] + 0.5 * (j0 + j1 - 1)
        ck = start[2] + 0.5 * (k0 + k1 - 1)
        x1 = offset[0] + affine[0, 0] * ci + affine[0, 1] * cj + affine[0, 2] * ck
        x2 = offset[1] + affine[1, 0] * ci + affine[1, 1] * cj + affine[1, 2] * ck
        x3 = offset[2] + affine[2, 0] * ci + affine[2, 1] * cj + affine[2, 2] * ck
        single = k1 - k0 == 1 and j1 - j0 == 1 and i1 - i0 == 1
        reach = 0.0 if single else _reach(affine, i1 - 1 - i0, j1 - 1 - j0, k1 - 1 - k0)
        code, shared = status(x1, x2, x3, kind, param, coef, lo, hi, standard_range, slopes, reach)
        if shared:
            if code == _TIE:
                ties += 1
            if code != _OUT:
                for k in range(start[2] + k0, start[2] + k1):
                    for j in range(start[1] + j0, start[1] + j1):
                        for i in range(start[0] + i0, start[0] + i1):
                            out[k, j, i] = code
            continue
        h = (s + 1) // 2
        for dk in range(2):
            for dj in range(2):
                for di in range(2):
                    stack[top, 0] = k0 + dk * h
                    stack[top, 1] = j0 + dj * h
                    stack[top, 2] = i0 + di * h
                    stack[top, 3] = h
                    top += 1
    return ties


@njit(cache=True)
def _positions(out, start, stop, size, ties):
    """The indices ``(k, j, i)`` of the _TIE voxels of the box ``[start,
    stop)``, from the top blocks that have them (``ties`` as
    :func:`_cavity_blocks` counts them)."""
    found = np.empty((ties.sum(), 3), dtype=np.int64)
    ni, nj = stop[0] - start[0], stop[1] - start[1]
    bj, bi = -(-nj // size), -(-ni // size)
    n = 0
    for block in range(ties.size):
        if ties[block] == 0:
            continue
        k0 = start[2] + (block // (bj * bi)) * size
        j0 = start[1] + ((block // bi) % bj) * size
        i0 = start[0] + (block % bi) * size
        for k in range(k0, min(k0 + size, stop[2])):
            for j in range(j0, min(j0 + size, stop[1])):
                for i in range(i0, min(i0 + size, stop[0])):
                    if out[k, j, i] == _TIE:
                        found[n, 0], found[n, 1], found[n, 2] = k, j, i
                        n += 1
    return found


def patch_slopes(coefficients, lo, hi, samples):
    """The largest ``|df/dv1|``, ``|df/dv2|`` over ``samples + 1`` squared
    points of each patch (its edges included), ``[i2, i1, 2]``.  (numpy: a
    kernel would add a second to the first run's compilation.)"""
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
    blocks = np.prod(-(-(stop - start) // BLOCK))
    ties = np.zeros(blocks, dtype=np.int64)
    coefficients = np.ascontiguousarray(coefficients, dtype=float)
    lo, hi = float(v2_range[0]), float(v2_range[1])
    # per patch, not per row of patches: a ball reaches one or two patches
    # around the axis, whose own slopes decide more blocks at once
    slopes = SLOPE_MARGIN * patch_slopes(coefficients, lo, hi, SLOPE_SAMPLES) + 1e-9
    _cavity_blocks(codes, start, stop, np.ascontiguousarray(affine, dtype=float), np.asarray(offset, dtype=float),
                   {"prolate": _PROLATE, "spherical": _SPHERICAL, "cylindrical": _CYLINDRICAL}[kind], float(param),
                   coefficients, lo, hi, bool(standard_range), slopes, BLOCK, ties)
    return codes, _positions(codes, start, stop, BLOCK, ties)


@njit(cache=True, parallel=True)
def _row_ends(values, out, first, last, inner):
    """The zero runs at both ends of every row along x into ``out``, each
    row's first and last non-zero (``first = nx``, ``last = nx - 1`` for a
    row of zeros) and its number of zeros between them, and the number of
    voxels filled; rows in parallel (they are independent), so that the
    serial flood visits only the rows with zeros inside."""
    nz, ny, nx = values.shape
    counts = np.zeros(nz, dtype=np.int64)
    for k in prange(nz):
        for j in range(ny):
            # a loop without an exit or a branch (LLVM vectorises it): the
            # scans that stopped at the ends' first non-zero took 2-3 times as long
            a, b, zeros = nx, -1, 0
            for i in range(nx):
                data = values[k, j, i] != 0
                zeros += not data
                a = min(a, i if data else nx)
                b = max(b, i if data else -1)
            b = max(b, a - 1)
            out[k, j, :a] = True
            out[k, j, b + 1:] = True
            first[k, j] = a
            last[k, j] = b
            ends = a + nx - 1 - b
            inner[k, j] = zeros - ends
            counts[k] += ends
    return counts.sum()


@njit(cache=True)
def _flood_zeros(values, out, stack):
    """The zeros of ``values`` 6-connected to the faces, into ``out``;
    their count, or -1 if ``stack`` overflows.

    A sector's padding is mostly the zero runs at both ends of each row
    along x, which touch an x face: they are filled in one parallel pass
    that also finds the rows with zeros inside.  Those zero runs are
    padding when they lie on a y or z face or touch an end run of one of
    the four neighbouring rows: they seed a span flood fill (fill a run,
    then seed the runs of the neighbouring rows that touch it) through the
    remaining zeros."""
    nz, ny, nx = values.shape
    first = np.empty((nz, ny), dtype=np.int64)  # the row's first and last non-zero
    last = np.empty((nz, ny), dtype=np.int64)
    inner = np.empty((nz, ny), dtype=np.int64)  # its zeros between them, unfilled
    count = _row_ends(values, out, first, last, inner)
    top = 0
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
                for dk, dj in ((-1, 0), (1, 0), (0, -1), (0, 1)):
                    if seed:
                        break
                    kk, jj = k + dk, j + dj
                    if 0 <= kk < nz and 0 <= jj < ny:  # [a, m) meets the end runs of row (kk, jj)
                        seed = a < first[kk, jj] or m - 1 > last[kk, jj]
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
        while a > 0 and values[k, j, a - 1] == 0 and not out[k, j, a - 1]:
            a -= 1
        b = i
        while b < nx - 1 and values[k, j, b + 1] == 0 and not out[k, j, b + 1]:
            b += 1
        for m in range(a, b + 1):
            out[k, j, m] = True
        count += b - a + 1
        inner[k, j] -= b - a + 1
        for dk, dj in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            kk, jj = k + dk, j + dj
            if kk < 0 or kk >= nz or jj < 0 or jj >= ny or inner[kk, jj] == 0:  # nothing left to fill there
                continue
            m = a
            while m <= b:
                if values[kk, jj, m] == 0 and not out[kk, jj, m]:
                    if top == len(stack):
                        return -1  # the caller retries with a larger stack
                    stack[top] = (kk * ny + jj) * nx + m
                    top += 1
                    while m <= b and values[kk, jj, m] == 0 and not out[kk, jj, m]:
                        m += 1
                else:
                    m += 1
    return count


def face_connected_zeros(array: np.ndarray) -> tuple[np.ndarray, int]:
    """The exact zeros 6-connected to the faces of a 3D array, and their count."""
    array = np.asarray(array)
    # the kernel reads float32 (a volume's voxels) in place; other types as
    # their non-zeros, exactly (float64's tiny values would round to 0)
    if array.dtype == np.float32:
        values = np.ascontiguousarray(array).view()
    else:
        values = np.not_equal(array, 0, out=np.empty(array.shape, dtype=np.float32))
    values.flags.writeable = False  # one kernel signature, whether or not the input was read-only
    # seeds (one a run), then run starts: a voxel can be pushed from each of
    # its four neighbouring rows before it is filled, so in the worst case 5
    # a voxel (a sector's padding needs a few hundred); a stack that
    # overflows makes the kernel return -1
    size = 4096
    while True:
        out = fresh_zeros(values.shape, bool)
        with PARALLEL_LOCK:  # its row pass is a parallel kernel
            count = _flood_zeros(values, out, np.empty(size, dtype=np.int64))
        if count >= 0:
            return out, int(count)
        size = min(8 * size, 5 * values.size + 16)


@njit(cache=True)
def _cache_probe():
    return 0


def _probe_misses() -> int:
    misses = getattr(getattr(_cache_probe, "stats", None), "cache_misses", None)  # none without the JIT
    return sum(misses.values()) if misses else 0


def cached() -> bool:
    """Whether numba's cache holds this module's kernels for its current
    source: a kernel of its own loaded rather than compiled."""
    _cache_probe()
    return _probe_misses() == 0


def compilations() -> int:
    """Kernels of this module numba compiled in this process (missed its
    cache), its cache probe aside."""
    return _compilations(sys.modules[__name__]) - _probe_misses()
