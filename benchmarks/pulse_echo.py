"""Accuracy on echo formed by a matrix array (issue 53).

    nice -n 19 python benchmarks/pulse_echo.py                 # the sweep below
    nice -n 19 python benchmarks/pulse_echo.py --check         # point target: geometry, pymust, DAS

The project's phantom and the development set form the image by convolution
(speckle times a point-spread function).  Here the phantom's anatomy and
echogenicity (:func:`spheroseg.synthetic.phantom.make_phantom`, its beam
space and scan conversion) are imaged as a 3D probe does: a square matrix
array (``MatrixArray``) fires a few diverging waves from virtual sources
behind it, every element's echo is delayed and summed (delay-and-sum, DAS)
and the transmits are compounded coherently, then envelope, attenuation,
noise, TGC and log compression as :mod:`spheroseg.synthetic.echo` does.

Two models of the same array:

* ``point_echoes`` + ``delay_and_sum``: per-element complex baseband (IQ)
  echoes of point scatterers, exact geometry (the echo of a scatterer at
  ``s`` on element ``e`` for the transmit from virtual source ``v`` arrives
  at ``(|s - v| - min_e |e - v| + |s - e|) / c``), a Gaussian pulse of the
  array's bandwidth and the elements' directivity; DAS onto any points.
  Checked against ``pymust.simus3`` (LGPL-3, the ``[bench]`` extra) on a
  point target, and used to check the next.
* ``array_envelope``: the volume's image, fast enough for a 3D phantom.
  With dynamic receive focusing the DAS image of a scatterer at the same
  range is, in the far field of the virtual sources, a function of the
  angle difference only: the receive array factor
  ``D(d) = sum_m w_m exp(i k x_m sin d)`` in azimuth and elevation times
  the transmits' phases ``exp(i k a (s_n . d))`` summed over the
  transmits (``a``: the virtual source's distance, ``s_n`` its tilt).  So
  the image is the scatterers' field convolved (FFT, per beam-space
  slice, in angle) with that kernel, and along the beam with the pulse's
  envelope; unapodised, its side lobes (-13 dB in each direction) carry
  the walls' echo into the blood pool.  Scatterers are complex Gaussian,
  one per beam-space sample, of power the echogenicity (as the phantom's).
  The kernel has unit energy: a uniform region keeps its mean intensity,
  so the grey-level calibration is the convolution model's.

Segmentation: ``spheroseg.segment`` with defaults from the true apex and
base; volumes against the phantom's exact truth.  ``--name NAME`` stores the
run's rows under that name in docs/pulse_echo.json (the other names kept)
and regenerates docs/benchmarks.md; each run is a minute or two:

    nice -n 19 python benchmarks/pulse_echo.py --name convolution --convolution
    nice -n 19 python benchmarks/pulse_echo.py --name array
    nice -n 19 python benchmarks/pulse_echo.py --name "16 elements" --elements 16
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from dataclasses import dataclass, replace

import numpy as np

from spheroseg.synthetic.echo import ImageFormation, log_compress
from spheroseg.volumes.beamspace import BeamGeometry, BeamVolume

SOUND_SPEED_MM_PER_US = 1.54


@dataclass(frozen=True)
class MatrixArray:
    """A square 2D matrix array and its diverging-wave sequence.

    Parameters
    ----------
    elements_per_side : int
        ``n x n`` elements.
    frequency_mhz : float
        Centre frequency (MHz).
    pitch_wavelengths : float
        Element pitch in wavelengths (0.5: no grating lobes).
    bandwidth : float
        Pulse-echo fractional bandwidth at -6 dB.
    transmits : int
        Diverging waves compounded: 1 (untilted), 3 (azimuth tilts),
        5 (cross: azimuth and elevation tilts) or 9 (3 x 3).
    tilt_deg : float
        Tilt of the outer diverging waves (degrees).
    half_angle_deg : float
        Half opening of the sector the diverging waves cover: the virtual
        source lies ``a = (aperture / 2) / tan(half_angle)`` behind the array.
    apodization : {"none", "hann"}
        Receive apodisation.
    side_lobes : bool
        False: the volume's kernel (``lateral_kernel``) is a Gaussian of the
        DAS kernel's main-lobe widths, without its side lobes (to tell the
        haze from the lateral blur).
    anisotropy_db : float
        Not the array's but the scene's: the echo of tissue whose
        boundary runs along the beam is this much weaker than where the beam
        meets it face on (the myocardium's backscatter anisotropy, 10-15 dB
        between parallel and perpendicular insonation; ``angular_echogenicity``).
    anisotropy_scale_mm : float
        The smoothing over which the wall's orientation is read: 2 mm dims
        the wall's layers next to the blood and the tissue at a wall along
        the beam, 6 mm the whole of an end-systolic wall.
    """

    elements_per_side: int = 32
    frequency_mhz: float = 2.5
    pitch_wavelengths: float = 0.5
    bandwidth: float = 0.6
    transmits: int = 5
    tilt_deg: float = 15.0
    half_angle_deg: float = 38.0
    apodization: str = "none"
    side_lobes: bool = True
    anisotropy_db: float = 0.0
    anisotropy_scale_mm: float = 2.0

    @property
    def wavelength_mm(self) -> float:
        return SOUND_SPEED_MM_PER_US / self.frequency_mhz

    @property
    def pitch_mm(self) -> float:
        return self.pitch_wavelengths * self.wavelength_mm

    @property
    def aperture_mm(self) -> float:
        return self.elements_per_side * self.pitch_mm

    def positions(self) -> np.ndarray:
        """Element centres ``(n*n, 3)`` mm, the array in the plane ``z = 0``."""
        x = (np.arange(self.elements_per_side) - (self.elements_per_side - 1) / 2) * self.pitch_mm
        gx, gy = np.meshgrid(x, x, indexing="ij")
        return np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])

    def weights_1d(self) -> np.ndarray:
        n = self.elements_per_side
        return np.ones(n) if self.apodization == "none" else np.hanning(n + 2)[1:-1]

    def tilts(self) -> np.ndarray:
        """Tilt sines ``(transmits, 2)`` (azimuth, elevation)."""
        s = np.sin(np.radians(self.tilt_deg))
        sets = {1: [(0, 0)], 3: [(0, 0), (-s, 0), (s, 0)], 5: [(0, 0), (-s, 0), (s, 0), (0, -s), (0, s)],
                9: [(a, b) for a in (-s, 0, s) for b in (-s, 0, s)]}
        if self.transmits not in sets:
            raise ValueError(f"transmits must be one of {sorted(sets)}, got {self.transmits!r}")
        return np.array(sets[self.transmits], float)

    @property
    def virtual_source_mm(self) -> float:
        return self.aperture_mm / 2 / np.tan(np.radians(self.half_angle_deg))

    def virtual_sources(self) -> np.ndarray:
        """``(transmits, 3)``: behind the array centre, opposite the tilt."""
        t = self.tilts()
        direction = np.column_stack([t, np.sqrt(1 - (t**2).sum(1))])
        return -self.virtual_source_mm * direction

    @property
    def pulse_sigma_us(self) -> float:
        """Std of the pulse-echo envelope (Gaussian spectrum of -6 dB
        fractional bandwidth ``bandwidth``), microseconds."""
        sigma_f = self.bandwidth * self.frequency_mhz / 2 / np.sqrt(2 * np.log(2))
        return 1 / (2 * np.pi * sigma_f)

    @property
    def axial_fwhm_mm(self) -> float:
        return 2 * np.sqrt(2 * np.log(2)) * self.pulse_sigma_us * SOUND_SPEED_MM_PER_US / 2

    def directivity(self, sine) -> np.ndarray:
        """One element's amplitude at direction sine ``sine`` (an element as
        wide as the pitch, baffled): ``sinc(w sin / lambda) cos``."""
        sine = np.asarray(sine, float)
        return np.sinc(self.pitch_mm * sine / self.wavelength_mm) * np.sqrt(np.clip(1 - sine**2, 0, 1))

    def formation(self, **changes) -> ImageFormation:
        """The phantom's formation (attenuation, TGC, noise, levels, dynamic
        range), its PSF fields set so that the beam space is sampled at half
        this array's axial and lateral resolution; no clutter (the side
        lobes are this image's haze)."""
        # the -3 dB width of the receive sinc (its amplitude's FWHM is 1.207 lambda / D): sampled finely
        lateral = 0.886 * self.wavelength_mm / self.aperture_mm * 80.0
        base = dict(axial_psf_mm=self.axial_fwhm_mm, lateral_psf_mm=lateral, elevation_psf_mm=lateral,
                    focus_depth_mm=80.0, depth_of_field_mm=1e6, clutter_db=None)
        return ImageFormation(**{**base, **changes})


