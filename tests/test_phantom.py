import hashlib

import numpy as np
import pytest

from spheroseg.synthetic.phantom import FAMILIES, make_phantom, make_sequence
from spheroseg.surfaces.surface import signed_volume


@pytest.fixture(scope="module")
def phantom():
    return make_phantom(seed=5)


def test_truth_volume_matches_mask(phantom):
    voxels = phantom.truth_mask.sum() * np.prod(phantom.volume.spacing) / 1000
    # voxelisation at 1 mm of a ~15000 mm^2 wall: well under 1 %
    assert abs(voxels - phantom.truth_volume_ml) < 0.01 * phantom.truth_volume_ml


def test_truth_mesh_encloses_truth_volume(phantom):
    points, faces = phantom.truth_mesh
    # with the origin on the base plane the missing flat cap adds nothing to
    # the divergence-theorem volume
    vol = abs(signed_volume(points - phantom.base, faces)) / 1000
    np.testing.assert_allclose(vol, phantom.truth_volume_ml, rtol=5e-3)


def test_apex_and_base_are_on_the_truth(phantom):
    assert phantom.volume.contains(phantom.apex) and phantom.volume.contains(phantom.base)
    d = np.linalg.norm(phantom.truth_mesh[0] - phantom.apex, axis=1).min()
    assert d < 1e-6


def test_image_looks_like_apical_echo(phantom):
    a = phantom.volume.array
    assert a.dtype == np.float32 and a.min() == 0 and a.max() <= 255
    assert (a == 0).mean() > 0.2, "the black outside of the sector"
    blood = np.median(a[phantom.truth_mask])
    assert blood < np.median(a[(a > 0) & ~phantom.truth_mask]), "blood is dark"


def test_deterministic():
    a = make_phantom(seed=9, spacing=2.0)
    b = make_phantom(seed=9, spacing=2.0)
    np.testing.assert_array_equal(a.volume.array, b.volume.array)
    c = make_phantom(seed=10, spacing=2.0)
    assert not np.array_equal(a.volume.array.shape, c.volume.array.shape) or not np.array_equal(a.volume.array, c.volume.array)


def test_sequence_volume_curve():
    seq = make_sequence(seed=2, n_frames=4, spacing=2.5)
    v = seq.truth_volumes_ml
    assert np.argmax(v) == 0 and np.argmin(v) == 2
    assert 45 < seq.truth_ef < 65


@pytest.mark.parametrize("formation", [None, "psf_wide"])
def test_sequence_frames_do_not_depend_on_the_workers(formation):
    from spheroseg.synthetic.phantom import FORMATIONS

    kwargs = dict(seed=4, n_frames=3, spacing=3.0, base_descent=6.0,
                  formation=None if formation is None else FORMATIONS[formation])
    one, three = make_sequence(workers=1, **kwargs), make_sequence(workers=3, **kwargs)
    for a, b in zip(one.frames, three.frames):
        np.testing.assert_array_equal(a.volume.array, b.volume.array)
        np.testing.assert_array_equal(a.truth_mask, b.truth_mask)
        assert a.truth_volume_ml == b.truth_volume_ml and np.array_equal(a.base, b.base)
    assert not np.array_equal(one.frames[0].volume.array, one.frames[1].volume.array)  # speckle changes
    with pytest.raises(ValueError, match="workers"):
        make_sequence(n_frames=2, spacing=3.0, workers=0)


def test_families_exist():
    assert {"clean", "speckle", "dropout", "clutter", "low_contrast", "tilted"} <= set(FAMILIES)


