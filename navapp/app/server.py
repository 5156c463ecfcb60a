"""``navapp serve``: the navigation viewer. The only package that imports viser is this one.

``App`` builds the viewer's rooms around one ``core.Core`` (what all browsers share, under
one lock) and wires them to viser: each browser tab that connects gets a
``panels.ClientView`` with its own GUI, 3D scene nodes, camera, plane, drawing and undo.

The rooms, each a module: ``core`` (shared state, lock, start-up, change notification),
``shown`` (the registered model on show: geometry, errors, predicted errors, target
readouts), ``runs`` (registrations and the cost sweep), ``drawing`` (contours and undo),
``imaging`` (ultrasound planes), ``stylus`` (the simulated sweep), ``live`` (a tracker),
``slicer`` (results to 3D Slicer), ``view2d`` (the 2D view's page and server), ``palette``
(colours and words), ``session`` (what is saved), ``actions`` (the session's action log),
``access`` and ``front`` (who may use the viewer: tokens, roles, TLS) and ``panels`` (the GUI).

Threads: viser's callbacks, the start-up thread, the registration worker, the stylus
sweep, the tracker pump, the 2D view's HTTP server and, when a token or TLS is asked
for, the front's event loop. They meet only in the rooms'
methods, which take ``Core.lock`` around shared data and never call viser while holding it
for long.
"""

import os
import shutil
import ssl
import tempfile
import time

import viser

from .. import progress
from ..defaults import EDGE_MM, K
from ..errors import NavappError
from ..simulation.simulate import scene_preop
from .access import OPEN, Access, Role
from .actions import FILE as ACTIONS_FILE
from .actions import Act
from .core import Core, Loaded, Ready
from .drawing import Drawing
from .front import TOKEN_HEADER, Front
from .imaging import Imaging
from .live import Live
from .panels import ClientView
from .runs import Runs
from .session import export
from .shown import Shown
from .slicer import Slicer
from .state import ClientState
from .stylus import Stylus
from .view2d import View2DServer
from .view2d.provider import View2D
from .worker import RegistrationWorker

STREAM_HZ = 20.0  # a running registration's states reach the browsers at most this often


