"""A live session in a real browser: ``navapp replay``'s server plays the demo scene over
OpenIGTLink (stylus sweep, probe moving between plane poses, B-mode frames at 25 Hz);
``navapp serve --igtl`` connects to it and ``--slicer`` sends results to a pyigtl server
standing in for 3D Slicer. In Chromium: the tools are seen, the stylus digitises while the
switch is on, a frame is frozen and shown in the 2D view, "Re-register on every frame"
follows the frames, and switched off keeps a converged result that reaches "Slicer".

The tracker → browser latency is measured on the way: each stylus position the browser's
websocket receives is matched to the replayed message carrying exactly that position
(printed; the closing numbers come from this test run with -s, not asserted).

Needs /usr/bin/chromium and playwright, like test_app_browser.py (whose ``Deadline`` bounds
every wait here too).
"""

import os
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import free_port
from test_app_browser import (
    ARGS,
    BUDGET_S,
    CHROMIUM,
    LOGS,
    VIEW,
    Deadline,
    playwright,
    server_log,
    us_frame,
    wait_text,
    wait_until,
)

EDGE, K = 6.0, 20  # as the other browser tests: a short cold start on 2 cores


def stylus_positions(frame: bytes) -> list:
    """Positions (3,) of the stylus node in one viser websocket frame (see
    test_app_browser.registered_liver_updates for the frame layout)."""
    from conftest import viser_messages

    out = []
    for m in viser_messages(frame):
        if m.get("name") == "/stylus/tool":
            pos = m.get("updates", {}).get("position", m.get("position"))
            if pos is not None and len(pos) == 3:
                out.append(np.array(pos, float))
    return out


def toggle(page, label, on, deadline: Deadline):
    """Set a checkbox, checking that the click took (the panel re-renders as status changes)."""
    box = page.get_by_label(label, exact=True).first
    for _ in range(5):
        if box.is_checked(timeout=deadline.ms()) == on:
            return
        box.click(timeout=deadline.ms())
        page.wait_for_timeout(300)
    assert box.is_checked() == on, f"{label!r} did not turn {'on' if on else 'off'}"