# The legacy image (no formation, no base descent) pinned: tests/data/descent_reference.npz
# was recorded on these arrays.  Digests computed on commit 5937444, before the
# image formations were added: sha256 of the grey levels (as uint8) and of the
# truth mask, the truth volume (mL) and the sum of |truth mesh coordinates| (mm).
LEGACY = {
    "default": ("d15e754af3f9a914", "9577648faf586f64", 123.965482193, 1570457.071154),
    "clean": ("df886091da439ae4", "d2f7355beb663b62", 152.395686567, 1604831.017122),
    "speckle": ("e40acde2339c7be8", "a67fff00e91de765", 181.083203306, 1692982.403721),
    "dropout": ("e9890724dc9650aa", "33da58fc8b4eb9dc", 110.520137351, 1535285.247347),
    "clutter": ("8e31985550107919", "31ad338a32b5e5ae", 141.911187248, 1605128.404669),
    "low_contrast": ("8f16a8ed3a6c5f12", "4f98eca66d9adfd4", 152.682477205, 1610810.47242),
    "tilted": ("2ed7f633082b232e", "41d3041a05127f74", 145.836617929, 1949602.07893),
}
LEGACY_SEQUENCE = [
    ("e2ca10c9cd9ac14a", "f950e51eba9324fd", 167.862158677, 1632090.640723),
    ("a1834965d1546c9e", "9e5358d5bc8298b2", 117.14388534, 1657463.134321),
    ("248be374b2896c3b", "67338907bd5af1cd", 75.525427076, 1686973.479338),
    ("b63b309edb105783", "9e5358d5bc8298b2", 117.14388534, 1657463.134321),
]


def _digest(ph):
    def sha(a):
        return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()[:16]

    return sha(ph.volume.array.astype(np.uint8)), sha(ph.truth_mask), ph.truth_volume_ml, np.abs(ph.truth_mesh[0]).sum()


def _check_legacy(ph, expected):
    image, mask, ml, mesh = _digest(ph)
    assert np.array_equal(ph.volume.array, ph.volume.array.astype(np.uint8)), "grey levels are integers"
    assert (image, mask) == expected[:2], "the legacy image or truth mask changed"
    np.testing.assert_allclose([ml, mesh], expected[2:], rtol=1e-9)


@pytest.mark.parametrize("family", list(LEGACY))
def test_legacy_phantoms_unchanged(family):
    # the families as tests/data/make_descent_reference.py makes them
    if family == "default":
        ph = make_phantom()
    else:
        ph = make_phantom(seed=200 + list(FAMILIES).index(family), spacing=1.5, **FAMILIES[family])
    _check_legacy(ph, LEGACY[family])


def test_legacy_sequence_unchanged():
    seq = make_sequence(seed=7, n_frames=4, spacing=2.0)
    for frame, expected in zip(seq.frames, LEGACY_SEQUENCE, strict=True):
        _check_legacy(frame, expected)
        np.testing.assert_allclose(frame.base, seq.frames[0].base)


# --- image formations ---------------------------------------------------------

from dataclasses import replace  # noqa: E402

from spheroseg.volumes.beamspace import BeamVolume  # noqa: E402
from spheroseg.synthetic.echo import ImageFormation  # noqa: E402
from spheroseg.synthetic.phantom import FORMATIONS, sweep_cases  # noqa: E402

# coarse voxels keep these fast; a wide PSF keeps the beam grid small
COARSE = dict(seed=4, spacing=2.5)
WIDE = replace(ImageFormation(), axial_psf_mm=1.6, lateral_psf_mm=5.0, elevation_psf_mm=5.0)


@pytest.fixture(scope="module")
def formed():
    return make_phantom(**COARSE, formation=WIDE, beam_space=True), make_phantom(**COARSE)


def test_formation_keeps_the_truth(formed):
    ph, legacy = formed
    np.testing.assert_array_equal(ph.truth_mask, legacy.truth_mask)
    assert ph.truth_volume_ml == legacy.truth_volume_ml
    np.testing.assert_array_equal(ph.apex, legacy.apex)
    np.testing.assert_array_equal(ph.base, legacy.base)
    np.testing.assert_array_equal(ph.truth_mesh[0], legacy.truth_mesh[0])
    assert ph.volume.shape == legacy.volume.shape and not np.array_equal(ph.volume.array, legacy.volume.array)


