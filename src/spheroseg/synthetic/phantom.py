"""Synthetic apical 3D echocardiography with exact ground truth.

The left-ventricular cavity is star-shaped about the centre of the mitral
plane (the base point) and closed by that plane.  In the ventricle's frame
(``x1`` from the base towards the apex), a point at distance ``r`` from the
base point and at spherical angles ``(theta, phi)`` (``phi = 0`` at the
apex) is in the cavity when ``x1 >= 0`` and

    r <= R(theta, phi) = E(phi) (1 - n(phi)) (1 + s(theta, phi)) - bumps

with ``E`` the half-ellipsoid of semi-axes ``(length, radius, radius)``,
``n`` a narrowing towards the mitral annulus, ``s`` a smooth asymmetry and
two papillary-muscle bumps.  None of it is a prolate spheroidal Hermite
surface, so a segmentation cannot be exact by construction.

Around it: myocardium, an atrium beyond the mitral plane and a right
ventricle (both dark blood, as the cavity), background tissue, fully
developed speckle (Rayleigh amplitude of a smoothed complex Gaussian field),
attenuation with depth, log compression to 8 bits and the black outside of a
conical sector (value 0, the volume's ``no_data_value``).  Options add
dropout (a wall region as dark as blood) and near-field clutter (haze in the
cavity near the probe).  The probe is at depth 0 (array index ``z = 0``).

The true volume is the integral ``int int R^3 / 3 sin(phi) dtheta dphi``
(Gauss-Legendre, exact to ~1e-9); the true mask tests voxel centres.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import ndimage

from .._compiled._runtime import usable_cores
from ..volumes.beamspace import BeamGeometry, BeamVolume, scan_convert
from .echo import ImageFormation, PostProcessing, form_image, postprocess, sector_geometry
from ..volumes.volume import ImageGrid, Volume

__all__ = ["Phantom", "PhantomSequence", "make_phantom", "make_sequence", "FAMILIES", "FORMATIONS", "POSTPROCESSINGS",
           "sweep_cases", "probe_sector", "MitralScene", "tilted_mitral_scene", "LateRegion", "myocardium_truth"]

#: the phantom families of the benchmarks, as keyword arguments of make_phantom
FAMILIES = {
    "clean": dict(speckle=False),
    "speckle": dict(),
    "dropout": dict(dropout=True),
    "clutter": dict(clutter=True),
    "low_contrast": dict(contrast=0.35),
    "tilted": dict(tilt_deg=25.0),
}

_DEFAULT = ImageFormation()
#: named image formations of the accuracy sweep: the default apical scan and
#: one setting changed at a time, to either side of it
FORMATIONS = {
    "default": _DEFAULT,
    "psf_narrow": replace(_DEFAULT, axial_psf_mm=0.5, lateral_psf_mm=2.0, elevation_psf_mm=2.2),
    "psf_wide": replace(_DEFAULT, axial_psf_mm=1.2, lateral_psf_mm=4.5, elevation_psf_mm=5.0),
    "dr_40": replace(_DEFAULT, dynamic_range_db=40.0),
    "dr_70": replace(_DEFAULT, dynamic_range_db=70.0),
    "gain_-6": replace(_DEFAULT, gain_db=-6.0),
    "gain_+6": replace(_DEFAULT, gain_db=6.0),
    "tgc_under": replace(_DEFAULT, tgc_db_per_cm=0.8),
    "tgc_over": replace(_DEFAULT, tgc_db_per_cm=2.6),
    # blood brighter or darker, the myocardium where it was
    "blood_low": replace(_DEFAULT, blood_db=_DEFAULT.blood_db - 8, contrast_db=_DEFAULT.contrast_db + 8),
    "blood_high": replace(_DEFAULT, blood_db=_DEFAULT.blood_db + 8, contrast_db=_DEFAULT.contrast_db - 8),
    # the myocardium brighter or darker, the blood where it was
    "contrast_high": replace(_DEFAULT, contrast_db=_DEFAULT.contrast_db + 7),
    "contrast_low": replace(_DEFAULT, contrast_db=_DEFAULT.contrast_db - 10),
    "clutter_none": replace(_DEFAULT, clutter_db=None),
    # haze nearly as bright as tissue over the apical third of the cavity (a poor window)
    "clutter_strong": replace(_DEFAULT, clutter_db=-3.0, clutter_depth_mm=40.0),
    "dropout": replace(_DEFAULT, dropout_db=30.0),
}

#: a scanner's post-processing of the default formation's export, as options
#: of make_phantom: smoothing, speckle reduction, persistence, and a finer or
#: coarser Cartesian grid (lateral resolution after scan conversion)
POSTPROCESSINGS = {
    "raw": {},
    "gaussian_1mm": dict(postprocessing=PostProcessing(gaussian_mm=1.0)),
    "gaussian_2mm": dict(postprocessing=PostProcessing(gaussian_mm=2.0)),
    "median_1mm": dict(postprocessing=PostProcessing(median_mm=1.0)),
    "median_2mm": dict(postprocessing=PostProcessing(median_mm=2.0)),
    "diffusion": dict(postprocessing=PostProcessing(diffusion_iterations=10)),
    "persistence_3": dict(postprocessing=PostProcessing(persistence=3)),
    "grid_0.7mm": dict(spacing=0.7),
    "grid_1.5mm": dict(spacing=1.5),
}

#: the options of make_phantom that place the scene (a family made only of
#: these can be imaged by any formation)
_SCENE_OPTIONS = {"length", "radius", "wall", "tilt_deg"}

_LEGACY_IMAGE = dict(speckle=True, dropout=False, clutter=False, contrast=1.0, dynamic_range_db=45.0)


@dataclass
class Phantom:
    """A synthetic volume and its truth."""

    volume: Volume
    truth_mask: np.ndarray
    truth_volume_ml: float
    apex: np.ndarray
    base: np.ndarray
    truth_mesh: tuple[np.ndarray, np.ndarray]
    params: dict = field(default_factory=dict)
    #: the beam-space image before scan conversion (``make_phantom(beam_space=True)``)
    beam_volume: BeamVolume | None = None
    #: ``make_phantom(epicardium=True)``: the wall below the mitral plane, its volume and mass (1.05 g/mL)
    truth_myocardium_mask: np.ndarray | None = None
    truth_myocardial_volume_ml: float | None = None
    truth_lv_mass_g: float | None = None


@dataclass
class PhantomSequence:
    """A synthetic 3D+t cycle starting at end-diastole."""

    frames: list[Phantom]

    @property
    def volumes(self) -> list[Volume]:
        return [f.volume for f in self.frames]

    @property
    def truth_volumes_ml(self) -> np.ndarray:
        return np.array([f.truth_volume_ml for f in self.frames])

    @property
    def truth_ef(self) -> float:
        v = self.truth_volumes_ml
        return float((v.max() - v.min()) / v.max() * 100.0)


class _Shape:
    """The cavity radius function R(theta, phi) in the ventricle's frame."""

    def __init__(self, length, radius, rng):
        self.length, self.radius = float(length), float(radius)
        self.asym = rng.uniform(0.03, 0.07), rng.uniform(0, 2 * np.pi)
        self.asym2 = rng.uniform(0.02, 0.05), rng.uniform(0, 2 * np.pi)
        self.narrowing = rng.uniform(0.08, 0.16)
        self.bumps = [(rng.uniform(0, 2 * np.pi), rng.uniform(0.9, 1.2), rng.uniform(2.0, 4.0)) for _ in range(2)]

    def __call__(self, theta, phi):
        a, b = self.length, self.radius
        r = a * b / np.sqrt((b * np.cos(phi)) ** 2 + (a * np.sin(phi)) ** 2)
        r = r * (1 - self.narrowing * np.exp(-(((np.pi / 2 - phi) / 0.3) ** 2)))
        (e1, t1), (e2, t2) = self.asym, self.asym2
        r = r * (1 + e1 * np.cos(theta - t1) * np.sin(phi) + e2 * np.cos(2 * theta - t2) * np.sin(phi) ** 2)
        for tb, pb, depth in self.bumps:
            dth = np.angle(np.exp(1j * (theta - tb)))
            r = r - depth * np.exp(-((dth / 0.3) ** 2) - ((phi - pb) / 0.2) ** 2)
        return r

    def volume_ml(self) -> float:
        x, w = np.polynomial.legendre.leggauss(200)
        phi = (x + 1) * np.pi / 4
        theta = np.linspace(0, 2 * np.pi, 400, endpoint=False)
        pp, tt = np.meshgrid(phi, theta, indexing="ij")
        integrand = self(tt, pp) ** 3 / 3 * np.sin(pp)
        return float((w * np.pi / 4) @ integrand.mean(1) * 2 * np.pi) / 1000.0

    def mesh(self, frame, base, n_theta=128, n_phi=64):
        """Wall of the cavity (open at the base plane), world mm."""
        phi = np.linspace(0, np.pi / 2, n_phi + 1)[1:]
        theta = np.arange(n_theta) * 2 * np.pi / n_theta
        pp, tt = np.meshgrid(phi, theta, indexing="ij")
        r = self(tt, pp)
        local = np.stack([r * np.cos(pp), r * np.sin(pp) * np.cos(tt), r * np.sin(pp) * np.sin(tt)], -1).reshape(-1, 3)
        apex = np.array([[self(0.0, 0.0), 0, 0]])
        points = np.concatenate([apex, local]) @ frame.T + base
        faces = [np.stack([np.zeros(n_theta, int), 1 + np.arange(n_theta), 1 + (np.arange(n_theta) + 1) % n_theta], 1)]
        for i in range(n_phi - 1):
            a, b = 1 + i * n_theta, 1 + (i + 1) * n_theta
            j, jn = np.arange(n_theta), (np.arange(n_theta) + 1) % n_theta
            faces += [np.stack([a + j, b + j, b + jn], 1), np.stack([a + j, b + jn, a + jn], 1)]
        return points, np.concatenate(faces)


