import numpy as np
import pytest

from spheroseg import Volume
from spheroseg import segment
from spheroseg.geometry.coords import Pose, ProlateSpheroidal
from spheroseg.tracking.epicardium import (
    DARK_EPICARDIUM, DARK_MAX_ITERATIONS, DARK_WALL, DARK_WALL_MARGIN, MAX_ITERATIONS, add_epicardium,
    conserving_start, enforce_thickness, initial_epicardium, segment_epicardium, wall_nepers,
)
from spheroseg.geometry.hermite import HermiteGrid
from spheroseg.surfaces.myocardium import SEGMENT_NAMES, cell_centres, myocardial_volume_ml, wall_thickness
from spheroseg.descent.quality import wall_report
from spheroseg.descent.results import SegmentationResult, TrackingResult
from spheroseg.surfaces.surface import Surface
from spheroseg.synthetic.echo import multiplicative_speckle

D, L_ENDO, L_EPI = 30.0, 0.8, 1.0
BASE = np.array([60.0, 60.0, 70.0])
APEX = BASE + [0, 0, -D * np.cosh(L_ENDO)]  # the long axis towards -z: the probe's side


def shell(l0, pose):
    system = ProlateSpheroidal(D)
    grid = HermiteGrid(8, 8, (0.0, np.pi / 2), poles=system.poles)
    return Surface.from_function(system, pose, grid, l0)


def shell_labels(*, l_epi=L_EPI):
    """Blood (0) inside lambda = 0.8, myocardium (1) to ``l_epi``, tissue (2)
    outside (a confocal prolate shell of 6-9 mm), blood beyond the mitral
    plane; 1.5 mm voxels: ``(labels, pose, spacing)``."""
    spacing = 1.5
    n = (54, 80, 80)
    k, j, i = np.meshgrid(*(np.arange(m) * spacing for m in n), indexing="ij")
    world = np.stack([i, j, k], -1)
    pose = Pose.from_apex_base(APEX, BASE)
    lam, _, mu = ProlateSpheroidal(D).from_cartesian(pose.to_local(world))
    below = mu <= np.pi / 2
    labels = np.where(below & (lam <= L_ENDO), 0, np.where(below & (lam <= l_epi), 1, 2))
    return np.where(~below & (lam <= l_epi), 0, labels), pose, spacing


def shells_image(*, myocardium=150.0, tissue=80.0, blood=20.0, seed=0, l_epi=L_EPI):
    """:func:`shell_labels` as grey levels with Gaussian noise."""
    labels, pose, spacing = shell_labels(l_epi=l_epi)
    image = np.array([blood, myocardium, tissue])[labels]
    image = image + np.random.default_rng(seed).normal(0, 12, image.shape)
    return Volume(np.clip(image, 1, 255).astype(np.uint8), spacing=(spacing,) * 3), pose


def test_initial_epicardium_has_the_prior_thickness():
    endo = Surface.from_apex_base(APEX, BASE)
    start = initial_epicardium(endo, thickness_mm=8.0)
    grid = endo.grid
    v2, v1 = np.meshgrid(grid.node_v2, grid.node_v1, indexing="ij")
    np.testing.assert_allclose(wall_thickness(endo, start, v1, v2), 8.0, rtol=1e-9)
    with pytest.raises(ValueError, match="thickness_mm"):
        initial_epicardium(endo, thickness_mm=-1.0)


def test_initial_epicardium_of_a_surface_collapsed_onto_the_focal_segment():
    """A descent that failed can leave ``v0 = 0`` (the focal segment), where
    the scale factor vanishes at the pole: the wall is still 8 mm thick at
    every node (it had infinite coefficients, and the quality checks raised)."""
    collapsed = shell(0.0, Surface.from_apex_base(APEX, BASE).pose)
    start = initial_epicardium(collapsed, thickness_mm=8.0)
    assert np.all(np.isfinite(start.coefficients))
    grid = collapsed.grid
    v2, v1 = np.meshgrid(grid.node_v2, grid.node_v1, indexing="ij")
    np.testing.assert_allclose(wall_thickness(collapsed, start, v1, v2), 8.0, rtol=1e-4)  # 0.5 um by the pole