@pytest.mark.integration  # 650 s on a loaded machine: CI runs it, `-m "not integration"` skips it
def test_a_live_session_from_the_replay_server(tmp_path):
    deadline = Deadline(2 * BUDGET_S)  # a cold start of the demo scene included

    from navapp.simulation.scene import demo_scene
    from navapp.tracking.replay import ReplayServer, quiet_server, script_from_scene
    from navapp.tracking.results import RIGID, TARGETS

    shots = Path(os.environ.get("NAVAPP_SCREENSHOTS", tmp_path))
    shots.mkdir(parents=True, exist_ok=True)
    script = script_from_scene(demo_scene(), transit_frames=2, edge=EDGE)  # simulates into the shared cache
    replay = ReplayServer(script, port=0, rate_hz=25).start()
    slicer = quiet_server(0)  # 3D Slicer's OpenIGTLinkIF connector in server mode
    slicer.start()
    port = free_port()
    log = tmp_path / "server.log"
    LOGS.append(log)  # a failed wait quotes this server's log, not the last other test's
    proc = subprocess.Popen([sys.executable, "-m", "navapp.cli", "--quiet", "serve", "--port", str(port),
                             "--session", str(tmp_path / "session"), "--edge", str(EDGE), "--k", str(K),
                             "--igtl", f"127.0.0.1:{replay.port}", "--slicer", f"127.0.0.1:{slicer.server_address[1]}"],
                            stdout=log.open("w"), stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})  # a file: a full pipe would block it
    frames = []
    marks = {}
    try:
        url = None
        t0 = time.time()
        while time.time() - t0 < 600 and url is None and proc.poll() is None:
            m = re.search(r"viewer at (http://\S+)", log.read_text())
            url = m.group(1) if m else None
            time.sleep(0.1)
        assert url, f"the server did not print its URL: {log.read_text()[-2000:]}"
        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=str(CHROMIUM), args=ARGS)
            page = deadline.open(browser.new_page(viewport=VIEW))
            page.on("websocket", lambda ws: ws.on("framereceived", lambda f: frames.append((time.time(), f))))
            page.goto(url)
            wait_text(page, r"Ready\.", deadline)
            wait_text(page, rf"connected to 127\.0\.0\.1:{replay.port}", deadline)
            wait_text(page, r"StylusTipToReference: \*?\*?seen", deadline)
            wait_text(page, r"Image_Reference: \*?\*?seen", deadline)

            # digitise while the switch is on
            # (until ten points are shown, not for a fixed time: on a loaded machine the switch
            # reached the server late, and the count read after it was switched off was 0)
            toggle(page, "Digitise (record while on)", True, deadline)
            count = r"(\d+) points digitised with the tracked stylus"
            while int(wait_text(page, count, deadline).group(1)) < 10:
                page.wait_for_timeout(500)
            toggle(page, "Digitise (record while on)", False, deadline)
            assert int(wait_text(page, count, deadline).group(1)) >= 10

            # freeze the live frame: it becomes a plane shown in the 2D view
            page.get_by_role("button", name="Freeze this frame as a plane (to draw on)").click(timeout=deadline.ms())
            us = us_frame(page, deadline)
            wait_until(page, lambda: "live 1" in us.inner_text("#title"), deadline, "the frozen frame shown")

            # re-register on every frame, then switch off: converged, kept, sent to Slicer
            marks["follow_on"] = time.time()
            toggle(page, "Re-register on every frame", True, deadline)
            # "Stopped: …" ends the wait at once (the follower switched off on an error): the
            # server's log below holds its traceback
            following = r"(\d+) frames re-registered, (\d+) ms median|Stopped: ([^\n]*)"
            m = wait_text(page, following, deadline)
            while m.group(3) is None and int(m.group(1)) < 10:
                page.wait_for_timeout(500)
                m = wait_text(page, following, deadline)
            assert m.group(3) is None, f"the live re-registration stopped: {m.group(3)}\n{server_log(60)}"
            page.mouse.move(700, 600)  # no tooltip over the panel in the picture
            page.wait_for_timeout(300)
            page.screenshot(path=shots / "app_live.png")
            toggle(page, "Re-register on every frame", False, deadline)
            marks["follow_off"] = time.time()
            wait_text(page, r"live \(every frame\)", deadline)  # the kept result's row in the run table
            rigid = slicer.wait_for_message(RIGID, timeout=deadline.left())
            targets = slicer.wait_for_message(TARGETS, timeout=deadline.left())
            assert rigid is not None and targets is not None
            assert np.isfinite(rigid.matrix).all() and len(targets.positions) == 2
            browser.close()
    except BaseException:
        print("server output:\n" + log.read_text()[-4000:])
        raise
    finally:
        proc.terminate()
        proc.wait(20)
        replay.stop()
        slicer.stop()

    # tracker message → browser: match the stylus positions the browser received to the
    # replayed messages carrying exactly them (float32 on the wire)
    sent = {}
    for stamp, name, m in list(replay.sent):
        if name == "StylusTipToReference":
            sent.setdefault(tuple(np.round(m[:3, 3].astype(float), 3)), stamp)
    lat = {"tracking only": [], "while re-registering every frame": []}
    for t, f in frames:
        for pos in stylus_positions(f):
            stamp = sent.get(tuple(np.round(pos, 3)))
            if stamp is not None:
                during = marks["follow_on"] <= t <= marks["follow_off"]
                lat["while re-registering every frame" if during else "tracking only"].append(1000 * (t - stamp))
    assert sum(map(len, lat.values())) >= 20, f"only {sum(map(len, lat.values()))} stylus positions matched"
    for what, xs in lat.items():
        if xs:
            xs.sort()
            print(f"\ntracker message → browser websocket, {what}: {len(xs)} stylus updates, median "
                  f"{statistics.median(xs):.1f} ms, p90 {xs[int(0.9 * len(xs))]:.1f} ms, max {xs[-1]:.1f} ms")