def _frame(axis):
    e1 = axis / np.linalg.norm(axis)
    helper = np.array([1.0, 0, 0]) if abs(e1[0]) < 0.9 else np.array([0, 1.0, 0])
    e2 = helper - (helper @ e1) * e1
    e2 /= np.linalg.norm(e2)
    return np.column_stack([e1, e2, np.cross(e1, e2)])


def _anatomy(world, *, base, frame, shape_fn, wall, length, radius, azimuth, papillary=False,
             trabecular_mm=0.0) -> dict:
    """Tissue classes at world points ``world`` (float32, ``(..., 3)``), and
    the points in the ventricle's frame (``local``).  ``inner_tissue``:
    papillary muscles and trabeculae, tissue standing in the cavity (which
    they are part of: the truth follows the compact wall)."""
    local = (world - base.astype(np.float32)) @ frame.astype(np.float32)
    r = np.linalg.norm(local, axis=-1)
    rho = np.hypot(local[..., 1], local[..., 2])
    phi = np.arctan2(rho, local[..., 0])
    theta = np.arctan2(local[..., 2], local[..., 1])
    big_r = shape_fn(theta, np.minimum(phi, np.pi / 2))
    cavity = (local[..., 0] >= 0) & (r <= big_r)
    outer = big_r + wall * (0.8 + 0.2 * np.sin(np.minimum(phi, np.pi / 2)))
    # the wall ends in an annulus 1.5 mm beyond the mitral plane; the orifice stays open
    annulus = (local[..., 0] < 0) & (local[..., 0] >= -1.5) & (rho >= shape_fn(theta, np.pi / 2)) & (rho <= outer)
    myocardium = ((local[..., 0] >= 0) & (r <= outer) & ~cavity) | annulus
    # atrium beyond the mitral plane, opening into the cavity
    # (it meets the mitral plane in an orifice of about 0.7 of the base radius)
    atrium_c = local - np.array([-18.0, 0, 0])
    atrium_q = (atrium_c[..., 0] / 25.0) ** 2 + (rho / radius) ** 2
    atrium = (atrium_q <= 1) & (local[..., 0] < 0)
    atrium_wall = (atrium_q <= 1.35) & (local[..., 0] < 0) & ~atrium
    # right ventricle beside the septum
    rv_dir = np.array([0, np.cos(azimuth + 2.0), np.sin(azimuth + 2.0)])
    rv_c = local - np.array([0.45 * length, 0, 0]) - rv_dir * (radius * 1.1 + wall + 10)
    rv = ((rv_c[..., 0] / (0.45 * length)) ** 2 + (rv_c[..., 1:] @ rv_dir[1:] / 9.0) ** 2 + ((rv_c[..., 1:] @ np.array([-rv_dir[2], rv_dir[1]])) / 22.0) ** 2) <= 1
    rv &= ~myocardium & ~cavity
    inner = np.zeros(cavity.shape, bool)
    if papillary:
        inner |= _papillary_muscles(local, shape_fn, length=length, azimuth=azimuth)
    if trabecular_mm > 0:
        inner |= _trabeculae(r, big_r, theta, phi, depth_mm=trabecular_mm)
    return dict(local=local, cavity=cavity, myocardium=myocardium, atrium=atrium, atrium_wall=atrium_wall, rv=rv,
                inner_tissue=inner & cavity)


