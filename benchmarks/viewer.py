"""The viewer's latency as a user feels it, and its screenshots in docs/.

    python benchmarks/viewer.py [--repeats 7] [--cetus-only]

Real echo first: CETUS Patient 7 ED from ``../shared/data/cetus/`` (skipped
when absent; 0.9 mm assumed, as its points file says), with the 3D view on:
base click -> final contour drawn on the slices, the 3D view drawn after
them, and a landmark's drag (release) -> final contour (targets 400 and
300 ms).  Then the demo phantom, as below.

The demo's first frame (``make_sequence(seed=0, n_frames=10, spacing=1.25)``,
the volume ``spheroseg demo`` tracks) is served by ``spheroseg.viewer``; Debian's
Chromium, headless with WebGL on SwiftShader (software rendering: the only
kind on these machines), opens the page at 1100 x 700 and Playwright clicks as a
user would.  Times are the page's own (``performance.now``), from the click's
handler to the surface drawn on screen (a one-pixel ``readPixels`` after
NiiVue's draw, which only returns once the frame is rendered):

- base click -> first surface drawn (the initial half-ellipsoid) and final
  surface drawn: each repeat clears the points and clicks the apex, then the
  base (every other time 1.25 mm higher);
- landmark drag (release) -> final surface drawn;
- ``*_3d``: the 3D view drawn after the slices (it waits until they are still);
- the base click again with the 3D view switched off (``*_slices_only``).

Also when the page had the surface, before drawing it (``*_received``: what a
desktop GPU, drawing in milliseconds, would show), and the segmentation's own
time on the server.  Medians over ``--repeats``.  Writes
docs/viewer.json and the screenshots docs/viewer-*.png (1: loaded, 2:
segmented, 3: landmark added, 4: sequence tracked, 5: CETUS Patient 7
segmented, 6: help).
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from spheroseg.io import save_volume
from spheroseg.synthetic.phantom import make_sequence
from spheroseg.apps.viewer import open_viewer
from spheroseg.apps.viewer.browser import launch, screen_xy, wait_done

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
CETUS = ROOT.parent / "shared" / "data" / "cetus"
WAIT = 120_000


def timing(page, job):
    return page.evaluate(f"viewer.state.timings.find((t) => t.job === {job})")


def move_slices_to(page, point) -> None:
    """Move the slices to ``point``, as scrolling would."""
    page.evaluate("""(mm) => { const nv = viewer.nv; nv.scene.crosshairPos = nv.mm2frac(viewer.toDisplay(mm));
        nv.drawScene(); }""", np.asarray(point, dtype=float).tolist())


def wait_3d(page, job) -> None:
    """Until the 3D view shows job ``job``'s surface (or is off)."""
    page.wait_for_function(f"Number(document.body.dataset.drawn3d || 0) >= {job} || "
                           "!document.getElementById('render3d').checked", polling=50, timeout=WAIT)


def clicks(page, apex, base, repeats, rows, suffix, job, server):
    """Clear, click apex then base (every other time 1 mm higher), ``repeats``
    + 1 times (the first a warm-up); the times in ``rows``."""
    for k in range(repeats + 1):
        sent = int(page.evaluate("Number(document.body.dataset.sent || 0)"))
        page.click("#clear")  # then apex and base clicked anew, as a user starting over
        page.wait_for_function(f"Number(document.body.dataset.sent) > {sent}", polling=50, timeout=WAIT)
        page.mouse.click(*screen_xy(page, 1, apex))
        page.wait_for_function(f"Number(document.body.dataset.sent) > {sent + 1}", polling=50, timeout=WAIT)
        page.mouse.click(*screen_xy(page, 1, base + [0.0, 0.0, 1.0 * (k % 2)]))
        job = wait_done(page, job, timeout_ms=WAIT)
        wait_3d(page, job)
        t = timing(page, job)
        if k:
            rows["base_to_first_ms" + suffix].append(t["first"] - t["click"])
            rows["base_to_final_ms" + suffix].append(t["final"] - t["click"])
            rows["base_to_first_received_ms" + suffix].append(t["firstReceived"] - t["click"])
            rows["base_to_final_received_ms" + suffix].append(t["finalReceived"] - t["click"])
            if t.get("final3d"):
                rows["base_to_3d_ms" + suffix].append(t["final3d"] - t["click"])
            rows["segment_ms" + suffix].append(1000 * server.session.results[0][1].seconds)
    return job


