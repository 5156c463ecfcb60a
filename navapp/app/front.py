"""The 3D viewer's authenticating front: what a browser reaches when the viewer asks for a
token or serves TLS. viser binds 127.0.0.1 behind it; the front (the ``websockets`` library
viser itself is built on) listens on ``--host``, refuses with a short 403 any page, file or
websocket without a valid token, and passes the rest through: files as HTTP, the websocket
message by message. Why a front rather than a hook in viser: docs/decisions/viewer.md, "Who may
use a viewer".

The token comes in the URL (``?token=``) and is then kept in a cookie of this port, so the
page's own files and its websocket (which carry no query) are let in too. The websocket to
viser carries the token in a header (``TOKEN_HEADER``), from which the viewer tells each
tab's role (``server.App``).
"""

from __future__ import annotations

import asyncio
import http.client
import logging
import ssl
import threading
from http import HTTPStatus
from urllib.parse import parse_qs, urlparse

import websockets
from websockets.asyncio.client import connect
from websockets.asyncio.server import ServerConnection, serve
from websockets.datastructures import Headers
from websockets.http11 import Request, Response

from .access import REFUSED, Access

TOKEN_HEADER = "X-Navapp-Token"
MAX_MESSAGE = 64 * 1024 * 1024  # viser allows 50 MB (a rendered image); a little more here
BACKEND_TIMEOUT_S = 30.0
PASSED_HEADERS = ("Content-Type", "Content-Encoding", "Cache-Control", "ETag", "Last-Modified")

log = logging.getLogger(__name__)


class _Quiet(logging.Filter):
    """Plain HTTP requests answered by a websocket server are logged as failed handshakes;
    they are the pages and files this front serves, not failures."""

    def filter(self, record):
        return not record.getMessage().startswith(("opening handshake failed", "connection rejected"))


class Front:
    """Listens on ``host:port`` (0: any free port) in a thread and passes what a valid token
    lets in to viser on ``127.0.0.1:backend_port``."""

    def __init__(self, access: Access, backend_port: int, host: str = "127.0.0.1", port: int = 0,
                 tls: ssl.SSLContext | None = None):
        self.access, self.backend_port, self.host, self.tls = access, backend_port, host, tls
        self.cookie = f"navapp-{port}"  # renamed once the port is known: a cookie is per host, not per port
        self._logger = logging.getLogger("navapp.front.websockets")
        self._logger.addFilter(_Quiet())
        self._loop = asyncio.new_event_loop()
        self._stop: asyncio.Event | None = None
        started = threading.Event()
        failed: list[BaseException] = []
        self.port = port

        async def main():
            self._stop = asyncio.Event()
            try:
                server = await serve(self._ws, host, port, process_request=self._request, ssl=tls,
                                     select_subprotocol=_first_offered, max_size=MAX_MESSAGE, compression=None,
                                     logger=self._logger)
            except OSError as exc:
                failed.append(exc)
                started.set()
                return
            self.port = server.sockets[0].getsockname()[1]
            self.cookie = f"navapp-{self.port}"
            started.set()
            async with server:
                await self._stop.wait()

        self._thread = threading.Thread(target=self._loop.run_until_complete, args=(main(),), daemon=True,
                                        name="navapp-front")
        self._thread.start()
        started.wait()
        if failed:
            raise failed[0]

    # ------------------------------------------------------------------ the gate
    def _token(self, request: Request) -> tuple[str | None, bool]:
        """The token a request carries, and whether it came in the URL (then kept in a cookie)."""
        q = parse_qs(urlparse(request.path).query)
        if q.get("token"):
            return q["token"][0], True
        for part in request.headers.get("Cookie", "").split(";"):
            name, _, value = part.strip().partition("=")
            if name == self.cookie:
                return value, False
        return None, False

    async def _request(self, connection: ServerConnection, request: Request) -> Response | None:
        token, in_url = self._token(request)
        if self.access.role_for(token) is None:
            return Response(HTTPStatus.FORBIDDEN, "Forbidden",
                            Headers({"Content-Type": "text/plain; charset=utf-8", "Cache-Control": "no-store",
                                     "Content-Length": str(len(REFUSED))}), REFUSED)
        if request.headers.get("Upgrade", "").lower() == "websocket":
            connection.navapp_token = token  # type: ignore[attr-defined]  # for _ws, on this connection
            return None
        try:
            status, headers, body = await asyncio.to_thread(self._fetch, request)
        except OSError as exc:
            log.warning("viewer front: %s from viser failed: %s", urlparse(request.path).path, exc)
            return Response(HTTPStatus.BAD_GATEWAY, "Bad Gateway", Headers({"Content-Length": "0"}), b"")
        headers["Content-Length"] = str(len(body))
        if in_url and token:
            secure = "; Secure" if self.tls is not None else ""
            headers["Set-Cookie"] = f"{self.cookie}={token}; Path=/; HttpOnly; SameSite=Strict{secure}"
        return Response(status, HTTPStatus(status).phrase, headers, body)

    def _fetch(self, request: Request) -> tuple[int, Headers, bytes]:
        conn = http.client.HTTPConnection("127.0.0.1", self.backend_port, timeout=BACKEND_TIMEOUT_S)
        try:
            conn.request("GET", request.path, headers={"Accept-Encoding": request.headers.get("Accept-Encoding", "")})
            r = conn.getresponse()
            body = r.read()
            headers = Headers({k: r.headers[k] for k in PASSED_HEADERS if r.headers.get(k)})
            return r.status, headers, body
        finally:
            conn.close()

    # ------------------------------------------------------------------ the websocket
    async def _ws(self, client: ServerConnection):
        token = getattr(client, "navapp_token", None)
        sub = [client.subprotocol] if client.subprotocol else None
        try:
            backend = await connect(f"ws://127.0.0.1:{self.backend_port}/", subprotocols=sub,
                                    additional_headers={TOKEN_HEADER: token or ""}, max_size=MAX_MESSAGE,
                                    compression=None, open_timeout=BACKEND_TIMEOUT_S)
        except (OSError, websockets.exceptions.WebSocketException) as exc:
            log.warning("viewer front: websocket to viser failed: %s", exc)
            await client.close(1011, "the viewer is not answering")
            return
        async with backend:
            pumps = [asyncio.create_task(_pump(client, backend)), asyncio.create_task(_pump(backend, client))]
            await asyncio.wait(pumps, return_when=asyncio.FIRST_COMPLETED)
            for p in pumps:
                p.cancel()
            await asyncio.gather(*pumps, return_exceptions=True)
            for a, b in ((client, backend), (backend, client)):
                if a.close_code is not None:  # the side that closed first: the other learns its code
                    await b.close(_sendable(a.close_code), a.close_reason or "")
            await client.close()

    def stop(self):
        if self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(timeout=5.0)


async def _pump(src, dst):
    try:
        async for message in src:
            await dst.send(message)
    except websockets.exceptions.ConnectionClosed:
        pass


def _sendable(code: int) -> int:
    """A close code that may be sent (1005, 1006 and 1015 only describe a closure)."""
    return 1000 if code in (1005, 1006, 1015) else code


def _first_offered(connection, subprotocols):
    """viser's client offers one subprotocol naming its version; viser checks it."""
    return subprotocols[0] if subprotocols else None