#: papillary muscles: (angle about the axis from the scene's azimuth, rad;
#: radius mm) of the anterolateral and posteromedial muscles
PAPILLARY_MUSCLES = ((0.9, 4.5), (-1.4, 5.0))


def _papillary_muscles(local, shape_fn, *, length, azimuth) -> np.ndarray:
    """Two muscles standing in the cavity: capsules from the wall at a third
    of the way from the apex to the base, their tips at two thirds, half
    way to the axis (where the chordae leave for the mitral leaflets)."""
    inside = np.zeros(local.shape[:-1], bool)
    for angle, radius in PAPILLARY_MUSCLES:
        theta = azimuth + angle
        ring = np.array([0.0, np.cos(theta), np.sin(theta)])
        x_root, x_tip = 0.67 * length, 0.3 * length
        phi = np.pi / 4
        for _ in range(30):  # the wall's point at height x_root: R(theta, phi) cos(phi) = x_root
            phi = np.arccos(min(1.0, x_root / shape_fn(theta, phi)))
        rho_root = shape_fn(theta, phi) * np.sin(phi) + 1.0  # into the wall by 1 mm: attached
        root = np.array([x_root, 0, 0]) + rho_root * ring
        tip = np.array([x_tip, 0, 0]) + 0.5 * shape_fn(theta, np.pi / 2) * ring
        along = tip - root
        t = np.clip(((local - root) @ along) / (along @ along), 0, 1)
        distance = np.linalg.norm(local - root - t[..., None] * along, axis=-1)
        inside |= distance <= radius
    return inside


def _trabeculae(r, big_r, theta, phi, *, depth_mm) -> np.ndarray:
    """A spongy rim ``depth_mm`` deep inside the compact wall: ridges along
    the long axis (about 40 % tissue), thinning towards the base."""
    rim = (r <= big_r) & (r >= big_r - depth_mm * np.sqrt(np.clip(np.cos(phi), 0, 1)))
    ridges = np.cos(18 * theta + 3 * np.sin(5 * phi)) > 0.25
    return rim & ridges


def _texture(shape, spacing, rng):
    """Unit-variance Gaussian random field smoothed over 3 mm on a grid."""
    texture = ndimage.gaussian_filter(rng.standard_normal(shape).astype(np.float32), 3.0 / spacing)
    return texture / (texture.std() + 1e-12)


