"""Notebook 05 in JupyterLab (Debian's Chromium through playwright, as ``test_browser.py``): the two-run table and
the patch map render, a box selection on the map fills the patch grid, a click on a point opens its recording at its
frame in the inline viewer, and a colour change redraws the map (timed in the page with ``performance.now()``).

Screenshots: ``test-artifacts/screenshots/notebook05_table.png``, ``notebook05_map.png``, ``notebook05_selected.png``,
``notebook05_open.png``; ``docs/two_runs.png`` must look like the table's and ``docs/patch_map.png`` like the selected
one's region from the colour menu to the grid's first row (refresh them with ``MASSVIZ_REFRESH_DOCS=1``). The redraw times go to ``browser_timings.json`` (``patch_map_redraw_ms``).
"""
from __future__ import annotations

import re
import statistics
import time

import cv2
import numpy as np
import pytest

from browser_support import (
    BENIGN,
    check_docs_picture,
    offline_page,
    open_and_run,
    record_timing,
    settle,
    shot,
    wait_for_image,
)

pytestmark = [pytest.mark.browser, pytest.mark.slow]  # ~90 s on 2 cores: JupyterLab, a kernel, the inline viewer

MAP = ".massviz-patch-map"
POINTS = f"{MAP} .scatterlayer path.point"
#: the first colour change after this records when the map's points change colour (``window.__redraw``)
WATCH = """(sel) => { window.__t0 = null; window.__t1 = null;
  const s = document.querySelector(sel);
  s.addEventListener('change', () => { if (window.__t0 === null) window.__t0 = performance.now(); },
                     {capture: true, once: true});
  const layer = document.querySelector('.massviz-patch-map .scatterlayer');
  const obs = new MutationObserver(() => { if (window.__t0 !== null && window.__t1 === null) {
      window.__t1 = performance.now(); obs.disconnect(); } });
  obs.observe(layer, {attributes: true, subtree: true, attributeFilter: ['style']}); }"""


def settle_clip(page, name: str, clip: dict, timeout: float = 10.0) -> np.ndarray:
    """Screenshots of the page's region ``clip`` until two in a row are the same (or ``timeout``), saved as
    ``name``."""
    from browser_support import ARTIFACTS, picture_difference

    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    path = ARTIFACTS / f"{name}.png"
    t0, before = time.monotonic(), None
    while True:
        page.screenshot(path=str(path), clip=clip)
        now = cv2.imread(str(path))
        if before is not None and (picture_difference(before, now, panel=1.0) <= 2.0 or
                                   time.monotonic() - t0 > timeout):
            return now
        before = now
        page.wait_for_timeout(1000)


