"""A viewer that asks for a token, in Chromium: ``navapp serve --token`` on 127.0.0.1 (the
token forced on, as beyond localhost). A page without the token shows nothing of the app;
with it the viewer and its 2D view work; an observer link watches live and its clicks change
nothing and say so. Needs /usr/bin/chromium, as test_app_browser."""

import json
import os
import re
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request

import pytest
from conftest import free_port
from test_app_browser import ARGS, CHROMIUM, VIEW, Deadline, click_button, us_frame, wait_text, wait_until

from navapp.app.access import OBSERVING

if not CHROMIUM.exists():
    pytest.skip("Chromium not installed", allow_module_level=True)
from playwright import sync_api as playwright  # noqa: E402

TOKEN = "test-token-" + "x" * 20
SCENE = """name = "accesstest"
[anatomy]
phantom = 0
[deformation]
release = "L"
mesh_edge_mm = 10.0
[stylus]
coverage = 0.2
[ius]
planes = 2
"""


def start(d, port):
    """``navapp serve --token`` on 127.0.0.1:``port`` with the session in ``d``; its two links."""
    log = d / f"server{len(list(d.glob('server*.log')))}.log"
    with log.open("w") as out:
        proc = subprocess.Popen([sys.executable, "-m", "navapp.cli", "--quiet", "serve", str(d / "scene.toml"),
                                 "--host", "127.0.0.1", "--port", str(port), "--token", TOKEN,
                                 "--session", str(d / "session"), "--edge", "12", "--k", "12"],
                                stdout=out, stderr=subprocess.STDOUT, text=True,
                                env={**os.environ, "PYTHONUNBUFFERED": "1"})
    t0, text = time.time(), ""
    while time.time() - t0 < 300 and proc.poll() is None:
        text = log.read_text(errors="replace")
        if "observer link" in text:
            break
        time.sleep(0.1)
    editor = re.search(r"viewer at (http://\S+)", text)
    observer = re.search(r"observer link \(watches, changes nothing\): (http://\S+)", text)
    assert editor and observer, text
    return proc, editor.group(1), observer.group(1)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    d = tmp_path_factory.mktemp("access")
    (d / "scene.toml").write_text(SCENE)
    port = free_port()
    proc, editor, observer = start(d, port)
    state = {"proc": proc, "editor": editor, "observer": observer, "port": port, "session": d / "session", "dir": d}
    yield state
    state["proc"].terminate()
    state["proc"].wait(20)