def _formed_image(formation, *, grid, probe, seed, speckle_seed, half_angle_deg, scene, former=None):
    """The scene imaged by ``formation`` in beam space from a probe at world
    point ``probe`` (centre beam along +z), scan-converted to the Cartesian
    ``grid``: ``(grey levels, BeamVolume)``.  ``former``: called as
    :func:`~spheroseg.synthetic.echo.form_image` is (default), to image the
    same echogenicity another way (``benchmarks/pulse_echo.py``)."""
    # the probe is at the top centre of the grid: its far corner is the farthest point
    corner = grid.index_to_world(np.array(grid.shape[::-1]) - 1.0) - probe
    to_world = np.eye(4)
    to_world[:3, 3] = probe
    geometry = sector_geometry(formation, half_angle_deg=half_angle_deg, max_radius_mm=float(np.linalg.norm(corner)),
                               probe_to_world=to_world)
    index = np.stack(np.meshgrid(*(np.arange(n, dtype=float) for n in geometry.shape), indexing="ij"), -1)
    points = geometry.index_to_world(index)
    anatomy = _anatomy(points.astype(np.float32), **scene)
    # myocardial and tissue inhomogeneity: a smooth random field (1.5 mm grid) sampled at the beams
    step = 1.5
    box = corner + probe + 2 * step
    tex = _texture(tuple(int(np.ceil(b / step)) + 1 for b in box[::-1]), step, np.random.default_rng(seed + 1_000_003))
    texture = ndimage.map_coordinates(tex, np.moveaxis(points[..., ::-1] / step, -1, 0), order=1, mode="nearest")

    f = formation
    tissue = 10 ** (0.2 * texture)  # 2 dB spread
    myo = 10 ** ((f.blood_db + f.contrast_db + 1.5 * texture) / 10)
    echo = np.where(anatomy["myocardium"] | anatomy["atrium_wall"], myo, tissue)
    echo = np.where(anatomy["cavity"] | anatomy["atrium"] | anatomy["rv"], 10 ** (f.blood_db / 10), echo)
    echo = np.where(anatomy["inner_tissue"], myo, echo)
    if f.dropout_db > 0:
        # signal lost over a lateral wall region (as the legacy dropout)
        s = scene
        centre = (np.array([0.5 * s["length"], 0, 0]) + np.array([0, np.cos(s["azimuth"] - 1.0),
                  np.sin(s["azimuth"] - 1.0)]) * (s["radius"] + s["wall"] / 2))
        d = np.linalg.norm(anatomy["local"] - centre, axis=-1)
        echo = echo * 10 ** (-f.dropout_db / 10 * np.clip((f.dropout_radius_mm - d) / 6.0, 0, 1))
    if f.clutter_db is not None:
        depth = np.linalg.norm(points - probe, axis=-1)
        haze = np.exp(-(((depth - f.clutter_depth_mm) / 12.0) ** 2)) * 10 ** ((f.clutter_db + 3.0 * texture) / 10)
        echo = echo + haze
    beam = (former or form_image)(echo.astype(np.float32), geometry, f, np.random.default_rng(speckle_seed))
    image = np.round(scan_convert(beam, grid).array).astype(np.uint8)
    return image, beam


def _persistence(image, frames, formation, *, speckle_seed, **options):
    """Mean grey levels of ``image`` and ``frames - 1`` more images of the
    same scene with independent speckle (a scanner's persistence on a still
    scene)."""
    total = image.astype(np.float32)
    for j in range(1, frames):
        total += _formed_image(formation, speckle_seed=speckle_seed + 7919 * j, **options)[0]
    return np.where(image > 0, np.clip(np.round(total / frames), 1, 255), 0).astype(np.uint8)


