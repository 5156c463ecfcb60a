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
import logging
import re
import ssl
import sys
import threading
from functools import cache
from html import escape
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib.resources import files
from typing import Any, Protocol
from urllib.parse import parse_qs, urlparse

from ..access import OBSERVING, OPEN, REFUSED, Access, Role
from ..palette import DRAWABLE, IN_PROGRESS

POLL_MS = 250  # how often a page asks whether anything changed
# a tab's token as ``core.new_client_state`` makes it; anything else is refused unread, so no
# request value ever reaches the page (with --host 0.0.0.0 a crafted link must not run script)
TOKEN = re.compile(r"[A-Za-z0-9_-]{1,64}")
BODY_TIMEOUT_S = 10.0  # a body shorter than its Content-Length must not hold a handler thread for ever
MAX_BODY = 64 * 1024  # a click or a command is a few dozen bytes
UNKNOWN_VIEW = b"This view is not connected (the viewer restarted?): reload the viewer page."

log = logging.getLogger(__name__)


class BadRequest(ValueError):
    """A request the page would never send; its message is the whole 400 answer."""


def _no_constant(name):
    raise BadRequest(f"{name} is not a number")


def _whole(text: str) -> int:
    # a pixel or plane index has a few digits, a time in ms since the epoch 13; Python refuses
    # int() past 4,300 with a ValueError the handler would not recognise (a 500 with a traceback)
    if len(text.lstrip("-")) > 15:
        raise BadRequest(f"{text[:12]}… is not a pixel, a plane index or a time")
    return int(text)


def _body(raw: bytes) -> dict:
    try:
        body = json.loads(raw or b"{}", parse_constant=_no_constant, parse_int=_whole)
    except RecursionError:
        raise BadRequest("the body is nested too deeply") from None
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise BadRequest("the body is not JSON") from None
    if not isinstance(body, dict):
        raise BadRequest("the body is not a JSON object")
    return body


def _int(body: dict, key: str, required: bool = True) -> int | None:
    v = body.get(key)
    if v is None and not required:
        return None
    if isinstance(v, bool) or not isinstance(v, int) or abs(v) > 1_000_000:
        raise BadRequest(f"{key} must be a whole number")
    return v


def _ms(body: dict, key: str) -> float | None:
    """A time on the browser's clock (ms since the epoch), or None where the page sent none."""
    v = body.get(key)
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v < 1e14:
        raise BadRequest(f"{key} must be a time in ms since the epoch")
    return float(v)


def _str(body: dict, key: str, required: bool = False) -> str:
    v = body.get(key, None if required else "")
    if not isinstance(v, str) or len(v) > 200:
        raise BadRequest(f"{key} must be a short string")
    return v


class Provider(Protocol):
    def view_etag(self, token: str) -> str | None: ...
    def view_state(self, token: str) -> dict | None: ...
    def view_image(self, token: str) -> bytes | None: ...
    def view_known(self, token: str) -> bool: ...
    def view_click(self, token: str, col: int, row: int, feature: str, plane: int) -> str | None: ...
    def view_command(self, token: str, cmd: str, feature: str, plane: int | None = None) -> str | None: ...
    def view_pixel_ratio(self, token: str, ratio: float) -> None: ...
    def view_resume(self, token: str, previous: str | None, opened_ms: float | None = None,
                    address: str | None = None) -> str | None: ...
    def view_going(self, token: str, at_ms: float | None, address: str | None) -> None: ...


@cache
def _asset(name: str) -> str:
    return (files(__package__) / name).read_text(encoding="utf-8")


def page(token: str, access: str = "") -> str:
    """The 2D view's page for one tab; ``access``: the viewer's token the page's requests carry."""
    options = "".join(f"<option>{escape(name)}</option>" for name in DRAWABLE)
    return (_asset("page.html").replace("__TOKEN__", escape(token)).replace("__ACCESS__", escape(access))
            .replace("__POLL__", str(POLL_MS))
            .replace("__IN_PROGRESS__", IN_PROGRESS).replace("__FEATURES__", options))