def test_enforce_thickness_keeps_the_epicardium_outside():
    endo = Surface.from_apex_base(APEX, BASE)
    epi = initial_epicardium(endo, thickness_mm=8.0)
    dented = epi.coefficients.copy()
    dented[2:4, 1:3, 0] -= 0.4  # a region inside the endocardium
    dented[2:4, 1:3, 2] += 0.5
    epi = epi.with_coefficients(endo.grid.constrain(dented))
    v1, v2 = np.random.default_rng(1).uniform([0, 0], [2 * np.pi, np.pi / 2], (5000, 2)).T
    assert wall_thickness(endo, epi, v1, v2).min() < 0
    fixed = enforce_thickness(endo, epi, min_thickness_mm=2.0)
    assert wall_thickness(endo, fixed, v1, v2).min() >= 2.0 - 0.05
    # far from the dent the wall is where it was (up to the lift)
    far = (v2 > 1.3) & (np.abs(np.angle(np.exp(1j * (v1 - 4.0)))) < 0.5)
    np.testing.assert_allclose(fixed.evaluate(v1[far], v2[far]), epi.evaluate(v1[far], v2[far]), atol=0.03)


@pytest.mark.parametrize("myocardium, tissue, polarity", [(150.0, 80.0, "bright"), (60.0, 140.0, "dark")])
def test_epicardium_of_a_prolate_shell(myocardium, tissue, polarity):
    volume, pose = shells_image(myocardium=myocardium, tissue=tissue)
    endo, truth = shell(L_ENDO, pose), shell(L_EPI, pose)
    # Gaussian noise on sharp edges, no log-compressed speckle: the midpoint is the edge
    result = segment_epicardium(volume, endo, thickness_mm=7.0, boundary="midpoint")
    assert result.parameters["polarity"] == polarity
    # a bright wall's edge to a coarser tolerance; a dark wall, which may collapse slowly, to the endocardium's
    assert result.parameters["tol"] == {"bright": 0.1, "dark": 0.05}[polarity]
    v1, v2 = np.meshgrid(np.linspace(0, 2 * np.pi, 24, endpoint=False), np.linspace(0.2, 1.5, 12))
    error = wall_thickness(endo, result.surface, v1, v2) - wall_thickness(endo, truth, v1, v2)
    assert np.median(np.abs(error)) < 1.0
    expected = myocardial_volume_ml(endo, truth)
    assert myocardial_volume_ml(endo, result.surface) == pytest.approx(expected, rel=0.1)


def speckle_shells_image(*, nepers=15.0, contrast_db=12.0, blur_mm=2.0, seed=0):
    """The shells of :func:`shells_image` as echo: intensities (blood -30 dB,
    myocardium 0 dB, tissue ``-contrast_db``) blurred by a Gaussian PSF,
    times fully developed speckle (exponential, independent per voxel),
    log-compressed at ``nepers`` grey levels per neper."""
    labels, pose, spacing = shell_labels()
    levels = np.array([1e-3, 1.0, 10 ** (-contrast_db / 10)])
    grey = multiplicative_speckle(levels[labels], blur_mm=blur_mm, spacing=spacing, nepers=nepers, seed=seed)
    return Volume(grey, spacing=(spacing,) * 3), pose


def test_wall_nepers_reads_the_log_compression():
    volume, pose = speckle_shells_image(nepers=15.0, blur_mm=0.1)
    endo = shell(L_ENDO, pose)
    assert wall_nepers(volume, endo, shell(L_EPI, pose)) == pytest.approx(15.0, rel=0.08)


def test_the_epicardium_reads_the_log_compression_the_endocardium_estimated():
    """The endocardium's intensity interface estimates the image's log
    compression (15 grey levels per neper here) and records it; the
    epicardium's outer boundary uses that one estimate.  Other data terms
    estimate none, and the epicardium then reads the wall's speckle."""
    volume, _ = speckle_shells_image(nepers=15.0)
    result = segment(volume, APEX, BASE, myocardium=True)
    assert result.log_compression == pytest.approx(15.0, rel=0.08)
    assert result.parameters["epicardium"]["nepers"] == result.log_compression
    local = segment(volume, APEX, BASE, myocardium=True, mode="local")
    assert local.log_compression is None
    assert local.parameters["epicardium"]["nepers"] == pytest.approx(15.0, rel=0.08)
    assert local.parameters["epicardium"]["nepers"] != result.log_compression
    with pytest.raises(ValueError, match="nepers must be a positive number"):
        segment_epicardium(volume, result.surface, nepers=-3.0)


