"""What a segmentation and a tracked sequence return
(spheroseg.descent.results), on confocal prolate spheroidal shells whose
volumes and wall thickness are analytic.

A shell ``lambda = l`` of focal length ``d``, cut at its equator (the base
plane ``mu = pi / 2``), is half a prolate spheroid of semi-axes
``a = d cosh l`` (along the long axis) and ``b = d sinh l``: volume
``2/3 pi a b^2``.  Between two confocal shells the wall along the
``lambda`` coordinate curve at ``mu`` is ``int d sqrt(sinh^2 + sin^2 mu)
dlambda``: ``d (cosh l2 - cosh l1)`` at the apex (``mu = 0``) and
``d (sinh l2 - sinh l1)`` at the base ring.  Segment curves and SDI are
tests/test_epicardium.py's test_tracking_result_segment_curves_and_sdi."""

import numpy as np
import pytest

from spheroseg.descent import results
from spheroseg.descent.results import STATUS_MESSAGES, SegmentationResult, TrackingResult
from spheroseg.geometry.coords import Pose, ProlateSpheroidal
from spheroseg.geometry.hermite import HermiteGrid
from spheroseg.surfaces.surface import Surface
from spheroseg.volumes.volume import Volume

D = 25.0
BASE = np.array([40.0, 40.0, 50.0])
POSE = Pose.from_apex_base(BASE - [0.0, 0.0, 40.0], BASE)


def shell(l0):
    system = ProlateSpheroidal(D)
    return Surface.from_function(system, POSE, HermiteGrid(4, 4, (0.0, np.pi / 2), poles=system.poles), l0)


def half_spheroid_ml(l0):
    a, b = D * np.cosh(l0), D * np.sinh(l0)
    return 2 / 3 * np.pi * a * b * b / 1000


def frame(l0, **kwargs):
    return SegmentationResult(shell(l0), iterations=10, converged=True, c_in=20.0, c_out=120.0, seconds=0.1, **kwargs)


def test_a_result_s_volume_is_its_surface_s():
    result = frame(0.8)
    assert result.volume_ml == pytest.approx(half_spheroid_ml(0.8), rel=1e-6)
    assert (result.status, result.message) == (0, STATUS_MESSAGES[0])
    points, faces = result.mesh(32, 16)
    assert points.shape[1] == 3 and faces.shape[1] == 3 and faces.max() == len(points) - 1


def test_the_myocardium_between_confocal_shells():
    result = frame(0.7, epicardium=shell(0.9))
    wall_ml = half_spheroid_ml(0.9) - half_spheroid_ml(0.7)
    assert result.myocardial_volume_ml == pytest.approx(wall_ml, rel=1e-6)
    assert result.lv_mass_g == pytest.approx(1.05 * wall_ml, rel=1e-6)
    thickness = result.wall_thickness_mm
    assert thickness.shape == (17,)
    apex, base_ring = D * (np.cosh(0.9) - np.cosh(0.7)), D * (np.sinh(0.9) - np.sinh(0.7))
    assert thickness[16] == pytest.approx(apex, rel=1e-9)  # segment 17: the thickness at the apex
    assert np.all((thickness > apex) & (thickness < base_ring))
    # a shape of revolution: each ring's segments alike, thicker towards the base
    basal, mid, apical = thickness[:6], thickness[6:12], thickness[12:16]
    for ring in (basal, mid, apical):
        np.testing.assert_allclose(ring, ring.mean(), rtol=1e-3)
    assert basal.mean() > mid.mean() > apical.mean()
    rows = result.segments
    assert [row["segment"] for row in rows] == list(range(1, 18))
    assert sum(row["cavity_ml"] for row in rows) == pytest.approx(result.volume_ml, rel=1e-3)
    assert sum(row["myocardium_ml"] for row in rows) == pytest.approx(wall_ml, rel=1e-3)


def test_without_an_epicardium_the_myocardium_is_an_error():
    result = frame(0.8)
    for name in ("myocardial_volume_ml", "lv_mass_g", "wall_thickness_mm"):
        with pytest.raises(ValueError, match="^this result has no epicardium: segment with myocardium=True$"):
            getattr(result, name)
    with pytest.raises(ValueError, match="no epicardium"):
        result.myocardium_mask(Volume(np.zeros((2, 2, 2))))
    assert all("myocardium_ml" not in row for row in result.segments)


def contained(surface, grid):
    """The voxel centres in the cavity, by Surface.contains (numpy), [z, y, x]."""
    k, j, i = np.meshgrid(*(np.arange(n) for n in grid.shape), indexing="ij")
    return surface.contains(grid.index_to_world(np.stack([i, j, k], -1).reshape(-1, 3))).reshape(grid.shape)


