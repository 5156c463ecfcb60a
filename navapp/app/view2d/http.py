"""The 2D view's HTTP side: a small server in a thread serving the page (``page.html`` and
``page.js``, package files), its state as JSON, the frame as PNG, and taking clicks and
commands. The page draws the current B-mode frame at native pixel scale on a canvas, with
mm rulers, the model's sections and the drawn contours, and sends clicks back as pixels.

viser's GUI has no click events on images, so the view is a page of its own, embedded in a
viser panel as an iframe (one per browser tab, identified by a token). Clicks are queued in
the page and sent one at a time; a vertex is drawn hollow until the server has stored it
and filled once acknowledged, so no click is lost however fast they come, and a failed
request is retried, not dropped. The page polls the state (an ETag per client) a few times
a second, so contours committed in another tab appear here too. No viser here: what is
served comes from a ``Provider`` (``view2d.provider.View2D`` in the viewer).
"""

import json
import threading
from functools import cache
from html import escape
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib.resources import files
from typing import Any, Protocol
from urllib.parse import parse_qs, urlparse

from ..palette import DRAWABLE, IN_PROGRESS

POLL_MS = 250  # how often a page asks whether anything changed


class Provider(Protocol):
    def view_etag(self, token: str) -> str | None: ...
    def view_state(self, token: str) -> dict | None: ...
    def view_image(self, token: str) -> bytes | None: ...
    def view_click(self, token: str, col: int, row: int, feature: str) -> str | None: ...
    def view_command(self, token: str, cmd: str, feature: str, plane: int | None = None) -> str | None: ...


@cache
def _asset(name: str) -> str:
    return (files(__package__) / name).read_text(encoding="utf-8")


def page(token: str) -> str:
    """The 2D view's page for one tab."""
    options = "".join(f"<option>{escape(name)}</option>" for name in DRAWABLE)
    return (_asset("page.html").replace("__TOKEN__", escape(token)).replace("__POLL__", str(POLL_MS))
            .replace("__IN_PROGRESS__", IN_PROGRESS).replace("__FEATURES__", options))


class _Handler(BaseHTTPRequestHandler):
    provider: Any = None  # a Provider, set per server class

    def log_message(self, *args):  # the app's console is for the user, not for every poll
        pass

    def _send(self, code, body: bytes, ctype="application/json"):
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Cache-Control", "no-store")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def _query(self):
        u = urlparse(self.path)
        return u.path, {k: v[0] for k, v in parse_qs(u.query).items()}

    def do_GET(self):
        path, q = self._query()
        token = q.get("c", "")
        try:
            if path == "/us":
                return self._send(200, page(token).encode(), "text/html; charset=utf-8")
            if path == "/us/page.js":
                return self._send(200, _asset("page.js").encode(), "text/javascript; charset=utf-8")
            if path == "/us/state":
                if q.get("v") and self.provider.view_etag(token) == q.get("v"):
                    return self._send(204, b"")
                out = self.provider.view_state(token)
                if out is None:
                    return self._send(404, b"unknown view")
                if out["etag"] == q.get("v"):
                    return self._send(204, b"")
                return self._send(200, json.dumps(out).encode())
            if path == "/us/image":
                png = self.provider.view_image(token)
                if png is None:
                    return self._send(404, b"no image")
                return self._send(200, png, "image/png")
        except Exception as exc:  # a failed request must not take the server down
            return self._send(500, f"{exc.__class__.__name__}: {exc}".encode(), "text/plain")
        return self._send(404, b"not found", "text/plain")

    def do_POST(self):
        path, q = self._query()
        token = q.get("c", "")
        try:
            n = int(self.headers.get("Content-Length") or 0)
            body = json.loads(self.rfile.read(n) or b"{}")
            if path == "/us/click":
                err = self.provider.view_click(token, int(body["col"]), int(body["row"]), str(body.get("feature", "")))
            elif path == "/us/command":
                plane = body.get("plane")
                err = self.provider.view_command(token, str(body["cmd"]), str(body.get("feature", "")),
                                                 None if plane is None else int(plane))
            else:
                return self._send(404, b"not found", "text/plain")
        except (ValueError, KeyError, TypeError) as exc:
            return self._send(400, f"bad request: {exc}".encode(), "text/plain")
        except Exception as exc:
            return self._send(500, f"{exc.__class__.__name__}: {exc}".encode(), "text/plain")
        if err:
            return self._send(409, err.encode(), "text/plain")
        return self._send(200, json.dumps(self.provider.view_state(token) or {}).encode())


class View2DServer:
    """Serves the 2D view pages on ``host:port`` (port 0: any free port) in a thread."""

    def __init__(self, provider: Provider, host: str = "127.0.0.1", port: int = 0):
        handler = type("Handler", (_Handler,), {"provider": provider})
        self.httpd = ThreadingHTTPServer((host, port), handler)
        self.httpd.daemon_threads = True
        self.port = self.httpd.server_address[1]
        self.host = host
        self._thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self._thread.start()

    def page_url(self, token: str, host: str | None = None) -> str:
        return f"http://{host or self.host}:{self.port}/us?c={token}"

    def stop(self):
        self.httpd.shutdown()
        self.httpd.server_close()