def make_phantom(
    *,
    seed: int = 0,
    spacing: float = 1.0,
    length: float | None = None,
    radius: float | None = None,
    wall: float = 9.0,
    tilt_deg: float = 0.0,
    speckle: bool = True,
    dropout: bool = False,
    clutter: bool = False,
    contrast: float = 1.0,
    dynamic_range_db: float = 45.0,
    formation: ImageFormation | None = None,
    beam_space: bool = False,
    postprocessing: PostProcessing | None = None,
    papillary: bool = False,
    trabecular_mm: float = 0.0,
    _shape: _Shape | None = None,
    _speckle_seed: int | None = None,
    _base_descent: float = 0.0,
    epicardium: bool = False,
    _former=None,
) -> Phantom:
    """Synthetic apical 3D echo volume of a left ventricle.

    Parameters
    ----------
    seed : int
        Seeds the shape (size, asymmetry, papillary muscles, tilt azimuth)
        and the speckle.
    spacing : float
        Isotropic voxel size in mm.
    length, radius : float, optional
        Apex-to-base distance and base radius of the ellipsoid before
        perturbation (mm); drawn from the seed when omitted
        (75-95 mm and 0.28-0.36 of the length).
    wall : float
        Myocardial thickness (mm).
    tilt_deg : float
        Angle between the long axis and the beam axis (depth).
    speckle, dropout, clutter : bool
        Options of the legacy image (see the module's docstring).
    contrast : float
        Legacy image: myocardium-to-blood echogenicity contrast relative to
        the standard case (1); 0.35 is a poor acoustic window.
    dynamic_range_db : float
        Legacy image: log compression range.
    formation : ImageFormation, optional
        Form the image as a phased-array scanner does (:mod:`spheroseg.synthetic.echo`):
        beam-space speckle with a depth-dependent PSF, attenuation, noise,
        TGC, log compression, scan conversion to the same Cartesian grid.
        The truth is the same as without it.  The legacy image options must
        then keep their defaults (the formation holds its own).  ``None``:
        the legacy image (the pinned reference's: its arrays never change).
    beam_space : bool
        With a formation, also return the beam-space image before scan
        conversion (:attr:`Phantom.beam_volume`, a
        :class:`spheroseg.beamspace.BeamVolume`; probe at the top centre of
        the Cartesian volume, centre beam along +z, tan convention).
    postprocessing : PostProcessing, optional
        Smoothing of the exported grey levels, as a scanner applies it
        (:func:`spheroseg.synthetic.echo.postprocess`); its ``persistence`` averages the
        grey levels of that many images of the scene with independent speckle
        (a formation only).  The truth is unchanged.
    papillary : bool
        Two papillary muscles standing in the cavity, as bright as the
        myocardium and attached to its wall (:data:`PAPILLARY_MUSCLES`).
    trabecular_mm : float
        Depth (mm) of a trabecular rim inside the compact wall (0: none).
        Muscles and trabeculae are cavity (the CETUS and ASE convention):
        the truth follows the compact wall, unchanged by them.
    epicardium : bool
        Also give the myocardium's truth (:func:`myocardium_truth`): its
        mask below the mitral plane, its volume and its mass.
    """
    if spacing <= 0:
        raise ValueError(f"spacing must be positive, got {spacing!r}")
    if formation is not None:
        if not isinstance(formation, ImageFormation):
            raise TypeError(f"formation must be an ImageFormation, got {type(formation).__name__}")
        legacy = dict(speckle=speckle, dropout=dropout, clutter=clutter, contrast=contrast,
                      dynamic_range_db=dynamic_range_db)
        changed = [k for k, v in legacy.items() if v != _LEGACY_IMAGE[k]]
        if changed:
            raise ValueError(f"{', '.join(changed)} belong to the legacy image; with a formation set them in "
                             "ImageFormation (dropout_db, clutter_db, contrast_db, dynamic_range_db)")
    elif beam_space:
        raise ValueError("beam_space=True needs a formation: the legacy image is made on the Cartesian grid")
    if formation is None and postprocessing is not None and postprocessing.persistence > 1:
        raise ValueError("postprocessing.persistence > 1 needs a formation (it images the scene again)")
    rng = np.random.default_rng(seed)
    length = float(length if length is not None else rng.uniform(75, 95))
    radius = float(radius if radius is not None else length * rng.uniform(0.28, 0.36))
    shape_fn = _shape or _Shape(length, radius, rng)
    azimuth = rng.uniform(0, 2 * np.pi)

    # geometry: probe at the top centre, the apex 22 mm deep, the axis tilted
    tilt = np.radians(tilt_deg)
    axis_down = np.array([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)])
    extent_lat = 2 * (radius * 1.25 + 24) + 2 * length * np.sin(tilt) * 0.6  # the same for every frame
    depth = 22 + length * np.cos(tilt) + 50
    nx = ny = int(np.ceil(extent_lat / spacing)) | 1
    nz = int(np.ceil(depth / spacing))
    probe = np.array([(nx - 1) / 2 * spacing, (ny - 1) / 2 * spacing, 0.0])
    apex = probe + np.array([0, 0, 22.0]) - axis_down * 0.0
    apex = apex + np.array([-np.sin(tilt) * np.cos(azimuth), -np.sin(tilt) * np.sin(azimuth), 0]) * length * 0.3
    base = apex + axis_down * (length - _base_descent)
    frame = _frame(-axis_down)  # e1 from base to apex

    z, y, x = np.meshgrid(*(np.arange(n, dtype=np.float32) * np.float32(spacing) for n in (nz, ny, nx)), indexing="ij")
    world = np.stack([x, y, z], -1)
    if not (np.isfinite(trabecular_mm) and 0 <= trabecular_mm < wall):
        raise ValueError(f"trabecular_mm must be in [0, wall), got {trabecular_mm!r}")
    inner_options = dict(papillary=bool(papillary), trabecular_mm=float(trabecular_mm))
    anatomy = _anatomy(world, base=base, frame=frame, shape_fn=shape_fn, wall=wall, length=length, radius=radius,
                       azimuth=azimuth, **inner_options)
    local, cavity, myocardium = anatomy["local"], anatomy["cavity"], anatomy["myocardium"]
    atrium, atrium_wall, rv = anatomy["atrium"], anatomy["atrium_wall"], anatomy["rv"]

    beam = None
    if formation is None:
        tex_rng = np.random.default_rng(seed + 1_000_003)
        texture = ndimage.gaussian_filter(tex_rng.standard_normal((nz, ny, nx)).astype(np.float32), 3.0 / spacing)
        texture /= texture.std() + 1e-12
        blood, tissue = 0.025, 0.30 * (1 + 0.25 * texture)
        myo = 0.04 + 0.9 * contrast * (1 + 0.15 * texture)
        echo = np.where(myocardium | atrium_wall, myo, tissue)
        echo = np.where(cavity | atrium | rv, blood, echo)
        echo = np.where(anatomy["inner_tissue"], myo, echo)
        if dropout:
            # a lateral wall region as dark as the blood pool
            centre = np.array([0.5 * length, 0, 0]) + np.array([0, np.cos(azimuth - 1.0), np.sin(azimuth - 1.0)]) * (radius + wall / 2)
            d = np.linalg.norm(local - centre, axis=-1)
            echo = np.where(d < 16.0, blood + (echo - blood) * np.clip((d - 10.0) / 6.0, 0, 1), echo)
        depth_mm = np.linalg.norm(world - probe, axis=-1)
        if clutter:
            echo = echo + 0.12 * contrast * np.exp(-((depth_mm - 26.0) / 12.0) ** 2) * (1 + 0.5 * texture)
        echo = ndimage.gaussian_filter(echo.astype(np.float32), sigma=(0.5 / spacing, 0.8 / spacing, 0.8 / spacing))
        echo = echo * np.exp(-0.004 * depth_mm)  # attenuation left after time-gain compensation
        if speckle:
            s_rng = np.random.default_rng(seed if _speckle_seed is None else _speckle_seed)
            field_ = [
                ndimage.gaussian_filter(s_rng.standard_normal((nz, ny, nx)).astype(np.float32), sigma=(0.6 / spacing, 1.0 / spacing, 1.0 / spacing))
                for _ in range(2)
            ]
            amp = np.hypot(*field_)
            echo = echo * amp / np.sqrt(np.mean(amp**2))
        db = 20 * np.log10(np.maximum(echo, 1e-6) / 1.0)
        image = np.clip((db + dynamic_range_db) / dynamic_range_db, 0, 1) * 254 + 1
        # conical sector from the probe: outside is 0 (no data)
        v = world - probe
        angle = np.degrees(np.arctan2(np.hypot(v[..., 0], v[..., 1]), v[..., 2]))
        image = np.where(angle <= 38.0 + tilt_deg * 0.6, np.round(image), 0).astype(np.uint8)
    else:
        grid = ImageGrid((nz, ny, nx), (spacing,) * 3, (0.0, 0.0, 0.0), np.eye(3))
        image, beam = _formed_image(formation, grid=grid, probe=probe, seed=seed,
                                    speckle_seed=seed if _speckle_seed is None else _speckle_seed,
                                    half_angle_deg=38.0 + tilt_deg * 0.6, former=_former,
                                    scene=dict(base=base, frame=frame, shape_fn=shape_fn, wall=wall, length=length,
                                               radius=radius, azimuth=azimuth, **inner_options))
        if postprocessing is not None and postprocessing.persistence > 1:
            image = _persistence(image, postprocessing.persistence, formation, grid=grid, probe=probe, seed=seed,
                                 former=_former,
                                 speckle_seed=seed if _speckle_seed is None else _speckle_seed,
                                 half_angle_deg=38.0 + tilt_deg * 0.6,
                                 scene=dict(base=base, frame=frame, shape_fn=shape_fn, wall=wall, length=length,
                                            radius=radius, azimuth=azimuth, **inner_options))
    if postprocessing is not None:
        if not isinstance(postprocessing, PostProcessing):
            raise TypeError(f"postprocessing must be a PostProcessing, got {type(postprocessing).__name__}")
        image = postprocess(image, spacing, postprocessing)

    volume = Volume(image, spacing=(spacing,) * 3, no_data_value=0)
    return Phantom(
        volume=volume,
        truth_mask=cavity,
        truth_volume_ml=shape_fn.volume_ml(),
        apex=base + frame[:, 0] * shape_fn(0.0, 0.0),
        base=base,
        truth_mesh=shape_fn.mesh(frame, base),
        params=dict(seed=seed, spacing=spacing, length=length, radius=radius, wall=wall, tilt_deg=tilt_deg,
                    speckle=speckle, dropout=dropout, clutter=clutter, contrast=contrast,
                    **({} if formation is None else dict(formation=formation)),
                    **({} if _base_descent == 0 else dict(base_descent=_base_descent)),
                    **({k: v for k, v in inner_options.items() if v})),
        beam_volume=beam if beam_space else None,
        **(myocardium_truth(shape_fn, wall, anatomy) if epicardium else {}),
    )


