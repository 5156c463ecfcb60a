"""Who may use a viewer (``navapp serve`` beyond this machine): the token decision, the 3D
viewer's front (its page, files and websocket) and the 2D view's server, headless over HTTP
and websockets. Every server here binds 127.0.0.1; the token is forced on."""

import asyncio
import ssl
import urllib.error
import urllib.request

import pytest
import websockets
from conftest import free_port
from websockets.asyncio.client import connect

from navapp.app.access import OBSERVING, REFUSED, Access, Role, decide, is_loopback, tls_context
from navapp.errors import InputError

EDITOR, OBSERVER = "e" * 20 + "ditor-token", "o" * 20 + "bserver-token"
ACCESS = Access(EDITOR, OBSERVER)


def get(url, headers=None, context=None):
    """(status, body, headers) of a GET, errors included."""
    try:
        with urllib.request.urlopen(urllib.request.Request(url, headers=headers or {}), timeout=20,
                                    context=context) as r:
            return r.status, r.read(), r.headers
    except urllib.error.HTTPError as e:
        return e.code, e.read(), e.headers


def post(url, body: bytes, context=None):
    try:
        with urllib.request.urlopen(urllib.request.Request(url, data=body, method="POST"), timeout=20,
                                    context=context) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.read()


# ---------------------------------------------------------------------- the decision
@pytest.mark.parametrize("host, loopback", [("127.0.0.1", True), ("localhost", True), ("::1", True),
                                            ("127.0.0.2", True), ("0.0.0.0", False), ("", False), ("::", False),
                                            ("192.168.1.20", False), ("or-screen.example", False)])
def test_loopback_is_told_from_the_host(host, loopback):
    assert is_loopback(host) is loopback
    access = decide(host, env={})
    assert access.required is not loopback
    if not loopback:  # a fresh random token each start, and an observer token beside it
        other = decide(host, env={})
        assert len(access.editor) >= 40 and access.editor != other.editor and access.observer != access.editor


def test_a_given_token_is_used_and_asked_for_even_on_localhost():
    assert decide("127.0.0.1", "my-own-token-1").editor == "my-own-token-1"
    assert decide("0.0.0.0", env={"NAVAPP_TOKEN": "from-the-env-2"}).editor == "from-the-env-2"
    assert decide("0.0.0.0", "flag-wins-3", env={"NAVAPP_TOKEN": "from-the-env-2"}).editor == "flag-wins-3"
    for bad in ("short", "has space in it", "plus+sign+x", "amp&ersand&x", "per%cent%20x"):
        with pytest.raises(InputError, match="at least 8 characters, each a letter"):
            decide("0.0.0.0", bad)


def test_roles_from_tokens():
    assert ACCESS.role_for(EDITOR) is Role.EDITOR and ACCESS.role_for(OBSERVER) is Role.OBSERVER
    for wrong in (None, "", EDITOR[:-1], EDITOR + "x", OBSERVER.upper()):
        assert ACCESS.role_for(wrong) is None
    assert Access().role_for(None) is Role.EDITOR  # nothing asked on localhost: as before tokens


# ---------------------------------------------------------------------- the 3D viewer's front
@pytest.fixture(scope="module")
def viser_behind_front():
    import viser

    from navapp.app.front import Front

    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    server.scene.add_icosphere("/liver_marker", radius=1.0)
    front = Front(ACCESS, server.get_port(), "127.0.0.1", free_port())
    yield server, front
    front.stop()
    server.stop()


def _viser_subprotocol():
    import viser

    return f"viser-v{viser.__version__}"


def _ws(port, query="", headers=None, ssl_context=None, scheme="ws"):
    """The messages a websocket gets within a second, or the status it was refused with."""
    async def go():
        try:
            async with connect(f"{scheme}://127.0.0.1:{port}/{query}", subprotocols=[_viser_subprotocol()],
                               additional_headers=headers or {}, ssl=ssl_context, open_timeout=20) as ws:
                got = []
                try:
                    while True:
                        got.append(await asyncio.wait_for(ws.recv(), 1.0))
                except (TimeoutError, websockets.exceptions.ConnectionClosed):
                    return got
        except websockets.exceptions.InvalidStatus as exc:
            return exc.response.status_code

    return asyncio.run(go())


def test_front_refuses_page_files_and_websocket_without_the_token(viser_behind_front):
    server, front = viser_behind_front
    base = f"http://127.0.0.1:{front.port}"
    for path in ("/", "/index.html", "/?token=", f"/?token={EDITOR[:-1]}", "/?c=anything"):
        status, body, _ = get(base + path)
        assert (status, body) == (403, REFUSED), path  # short, and nothing of the app
    status, body, _ = get(base + "/", {"Cookie": f"{front.cookie}=wrong-token-value"})
    assert status == 403
    assert _ws(front.port) == 403  # refused at the handshake: not one message
    assert _ws(front.port, "?token=nope-nope-nope") == 403
    # viser itself answers the same request (the front is what refuses)
    status, body, _ = get(f"http://127.0.0.1:{server.get_port()}/")
    assert status == 200 and b"<html" in body.lower()


