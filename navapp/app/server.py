"""``navapp serve``: the navigation viewer. The only package that imports viser is this one.

``App`` holds what all browsers share (scene data, session, registration model, the
registered result) and performs every action on it under one lock; each browser tab gets a
``ClientView`` (``panels/``) with its own GUI, 3D scene nodes, camera, plane, drawing and
undo. A change to shared data bumps ``App.version`` and is pushed to every view.

Threads: viser's callbacks, the start-up thread (``start()``), the registration worker, the
stylus animation and the 2D view's HTTP server. They meet only in ``App``'s methods, which
take ``App.lock`` around shared data and never call back into viser while holding it for
long.
"""

import io
import secrets
import threading
import time
from pathlib import Path

import numpy as np
import viser

from .. import progress
from ..anatomy.phantom import make_phantom
from ..defaults import EDGE_MM, K
from ..errors import NavappError
from ..evaluation.cost import lm_sweep
from ..registration.libr import LibrResult
from ..registration.pipeline import Registration, deform_points, prepare
from ..registration.rigid import RigidResult
from ..registration.targets import registered_targets, target_interpolation
from ..simulation.scenedata import acquire_free_plane, load_scene_data
from .contours import CENTERLINE_OF, DRAWABLE, Contour, contour_pixels
from .live import LIVE_PLANE_BASE
from .overlays import Overlay, section_pixels
from .session import default_folder, export, open_session
from .state import Action, ClientState, RegisteredState, StateGeometry, TargetBand
from .view2d import View2DServer
from .worker import RegistrationWorker, cancelled

STYLUS_MM_PER_S = 40.0  # a steady sweep of the tip, at "1×"
FRAME_S = 0.05
FREE_PLANE_BASE = 100  # indices of planes placed by hand start here
RUN_LABELS = {"rigid": "rigid", "surface": "deformable, surface", "all": "deformable, all data",
              "warm": "deformable, all data (warm)"}
VESSEL_SHORT = {"portal_contour": "PV", "hepatic_contour": "HV"}
# 2D overlay colours: preoperative (rigidly placed) dashed, registered solid
OVERLAY_STYLE = {
    "liver": ("#e0b090", "#ffd040"), "portal": ("#ff8080", "#ff2020"), "hepatic": ("#80a0ff", "#2f6bff"),
    "target": ("#c080ff", "#e000ff"),
}
DRAWN_COLOURS = {"portal_contour": "#ff9a1f", "hepatic_contour": "#2ee6ff", "posterior": "#ffee55"}