def test_formed_image_looks_like_apical_echo(formed):
    ph, _ = formed
    a = ph.volume.array
    assert np.array_equal(a, np.round(a)) and a.min() == 0 and a.max() <= 255
    # the black outside of the pyramidal sector, 0 only there
    assert (a == 0).mean() > 0.2
    assert np.all(a[ph.truth_mask] > 0)
    assert np.median(a[ph.truth_mask]) < np.median(a[(a > 0) & ~ph.truth_mask]) - 60
    beam = ph.beam_volume
    assert isinstance(beam, BeamVolume) and beam.array.min() >= 1 and np.array_equal(beam.array, np.round(beam.array))
    # the probe at the top centre of the Cartesian volume, the centre beam down its z axis
    probe = np.array([(ph.volume.shape[2] - 1) / 2, (ph.volume.shape[1] - 1) / 2, 0.0]) * ph.volume.spacing
    np.testing.assert_allclose(beam.geometry.apex, probe)
    on_axis = beam.geometry.index_to_world([[10.0, *beam.geometry.centre_index]])
    np.testing.assert_allclose(on_axis, [probe + [0, 0, 10 * beam.geometry.radius_sample_size]])
    # the Cartesian image is the beam image sampled at the voxel centres, rounded
    k, j, i = np.nonzero(a > 0)
    pick = np.random.default_rng(0).choice(len(i), 500, replace=False)
    world = np.stack([i[pick], j[pick], k[pick]], 1) * ph.volume.spacing
    np.testing.assert_array_equal(a[k[pick], j[pick], i[pick]], np.round(beam.sample(world)))


def test_formation_deterministic_and_seeded():
    f = replace(WIDE, clutter_db=None)
    a = make_phantom(seed=1, spacing=3.0, formation=f)
    b = make_phantom(seed=1, spacing=3.0, formation=f)
    np.testing.assert_array_equal(a.volume.array, b.volume.array)
    assert make_phantom(seed=1, spacing=3.0).params.get("formation") is None
    assert a.params["formation"] == f


def test_formation_settings_act_where_they_should():
    # the same scene and speckle: strong clutter brightens the near field only
    base = make_phantom(seed=2, spacing=3.0, formation=replace(WIDE, clutter_db=None))
    hazy = make_phantom(seed=2, spacing=3.0, formation=replace(WIDE, clutter_db=-12.0))
    depth = np.arange(base.volume.shape[0])[:, None, None] * 3.0 * np.ones(base.volume.shape)
    cavity = base.truth_mask
    diff = hazy.volume.array - base.volume.array
    near, far = cavity & (depth < 40), cavity & (depth > 70)
    assert diff[near].mean() > 20 and abs(diff[far].mean()) < 1
    # gain shifts every grey level by gain * 254 / DR where nothing clips
    bright = make_phantom(seed=2, spacing=3.0, formation=replace(WIDE, clutter_db=None, gain_db=4.0))
    a, b = base.volume.array, bright.volume.array
    ok = (a > 30) & (a < 200)
    assert np.median((b - a)[ok]) == pytest.approx(4.0 * 254 / WIDE.dynamic_range_db, abs=1.0)


def test_formation_rejects_legacy_image_options():
    with pytest.raises(ValueError, match="dropout"):
        make_phantom(spacing=3.0, formation=ImageFormation(), dropout=True)
    with pytest.raises(ValueError, match="formation"):
        make_phantom(spacing=3.0, beam_space=True)
    with pytest.raises(TypeError, match="ImageFormation"):
        make_phantom(spacing=3.0, formation=dict(gain_db=3))


def test_sweep_cases():
    cases = list(sweep_cases())
    assert 20 <= len(cases) <= 40
    assert {name for _, name, _ in cases} == set(FORMATIONS)
    assert all(kw["formation"] is FORMATIONS[name] for _, name, kw in cases)
    # every formation sees the same scenes
    seeds = {name: sorted(kw["seed"] for _, n, kw in cases if n == name) for name in FORMATIONS}
    assert len({tuple(s) for s in seeds.values()}) == 1
    with pytest.raises(ValueError, match="cannot be imaged"):
        list(sweep_cases(families=("dropout",)))
    with pytest.raises(ValueError, match="unknown formation"):
        list(sweep_cases(formations=("nope",)))


# --- base descent -----------------------------------------------------------


@pytest.fixture(scope="module")
def descending():
    return make_sequence(seed=3, n_frames=4, spacing=2.0, base_descent=12.0), make_sequence(seed=3, n_frames=4,
                                                                                          spacing=2.0)


