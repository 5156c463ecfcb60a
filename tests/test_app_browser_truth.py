"""Issue 26 in Chromium: what the surgeon sees must be true. Clicks queued in the 2D view
while the plane is changed elsewhere land on the plane they were aimed at; Undo stays in
its tab and survives a reload; Cancel is reachable while a run or the accuracy sweep runs,
and nothing else can be started meanwhile.

One ``navapp serve`` for the module (the demo scene at 6 mm, k = 20, as the other browser
tests); every wait bounded by the test's ``Deadline``. Screenshots go to
$NAVAPP_SCREENSHOTS (default: the test's temporary folder).
"""

import json
import os
import re
import urllib.request
from pathlib import Path

import pytest
from conftest import free_port
from test_app_browser import (
    ARGS,
    CHROMIUM,
    VIEW,
    Deadline,
    canvas_xy,
    click_button,
    playwright,
    start_server,
    us_frame,
    wait_text,
    wait_until,
)

COLD_S = 1200  # the first test starts the server cold (simulation, mesh, basis)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    port = free_port()
    session = tmp_path_factory.mktemp("session")
    proc, url = start_server(port, session)
    yield {"proc": proc, "url": url, "session": session}
    proc.terminate()
    proc.wait(20)


def shots(tmp_path) -> Path:
    out = Path(os.environ.get("NAVAPP_SCREENSHOTS", tmp_path))
    out.mkdir(parents=True, exist_ok=True)
    return out


def saved(session) -> dict:
    return json.loads((session / "session.json").read_text())


def token_of(frame) -> str:
    return re.search(r"[?&]c=([^&]+)", frame.url).group(1)


def command(frame, body: dict):
    """A command to a tab's 2D view from outside its page: what the 3D panel's Plane list,
    the guide's "Show plane" and "Suggest the next plane" do to the tab's plane."""
    base = re.match(r"(https?://[^/]+)", frame.url).group(1)
    req = urllib.request.Request(f"{base}/us/command?c={token_of(frame)}", data=json.dumps(body).encode())
    return json.loads(urllib.request.urlopen(req, timeout=60).read())


def choose_plane(frame, index: int, deadline: Deadline):
    """Show plane ``index`` in the tab's 2D view; returns the view's frame. Right after the page
    loads, the docked panel settling its width may mount the view's frame again (CI saw the
    first frame detached while its plane list loaded): the page's new frame is then taken."""
    while True:
        try:
            frame.wait_for_selector(f"#plane option[value='{index}']", state="attached", timeout=deadline.ms())
            break
        except playwright.Error as exc:
            if "detached" not in str(exc) or not deadline.left():
                raise
            frame = us_frame(frame.page, deadline)
    frame.select_option("#plane", value=str(index), timeout=deadline.ms())
    wait_until(frame.page, lambda: f"Plane {index + 1} (" in frame.inner_text("#title"), deadline,
               f"plane {index + 1} shown")
    return frame


def test_queued_clicks_land_on_the_plane_they_were_aimed_at(server, tmp_path):
    deadline = Deadline(COLD_S)
    out = shots(tmp_path)
    with playwright.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=ARGS)
        page = deadline.open(browser.new_page(viewport=VIEW))
        page.goto(server["url"])
        us = us_frame(page, deadline)
        us = choose_plane(us, 0, deadline)
        before = len(saved(server["session"])["contours"]) if (server["session"] / "session.json").exists() else 0
        # the server is slow to answer (a loaded machine): the first click's request is held,
        # the others wait in the page's queue
        held, hold = [], [True]
        page.route(re.compile(r"/us/click\?"), lambda route: held.append(route) if hold[0] else route.continue_())
        aimed = [(60 + 8 * k, 90 + 3 * k) for k in range(6)]
        canvas = us.locator("#cv")
        for c, r in aimed:
            x, y = canvas_xy(c, r)
            canvas.click(position={"x": x, "y": y}, timeout=deadline.ms())
            page.wait_for_timeout(100)
        wait_until(page, lambda: held, deadline, "the first click sent")
        command(us, {"cmd": "Plane", "plane": 1})  # the plane changes while the clicks wait
        wait_until(page, lambda: "Plane 2 (" in us.inner_text("#title"), deadline, "plane 2 shown")
        page.wait_for_timeout(500)
        canvas.screenshot(path=out / "truth_queued_on_other_plane.png")  # plane 2: none of plane 1's markers
        hold[0] = False
        for route in held:
            route.continue_()
        wait_until(page, lambda: us.evaluate("window.navappLatencies.length") >= len(aimed), deadline,
                   "every click acknowledged")
        new = saved(server["session"])["contours"][before:]
        assert [(c["plane"], [tuple(v) for v in c["vertices"]]) for c in new] == [(0, aimed)], new
        us = choose_plane(us, 0, deadline)
        page.wait_for_timeout(500)
        canvas.screenshot(path=out / "truth_queued_landed.png")  # back on plane 1: all six, one open line
        for _ in aimed:  # leave the session as it was
            us.get_by_role("button", name="Undo", exact=True).click(timeout=deadline.ms())
            page.wait_for_timeout(150)
        wait_until(page, lambda: len(saved(server["session"])["contours"]) == before, deadline, "undone")
        browser.close()


