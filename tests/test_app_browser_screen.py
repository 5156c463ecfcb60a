"""The screen at 1366 × 768 in Chromium: the 2D view docks at 1× so that the 3D view is no
strip, and a gross rigid pose (one plane's wall alone) gets the red banner. Same server and
helpers as ``test_app_browser``; every wait bounded by the test's budget."""

import io
import os
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import free_port
from PIL import Image
from test_app_browser import (
    ARGS,
    BUDGET_S,
    CHROMIUM,
    Deadline,
    click_button,
    playwright,
    set_checkbox,
    start_server,
    us_frame,
    wait_text,
    wait_until,
)

SMALL = {"width": 1366, "height": 768}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    proc, url = start_server(free_port(), tmp_path_factory.mktemp("session"))
    yield {"url": url}
    proc.terminate()
    proc.wait(20)


def test_a_small_window_keeps_the_3d_view_and_a_gross_pose_is_red(server, tmp_path):
    deadline = Deadline(BUDGET_S + 600)  # this module's server starts cold
    shots = Path(os.environ.get("NAVAPP_SCREENSHOTS", tmp_path))
    shots.mkdir(parents=True, exist_ok=True)
    with playwright.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=ARGS)
        page = deadline.open(browser.new_page(viewport=SMALL))
        page.goto(server["url"])
        wait_text(page, r"Ready\.", deadline)

        def widths():
            return page.evaluate("""() => ({
                dock: document.querySelector('iframe').getBoundingClientRect().width,
                canvas: Math.max(...[...document.querySelectorAll('canvas')]
                                 .map(c => c.getBoundingClientRect().width))})""")

        # the 3D canvas: the window less the narrow dock (it is laid out a moment after the dock:
        # the two-worker suite measured 752 px once, right after the dock was narrowed)
        wait_until(page, lambda: widths()["dock"] <= 360 and widths()["canvas"] >= 1366 - 360, deadline,
                   "the 2D view docked at 1× and the 3D canvas beside it")
        us = us_frame(page, deadline)
        wait_until(page, lambda: us.evaluate("document.getElementById('cv').width") <= 300, deadline,
                   "the 2D image at 1× (34 px ruler + 256 px + 4)")
        page.wait_for_timeout(1500)
        page.screenshot(path=shots / "app_1366.png")

        # one plane's posterior wall as the only data, then Rigid: a pose nobody should believe
        click_button(page, "Add this plane's segmentation (simulated)", deadline)
        click_button(page, "Rigid", deadline)
        wait_text(page, r"Registered pose not to be believed", deadline)
        colours = page.get_by_text("Registered pose not to be believed").evaluate_all(
            "es => es.map(e => getComputedStyle(e.closest('div')).backgroundColor)")
        assert "rgb(204, 0, 0)" in colours, colours  # the panel's banner is red
        assert "cover" in page.inner_text("body")
        page.screenshot(path=shots / "app_gross_pose.png")

        # the surgeon scrolls the control panel down to the run table: the warning stays in sight
        # (the panel's banner scrolls away with the panel; the pinned one over the 3D view does not)
        page.evaluate("""() => { for (const e of document.querySelectorAll('*')) {
            const s = getComputedStyle(e);
            if ((s.overflowY === 'auto' || s.overflowY === 'scroll') && e.scrollHeight > e.clientHeight + 20)
                e.scrollTop = e.scrollHeight; } }""")
        # read until it holds (bounded by the test's budget alone): a notification closing above the pinned one
        # slides it up, and CI once read it mid-slide (stop 58)
        def banners():
            return page.evaluate("""() => [...document.querySelectorAll('body *')]
                .filter(e => e.children.length === 0 && /Registered pose not to be believed/.test(e.textContent))
                .map(e => { const r = e.getBoundingClientRect();
                            const hit = document.elementFromPoint(r.left + r.width / 2, r.top + r.height / 2);
                            const what = hit ? `${hit.tagName}.${hit.className}: ${hit.textContent.slice(0, 60)}` : '';
                            return {top: r.top, bottom: r.bottom, on_top: !!hit && (hit === e || e.contains(hit)),
                                    hit: what}; })""")

        def in_sight(seen):
            return any(s["on_top"] and 0 <= s["top"] and s["bottom"] <= SMALL["height"] for s in seen)

        seen = banners()
        while not in_sight(seen) and time.monotonic() < deadline.end:
            page.wait_for_timeout(250)
            seen = banners()
        assert len(seen) >= 2, seen  # the panel's banner and the pinned one
        if not in_sight(seen):
            page.screenshot(path=shots / "app_gross_pose_hidden.png")
        assert in_sight(seen), seen
        assert not all(s["on_top"] for s in seen), f"the panel did not scroll: {seen}"
        # said once over the 3D view, not also in a second red box with the same words
        assert page.get_by_text("Registration: check the fit").count() == 0
        page.screenshot(path=shots / "app_gross_pose_scrolled.png")

        # the error dots leave the registered vessels in sight: the vessels' pixels (with and without
        # them) against those the dots change, the rest of the scene hidden, from the front
        def shot():
            # read once the view has settled (two screenshots a second apart alike): a fixed 2.5 s
            # pause read 15 % in CI beside the other worker, where the settled view gives 4 %
            prev = None
            while True:
                page.wait_for_timeout(1000)
                deadline.left()
                img = np.asarray(Image.open(io.BytesIO(page.screenshot())).convert("RGB"), int)
                if prev is not None and (np.abs(img - prev).sum(2) > 40).mean() < 1e-4:
                    return img
                prev = img

        page.get_by_text("Layers and views").first.click(timeout=deadline.ms())
        for layer in ("Preoperative liver", "Preoperative vessels", "Collected data", "Targets", "Ultrasound plane"):
            set_checkbox(page, layer, False, deadline)
        click_button(page, "Anterior", deadline)
        # only the 3D scene's own pixels count: the panels over it change with the checkboxes
        scene = np.array(page.evaluate("""([w, h]) => {
            const c = [...document.querySelectorAll('canvas')]
                .reduce((a, b) => a.getBoundingClientRect().width >= b.getBoundingClientRect().width ? a : b);
            const cr = c.getBoundingClientRect(), rows = [];
            for (let y = 0; y < h; y++) { const row = [];
                for (let x = 0; x < w; x++) {
                    // the canvas, or a layer over all of it (viser's own), not a panel
                    const e = document.elementFromPoint(x * 8 + 4, y * 8 + 4), r = e && e.getBoundingClientRect();
                    const whole = r && r.width >= cr.width - 1 && r.height >= cr.height - 1;
                    row.push(e && (e === c || e.contains(c) || whole) ? 1 : 0); }
                rows.push(row); }
            return rows; }""", [-(-SMALL["width"] // 8), -(-SMALL["height"] // 8)]), bool)
        scene = np.kron(scene, np.ones((8, 8), bool))

        def moved(x, y):
            return int(((np.abs(x - y).sum(2) > 40) & scene[:x.shape[0], :x.shape[1]]).sum())

        # each picture taken twice, the layers switched off and back on between: a view that moved
        # meanwhile (CI once read 15.02 % against the 4.4 % of a loaded run here) is taken again
        for _ in range(3):
            with_dots = shot()
            set_checkbox(page, "Error colours", False, deadline)
            without = shot()
            set_checkbox(page, "Registered vessels", False, deadline)
            no_vessels = shot()
            set_checkbox(page, "Registered vessels", True, deadline)
            without_again = shot()
            set_checkbox(page, "Error colours", True, deadline)
            with_dots_again = shot()
            changes = moved(with_dots, with_dots_again) + moved(without, without_again)
            print(f"pixels of the 3D view changed between the same layers: {changes}")
            if changes < 200:
                break
        assert changes < 200, f"the 3D view changed by {changes} pixels while only layers were switched"
        scene = scene[:without.shape[0], :without.shape[1]]
        vessel = scene & (np.abs(without - no_vessels).sum(2) > 40)
        covered = (vessel & (np.abs(with_dots - without).sum(2) > 40)).sum() / max(vessel.sum(), 1)
        Image.fromarray(with_dots.astype(np.uint8)).save(shots / "app_error_dots.png")
        print(f"error dots cover {covered:.3f} of {vessel.sum()} vessel pixels")
        assert vessel.sum() > 1000, vessel.sum()  # the vessels were in the picture
        assert covered < 0.15, f"the error dots cover {covered:.0%} of the registered vessels' pixels"
        browser.close()


def test_a_hidpi_laptop_is_framed_for_its_css_window(server, tmp_path):
    """A 1366 × 768 window at two device pixels per CSS pixel (a HiDPI laptop): viser reports
    the 3D canvas in device pixels (``canvas.width``), which the app took for CSS pixels: the
    window looked 2732 px wide and the 2D view docked 610 px wide over the 3D view. The 2D view's
    page reports the tab's pixel ratio, and the dock is the narrow one, as at 1×."""
    deadline = Deadline(BUDGET_S + 600)
    with playwright.sync_playwright() as p:
        # the whole device at 2, as a HiDPI screen: Playwright's own emulation alone leaves the
        # cross-origin 2D view's frame at 1
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=ARGS + ["--force-device-scale-factor=2"])
        page = deadline.open(browser.new_page(viewport=SMALL, device_scale_factor=2))
        page.goto(server["url"])
        wait_text(page, r"Ready\.", deadline)
        us_frame(page, deadline)

        def dock():
            return page.evaluate("() => document.querySelector('iframe').getBoundingClientRect().width")

        t_end = time.monotonic() + 120  # the dock follows the 2D page's first poll; not the whole budget
        while dock() > 360 and time.monotonic() < t_end:
            page.wait_for_timeout(500)
        assert dock() <= 360, f"the 2D view docked {dock():.0f} px wide in a 1366 px window"
        page.screenshot(path=Path(os.environ.get("NAVAPP_SCREENSHOTS", tmp_path)) / "app_1366_dpr2.png")
        browser.close()