# -- exact per-element model (point targets) --------------------------------------------------------------------

def transmit_times(array: MatrixArray, points, transmit: int) -> np.ndarray:
    """Arrival time (us) of diverging wave ``transmit`` at ``points``
    ``(..., 3)`` mm: the elements fire at ``(|e - v| - min |e - v|) / c``."""
    v = array.virtual_sources()[transmit]
    first = np.linalg.norm(array.positions() - v, axis=1).min()
    return (np.linalg.norm(np.asarray(points, float) - v, axis=-1) - first) / SOUND_SPEED_MM_PER_US


def transmit_delays(array: MatrixArray, transmit: int) -> np.ndarray:
    """Firing delay of every element (us) for diverging wave ``transmit``."""
    return transmit_times(array, array.positions(), transmit)


def point_echoes(array: MatrixArray, scatterers, amplitudes, times_us, transmit: int) -> np.ndarray:
    """Complex baseband echoes ``(elements, times)`` of point scatterers
    ``(m, 3)`` mm with complex ``amplitudes`` for one diverging wave: each a
    Gaussian envelope at ``transmit_times + |s - e| / c`` with the carrier's
    phase ``exp(-i 2 pi f0 tau)``, times both directivities (1/r spreading
    left to the TGC)."""
    s = np.atleast_2d(np.asarray(scatterers, float))
    a = np.asarray(amplitudes, complex).ravel()
    e = array.positions()
    t_tx = transmit_times(array, s, transmit)                                  # (m,)
    rx = s[None, :, :] - e[:, None, :]
    d_rx = np.linalg.norm(rx, axis=-1)                                         # (E, m)
    tau = t_tx[None, :] + d_rx / SOUND_SPEED_MM_PER_US
    gain = array.directivity(np.hypot(rx[..., 0], rx[..., 1]) / d_rx)
    gain = gain * array.directivity(np.hypot(s[:, 0], s[:, 1]) / np.linalg.norm(s, axis=1))[None, :]
    t = np.asarray(times_us, float)
    out = np.zeros((e.shape[0], t.size), complex)
    for j in range(s.shape[0]):
        env = np.exp(-((t[None, :] - tau[:, j:j + 1]) ** 2) / (2 * array.pulse_sigma_us**2))
        out += (a[j] * gain[:, j:j + 1] * np.exp(-2j * np.pi * array.frequency_mhz * tau[:, j:j + 1])) * env
    return out