def drags(page, server, repeats, rows, suffix, job, offset=3.0):
    """A landmark ``offset`` mm outside the wall half way up, then dragged
    back and forth by 2.5 mm along z ``repeats`` times."""
    session = server.session
    surface = session.results[0][1].surface
    mid = 0.5 * (session.points.apex + session.points.base)
    points = surface.mesh(96, 48)[0]
    y = page.evaluate("viewer.crosshairLPS()")[1]
    near = points[(np.abs(points[:, 1] - y) < 1.5) & (np.abs(points[:, 2] - mid[2]) < 3.0)]
    rim = near[np.argmax(np.abs(near[:, 0] - mid[0]))]
    landmark = rim + [offset * np.sign(rim[0] - mid[0]), 0.0, 0.0]
    landmark[1] = y
    page.keyboard.down("Shift")
    page.mouse.click(*screen_xy(page, 1, landmark))
    page.keyboard.up("Shift")
    job = wait_done(page, job, timeout_ms=WAIT)
    for k in range(repeats):
        now = session.points.landmarks[0]
        page.mouse.move(*screen_xy(page, 1, now))
        page.mouse.down()
        page.mouse.move(*screen_xy(page, 1, now + [0.0, 0.0, 2.5 if k % 2 == 0 else -2.5]), steps=3)
        page.mouse.up()
        job = wait_done(page, job, timeout_ms=WAIT)
        t = timing(page, job)
        rows["drag_to_final_ms" + suffix].append(t["final"] - t["click"])
        rows["drag_to_final_received_ms" + suffix].append(t["finalReceived"] - t["click"])
        rows["drag_segment_ms" + suffix].append(1000 * session.results[0][1].seconds)
    return job


