"""Driving the viewer's page from Python with Playwright (the browser tests
and ``benchmarks/viewer.py``): Debian's Chromium, headless, WebGL on
SwiftShader.  Needs ``spheroseg[browser]`` and a ``chromium`` on PATH."""

from __future__ import annotations

import shutil

import numpy as np

#: flags for Chromium as root with no network and no GPU (WebGL on SwiftShader)
CHROMIUM_ARGS = ["--no-sandbox", "--disable-dev-shm-usage", "--disable-quic", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run", "--use-angle=swiftshader",
                 "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]


def launch(playwright, *, executable: str | None = None):
    """A headless Chromium from ``playwright`` (``sync_playwright()``'s
    object): the ``chromium`` on PATH unless ``executable`` is given
    (Playwright's own browser download is never used)."""
    executable = executable or shutil.which("chromium")
    if executable is None:
        raise FileNotFoundError("no chromium on PATH (Debian: apt-get install chromium)")
    return playwright.chromium.launch(executable_path=executable, headless=True, args=CHROMIUM_ARGS)


def screen_xy(page, tile: int, point) -> tuple[float, float]:
    """Page coordinates (CSS pixels) of the world point ``point`` (LPS mm) on
    a slice tile (0 axial, 1 coronal, 2 sagittal), from NiiVue's layout of it
    (in the page's current orientation)."""
    return tuple(page.evaluate(
        """([kind, lps]) => {
            const mm = viewer.toDisplay(lps);
            const tile = viewer.sliceTiles().find((t) => t.axCorSag === kind);
            const plane = [[0, 1], [0, 2], [1, 2]][kind];
            const canvas = document.getElementById('gl');
            const r = canvas.getBoundingClientRect();
            const s = viewer.toScreen(tile, mm[plane[0]], mm[plane[1]]);
            return [r.left + s[0] * r.width / canvas.width, r.top + s[1] * r.height / canvas.height];
        }""", [tile, np.asarray(point, dtype=float).tolist()]))


def wait_done(page, after: int = 0, *, timeout_ms: float = 120_000) -> int:
    """Wait until the page shows the final surface of a job numbered above
    ``after``; its number.  ``AssertionError`` with the page's status if it
    shows an error instead."""
    page.wait_for_function(
        f"document.body.dataset.state === 'error' || (document.body.dataset.state === 'done' && "
        f"Number(document.body.dataset.job) > {after})", polling=50, timeout=timeout_ms)
    assert page.evaluate("document.body.dataset.state") == "done", page.text_content("#status")
    return int(page.evaluate("document.body.dataset.job"))