def _outer_radius(shape_fn, wall, theta, phi):
    """The epicardium's distance from the base point (as :func:`_anatomy`)."""
    return shape_fn(theta, phi) + wall * (0.8 + 0.2 * np.sin(phi))


def myocardium_truth(shape_fn, wall: float, anatomy: dict) -> dict:
    """The myocardium's truth: the mask of :func:`_anatomy`'s wall below
    the mitral plane (``x1 >= 0``), and its volume
    ``int int (R_epi^3 - R^3) / 3 sin(phi) dtheta dphi`` (Gauss-Legendre,
    as the cavity's) and mass at 1.05 g/mL."""
    x, w = np.polynomial.legendre.leggauss(200)
    phi = (x + 1) * np.pi / 4
    theta = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    pp, tt = np.meshgrid(phi, theta, indexing="ij")
    shell = (_outer_radius(shape_fn, wall, tt, pp) ** 3 - shape_fn(tt, pp) ** 3) / 3 * np.sin(pp)
    volume = float((w * np.pi / 4) @ shell.mean(1) * 2 * np.pi) / 1000.0
    mask = anatomy["myocardium"] & (anatomy["local"][..., 0] >= 0)
    return dict(truth_myocardium_mask=mask, truth_myocardial_volume_ml=volume, truth_lv_mass_g=1.05 * volume)