def cetus(browser, folder, repeats, rows) -> dict | None:
    """CETUS Patient 7 ED at 0.9 mm, the 3D view on."""
    if not (CETUS / "Patient7_points.json").is_file():
        return None
    from spheroseg.volumes.volume import Volume

    marks = json.loads((CETUS / "Patient7_points.json").read_text())
    spacing = marks["assumed_spacing_mm"]
    array = np.load(CETUS / marks["ED"]["file"])
    save_volume(folder / "p7.mha", Volume(array.astype(np.float32), spacing=(spacing,) * 3))
    apex, base = (np.array(marks["ED"][k][::-1], dtype=float) * spacing for k in ("apex_index", "base_index"))
    base[1] = apex[1]  # both clicked on the coronal slice through the apex
    server = open_viewer(folder / "p7.mha", save_root=folder)
    server.serve_in_thread()
    page = browser.new_page(viewport={"width": 1100, "height": 700})
    page.goto(server.url)
    page.wait_for_function("document.body.dataset.state === 'ready'", polling=50, timeout=WAIT)
    move_slices_to(page, apex)
    job = clicks(page, apex, base, repeats, rows, "_cetus", 0, server)
    move_slices_to(page, 0.5 * (apex + base))
    wait_3d(page, job)
    page.wait_for_timeout(1500)
    page.screenshot(path=str(DOCS / "viewer-5-cetus.png"))
    drags(page, server, repeats, rows, "_cetus", job, offset=3.0)
    volume_ml = server.session.results[0][1].surface.volume_ml()
    page.close()
    server.close()
    return {"cetus_p7_ed_ml_with_landmark": volume_ml}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--cetus-only", action="store_true", help="CETUS Patient 7 only")
    args = parser.parse_args()
    from playwright.sync_api import sync_playwright

    folder = Path(tempfile.mkdtemp(prefix="spheroseg-viewer-bench-"))
    seq = make_sequence(seed=0, n_frames=10, spacing=1.25)
    save_volume(folder / "demo-frame0.mha", seq.volumes[0])
    save_volume(folder / "demo.nrrd", list(seq.volumes))
    first = seq.frames[0]
    keys = ("base_to_first_ms", "base_to_final_ms", "base_to_3d_ms", "base_to_first_received_ms",
            "base_to_final_received_ms", "segment_ms", "drag_to_final_ms", "drag_to_final_received_ms",
            "drag_segment_ms")
    rows = {k + suffix: [] for k in keys for suffix in ("", "_slices_only", "_cetus")}
    extra = {}
    with sync_playwright() as p:
        browser = launch(p)
        version = browser.version
        extra = cetus(browser, folder, args.repeats, rows) or {}
        if args.cetus_only:
            browser.close()
            report(args, version, None, rows, None, extra)
            return
        server = open_viewer(folder / "demo-frame0.mha", save_root=folder)
        server.serve_in_thread()
        page = browser.new_page(viewport={"width": 1100, "height": 700})
        t0 = time.perf_counter()
        page.goto(server.url)
        page.wait_for_function("document.body.dataset.state === 'ready'", polling=50, timeout=WAIT)
        ready_s = time.perf_counter() - t0
        page.screenshot(path=str(DOCS / "viewer-1-loaded.png"))
        job = clicks(page, first.apex, first.base, args.repeats, rows, "", 0, server)
        page.screenshot(path=str(DOCS / "viewer-2-segmented.png"))
        page.click("#render3d")  # the 3D view off: the three slices alone
        page.wait_for_timeout(500)
        job = clicks(page, first.apex, first.base, args.repeats, rows, "_slices_only", job, server)
        page.click("#render3d")
        page.wait_for_timeout(500)
        wait_3d(page, drags(page, server, args.repeats, rows, "", job))
        page.screenshot(path=str(DOCS / "viewer-3-landmark.png"))
        page.keyboard.press("?")
        page.screenshot(path=str(DOCS / "viewer-6-help.png"))
        server.close()
        # the sequence, tracked
        server = open_viewer(folder / "demo.nrrd", save_root=folder)
        server.serve_in_thread()
        page = browser.new_page(viewport={"width": 1100, "height": 700})
        page.goto(server.url)
        page.wait_for_function("document.body.dataset.state === 'ready'", polling=50, timeout=WAIT)
        page.mouse.click(*screen_xy(page, 1, first.apex))
        page.mouse.click(*screen_xy(page, 1, first.base))
        wait_done(page, 0, timeout_ms=WAIT)
        page.click("#track")
        page.wait_for_function("viewer.state.tracking !== null", polling=50, timeout=WAIT)
        es = page.evaluate("viewer.state.tracking.es_frame")
        page.evaluate(f"document.getElementById('frame').value = '{es}'; "
                      "document.getElementById('frame').dispatchEvent(new Event('input'))")
        page.wait_for_function(f"viewer.state.frame === {es} && viewer.state.shown !== null", polling=50,
                               timeout=WAIT)
        page.wait_for_timeout(500)
        page.screenshot(path=str(DOCS / "viewer-4-tracked.png"))
        tracking = page.evaluate("viewer.state.tracking")
        server.close()
        browser.close()
    shutil.rmtree(folder, ignore_errors=True)
    report(args, version, ready_s, rows, tracking["ef_percent"], extra)


def report(args, version, ready_s, rows, ef_percent, extra) -> None:
    medians = {k: float(np.median(v)) for k, v in rows.items() if v}
    result = {
        "command": "python benchmarks/viewer.py --repeats %d" % args.repeats + (" --cetus-only" if args.cetus_only
                                                                                  else ""),
        "date": time.strftime("%Y-%m-%d"),
        "machine": f"{platform.machine()}, {__import__('os').cpu_count()} cores, Chromium {version} headless, "
                   "WebGL on SwiftShader (software)",
        "load_average_1min": __import__("os").getloadavg()[0],
        "viewport": [1100, 700], "page_ready_s": ready_s, "medians_ms": medians,
        "runs_ms": {k: v for k, v in rows.items() if v}, "tracked_ef_percent": ef_percent, **extra,
    }
    (DOCS / "viewer.json").write_text(json.dumps(result, indent=1))
    print(json.dumps({"page_ready_s": ready_s, **medians, **extra}, indent=1))

if __name__ == "__main__":
    main()
