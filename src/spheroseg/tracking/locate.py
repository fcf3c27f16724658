"""The left ventricle found without clicks, and clicks checked against it.

An apical acquisition looks down the ventricle from the probe: the cavity is
a dark (blood) pool whose apex is nearest the probe, closed at the far end by
the mitral annulus, beyond which the atrium is dark again.  :func:`locate`
finds that pool on a coarse copy of the image (3 mm voxels, each the mean
of 27 points fixed in mm, which averages the speckle out and costs the same
whatever the image's resolution):

1. blood is what is darker than Otsu's threshold of the smoothed grey levels
   inside the sector, once each shell of depth from the probe is brought to
   one level of its brighter quartile (time-gain compensation leaves the
   grey level drifting with depth); an image whose two classes lie less
   than :data:`CONTRAST_MIN` of the speckle's own spread apart (the grey
   levels' standard deviation within a coarse voxel: log-compressed
   speckle's does not depend on the tissue) has no blood pool;
2. its connected pools (after an opening of one coarse voxel, which cuts thin
   bridges) are the candidates; the left ventricle is the one of plausible
   size (the part before its waist, :data:`VOLUME_RANGE_ML`) scored by its
   size and its closeness to the sector's axis (the apical view centres the
   left ventricle; the right ventricle lies to one side and is smaller);
3. the long axis is the pool's principal axis, turned towards the probe;
4. along that axis the pool's cross-section grows from the apex to the base
   and narrows at the mitral orifice before the atrium widens it again: the
   base is the narrowest section (the waist) beyond the widest one, or the
   pool's far end when the atrium is not joined to it (a closed valve, an
   atrium out of the sector); the full-resolution image across the axis
   then moves it to where the cavity's grey level rises into the annulus
   (the waist of the coarse pool lies a few millimetres beyond);
5. the apex is the pool's first section along the axis from the probe side;
6. when no pool is a ventricle (a faint wall joins the cavity to the dark
   around it), the cavity is followed along its sections across the sector
   that are still dark discs ringed by the wall, the long axis through their
   centres (from the probe when they are few); such a location's confidence
   is at most :data:`JOINED_POOL`.

``confidence`` combines how well blood and tissue separate, how clear the
waist is, how plausible the size and length are, how much brighter the
pool's wall is than its blood and how elongated the cavity is (a ventricle
is longer than wide; a cavity whose apex haze hides is a stump).  Under
:data:`CHECK_CONFIDENCE` clicks are not checked against the location, and
a result says so.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from .annulus import basal_profile
from .._compiled.raster import block_means

__all__ = ["Located", "NoVentricleError", "locate", "check_points", "initialise", "annotate", "VOLUME_RANGE_ML",
           "JOINED_POOL"]

#: cavity volumes (mL, the part before the waist) a left ventricle can have
VOLUME_RANGE_ML = (15.0, 450.0)
#: coarse pool volumes (mL) of the usual ventricles, 40-350 mL: the pool
#: measures 0.8-0.9 of the cavity (the opening and the blurred wall)
SIZE_RANGE_ML = (15.0, 380.0)
#: the ratio of a cavity's length (apex to base) to its width under which
#: it is no ventricle's (it scores fully from 0.2 more, a half at 1.35):
#: 1.43-2.93 on two phantom sweeps (seeds 29, 30), 1.49-2.33 on the
#: devset; a cavity whose apex haze hides (``clutter_strong``, seeds 0-5
#: at 1.5 and 2 mm and the sweeps') 0.99-1.30
ELONGATION_MIN = 1.25
#: the least narrowing at the mitral orifice (1 - its section over the
#: widest on either side) that is a waist: twice it scores fully (0.22-0.87
#: on the phantom sweep and the devset; an atrium taken in, 0.13)
WAIST_MIN = 0.1
#: apex-to-base lengths (mm) a left ventricle can have
LENGTH_RANGE_MM = (35.0, 140.0)


#: the least distance (in the speckle's grey-level spread) between the
#: means of the dark and the bright classes of an image with a blood pool
CONTRAST_MIN = 1.4
#: a dark region whose surroundings are not this much brighter (in the
#: classes' deviations) is a dark patch of tissue, not a cavity
WALL_MIN = 1.0

#: thickness (mm) of the shells of depth whose grey levels are levelled
DEPTH_SHELL_MM = 6.0

#: radius of the disc whose grey level finds the mitral plane, as a fraction
#: of the cavity's coarse radius near its base: 0.5 left the disc inside
#: the orifice, 1.0 reached the wall (0.9: base 0.6-2.0 mm off on the sweep)
BASE_DISC = 0.9

#: a pool whose second principal spread is over this fraction of its first
#: has no one long axis: the direction in their plane nearest the sector's
#: centre line is taken
ROUND_POOL = 0.9

#: an apical view looks down the long axis: at most this angle (degrees)
#: between the long axis and the sector's centre line (25 is a tilted view)
AXIS_MAX_DEG = 45.0

#: the confidence's factor for a cavity found along its ringed sections, its
#: dark pool joined to the dark around it (:func:`_along_ringed_sections`):
#: under a half, so that such a location is reported as one to check
JOINED_POOL = 0.3
#: the ringed sections (3 mm apart) narrowing by this fraction of their area
#: against the widest on both sides: the mitral orifice, the atrium's
#: sections beyond it
RING_WAIST = 0.05
#: how far (mm) beyond the last ringed section the base may lie: a faint
#: basal wall leaves some of the ventricle unringed (12-19 mm on CETUS
#: Patient 7); farther, the axis has run through an open valve to the
#: atrium's far wall (35-41 mm on phantoms), and the image is refused
BASE_REACH_MM = 30.0
#: ringed sections spanning this many mm give the long axis by their
#: centres (PCA); a shorter series leaves it to the line from the probe
#: (CETUS Patient 7's span 27 mm: the PCA's axis put its apex 11 mm off)
AXIS_SPAN_MM = 40.0

#: the least confidence of a location that clicks are checked against (and
#: that a segmentation from it is not flagged for)
CHECK_CONFIDENCE = 0.5

#: what a low score means, for ``Located.reason``
_REASONS = {
    "separation": "blood and tissue barely differ in grey level",
    "waist": "no narrowing where the cavity meets the atrium (the base is a guess)",
    "size": "the cavity's size is unusual",
    "length": "the long axis has an unusual length",
    "wall": "the cavity's wall is barely brighter than its blood",
    "elongation": "the cavity is hardly longer than it is wide (haze or the sector's edge hides the apex?)",
    "pool": "the cavity is joined to the dark regions around it (a faint wall): found along its ringed sections",
}


class NoVentricleError(ValueError):
    """No dark pool in the image looks like a left ventricle."""


@dataclass(frozen=True)
class Located:
    """Where :func:`locate` found the left ventricle (world mm, LPS).

    Attributes
    ----------
    apex : (3,) array
        The endocardial apex.
    base : (3,) array
        The centre of the mitral plane.
    normal : (3,) array
        Unit normal of the mitral plane, from the base towards the apex.
    confidence : float
        In [0, 1]: the product of the scores in ``scores``.
    reason : str
        Why the confidence is low ('' when it is not).
    volume_ml : float
        Volume of the dark pool between apex and base (coarse, mL).
    scores : dict
        ``separation`` (blood against tissue), ``waist`` (how clearly the
        pool narrows at the base), ``size`` and ``length`` (plausibility),
        ``wall`` and ``elongation``, each in [0, 1]; or, for a cavity found
        along its ringed sections, ``separation`` and ``pool``
        (:data:`JOINED_POOL`).
    measures : dict
        What the scores are read from: ``contrast`` (the classes' distance
        in speckle spreads), ``waist`` (the orifice's dip in section),
        ``elongation`` (length over the widest diameter), ``length_mm``,
        ``width_mm`` and ``wall`` (the wall over the blood, in the classes'
        pooled spreads), as far as known.
    """

    apex: np.ndarray
    base: np.ndarray
    normal: np.ndarray
    confidence: float
    reason: str = ""
    volume_ml: float = float("nan")
    scores: dict = field(default_factory=dict)
    measures: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        """Plain JSON values."""
        return {"apex": [float(x) for x in self.apex], "base": [float(x) for x in self.base],
                "normal": [float(x) for x in self.normal], "confidence": float(self.confidence),
                "reason": self.reason, "volume_ml": float(self.volume_ml),
                "scores": {k: float(v) for k, v in self.scores.items()},
                "measures": {k: float(v) for k, v in self.measures.items()}}


#: voxels of the full image the coarse copy reads at once: its temporaries
#: (some 13 bytes a voxel: masks, a float copy, partial sums) are of a slab
#: of the image, not of all of it, whatever the image's size
_SLAB_VOXELS = 1 << 23


def _block_mean(array: np.ndarray, missing, factor) -> np.ndarray:
    """:func:`~spheroseg.raster.block_means`, slab by slab of whole blocks
    along the first axis (the same sums), refusing an image too small to
    hold a ventricle; ``missing(z0, z1)`` gives the slab's missing voxels."""
    factor = np.asarray(factor, int)
    shape = np.array(array.shape) // factor
    if np.any(shape < 4):
        raise NoVentricleError(f"no left ventricle found: the image ({array.shape}) is too small to hold one")
    rows = factor[0] * max(1, _SLAB_VOXELS // (factor[0] * array.shape[1] * array.shape[2]))
    return np.concatenate([block_means(array[z:z + rows], missing(z, z + rows), factor)
                           for z in range(0, shape[0] * factor[0], rows)])


def _missing(volume):
    """The function giving a slab ``[z0:z1]`` of the volume's missing voxels
    (no data, or not finite)."""
    array, mask = np.asarray(volume.array), volume.no_data_mask

    def rows(z0: int, z1: int) -> np.ndarray:
        missing = ~np.isfinite(array[z0:z1])
        return missing if mask is None else missing | mask[z0:z1]

    return rows


#: samples per axis of each coarse voxel (:func:`_coarse`): the copy reads
#: this many cubed voxels per coarse voxel, whatever the image's resolution
SUBSAMPLES = 3
#: most coarse voxels along an axis: a larger image is searched on coarser
#: voxels, so that the search's cost does not grow with the image
MAX_COARSE = 96
#: coarse voxels read at once by :func:`fixed_size_copy` (its indices and
#: values, m**3 = 27 points each: a few MB whatever the image)
GATHER_BLOCK = 8192


def fixed_size_copy(volume, spacing: float):
    """Means and standard deviations over coarse voxels of about ``spacing``
    mm of a Cartesian ``volume``, each from its nearest voxels at
    :data:`SUBSAMPLES` cubed points evenly spread over it (NaN where half
    of them or more have no data): ``(means, deviations, coarse step in
    index units (x, y, z), index (x, y, z) of coarse voxel 0)``.

    The points are fixed in mm, not in voxels, so that an image and the
    same image resampled finer give the same copy, and their number is
    fixed, so that its cost does not grow with the image's resolution; a
    grid over :data:`MAX_COARSE` voxels along an axis is made coarser."""
    shape_xyz = np.array(volume.shape[::-1])
    extent = shape_xyz * volume.spacing
    spacing = max(float(spacing), float(np.max(extent)) / MAX_COARSE)
    q = spacing / volume.spacing  # coarse step, in voxels (x, y, z)
    n = np.floor(shape_xyz / q).astype(int)
    if np.any(n < 4):
        raise NoVentricleError(f"no left ventricle found: the image ({volume.shape}) is too small to hold one")
    first = 0.5 * q - 0.5
    m = SUBSAMPLES
    samples = volume.sampling_view().values  # flat, NaN off the data

    strides = (volume.shape[1] * volume.shape[2], volume.shape[2], 1)
    shape = tuple(n[::-1])

    def nearest(spread, k):
        """Flat indices of the nearest voxels at ``k`` points a side,
        ``spread`` voxels apart (x, y, z), about each coarse voxel's
        centre, along z, y and x: ``(k, n)`` each."""
        # (rounded half up, not to even: a voxel split in two halves keeps its points)
        return [np.clip(np.floor(first[d] + (np.arange(k)[:, None] - (k - 1) / 2) * spread[d]
                                 + q[d] * np.arange(n[d])[None, :] + 0.5), 0, shape_xyz[d] - 1).astype(np.intp) * st
                for d, st in zip((2, 1, 0), strides)]

    # the coarse voxels near the data (their centres' voxels, one coarse voxel around): the rest are empty
    kz, jy, ix = nearest(q, 1)
    near = np.isfinite(samples.take(kz[0][:, None, None] + jy[0][None, :, None] + ix[0][None, None, :]))
    where = np.nonzero(ndimage.binary_dilation(near, iterations=1))

    def gather(spread):
        """Count, sum and sum of squares of the nearest voxels at ``m``
        points a side, ``spread`` voxels apart, over each coarse voxel near
        the data: one read of the ``m**3`` points of each, a block of
        coarse voxels at a time (the indices and values of all at once
        would hold several times the image's bytes)."""
        kz, jy, ix = nearest(spread, m)
        out = [np.zeros(shape, np.int64), np.zeros(shape), np.zeros(shape)]
        for block in range(0, len(where[0]), GATHER_BLOCK):
            at = tuple(w[block:block + GATHER_BLOCK] for w in where)
            # (sub-point, coarse voxel): each sub-point's values contiguous
            flat = (kz[:, at[0]][:, None, None] + jy[:, at[1]][None, :, None] + ix[:, at[2]][None, None, :])
            values = samples.take(flat.reshape(m ** 3, -1))
            ok = np.isfinite(values)
            values = np.where(ok, values, np.float32(0))
            out[0][at], out[1][at] = ok.sum(0), values.sum(0, dtype=np.float64)
            out[2][at] = np.einsum("ij,ij->j", values, values, dtype=np.float64)
        return out

    count, total, squares = gather(q / m)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > m ** 3 / 2, total / count, np.nan)
    # the speckle's spread from distinct voxels: a voxel apart at least
    if np.any(q / m < 1):
        count, total, squares = gather(np.maximum(q / m, 1.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        deviation = np.sqrt(np.maximum(squares - total ** 2 / count, 0.0) / np.maximum(count - 1, 1))
    return mean.astype(np.float32), deviation, q, first


def _coarse(volume, spacing: float):
    """The image on a Cartesian grid of about ``spacing`` mm, speckle averaged:
    ``(grey levels [k, j, i] with NaN off the data, index -> world function,
    voxel size (x, y, z) mm, probe point, whether it is known, depth direction,
    each voxel's distance from the probe in mm, the speckle's spread)``.

    The speckle's spread is the median over the coarse voxels of the grey
    levels' standard deviation within each (most coarse voxels lie in one
    tissue, where log-compressed speckle's spread does not depend on the
    tissue's brightness)."""
    from ..volumes.beamspace import BeamVolume

    if isinstance(volume, BeamVolume):
        # averaged along each beam to about the coarse voxel, then read at the
        # coarse grid's points: the beams are already that far apart laterally
        geometry = volume.geometry
        f_r = max(1, int(round(spacing / geometry.radius_sample_size)))
        array, missing = np.asarray(volume.array, np.float32), _missing(volume)
        beams = _block_mean(array, missing, (f_r, 1, 1))
        with np.errstate(invalid="ignore"):
            within = np.sqrt(np.maximum(_block_mean(array * array, missing, (f_r, 1, 1)) - beams ** 2, 0)
                             * f_r / max(f_r - 1, 1))
        speckle = float(np.nanmedian(within))
        grid = geometry.cartesian_grid(spacing)
        # the grid's axes are the probe's: its points in the probe frame are a product of three ranges
        start = (grid.origin - geometry.apex) @ geometry.rotation
        x, y, z = (start[d] + np.arange(n) * grid.spacing[d] for d, n in enumerate(grid.shape[::-1]))
        probe_points = np.stack(np.broadcast_arrays(x, y[:, None], z[:, None, None]), -1)  # [k, j, i, xyz]
        spherical = geometry.probe_to_spherical(probe_points)
        distance = spherical[..., 0]
        beam_index = (spherical - geometry.index_offset) / geometry.separations
        beam_index[..., 0] = (beam_index[..., 0] - (f_r - 1) / 2) / f_r
        within = np.all(np.isfinite(beam_index) & (beam_index >= 0) & (beam_index <= np.array(beams.shape) - 1), -1)
        # read only the points in the sector (a third of the pyramid's box)
        grey = np.full(within.shape, np.nan, np.float32)
        grey[within] = ndimage.map_coordinates(beams, beam_index[within].T, order=1)
        origin, direction, step = grid.origin, grid.direction, grid.spacing
        probe, depth = geometry.apex, geometry.rotation[:, 2]
        probe_known = True
    else:
        probe_known = True
        grey, deviation, q, first = fixed_size_copy(volume, spacing)
        speckle = float(np.nanmedian(np.where(np.isfinite(grey), deviation, np.nan))) if np.isfinite(grey).any() \
            else float("nan")
        step = volume.spacing * q
        origin = volume.index_to_world(first)
        direction, depth = volume.direction, volume.direction[:, 2]
        # an apical sector (data missing around it) has its probe over the shallowest data
        probe = None
        if volume.no_data_mask is not None and volume.no_data_mask.any():
            rows = np.flatnonzero(np.isfinite(grey).any((1, 2)))
            if rows.size:
                jj, ii = np.nonzero(np.isfinite(grey[rows[0]]))
                probe = origin + direction @ (np.array([ii.mean(), jj.mean(), -0.5]) * step)
        if probe is None:  # no sector: the project's convention, the probe over the top face's centre
            probe = origin + direction @ (np.array([(grey.shape[2] - 1) / 2, (grey.shape[1] - 1) / 2, -0.5]) * step)
            probe_known = False
        # the distance from the probe of every voxel, a sum of one offset along each axis
        offset = [np.asarray(direction)[:, d] * step[d] * np.arange(n)[:, None]
                  for d, n in enumerate(grey.shape[::-1])]  # x, y, z: (n, 3)
        start = np.asarray(origin, float) - probe
        distance = np.sqrt(sum((start[c] + offset[2][:, c, None, None] + offset[1][None, :, c, None]
                                + offset[0][None, None, :, c]) ** 2 for c in range(3)))

    def to_world(index_zyx):
        return origin + (np.asarray(index_zyx, float)[..., ::-1] * step) @ np.asarray(direction).T

    return (grey, to_world, np.asarray(step, float), np.asarray(probe, float), probe_known,
            np.asarray(depth, float) / np.linalg.norm(depth), distance, speckle)


def _otsu(values: np.ndarray) -> tuple[float, float, float]:
    """Otsu's threshold of ``values`` and how far apart its two classes are:
    the difference of their means over their pooled standard deviation
    (about 2.7 for one Gaussian class split in two), and that deviation."""
    hist, edges = np.histogram(values, bins=128)
    p = hist / hist.sum()
    centres = (edges[:-1] + edges[1:]) / 2
    w0 = np.cumsum(p)
    m0 = np.cumsum(p * centres)
    mean = m0[-1]
    with np.errstate(invalid="ignore", divide="ignore"):
        between = (mean * w0 - m0) ** 2 / (w0 * (1 - w0))
    k = int(np.argmax(np.nan_to_num(between[:-1])))
    threshold = float(edges[k + 1])
    dark, bright = values[values < threshold], values[values >= threshold]
    spread = np.sqrt(0.5 * (dark.var() + bright.var()))
    return threshold, float((bright.mean() - dark.mean()) / spread) if spread > 0 else 0.0, float(spread)


def locate(volume, *, spacing: float | None = None) -> Located:
    """Find the left ventricle of an apical 3D echo volume.

    Parameters
    ----------
    volume : Volume or BeamVolume
        Apical acquisition (probe at the sector's apex, blood dark).
    spacing : float, optional
        Voxel size (mm) of the coarse copy the search runs on.  Default 3 mm
        on a Cartesian volume (coarser when the image spans more than
        :data:`MAX_COARSE` such voxels along an axis) and 4 mm on a
        beam-space one, whose
        copy is interpolated over the whole box around the sector (three
        times the sector's volume): 3 mm there took twice the time for the
        same apex and base.

    Returns
    -------
    Located
        Apex, base, the mitral plane's normal, ``confidence`` and ``reason``.

    Raises
    ------
    NoVentricleError
        When no dark pool of a ventricle's size is in the image.
    """
    if spacing is None:
        from ..volumes.beamspace import BeamVolume

        spacing = 4.0 if isinstance(volume, BeamVolume) else 3.0
    if not (np.isfinite(spacing) and spacing > 0):
        raise ValueError(f"spacing must be a positive number of mm, got {spacing!r}")
    grey, to_world, step, probe, probe_known, depth, distance, speckle = _coarse(volume, spacing)
    data = np.isfinite(grey)
    if data.sum() < 64:
        raise NoVentricleError("no left ventricle found: the image has too little data")
    voxel_ml = float(np.prod(step)) / 1000.0
    # smoothed over the data only (normalised convolution), the sector edge kept out
    sigma = 3.0 / step[::-1]
    weight = ndimage.gaussian_filter(data.astype(np.float32), sigma)
    with np.errstate(invalid="ignore", divide="ignore"):
        smooth = ndimage.gaussian_filter(np.where(data, grey, 0).astype(np.float32), sigma) / weight
    inside = data & (weight > 0.5)
    # time-gain compensation leaves the grey level drifting with depth: each
    # shell of depth is brought to one level of its brighter (tissue) quartile
    distance = distance[inside]
    shell = (distance // DEPTH_SHELL_MM).astype(int)
    raw = smooth[inside]
    levels = np.full(shell.max() + 1, np.nan)
    for k in np.unique(shell):
        here = raw[shell == k]
        if here.size >= 20:
            levels[k] = np.percentile(here, 75)
    known = np.flatnonzero(np.isfinite(levels))
    if known.size == 0:
        raise NoVentricleError("no left ventricle found: the image has too little data")
    centres = (np.arange(levels.size) + 0.5) * DEPTH_SHELL_MM
    drift = np.interp(centres, centres[known], levels[known]) - np.median(levels[known])
    values = raw - np.interp(distance, centres, drift)
    smooth = smooth.copy()
    smooth[inside] = values
    if values.size < 64 or not np.ptp(values) > 0:
        raise NoVentricleError("no left ventricle found: the image is constant")
    threshold, separation, spread = _otsu(values)
    # the classes' distance in speckle spreads: a region of one tissue (a
    # uniform speckle volume) averaged over coarse voxels has classes far
    # less than one apart, whatever the image's gain and compression
    contrast = separation * spread / speckle if speckle > 0 else 0.0
    if not contrast >= CONTRAST_MIN:
        raise NoVentricleError(f"no left ventricle found: no region of the image is darker than the rest as blood "
                               f"is (dark and bright classes {contrast:.2f} speckle deviations apart, fewer than "
                               f"{CONTRAST_MIN})")
    dark = inside & (smooth < threshold)
    best, largest = None, 0.0
    # a wider opening cuts wider bridges (a ventricle joined to the atrium
    # through an open valve, or to clutter out of the sector)
    for opening in (1, 2, 3):
        labels, n = ndimage.label(ndimage.binary_opening(dark, iterations=opening))
        if n == 0:
            continue
        sizes = ndimage.sum_labels(np.ones_like(labels), labels, np.arange(1, n + 1)) * voxel_ml
        largest = max(largest, float(sizes.max()))
        for label in np.flatnonzero(sizes >= VOLUME_RANGE_ML[0]) + 1:
            mask = labels == label
            candidate = _pool(mask, to_world, probe, probe_known, depth, voxel_ml, float(step.max()))
            if candidate is None:
                continue
            # a cavity is walled by tissue brighter than its blood
            shell = ndimage.binary_dilation(mask, iterations=2) & ~mask & inside
            wall = (smooth[shell].mean() - smooth[mask].mean()) / spread if shell.any() else 0.0
            candidate["scores"]["wall"] = float(np.clip((wall - WALL_MIN) / 1.0, 0, 1))
            candidate["measures"]["wall"] = float(wall)
            candidate["score"] *= candidate["scores"]["wall"]
            if best is None or candidate["score"] > best["score"]:
                best = candidate
        if best is not None and best["score"] > 0:
            break
    if best is None or best["score"] <= 0:
        best = _along_ringed_sections(volume, smooth, inside, threshold, spread, separation * spread, to_world,
                                      probe, depth)
    if best is None:
        raise NoVentricleError(f"no left ventricle found: no dark region of {VOLUME_RANGE_ML[0]:.0f}-"
                               f"{VOLUME_RANGE_ML[1]:.0f} mL, walled by brighter tissue, along the sector (the "
                               f"largest dark region is {largest:.0f} mL)")
    if best.get("refined"):  # found on the full-resolution image already
        apex, base = best["apex"], best["base"]
    else:
        local = threshold + np.interp(np.linalg.norm(best["apex"] - probe), centres, drift)
        apex = _endocardial_apex(volume, best["apex"], best["normal"], local)
        base = _mitral_plane(volume, best["base"], best["normal"], BASE_DISC * best["base_radius"],
                             separation * spread)
    scores = {"separation": float(np.clip((contrast - CONTRAST_MIN) / 0.5, 0, 1)), **best["scores"]}
    confidence = float(np.prod(list(scores.values())))
    # the scores that brought it down (the lowest, when each alone is fair)
    low = [name for name, value in scores.items() if value < 0.75] or [min(scores, key=scores.get)]
    reason = "; ".join(_REASONS[name] for name in low) if confidence < CHECK_CONFIDENCE else ""
    normal = (apex - base) / np.linalg.norm(apex - base)
    measures = {"contrast": float(contrast), **best["measures"]}
    return Located(apex=apex, base=base, normal=normal, confidence=confidence, reason=reason,
                   volume_ml=best["volume_ml"], scores=scores, measures=measures)


def _pool(mask: np.ndarray, to_world, probe, probe_known: bool, depth, voxel_ml, slab) -> dict | None:
    """The apex, base and scores of one dark pool (None if it is no ventricle).

    With the probe known, the apex is the end towards it (and a pool lying
    across the sector is no ventricle in an apical view); otherwise the end
    whose side of the waist holds more blood (a ventricle holds two to three
    times its atrium)."""
    points = to_world(np.argwhere(mask))
    centre = points.mean(0)
    _, spreads, vt = np.linalg.svd(points - centre, full_matrices=False)
    axis = vt[0]
    if probe_known and spreads[1] > ROUND_POOL * spreads[0]:
        # as long one way as another (a ventricle joined to a neighbour
        # across): its long axis is the one of them nearest the sector's
        axis = (depth @ vt[0]) * vt[0] + (depth @ vt[1]) * vt[1]
        axis /= np.linalg.norm(axis)
    axis = axis if axis @ (probe - centre) >= 0 else -axis
    if probe_known and abs(axis @ depth) < np.cos(np.radians(AXIS_MAX_DEG)):
        return None  # not an apical view of this pool
    found = [_along(points, centre, axis, voxel_ml, slab)]
    if not probe_known:
        found.append(_along(points, centre, -axis, voxel_ml, slab))
        found = [max(found, key=lambda f: (f is not None, f is not None and f["scores"]["waist"] == 1.0,
                                            f is not None and -f["taper"]))]
    best = found[0]
    if best is None:
        return None
    # the apical view centres the left ventricle: off the sector axis counts against a pool
    middle = best["middle"] - probe
    off_axis = np.linalg.norm(middle - (middle @ depth) * depth)
    best["score"] = best["volume_ml"] * np.exp(-((off_axis / 30.0) ** 2)) * best["scores"]["length"]
    return best


def _waist(area, first: int, last: int, allowed) -> tuple[int, float]:
    """The section narrowest against the widest on either side of it: its
    index among ``allowed`` strictly between ``first`` and ``last`` and that
    dip, ``1 - area / min(widest before, widest after)`` (``last`` and 0
    when no section dips).  The widest sections on either side are running
    maxima: linear in the number of sections."""
    ks = np.arange(first + 1, last)
    if ks.size == 0:
        return last, 0.0
    span = np.asarray(area[first:last + 1], dtype=float)
    before = np.maximum.accumulate(span)[ks - first - 1]  # widest of area[first:k]
    after = np.maximum.accumulate(span[::-1])[::-1][ks - first]  # widest of area[k:last + 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        here = 1 - span[ks - first] / np.minimum(before, after)
    here = np.where(np.asarray(allowed)[ks] & np.isfinite(here), here, -np.inf)
    k = int(np.argmax(here))  # the first of the deepest, as a scan keeping strict improvements
    return (int(ks[k]), float(here[k])) if here[k] > 0 else (last, 0.0)


def _along(points, centre, axis, voxel_ml, slab, *, bin_mm: float = 2.0) -> dict | None:
    """Apex, base and scores of a pool whose apex lies along ``axis``."""
    t = (points - centre) @ axis
    if not (t.size and np.all(np.isfinite(t))) or np.ptp(t) > 4 * LENGTH_RANGE_MM[1]:
        return None  # no ventricle: and its sections would be millions (a wrong spacing)
    edges = np.arange(t.min() - bin_mm / 2, t.max() + bin_mm, bin_mm)
    area = np.histogram(t, edges)[0] * voxel_ml * 1000.0 / bin_mm  # mm^2 of section
    heights = (edges[:-1] + edges[1:]) / 2
    # from the apex side (largest t) towards the base
    heights, area = heights[::-1], ndimage.uniform_filter1d(area[::-1], 3)
    present = np.flatnonzero(area > 0.05 * area.max())
    first, last = present[0], present[-1]
    # the waist: the section narrowest against the widest on either side of it
    # (a ventricle's own sections only narrow towards the apex)
    waist, depth_of_waist = _waist(area, first, last, heights[first] - heights >= LENGTH_RANGE_MM[0])
    stepped = False
    if depth_of_waist < 0.1:
        waist, depth_of_waist = last, 0.0
        # no waist: a step down into a narrower atrium (or the pool's end)
        widest = first + int(np.argmax(area[first:last + 1]))
        reach = int(round(10.0 / bin_mm))
        for k in range(max(widest, first + 2), last - reach):
            if heights[first] - heights[k] < LENGTH_RANGE_MM[0] or area[k + reach] < 0.3 * area[widest]:
                continue
            drop = 1 - area[k + 2] / area[k - 2]
            if drop > max(depth_of_waist, 0.15):
                waist, depth_of_waist, stepped = k, drop, True
    apex_t, base_t = heights[first] - bin_mm / 2, heights[waist]
    length = apex_t - base_t
    lv = t >= base_t
    volume_ml = float(lv.sum() * voxel_ml)
    lo, hi = VOLUME_RANGE_ML
    if not (lo <= volume_ml <= hi):
        return None
    # whole layers of voxels on either side (a thinner slab of a slightly
    # tilted grid is a strip off to one side)
    p = points[np.abs(t - base_t) <= slab].mean(0)
    base = p + axis * (base_t - (p - centre) @ axis)
    p = points[t >= apex_t - 2 * slab].mean(0)
    apex = p + axis * (apex_t - (p - centre) @ axis)
    # a ventricle is longer than it is wide (apex to base over the widest
    # section's diameter); a cavity whose apex haze or the sector's edge cuts
    # off is a squat stump
    widest = area[first:waist + 1].max()
    # its width from its narrower spread across the axis (a disc's diameter
    # is sqrt(20) of it), which a neighbour joined on one side leaves alone
    across = points[lv] - points[lv].mean(0)
    across = across - np.outer(across @ axis, axis)
    narrow = float(np.sqrt(max(np.linalg.eigvalsh(across.T @ across / max(len(across), 1))[1], 0.0)))
    elongation = float(length / (np.sqrt(20.0) * narrow)) if narrow > 0 else 0.0
    # an apex tapers (10 mm from it the section is a quarter to a third of
    # the widest on an ellipsoid): the end of a pool with no probe known
    taper = float(np.interp(apex_t - 10.0, heights[::-1], area[::-1]) / widest)
    l_lo, l_hi = LENGTH_RANGE_MM
    scores = {
        "waist": 0.4 if stepped or waist == last else float(np.clip((depth_of_waist - WAIST_MIN) / WAIST_MIN, 0, 1)),
        # alone enough to take the confidence under 0.5: a pool of an unusual
        # size is as often the wrong region, or part of the right one
        "size": 1.0 if SIZE_RANGE_ML[0] <= volume_ml <= SIZE_RANGE_ML[1] else 0.4,
        "length": float(l_lo <= length <= l_hi),
        "elongation": float(np.clip((elongation - ELONGATION_MIN) / 0.2, 0, 1)),
    }
    # the cavity's radius within 10 mm of the base, on the ventricle's side
    near = area[max(first, waist - int(round(10.0 / bin_mm))):waist + 1]
    base_radius = float(np.sqrt(near.max() / np.pi))
    measures = {"waist": float(depth_of_waist), "elongation": elongation, "length_mm": float(length),
                "width_mm": float(np.sqrt(20.0) * narrow)}
    return {"apex": apex, "base": base, "normal": axis, "volume_ml": volume_ml, "scores": scores,
            "base_radius": base_radius, "middle": points[lv].mean(0), "taper": taper,
            "measures": measures}


def _across(axis) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors across ``axis`` (unit), at right angles to each other."""
    e2 = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    e2 /= np.linalg.norm(e2)
    return e2, np.cross(axis, e2)


def _sections(sample, origin, axis, heights, *, radius: float = 36.0, spacing: float = 1.5):
    """Planes across ``axis`` at ``heights`` (mm from ``origin``): for
    each, the points of a square of half-width ``radius`` about the axis
    (``(heights, n, n, 3)`` world mm) and the levelled grey levels there
    (NaN off the data)."""
    e2, e3 = _across(axis)
    s = np.arange(-radius, radius + spacing / 2, spacing)
    plane = s[:, None, None] * e2 + s[None, :, None] * e3  # (n, n, 3)
    points = origin + np.asarray(heights)[:, None, None, None] * axis + plane[None]
    return points, sample(points)


def _ringed_sections(sample, origin, axis, heights, threshold: float, spread: float, *,
                     spacing: float = 1.5) -> list:
    """The cavity's sections that are closed all round by brighter tissue:
    ``(height, centre (world mm), area mm^2)`` of each plane across ``axis``
    whose dark region about the axis (the connected part of it nearest the
    axis, below ``threshold``) does not reach the square sampled and is
    ringed by tissue brighter by :data:`WALL_MIN` ``spread``; each plane
    sampled every ``spacing`` mm."""
    points, grey = _sections(sample, origin, axis, heights, spacing=spacing)
    n = grey.shape[1]
    middle = n // 2
    found = []
    for height, plane, values in zip(heights, points, grey):
        dark = np.isfinite(values) & (values < threshold)
        labels, count = ndimage.label(dark)
        if count == 0:
            continue
        # the part nearest the axis
        near = np.argwhere(labels > 0)
        label = labels[tuple(near[np.argmin(np.sum((near - middle) ** 2, axis=1))])]
        region = labels == label
        if region[0].any() or region[-1].any() or region[:, 0].any() or region[:, -1].any():
            continue  # joined to the dark around it (or cut by the sector's edge)
        area = region.sum() * spacing ** 2
        if not (np.pi * 6.0 ** 2 <= area <= np.pi * 35.0 ** 2):
            continue
        ring = ndimage.binary_dilation(region, iterations=2) & ~region
        if not np.isfinite(values[ring]).all():
            continue  # closed by the sector's edge, not by tissue
        if (values[ring].mean() - values[region].mean()) / spread < WALL_MIN:
            continue
        found.append((float(height), plane[region].mean(0), float(area)))
    return found


def _along_ringed_sections(volume, smooth, inside, threshold: float, spread: float, contrast: float, to_world,
                           probe, depth, *, reach: float = 200.0) -> dict | None:
    """Apex, base and scores of a cavity whose dark pool is joined to the
    dark regions around it (a faint wall), or None.

    Where the wall is clear, the cavity's sections across the sector's
    centre line are still dark discs ringed by brighter tissue
    (:func:`_ringed_sections`, on the coarse levelled image).  The longest
    series of neighbouring ones (of equals, the nearest the probe) is the
    cavity, cut at its waist when it has one (an open mitral valve joins the
    atrium's sections on).  The long axis is the line through the sections'
    centres when they span :data:`AXIS_SPAN_MM`, and otherwise the line
    from the probe through them (an apical view looks down the long axis
    from over the apex).  Along it the apex and, without a waist, the base
    are where the full-resolution grey level leaves the blood's
    (:func:`_cavity_ends`); at a waist, the base is its section moved onto
    the mitral plane (:func:`_mitral_plane`).  Each rise must be at least
    half the image's tissue-blood ``contrast`` (grey levels): a cavity that
    runs off the data or into more dark is not located.
    """
    filled = np.where(inside, smooth, 0.0).astype(np.float64)
    valid = inside.astype(np.float64)
    origin_index = to_world(np.zeros(3))
    jacobian = np.stack([to_world(e) - origin_index for e in np.eye(3)], 1)  # world = o + J index_zyx
    inverse = np.linalg.inv(jacobian)

    def sample(points):
        index = (np.asarray(points, float) - origin_index) @ inverse.T
        flat = index.reshape(-1, 3).T
        grey = ndimage.map_coordinates(filled, flat, order=1, cval=0.0)
        ok = ndimage.map_coordinates(valid, flat, order=1, cval=0.0) > 0.99  # all eight neighbours on the data
        return np.where(ok, grey, np.nan).reshape(index.shape[:-1])

    probe, depth = np.asarray(probe, float), np.asarray(depth, float)
    rings = _ringed_sections(sample, probe, depth, np.arange(0.0, reach, 3.0), threshold, spread)
    if not rings:
        return None
    # the longest series of neighbouring sections (others lie in the atrium or beside the heart)
    breaks = np.flatnonzero(np.diff([h for h, _, _ in rings]) > 6.0) + 1
    series = np.split(np.arange(len(rings)), breaks)
    rings = [rings[k] for k in series[int(np.argmax([len(g) for g in series]))]]
    # an open mitral valve joins the atrium's sections on: they end at the waist
    area = np.array([a for _, _, a in rings])
    waist, dip = _waist(area, 0, len(rings) - 1, np.ones(len(rings), bool))
    if dip >= RING_WAIST:
        rings = rings[:waist + 1]
    centres = np.array([c for _, c, _ in rings])
    middle = centres.mean(0)
    if np.ptp([h for h, _, _ in rings]) >= AXIS_SPAN_MM:  # the sections' centres line up on the axis
        axis = np.linalg.svd(centres - middle, full_matrices=False)[2][0]
        axis = axis if axis @ depth >= 0 else -axis
    else:  # too few to tilt it: an apical view looks down the long axis from over the apex
        axis = (middle - probe) / np.linalg.norm(middle - probe)
    if axis @ depth < np.cos(np.radians(AXIS_MAX_DEG)):
        return None  # not an apical view of it
    start = middle - ((middle - probe) @ axis) * axis  # the axis's point nearest the probe
    apex_t, base_t = _cavity_ends(volume, start, axis, (centres - start) @ axis, 0.5 * contrast, reach)
    base_radius = float(np.sqrt(max(a for _, _, a in rings) / np.pi))
    if dip >= RING_WAIST:  # the base at the waist, moved onto the mitral plane
        base = _mitral_plane(volume, start + ((centres[-1] - start) @ axis) * axis, -axis,
                             BASE_DISC * float(np.sqrt(area[waist] / np.pi)), contrast)
    elif base_t is not None:
        base = start + base_t * axis
    else:
        return None
    if apex_t is None:
        return None
    apex = start + apex_t * axis
    length = float(np.linalg.norm(base - apex))
    if not (LENGTH_RANGE_MM[0] <= length <= LENGTH_RANGE_MM[1]):
        return None
    # a half-ellipsoid of the widest ringed section's radius
    volume_ml = 2.0 / 3.0 * np.pi * base_radius ** 2 * length / 1000.0
    return {"apex": apex, "base": base, "volume_ml": float(volume_ml), "refined": True,
            "scores": {"pool": JOINED_POOL}, "score": 1.0, "measures": {"waist": float(dip)}}


def _cavity_ends(volume, start, axis, held, rise: float, reach: float) -> tuple[float | None, float | None]:
    """Heights (mm from ``start`` along ``axis``) of the apex and the base
    of a cavity known to span the heights ``held``: where the
    full-resolution grey level crosses half way from the blood's (its
    median over ``held``) to the wall's, towards the probe and away from it
    (:func:`_crossing`; the base within :data:`BASE_REACH_MM`).  None for a
    side that rises by no more than ``rise`` grey levels or runs off the
    data."""
    t = np.arange(0.0, reach, 1.0)
    profile = _axial_profile(volume, start, axis, t)
    inside = (t >= np.min(held)) & (t <= np.max(held))
    if not np.isfinite(profile[inside]).any():
        return None, None
    blood = float(np.nanmedian(profile[inside]))
    first, last = int(np.flatnonzero(inside)[0]), int(np.flatnonzero(inside)[-1])
    return (_crossing(profile, t, blood, first, -1, first, rise=rise),
            _crossing(profile, t, blood, last, +1, int(BASE_REACH_MM), rise=rise))


def _axial_profile(volume, start, axis, heights, *, disc: float = 3.0, smooth_mm: float = 2.0) -> np.ndarray:
    """Grey levels of ``volume`` along ``axis`` from ``start`` at the evenly
    spaced ``heights`` (mm), averaged over a disc of radius ``disc`` mm
    across it (the centre and 8 points on its rim; speckle) and smoothed by
    a Gaussian of ``smooth_mm``; NaN where no point of the disc has data."""
    e2, e3 = _across(axis)
    angles = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    offsets = np.concatenate([[[0.0, 0.0, 0.0]], disc * (np.cos(angles)[:, None] * e2 + np.sin(angles)[:, None] * e3)])
    values = volume.sample(start + np.asarray(heights)[:, None, None] * axis + offsets[None])
    ok = np.isfinite(values)
    with np.errstate(invalid="ignore"):
        profile = np.where(ok, values, 0).sum(1) / ok.sum(1)
    step = float(heights[1] - heights[0]) if len(heights) > 1 else 1.0
    smoothed = ndimage.gaussian_filter1d(np.nan_to_num(profile), smooth_mm / step)
    return np.where(np.isfinite(profile), smoothed, np.nan)


def _crossing(profile, heights, blood: float, start: int, direction: int, reach, *, rise: float = 0.0,
              near: int = 12):
    """Where ``profile`` first crosses half way from ``blood`` to its
    brightest level within ``reach`` samples from ``start`` in
    ``direction`` (interpolated height), or None when that level is not
    ``rise`` above ``blood`` or data runs out before the crossing."""
    end = min(max(start + direction * int(reach), 0), len(profile) - 1)
    window = np.arange(start, end + direction, direction)
    values = profile[window]
    if values.size < 2 or not np.isfinite(values).any():
        return None
    if float(np.nanmax(values)) - blood <= rise:
        return None
    # half way to the brightest level, then to the brightest within ``near``
    # samples beyond that crossing (the wall or the haze next to the blood,
    # not a brighter echo further off: the near field's ringing)
    k = _first_at_or_above(values, 0.5 * (blood + float(np.nanmax(values))))
    if k is None:
        return None
    level = 0.5 * (blood + float(np.nanmax(values[k:k + near + 1])))
    k = _first_at_or_above(values, level)
    if k is None:
        return None
    a, b = values[k - 1], values[k]
    return float(heights[window[k - 1]] + (heights[window[k]] - heights[window[k - 1]]) * (level - a) / (b - a))


def _first_at_or_above(values, level: float) -> int | None:
    """The first index (from 1) at which ``values`` reach ``level``, None
    when data runs out (NaN) before."""
    for k in range(1, values.size):
        if not np.isfinite(values[k]):
            return None
        if values[k] >= level:
            return k
    return None


def _mitral_plane(volume, base, axis, radius: float, contrast: float, *, reach: float = 12.0) -> np.ndarray:
    """The coarse ``base`` moved along ``axis`` to where the cavity meets the
    mitral annulus.

    The mean grey level over a disc of ``radius`` mm across the axis (rings
    at a quarter to the whole of it, weighted by the area each stands for) is the
    blood's level inside the ventricle and rises where the disc meets the
    annulus, the closed leaflets or the narrower orifice.  The plane is where
    that profile, smoothed over 1 mm, crosses half-way from the blood's level
    (its median over the half of the ``reach`` on the apex side) to its peak
    beyond, searching from the peak towards the apex.  The coarse pool's
    narrowest section lies a few millimetres beyond it (3-4 mm voxels, and
    the atrium widening past the orifice).  ``base`` is kept when the rise is
    under 0.15 of ``contrast`` (the grey-level difference of tissue and
    blood): no annulus is seen.
    """
    heights = np.arange(-reach, reach + 0.5, 1.0)
    radii = np.array([0.25, 0.5, 0.75, 1.0])
    profile = basal_profile(volume, base, axis, radius, heights=heights, radii=radii, n_angles=16)
    if not np.isfinite(profile).all():
        return base
    disc = ndimage.gaussian_filter1d(np.array([0.25, 0.5, 0.75, 0.5]) @ profile / 2.0, 1.0)
    blood = float(np.median(disc[heights >= reach / 2]))
    peak = int(np.argmax(np.where(heights < reach / 2, disc, -np.inf)))
    if disc[peak] - blood < 0.15 * contrast:
        return base
    level = 0.5 * (blood + disc[peak])
    if not (disc[peak:] < level).any():
        return base
    k = peak + int(np.argmax(disc[peak:] < level)) - 1  # the last sample at or above the level
    z = heights[k] + (disc[k] - level) / (disc[k] - disc[k + 1])
    return base + z * axis


def _endocardial_apex(volume, apex, axis, threshold: float, *, reach: float = 12.0, disc: float = 3.0) -> np.ndarray:
    """Where the grey level along ``axis`` first rises above ``threshold``
    beyond the cavity, within ``reach`` mm of the coarse ``apex`` either way.

    The coarse pool's tip is rounded off by the opening and the 3 mm voxels;
    the full-resolution image along the axis (averaged over a disc of radius
    ``disc`` mm across it, and over 2 mm along it, for the speckle) finds the
    wall itself.
    """
    heights = np.arange(-reach, reach + 0.25, 0.5)
    profile = _axial_profile(volume, apex, axis, heights, disc=disc, smooth_mm=1.0)
    if not np.isfinite(profile).all():
        return apex
    inside = np.flatnonzero(profile < threshold)
    if inside.size == 0:
        return apex
    # from the deepest blood sample at or before the coarse apex outwards to the first tissue
    start = inside[inside <= len(heights) // 2]
    if start.size == 0:
        return apex
    beyond = np.flatnonzero(profile[start[-1]:] >= threshold)
    if beyond.size == 0:
        return apex
    k = start[-1] + beyond[0]
    # interpolate the crossing between samples k - 1 and k
    a, b = profile[k - 1], profile[k]
    height = heights[k - 1] + 0.5 * (threshold - a) / (b - a)
    return apex + height * axis


def check_points(located: Located, apex, base, *, tolerance_mm: float = 10.0) -> list[str]:
    """Warnings about clicked points that disagree grossly with ``located``.

    Four errors are looked for: apex and base swapped (the clicked long axis
    points away from the located one), the base off the located mitral plane
    (measured along its normal: into the atrium, or short of the plane
    towards the apex), the apex beyond that plane (in the atrium) and the
    apex more than ``tolerance_mm`` from the located one (a confident
    location's apex was within 5 mm of the truth on 60 phantoms of every
    image formation, tilt, poor window, clutter and dropout; haze that hides
    the apex leaves the location without confidence).

    Parameters
    ----------
    located : Located
        What :func:`locate` found; nothing is said when its confidence is
        under :data:`CHECK_CONFIDENCE`.
    apex, base : (3,) world mm
        The points given.
    tolerance_mm : float
        How far (mm) the base may lie from the located mitral plane, and the
        apex from the located apex, before it is called wrong.

    Returns
    -------
    list of str
        One warning per point that looks wrong, naming where the located one
        is; empty when the points agree (or ``located`` is not confident).
    """
    if not located.confidence >= CHECK_CONFIDENCE:
        return []
    apex, base = np.asarray(apex, float), np.asarray(base, float)
    here = lambda p: "(" + ", ".join(f"{x:.1f}" for x in p) + ")"  # noqa: E731
    axis = apex - base
    if axis @ located.normal < 0:
        return [f"the apex and the base look swapped: the ventricle's apex was found at {here(located.apex)} and "
                f"its base at {here(located.base)}"]
    warnings = []
    offset = float((base - located.base) @ located.normal)
    if abs(offset) > tolerance_mm:
        where = ("short of the mitral plane, towards the apex" if offset > 0
                 else "beyond the mitral plane, in the atrium")
        warnings.append(f"the base looks wrong: {abs(offset):.0f} mm {where}; the mitral plane's centre was found "
                        f"at {here(located.base)}")
    if (apex - located.base) @ located.normal < 0:
        warnings.append(f"the apex looks wrong: it lies beyond the mitral plane, in the atrium; the apex was found at "
                        f"{here(located.apex)}")
    else:
        miss = float(np.linalg.norm(apex - located.apex))
        if miss > tolerance_mm:
            warnings.append(f"the apex looks wrong: {miss:.0f} mm from the apex found at {here(located.apex)}")
    return warnings


def initialise(volume, apex, base, *, annulus=None, init=None, check: bool = True, locator=None):
    """The points a segmentation starts from, and how they were had.

    With no points (and no ``annulus`` or ``init``) the ventricle is located;
    otherwise the points given are used and, if ``check``, located as well to
    check them (:func:`check_points`).  ``locator(volume) -> Located`` is
    called in place of :func:`locate` when given (the viewer's, which
    locates each frame once however often the user clicks).

    Returns
    -------
    apex, base : arrays or the inputs
    initialisation : dict
        ``method`` (``"located"`` or ``"given"``), ``apex``, ``base``, and
        ``located`` (:meth:`Located.as_dict`) when it was located.
    located : Located or None
    """
    locator = locate if locator is None else locator
    if apex is None and base is None and annulus is None and init is None:
        found = locator(volume)
        return found.apex, found.base, {"method": "located", "apex": found.apex.tolist(),
                                        "base": found.base.tolist(), "located": found.as_dict()}, found
    if apex is None:
        raise ValueError("give the apex with the base (or annulus), or neither to locate the ventricle")
    initialisation = {"method": "given", "apex": np.asarray(apex, float).tolist(),
                      "base": None if base is None else np.asarray(base, float).tolist()}
    found = None
    if check and init is None:
        try:
            found = locator(volume)
            initialisation["located"] = found.as_dict()
        except NoVentricleError as error:
            initialisation["located"] = str(error)
    return apex, base, initialisation, found


def annotate(result, initialisation: dict, located: Located | None) -> None:
    """Record ``initialisation`` on ``result`` and add to its quality report
    what the location says: a low confidence when the points were located,
    the click checks when they were given, and that they could not be
    checked when the ventricle was not found or not with confidence
    (:data:`CHECK_CONFIDENCE`)."""
    result.initialisation = initialisation
    if result.quality is None:
        return
    checked = initialisation.get("located")
    if initialisation["method"] == "located":
        warnings = [] if located is None or located.confidence >= CHECK_CONFIDENCE else [
            f"the ventricle was found with low confidence ({located.confidence:.2f}: {located.reason}); "
            "give the apex and base"]
    elif checked is None:  # not asked to check
        warnings = []
    elif located is None or not located.confidence >= CHECK_CONFIDENCE:
        # said, not flagged: the clicks may well be right (a real scan whose ventricle the coarse look cannot
        # find with confidence); the result is poor only by what the image says of it
        why = checked if located is None else (f"the ventricle was found with low confidence "
                                               f"({located.confidence:.2f}: {located.reason})")
        result.quality["notes"] = list(result.quality.get("notes", [])) + [
            f"the clicked points could not be checked: {why}"]
        warnings = []
    else:
        base = result.surface.pose.origin if initialisation["base"] is None else initialisation["base"]
        warnings = check_points(located, initialisation["apex"], base)
    if warnings:
        result.quality["warnings"] = list(result.quality["warnings"]) + warnings
        result.quality["poor"] = True
