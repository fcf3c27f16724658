"""B-mode image formation of a phased-array 3D echo scanner, in beam space.

Given the backscatter (echogenicity) of the scene at every beam-space
sample, this module forms what a scanner displays:

1. **Speckle**: complex Gaussian scatterers of power ``echogenicity``,
   convolved with the point-spread function (PSF) of the beam: a Gaussian
   of FWHM ``axial_psf_mm`` along the beam and of lateral and elevation
   FWHM ``w(r)`` that grows with depth ``r`` as from a focused phased array
   (see :meth:`ImageFormation.beam_width`).  The PSF is normalised to unit
   energy, so a uniform region of echogenicity ``e`` has mean intensity
   ``e`` and a Rayleigh envelope (fully developed speckle).
2. **Attenuation** ``attenuation_db_per_cm`` (two-way) along the beam, then
   additive thermal noise of power ``noise_db``, then **time-gain
   compensation** (TGC) ``tgc_db_per_cm`` and the overall **gain**.
3. **Log compression** of the envelope to 8 bits over ``dynamic_range_db``:
   grey ``1 + 254 (L - L_top + DR) / DR`` clipped to ``[1, 255]``, with
   ``L`` the level in dB and ``L_top = 10 dB`` above the reference tissue;
   0 is kept for "no data".

Levels are in dB of power relative to the reference tissue (the tissue
around the heart) at the transducer: echogenicity 1 is 0 dB.

Beam space is a :class:`spheroseg.beamspace.BeamGeometry` (``[radius,
elevation, azimuth]``, ITK's ``PhasedArray3DSpecialCoordinatesImage`` terms);
:func:`sector_geometry` samples a sector as finely as a scanner would for a
given PSF, :func:`form_image` returns a
:class:`~spheroseg.beamspace.BeamVolume`, and
:func:`spheroseg.beamspace.scan_convert` takes it to a Cartesian grid.
:class:`PostProcessing` and :func:`postprocess` smooth the scan-converted
grey levels as a scanner does before export.  :func:`multiplicative_speckle`
is the simpler model many simulators use, for images of another making.
Nothing here knows what is being imaged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..volumes.beamspace import BeamGeometry, BeamVolume

__all__ = ["ImageFormation", "sector_geometry", "speckle_envelope", "log_compress", "form_image", "RAYLEIGH_DB_STD",
           "PostProcessing", "postprocess", "multiplicative_speckle"]

#: standard deviation of ``20 log10`` of a Rayleigh amplitude (fully
#: developed speckle), dB: ``(20 / ln 10) * pi / (2 sqrt 6)``
RAYLEIGH_DB_STD = 20 / np.log(10) * np.pi / (2 * np.sqrt(6))

FWHM_PER_SIGMA = 2 * np.sqrt(2 * np.log(2))

#: the display's white level, dB above the reference tissue at gain 0
TOP_DB = 10.0


@dataclass(frozen=True)
class ImageFormation:
    """How a phased-array 3D echo scanner forms a B-mode volume.

    The defaults resemble an adult apical 3D scan with a 2.5-3.5 MHz
    matrix array (wavelength ~0.5 mm, aperture ~20 mm): axial resolution
    0.8 mm, lateral and elevation resolution about 3 mm at 80 mm depth,
    55 dB dynamic range, TGC set to compensate most of the attenuation.

    Parameters
    ----------
    axial_psf_mm : float
        Full width at half maximum (FWHM) of the envelope PSF along the
        beam, mm (about the pulse length: 1.5-2 cycles at 3 MHz).
    lateral_psf_mm, elevation_psf_mm : float
        FWHM of the PSF across the beam in azimuth and elevation at
        ``reference_depth_mm``, mm.
    reference_depth_mm : float
        Depth at which the lateral and elevation widths are given, mm.
    focus_depth_mm, depth_of_field_mm : float
        Transmit focus and the depth over which the beam stays near its
        focal angular width, mm (see :meth:`beam_width`).
    dynamic_range_db : float
        Range of levels mapped to grey 1-255, dB (scanners offer 40-70).
    gain_db : float
        Overall receive gain, dB.
    attenuation_db_per_cm : float
        Two-way attenuation along the beam, dB/cm (0.5 dB/cm/MHz one way in
        soft tissue, less in blood: ~2 dB/cm at 3 MHz through the heart).
    tgc_db_per_cm : float
        Time-gain compensation, dB/cm of depth: below the attenuation leaves
        the far field darker, above it brighter.
    noise_db : float
        Thermal noise power per sample, before TGC, dB relative to the
        reference tissue at the transducer.
    blood_db : float
        Backscatter of blood relative to the reference tissue, dB.
    contrast_db : float
        Backscatter of myocardium relative to blood, dB (so the myocardium
        is at ``blood_db + contrast_db`` relative to the reference tissue).
    clutter_db : float or None
        Power of the near-field clutter (reverberation haze), dB relative to
        the reference tissue, at ``clutter_depth_mm``; ``None``: no clutter.
    clutter_depth_mm : float
        Depth of the clutter's maximum, mm (the apex region of an apical
        view); it falls off as a Gaussian of 1/e half-width 12 mm.
    dropout_db : float
        Loss of signal from a wall region (a wall parallel to the beams, a
        rib shadow), dB; 0: none.  Where it lies is the scene's business.
    dropout_radius_mm : float
        Size of that region: the loss is full within ``dropout_radius_mm - 6``
        of its centre and fades to none at ``dropout_radius_mm`` (> 6).

    Notes
    -----
    A frozen dataclass: formations are values, ``dataclasses.replace`` makes
    a variant.
    """

    axial_psf_mm: float = 0.8
    lateral_psf_mm: float = 3.0
    elevation_psf_mm: float = 3.4
    reference_depth_mm: float = 80.0
    focus_depth_mm: float = 70.0
    depth_of_field_mm: float = 50.0
    dynamic_range_db: float = 55.0
    gain_db: float = 0.0
    attenuation_db_per_cm: float = 2.0
    tgc_db_per_cm: float = 1.6
    noise_db: float = -55.0
    blood_db: float = -30.0
    contrast_db: float = 35.0
    clutter_db: float | None = -32.0
    clutter_depth_mm: float = 26.0
    dropout_db: float = 0.0
    dropout_radius_mm: float = 16.0

    def __post_init__(self):
        positive = ("axial_psf_mm", "lateral_psf_mm", "elevation_psf_mm", "reference_depth_mm", "focus_depth_mm",
                    "depth_of_field_mm", "dynamic_range_db")
        for name in positive:
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"ImageFormation.{name} must be a positive number, got {value!r}")
        for name in ("gain_db", "attenuation_db_per_cm", "tgc_db_per_cm", "noise_db", "blood_db", "contrast_db",
                     "clutter_depth_mm", "dropout_db"):
            if not np.isfinite(getattr(self, name)):
                raise ValueError(f"ImageFormation.{name} must be finite, got {getattr(self, name)!r}")
        if self.clutter_db is not None and not np.isfinite(self.clutter_db):
            raise ValueError(f"ImageFormation.clutter_db must be finite or None, got {self.clutter_db!r}")
        if not self.dropout_radius_mm > 6.0:
            raise ValueError(f"ImageFormation.dropout_radius_mm must be more than 6 mm, got {self.dropout_radius_mm}")
        if self.attenuation_db_per_cm < 0 or self.dropout_db < 0:
            raise ValueError("ImageFormation.attenuation_db_per_cm and dropout_db must be >= 0")

    def beam_width(self, depth_mm, *, direction: str = "lateral") -> np.ndarray:
        """FWHM of the PSF across the beam at ``depth_mm``, mm.

        ``w(r) = w_ref (r / r_ref) g(r) / g(r_ref)`` with
        ``g(r) = sqrt(1 + ((r - r_focus) / depth_of_field)^2)``: a diffraction
        width ``wavelength * r / aperture`` (constant angle, so growing
        linearly with depth), widened away from the transmit focus.

        Parameters
        ----------
        depth_mm : array_like
            Distance from the probe along the beam, mm.
        direction : {"lateral", "elevation"}
        """
        return self.angular_width(depth_mm, direction=direction) * np.asarray(depth_mm, dtype=float)

    def angular_width(self, depth_mm, *, direction: str = "lateral") -> np.ndarray:
        """FWHM of the PSF across the beam as an angle, radians:
        ``beam_width(r) / r`` (finite at the probe)."""
        if direction not in ("lateral", "elevation"):
            raise ValueError(f"direction must be 'lateral' or 'elevation', got {direction!r}")
        ref = self.lateral_psf_mm if direction == "lateral" else self.elevation_psf_mm

        def g(r):
            return np.sqrt(1 + ((r - self.focus_depth_mm) / self.depth_of_field_mm) ** 2)

        r = np.asarray(depth_mm, dtype=float)
        return ref / self.reference_depth_mm * g(r) / g(self.reference_depth_mm)

    def sampling(self) -> tuple[float, float, float]:
        """Beam-space sample steps a scanner would use for this PSF:
        ``(radius mm, elevation rad, azimuth rad)``, half the narrowest FWHM
        (the axial width; the angular widths at the focus)."""
        narrowest = {d: float(self.angular_width(self.focus_depth_mm, direction=d)) for d in ("lateral", "elevation")}
        return self.axial_psf_mm / 2, narrowest["elevation"] / 2, narrowest["lateral"] / 2


def sector_geometry(formation: ImageFormation, *, half_angle_deg: float, max_radius_mm: float,
                    probe_to_world=None) -> BeamGeometry:
    """A square pyramidal sector of ``+-half_angle_deg`` from the probe to
    ``max_radius_mm``, sampled at :meth:`ImageFormation.sampling` (tan
    convention, the first sample at the probe).

    Parameters
    ----------
    formation : ImageFormation
    half_angle_deg : float
        Half opening angle in azimuth and in elevation, degrees (< 90).
    max_radius_mm : float
        Depth of the last sample along each beam, mm.
    probe_to_world : 4x4 array, optional
        Rigid placement of the probe frame in the world (default identity).
    """
    if not 0 < half_angle_deg < 90 or not max_radius_mm > 0:
        raise ValueError(f"need 0 < half_angle_deg < 90 and max_radius_mm > 0, got {half_angle_deg!r}, "
                         f"{max_radius_mm!r}")
    dr, de, da = formation.sampling()
    half = np.radians(half_angle_deg)
    ne, na = (2 * int(np.ceil(half / step)) + 1 for step in (de, da))
    nr = int(np.ceil(max_radius_mm / dr)) + 1
    return BeamGeometry((nr, ne, na), dr, 0.0, azimuth_angular_separation=half / ((na - 1) / 2),
                        elevation_angular_separation=half / ((ne - 1) / 2),
                        probe_to_world=np.eye(4) if probe_to_world is None else probe_to_world)


def _radii(geometry: BeamGeometry) -> np.ndarray:
    return geometry.first_sample_distance + np.arange(geometry.shape[0]) * geometry.radius_sample_size


def _unit_energy_kernel(sigma: float) -> np.ndarray:
    """Sampled Gaussian (std ``sigma`` samples) with sum of squares 1."""
    if sigma < 0.05:
        return np.ones(1)
    half = max(1, int(np.ceil(4 * sigma)))
    x = np.arange(-half, half + 1)
    k = np.exp(-(x**2) / (2 * sigma**2))
    return k / np.sqrt(np.sum(k**2))


def speckle_envelope(echogenicity: np.ndarray, geometry: BeamGeometry, formation: ImageFormation,
                     rng: np.random.Generator) -> np.ndarray:
    """Received envelope (linear amplitude) of a scene in beam space.

    Scatterers ``sqrt(e) (n1 + i n2) / sqrt(2)`` with ``n`` standard normal
    at every sample, convolved with the unit-energy PSF (across the beam
    slice by slice, with the angular width of that depth; then along the
    beam), times the two-way attenuation; plus complex noise of power
    ``noise_db`` (band-limited by the axial PSF); times TGC and gain.

    Parameters
    ----------
    echogenicity : array, shape ``geometry.shape``
        Backscattered power per sample relative to the reference tissue.
    geometry : BeamGeometry
    formation : ImageFormation
    rng : numpy.random.Generator

    Returns
    -------
    envelope : float32 array, shape ``geometry.shape``
        Its square has mean ``echogenicity * 10^((tgc - att) r / 10) * gain``
        in uniform regions (plus the noise).
    """
    echogenicity = np.asarray(echogenicity, dtype=np.float32)
    if not isinstance(geometry, BeamGeometry):
        raise TypeError(f"geometry must be a BeamGeometry, got {type(geometry).__name__}")
    if echogenicity.shape != geometry.shape:
        raise ValueError(f"echogenicity has shape {echogenicity.shape}, the beam geometry {geometry.shape}")
    if np.any(echogenicity < 0) or not np.all(np.isfinite(echogenicity)):
        raise ValueError("echogenicity must be finite and >= 0")
    radius = _radii(geometry)

    def complex_normal(shape):
        return ((rng.standard_normal(shape, dtype=np.float32)
                 + 1j * rng.standard_normal(shape, dtype=np.float32)) / np.sqrt(2)).astype(np.complex64)

    field = complex_normal(geometry.shape) * np.sqrt(echogenicity)
    steps = {"elevation": geometry.elevation_angular_separation, "lateral": geometry.azimuth_angular_separation}
    sigmas = {d: formation.angular_width(radius, direction=d) / FWHM_PER_SIGMA / steps[d] for d in steps}
    for i in range(geometry.shape[0]):
        field[i] = ndimage.correlate1d(field[i], _unit_energy_kernel(sigmas["elevation"][i]), axis=0, mode="constant")
        field[i] = ndimage.correlate1d(field[i], _unit_energy_kernel(sigmas["lateral"][i]), axis=1, mode="constant")
    axial = _unit_energy_kernel(formation.axial_psf_mm / FWHM_PER_SIGMA / geometry.radius_sample_size)
    field = ndimage.correlate1d(field, axial, axis=0, mode="constant")
    cm = (radius / 10.0)[:, None, None]
    field *= (10 ** (-formation.attenuation_db_per_cm * cm / 20)).astype(np.float32)
    noise = ndimage.correlate1d(complex_normal(geometry.shape), axial, axis=0, mode="constant")
    field += np.float32(10 ** (formation.noise_db / 20)) * noise
    field *= (10 ** ((formation.tgc_db_per_cm * cm + formation.gain_db) / 20)).astype(np.float32)
    return np.abs(field).astype(np.float32)


def log_compress(envelope: np.ndarray, formation: ImageFormation) -> np.ndarray:
    """8-bit grey levels of an envelope: ``L = 20 log10(envelope)`` dB mapped
    from ``[TOP_DB - dynamic_range, TOP_DB]`` to ``[1, 255]``, rounded
    (0 stays free for "no data").  A grey step is ``dynamic_range / 254`` dB."""
    level = 20 * np.log10(np.maximum(np.asarray(envelope, dtype=np.float64), 1e-12))
    dr = formation.dynamic_range_db
    return np.round(1 + 254 * np.clip((level - TOP_DB + dr) / dr, 0, 1)).astype(np.uint8)


def form_image(echogenicity: np.ndarray, geometry: BeamGeometry, formation: ImageFormation,
               rng: np.random.Generator) -> BeamVolume:
    """Beam-space 8-bit B-mode of a scene (:func:`speckle_envelope` then
    :func:`log_compress`), every sample data (grey >= 1)."""
    grey = log_compress(speckle_envelope(echogenicity, geometry, formation, rng), formation)
    return BeamVolume(grey, geometry)


@dataclass(frozen=True)
class PostProcessing:
    """What a scanner does to the scan-converted grey levels before export.

    Parameters
    ----------
    gaussian_mm : float
        Standard deviation of a Gaussian smoothing, mm (0: none).
    median_mm : float
        Half width of the cube of a median filter, mm (0: none; 1 mm on a
        1 mm grid is the 3 x 3 x 3 median).
    diffusion_iterations : int
        Iterations of Perona-Malik anisotropic diffusion, a speckle-reducing
        filter that smooths within regions and less across edges (0: none).
    persistence : int
        Frames averaged (temporal persistence; 1: none).  Applied where the
        frames are made (:func:`spheroseg.synthetic.phantom.make_phantom`), not here.

    Notes
    -----
    Filters are applied in the order Gaussian, median, diffusion, on the
    grey levels (after log compression, as scanners do), within the sector
    only: "no data" (grey 0) stays 0 and does not darken the sector's edge.
    """

    gaussian_mm: float = 0.0
    median_mm: float = 0.0
    diffusion_iterations: int = 0
    persistence: int = 1

    def __post_init__(self):
        for name in ("gaussian_mm", "median_mm"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"PostProcessing.{name} must be a number >= 0, got {value!r}")
        for name in ("diffusion_iterations", "persistence"):
            value = getattr(self, name)
            if not (isinstance(value, (int, np.integer)) and value >= (1 if name == "persistence" else 0)):
                raise ValueError(f"PostProcessing.{name} must be an integer >= {1 if name == 'persistence' else 0}, "
                                 f"got {value!r}")


def postprocess(grey: np.ndarray, spacing, processing: PostProcessing) -> np.ndarray:
    """Smooth an 8-bit B-mode volume as :class:`PostProcessing` says.

    Parameters
    ----------
    grey : uint8 array, 3D
        Scan-converted grey levels, 0 for "no data" (outside the sector).
    spacing : float or sequence of 3 floats
        Voxel size along the array's axes, mm.
    processing : PostProcessing

    Returns
    -------
    uint8 array of the same shape, 0 exactly where ``grey`` is 0.
    """
    grey = np.asarray(grey)
    if grey.ndim != 3:
        raise ValueError(f"grey must be a 3D array, got shape {grey.shape}")
    spacing = np.broadcast_to(np.asarray(spacing, dtype=float), (3,))
    if not np.all(spacing > 0):
        raise ValueError(f"spacing must be positive, got {tuple(spacing)}")
    data = grey > 0
    image = grey.astype(np.float32)
    if processing.gaussian_mm > 0:
        # normalised convolution: the mean of the data samples only
        sigma = processing.gaussian_mm / spacing
        weight = ndimage.gaussian_filter(data.astype(np.float32), sigma)
        image = ndimage.gaussian_filter(image, sigma) / np.maximum(weight, 1e-6)
    if processing.median_mm > 0:
        size = tuple(2 * int(round(processing.median_mm / s)) + 1 for s in spacing)
        # no-data samples take the nearest data value, so the median does not see them
        nearest = ndimage.distance_transform_edt(~data, return_distances=False, return_indices=True)
        image = ndimage.median_filter(image[tuple(nearest)], size=size)
    if processing.diffusion_iterations:
        image = _perona_malik(image, data, processing.diffusion_iterations, spacing)
    return np.where(data, np.clip(np.round(image), 1, 255), 0).astype(np.uint8)


def _perona_malik(image: np.ndarray, data: np.ndarray, iterations: int, spacing: np.ndarray) -> np.ndarray:
    """Perona-Malik diffusion ``du/dt = div(g(|grad u|) grad u)``, with
    ``g(s) = 1 / (1 + (s / K)^2)`` and ``K`` the median gradient magnitude of
    the data (speckle's own gradients diffuse, stronger edges less), an
    explicit step of ``h^2 / 7`` (stable below ``h^2 / 6`` with six neighbours
    at the least spacing ``h``); no flux
    across the sector's edge."""
    u = image.astype(np.float32).copy()
    step = np.float32(np.min(spacing) ** 2 / 7)
    for _ in range(iterations):
        fluxes = []
        for axis in range(3):
            diff = np.diff(u, axis=axis) / np.float32(spacing[axis])
            both = np.logical_and(np.take(data, range(1, u.shape[axis]), axis=axis),
                                  np.take(data, range(u.shape[axis] - 1), axis=axis))
            diff = np.where(both, diff, 0)
            fluxes.append(diff)
        gradients = np.abs(np.concatenate([f[f != 0] for f in fluxes]))
        k = max(float(np.median(gradients)), 1e-3) if gradients.size else 1.0  # flat: nothing diffuses
        change = np.zeros_like(u)
        for axis, diff in enumerate(fluxes):
            flux = diff / (1 + (diff / k) ** 2) / np.float32(spacing[axis])
            pad = [(0, 0)] * 3
            pad[axis] = (1, 0)
            inflow = np.pad(flux, pad)
            pad[axis] = (0, 1)
            outflow = np.pad(flux, pad)
            change += outflow - inflow
        u += step * change
    return u


def multiplicative_speckle(echogenicity: np.ndarray, *, blur_mm: float, spacing: float, nepers: float = 15.0,
                           seed: int = 0) -> np.ndarray:
    """Grey levels of echo as a simpler simulator makes it (not a scanner):
    the echogenicity (mean intensity, on a Cartesian grid of ``spacing``
    mm) blurred by an isotropic Gaussian of standard deviation ``blur_mm``,
    times fully developed speckle independent from voxel to voxel (an
    exponential intensity), log-compressed at ``nepers`` grey levels per
    neper: ``128 + nepers ln(I)`` rounded and clipped to ``[1, 255]``
    (uint8).  Unlike :func:`form_image`'s, its speckle does not show the
    blur of its walls."""
    echogenicity = np.asarray(echogenicity, dtype=float)
    if echogenicity.ndim != 3 or not np.all(echogenicity >= 0):
        raise ValueError("echogenicity must be a 3D array of mean intensities >= 0")
    if not (blur_mm >= 0 and spacing > 0 and nepers > 0):
        raise ValueError(f"blur_mm must be >= 0, spacing and nepers > 0; got {blur_mm!r}, {spacing!r}, {nepers!r}")
    intensity = ndimage.gaussian_filter(echogenicity, blur_mm / spacing)
    speckle = np.random.default_rng(seed).exponential(1.0, intensity.shape)
    with np.errstate(divide="ignore"):  # no echo: the darkest grey level
        return np.clip(np.round(128 + nepers * np.log(intensity * speckle)), 1, 255).astype(np.uint8)