class App:
    """The viewer. ``start()`` begins the start-up work in a thread and returns an event set
    when the registration model is ready (or start-up failed: ``core.failed``)."""

    def __init__(self, scene, host="127.0.0.1", port=8080, session_dir=None, edge=EDGE_MM, k=K, cache_root=None,
                 view2d_port: int | None = 0, tracking=None, results=None, access: Access = OPEN,
                 tls: ssl.SSLContext | None = None):
        preop = scene_preop(scene)
        core = self.core = Core(scene, preop, edge, k, cache_root, session_dir)
        # the rooms, each given what it uses; none knows the App
        def following():
            return self.live.following

        self.slicer = Slicer(preop, results)
        self.shown = Shown(core, self.slicer)
        self.drawing = Drawing(core)
        self.imaging = Imaging(core, following)
        self.stylus = Stylus(core)
        self.live = Live(core, self.shown, self.slicer, self.imaging, tracking)
        self.runs = Runs(core, self.shown, self.slicer, following)
        self.view2d_state = View2D(core, self.imaging, self.shown, self.drawing)
        self.access, self.front = access, None
        scheme = "https" if tls is not None else "http"
        if access.required or tls is not None:
            # viser on loopback behind a front that asks for the token and serves TLS (``front``)
            self.server = viser.ViserServer(host="127.0.0.1", port=0, label="navapp", verbose=False)
            self.front = _front(access, self.server.get_port(), host, port, tls)
            viewer_port = self.front.port
        else:
            self.server = viser.ViserServer(host=host, port=port, label="navapp", verbose=False)
            viewer_port = self.server.get_port()
        site = _link_host(host)
        self.url = f"{scheme}://{site}:{viewer_port}" + (f"/?token={access.editor}" if access.editor else "")
        self.observer_url = (f"{scheme}://{site}:{viewer_port}/?token={access.observer}" if access.observer
                             else None)
        self.view2d = _view2d_server(self.view2d_state, host if host not in ("", "::") else "0.0.0.0",
                                     view2d_port, viewer_port, access, tls)
        self.view2d_host = _other_site(host)
        self.server.scene.set_up_direction("+z")
        cam = self.server.initial_camera
        from .panels.layers import HOME_VIEW_MM

        cam.up_direction, cam.near, cam.far = (0.0, 0.0, 1.0), 1.0, 5000.0
        cam.look_at, cam.position = self.core.centre, self.core.centre + HOME_VIEW_MM
        self.server.gui.configure_theme(control_width="large", dark_mode=False)
        # no cascaded shadows and no image-based lighting: on a machine without a GPU (WebGL
        # drawn in software) they cost the idle viewer more than a core (docs/decisions/viewer.md,
        # "The viewer's lighting"), and a shadow on a semi-transparent liver hides what is inside
        self.server.scene.configure_default_lights(enabled=True, cast_shadow=False)
        self.server.scene.configure_environment_map(hdri=None)
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)

    def start(self):
        return self.core.start(self._loaded, self._ready)

    def _loaded(self, loaded: Loaded):
        from .session import read_tabs

        # the tabs open before a restart (a kill -9 included) take their work back as they reconnect
        self.drawing.restore_tabs(read_tabs(loaded.session.folder))
        self.live.connect()

    def _ready(self, ready: Ready):
        core = self.core
        with core.lock:
            core.model, core.truth_nodes = ready.model, ready.truth_nodes
            core.worker = RegistrationWorker(ready.model, self.runs.on_update, self.runs.on_done, self.runs.on_error,
                                             max_rate_hz=STREAM_HZ)
            self.shown.restore()
        self.runs.restore_worst()
        self.runs.prepare_held()  # the supports the session or the case states: their model made ahead

    def export(self, cs: ClientState | None = None):
        """The registered model, the data and the action log into the session's export/ folder,
        an action of ``cs``: (folder or None, message)."""
        core = self.core
        if core.last_reg is None:
            return None, "Register first: the export holds the registered model."
        sd, session = core.need_scene()
        out = session.folder / "export"
        files = export(out, core.last_reg, sd, core.data())
        shown = core.result.run if core.result is not None else "?"
        core.record(cs, Act.EXPORT, f"{len(files) + 1} files to {out} (result on show: {shown})")
        if core.actions is not None:  # after its own line: the export's log ends with the export
            shutil.copy2(core.actions.path, out / ACTIONS_FILE)
        return out, f"{len(files) + 1} files written to {out}"

    def _connect(self, client):
        core = self.core
        cs = core.new_client_state(client.client_id, self._role(client))
        view = ClientView(self, client, cs)
        with core.lock:
            core.views[client.client_id] = view
        view.refresh_all()
        # viser calls this on a worker thread after the tab's first camera report, and runs the
        # camera callbacks at once, before the view has registered its own; the 2D page's first
        # pixel-ratio report may also come while the view is built and find none to lay out.
        # Both are read now: the view is registered, so every later report reaches it.
        view.camera_changed()

    def _disconnect(self, client):
        core = self.core
        with core.lock:
            view = core.views.pop(client.client_id, None)
            if view is not None:
                core.park(view.cs.token)
        if view is not None:
            view.layers.tween.close()  # no frames to a closed tab

    def _role(self, client) -> Role:
        """The tab's role, from the token the front passed on with its websocket. viser's
        client handle does not carry its request, so it is read from viser's connection; when
        it cannot be read (a later viser), or a websocket reached viser's loopback port without
        the front, the tab only watches: never more than its link gives."""
        if not self.access.required:
            return Role.EDITOR
        try:
            request = self.server._websock_server._live_connections[client.client_id].request
            token = request.headers.get(TOKEN_HEADER) if request is not None else None
        except (AttributeError, KeyError):
            token = None
        return self.access.role_for(token) or Role.OBSERVER


def _link_host(host: str) -> str:
    """The host of the printed links: this machine's name for a wildcard address (0.0.0.0 is
    no address another machine can open), an IPv6 address in brackets."""
    if host in ("0.0.0.0", "::", ""):
        import socket

        return socket.gethostname()
    return f"[{host}]" if ":" in host else host


def _front(access: Access, backend_port: int, host: str, port: int, tls) -> Front:
    """The front on ``port``, or the next free one as viser does for itself."""
    for p in range(port, min(port + 100, 65536)) if port else (0,):
        try:
            return Front(access, backend_port, host, p, tls)
        except OSError:
            continue
    raise NavappError(f"no free port from {port} to {min(port + 99, 65535)} on {host}")