def test_intensity_interface_removes_the_midpoints_bias():
    """Blurred echo of a wall 12 dB brighter than the tissue beyond it: the
    grey levels' midpoint puts the epicardium outside the true one (at the
    intensities' geometric mean); the half-way intensity on it."""
    volume, pose = speckle_shells_image()
    endo, truth = shell(L_ENDO, pose), shell(L_EPI, pose)
    v1, v2 = np.meshgrid(np.linspace(0, 2 * np.pi, 24, endpoint=False), np.linspace(0.2, 1.5, 12))
    errors = {}
    for boundary in ("intensity", "midpoint"):
        result = segment_epicardium(volume, endo, thickness_mm=7.0, boundary=boundary)
        assert result.parameters["boundary"] == boundary
        errors[boundary] = np.median(wall_thickness(endo, result.surface, v1, v2) - wall_thickness(endo, truth, v1, v2))
    assert abs(errors["intensity"]) < 0.5 < errors["midpoint"] - abs(errors["intensity"])
    # its quality is the wall's, on 48 x 48 points of the endocardium's (v1, v2)
    lo, hi = endo.grid.v2_range
    v1, v2 = cell_centres(endo)
    np.testing.assert_allclose(v1[:2], [np.pi / 48, np.pi / 16])
    np.testing.assert_allclose(v2[[0, -1]], [lo + (hi - lo) / 96, hi - (hi - lo) / 96])
    v1, v2 = np.meshgrid(v1, v2)
    expected = wall_report(wall_thickness(endo, result.surface, v1, v2, order=4), min_thickness_mm=2.0)
    assert result.quality["warnings"] == expected.pop("warnings")  # pytest 9.2's approx takes no nested list
    assert {k: v for k, v in result.quality.items() if k != "warnings"} == pytest.approx(expected, rel=1e-12)
    with pytest.raises(ValueError, match="boundary must be"):
        segment_epicardium(volume, endo, boundary="outer")



@pytest.mark.parametrize("contrast_db, polarity", [(12.0, "bright"), (-6.0, "dark")])
def test_a_wall_darker_than_what_lies_beyond_it_is_flagged(contrast_db, polarity):
    """With the points checked, the endocardium's report says when its wall
    is darker than the tissue beyond it (the intensity interface may read
    that tissue past a thin wall), and the epicardium takes that polarity
    and says its outer edge is weak."""
    volume, pose = speckle_shells_image(contrast_db=contrast_db)
    res = segment(volume, APEX, BASE)
    assert (DARK_WALL in res.quality["warnings"]) is (polarity == "dark")
    assert np.sign(res.quality["wall_contrast"]) == {"bright": 1, "dark": -1}[polarity]
    assert res.quality["poor"] or polarity == "bright"
    both = segment(volume, APEX, BASE, myocardium=True)
    assert both.parameters["epicardium"]["polarity"] == polarity
    assert (DARK_EPICARDIUM in both.quality["epicardium"]["warnings"]) is (polarity == "dark")
    cap = {"bright": MAX_ITERATIONS, "dark": DARK_MAX_ITERATIONS}[polarity]  # a dark wall drifts: stopped sooner
    assert both.parameters["epicardium"]["max_iterations"] == cap
    assert "wall_contrast" not in segment(volume, APEX, BASE, check=False).quality

def test_a_wall_as_bright_as_the_tissue_beyond_it_is_not_flagged():
    """Its contrast with the tissue beyond reads within the margin, of
    either sign (here the blurred edge leaves the wall a little darker)."""
    volume, _ = speckle_shells_image(contrast_db=0.0)
    level = segment(volume, APEX, BASE)
    assert abs(level.quality["wall_contrast"]) < DARK_WALL_MARGIN * (level.c_out - level.c_in)
    assert DARK_WALL not in level.quality["warnings"]