def test_base_descends_towards_the_apex(descending):
    seq, still = descending
    ed, es = seq.frames[0], seq.frames[2]
    axis = (ed.apex - ed.base) / np.linalg.norm(ed.apex - ed.base)
    np.testing.assert_allclose(es.base - ed.base, 12.0 * axis, atol=1e-9)
    np.testing.assert_allclose(seq.frames[1].base - ed.base, 6.0 * axis, atol=1e-9)  # s = 1/2
    for frame in seq.frames:
        np.testing.assert_allclose(frame.apex, ed.apex, atol=1e-6)  # the apex stays put
    # end-diastole is the same as without descent; end-systole is smaller
    np.testing.assert_array_equal(ed.truth_mask, still.frames[0].truth_mask)
    assert seq.truth_volumes_ml[2] < still.truth_volumes_ml[2] - 5
    assert seq.truth_ef > still.truth_ef + 3


def test_base_descent_truth_follows(descending):
    seq, _ = descending
    spacing = 2.0
    for frame in seq.frames:
        voxels = frame.truth_mask.sum() * spacing**3 / 1000
        # voxel centres at 2 mm against the exact integral: within 2 %
        assert voxels == pytest.approx(frame.truth_volume_ml, rel=0.02)
        # the cavity closes at this frame's base plane
        axis = (frame.apex - frame.base) / np.linalg.norm(frame.apex - frame.base)
        k, j, i = np.nonzero(frame.truth_mask)
        height = (np.stack([i, j, k], 1) * spacing - frame.base) @ axis
        assert height.min() >= 0 and height.min() < spacing
        # the true mesh closes there too
        h = (frame.truth_mesh[0] - frame.base) @ axis
        assert abs(h.min()) < 0.5 and abs(signed_volume(frame.truth_mesh[0] - frame.base, frame.truth_mesh[1]) / 1000
                                          - frame.truth_volume_ml) < 0.005 * frame.truth_volume_ml


def test_base_descent_validation():
    with pytest.raises(ValueError, match="base_descent"):
        make_sequence(n_frames=2, spacing=3.0, base_descent=-1.0)


def test_dropout_darkens_a_wall_region_only():
    f = replace(WIDE, clutter_db=None)
    base = make_phantom(seed=2, spacing=3.0, formation=f)
    lost = make_phantom(seed=2, spacing=3.0, formation=replace(f, dropout_db=30.0))
    diff = base.volume.array - lost.volume.array
    k, j, i = np.nonzero(diff > 20)
    centre = np.stack([i, j, k], 1).mean(0) * 3.0
    assert len(i) > 20 and np.linalg.norm(base.truth_mesh[0] - centre, axis=1).min() < 10, "on the wall"
    # the same image elsewhere: a region of 16 mm radius (plus the PSF)
    k, j, i = np.nonzero(np.abs(diff) > 1)
    assert np.linalg.norm(np.stack([i, j, k], 1) * 3.0 - centre, axis=1).max() < 30
    assert diff[np.abs(diff) > 1].mean() > 20, "darker there"


def test_sequence_with_formation_keeps_the_truth():
    formed = make_sequence(seed=5, n_frames=2, spacing=3.0, base_descent=9.0, formation=WIDE)
    plain = make_sequence(seed=5, n_frames=2, spacing=3.0, base_descent=9.0)
    for a, b in zip(formed.frames, plain.frames, strict=True):
        np.testing.assert_array_equal(a.truth_mask, b.truth_mask)
        np.testing.assert_array_equal(a.base, b.base)
        assert a.params["formation"] == WIDE and not np.array_equal(a.volume.array, b.volume.array)
    # speckle changes from frame to frame
    assert not np.array_equal(formed.frames[0].volume.array, formed.frames[1].volume.array)


def test_tilted_mitral_scene_truth():
    from spheroseg.geometry.coords import annulus_plane
    from spheroseg.synthetic.phantom import tilted_mitral_scene

    scene = tilted_mitral_scene(10.0)
    # 1 mm voxels: the mask's voxel count is the analytic half-ellipsoid's volume
    assert scene.truth_mask.sum() / 1000 == pytest.approx(scene.truth_ml, rel=0.01)
    # the ring lies in the plane through the base tilted 10 degrees from the axis (z)
    centre, normal = annulus_plane(scene.annulus)
    np.testing.assert_allclose(centre, scene.base, atol=1e-9)
    assert np.degrees(np.arccos(abs(normal[2]))) == pytest.approx(10.0, abs=1e-9)