def test_token_observer_and_refusals_in_chromium(server):
    deadline = Deadline(900)
    editor_url, observer_url = server["editor"], server["observer"]
    assert editor_url == f"http://127.0.0.1:{server['port']}/?token={TOKEN}"
    with playwright.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=ARGS)
        # without the token: a short 403, nothing of the viewer
        bare = deadline.open(browser.new_context(viewport=VIEW).new_page())
        r = bare.goto(f"http://127.0.0.1:{server['port']}/")
        assert r.status == 403
        assert "token" in bare.inner_text("body") and bare.locator("canvas").count() == 0
        # a websocket opened from that page is closed before any message
        got = bare.evaluate("""sub => new Promise(done => {
            const ws = new WebSocket(location.href.replace('http', 'ws'), [sub]);
            let n = 0; ws.onmessage = () => n++; ws.onclose = () => done(n);
            setTimeout(() => done(-1), 10000); })""", f"viser-v{__import__('viser').__version__}")
        assert got == 0

        editor = deadline.open(browser.new_context(viewport=VIEW).new_page())
        editor.goto(editor_url)
        wait_text(editor, r"Ready\.", deadline)
        wait_text(editor, r"0 of \d+ sweep points digitised", deadline)
        us = us_frame(editor, deadline)
        assert f"t={TOKEN}" in us.url
        # the 2D view's server refuses this tab's own, valid value without the token
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(us.url.replace(f"&t={TOKEN}", ""), timeout=30)
        assert refused.value.code == 403
        with urllib.request.urlopen(us.url, timeout=30) as r:
            assert r.status == 200
        wait_until(editor, lambda: "Plane" in us.inner_text("body"), deadline, "the 2D view's page")

        observer = deadline.open(browser.new_context(viewport=VIEW).new_page())
        observer.goto(observer_url)
        wait_text(observer, r"Observer link", deadline)
        m = wait_text(observer, r"0 of (\d+) sweep points digitised", deadline)
        total = int(m.group(1))
        click_button(observer, "Collect the whole sweep now", deadline)
        assert OBSERVING.endswith("The change was refused.")
        wait_text(observer, r"The change was refused", deadline, step_s=120)  # said in a notification over the 3D view
        time.sleep(1.0)
        saved = server["session"] / "session.json"
        assert not saved.exists() or json.loads(saved.read_text())["stylus_count"] == 0
        assert re.search(r"\b0 of \d+ sweep points digitised", editor.inner_text("body"))
        # the observer's 2D view shows the plane; a click there is refused and said so
        obs_us = us_frame(observer, deadline)
        wait_until(observer, lambda: obs_us.locator("#plane option").count() > 1, deadline, "the planes listed")
        obs_us.locator("#plane").select_option(index=1)  # the plane its own tab shows: allowed
        wait_until(observer, lambda: obs_us.inner_text("#title").startswith("Plane"), deadline, "the plane shown")
        obs_us.locator("#cv").click(position={"x": 150, "y": 150})
        wait_until(observer, lambda: "refused" in obs_us.inner_text("#msg"), deadline, "the refused click said")
        assert obs_us.evaluate("window.navappLatencies.length") == 1

        # the editor's change reaches the observer live
        click_button(editor, "Collect the whole sweep now", deadline)
        wait_text(observer, rf"{total} of {total} sweep points digitised", deadline)
        assert json.loads((server["session"] / "session.json").read_text())["stylus_count"] == total
        # the action log, in the Session panel of every tab, the observer's too
        wait_text(observer, r"tab \d+: points digitised — whole sweep at once", deadline)
        assert "points digitised" in editor.inner_text("body")

        # kill -9 and a restart on the same session: the log is all there
        server["proc"].send_signal(signal.SIGKILL)
        server["proc"].wait(30)
        server["proc"], editor_url, _ = start(server["dir"], server["port"])
        again = deadline.open(browser.new_context(viewport=VIEW).new_page())
        again.goto(editor_url)
        wait_text(again, r"Ready\.", deadline)
        wait_text(again, r"tab \d+: points digitised — whole sweep at once", deadline)
        logged = [json.loads(x) for x in (server["session"] / "actions.jsonl").read_text().splitlines()]
        assert [x["action"] for x in logged] == ["points digitised"] and logged[0]["role"] == "editor"
        browser.close()


def test_viewer_page_over_tls_opens_its_websocket_on_wss(tmp_path):
    """viser's client behind the front on TLS (a self-signed certificate made here): the page
    loads over https with the token, and its websocket goes over wss and receives the scene."""
    import viser
    from test_app_access import ACCESS, EDITOR, make_cert

    from navapp.app.access import tls_context
    from navapp.app.front import Front

    certfile, keyfile = make_cert(tmp_path)
    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    server.scene.add_icosphere("/marker", radius=1.0)
    front = Front(ACCESS, server.get_port(), "127.0.0.1", free_port(), tls_context(certfile, keyfile))
    try:
        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=str(CHROMIUM), args=ARGS)
            page = browser.new_context(ignore_https_errors=True).new_page()
            sockets, frames = [], []

            def opened(ws):
                sockets.append(ws.url)
                ws.on("framereceived", lambda f: frames.append(f))

            page.on("websocket", opened)
            page.goto(f"https://127.0.0.1:{front.port}/?token={EDITOR}")
            page.wait_for_function("() => document.querySelector('canvas') !== null", timeout=60_000)
            t0 = time.time()
            while not frames and time.time() - t0 < 60:
                page.wait_for_timeout(100)
            assert sockets and all(u.startswith(f"wss://127.0.0.1:{front.port}") for u in sockets), sockets
            assert frames, "nothing reached the page over wss"
            browser.close()
    finally:
        front.stop()
        server.stop()
