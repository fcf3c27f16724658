"""The viewer's page driven in headless Chromium (Debian's ``chromium`` and
Python Playwright), as a user would: click apex and base on the slices, watch
the contour, add, drag, delete and undo a landmark, track, save.

Outside CI these tests skip when no Chromium or Playwright is installed;
under CI (``CI=true``) a missing browser fails them, so a green run means the
page was driven.  Screenshots of each step go to pytest's temporary folder
(``benchmarks/viewer.py`` writes the ones in ``docs/``).
"""

import base64
import json
import os
import shutil

import numpy as np
import pytest
import SimpleITK as sitk

import spheroseg
from spheroseg.fit import point_to_surface_distance
from spheroseg.io import save_volume
from spheroseg.metrics import dice
from spheroseg.phantom import make_phantom, make_sequence, tilted_mitral_scene
from spheroseg.viewer import open_viewer
from spheroseg.viewer.browser import launch, screen_xy, wait_done
from spheroseg.viewer.session import lps_to_ras, ras_to_lps

TIMEOUT_MS = 120_000


def _missing_browser(reason: str):
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(f"CI=true but {reason}: .ci/run installs Debian's chromium and playwright")
    pytest.skip(reason)


@pytest.fixture(scope="module")
def browser():
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        _missing_browser("Python Playwright is not installed")
    if shutil.which("chromium") is None:
        _missing_browser("no chromium on PATH")
    with sync_playwright() as p:
        browser = launch(p)
        yield browser
        browser.close()


def open_page(browser, server):
    page = browser.new_page(viewport={"width": 1100, "height": 700})
    errors = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(server.url)
    page.wait_for_function("['ready', 'error'].includes(document.body.dataset.state)", polling=100,
                           timeout=TIMEOUT_MS)
    assert page.evaluate("document.body.dataset.state") == "ready", page.text_content("#status")
    assert page.url.endswith("/"), "the token should leave the address bar for a cookie"
    return page, errors


def crosshair_lps(page) -> np.ndarray:
    return ras_to_lps(page.evaluate("viewer.crosshairMM()"))


@pytest.fixture(scope="module")
def phantom_file(tmp_path_factory):
    ph = make_phantom(seed=1, spacing=1.5)
    path = tmp_path_factory.mktemp("viewer") / "phantom.mha"
    save_volume(path, ph.volume)
    return ph, path


