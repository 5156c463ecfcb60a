"""The 2D view's HTTP server against what a hostile or broken client sends (issue 26, item 5):
a crafted link must not run script in the page (the server may listen on 0.0.0.0), a body
shorter than its Content-Length must not hold a handler thread for ever, and JSON the page
never sends (Infinity, NaN, deep nesting, wrong types) is one short 400, never a 500 with
Python's error text. A stand-in provider: no scene is needed to test the server."""

import json
import os
import re
import socket
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from navapp.app.view2d import http as view2d_http
from navapp.app.view2d.http import View2DServer

TOKEN = "Abc_123-xyz"
INJECTION = "%22;window.__xss=1;//"


class FakeProvider:
    def __init__(self):
        self.clicks = []
        self.ratios = []
        self.going = []
        self.resumed = []

    def view_known(self, token):
        return token == TOKEN

    def view_etag(self, token):
        return "e1" if token == TOKEN else None

    def view_state(self, token):
        if token != TOKEN:
            return None
        return {"etag": "e1", "plane": None, "overlays": [], "contours": [], "drawing": None, "targets": [],
                "legend": [], "message": "", "planes": [], "plane_index": None}

    def view_image(self, token):
        return None

    def view_click(self, token, col, row, feature, plane=None):
        self.clicks.append((col, row, feature, plane))
        return None

    def view_command(self, token, cmd, feature, plane=None):
        return None

    def view_pixel_ratio(self, token, ratio):
        self.ratios.append(ratio)

    def view_going(self, token, at_ms, address):
        self.going.append((token, at_ms, address))

    def view_resume(self, token, previous, opened_ms=None, address=None):
        self.resumed.append((token, previous, opened_ms, address))


@pytest.fixture
def served():
    provider = FakeProvider()
    server = View2DServer(provider)
    yield provider, f"http://127.0.0.1:{server.port}", server
    server.stop()


def post(url, raw: bytes):
    try:
        r = urllib.request.urlopen(urllib.request.Request(url, data=raw), timeout=30)
        return r.status, r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.read()


def short_and_plain(body: bytes):
    text = body.decode()
    assert len(text) < 120, text
    for word in ("Error", "Traceback", "Exception", "float", "int("):
        assert word not in text, text


def test_the_pages_pixel_ratio_reaches_the_provider_and_junk_is_ignored(served):
    provider, base, _ = served
    for dpr in ("2", "1.5", "abc", ""):
        r = urllib.request.urlopen(f"{base}/us/state?c={TOKEN}&dpr={dpr}", timeout=30)
        assert r.status == 200
    assert provider.ratios == [2.0, 1.5]


def test_a_pages_beacon_and_its_times_reach_the_provider(served):
    """The beacon of a page whose tab is gone already (its viewer connection closed first, so
    the tab is no longer known) still reaches the provider, with the browser's clock."""
    provider, base, _ = served
    at = 1_765_000_000_123
    code, _ = post(f"{base}/us/going?c=GoneTab_1", json.dumps({"at": at}).encode())
    assert code == 204 and provider.going == [("GoneTab_1", float(at), "127.0.0.1")]
    code, _ = post(f"{base}/us/resume?c={TOKEN}", json.dumps({"previous": "", "opened": at + 900}).encode())
    assert code == 200 and provider.resumed == [(TOKEN, None, float(at + 900), "127.0.0.1")]
    for junk in (b'{"at": "soon"}', b'{"at": -5}', b'{"at": 1e300}', b'{"at": true}'):
        code, body = post(f"{base}/us/going?c={TOKEN}", junk)
        assert code == 400, junk
        short_and_plain(body)
    assert len(provider.going) == 1


def test_a_crafted_token_is_never_copied_into_the_page(served):
    provider, base, _ = served
    with pytest.raises(urllib.error.HTTPError) as e:
        urllib.request.urlopen(f"{base}/us?c={INJECTION}", timeout=30)
    assert e.value.code == 404
    body = e.value.read()
    assert b"__xss" not in body and b"<script" not in body
    page = urllib.request.urlopen(f"{base}/us?c={TOKEN}", timeout=30).read().decode()
    assert f'data-token="{TOKEN}"' in page


@pytest.mark.parametrize("raw", [b'{"col": Infinity, "row": 3, "feature": "PV contour"}',
                                 b'{"col": NaN, "row": 3}', b'{"col": -Infinity, "row": 3}',
                                 b"[" * 30_000 + b"]" * 30_000, b'{"col": [[[[1]]]], "row": 3}',
                                 b'{"col": 1.5, "row": 3}', b'{"col": true, "row": 3}', b'[1, 2]',
                                 b'{"col": 1e400, "row": 3}', b"\xff\xfe",
                                 # past Python's 4,300-digit limit int() raises a ValueError of its own
                                 pytest.param(b'{"col": ' + b"9" * 5000 + b', "row": 3}', id="5000-digit-int")])