def test_segment_with_myocardium_gives_the_wall():
    volume, pose = speckle_shells_image()
    res = segment(volume, APEX, BASE, myocardium=True, rv_insertion=0.5)
    assert isinstance(res.epicardium, Surface)
    np.testing.assert_array_equal(res.myocardium_mask(volume),
                                  res.epicardium.mask(volume.grid) & ~res.surface.mask(volume.grid))
    assert res.lv_mass_g == pytest.approx(1.05 * res.myocardial_volume_ml)
    truth_ml = myocardial_volume_ml(shell(L_ENDO, pose), shell(L_EPI, pose))
    assert res.myocardial_volume_ml == pytest.approx(truth_ml, rel=0.15)
    table = res.segments
    assert [row["name"] for row in table] == list(SEGMENT_NAMES)
    assert sum(row["cavity_ml"] for row in table) == pytest.approx(res.volume_ml, rel=1e-3)
    assert sum(row["myocardium_ml"] for row in table) == pytest.approx(res.myocardial_volume_ml, rel=1e-3)
    assert res.wall_thickness_mm.shape == (17,) and np.all(res.wall_thickness_mm > 3)
    assert res.segment_convention.rv_insertion == 0.5
    assert "epicardium" in res.quality and res.parameters["epicardium"]["polarity"] == "bright"
    plain = segment(volume, APEX, BASE)
    with pytest.raises(ValueError, match="myocardium=True"):
        plain.lv_mass_g


def test_wall_report_flags_a_collapse_and_an_explosion():
    rng = np.random.default_rng(0)
    normal = wall_report(rng.uniform(6, 12, 1000), min_thickness_mm=2.0)
    assert not normal["poor"] and 8 < normal["thickness_median_mm"] < 10
    collapsed = wall_report(np.r_[np.full(300, 2.0), rng.uniform(6, 12, 700)], min_thickness_mm=2.0)
    assert collapsed["poor"] and "collapsed" in collapsed["warnings"][0]
    exploded = wall_report(rng.uniform(20, 40, 1000), min_thickness_mm=2.0)
    assert exploded["poor"] and "thick" in exploded["warnings"][0]


def test_wall_report_flags_a_wall_thin_everywhere_but_off_its_floor():
    # the tilted contrast_low case: 3 mm nearly everywhere, 2 mm floor seldom reached
    rng = np.random.default_rng(1)
    thin = wall_report(np.r_[rng.uniform(2.6, 3.4, 950), rng.uniform(6, 9, 50)], min_thickness_mm=2.0)
    assert thin["floor_fraction"] < 0.1 and thin["poor"] and "thin" in thin["warnings"][0]
    assert not wall_report(rng.uniform(4.5, 7.0, 1000), min_thickness_mm=2.0)["poor"]


def test_wall_report_flags_an_epicardium_still_moving():
    rng = np.random.default_rng(2)
    thickness = rng.uniform(6, 12, 1000)
    assert not wall_report(thickness, min_thickness_mm=2.0)["poor"]
    moving = wall_report(thickness, min_thickness_mm=2.0, settled=False)
    assert moving["poor"] and moving["warnings"] == [
        "the epicardium was still moving at its iteration cap: no clear outer boundary"]


def test_an_epicardium_stopped_by_its_cap_is_poor():
    """The cap (30 iterations by default; a bright wall settles in 5-12)
    reached: the wall report says the epicardium was still moving.  Here
    the cap is 2, the start some 4 mm outside the wall."""
    volume, pose = shells_image()
    endo = shell(L_ENDO, pose)
    capped = segment_epicardium(volume, endo, thickness_mm=12.0, max_iterations=2)
    assert capped.status == 1 and capped.iterations == 2
    assert capped.quality["poor"] and "still moving" in capped.quality["warnings"][-1]
    settled = segment_epicardium(volume, endo, thickness_mm=12.0)
    assert settled.parameters["max_iterations"] == MAX_ITERATIONS == 30
    assert settled.status == 0 and settled.iterations > 2 and not settled.quality["poor"]


def test_a_collapsed_epicardium_makes_the_result_poor():
    # a wall of about 1 mm: the epicardium falls onto its 3 mm floor
    volume, pose = shells_image(l_epi=0.83)
    endo = shell(L_ENDO, pose)
    result = SegmentationResult(endo, 10, True, 20.0, 150.0, 0.1, quality={"warnings": [], "poor": False})
    add_epicardium(result, volume, thickness_mm=6.0, min_thickness_mm=3.0)
    assert result.epicardium is not None and result.quality["epicardium"]["floor_fraction"] > 0.1
    assert result.quality["poor"] and result.quality["warnings"][0].startswith("epicardium: the wall collapsed")