def make_sequence(*, n_frames: int = 10, seed: int = 0, shortening: float = 0.33, base_descent: float = 0.0,
                  formation: ImageFormation | None = None, workers: int | None = None,
                  late_region: "LateRegion | None" = None, progress=None, **kwargs) -> PhantomSequence:
    """A cardiac cycle from end-diastole.

    At phase ``s(t) = (1 - cos(2 pi t / n_frames)) / 2`` (0 at end-diastole,
    1 at end-systole, mid-cycle) the cavity radius shrinks by the fraction
    ``shortening * s``, the wall thickens by ``50 % * s`` and the mitral
    annulus (the base plane) moves towards the apex by ``base_descent * s``
    mm, the long axis shortening by as much (the apex stays put).  Speckle
    changes every frame.

    Parameters
    ----------
    n_frames : int
    seed : int
    shortening : float
        Fractional radial shortening at end-systole.
    base_descent : float
        Descent of the mitral annulus at end-systole, mm (8-15 mm in adult
        hearts; 0 keeps the base plane still, the legacy sequence's).  Each frame's
        :attr:`Phantom.base` is its true base point.
    formation : ImageFormation, optional
        Image formation of every frame (see :func:`make_phantom`).
    late_region : LateRegion, optional
        A region of the wall that moves late or little (regional motion:
        the truth of segmental volume curves and dyssynchrony).
    workers : int, optional
        Frames made at once, in threads (numpy's array loops release the
        GIL): by default the cores this process may run on.  The frames do
        not depend on it (each has its own seeds); memory grows with it.
    progress : callable, optional
        ``progress(done, total)`` after each frame is made (a progress bar).
    **kwargs
        Further options of :func:`make_phantom`.
    """
    if n_frames < 2:
        raise ValueError(f"n_frames must be >= 2, got {n_frames!r}")
    rng = np.random.default_rng(seed)
    length = kwargs.pop("length", None) or rng.uniform(75, 95)
    radius = kwargs.pop("radius", None) or length * rng.uniform(0.28, 0.36)
    wall = kwargs.pop("wall", 9.0)
    if not (np.isfinite(base_descent) and 0 <= base_descent < length / 3):
        raise ValueError(f"base_descent must be in [0, {length / 3:.1f}) mm (a third of the long axis), "
                         f"got {base_descent!r}")
    if workers is not None and not (isinstance(workers, (int, np.integer)) and workers >= 1):
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    ed_shape = _Shape(length, radius, np.random.default_rng(seed))

    def frame(t: int) -> Phantom:
        s = 0.5 * (1 - np.cos(2 * np.pi * t / n_frames))
        descent = base_descent * s
        shape = _Shape(length - descent, radius * (1 - shortening * s), np.random.default_rng(seed))
        shape.bumps = [(tb, pb, d * (1 + s)) for tb, pb, d in ed_shape.bumps]
        if late_region is not None:
            shape = late_region.shape(shape, t=t, n_frames=n_frames, shortening=shortening)
        return make_phantom(seed=seed, length=length, radius=radius, wall=wall * (1 + 0.5 * s), _shape=shape,
                            _speckle_seed=seed * 1000 + t, _base_descent=descent, formation=formation, **kwargs)

    with ThreadPoolExecutor(min(n_frames, workers or usable_cores())) as pool:  # the frames' speckle, on every core
        frames = []
        for made in pool.map(frame, range(n_frames)):  # in order, as each is made
            frames.append(made)
            if progress is not None:
                progress(len(frames), n_frames)
        return PhantomSequence(frames)


@dataclass(frozen=True)
class LateRegion:
    """A region of the wall whose motion is late or reduced.

    Around the angle ``theta`` (radians, about the phantom's long axis,
    from its second frame axis towards its third) within a window
    ``cos^2(pi/2 (theta - theta_0) / half_width)`` (zero beyond
    ``half_width``), the cavity's radius follows the phase ``s(t - delay)``
    (``delay`` a fraction of the cycle) and shortens by ``amplitude`` of
    the rest's shortening.

    Parameters
    ----------
    theta, half_width : float
        Centre and half-width of the region (radians).
    delay : float
        Delay of its motion, fraction of the cycle (0.1: 10 % late).
    amplitude : float
        Its shortening relative to the rest (1: the same; 0.5: hypokinetic).
    """

    theta: float = 0.0
    half_width: float = np.pi / 3
    delay: float = 0.1
    amplitude: float = 1.0

    def window(self, theta) -> np.ndarray:
        d = np.angle(np.exp(1j * (np.asarray(theta) - self.theta)))
        return np.where(np.abs(d) < self.half_width, np.cos(np.pi / 2 * d / self.half_width) ** 2, 0.0)

    def shape(self, shape: _Shape, *, t: int, n_frames: int, shortening: float) -> _Shape:
        """``shape`` (a frame's cavity at phase ``s(t)``) with the region's
        radius scaled to its own phase and amplitude."""
        def phase(u):
            return 0.5 * (1 - np.cos(2 * np.pi * u))

        now = 1 - shortening * phase(t / n_frames)
        late = 1 - self.amplitude * shortening * phase(t / n_frames - self.delay)
        return _RegionalShape(shape, self, late / now)