class _Handler(BaseHTTPRequestHandler):
    provider: Any = None  # a Provider, set per server class
    access: Access = OPEN  # the viewer's tokens (``access``), set per server class
    timeout = BODY_TIMEOUT_S  # socketserver sets it on the connection: every read is bounded

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

    def _token(self, q) -> str | None:
        token = q.get("c", "")
        return token if TOKEN.fullmatch(token) else None

    def _role(self, q) -> Role | None:
        """The role the request's access token (``t``) gives; None: refused with a short 403,
        before the tab's value is looked at (a valid tab value without the token is refused too)."""
        role = self.access.role_for(q.get("t"))
        if role is None:
            self._send(403, REFUSED, "text/plain; charset=utf-8")
        return role

    def do_GET(self):
        path, q = self._query()
        token = self._token(q)
        if self._role(q) is None:
            return
        try:
            if path == "/us/page.js":
                return self._send(200, _asset("page.js").encode(), "text/javascript; charset=utf-8")
            if token is None or not self.provider.view_known(token):
                if path.startswith("/us"):
                    return self._send(404, UNKNOWN_VIEW, "text/plain; charset=utf-8")
                return self._send(404, b"not found", "text/plain")
            if path == "/us":
                return self._send(200, page(token, q.get("t", "")).encode(), "text/html; charset=utf-8")
            if path == "/us/state":
                try:
                    self.provider.view_pixel_ratio(token, float(q.get("dpr", "")))
                except ValueError:  # none or not a number: an older page, nothing to lay out again
                    pass
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
        except ConnectionError:  # the tab went: nobody to answer, nothing to log (_Server.handle_error)
            raise
        except Exception:  # a failed request must not take the server down; the details go to the log
            log.exception("2D view: GET %s failed", path)
            return self._send(500, b"internal error (see the server's log)", "text/plain")
        return self._send(404, b"not found", "text/plain")

    def _read_body(self) -> bytes:
        try:
            n = int(self.headers.get("Content-Length") or 0)
        except ValueError:
            raise BadRequest("bad Content-Length") from None
        if not 0 <= n <= MAX_BODY:
            raise BadRequest("the body is too long")
        try:
            raw = self.rfile.read(n)
        except TimeoutError:
            raw = b""
        if len(raw) != n:
            self.close_connection = True  # what is left of the body would be read as the next request
            raise BadRequest("the body is shorter than its Content-Length")
        return raw

    def do_POST(self):
        path, q = self._query()
        token = self._token(q)
        role = self._role(q)
        if role is None:
            self.close_connection = True  # the body is left unread
            return
        try:
            body = _body(self._read_body())
            if role is Role.OBSERVER and path in ("/us/click", "/us/command") and body.get("cmd") not in (
                    "Plane", "Feature"):
                return self._send(403, OBSERVING.encode(), "text/plain; charset=utf-8")
            if path == "/us/going" and token is not None:
                # the page's last word (a beacon; nothing to answer): its tab may be gone already,
                # its viewer connection closed just before
                self.provider.view_going(token, _ms(body, "at"), self.client_address[0])
                return self._send(204, b"", "text/plain")
            # a view this server does not know (a tab of a server since restarted): 404, as GET
            # answers it, so the page tells it from a refused click and asks for a reload
            if token is None or not self.provider.view_known(token):
                return self._send(404, UNKNOWN_VIEW, "text/plain; charset=utf-8")
            if path == "/us/click":
                # the plane is the one the click was aimed at: the tab's plane may have changed since
                err = self.provider.view_click(token, _int(body, "col"), _int(body, "row"), _str(body, "feature"),
                                               _int(body, "plane"))
            elif path == "/us/command":
                err = self.provider.view_command(token, _str(body, "cmd", required=True), _str(body, "feature"),
                                                 _int(body, "plane", required=False))
            elif path == "/us/resume":
                previous = _str(body, "previous")
                err = self.provider.view_resume(token, previous if TOKEN.fullmatch(previous) else None,
                                                _ms(body, "opened"), self.client_address[0])
            else:
                return self._send(404, b"not found", "text/plain")
        except BadRequest as exc:
            return self._send(400, f"bad request: {exc}".encode(), "text/plain; charset=utf-8")
        except ConnectionError:
            raise
        except Exception:
            log.exception("2D view: POST %s failed", path)
            return self._send(500, b"internal error (see the server's log)", "text/plain")
        if err:
            return self._send(409, err.encode(), "text/plain")
        return self._send(200, json.dumps(self.provider.view_state(token) or {}).encode())


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    tls: ssl.SSLContext | None = None

    def get_request(self):
        sock, addr = super().get_request()
        if self.tls is None:
            return sock, addr
        # the TLS handshake is made in the request's own thread (``finish_request``): made here,
        # one client that never completes it would hold every other one back
        return self.tls.wrap_socket(sock, server_side=True, do_handshake_on_connect=False), addr

    def finish_request(self, request, client_address):
        if self.tls is not None:
            request.settimeout(BODY_TIMEOUT_S)
            try:
                request.do_handshake()
            except (OSError, ssl.SSLError):  # not TLS, or a certificate the browser refused: nothing to serve
                return
        super().finish_request(request, client_address)

    def handle_error(self, request, client_address):
        # a tab closed while its response was on the way: the browser wanted nothing more, and a
        # traceback on the viewer's terminal for it would hide the lines that matter (a real
        # failure's traceback among them)
        if isinstance(sys.exc_info()[1], ConnectionError):
            return
        super().handle_error(request, client_address)


class View2DServer:
    """Serves the 2D view pages on ``host:port`` (port 0: any free port) in a thread."""

    def __init__(self, provider: Provider, host: str = "127.0.0.1", port: int = 0, access: Access = OPEN,
                 tls: ssl.SSLContext | None = None):
        handler = type("Handler", (_Handler,), {"provider": provider, "access": access})
        self.httpd = _Server((host, port), handler)
        self.httpd.tls = tls
        self.port = self.httpd.server_address[1]
        self.host = host
        self._thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self._thread.start()

    def page_url(self, token: str, host: str | None = None, access: str | None = None) -> str:
        """The tab ``token``'s page; ``access``: the token of the link the tab was opened with."""
        scheme = "https" if self.httpd.tls is not None else "http"
        return f"{scheme}://{host or self.host}:{self.port}/us?c={token}" + (f"&t={access}" if access else "")

    def stop(self):
        self.httpd.shutdown()
        self.httpd.server_close()
