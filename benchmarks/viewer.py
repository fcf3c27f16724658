"""The viewer's latency as a user feels it, and its screenshots in docs/.

    python benchmarks/viewer.py [--repeats 7]

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
- the base click again with the 3D view switched off (``*_slices_only``).

Also when the page had the surface, before drawing it (``*_received``: what a
desktop GPU, drawing in milliseconds, would show), and the segmentation's own
time on the server.  Medians over ``--repeats``.  Writes
docs/viewer.json and the screenshots docs/viewer-*.png (1: loaded, 2:
segmented, 3: landmark added, 4: sequence tracked).
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
from spheroseg.phantom import make_sequence
from spheroseg.viewer import open_viewer
from spheroseg.viewer.browser import launch, screen_xy, wait_done

DOCS = Path(__file__).resolve().parents[1] / "docs"
WAIT = 120_000


def timing(page, job):
    return page.evaluate(f"viewer.state.timings.find((t) => t.job === {job})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    from playwright.sync_api import sync_playwright

    folder = Path(tempfile.mkdtemp(prefix="spheroseg-viewer-bench-"))
    seq = make_sequence(seed=0, n_frames=10, spacing=1.25)
    save_volume(folder / "demo-frame0.mha", seq.volumes[0])
    save_volume(folder / "demo.nrrd", list(seq.volumes))
    first = seq.frames[0]
    rows = {"base_to_first_ms": [], "base_to_final_ms": [], "drag_to_final_ms": [], "segment_ms": [],
            "drag_segment_ms": [], "base_to_first_received_ms": [], "base_to_final_received_ms": [],
            "drag_to_final_received_ms": [], **{k + "_slices_only": [] for k in (
                "base_to_first_ms", "base_to_final_ms", "base_to_first_received_ms", "base_to_final_received_ms")}}
    server = open_viewer(folder / "demo-frame0.mha", save_root=folder)
    server.serve_in_thread()
    with sync_playwright() as p:
        browser = launch(p)
        version = browser.version
        page = browser.new_page(viewport={"width": 1100, "height": 700})
        t0 = time.perf_counter()
        page.goto(server.url)
        page.wait_for_function("document.body.dataset.state === 'ready'", polling=50, timeout=WAIT)
        ready_s = time.perf_counter() - t0
        page.screenshot(path=str(DOCS / "viewer-1-loaded.png"))
        job = 0
        for k in range(2 * args.repeats + 2):  # the first of each layout is a warm-up
            layout = "slices" if k > args.repeats else "3d"
            if k == args.repeats + 1:
                page.click("#render3d")  # the 3D view off: the three slices alone
                page.wait_for_timeout(500)
            sent = int(page.evaluate("Number(document.body.dataset.sent || 0)"))
            page.click("#clear")  # then apex and base clicked anew, as a user starting over
            page.wait_for_function(f"Number(document.body.dataset.sent) > {sent}", polling=50, timeout=WAIT)
            page.mouse.click(*screen_xy(page, 1, first.apex))
            page.wait_for_function(f"Number(document.body.dataset.sent) > {sent + 1}", polling=50, timeout=WAIT)
            page.mouse.click(*screen_xy(page, 1, first.base + [0.0, 0.0, 1.25 * (k % 2)]))
            job = wait_done(page, job, timeout_ms=WAIT)
            t = timing(page, job)
            if k not in (0, args.repeats + 1):
                suffix = "" if layout == "3d" else "_slices_only"
                rows["base_to_first_ms" + suffix].append(t["first"] - t["click"])
                rows["base_to_final_ms" + suffix].append(t["final"] - t["click"])
                rows["base_to_first_received_ms" + suffix].append(t["firstReceived"] - t["click"])
                rows["base_to_final_received_ms" + suffix].append(t["finalReceived"] - t["click"])
                rows["segment_ms"].append(1000 * server.session.results[0][1].seconds)
            if k == args.repeats:
                page.screenshot(path=str(DOCS / "viewer-2-segmented.png"))
        page.click("#render3d")
        page.wait_for_timeout(500)
        # a landmark on the wall, half way up; then dragged back and forth by 2.5 mm
        surface = server.session.results[0][1].surface
        mid = 0.5 * (server.session.points.apex + server.session.points.base)
        points = surface.mesh(96, 48)[0]
        y = server.session.points.apex[1]
        near = points[(np.abs(points[:, 1] - y) < 1.5) & (np.abs(points[:, 2] - mid[2]) < 3.0)]
        rim = near[np.argmax(np.abs(near[:, 0] - mid[0]))]
        landmark = rim + [3.0 * np.sign(rim[0] - mid[0]), 0.0, 0.0]
        page.keyboard.down("Shift")
        page.mouse.click(*screen_xy(page, 1, landmark))
        page.keyboard.up("Shift")
        job = wait_done(page, job, timeout_ms=WAIT)
        page.screenshot(path=str(DOCS / "viewer-3-landmark.png"))
        for k in range(args.repeats):
            now = server.session.points.landmarks[0]
            page.mouse.move(*screen_xy(page, 1, now))
            page.mouse.down()
            page.mouse.move(*screen_xy(page, 1, now + [0.0, 0.0, 2.5 if k % 2 == 0 else -2.5]), steps=3)
            page.mouse.up()
            job = wait_done(page, job, timeout_ms=WAIT)
            t = timing(page, job)
            rows["drag_to_final_ms"].append(t["final"] - t["click"])
            rows["drag_to_final_received_ms"].append(t["finalReceived"] - t["click"])
            rows["drag_segment_ms"].append(1000 * server.session.results[0][1].seconds)
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
    medians = {k: float(np.median(v)) for k, v in rows.items()}
    result = {
        "command": "python benchmarks/viewer.py --repeats %d" % args.repeats, "date": time.strftime("%Y-%m-%d"),
        "machine": f"{platform.machine()}, {__import__('os').cpu_count()} cores, Chromium {version} headless, "
                   "WebGL on SwiftShader (software)",
        "viewport": [1100, 700], "page_ready_s": ready_s, "medians_ms": medians,
        "runs_ms": rows, "tracked_ef_percent": tracking["ef_percent"],
    }
    (DOCS / "viewer.json").write_text(json.dumps(result, indent=1))
    print(json.dumps({"page_ready_s": ready_s, **medians}, indent=1))


if __name__ == "__main__":
    main()