class App:
    """The shared side of the viewer. ``start()`` begins the start-up work in a thread and
    returns an event set when the registration model is ready (or start-up failed)."""

    def __init__(self, scene, host="127.0.0.1", port=8080, session_dir=None, edge=EDGE_MM, k=K, cache_root=None,
                 view2d_port=0, tracking=None, results=None):
        self.scene, self.edge, self.k, self.cache_root = scene, edge, k, cache_root
        self.session_dir = session_dir
        self.lock = threading.RLock()
        self.version = 0  # bumped on every change to shared data
        self.sd = None
        self.session = None
        self.planes: dict = {}
        self.model = None
        self.worker: RegistrationWorker | None = None
        self.result: RegisteredState | None = None  # the registered model on show
        self.last_reg: Registration | None = None  # what Export and a warm start use
        self.truth_nodes = None
        self.stage = "Starting…"
        self.stage_fraction: float | None = None
        self.failed: str | None = None
        self.ready = threading.Event()  # set when start-up has finished (or failed: see .failed)
        self.run: dict | None = None  # the registration in progress: label, points, t0, trace
        self.stylus_thread = None
        self.stylus_stop = threading.Event()
        self.stylus_tip: np.ndarray | None = None
        self._sweeping = False
        self.states: dict[str, ClientState] = {}  # token → per-browser state
        self.views: dict = {}  # client_id → ClientView
        self._pending: list[str] = []  # view refreshes not yet done, coalesced
        self._pending_cv = threading.Condition()
        self._refreshed = 0
        threading.Thread(target=self._refresher, daemon=True, name="navapp-refresh").start()
        self._overlay_cache: dict = {}
        self._image_cache: dict = {}
        self._target_B = None  # interpolation matrix of the target points in the registration mesh
        self._geometry: StateGeometry | None = None  # the last state's geometry (see geometry())
        self.tracking_config = tracking  # a tracking.TrackingConfig: connect to a tracker once the scene is ready
        self.live = None  # LiveLink while connected to a tracker
        self.results = results  # a tracking.ResultsSender: registrations go to 3D Slicer
        self.results_error: str | None = None
        self._live_start: int | None = None  # live points before the recording in progress (its undo point)
        self._live_shown = 0.0  # when a live registration was last drawn
        self._results_sent = 0.0  # when results last went to Slicer
        self.preop = make_phantom(scene.phantom) if scene.phantom is not None else self._read_case_preop()
        self.centre = self.preop.liver.vertices.mean(0)
        self.server = viser.ViserServer(host=host, port=port, label="navapp", verbose=False)
        self.url = f"http://{self.server.get_host()}:{self.server.get_port()}"
        self.view2d = View2DServer(self, host=host if host not in ("", "::") else "0.0.0.0", port=view2d_port)
        self.view2d_host = _other_site(host)
        self.server.scene.set_up_direction("+z")
        cam = self.server.initial_camera
        from .panels.layers import HOME_VIEW_MM

        cam.up_direction, cam.near, cam.far = (0.0, 0.0, 1.0), 1.0, 5000.0
        cam.look_at, cam.position = self.centre, self.centre + HOME_VIEW_MM
        self.server.gui.configure_theme(control_width="large", dark_mode=False)
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)

    def _read_case_preop(self):
        from ..anatomy.caseio import read_case

        return read_case(self.scene.case).preop

    # ------------------------------------------------------------------ clients
    def new_client_state(self, client_id: int = -1) -> ClientState:
        """A browser's own state (also used headless, by tests and scripts)."""
        cs = ClientState(client_id, secrets.token_urlsafe(8))
        with self.lock:
            self.states[cs.token] = cs
        return cs

    def _connect(self, client):
        from .panels import ClientView

        cs = self.new_client_state(client.client_id)
        view = ClientView(self, client, cs)
        with self.lock:
            self.views[client.client_id] = view
        view.refresh_all()

    def _disconnect(self, client):
        with self.lock:
            view = self.views.pop(client.client_id, None)
            if view is not None:
                self.states.pop(view.cs.token, None)

    def each_view(self, fn):
        """Call ``fn(view)`` for every connected browser; one failing view does not stop the others."""
        with self.lock:
            views = list(self.views.values())
        for v in views:
            try:
                fn(v)
            except Exception:  # a tab closing mid-update
                pass

    def changed(self, what: str = "data"):
        """Shared data changed: bump the version and save the session now (so nothing
        acknowledged can be lost), then refresh every view from the refresher thread, so
        that a click is acknowledged without waiting for the GUIs of all browsers."""
        with self.lock:
            self.version += 1
            if self.session is not None and what in ("data", "result", "log"):
                self.session.save(self.sd, self.planes)
        with self._pending_cv:
            if what not in self._pending:
                self._pending.append(what)
            self._pending_cv.notify()

    def _refresher(self):
        while True:
            with self._pending_cv:
                while not self._pending:
                    self._pending_cv.wait()
                todo, self._pending = self._pending, []
            for what in todo:
                self.each_view(lambda v, what=what: v.refresh(what))
            with self._pending_cv:
                self._refreshed += 1
                self._pending_cv.notify_all()

    def settle(self, timeout=10.0) -> bool:
        """Wait until every change so far has reached the views (for tests and scripts)."""
        t_end = time.monotonic() + timeout
        with self._pending_cv:
            while self._pending:
                if not self._pending_cv.wait(max(0.0, t_end - time.monotonic())):
                    return False
        return True

    def notify(self, title, body, error=False):
        self.each_view(lambda v: v.notify(title, body, error))

    def set_stage(self, text, fraction=None):
        self.stage, self.stage_fraction = text, fraction
        self.each_view(lambda v: v.refresh("status"))

    # ------------------------------------------------------------------ start-up
    def start(self) -> threading.Event:
        threading.Thread(target=self._start_up, daemon=True, name="navapp-startup").start()
        return self.ready

    def _start_up(self):
        stage = {"name": "", "t0": time.monotonic()}

        def on_progress(desc, fraction):
            if desc != stage["name"]:
                stage.update(name=desc, t0=time.monotonic())
            eta = ""
            elapsed = time.monotonic() - stage["t0"]
            if fraction is not None and 0.02 < fraction < 1 and elapsed > 1.0:
                eta = f", about {_duration(elapsed * (1 - fraction) / fraction)} left"
            pct = f" — {100 * fraction:.0f} %" if fraction is not None else ""
            self.set_stage(f"{stage['what']}: {desc}{pct}{eta}", fraction)

        listener = progress.add_listener(on_progress)
        try:
            stage["what"] = "Simulating the intraoperative scene (true deformation, stylus sweep, ultrasound; " \
                            "cached after the first start)"
            self.set_stage(stage["what"])
            sd = load_scene_data(self.scene, self.cache_root, self.edge)
            folder = Path(self.session_dir) if self.session_dir else default_folder(sd)
            session, planes = open_session(folder, sd)
            with self.lock:
                self.sd, self.session, self.planes = sd, session, planes
            self.changed("scene")
            if self.tracking_config is not None:
                from .live import LiveLink

                self.live = LiveLink(self, self.tracking_config).start()
                self.changed("live")
            stage["what"] = (f"Building the registration model (mesh at {self.edge:g} mm, basis of k = {self.k} "
                             f"control points; cached after the first start)")
            self.set_stage(stage["what"])
            model, _ = prepare(sd.case, self.edge, self.k, self.cache_root)
            x0 = sd.case.targets[:, :3] if sd.case.targets is not None else None
            truth = None
            if x0 is not None and x0.shape == model.basis.nodes.shape and np.allclose(x0, model.basis.nodes):
                truth = sd.case.targets[:, 3:]
            with self.lock:
                self.model, self.truth_nodes = model, truth
                self.worker = RegistrationWorker(model, self._on_update, self._on_done, self._on_error,
                                                 max_rate_hz=20.0)
                self._restore_result()
            self.set_stage(f"Ready. {len(model.basis.nodes):,} nodes, k = {self.k}. Session: {session.folder}", 1.0)
            self.changed("model")
        except NavappError as exc:
            self.failed = str(exc)
            self.set_stage(f"Error: {exc}", 0.0)
            self.notify("navapp", str(exc), error=True)
        except Exception as exc:  # shown, not lost in a thread
            self.failed = f"{exc.__class__.__name__}: {exc}"
            self.set_stage(f"Error while starting: {self.failed}", 0.0)
            self.notify("navapp", self.failed, error=True)
            raise
        finally:
            progress.remove_listener(listener)
            self.ready.set()

    def _restore_result(self):
        """The registered model stored in the session (rigid pose and β) after a restart."""
        d = self.session.result
        if not d:
            return
        rigid = RigidResult(np.array(d["R"]), np.array(d["t"]), 0, float(d.get("rms_mm", np.nan)))
        beta = None if d.get("beta") is None else np.array(d["beta"], float)
        if beta is not None and len(beta) != self.model.basis.Ju.shape[1] + 6:
            return  # another basis size (different --k): nothing to restore
        libr = None if beta is None else LibrResult(beta, float("nan"), 0, "restored", [], [], {}, 0.0, {})
        # the data in the model frame (T⁻¹), for the predicted error: what the session holds now
        inv = {k: (np.asarray(v, float) - rigid.t) @ rigid.R for k, v in self.data("all").items()}
        reg = Registration(self.model, rigid, libr, inv)
        self.last_reg = self.worker.last = reg
        predicted = self._predict(reg)
        saved = d.get("predicted_mm")
        if saved is not None and len(saved) == len(self.model.basis.surface):
            predicted = (np.array(saved, float), [TargetBand(*b) for b in d.get("target_bands", [])])
        self.result = RegisteredState(d.get("run", "restored"), rigid, beta, self._node_error(rigid, beta),
                                      *predicted)
        self.send_results(reg)  # queued: a Slicer connecting later receives the result on show

    def _predict(self, reg) -> tuple:
        """The predicted error without the truth (``registration.uncertainty``): (S,) at the
        surface nodes, and a ``TargetBand`` per target; (None, []) for a rigid result or
        when it cannot be had (too few data)."""
        from ..registration.uncertainty import estimate_error

        if reg.libr is None or not reg.data_model_frame:
            return None, []
        try:
            surface = estimate_error(reg, nodes=self.model.basis.surface).predicted_mm
            bands = []
            if self.preop.targets:
                est = estimate_error(reg, points=np.array([t.centre for t in self.preop.targets]))
                bands = [TargetBand(t.name, float(e), float(lo), float(hi)) for t, e, lo, hi in
                         zip(self.preop.targets, est.predicted_mm, est.lower_mm, est.upper_mm, strict=True)]
            return surface, bands
        except (np.linalg.LinAlgError, ValueError):
            return None, []

    def surface_error(self, cs: ClientState, node_error=None) -> np.ndarray | None:
        """(S,) the error this tab colours the registered surface by: the predicted error
        of the result on show, or the true error (``node_error`` (M,) of a streaming state,
        else the result's) when the truth is known and the tab chose it."""
        res = self.result
        if cs.error_source == "predicted" or self.truth_nodes is None:
            return None if res is None or node_error is not None else res.predicted_mm
        e = node_error if node_error is not None else (res.node_error_mm if res is not None else None)
        return None if e is None else e[self.model.basis.surface]

    def suggest_plane(self, cs: ClientState, on_done) -> str | None:
        """Rank candidate probe poses by the expected drop of the mean predicted error
        (``registration.next_plane``) in the worker thread; the best is acquired as this
        tab's plane and ``on_done(message)`` says what was suggested."""
        from ..registration.next_plane import suggest_planes

        reg = self.last_reg
        if reg is None or reg.libr is None or not reg.data_model_frame:
            return "Register deformably first: the suggestion ranks planes by what they would add to a fit."
        if self.live is not None and self.live.follower.on:
            return "Live re-registration is on: switch it off first."

        def job(cancel):
            try:
                return suggest_planes(reg, preop=self.preop)
            except Exception as exc:  # said in the panel; the button comes back
                return f"No suggestion: {exc.__class__.__name__}: {exc}"

        def done(sug):
            if isinstance(sug, str) or not sug.candidates:
                on_done(sug if isinstance(sug, str) else "No candidate pose on the anterior surface.")
                return
            best = sug.best
            with self.lock:  # suggested again at the same pose (unchanged fit): show that plane, make no copy
                same = [i for i, p in self.planes.items() if i >= FREE_PLANE_BASE and p.orientation == "free"
                        and np.allclose(p.probe_to_tracker, best.pose, atol=1e-6)]
            if same:
                index = same[0]
                self.show_plane(cs, index)
            else:
                index = self.place_probe(cs, best.pose)
            o = best.pose[:3, 3]
            feats = ", ".join(FEATURE_WORDS.get(f, f) for f in sorted(best.features)) or "nothing"
            on_done(f"Suggested: a {best.orientation} plane with its probe face at ({o[0]:.0f}, {o[1]:.0f}, "
                    f"{o[2]:.0f}) mm (now {self.plane_label(index)}), expected to show {feats}; mean predicted "
                    f"error over the whole organ (sampled mesh nodes) {sug.current_mean_mm:.2f} → "
                    f"{best.predicted_mean_mm:.2f} mm. "
                    f"{len(sug.candidates)} poses ranked in {sug.seconds:.1f} s. Add its segmentation or draw on it.")

        ok = self.worker is not None and self.worker.submit(job, done)
        return None if ok else "A registration is running; try again when it has finished."

    # ------------------------------------------------------------------ derived geometry
    def node_positions(self, rigid, beta) -> np.ndarray:
        """All mesh nodes at state β in tracker space, (M, 3) mm (eq. 8 through pipeline.deform_points)."""
        import scipy.sparse as sp

        nodes = self.model.basis.nodes
        if beta is None:
            return rigid.apply(nodes)
        return rigid.apply(deform_points(self.model.basis, self.model.centroid, beta, nodes,
                                         B=sp.identity(len(nodes), format="csr")))

    def _node_error(self, rigid, beta):
        if self.truth_nodes is None:
            return None
        return np.linalg.norm(self.node_positions(rigid, beta) - self.truth_nodes, axis=1)

    def geometry(self, rigid=None, beta=None, surfaces=None) -> StateGeometry:
        """The model at a registered state, computed once per state (the last one is kept):
        by default the state on show — the streaming one while a registration runs, else
        the result, else the preoperative model as-is. ``surfaces``: the worker's vertices
        for this state when it already has them (name → (V, 3))."""
        if rigid is None:
            run = self.run
            if run is not None and "state" in run:
                rigid, beta = run["state"]
            elif self.result is not None:
                rigid, beta = self.result.rigid, self.result.beta
        g = self._geometry
        if g is not None and g.rigid is rigid and g.beta is beta:
            return g
        pre = self.preop.targets
        if rigid is None or self.model is None:
            g = StateGeometry(None, None, {}, pre)
        else:
            if surfaces is None:
                assert self.worker is not None  # the model (hence the worker) exists: rigid is not None
                surfaces = self.worker.surfaces(rigid, beta)
            cells = {name: self.model.features[name].cells for name in surfaces}
            reg = Registration(self.model, rigid, None, {})  # transform: rigid ∘ eq. 8 at β
            if pre and self._target_B is None:  # locating the target points in the mesh once
                self._target_B = target_interpolation(reg, pre)
            moved = registered_targets(reg, pre, beta, self._target_B) if pre else []
            g = StateGeometry(rigid, beta, {n: (v, cells[n]) for n, v in surfaces.items()}, moved)
        self._geometry = g
        return g

    def plane_label(self, i) -> str:
        p = self.planes[i]
        if p.orientation == "live":
            return f"live {i - LIVE_PLANE_BASE + 1} (tracked frame)"
        vessels = sorted({VESSEL_SHORT[f] for f in p.features if f in VESSEL_SHORT})
        what = ", ".join(vessels) if vessels else "no vessel"
        name = f"{i + 1} ({p.orientation})" if i < FREE_PLANE_BASE else f"free {i - FREE_PLANE_BASE + 1}"
        return f"{name} — {what}"

    def plane_from_label(self, label):
        for i in self.planes:
            if self.plane_label(i) == label:
                return i
        return None

    # ------------------------------------------------------------------ stylus
    def start_stylus(self, speed=lambda: 1.0) -> bool:
        """Start (or stop, if running) the stylus sweep; ``speed()`` is read every frame."""
        if self.sd is None:
            return False
        if self._sweeping:
            self.stylus_stop.set()
            return True
        self.stylus_stop.clear()
        self._sweeping = True
        self.stylus_thread = threading.Thread(target=self._sweep_stylus, args=(speed,), daemon=True)
        self.stylus_thread.start()
        return True

    @property
    def sweeping(self) -> bool:
        return self._sweeping

    def _sweep_stylus(self, speed):
        path = self.sd.stylus_path
        with self.lock:
            i = min(self.session.stylus_count, len(path))
            start = i
        pos = path[i] if i < len(path) else path[-1]
        last_saved = time.monotonic()
        while i < len(path) and not self.stylus_stop.is_set():
            step = STYLUS_MM_PER_S * speed() * FRAME_S
            while step > 0 and i < len(path):
                d = np.linalg.norm(path[i] - pos)
                if d <= step:
                    pos, step, i = path[i], step - d, i + 1
                else:
                    pos, step = pos + (path[i] - pos) * step / d, 0.0
            self.stylus_tip = pos
            with self.lock:
                self.session.stylus_count = i
            self.each_view(lambda v, pos=pos: v.show_stylus(pos))
            if time.monotonic() - last_saved > 0.5 or i == len(path):
                self.changed("data")
                last_saved = time.monotonic()
            time.sleep(FRAME_S)
        self.stylus_tip = None
        self._sweeping = False  # before the last refresh, so the views see the sweep as over
        self._record_stylus_batch(start)
        self.each_view(lambda v: v.show_stylus(None))
        self.changed("data")

    def _record_stylus_batch(self, start):
        """One undoable action per sweep (per browser that sees it: the stylus is shared)."""
        with self.lock:
            if self.session.stylus_count > start:
                for cs in self.states.values():
                    cs.undo.append(Action("stylus", before=start))

    def collect_stylus_now(self):
        self.stylus_stop.set()
        if self.stylus_thread is not None:
            self.stylus_thread.join()
        with self.lock:
            start = self.session.stylus_count
            self.session.stylus_count = len(self.sd.stylus_path)
        self._record_stylus_batch(start)
        self.changed("data")

    # ------------------------------------------------------------------ tracker (live)
    def add_live_points(self, pts, labels):
        """Points the tracked stylus digitised (tracker mm) become session data at once."""
        with self.lock:
            for p, lab in zip(np.asarray(pts, float), labels, strict=True):
                self.session.live_points.append([float(p[0]), float(p[1]), float(p[2]), str(lab)])
        self.changed("data")

    def set_live_recording(self, on: bool, label="anterior") -> str | None:
        if self.live is None:
            return "No tracker connected (navapp serve --igtl HOST:PORT)."
        with self.lock:
            if on and not self.live.recording:
                self._live_start = len(self.session.live_points)
        self.live.set_recording(on, label)
        if not on:
            with self.lock:
                start, self._live_start = self._live_start, None
                if start is not None and len(self.session.live_points) > start:
                    for cs in self.states.values():
                        cs.undo.append(Action("live", before=start))
        self.changed("live")
        return None

    def set_live_follow(self, on: bool) -> str | None:
        """Re-register on every new tracked frame while on; switched off, the fit is
        converged on the last frame's data and kept as the result."""
        if self.live is None:
            return "No tracker connected (navapp serve --igtl HOST:PORT)."
        if on and self.worker is not None and self.worker.busy:
            return "A registration is running; wait for it or cancel it."
        err = self.live.follower.set(on)
        self.changed("live")
        return err

    def show_live_registration(self, reg, final: bool, summary: str = ""):
        """A live re-registration (``LiveFollower``): shown at most ``VIEW_MIN_S`` apart
        while the probe moves, sent to Slicer, and kept as the result when ``final``."""
        from .live import VIEW_MIN_S

        beta = reg.libr.beta if reg.libr is not None else None
        now = time.monotonic()
        self.send_results(reg, throttle=not final)
        if not final and now - self._live_shown < VIEW_MIN_S:
            return
        self._live_shown = now
        err = self._node_error(reg.rigid, beta)
        predicted = self._predict(reg) if final else (None, [])  # ~0.1 s: not on every frame
        state = RegisteredState("live (every frame)", reg.rigid, beta, err, *predicted)
        with self.lock:
            self.result, self.last_reg = state, reg
            if self.worker is not None:
                self.worker.last = reg  # a warm start continues from here
            if final:
                self.session.result = state.to_json()
                lm = reg.libr
                entry: dict = {"run": state.run, "points": int(sum(len(v) for v in self.data("all").values())),
                               "seconds": round(float(sum(reg.seconds.values())), 3),
                               "iterations": lm.iterations if lm else 0, "stop": lm.stop_reason if lm else "rigid",
                               "updates_streamed": 0, "cancelled": False, "trace": [], "live": summary,
                               "note": summary.split(",")[0]}
                if err is not None:
                    entry.update(error_mean_mm=round(float(err.mean()), 3), error_max_mm=round(float(err.max()), 3))
                self.session.log.append(entry)
        if final:
            self.changed("result")
            return
        geom = self.geometry(reg.rigid, beta)
        self.each_view(lambda v: v.show_live_registration(geom, err))

    # ------------------------------------------------------------------ results to 3D Slicer
    def send_results(self, reg, throttle=False):
        """The registration to 3D Slicer over OpenIGTLink (``--slicer``): rigid pose,
        registered targets and centerlines, status; at most 10 a second while live."""
        sender = self.results
        if sender is None:
            return
        now = time.monotonic()
        if throttle and now - self._results_sent < 0.1:
            return
        self._results_sent = now
        from ..tracking.results import status_line

        pre = self.preop
        centres = np.array([t.centre for t in pre.targets]) if pre.targets else None
        lines = {n: pre.centerline(n).points for n in ("portal", "hepatic") if pre.centerline(n) is not None}
        try:
            sender.send_registration(reg, centres, lines, status=status_line(reg))
        except Exception as exc:  # Slicer gone: the viewer carries on
            self.results_error = f"{exc.__class__.__name__}: {exc}"

    def freeze_frame(self, cs: ClientState) -> str | None:
        """The latest tracked ultrasound frame becomes a plane of the session (to draw on)."""
        if self.live is None:
            return "No tracker connected (navapp serve --igtl HOST:PORT)."
        with self.lock:
            index = LIVE_PLANE_BASE + len(self.session.live_planes)
            plane = self.live.frozen_plane(index)
            if plane is None:
                return "No ultrasound frame received yet."
            probe = self.sd.probe
            H, W = plane.image.shape[:2]
            f = self.live.frame
            spacing = f.spacing_mm
            if (H, W) != (probe.height_px, probe.width_px) or abs(spacing[0] - probe.spacing_mm) > 1e-6 \
                    or abs(spacing[1] - probe.spacing_mm) > 1e-6:
                return (f"the tracked frame is {W}×{H} px at {spacing[0]:.3f}×{spacing[1]:.3f} mm, the scene's "
                        f"probe {probe.width_px}×{probe.height_px} px at {probe.spacing_mm} mm: set the scene's probe")
            from PIL import Image

            rel = f"live/frame_{index - LIVE_PLANE_BASE:03d}.png"
            (self.session.folder / "live").mkdir(parents=True, exist_ok=True)
            Image.fromarray(plane.image).save(self.session.folder / rel)
            self.planes[index] = plane
            self.session.live_planes.append({"index": index, "pose": plane.probe_to_tracker.tolist(), "png": rel})
        self.show_plane(cs, index)
        self.changed("data")
        return None

    # ------------------------------------------------------------------ ultrasound
    def show_plane(self, cs: ClientState, index) -> bool:
        if index is None or index not in self.planes:
            return False
        with self.lock:
            cs.plane = index
            if cs.drawing is not None and cs.drawing.plane != index:
                cs.drawing = None  # an unfinished contour stays as drawn (an open line) on its own plane
            cs.touch()
        view = self.views.get(cs.client_id)
        if view is not None:
            view.refresh("plane")
        return True

    def add_plane(self, cs: ClientState) -> str | None:
        """The simulated segmentation of this browser's plane becomes data."""
        if cs.plane is None:
            return "Choose a plane first."
        with self.lock:
            if cs.plane in self.session.planes_added:
                return None
            self.session.planes_added.append(cs.plane)
            cs.undo.append(Action("plane", plane=cs.plane))
        self.changed("data")
        return None

    def place_probe(self, cs: ClientState, T) -> int:
        """Acquire a new plane at a hand-placed pose (kept in the session); returns its index."""
        plane = self.acquire_at(T, None)
        with self.lock:
            index = FREE_PLANE_BASE + len(self.session.free_planes)
            while index in self.planes:
                index += 1
            plane.index = index
            self.planes[index] = plane
            self.session.free_planes.append({"index": index, "pose": np.asarray(T).tolist()})
            cs.undo.append(Action("free_plane", plane=index))
        self.show_plane(cs, index)
        self.changed("data")
        return index

    def acquire_at(self, T, index=None):
        """A simulated plane at pose T (4×4), not kept: the free probe's preview."""
        i = index if index is not None else FREE_PLANE_BASE + len(self.session.free_planes)
        return acquire_free_plane(self.sd, i, np.asarray(T, float))

    # ------------------------------------------------------------------ drawing
    def click(self, cs: ClientState, col: int, row: int, feature: str | None = None) -> str | None:
        """A vertex at image pixel (col, row) of this browser's plane; returns an error or None."""
        if cs.plane is None:
            return "Choose a plane first."
        if not (0 <= col < self.sd.probe.width_px and 0 <= row < self.sd.probe.height_px):
            return "That click is outside the image."
        name = feature if feature in DRAWABLE else cs.feature
        with self.lock:
            cs.feature = name
            c = cs.drawing
            if c is None or c.plane != cs.plane or c.feature != DRAWABLE[name] or c.closed \
                    or c not in self.session.contours:
                c = cs.drawing = Contour(cs.plane, DRAWABLE[name])
                self.session.contours.append(c)
            c.vertices.append((int(col), int(row)))
            cs.undo.append(Action("vertex", contour=c))
            cs.touch()
        self.changed("data")
        return None

    def contour_command(self, cs: ClientState, cmd: str, feature: str | None = None) -> str | None:
        """Close / Finish line / Undo / Clear plane / Feature, for this browser; an error or None."""
        msg = None
        with self.lock:
            c = cs.drawing
            if cmd == "Feature":
                if feature in DRAWABLE:
                    cs.feature = feature
                    if c is not None and c.feature != DRAWABLE[feature]:
                        cs.drawing = None
                cs.touch()
                return None
            if cmd == "Close":
                if c is None:
                    msg = "Nothing is being drawn."
                elif len(c.vertices) < 3:
                    msg = "A closed contour needs at least 3 vertices."
                else:
                    c.closed = True
                    cs.drawing = None
                    cs.undo.append(Action("close", contour=c))
            elif cmd == "Finish line":
                cs.drawing = None
            elif cmd == "Undo":
                msg = self._undo(cs)
            elif cmd == "Clear plane":
                removed = [x for x in self.session.contours if x.plane == cs.plane]
                self.session.contours = [x for x in self.session.contours if x.plane != cs.plane]
                was_added = cs.plane in self.session.planes_added
                if was_added:
                    self.session.planes_added.remove(cs.plane)
                cs.undo.append(Action("clear", plane=cs.plane, before=(removed, was_added)))
                cs.drawing = None
            else:
                return f"unknown command {cmd!r}"
            cs.message = msg or ""
            cs.touch()
        self.changed("data")
        return msg

    def _undo(self, cs: ClientState) -> str | None:
        """Undo this browser's last action of any kind; others' work is left alone."""
        while cs.undo:
            a = cs.undo.pop()
            if a.kind == "vertex":
                c = a.contour
                if c is None or c not in self.session.contours or not c.vertices:
                    continue  # removed meanwhile (e.g. cleared): nothing of it left to undo
                c.vertices.pop()
                c.closed = False
                if not c.vertices:
                    self.session.contours.remove(c)
                    cs.drawing = None
                else:
                    cs.drawing = c
                    cs.plane = c.plane
                return None
            if a.kind == "close":
                if a.contour is not None and a.contour in self.session.contours:
                    a.contour.closed = False
                    cs.drawing = a.contour
                    cs.plane = a.contour.plane
                    return None
                continue
            if a.kind == "plane":
                if a.plane in self.session.planes_added:
                    self.session.planes_added.remove(a.plane)
                    return None
                continue
            if a.kind == "free_plane":
                used = any(c.plane == a.plane for c in self.session.contours) or a.plane in self.session.planes_added
                if used:
                    return "That free plane has contours or data on it now; clear it first."
                self.session.free_planes = [f for f in self.session.free_planes if f["index"] != a.plane]
                self.planes.pop(a.plane, None)
                if cs.plane == a.plane:
                    cs.plane = None
                return None
            if a.kind == "live":
                if self.live is not None and self.live.recording:
                    cs.undo.append(a)
                    return "Stop digitising first."
                del self.session.live_points[a.before:]
                return None
            if a.kind == "stylus":
                if self.sweeping:
                    cs.undo.append(a)
                    return "Stop the stylus sweep first."
                self.session.stylus_count = min(self.session.stylus_count, a.before)
                return None
            if a.kind == "clear":
                removed, was_added = a.before
                self.session.contours.extend(removed)
                if was_added and a.plane not in self.session.planes_added:
                    self.session.planes_added.append(a.plane)
                return None
        return "Nothing of yours to undo."

    # ------------------------------------------------------------------ registration
    def data(self, kind="all") -> dict:
        with self.lock:
            return self.session.data(self.sd, self.planes, surface_only=kind == "surface")

    def register(self, kind) -> str | None:
        """Start a registration; returns why it could not start, or None."""
        if self.worker is None:
            return "Still preparing the registration model."
        data = self.data(kind)
        npts = sum(len(v) for v in data.values())
        if npts < 3:
            return "Collect data first (stylus sweep or an ultrasound plane)."
        if self.worker.busy:
            return "A registration is already running; wait for it or cancel it."
        if self.live is not None and self.live.follower.on:
            return "Live re-registration is on (Live tracking panel): switch it off first."
        if kind == "warm" and self.worker.last is None:
            kind = "all"
        run = {"label": RUN_LABELS[kind], "points": npts, "t0": time.monotonic(), "trace": [], "streamed": 0,
               "iteration": 0, "omega": float("nan")}
        with self.lock:
            self.run = run
        if not self.worker.start(data, deform=kind != "rigid", warm=kind == "warm"):
            return "A registration is already running; wait for it or cancel it."
        self.changed("run")
        return None

    def cancel(self):
        if self.worker is not None:
            self.worker.cancel()

    def _on_update(self, u):
        run = self.run
        run["streamed"] += 1
        run["iteration"], run["omega"] = u.iteration, u.omega
        if self.truth_nodes is not None:
            err = np.linalg.norm(self.node_positions(u.rigid, u.beta) - self.truth_nodes, axis=1)
            run["trace"].append((u.elapsed, float(err.mean())))
            run["error"] = err
        run["state"] = (u.rigid, u.beta)
        geom = self.geometry(u.rigid, u.beta, surfaces={"liver": u.liver, **u.vessels})
        self.each_view(lambda v: v.show_update(u, geom))

    def _on_done(self, reg):
        run = self.run
        seconds = time.monotonic() - run["t0"]
        stopped = cancelled(reg)
        entry = {"run": run["label"], "points": run["points"], "seconds": round(seconds, 3),
                 "iterations": reg.libr.iterations if reg.libr else 0,
                 "stop": reg.libr.stop_reason if reg.libr else "rigid", "updates_streamed": run["streamed"],
                 "cancelled": stopped, "trace": [[round(t, 3), round(e, 3)] for t, e in run["trace"]]}
        if reg.quality is not None and reg.quality.warning:
            entry["warning"] = reg.quality.warning
        beta = reg.libr.beta if reg.libr is not None else None
        if not stopped:
            err = self._node_error(reg.rigid, beta)
            if err is not None:
                entry.update(error_mean_mm=round(float(err.mean()), 3), error_max_mm=round(float(err.max()), 3))
            predicted = self._predict(reg)
            with self.lock:
                self.result = RegisteredState(run["label"], reg.rigid, beta, err, *predicted)
                self.last_reg = reg
                self.session.result = self.result.to_json()
        with self.lock:
            self.session.log.append(entry)
            self.run = None
        self.changed("result")
        if not stopped:
            self.send_results(reg)
        if stopped:
            self.notify("Registration", "Cancelled: the previous result is kept.")
        elif entry.get("warning"):
            self.notify("Registration: check the fit", entry["warning"], error=True)

    def _on_error(self, exc):
        msg = str(exc) if isinstance(exc, NavappError) else f"{exc.__class__.__name__}: {exc}"
        with self.lock:
            self.run = None
        self.notify("Registration failed", msg, error=True)
        self.changed("run")

    # ------------------------------------------------------------------ cost sweep
    def sweep(self, on_row=None, on_done=None) -> str | None:
        if self.truth_nodes is None:
            return "This panel needs the true deformation (simulated scenes)."
        data = self.data("all")
        if sum(len(v) for v in data.values()) < 3:
            return "Collect data first."
        import scipy.sparse as sp

        x0 = self.model.basis.nodes
        B = sp.identity(len(x0), format="csr")  # the targets are the mesh nodes themselves
        assert self.worker is not None  # checked by the caller's truth_nodes: the model is ready
        ok = self.worker.submit(lambda cancel: lm_sweep(self.model, data, x0, self.truth_nodes, cancel=cancel,
                                                        on_row=on_row, B=B), on_done)
        return None if ok else "A registration is running; try again when it has finished."

    # ------------------------------------------------------------------ export
    def export(self) -> tuple[Path | None, str]:
        if self.last_reg is None:
            return None, "Register first: the export holds the registered model."
        out = self.session.folder / "export"
        files = export(out, self.last_reg, self.sd, self.data("all"))
        return out, f"{len(files)} files written to {out}"

    # ------------------------------------------------------------------ 2D view provider
    def _state_for(self, token):
        with self.lock:
            return self.states.get(token)

    def view_state(self, token) -> dict | None:
        cs = self._state_for(token)
        if cs is None or self.sd is None:
            return None if cs is None else {"etag": "wait", "plane": None, "overlays": [], "contours": [],
                                            "drawing": None, "targets": [], "legend": [],
                                            "message": "Preparing the scene…"}
        with self.lock:
            out = {"etag": self.view_etag(token), "plane": None, "width": self.sd.probe.width_px,
                   "height": self.sd.probe.height_px,
                   "spacing": self.sd.probe.spacing_mm, "overlays": [], "contours": [], "drawing": None,
                   "targets": [], "legend": [], "message": cs.message, "feature": cs.feature,
                   "planes": [{"index": i, "label": self.plane_label(i)} for i in sorted(self.planes)],
                   "plane_index": cs.plane}
            if cs.plane is None or cs.plane not in self.planes:
                return out
            plane = self.planes[cs.plane]
            out["plane"] = f"Plane {self.plane_label(cs.plane)}" + \
                (" · added as data" if cs.plane in self.session.planes_added else "")
            out["image_id"] = f"{cs.plane}-{id(plane)}"
            contours = [c for c in self.session.contours if c.plane == cs.plane]
            drawing = cs.drawing if cs.drawing in contours else None
        for ov in self.overlays(cs.plane):
            out["overlays"].append(ov.to_json())
        for c in contours:
            if c is drawing:
                continue
            centroid = None
            if c.closed and c.feature in CENTERLINE_OF:
                cols, rows = contour_pixels(c)
                centroid = [float(cols.mean()), float(rows.mean())]
            out["contours"].append({"feature": c.feature, "colour": DRAWN_COLOURS.get(c.feature, "#fff"),
                                    "vertices": [list(v) for v in c.vertices], "closed": c.closed,
                                    "centroid": centroid})
        if drawing is not None:
            out["drawing"] = {"feature": drawing.feature, "vertices": [list(v) for v in drawing.vertices]}
        out["legend"] = [{"name": o["name"], "colour": o["colour"]} for o in out["overlays"]] + \
            [{"name": f"drawn {n}", "colour": DRAWN_COLOURS[f]} for n, f in DRAWABLE.items()]
        out["targets"] = [line.replace("**", "") for line in self.target_plane_lines(cs.plane)]
        return out

    def view_etag(self, token) -> str | None:
        """What ``view_state`` would call its ETag, without building the state (a poll that
        finds nothing changed costs this only)."""
        cs = self._state_for(token)
        if cs is None or self.sd is None:
            return None
        with self.lock:
            return f"{self.version}-{cs.version}-{self._result_version()}"

    def _result_version(self):
        run = self.run
        return f"{id(self.result)}-{run['streamed'] if run else 0}"

    def view_image(self, token) -> bytes | None:
        cs = self._state_for(token)
        if cs is None or cs.plane is None or self.sd is None:
            return None
        plane = self.planes.get(cs.plane)
        if plane is None:
            return None
        key = (cs.plane, id(plane))
        png = self._image_cache.get(key)
        if png is None:
            from PIL import Image

            img = plane.image if plane.image is not None else np.zeros((self.sd.probe.height_px,
                                                                         self.sd.probe.width_px), np.uint8)
            buf = io.BytesIO()
            Image.fromarray(np.asarray(img, np.uint8)).save(buf, format="PNG")
            png = self._image_cache[key] = buf.getvalue()
        return png

    def view_click(self, token, col, row, feature) -> str | None:
        cs = self._state_for(token)
        if cs is None:
            return "This view is no longer connected: reload the page."
        return self.click(cs, col, row, feature)

    def view_command(self, token, cmd, feature, plane=None) -> str | None:
        cs = self._state_for(token)
        if cs is None:
            return "This view is no longer connected: reload the page."
        if cmd == "Plane":
            return None if self.show_plane(cs, plane) else f"there is no plane {plane}"
        return self.contour_command(cs, cmd, feature)

    def overlays(self, index) -> list[Overlay]:
        """The model's sections with plane ``index``: preoperative (rigidly placed by the
        current result, as-is before any registration) dashed, registered solid."""
        geom = self.geometry()
        plane = self.planes[index]
        cached = self._overlay_cache.get(index)
        if cached is not None and cached[0] is plane and cached[1] is geom:  # same plane, same state
            return cached[2]
        T = self.planes[index].probe_to_tracker
        probe = self.sd.probe
        out = []
        rigid = geom.rigid
        place = rigid.apply if rigid is not None else (lambda x: np.asarray(x))
        pre = {"liver": self.preop.liver, "portal": self.preop.portal, "hepatic": self.preop.hepatic}
        for name, mesh in pre.items():
            if mesh is not None:
                seg = section_pixels(probe, T, place(mesh.vertices), mesh.faces)
                out.append(Overlay(f"{name} (preop{', rigid' if rigid is not None else ''})",
                                   OVERLAY_STYLE[name][0], True, seg))
        for name, (v, f) in geom.surfaces.items():
            out.append(Overlay(f"{name} (registered)", OVERLAY_STYLE[name][1], False, section_pixels(probe, T, v, f)))
        for t in geom.targets:
            if t.surface is not None:
                out.append(Overlay(f"target {t.name}", OVERLAY_STYLE["target"][1], False,
                                   section_pixels(probe, T, t.surface.vertices, t.surface.faces)))
        self._overlay_cache[index] = (plane, geom, out)
        return out

    # ------------------------------------------------------------------ targets
    def _which(self):
        return "registered" if (self.result is not None or self.run is not None) else "preoperative"

    def target_plane_lines(self, index) -> list[str]:
        """One line per target: its distance from this plane's image (0: the image cuts it)."""
        from ..geometry.targets_distance import ImagePlane, plane_distances

        targets = self.geometry().targets
        if not targets or index not in self.planes:
            return []
        p = self.sd.probe
        plane = ImagePlane.from_pose(self.planes[index].probe_to_tracker, p.width_px * p.spacing_mm,
                                     p.height_px * p.spacing_mm)
        bands = {b.name: b for b in self.result.target_bands} if self.result is not None else {}
        out = []
        for t, d in zip(targets, plane_distances(plane, targets), strict=True):
            band = bands.get(t.name)
            out.append(f"**{t.name}** ({self._which()}): " +
                       ("in this image" if d <= 0.05 else f"{d:.1f} mm from this image") +
                       (f"; {band.text()}" if band is not None and self.run is None else ""))
        return out

    def target_distance_lines(self, tip) -> list[str]:
        """One line per target: the stylus tip's distance to its surface."""
        from ..geometry.targets_distance import tip_distances

        targets = self.geometry().targets
        if not targets or tip is None:
            return []
        return [f"**{t.name}**: " + (f"tip inside, {-d:.1f} mm deep" if d < 0 else f"{d:.1f} mm from the stylus tip")
                for t, d in zip(targets, tip_distances(tip, targets), strict=True)]