def delay_and_sum(array: MatrixArray, echoes, times_us, points, transmit: int) -> np.ndarray:
    """DAS of baseband ``echoes`` ``(elements, times)`` onto ``points``
    ``(p, 3)`` mm: each element's echo at the point's two-way delay,
    phase-rotated back by the carrier, apodised and summed."""
    p = np.atleast_2d(np.asarray(points, float))
    e = array.positions()
    tau = transmit_times(array, p, transmit)[None, :] + np.linalg.norm(p[None] - e[:, None], axis=-1) / SOUND_SPEED_MM_PER_US
    w = np.outer(array.weights_1d(), array.weights_1d()).ravel()
    t = np.asarray(times_us, float)
    out = np.zeros(p.shape[0], complex)
    for i in range(e.shape[0]):
        re = np.interp(tau[i], t, echoes[i].real)
        im = np.interp(tau[i], t, echoes[i].imag)
        out += w[i] * (re + 1j * im) * np.exp(2j * np.pi * array.frequency_mhz * tau[i])
    return out


# -- the volume's image ---------------------------------------------------------------------------------------

def lateral_kernel(array: MatrixArray, step_az: float, step_el: float, half_width: int) -> np.ndarray:
    """Complex DAS kernel over angle offsets ``(2h+1, 2h+1)`` samples
    ``[elevation, azimuth]`` (steps in radians), compounded over the
    transmits, unit energy."""
    k = 2 * np.pi / array.wavelength_mm
    x = (np.arange(array.elements_per_side) - (array.elements_per_side - 1) / 2) * array.pitch_mm
    w = array.weights_1d()
    offsets = np.arange(-half_width, half_width + 1)

    def factor(step):
        sine = np.sin(offsets * step)
        return (w[None, :] * np.exp(1j * k * np.outer(sine, x))).sum(1), sine

    d_az, s_az = factor(step_az)
    d_el, s_el = factor(step_el)
    a = array.virtual_source_mm
    kernel = np.zeros((offsets.size, offsets.size), complex)
    for tx, ty in array.tilts():
        kernel += np.outer(d_el * np.exp(1j * k * a * ty * s_el), d_az * np.exp(1j * k * a * tx * s_az))
    if not array.side_lobes:
        c = half_width
        sig = [fwhm(profile, 1.0) / (2 * np.sqrt(2 * np.log(2))) for profile in (kernel[:, c], kernel[c, :])]
        kernel = np.outer(*(np.exp(-offsets**2 / (2 * s**2)) for s in sig)).astype(complex)
    return kernel / np.sqrt((np.abs(kernel) ** 2).sum())