@pytest.fixture
def own_server(tmp_path_factory):
    """A server of this test's own: a reload is matched to the one tab that closed within the
    last minute, and the previous test's closed tab made two (its reload then came back as a
    new tab once the suite ran fast enough to reload within that minute). The cache is warm."""
    session = tmp_path_factory.mktemp("session")
    proc, url = start_server(free_port(), session)
    yield {"proc": proc, "url": url, "session": session}
    proc.terminate()
    proc.wait(20)


def test_undo_stays_in_its_tab_and_survives_a_reload(own_server, tmp_path):
    server = own_server
    deadline = Deadline(COLD_S)
    out, session = shots(tmp_path), server["session"]
    with playwright.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=ARGS)
        a, b = (deadline.open(browser.new_context(viewport=VIEW).new_page()) for _ in range(2))
        for page in (a, b):
            page.goto(server["url"])
            wait_text(page, r"sweep points digitised", deadline)
        # tab A collects the stylus sweep; tab B, which did nothing, presses Undo
        click_button(a, "Collect the whole sweep now", deadline)
        total = int(wait_text(a, r"of (\d+) sweep points digitised", deadline).group(1))
        wait_text(a, rf"{total} of {total} sweep points digitised", deadline)
        wait_until(a, lambda: saved(session)["stylus_count"] == total, deadline, "the sweep saved")
        ub = us_frame(b, deadline)
        ub.get_by_role("button", name="Undo", exact=True).click(timeout=deadline.ms())
        wait_until(b, lambda: "Nothing of yours to undo." in ub.inner_text("#msg"), deadline, "tab B's answer")
        b.wait_for_timeout(500)
        ub.locator("body").screenshot(path=out / "truth_undo_other_tab.png")
        assert saved(session)["stylus_count"] == total, "tab B's Undo took away tab A's sweep"

        # tab A draws two vertices of a contour, reloads, and can still undo them
        ua = us_frame(a, deadline)
        old = token_of(ua)
        ua = choose_plane(ua, 1, deadline)  # not the plane a new tab starts on: its return proves the resume
        n0 = len(saved(session)["contours"])
        for c, r in ((70, 100), (90, 110)):
            x, y = canvas_xy(c, r)
            ua.locator("#cv").click(position={"x": x, "y": y}, timeout=deadline.ms())
            a.wait_for_timeout(150)
        wait_until(a, lambda: ua.evaluate("window.navappLatencies.length") >= 2, deadline, "the clicks stored")
        a.reload()
        deadline = Deadline(min(420, deadline.left()))  # what follows fails in minutes, not the cold budget
        wait_text(a, r"sweep points digitised", deadline)

        def reloaded():
            return next((f for f in a.frames if "/us?c=" in f.url and token_of(f) != old), None)

        wait_until(a, lambda: reloaded() is not None, deadline, "the reloaded 2D view")
        ua = reloaded()
        # the reloaded tab took its work back: its plane, and the contour in progress
        wait_until(a, lambda: "Plane 2 (" in ua.inner_text("#title"), deadline, "the plane back after the reload")
        a.wait_for_timeout(500)
        ua.locator("#cv").screenshot(path=out / "truth_reloaded_contour.png")
        ua.get_by_role("button", name="Undo", exact=True).click(timeout=deadline.ms())
        wait_until(a, lambda: [len(c["vertices"]) for c in saved(session)["contours"][n0:]] == [1], deadline,
                   f"one vertex undone after the reload: {saved(session)['contours'][n0:]}")
        ua.get_by_role("button", name="Undo", exact=True).click(timeout=deadline.ms())
        wait_until(a, lambda: len(saved(session)["contours"]) == n0, deadline, "the contour undone")
        ua.get_by_role("button", name="Undo", exact=True).click(timeout=deadline.ms())  # then tab A's sweep
        wait_until(a, lambda: saved(session)["stylus_count"] < total, deadline, "tab A's sweep undone")
        browser.close()