def test_click_segment_landmark_drag_undo_save(browser, phantom_file, tmp_path):
    ph, path = phantom_file
    server = open_viewer(path, save_root=tmp_path)
    server.serve_in_thread()
    try:
        page, errors = open_page(browser, server)
        page.screenshot(path=str(tmp_path / "1-loaded.png"))
        # the apex and the base clicked on the coronal slice through the volume's centre
        page.mouse.click(*screen_xy(page, 1, ph.apex))
        page.wait_for_function("Number(document.body.dataset.sent) >= 1", polling=100, timeout=TIMEOUT_MS)
        # a click moves the slices to the clicked point, as NiiVue's own cursor: both agree
        clicked = server.session.points.apex
        assert clicked is not None and np.linalg.norm(clicked - ph.apex) < 1.0
        np.testing.assert_allclose(crosshair_lps(page)[[0, 2]], clicked[[0, 2]], atol=1.6)
        page.mouse.click(*screen_xy(page, 1, ph.base))
        job = wait_done(page)
        page.screenshot(path=str(tmp_path / "2-segmented.png"))
        session = server.session
        apex, base = session.points.apex, session.points.base
        assert np.linalg.norm(base - ph.base) < 1.0
        # what the page shows is spheroseg.segment with the same points
        api = spheroseg.segment(session.frames[0], apex, base)
        result = session.results[0][1]
        np.testing.assert_allclose(result.surface.coefficients, api.surface.coefficients, rtol=0, atol=1e-9)
        vertices = np.frombuffer(base64.b64decode(page.evaluate(
            "btoa(String.fromCharCode(...new Uint8Array(viewer.state.shown.buffer)))")), "<f4").reshape(-1, 3)
        np.testing.assert_allclose(ras_to_lps(vertices), api.surface.mesh(48, 24)[0], atol=1e-3)
        # the contour is drawn: yellow pixels on the overlay
        yellow = page.evaluate("""() => { const c = document.getElementById('overlay');
            const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; let n = 0;
            for (let i = 0; i < d.length; i += 4) if (d[i] > 200 && d[i + 1] > 170 && d[i + 2] < 120) n++; return n; }""")
        assert yellow > 500

        # a landmark 4 mm outside the wall, half way up, shift-clicked on the coronal slice
        # (the wall's point on the coronal slice, half way up, farthest from the axis in x)
        mid = 0.5 * (apex + base)
        points = api.surface.mesh(96, 48)[0]
        plane = crosshair_lps(page)[1]
        near = points[(np.abs(points[:, 1] - plane) < 1.5) & (np.abs(points[:, 2] - mid[2]) < 3.0)]
        rim = near[np.argmax(np.abs(near[:, 0] - mid[0]))]
        wanted = rim + [4.0 * np.sign(rim[0] - mid[0]), 0.0, 0.0]
        wanted[1] = plane
        page.keyboard.down("Shift")
        page.mouse.click(*screen_xy(page, 1, wanted))
        page.keyboard.up("Shift")
        job = wait_done(page, job)
        landmark = session.points.landmarks[0]
        assert np.linalg.norm(landmark - wanted) < 1.0
        result = session.results[0][1]
        assert point_to_surface_distance(landmark[None], result.surface)[0] < 1.0
        page.screenshot(path=str(tmp_path / "3-landmark.png"))

        # drag it 5 mm further along z
        start = screen_xy(page, 1, landmark)
        end = screen_xy(page, 1, landmark + [0, 0, 5.0])
        page.mouse.move(*start)
        page.mouse.down()
        page.mouse.move(*end, steps=5)
        page.mouse.up()
        job = wait_done(page, job)
        dragged = session.points.landmarks[0]
        assert abs(dragged[2] - landmark[2] - 5.0) < 1.0 and np.linalg.norm(dragged[:2] - landmark[:2]) < 1.0
        assert point_to_surface_distance(dragged[None], session.results[0][1].surface)[0] < 1.0
        page.screenshot(path=str(tmp_path / "4-dragged.png"))

        # undo puts it back; Delete removes the selected landmark, and the surface follows
        page.click("#undo")
        job = wait_done(page, job)
        np.testing.assert_allclose(session.points.landmarks[0], landmark)
        page.mouse.click(*screen_xy(page, 1, landmark))  # selects it
        page.keyboard.press("Delete")
        job = wait_done(page, job)
        assert len(session.points.landmarks) == 0
        np.testing.assert_allclose(session.results[0][1].surface.coefficients, api.surface.coefficients, atol=1e-9)

        # put the dragged landmark back (undo twice: the deletion, then nothing else) and save
        page.click("#undo")
        job = wait_done(page, job)
        page.fill("#folder", "saved/case1")
        page.click("#save")
        page.wait_for_function("document.body.dataset.saved || document.body.dataset.state === 'error'",
                               polling=100, timeout=TIMEOUT_MS)
        folder = tmp_path / "saved" / "case1"
        assert page.evaluate("document.body.dataset.saved") == str(folder)
        points = spheroseg.io.read_markups(folder / "points.mrk.json")
        np.testing.assert_allclose(points["apex"], apex)
        np.testing.assert_allclose(points["landmarks"], session.points.landmarks)
        again = spheroseg.segment(session.frames[0], points["apex"], points["base"], landmarks=points["landmarks"])
        saved = sitk.GetArrayFromImage(sitk.ReadImage(str(folder / "mask.mha"))).astype(bool)
        np.testing.assert_array_equal(saved, again.mask(session.frames[0]))
        for name in ("mesh.vtk", "mesh.ply", "surface.json", "surface.exnode", "results.json", "report.png"):
            assert (folder / name).is_file(), name
        # saving again into the same folder is refused, in the page, and nothing is overwritten
        page.evaluate("delete document.body.dataset.saved")
        page.click("#save")
        page.wait_for_function("document.body.dataset.state === 'error'", polling=100, timeout=TIMEOUT_MS)
        assert "exists" in page.text_content("#saved")
        page.screenshot(path=str(tmp_path / "5-saved.png"))
        assert errors == []
    finally:
        server.close()