@pytest.fixture(scope="module")
def papillary():
    return make_phantom(seed=3, spacing=1.5), make_phantom(seed=3, spacing=1.5, papillary=True, trabecular_mm=3.0)


def test_papillary_muscles_and_trabeculae_stand_in_the_cavity(papillary):
    """Off by default; on, the truth is the same (muscles and trabeculae
    are cavity), and the voxels that brightened are cavity voxels, nearer
    the myocardium's grey level than the blood's, in pieces that reach the
    wall."""
    from scipy import ndimage

    plain, inner = papillary
    assert np.array_equal(plain.truth_mask, inner.truth_mask) and plain.truth_volume_ml == inner.truth_volume_ml
    changed = plain.volume.array != inner.volume.array
    tissue = changed & (inner.volume.array.astype(int) - plain.volume.array > 40)
    assert tissue.sum() > 0.03 * plain.truth_mask.sum()  # muscles and rim: a few percent of the cavity
    assert plain.truth_mask[tissue].all()
    grey = inner.volume.array.astype(float)
    myocardium = ~plain.truth_mask & (grey > 0) & ndimage.binary_dilation(plain.truth_mask, iterations=3)
    blood = np.median(plain.volume.array[plain.truth_mask & (plain.volume.array > 0)])
    # brighter than half way from blood to myocardium (thin trabeculae blur)
    assert np.median(grey[tissue]) > (blood + np.median(grey[myocardium])) / 2
    # each muscle touches the wall: every piece of new tissue reaches the cavity's border
    labels, n = ndimage.label(tissue)
    border = plain.truth_mask & ~ndimage.binary_erosion(plain.truth_mask)
    assert n >= 2 and all(border[labels == k].any() for k in range(1, n + 1) if (labels == k).sum() > 20)


def test_papillary_options_validated():
    with pytest.raises(ValueError, match="trabecular_mm"):
        make_phantom(spacing=3.0, trabecular_mm=-1.0)


def test_papillary_phantom_volume_within_3_percent():
    """Muscles standing in the cavity of the default formation's image:
    the wall still follows the compact myocardium (volume -0.5 %; +0.1 %
    without them)."""
    from spheroseg.surfaces.metrics import dice
    from spheroseg.tracking.segment import segment

    ph = make_phantom(seed=0, formation=FORMATIONS["default"], papillary=True)
    r = segment(ph.volume, ph.apex, ph.base)
    assert abs(r.volume_ml / ph.truth_volume_ml - 1) < 0.03
    assert dice(r.mask(ph.volume), ph.truth_mask) > 0.95


def test_epicardial_truth_mask_has_the_analytic_volume():
    ph = make_phantom(seed=2, spacing=1.0, speckle=False, epicardium=True)
    voxels = ph.truth_myocardium_mask.sum() * 1.0 / 1000
    assert ph.truth_myocardial_volume_ml == pytest.approx(voxels, rel=0.01)
    assert ph.truth_lv_mass_g == pytest.approx(1.05 * ph.truth_myocardial_volume_ml)
    # the wall and the cavity do not overlap, and the wall stops at the mitral plane
    assert not (ph.truth_myocardium_mask & ph.truth_mask).any()
    assert make_phantom(seed=2, spacing=4.0).truth_myocardium_mask is None


def test_late_region_moves_its_wall_later():
    from spheroseg.synthetic.phantom import LateRegion

    plain = make_sequence(n_frames=4, seed=1, spacing=3.0, speckle=False)
    on_time = make_sequence(n_frames=4, seed=1, spacing=3.0, speckle=False, late_region=LateRegion(delay=0.0))
    late = make_sequence(n_frames=4, seed=1, spacing=3.0, speckle=False, late_region=LateRegion(delay=0.25))
    np.testing.assert_allclose(on_time.truth_volumes_ml, plain.truth_volumes_ml, rtol=1e-12)
    # a quarter of a cycle late, the region is half-way in at end-diastole and half-way out at end-systole
    assert late.truth_volumes_ml[0] < plain.truth_volumes_ml[0] / 1.02
    assert late.truth_volumes_ml[2] > plain.truth_volumes_ml[2] * 1.02
    # and the voxels agree with the analytic volume
    voxels = late.frames[2].truth_mask.sum() * 27.0 / 1000
    assert voxels == pytest.approx(late.truth_volumes_ml[2], rel=0.05)