def test_front_lets_the_token_in_and_keeps_it_in_a_cookie(viser_behind_front):
    server, front = viser_behind_front
    status, body, headers = get(f"http://127.0.0.1:{front.port}/?token={EDITOR}")
    assert status == 200 and b"<html" in body.lower()
    cookie = headers["Set-Cookie"]
    assert cookie.startswith(f"{front.cookie}={EDITOR};") and "HttpOnly" in cookie and "SameSite=Strict" in cookie
    # the page's own files and its websocket carry the cookie, not the query
    status, _, _ = get(f"http://127.0.0.1:{front.port}/index.html", {"Cookie": f"{front.cookie}={EDITOR}"})
    assert status == 200
    for kw in ({"headers": {"Cookie": f"{front.cookie}={EDITOR}"}}, {"query": f"?token={OBSERVER}"}):
        got = _ws(front.port, **kw)
        assert isinstance(got, list) and len(got) > 0, got  # viser's scene reaches the browser through the front


def test_front_passes_the_token_to_viser_for_the_role(viser_behind_front):
    from navapp.app.front import TOKEN_HEADER

    server, front = viser_behind_front
    seen = []
    # viser's own connect callback waits for the browser's first camera message; the websocket
    # layer's is called at once, on the same connection ``server.App._role`` reads
    ws = server._websock_server
    ws.on_client_connect(lambda c: seen.append(ws._live_connections[c.client_id].request.headers.get(TOKEN_HEADER)))
    _ws(front.port, f"?token={OBSERVER}")
    assert seen == [OBSERVER]


# ---------------------------------------------------------------------- the 2D view's server
class _Provider:
    """A 2D view provider that knows one tab and records what reaches it."""

    def __init__(self):
        self.clicks = []

    def view_known(self, token):
        return token == "tab1"

    def view_etag(self, token):
        return "e1"

    def view_state(self, token):
        return {"etag": "e1", "message": ""}

    def view_image(self, token):
        return b"\x89PNG"

    def view_click(self, token, col, row, feature, plane):
        self.clicks.append((col, row))

    def view_command(self, token, cmd, feature, plane=None):
        self.clicks.append(cmd)

    def view_pixel_ratio(self, token, ratio):
        pass

    def view_resume(self, token, previous, opened_ms=None, address=None):
        return None

    def view_going(self, token, at_ms, address):
        pass


@pytest.fixture()
def view2d():
    from navapp.app.view2d import View2DServer

    provider = _Provider()
    srv = View2DServer(provider, "127.0.0.1", 0, access=ACCESS)
    yield srv, provider
    srv.stop()


def test_view2d_refuses_a_valid_tab_without_the_token(view2d):
    srv, provider = view2d
    base = f"http://127.0.0.1:{srv.port}"
    for path in ("/us?c=tab1", "/us/state?c=tab1", "/us/image?c=tab1", "/us/page.js", f"/us?c=tab1&t={EDITOR}x"):
        status, body, _ = get(base + path)
        assert (status, body) == (403, REFUSED), path
    assert post(base + "/us/click?c=tab1", b'{"col": 1, "row": 2, "plane": 0}')[0] == 403
    assert provider.clicks == []
    status, body, _ = get(srv.page_url("tab1", access=EDITOR))
    assert status == 200 and f'data-access="{EDITOR}"'.encode() in body and b"page.js?t=" in body
    assert get(base + f"/us/page.js?t={EDITOR}")[0] == 200
    assert post(base + f"/us/click?c=tab1&t={EDITOR}", b'{"col": 1, "row": 2, "plane": 0, "feature": ""}')[0] == 200
    assert provider.clicks == [(1, 2)]


def test_view2d_observer_sees_but_its_clicks_are_refused(view2d):
    srv, provider = view2d
    base = f"http://127.0.0.1:{srv.port}"
    assert get(base + f"/us/state?c=tab1&t={OBSERVER}")[0] == 200
    status, body = post(base + f"/us/click?c=tab1&t={OBSERVER}", b'{"col": 1, "row": 2, "plane": 0, "feature": ""}')
    assert status == 403 and body.decode() == OBSERVING
    for cmd in ("Close", "Undo", "Clear plane", "Finish line"):
        assert post(base + f"/us/command?c=tab1&t={OBSERVER}", f'{{"cmd": "{cmd}"}}'.encode())[0] == 403
    assert provider.clicks == []
    assert post(base + f"/us/command?c=tab1&t={OBSERVER}", b'{"cmd": "Plane", "plane": 0}')[0] == 200  # its own view