def test_the_masks_are_the_cavity_and_the_wall_on_the_volume_s_grid(monkeypatch):
    # the rasteriser (compiled; tests/test_raster.py) replaced by the
    # definition it is checked against, so that this file compiles nothing
    monkeypatch.setattr(results, "surface_mask", contained)
    monkeypatch.setattr("spheroseg._compiled.raster.surface_mask", contained)
    volume = Volume(np.zeros((40, 34, 34), np.float32), spacing=(2.0, 2.0, 1.5), origin=(6.0, 6.0, 0.0))
    result = frame(0.7, epicardium=shell(0.9))
    voxel_ml = 2.0 * 2.0 * 1.5 / 1000
    cavity, wall = result.mask(volume), result.myocardium_mask(volume)
    assert cavity.shape == wall.shape == (40, 34, 34) and not (cavity & wall).any()
    assert cavity.sum() * voxel_ml == pytest.approx(result.volume_ml, rel=0.03)
    assert wall.sum() * voxel_ml == pytest.approx(result.myocardial_volume_ml, rel=0.05)
    # the apex, 40 mm from the base along -z, is cavity; a voxel beyond the base plane is neither
    apex_voxel = np.rint(volume.world_to_index([BASE - [0.0, 0.0, D * np.cosh(0.7) - 2.0]])[0]).astype(int)[::-1]
    assert cavity[tuple(apex_voxel)]
    beyond = np.rint(volume.world_to_index([BASE + [0.0, 0.0, 3.0]])[0]).astype(int)[::-1]
    assert not cavity[tuple(beyond)] and not wall[tuple(beyond)]


LAMBDAS = [0.8, 0.9, 0.75, 0.7, 0.85]  # end-diastole at frame 1, end-systole at frame 3


def test_a_tracked_sequence_s_volumes_and_ejection_fraction():
    tracked = TrackingResult([frame(l0) for l0 in LAMBDAS])
    exact = np.array([half_spheroid_ml(l0) for l0 in LAMBDAS])
    np.testing.assert_allclose(tracked.volumes_ml, exact, rtol=1e-6)
    assert (tracked.ed_frame, tracked.es_frame) == (1, 3)
    assert tracked.edv_ml == pytest.approx(exact[1], rel=1e-6)
    assert tracked.esv_ml == pytest.approx(exact[3], rel=1e-6)
    # EF by hand: 100 (1 - cosh 0.7 sinh^2 0.7 / (cosh 0.9 sinh^2 0.9)) = 52.17 %
    ef = 100 * (1 - np.cosh(0.7) * np.sinh(0.7) ** 2 / (np.cosh(0.9) * np.sinh(0.9) ** 2))
    assert tracked.ef == pytest.approx(ef, rel=1e-6) and tracked.ef == pytest.approx(52.17, abs=0.005)
    with pytest.raises(ValueError, match="no epicardium"):
        _ = tracked.masses_g


def test_a_tracked_sequence_s_masses_and_initialisation():
    start = {"method": "given", "apex": [0.0, 0.0, 0.0]}
    frames = [frame(l0, epicardium=shell(l0 + 0.15), initialisation=start if t == 0 else None)
              for t, l0 in enumerate(LAMBDAS)]
    tracked = TrackingResult(frames)
    expected = [1.05 * (half_spheroid_ml(l0 + 0.15) - half_spheroid_ml(l0)) for l0 in LAMBDAS]
    np.testing.assert_allclose(tracked.masses_g, expected, rtol=1e-6)
    assert tracked.initialisation is start
    assert TrackingResult([]).initialisation is None


def test_a_tracked_sequence_s_quality_is_its_frames():
    reports = [None, {"warnings": ["low contrast"], "poor": True}, {"warnings": [], "poor": False},
               {"warnings": ["not converged", "apex moved"], "poor": True}]
    tracked = TrackingResult([frame(0.8, quality=q) for q in reports])
    assert tracked.quality == {"poor": True, "frames": [{}] + reports[1:],
                               "warnings": ["frame 1: low contrast", "frame 3: not converged", "frame 3: apex moved"]}
    good = TrackingResult([frame(0.8, quality={"warnings": [], "poor": False}), frame(0.7)])
    assert good.quality["poor"] is False and good.quality["warnings"] == []
    # poor when a frame's report is, whatever its warnings say
    assert TrackingResult([frame(0.8, quality={"warnings": [], "poor": True})]).quality["poor"] is True