def test_sequence_track_slider_and_curve(browser, tmp_path):
    seq = make_sequence(seed=2, n_frames=4, spacing=2.0)
    path = tmp_path / "cine.nrrd"
    save_volume(path, list(seq.volumes))
    server = open_viewer(path, save_root=tmp_path)
    server.serve_in_thread()
    try:
        page, errors = open_page(browser, server)
        assert page.is_visible("#sequence")
        first = seq.frames[0]
        page.mouse.click(*screen_xy(page, 1, first.apex))
        page.mouse.click(*screen_xy(page, 1, first.base))
        wait_done(page)
        page.click("#track")
        page.wait_for_function("document.body.dataset.state === 'error' || viewer.state.tracking !== null",
                               polling=100, timeout=TIMEOUT_MS)
        session = server.session
        apex, base = session.points.apex, session.points.base
        api = spheroseg.track(session.frames, apex, base)
        tracking = page.evaluate("viewer.state.tracking")
        np.testing.assert_allclose(tracking["volumes_ml"], api.volumes_ml, rtol=1e-9)
        assert tracking["ef_percent"] == pytest.approx(api.ef, rel=1e-9)
        assert f"EF {api.ef:.1f} %" in page.text_content("#indices")
        # the slider shows each frame's surface
        page.evaluate("document.getElementById('frame').value = '2'; document.getElementById('frame')"
                      ".dispatchEvent(new Event('input'))")
        page.wait_for_function("viewer.state.frame === 2 && viewer.state.shown !== null", polling=100,
                               timeout=TIMEOUT_MS)
        assert page.evaluate("viewer.nv.volumes[0].frame4D") == 2
        frame_volume = float(page.text_content("#volume").split()[0])
        assert frame_volume == pytest.approx(api.volumes_ml[2], abs=0.05)
        page.screenshot(path=str(tmp_path / "6-tracked.png"))
        # Play steps through the frames, Pause stops
        page.click("#play")
        page.wait_for_function("viewer.state.frame !== 2", polling=100, timeout=TIMEOUT_MS)
        page.click("#play")
        assert page.text_content("#play") == "Play"
        stopped = page.evaluate("viewer.state.frame")
        page.wait_for_timeout(600)
        assert page.evaluate("viewer.state.frame") == stopped
        page.fill("#folder", "cine-out")
        page.click("#save")
        page.wait_for_function("document.body.dataset.saved || document.body.dataset.state === 'error'",
                               polling=100, timeout=TIMEOUT_MS)
        saved = json.loads((tmp_path / "cine-out" / "results.json").read_text())
        assert saved["ef_percent"] == pytest.approx(api.ef, rel=1e-9)
        assert len(list((tmp_path / "cine-out" / "masks").iterdir())) == 4
        assert errors == []
    finally:
        server.close()


def test_annulus_points_close_the_cavity_at_their_plane(browser, tmp_path):
    """Apex, then three points of a mitral ring tilted 10 degrees, each clicked
    on the coronal slice through it (scrolled there first, as a user would)."""
    scene = tilted_mitral_scene(10.0)
    path = tmp_path / "tilted.mha"
    save_volume(path, scene.volume)
    server = open_viewer(path, save_root=tmp_path)
    server.serve_in_thread()
    try:
        page, errors = open_page(browser, server)

        def click_on_its_slice(point):
            page.evaluate("""(mm) => { const nv = viewer.nv;
                nv.scene.crosshairPos = nv.mm2frac(mm); nv.drawScene(); }""", lps_to_ras(point).tolist())
            page.mouse.click(*screen_xy(page, 1, point))

        click_on_its_slice(scene.apex)
        page.wait_for_function("Number(document.body.dataset.sent) >= 1", polling=100, timeout=TIMEOUT_MS)
        page.click("button[data-mode=annulus]")
        for k, point in enumerate(scene.annulus[[0, 3, 5]]):
            click_on_its_slice(point)
            if k < 2:
                page.wait_for_function(f"Number(document.body.dataset.sent) >= {k + 2}", polling=100,
                                       timeout=TIMEOUT_MS)
        wait_done(page)
        session = server.session
        assert session.points.base is None and len(session.points.annulus) == 3
        np.testing.assert_allclose(session.points.annulus, scene.annulus[[0, 3, 5]], atol=1.0)
        api = spheroseg.segment(session.frames[0], session.points.apex, annulus=session.points.annulus)
        np.testing.assert_allclose(session.results[0][1].surface.coefficients, api.surface.coefficients, atol=1e-9)
        assert dice(api.mask(scene.volume), scene.truth_mask) > 0.9
        page.screenshot(path=str(tmp_path / "7-annulus.png"))
        assert errors == []
    finally:
        server.close()