def array_envelope(echogenicity, geometry: BeamGeometry, formation: ImageFormation, rng, array: MatrixArray,
                   *, kernel_half_width: int | None = None) -> np.ndarray:
    """Envelope of the scene in beam space as ``array`` forms it (module
    docstring), with the formation's attenuation, noise, TGC and gain."""
    e = np.asarray(echogenicity, np.float32)
    nr, ne, na = geometry.shape
    da, de = geometry.azimuth_angular_separation, geometry.elevation_angular_separation
    # the kernel reaches the array factor's far side lobes: four main-lobe widths
    h = kernel_half_width or int(np.ceil(4 * array.wavelength_mm / array.aperture_mm / min(da, de)))
    kernel = lateral_kernel(array, da, de, h)
    az = (np.arange(na) - (na - 1) / 2) * da
    el = (np.arange(ne) - (ne - 1) / 2) * de
    gain = np.outer(array.directivity(np.sin(el)), array.directivity(np.sin(az))) ** 2
    field = ((rng.standard_normal(e.shape, dtype=np.float32) + 1j * rng.standard_normal(e.shape, dtype=np.float32))
             / np.sqrt(2)).astype(np.complex64) * np.sqrt(e)
    field *= gain.astype(np.float32)[None]
    shape = (ne + 2 * h, na + 2 * h)
    khat = np.fft.fft2(np.pad(kernel, ((0, shape[0] - kernel.shape[0]), (0, shape[1] - kernel.shape[1]))))
    out = np.empty_like(field)
    for i in range(nr):  # slice by slice: memory
        f = np.fft.ifft2(np.fft.fft2(field[i], s=shape) * khat)
        out[i] = f[h:h + ne, h:h + na]
    from scipy import ndimage
    sigma = array.axial_fwhm_mm / (2 * np.sqrt(2 * np.log(2))) / geometry.radius_sample_size
    half = max(1, int(np.ceil(4 * sigma)))
    ax = np.exp(-np.arange(-half, half + 1) ** 2 / (2 * sigma**2))
    ax /= np.sqrt((ax**2).sum())
    out = (ndimage.correlate1d(out.real, ax, axis=0, mode="constant")
           + 1j * ndimage.correlate1d(out.imag, ax, axis=0, mode="constant")).astype(np.complex64)
    radius = geometry.first_sample_distance + np.arange(nr) * geometry.radius_sample_size
    cm = (radius / 10.0)[:, None, None]
    out *= (10 ** (-formation.attenuation_db_per_cm * cm / 20)).astype(np.float32)
    noise = ((rng.standard_normal(e.shape, dtype=np.float32) + 1j * rng.standard_normal(e.shape, dtype=np.float32))
             / np.sqrt(2))
    out += np.float32(10 ** (formation.noise_db / 20)) * noise
    out *= (10 ** ((formation.tgc_db_per_cm * cm + formation.gain_db) / 20)).astype(np.float32)
    return np.abs(out).astype(np.float32)