def test_tracking_result_segment_curves_and_sdi():
    pose = Pose.from_apex_base(APEX, BASE)
    n = 8
    lam = L_ENDO - 0.1 * (1 - np.cos(2 * np.pi * np.arange(n) / n)) / 2  # smallest at frame 4: half the cycle
    frames = [SegmentationResult(shell(l0, pose), 1, True, 0.0, 1.0, 0.0, epicardium=shell(l0 + 0.2, pose))
              for l0 in lam]
    tracked = TrackingResult(frames)
    curves = tracked.segment_volumes_ml
    assert curves.shape == (n, 17)
    np.testing.assert_allclose(curves.sum(1), tracked.volumes_ml, rtol=1e-4)
    np.testing.assert_allclose(tracked.times_to_minimum, 50.0, atol=1e-6)
    assert tracked.sdi == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_allclose(tracked.masses_g, [1.05 * f.myocardial_volume_ml for f in frames])


def test_track_with_myocardium_gives_every_frame_its_wall():
    from spheroseg import track

    volume, pose = speckle_shells_image()
    other, _ = speckle_shells_image(seed=1)
    tracked = track([volume, other, volume], APEX, BASE, myocardium=True, rv_insertion=0.3)
    assert all(f.epicardium is not None and f.segment_convention.rv_insertion == 0.3 for f in tracked.frames)
    truth_g = 1.05 * myocardial_volume_ml(shell(L_ENDO, pose), shell(L_EPI, pose))
    np.testing.assert_allclose(tracked.masses_g, truth_g, rtol=0.15)
    assert tracked.segment_volumes_ml.shape == (3, 17)


def test_conserving_start_keeps_the_myocardial_volume():
    pose = Pose.from_apex_base(APEX, BASE)
    endo, epi = shell(L_ENDO, pose), shell(L_EPI, pose)
    smaller = shell(0.7, pose)
    start = conserving_start(smaller, endo, epi)
    np.testing.assert_allclose(myocardial_volume_ml(smaller, start), myocardial_volume_ml(endo, epi), rtol=1e-9)
    # a smaller cavity with the same wall volume: a thicker wall
    v1, v2 = np.meshgrid(np.linspace(0, 6, 7), np.linspace(0.2, 1.5, 5))
    assert np.all(wall_thickness(smaller, start, v1, v2) > wall_thickness(endo, epi, v1, v2))


def test_cetus_patient7_mass_is_an_adults_and_agrees_at_ed_and_es(tmp_path):
    """Real echo (CETUS Patient 7, read from ../shared; its 0.9 mm spacing
    assumed): the LV mass in the adult range (Lang et al. 2015: 67-224 g
    across women and men, widened to 50-300 g for the assumed spacing), the
    wall not flagged, and the two phases' masses, segmented independently,
    within 8 % of each other (the myocardium is nearly incompressible)."""
    import json

    from conftest import cetus_file

    from spheroseg import load

    points = json.loads(cetus_file("Patient7_points.json").read_text())
    spacing = points["assumed_spacing_mm"]
    masses = []
    for phase in ("ED", "ES"):
        np.save(tmp_path / "p7.npy", np.load(cetus_file(points[phase]["file"])))  # as the CLI reads it
        volume = load(tmp_path / "p7.npy", spacing=(spacing,) * 3)
        apex = np.array(points[phase]["apex_index"][::-1], float) * spacing
        base = np.array(points[phase]["base_index"][::-1], float) * spacing
        result = segment(volume, apex, base, myocardium=True)
        assert result.parameters["epicardium"]["polarity"] == "bright"
        assert not result.quality["epicardium"]["warnings"], result.quality["epicardium"]
        assert 4.0 < result.quality["epicardium"]["thickness_median_mm"] < 12.0
        masses.append(result.lv_mass_g)
    assert all(50.0 < m < 300.0 for m in masses), masses
    assert abs(masses[1] / masses[0] - 1) < 0.08, masses