def _other_site(host: str) -> str:
    """The host name the 2D view's frame is loaded from: another *site* than the viewer's
    page where possible (127.0.0.1 ↔ localhost), so that Chromium gives the frame its own
    renderer process and a busy 3D view (software WebGL) does not delay the clicks'
    acknowledgements (median 20–40 ms instead of spikes of 1.5 s, measured headless)."""
    if host == "127.0.0.1":
        return "localhost"
    if host == "localhost":
        return "127.0.0.1"
    if host in ("0.0.0.0", "::", ""):
        import socket

        return socket.gethostname()
    return host



def _view2d_server(provider, host: str, port: int | None, viewer_port: int, access: Access = OPEN,
                   tls: ssl.SSLContext | None = None) -> View2DServer:
    """The 2D view's server on ``port`` (0: any free port; None: the viewer's port + 1 where
    free, else any). A fixed port lets a tab left open across a server restart reach the new
    server, which tells it to reload (its view is unknown there) instead of "not answering"."""
    if port is None:
        try:
            return View2DServer(provider, host=host, port=viewer_port + 1 if viewer_port < 65535 else 0,
                                access=access, tls=tls)
        except OSError:  # taken: another program, or a second navapp beside this one
            port = 0
    return View2DServer(provider, host=host, port=port, access=access, tls=tls)


def serve(scene, host="127.0.0.1", port=8080, session_dir=None, edge=EDGE_MM, k=K, cache_root=None, view2d_port=None,
          tracking=None, slicer=None, access: Access = OPEN, tls: ssl.SSLContext | None = None):
    """Start the viewer and block until interrupted. ``tracking``: a ``TrackingConfig`` to
    connect to an OpenIGTLink server (PLUS, 3D Slicer, ``navapp replay``); ``slicer``:
    where registrations go, ``(host, port)`` of Slicer's OpenIGTLinkIF connector as server,
    or ``(None, port)`` to listen for it as client."""
    results = None
    if slicer is not None:
        from ..tracking.results import ResultsSender

        host_s, port_s = slicer
        results = ResultsSender.connect(host_s, port_s) if host_s else ResultsSender.serve(port_s)
    app = App(scene, host, port, session_dir, edge, k, cache_root, view2d_port, tracking, results, access, tls)
    app.core.log = lambda line: progress.echo(f"navapp: {line}")
    print(f"navapp: viewer at {app.url}  (Ctrl+C to stop)", flush=True)
    if app.observer_url is not None:
        print(f"navapp: observer link (watches, changes nothing): {app.observer_url}", flush=True)
    if results is not None:
        where = f"to {slicer[0]}:{slicer[1]}" if slicer[0] else f"on 127.0.0.1:{results.port} (Slicer connects)"
        print(f"navapp: registrations go to 3D Slicer over OpenIGTLink {where}", flush=True)
    try:
        ready = app.start()
        while not ready.wait(3600):
            pass
        if app.core.failed is not None:
            _stop_on_failure(app)
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        app.view2d.stop()
        if app.front is not None:
            app.front.stop()
        app.live.stop()
        if results is not None:
            results.close()
    return app


def _stop_on_failure(app: App):
    """End ``navapp serve`` after a failed start-up, saying why in the browsers and (through
    the CLI, exit 2) on the terminal. Stopping rather than offering a retry: what fails at
    start-up is decided by the command's input (the scene, the case folder, --edge, --k,
    the memory budget; meshing no longer depends on how busy the machine is), so a retry
    would fail the same way, and a process left up with a dead viewer looks alive to the
    user and to any script that waits for it."""
    message = app.core.failed
    if app.core.failed_traceback is not None:  # a bug: the one line names where its traceback is
        fd, path = tempfile.mkstemp(prefix="navapp-serve-", suffix=".traceback.txt")
        with os.fdopen(fd, "w") as f:
            f.write(app.core.failed_traceback)
        message = f"{message} (a bug in navapp: the traceback is in {path})"
    app.core.set_stage(f"Error: {message}. The viewer has stopped (its terminal says the same): "
                       f"run navapp serve again once this is fixed.", 0.0)
    app.server.flush()
    time.sleep(0.5)  # let the browsers receive it before the server closes
    app.server.stop()
    raise NavappError(f"the viewer could not start: {message}")