FEATURE_WORDS = {"portal_contour": "portal-vein contours", "hepatic_contour": "hepatic-vein contours",
                 "posterior": "the posterior liver wall", "portal_centerline": "portal-vein centres",
                 "hepatic_centerline": "hepatic-vein centres"}


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


def _duration(seconds: float) -> str:
    seconds = max(0.0, seconds)
    if seconds < 90:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.0f} min"


def serve(scene, host="127.0.0.1", port=8080, session_dir=None, edge=EDGE_MM, k=K, cache_root=None, view2d_port=0,
          tracking=None, slicer=None):
    """Start the viewer and block until interrupted. ``tracking``: a ``TrackingConfig`` to
    connect to an OpenIGTLink server (PLUS, 3D Slicer, ``navapp replay``); ``slicer``:
    where registrations go, ``(host, port)`` of Slicer's OpenIGTLinkIF connector as server,
    or ``(None, port)`` to listen for it as client."""
    results = None
    if slicer is not None:
        from ..tracking.results import ResultsSender

        host_s, port_s = slicer
        results = ResultsSender.connect(host_s, port_s) if host_s else ResultsSender.serve(port_s)
    app = App(scene, host, port, session_dir, edge, k, cache_root, view2d_port, tracking, results)
    app.start()
    print(f"navapp: viewer at {app.url}  (Ctrl+C to stop)", flush=True)
    if results is not None:
        where = f"to {slicer[0]}:{slicer[1]}" if slicer[0] else f"on 127.0.0.1:{results.port} (Slicer connects)"
        print(f"navapp: registrations go to 3D Slicer over OpenIGTLink {where}", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        app.view2d.stop()
        if app.live is not None:
            app.live.stop()
        if results is not None:
            results.close()
    return app