def test_json_the_page_never_sends_is_one_short_400(served, raw):
    provider, base, _ = served
    code, body = post(f"{base}/us/click?c={TOKEN}", raw)
    assert code == 400, (code, body)
    short_and_plain(body)
    assert provider.clicks == []
    code, body = post(f"{base}/us/command?c={TOKEN}", raw.replace(b'"col"', b'"cmd"'))
    assert code == 400, (code, body)
    short_and_plain(body)
    code, _ = post(f"{base}/us/click?c={TOKEN}", json.dumps({"col": 3, "row": 4, "plane": 0}).encode())
    assert code == 200  # still serving


def test_a_body_shorter_than_its_content_length_is_answered_not_waited_for(served):
    provider, base, server = served
    wait = getattr(view2d_http, "BODY_TIMEOUT_S", 10.0) + 15  # the 400 comes after the body timeout, on a busy machine
    with socket.create_connection(("127.0.0.1", server.port), timeout=wait) as s:
        s.sendall(f"POST /us/click?c={TOKEN} HTTP/1.1\r\nHost: x\r\nContent-Length: 100\r\n\r\n".encode()
                  + b'{"col": 1}')
        t0 = time.monotonic()
        answer = b""
        while b"\r\n\r\n" not in answer:
            chunk = s.recv(4096)  # socket.timeout here: the handler waits for the missing bytes for ever
            if not chunk:
                break
            answer += chunk
        # the body may come in a segment of its own after the head: read all Content-Length says
        head, _, rest = answer.partition(b"\r\n\r\n")
        m = re.search(rb"(?i)content-length:\s*(\d+)", head)
        while m and len(rest) < int(m.group(1)):
            chunk = s.recv(4096)
            if not chunk:
                break
            rest += chunk
        assert time.monotonic() - t0 < wait
    assert head.startswith(b"HTTP/1.0 400") or head.startswith(b"HTTP/1.1 400"), answer
    assert b"shorter than its Content-Length" in rest
    assert provider.clicks == []
    code, _ = post(f"{base}/us/click?c={TOKEN}", json.dumps({"col": 3, "row": 4, "plane": 0}).encode())
    assert code == 200


CHROMIUM = Path("/usr/bin/chromium")


@pytest.mark.skipif(not CHROMIUM.exists(), reason="Chromium not installed")
def test_a_click_for_a_view_the_server_does_not_know_is_a_404(served):
    """A tab of a server since restarted: its click is answered 404, as its poll is, and the
    page asks for a reload (it was a 409 whose words the page had to match)."""
    provider, base, _ = served
    status, body = post(f"{base}/us/click?c=Unknown_123", json.dumps({"col": 1, "row": 2, "plane": 0,
                                                                       "feature": "PV contour"}).encode())
    assert status == 404 and b"reload" in body and not provider.clicks
    status, _ = post(f"{base}/us/click?c={TOKEN}", json.dumps({"col": 1, "row": 2, "plane": 0,
                                                                "feature": "PV contour"}).encode())
    assert status == 200 and provider.clicks == [(1, 2, "PV contour", 0)]


def test_the_injection_url_runs_no_script_in_chromium(served, tmp_path):
    from playwright import sync_api as playwright
    from test_app_browser import ARGS, Deadline

    provider, base, _ = served
    deadline = Deadline(300)
    with playwright.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=ARGS)
        page = deadline.open(browser.new_page())
        page.goto(f"{base}/us?c={INJECTION}")
        assert page.evaluate("window.__xss") is None
        assert "not connected" in page.inner_text("body")
        page.screenshot(path=Path(os.environ.get("NAVAPP_SCREENSHOTS", tmp_path)) / "view2d_injection.png")
        page.goto(f"{base}/us?c={TOKEN}")  # the real page still runs its script
        page.wait_for_function("document.getElementById('title').textContent.startsWith('No plane shown yet:')",
                               timeout=deadline.ms())
        browser.close()


def test_the_2d_view_takes_the_viewer_port_plus_one_where_free():
    """A tab left open across a server restart reaches the new 2D server only if it is on the
    same port: by default the viewer's port + 1, any free port where that is taken."""
    from navapp.app.server import _view2d_server

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        viewer = s.getsockname()[1]  # a port that was free; the one after it is tried
    provider = object()
    first = _view2d_server(provider, "127.0.0.1", None, viewer)
    try:
        if first.port != viewer + 1:  # the next port was taken on this machine: nothing to check
            pytest.skip(f"port {viewer + 1} was not free")
        second = _view2d_server(provider, "127.0.0.1", None, viewer)  # taken now: any free one
        try:
            assert second.port not in (0, viewer + 1)
        finally:
            second.stop()
    finally:
        first.stop()