def test_notebook_05_map_selection_and_open_in_the_browser(browser, lab, samples_dir):
    from massviz.io.recording import open_recording

    with offline_page(browser, {"width": 1280, "height": 1700}) as (page, messages, _):
        seconds = open_and_run(page, lab, "05_two_runs_and_patch_map.ipynb", upto="pitcher = pmap.patches")
        table = page.locator(".massviz-runs").first
        table.wait_for(state="visible", timeout=60_000)
        page.wait_for_function("() => (document.querySelector('.massviz-runs-count') || {}).innerText === "
                               "'3 of 3 recordings'", timeout=30_000)
        rows = table.locator("table.massviz-runs-table").first.locator("tbody tr")
        assert rows.count() == 3 and "cup_handover" in rows.first.inner_text()  # the largest change first
        table.scroll_into_view_if_needed()
        check_docs_picture(settle(page, "notebook05_table", locator=table, timeout=5), "two_runs.png", panel=1.0)

        page.wait_for_function("(s) => document.querySelectorAll(s).length === 30", arg=POINTS, timeout=60_000)
        pmap = page.locator(MAP).first
        pmap.scroll_into_view_if_needed()
        plot = page.locator(f"{MAP} .js-plotly-plot").first
        shot(page, "notebook05_map", plot)
        note = page.locator(".massviz-map-note").first
        assert "select a region" in note.inner_text() and page.locator(".massviz-map-tile").count() == 0

        # a click on point 5 (run A's cup_handover ★0, frame 9): the viewer shows that recording at that frame.
        # Before the selection: a selection's outline takes the clicks inside it (a double click clears it)
        plot.scroll_into_view_if_needed()
        box = page.locator(POINTS).nth(5).bounding_box()
        x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
        page.mouse.move(x - 20, y - 20)
        page.mouse.move(x, y, steps=5)  # hover first, as a person's pointer does
        page.wait_for_timeout(300)
        page.mouse.down()
        page.mouse.up()
        page.wait_for_function("() => /opened \\S+ at frame \\d+/.test(document.querySelector("
                               "'.massviz-map-note').innerText)", timeout=30_000)
        opened = re.search(r"opened (\S+) at frame (\d+)", note.inner_text())
        canvas = page.locator(f"{MAP} canvas").first
        canvas.wait_for(state="visible", timeout=120_000)
        canvas.scroll_into_view_if_needed()
        rgb = cv2.cvtColor(open_recording(samples_dir / "cup_handover").read_frame(9).rgb, cv2.COLOR_RGB2BGR)
        match = wait_for_image(page, "notebook05_open", canvas, rgb, np.arange(0.2, 1.01, 0.02), 90)

        # a box over the left half of the plot: the grid shows the points inside it
        plot.scroll_into_view_if_needed()
        area = page.locator(f"{MAP} .nsewdrag").first.bounding_box()
        x1, y1 = area["x"] + 2, area["y"] + 2
        x2, y2 = area["x"] + area["width"] / 2, area["y"] + area["height"] - 2
        inside = page.evaluate("""([s, x1, y1, x2, y2]) => [...document.querySelectorAll(s)].filter(p => {
              const r = p.getBoundingClientRect(), x = r.x + r.width / 2, y = r.y + r.height / 2;
              return x > x1 && x < x2 && y > y1 && y < y2; }).length""", [POINTS, x1, y1, x2, y2])
        assert 0 < inside < 30, inside
        page.mouse.move(x1, y1)
        page.mouse.down()
        page.mouse.move(x2, y2, steps=12)
        page.mouse.up()
        page.wait_for_function("(n) => document.querySelectorAll('.massviz-map-tile').length === n", arg=inside,
                               timeout=30_000)
        page.wait_for_function("(n) => document.querySelector('.massviz-map-note').innerText.startsWith("
                               "n + ' patches selected')", arg=inside, timeout=30_000)
        page.wait_for_function("""() => [...document.querySelectorAll('.massviz-map-tile img')].every(
            i => i.complete && i.naturalWidth > 0)""", timeout=30_000)
        # the map, its colouring and the first row of the selected patches: docs/patch_map.png
        page.locator(f"{MAP} .widget-dropdown").first.evaluate("e => e.scrollIntoView({block: 'start'})")
        page.wait_for_timeout(500)
        top = page.locator(f"{MAP} .widget-dropdown").first.bounding_box()
        tile = page.locator(".massviz-map-tile").first.bounding_box()  # down to the grid's first row
        clip = {"x": top["x"] - 8, "y": top["y"] - 4, "width": 900, "height": tile["y"] + tile["height"] - top["y"] + 10}
        check_docs_picture(settle_clip(page, "notebook05_selected", clip), "patch_map.png", panel=1.0)

        # colour changes, timed in the page: from the dropdown's change to the points' new colours
        colour = page.locator(f"{MAP} .widget-dropdown select").first
        redraw = []
        for label in ("flag", "run", "class", "relative error", "flag", "run"):
            page.evaluate(WATCH, f"{MAP} .widget-dropdown select")
            colour.select_option(label=label)
            page.wait_for_function("() => window.__t1 !== null", timeout=30_000)
            redraw.append(page.evaluate("() => window.__t1 - window.__t0"))
        record_timing("patch_map_redraw_ms", [round(v, 1) for v in redraw])

        errors = [m for t, m in messages if t in ("error", "pageerror") and not BENIGN.search(m)]
    print(f"notebook 05 in the browser: ran in {seconds:.0f} s; box selection: {inside} patches in the grid; "
          f"colour redraw in the page (ms): {[round(v) for v in redraw]}, median {statistics.median(redraw):.0f}; "
          f"click: {opened.group(0)}, its frame in the viewer with correlation {match:.2f}")
    assert opened.groups() == ("cup_handover", "9")
    assert match >= 0.6, f"the click did not show cup_handover's frame 9 (best match {match:.2f}; notebook05_open.png)"
    assert all(v > 0 for v in redraw)
    assert not [m for m in errors if not m.startswith("Failed to load resource")], errors