class _RegionalShape(_Shape):
    """A cavity shape whose radius is scaled by ``1 + w(theta) (ratio - 1)``."""

    def __init__(self, shape: _Shape, region: LateRegion, ratio: float):
        self.__dict__.update(shape.__dict__)
        self.region, self.ratio = region, float(ratio)

    def __call__(self, theta, phi):
        return super().__call__(theta, phi) * (1 + self.region.window(theta) * (self.ratio - 1))


def sweep_cases(*, families=("speckle", "tilted"), formations=None, seeds=(0,)) -> Iterator[tuple[str, str, dict]]:
    """The cross of scene families x image formations x seeds, for benchmarks.

    Yields ``(family, formation name, keyword arguments of make_phantom)``.
    Every formation sees the same scenes (seed ``s + 10 * k`` for the k-th
    family), so that settings compare on equal cases.  The default is
    2 families x 16 formations = 32 cases.

    Parameters
    ----------
    families : sequence of str
        Names in :data:`FAMILIES` that only place the scene (``speckle``, the
        upright ventricle, and ``tilted``); the others set the legacy image.
    formations : sequence of str, optional
        Names in :data:`FORMATIONS`; all of them by default.
    seeds : sequence of int
    """
    formations = list(FORMATIONS) if formations is None else list(formations)
    for name in families:
        if name not in FAMILIES or not set(FAMILIES[name]) <= _SCENE_OPTIONS:
            scene = [k for k, v in FAMILIES.items() if set(v) <= _SCENE_OPTIONS]
            raise ValueError(f"family {name!r} cannot be imaged by a formation; choose from {scene}")
    for name in formations:
        if name not in FORMATIONS:
            raise ValueError(f"unknown formation {name!r}; choose from {list(FORMATIONS)}")
    for (k, family), seed, name in itertools.product(enumerate(families), seeds, formations):
        yield family, name, dict(seed=seed + 10 * k, formation=FORMATIONS[name], **FAMILIES[family])


def probe_sector(volume: Volume, *, shape=(150, 57, 57), radius_spacing: float = 1.0, first_sample: float = 5.0,
                 angle_deg: float = 1.0, tilt_deg: float = 0.0, convention: str = "tan") -> BeamGeometry:
    """A beam-space sector over a phantom volume, from its probe (the top
    face's centre, depth along +z): ``shape`` (radius, elevation, azimuth)
    samples, ``radius_spacing`` and ``first_sample`` in mm, ``angle_deg``
    between beams, the probe turned ``tilt_deg`` about its y axis."""
    nz, ny, nx = volume.shape
    s = volume.spacing[0]
    t = np.radians(tilt_deg)
    pose = np.eye(4)
    pose[:3, :3] = [[np.cos(t), 0, np.sin(t)], [0, 1, 0], [-np.sin(t), 0, np.cos(t)]]
    pose[:3, 3] = [(nx - 1) / 2 * s, (ny - 1) / 2 * s, 0.0]
    angle = np.radians(angle_deg)
    return BeamGeometry(shape, radius_spacing, first_sample, angle, angle, convention=convention, probe_to_world=pose)


@dataclass(frozen=True)
class MitralScene:
    """:func:`tilted_mitral_scene`: the image, its truth and the points a user
    would click (world mm)."""

    volume: Volume
    truth_mask: np.ndarray
    truth_ml: float
    apex: np.ndarray
    base: np.ndarray
    annulus: np.ndarray


def tilted_mitral_scene(tilt_deg: float, *, seed: int = 0) -> MitralScene:
    """A cavity whose mitral plane is tilted from the apex-base line.

    An ellipsoid (axis z, semi-axes 80, 26, 26 mm) cut by a plane through
    its centre whose normal is tilted ``tilt_deg`` towards y, a dark atrium
    beyond, bright tissue around, Gaussian noise (seeded); 1 mm voxels.  The
    base is the centre, the annulus 8 points of the mitral ring (the ellipse
    where the plane cuts the ellipsoid); a plane through the centre halves
    the ellipsoid, so the true volume is ``2/3 pi a b c``.
    """
    length, radius = 80.0, 26.0
    n = np.array([0.0, np.sin(np.radians(tilt_deg)), np.cos(np.radians(tilt_deg))])
    base = np.array([50.0, 50.0, 40.0])
    k, j, i = np.meshgrid(np.arange(130.0), np.arange(100.0), np.arange(100.0), indexing="ij")
    x = np.stack([i, j, k], -1) - base
    above = x @ n
    cavity = ((x[..., 2] / length) ** 2 + (x[..., 0] ** 2 + x[..., 1] ** 2) / radius**2 <= 1) & (above >= 0)
    atrium = (above < 0) & (above > -35) & ((x**2).sum(-1) - above**2 <= (0.85 * radius) ** 2)
    image = np.where(cavity | atrium, 30.0, 120.0) + np.random.default_rng(seed).normal(0, 15, cavity.shape)
    t = np.arange(8) * np.pi / 4
    d = np.cos(t)[:, None] * [1.0, 0, 0] + np.sin(t)[:, None] * np.cross(n, [1.0, 0, 0])
    r = 1 / np.sqrt((d[:, 2] / length) ** 2 + (d[:, 0] ** 2 + d[:, 1] ** 2) / radius**2)
    return MitralScene(Volume(np.clip(image, 1, 255).astype(np.uint8)), cavity, 2 / 3 * np.pi * length * radius**2 / 1000,
                       base + [0, 0, length], base, base + r[:, None] * d)