def angular_echogenicity(echogenicity, geometry: BeamGeometry, anisotropy_db: float, *, blood_db: float,
                         scale_mm: float = 2.0) -> np.ndarray:
    """Echogenicity of the non-blood samples (over ``blood_db + 3`` dB)
    lowered by ``anisotropy_db (1 - cos^2)``, ``cos`` the angle between the
    beam and the gradient of the log echogenicity smoothed over
    ``scale_mm`` (a wall's orientation across its thickness); uniform
    regions (gradient under 0.05 neper/mm) keep theirs."""
    from scipy import ndimage
    e = np.asarray(echogenicity, np.float32)
    nr = geometry.shape[0]
    dr = geometry.radius_sample_size
    radius = geometry.first_sample_distance + np.arange(nr) * dr
    mid = radius[nr // 2]
    le = ndimage.gaussian_filter(np.log(np.maximum(e, 1e-12)), (scale_mm / dr,
                                 scale_mm / (mid * geometry.elevation_angular_separation),
                                 scale_mm / (mid * geometry.azimuth_angular_separation)))
    r = np.maximum(radius, dr)[:, None, None]
    gr = np.gradient(le, dr, axis=0)
    ge = np.gradient(le, axis=1) / (r * geometry.elevation_angular_separation)
    ga = np.gradient(le, axis=2) / (r * geometry.azimuth_angular_separation)
    eps = 0.05**2
    cos2 = (gr**2 + eps) / (gr**2 + ge**2 + ga**2 + eps)
    tissue = e > 10 ** ((blood_db + 3) / 10)
    return np.where(tissue, e * 10 ** (-anisotropy_db * (1 - cos2) / 10), e).astype(np.float32)


def array_former(array: MatrixArray):
    """A ``former`` for ``make_phantom(_former=...)``: the beam-space image."""
    def former(echogenicity, geometry, formation, rng):
        if array.anisotropy_db:
            echogenicity = angular_echogenicity(echogenicity, geometry, array.anisotropy_db,
                                                blood_db=formation.blood_db, scale_mm=array.anisotropy_scale_mm)
        return BeamVolume(log_compress(array_envelope(echogenicity, geometry, formation, rng, array), formation),
                          geometry)
    return former


# -- checks and the sweep ---------------------------------------------------------------------------------------

def fwhm(profile, step) -> float:
    """Full width at half maximum of a sampled amplitude profile (linear interpolation)."""
    p = np.abs(profile) / np.abs(profile).max()
    i = int(np.argmax(p))
    left = i - np.argmax(p[i::-1] < 0.5)
    right = i + np.argmax(p[i:] < 0.5)
    xl = left + (0.5 - p[left]) / (p[left + 1] - p[left])
    xr = right - 1 + (p[right - 1] - 0.5) / (p[right - 1] - p[right])
    return float((xr - xl) * step)


def point_target_check(array: MatrixArray, depth_mm: float = 60.0) -> dict:
    """One scatterer on the axis at ``depth_mm``: the lateral DAS profile
    (exact model, all transmits compounded) against ``lateral_kernel``."""
    fs = 4 * array.frequency_mhz * 4
    t = np.arange(0, 2.2 * depth_mm / SOUND_SPEED_MM_PER_US + 10, 1 / fs)
    step = np.radians(0.25)
    angles = np.arange(-60, 61) * step
    points = depth_mm * np.column_stack([np.sin(angles), np.zeros_like(angles), np.cos(angles)])
    image = np.zeros(angles.size, complex)
    for n in range(array.transmits):
        image += delay_and_sum(array, point_echoes(array, [[0, 0, depth_mm]], [1.0], t, n), t, points, n)
    kernel = lateral_kernel(array, step, step, 60)[60]
    das = np.abs(image) / np.abs(image).max()
    fast = np.abs(kernel) / np.abs(kernel).max()
    return dict(depth_mm=depth_mm, das_fwhm_deg=np.degrees(fwhm(das, step)), kernel_fwhm_deg=np.degrees(fwhm(fast, step)),
                das_fwhm_mm=fwhm(das, step) * depth_mm, max_profile_difference=float(np.abs(das - fast).max()))


def pymust_arrival_check(array: MatrixArray, scatterer=(5.0, 3.0, 40.0)) -> dict:
    """``pymust.simus3``'s echo of one scatterer for diverging wave 0 (our
    delays): its envelope's peak on every element against the geometric
    arrival time of ``point_echoes``."""
    import pymust
    from pymust import utils
    from scipy.signal import hilbert
    param = utils.Param()
    param.fc = array.frequency_mhz * 1e6
    param.bandwidth = array.bandwidth * 100
    param.width = param.height = array.pitch_mm * 1e-3 * 0.95
    param.elements = array.positions()[:, :2].T * 1e-3
    param.c = SOUND_SPEED_MM_PER_US * 1e3
    param.fs = 16 * param.fc
    options = utils.Options()
    options.ParPool = False
    delays = transmit_delays(array, 0)[None, :] * 1e-6
    s = np.asarray(scatterer, float)
    rf, _ = pymust.simus3(np.array([s[0]]) * 1e-3, np.array([s[1]]) * 1e-3, np.array([s[2]]) * 1e-3, np.array([1.0]),
                          delays, param, options)
    peak_us = np.argmax(np.abs(hilbert(rf, axis=0)), axis=0) / param.fs * 1e6
    geometric = transmit_times(array, s, 0) + np.linalg.norm(array.positions() - s, axis=1) / SOUND_SPEED_MM_PER_US
    error = peak_us - geometric
    return dict(median_error_us=float(np.median(error)), max_abs_error_us=float(np.abs(error).max()),
                sample_us=1e6 / param.fs, pulse_sigma_us=array.pulse_sigma_us)


def segment_case(array: MatrixArray | None, *, seed: int, spacing: float, papillary: bool, formation_changes=None,
                 options=None):
    """ED and ES phantoms (``make_sequence(n_frames=2)``) imaged by ``array``
    (``None``: the phantom's convolution formation, the same changes),
    each segmented with defaults from the true apex and base."""
    import spheroseg
    from spheroseg.synthetic.phantom import make_sequence
    if array is None or array.elements_per_side == 0:
        formation, former = replace(ImageFormation(), **(formation_changes or {})), None
        if array is not None and array.anisotropy_db:  # the convolution's image of the angular echogenicity
            from spheroseg.synthetic.echo import form_image

            def former(echogenicity, geometry, formation, rng):
                e = angular_echogenicity(echogenicity, geometry, array.anisotropy_db, blood_db=formation.blood_db,
                                         scale_mm=array.anisotropy_scale_mm)
                return form_image(e, geometry, formation, rng)
    else:
        formation, former = array.formation(**(formation_changes or {})), array_former(array)
    seq = make_sequence(n_frames=2, seed=seed, formation=formation, spacing=spacing, papillary=papillary,
                        _former=former, workers=1)
    rows = []
    for phase, ph in zip(("ED", "ES"), seq.frames):
        t0 = time.perf_counter()
        res = spheroseg.segment(ph.volume, apex=ph.apex, base=ph.base, **(options or {}))
        mask = res.mask(ph.volume) if hasattr(res, "mask") else None
        dice = None
        if mask is not None:
            dice = 2 * (mask & ph.truth_mask).sum() / (mask.sum() + ph.truth_mask.sum())
        rows.append(dict(phase=phase, truth_ml=ph.truth_volume_ml, ml=res.volume_ml,
                         error_pct=100 * (res.volume_ml / ph.truth_volume_ml - 1), dice=dice,
                         log_compression=res.log_compression, flags=(res.quality or {}).get("warnings"),
                         seconds=time.perf_counter() - t0, result=res, phantom=ph))
    return rows


def diagnose(row, formation: ImageFormation) -> dict:
    """Where the segmented wall sits and what the image's levels are:
    the signed distance (mm, + outside) of the segmented surface from the
    true one at the mask's boundary voxels (median; walls facing the beam,
    normal within 45 degrees of it, and walls along it); the grey levels
    (median) of the cavity's core (over 5 mm inside the truth), of the
    shell 2-5 mm outside it (the myocardium) and their difference in dB
    (``dynamic_range / 254`` dB a grey level)."""
    from scipy import ndimage
    ph, res = row["phantom"], row["result"]
    spacing = ph.volume.spacing[0]
    truth = ph.truth_mask
    grey = ph.volume.array.astype(float)
    inside = ndimage.distance_transform_edt(truth) * spacing
    outside = ndimage.distance_transform_edt(~truth) * spacing
    # the true wall half a voxel from the centres either side of it
    signed = np.where(truth, -inside + spacing / 2, outside - spacing / 2)
    points, _ = res.mesh(closed=False)
    index = (points - np.asarray(ph.volume.grid.origin)) / spacing  # identity direction: (x, y, z) voxel index
    d = ndimage.map_coordinates(signed, index[:, ::-1].T, order=1, mode="nearest")
    # the beam from the probe (top centre of the grid) against the truth's normal there
    smooth = ndimage.gaussian_filter(truth.astype(float), 1.5)
    normal = np.column_stack([ndimage.map_coordinates(g, index[:, ::-1].T, order=1, mode="nearest")
                              for g in np.gradient(smooth)[::-1]])
    probe = np.array([(truth.shape[2] - 1) / 2, (truth.shape[1] - 1) / 2, 0.0])
    beam = index - probe
    cos = np.abs((beam * normal).sum(1)) / (np.linalg.norm(beam, axis=1) * np.linalg.norm(normal, axis=1) + 1e-12)
    below = (points - ph.base) @ (ph.apex - ph.base) / np.linalg.norm(ph.apex - ph.base) > 3.0  # off the base plane
    d, cos = d[below], cos[below]
    core = truth & (inside > 5)
    shell = (outside > 2) & (outside < 5) & (grey > 0)
    step = formation.dynamic_range_db / 254
    return dict(offset_mm=float(np.median(d)), offset_facing_mm=float(np.median(d[cos > 0.707])),
                offset_along_mm=float(np.median(d[cos <= 0.707])), core_grey=float(np.median(grey[core])),
                wall_grey=float(np.median(grey[shell])),
                contrast_db=float((np.median(grey[shell]) - np.median(grey[core])) * step),
                true_log_compression=254 * 10 / np.log(10) / formation.dynamic_range_db)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--check", action="store_true", help="point-target checks only")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--spacing", type=float, default=1.0)
    parser.add_argument("--papillary", action="store_true")
    parser.add_argument("--elements", type=int, default=32)
    parser.add_argument("--frequency", type=float, default=2.5)
    parser.add_argument("--transmits", type=int, default=5)
    parser.add_argument("--dynamic-range", type=float, default=55.0)
    parser.add_argument("--blood-db", type=float, default=None, help="blood level (dB), the myocardium kept")
    parser.add_argument("--apodization", default="none")
    parser.add_argument("--convolution", action="store_true", help="the phantom's own formation (baseline)")
    parser.add_argument("--anisotropy", type=float, default=0.0, help="the myocardium's anisotropy (dB)")
    parser.add_argument("--anisotropy-scale", type=float, default=2.0, help="mm over which the wall's angle is read")
    parser.add_argument("--no-profile-blur", action="store_true",
                        help="diagnosis: the intensity interface never reads a wider blur from the outer band's profile")
    parser.add_argument("--name", help="store the rows under this name in docs/pulse_echo.json")
    parser.add_argument("--no-side-lobes", action="store_true", help="a Gaussian kernel of the DAS main lobe")
    args = parser.parse_args(argv)
    array = MatrixArray(elements_per_side=args.elements, frequency_mhz=args.frequency, transmits=args.transmits,
                        apodization=args.apodization, side_lobes=not args.no_side_lobes,
                        anisotropy_db=args.anisotropy, anisotropy_scale_mm=args.anisotropy_scale)
    if args.check:
        print("point target (DAS vs kernel):", point_target_check(array))
        try:
            print("pymust arrival:", pymust_arrival_check(replace(array, elements_per_side=16)))
        except ImportError:
            print("pymust not installed (pip install spheroseg[bench])")
        return
    if args.no_profile_blur:  # the blur the speckle's correlation gives, never more (spheroseg.descent.speckle)
        from spheroseg.descent import dataterms
        dataterms.profile_blur_mm = lambda profile, *, sigma_mm, **options: sigma_mm
    changes = dict(dynamic_range_db=args.dynamic_range)
    if args.blood_db is not None:
        default = ImageFormation()
        changes.update(blood_db=args.blood_db, contrast_db=default.blood_db + default.contrast_db - args.blood_db)
    print(f"array {array}  formation changes {changes}")
    formation = (replace(ImageFormation(), **changes) if args.convolution else array.formation(**changes))
    stored, start = [], time.perf_counter()
    for seed in args.seeds:
        for row in segment_case(replace(array, elements_per_side=0) if args.convolution else array, seed=seed, spacing=args.spacing,
                                papillary=args.papillary, formation_changes=changes):
            diagnosis = diagnose(row, formation)
            stored.append(dict(seed=seed, **{k: row[k] for k in ("phase", "truth_ml", "ml", "error_pct", "dice",
                                                               "log_compression", "flags")}, **diagnosis,
                               quality={k: v for k, v in row["result"].quality.items()
                                        if isinstance(v, (int, float)) and not isinstance(v, bool)}))
            print(f"seed {seed} {row['phase']}: truth {row['truth_ml']:.1f} mL  seg {row['ml']:.1f} mL  "
                  f"error {row['error_pct']:+.1f} %  dice {row['dice'] if row['dice'] is None else round(row['dice'], 3)}  "
                  f"log_compression {row['log_compression']:.2f}  warnings {row['flags']}", flush=True)
            print("    " + "  ".join(f"{k} {v:.2f}" for k, v in diagnosis.items()), flush=True)
    if args.name:
        here = Path(__file__).resolve().parent
        sys.path.insert(0, str(here))
        from common import DOCS, machine, write_json
        from report import write_markdown
        import fcntl
        path = DOCS / "pulse_echo.json"
        lock = open(Path(tempfile.gettempdir()) / "spheroseg-pulse_echo.lock", "w")  # runs side by side: one file
        fcntl.flock(lock, fcntl.LOCK_EX)
        data = json.loads(path.read_text()) if path.exists() else {"runs": {}}
        data["machine"] = machine()
        data["runs"][args.name] = dict(
            command="nice -n 19 python benchmarks/pulse_echo.py " + " ".join(argv if argv is not None else sys.argv[1:]),
            array=None if args.convolution else vars(array) if hasattr(array, "__dict__") else None,
            formation={k: getattr(formation, k) for k in ("dynamic_range_db", "blood_db", "contrast_db",
                                                          "axial_psf_mm", "lateral_psf_mm")},
            spacing=args.spacing, papillary=args.papillary, wall_seconds=time.perf_counter() - start, rows=stored)
        write_json("pulse_echo.json", data)
        print("wrote", write_markdown())
        fcntl.flock(lock, fcntl.LOCK_UN)


if __name__ == "__main__":
    main()