# ---------------------------------------------------------------------- TLS
def make_cert(d):
    """A self-signed certificate for 127.0.0.1 and its key (PEM) in folder ``d``, made with
    ``cryptography``: (cert.pem, key.pem)."""
    import datetime
    import ipaddress

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "127.0.0.1")])
    now = datetime.datetime.now(datetime.UTC)
    c = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
         .serial_number(x509.random_serial_number()).not_valid_before(now - datetime.timedelta(days=1))
         .not_valid_after(now + datetime.timedelta(days=2))
         .add_extension(x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]), False)
         .sign(key, hashes.SHA256()))
    (d / "cert.pem").write_bytes(c.public_bytes(serialization.Encoding.PEM))
    (d / "key.pem").write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                                  serialization.NoEncryption()))
    return d / "cert.pem", d / "key.pem"


@pytest.fixture(scope="module")
def cert(tmp_path_factory):
    d = tmp_path_factory.mktemp("tls")
    certfile, keyfile = make_cert(d)
    return certfile, keyfile, ssl.create_default_context(cafile=str(certfile))


def test_tls_for_both_servers_and_wss(cert):
    import viser

    from navapp.app.front import Front
    from navapp.app.view2d import View2DServer

    certfile, keyfile, client = cert
    tls = tls_context(certfile, keyfile)
    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    front = Front(ACCESS, server.get_port(), "127.0.0.1", free_port(), tls)
    srv = View2DServer(_Provider(), "127.0.0.1", 0, access=ACCESS, tls=tls)
    try:
        status, body, headers = get(f"https://127.0.0.1:{front.port}/?token={EDITOR}", context=client)
        assert status == 200 and b"<html" in body.lower() and "Secure" in headers["Set-Cookie"]
        assert get(f"https://127.0.0.1:{front.port}/", context=client)[0] == 403
        got = _ws(front.port, f"?token={EDITOR}", ssl_context=client, scheme="wss")
        assert isinstance(got, list) and len(got) > 0
        assert _ws(front.port, ssl_context=client, scheme="wss") == 403
        url = srv.page_url("tab1", "127.0.0.1", EDITOR)
        assert url.startswith("https://")
        assert get(url, context=client)[0] == 200
        with pytest.raises((urllib.error.URLError, ConnectionError)):  # plain http to a TLS server gets nothing
            urllib.request.urlopen(url.replace("https", "http"), timeout=10).read()
    finally:
        srv.stop()
        front.stop()
        server.stop()


def test_tls_files_are_checked_in_one_line(cert, tmp_path):
    certfile, keyfile, _ = cert
    with pytest.raises(InputError, match="no such file"):
        tls_context(tmp_path / "missing.pem", keyfile)
    with pytest.raises(InputError, match="needs --certfile"):
        tls_context(None, keyfile)
    (tmp_path / "junk.pem").write_text("not a certificate")
    with pytest.raises(InputError, match="not a PEM certificate"):
        tls_context(tmp_path / "junk.pem", keyfile)
    assert tls_context(None, None) is None



def test_app_behind_the_front_with_tls(cert, tmp_path):
    """The viewer's own wiring: viser on loopback behind the front, both servers on TLS, the
    printed links carrying the tokens, the 2D view's links carrying the tab's token."""
    from navapp.app.server import App
    from navapp.simulation.scene import parse_scene

    certfile, keyfile, client = cert
    scene = parse_scene({"name": "tlstest", "anatomy": {"phantom": 0}, "deformation": {"mesh_edge_mm": 10.0},
                         "stylus": {"coverage": 0.2}, "ius": {"planes": 2}})
    port = free_port()
    app = App(scene, host="127.0.0.1", port=port, session_dir=tmp_path / "s", edge=12.0, k=12,
              cache_root=tmp_path / "cache", access=ACCESS, tls=tls_context(certfile, keyfile))
    try:
        assert app.url == f"https://127.0.0.1:{port}/?token={EDITOR}"
        assert app.observer_url == f"https://127.0.0.1:{port}/?token={OBSERVER}"
        assert app.server.get_host() == "127.0.0.1" and app.server.get_port() != port  # viser behind the front
        assert get(app.url, context=client)[0] == 200
        assert get(f"https://127.0.0.1:{port}/", context=client)[0] == 403
        url = app.view2d.page_url("tab1", "127.0.0.1", ACCESS.token_for(Role.OBSERVER))
        assert url.startswith("https://") and url.endswith(f"&t={OBSERVER}")
        assert get(url, context=client)[0] == 404  # let in, and the tab is unknown (nothing connected)
        assert get(url.split("&t=")[0], context=client)[0] == 403
    finally:
        app.front.stop()
        app.server.stop()
        app.view2d.stop()


def test_printed_links_name_a_host_another_machine_can_open():
    import socket

    from navapp.app.server import _link_host

    assert _link_host("0.0.0.0") == _link_host("") == _link_host("::") == socket.gethostname()
    assert _link_host("::1") == "[::1]" and _link_host("192.168.1.20") == "192.168.1.20"
