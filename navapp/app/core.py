"""What every browser of one viewer shares, and the one lock around it: the scene data, the
session (what the users entered), the planes, the registration model and its worker, the
run in progress and the result on show; each browser's own ``ClientState``; the start-up
that fills them in. No viser here.

A change to shared data is announced with ``changed(Change.X)``: the version is bumped,
the session saved at once (so nothing acknowledged can be lost), and every view refreshed
from one refresher thread, so that a click is acknowledged without waiting for the GUIs of
all browsers.
"""

from __future__ import annotations

import secrets
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .. import progress
from ..anatomy.meshing import check_size
from ..anatomy.truth import TruthField
from ..errors import NavappError
from ..mechanics.supports import HeldSupports
from ..registration.pipeline import Registration, held_model, mesh_and_basis, prepare
from ..simulation.scenedata import SceneData, is_simulated, load_scene_data
from ..simulation.ultrasound import PlaneData
from .access import Role
from .actions import Act, ActionLog, interrupted_run
from .display import DisplaySurfaces
from .session import Session, default_folder, open_session, write_tabs
from .state import Change, ClientState, RegisteredState, Run, RunEntry, WorstPoint

if TYPE_CHECKING:
    from ..registration.model import RegistrationModel
    from .worker import RegistrationWorker


PARKED = 32  # disconnected tabs kept for their reload
RELOAD_S = 60.0  # a tab whose connection closed this recently may be coming back as a reload (slow on a loaded machine)
# a reload's old connection closes about when its new one asks (before it, or after it by as
# long as a loaded server lags): a tab parked later than this after a new tab asked is not
# that tab's old self. Without the bound a tab opened beside another waited RELOAD_S and took
# the work of the next tab to reload within that minute (its plane, contour and undo)
CLOSE_LAG_S = 5.0
# how long a new page is told to ask again while no tab has left before it: the old page's
# beacon, which the browser's clock puts before the new page, may reach a loaded server late
ASK_S = 20.0
WAIT = "wait: the tab before the reload is still connected"
SAVED = (Change.DATA, Change.RESULT, Change.LOG, Change.POSE)  # changes the session file must hold at once
ON_CONNECT = (Change.STATUS, Change.SCENE, Change.MODEL, Change.DATA, Change.PLANE, Change.RESULT, Change.ACTIONS,
              Change.POSE)


class NotReady(RuntimeError):
    """Shared state asked for before start-up has made it (a caller's missing check)."""


INTERRUPTED = "interrupted"  # the stop of a run the server was killed in


@dataclass(frozen=True)
class Loaded:
    """Start-up's first stage: the scene data, its session and planes."""

    sd: SceneData
    session: Session
    planes: dict[int, PlaneData]


@dataclass(frozen=True)
class Ready:
    """Start-up's second stage: the registration model and, for simulated scenes whose true
    displacement is known at the mesh nodes, the true deformed node positions."""

    model: RegistrationModel
    truth_nodes: np.ndarray | None


class Core:
    def __init__(self, scene, preop, edge: float, k: int, cache_root=None, session_dir=None):
        # a registration mesh that would not fit in memory is refused before the viewer starts:
        # a --edge too fine failed only after the scene's simulation; the scene's own truth mesh
        # is checked by the simulation, first thing, naming the scene file
        check_size(preop.liver, edge, "--edge")
        self.scene, self.preop, self.edge, self.k = scene, preop, edge, k
        self.cache_root, self.session_dir = cache_root, session_dir
        self.centre = preop.liver.vertices.mean(0)
        self.display = DisplaySurfaces()  # the surfaces as the tabs draw them
        self.lock = threading.RLock()
        self.version = 0  # bumped on every change to shared data
        self.sd: SceneData | None = None
        self.session: Session | None = None
        self.actions: ActionLog | None = None  # the session's action log, opened with it
        self.planes: dict[int, PlaneData] = {}
        self.model: RegistrationModel | None = None
        # the same mesh's models held at stated supports (``held_model``), built as they are stated
        self.models: dict[HeldSupports, RegistrationModel] = {}
        self.worker: RegistrationWorker | None = None
        self.truth_nodes: np.ndarray | None = None
        self.run: Run | None = None  # the registration in progress
        self.sweeping = False  # the accuracy sweep holds the worker (``runs.Runs.sweep``)
        self.result: RegisteredState | None = None  # the registered model on show
        self.last_reg: Registration | None = None  # what Export and a warm start use
        # the last finished run's data points furthest from its model; None: not known (a result
        # restored after a restart whose data have changed since, ``Runs.restore_worst``)
        self.worst: list[WorstPoint] | None = []
        # every finished run of this server's life by its row in the session's log: any can be put
        # back on show (``runs.Runs.show``), so a Rigid press never loses a good deformable result
        self.shown_runs: dict[int, tuple[RegisteredState, Registration, list[WorstPoint]]] = {}
        self.stage = "Starting…"
        self.stage_fraction: float | None = None
        self.failed: str | None = None
        self.failed_traceback: str | None = None  # when start-up failed on a bug rather than on its input
        # where start-up's stages, failures and "Ready." also go, one line each (``navapp serve``:
        # the terminal, as the viewer may have no browser open yet); None for headless use
        self.log: Callable[[str], None] | None = None
        self.ready = threading.Event()  # set when start-up has finished (or failed: see .failed)
        self.states: dict[str, ClientState] = {}  # token → per-browser state
        # tabs gone (closed or reloading), kept so that a reload can take its work back (``resume``)
        self.parked: dict[str, ClientState] = {}
        # each editing tab's own work as JSON, for the session folder (``drawing.Drawing.tabs_json``)
        self.tab_state: Callable[[], dict] | None = None
        self.views: dict[int, Any] = {}  # client_id → panels.ClientView
        self._pending: list[Change] = []  # view refreshes not yet done, coalesced
        self._pending_cv = threading.Condition()
        threading.Thread(target=self._refresher, daemon=True, name="navapp-refresh").start()

    # ------------------------------------------------------------------ typed access
    def need_scene(self) -> tuple[SceneData, Session]:
        sd, session = self.sd, self.session
        if sd is None or session is None:
            raise NotReady("the scene is still being prepared")
        return sd, session

    def need_session(self) -> Session:
        return self.need_scene()[1]

    def need_model(self) -> tuple[RegistrationModel, RegistrationWorker]:
        model, worker = self.model, self.worker
        if model is None or worker is None:
            raise NotReady("the registration model is still being prepared")
        return model, worker

    def model_for(self, held: HeldSupports | None) -> RegistrationModel | None:
        """The registration model whose basis is held at ``held`` (None: free-floating), or None
        while it is not built."""
        with self.lock:
            return self.model if held is None else self.models.get(held)

    def kept_model(self, model: RegistrationModel) -> RegistrationModel | None:
        """What a result keeps of the model it is in (``RegisteredState.model``): None for the
        free-floating one, which ``model`` always is."""
        return None if model is self.model else model

    def build_held(self, held: HeldSupports) -> RegistrationModel:
        """The model held at ``held``: the free model's mesh and features, the basis computed
        with the supports (or read from the basis cache). Blocks for as long as a basis takes."""
        model, _ = self.need_model()
        built = self.model_for(held)
        if built is None:
            built = held_model(model, held.held.value, held.release, self.cache_root, held.stiffness, held.points)
            with self.lock:
                built = self.models.setdefault(held, built)
        return built

    def data(self, surface_only: bool = False) -> dict[str, np.ndarray]:
        """The registration data the session holds now: {feature: (N, 3) tracker mm}."""
        with self.lock:
            sd, session = self.need_scene()
            return session.data(sd, self.planes, surface_only=surface_only)

    def data_with_origins(self, surface_only: bool = False, left_out: list | None = None) -> tuple[dict, dict]:
        """``data`` and each point's ``contours.Origin`` per feature; ``left_out``: appended the
        drawn vertices left out before the fit (``contours.StrayVertex``)."""
        with self.lock:
            sd, session = self.need_scene()
            return session.data_with_origins(sd, self.planes, surface_only=surface_only, left_out=left_out)

    # ------------------------------------------------------------------ browsers
    def new_client_state(self, client_id: int = -1, role: Role = Role.EDITOR) -> ClientState:
        """A browser's own state (also used headless, by tests and scripts)."""
        cs = ClientState(client_id, secrets.token_urlsafe(8), role)
        with self.lock:
            self.states[cs.token] = cs
        return cs

    def park(self, token: str):
        """A tab disconnected: its state is kept aside (the newest ``PARKED`` tabs) for its reload."""
        with self.lock:
            cs = self.states.pop(token, None)
            if cs is not None and cs.successor is None:  # not one a reload has taken over already
                cs.parked = time.monotonic()
                self.parked[token] = cs
                while len(self.parked) > PARKED:
                    self.parked.pop(next(iter(self.parked)))

    def going(self, cs: ClientState, at_ms: float | None = None, address: str | None = None):
        """The 2D view's page of ``cs`` is being left (reloaded or closed), at ``at_ms`` on the
        browser's clock: heard at once, while the viewer's own connection may be closed many
        seconds later on a loaded server (a reload's new page had asked for its work back
        before then, and been refused), or a little before."""
        with self.lock:
            cs.going, cs.going_ms = time.monotonic(), at_ms
            cs.address = cs.address or address

    def resume(self, cs: ClientState, previous: str | None, opened_ms: float | None = None,
               address: str | None = None) -> str | None:
        """The tab ``cs`` may be a reload: it takes the work of the tab it was back. Its page
        names that tab (``previous``) from the browser's per-tab session storage where the
        browser lets the 2D view's frame keep one (Chromium refuses it to a frame of another
        site when third-party storage is blocked); else (None) the one tab that left within
        ``RELOAD_S`` is taken, and none when there are several.

        A tab whose page said it was going (``going``) counts only if it was left before this
        page began (``opened_ms``, both on the browser's clock; the server's order of hearing
        them where the page gave no time): a reload's new page exists only after its old one was
        left, so a tab opened beside it and still asking is not its reload, and a beacon that a
        loaded server hears after the new page asked is still in order. A tab that left without
        a word (its connection closed) may have closed as late as ``CLOSE_LAG_S`` after this page
        first asked. Tabs of another address are never taken. ``WAIT`` while no tab has left
        before this page and its old one may still say so (``ASK_S``)."""
        with self.lock:
            cs.going = cs.going_ms = None  # asking again: this page is here (its frame was only redrawn)
            cs.address = cs.address or address
            if previous is not None:
                old = self.parked.pop(previous, None)
                if old is None:
                    return WAIT if previous in self.states else None
            else:
                now = time.monotonic()
                if cs.resume_asked is None:
                    cs.resume_asked, cs.opened_ms = now, opened_ms
                asked = cs.resume_asked

                def left(p: ClientState) -> bool:
                    if p.address is not None and cs.address is not None and p.address != cs.address:
                        return False  # another browser's tab
                    if p.going is not None:
                        if p.going_ms is not None and cs.opened_ms is not None:
                            before = p.going_ms <= cs.opened_ms  # in the browser's own order
                        else:
                            before = p.going < asked
                        return before and now - p.going < RELOAD_S
                    return p.parked is not None and now - p.parked < RELOAD_S and p.parked - asked < CLOSE_LAG_S

                gone = [p for p in (*self.parked.values(), *self.states.values())
                        if p is not cs and p.successor is None and left(p)]
                if len(gone) != 1:
                    # a loaded server may hear the old tab leave seconds after the new one asked
                    return WAIT if not gone and now - asked < ASK_S else None
                old = gone[0]
                self.parked.pop(old.token, None)  # else still connected: parked no more (``park``)
            cs.take_over(old)
        self.refresh_view(cs, Change.PLANE)
        return None

    def state_or_parked(self, token: str) -> ClientState | None:
        """A connected tab, or one gone and kept for its reload (``park``)."""
        with self.lock:
            return self.states.get(token) or self.parked.get(token)

    def state_for(self, token: str) -> ClientState | None:
        with self.lock:
            return self.states.get(token)

    def each_view(self, fn: Callable[[Any], None]):
        """Call ``fn(view)`` for every connected browser; one failing view does not stop the others."""
        with self.lock:
            views = list(self.views.values())
        for v in views:
            try:
                with v.lock:  # one thread at a time per tab (``ClientView.lock``)
                    fn(v)
            except Exception:  # a tab closing mid-update
                pass

    def refresh_view(self, cs: ClientState, what: Change):
        view = self.views.get(cs.client_id)
        if view is not None:
            view.refresh(what)  # under the view's lock

    def record(self, cs: ClientState | None, act: Act, detail: str = ""):
        """Append a change to shared data to the session's action log (``actions``): by the tab
        ``cs``, or by the server (None) following a tab's action (a run's end, a send to Slicer)."""
        log = self.actions
        if log is None:
            return
        tab, role = ("server", "server") if cs is None else (
            f"tab {cs.client_id}" if cs.client_id >= 0 else "script", cs.role)
        with self.lock:  # not beside a session's first save, which carries the file into the new folder
            log.append(tab, role, act, detail)
        self.changed(Change.ACTIONS)

    def changed(self, what: Change = Change.DATA):
        with self.lock:
            self.version += 1
            if self.session is not None and self.sd is not None and what in SAVED:
                self.session.save(self.sd, self.planes)
                self.save_tabs()
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
                self.each_view(_refresh(what))
            with self._pending_cv:
                self._pending_cv.notify_all()

    def settle(self, timeout: float = 10.0) -> bool:
        """Wait until every change so far has reached the views (for tests and scripts)."""
        t_end = time.monotonic() + timeout
        with self._pending_cv:
            while self._pending:
                if not self._pending_cv.wait(max(0.0, t_end - time.monotonic())):
                    return False
        return True

    def notify(self, title: str, body: str, error: bool = False):
        self.each_view(lambda v: v.notify(title, body, error))

    def withdraw(self, title: str):
        """Take down every tab's red box of this title (its condition no longer holds)."""
        self.each_view(lambda v: v.withdraw(title))

    def set_stage(self, text: str, fraction: float | None = None):
        self.stage, self.stage_fraction = text, fraction
        self.each_view(lambda v: v.refresh(Change.STATUS))

    # ------------------------------------------------------------------ start-up
    def start(self, on_loaded: Callable[[Loaded], None], on_ready: Callable[[Ready], None]) -> threading.Event:
        """Load the scene and session, then build the registration model, in a thread;
        ``on_loaded`` / ``on_ready`` run in it after each stage. Returns ``ready``."""
        threading.Thread(target=self._start_up, args=(on_loaded, on_ready), daemon=True,
                         name="navapp-startup").start()
        return self.ready

    def save_tabs(self):
        """Write each editing tab's own work into the session folder (``session.write_tabs``)."""
        with self.lock:
            if self.tab_state is None or self.session is None or not self.session.written:
                return
            write_tabs(self.session.folder, self.tab_state())

    def _interrupted(self):
        """A run the last server was killed in leaves its row ("interrupted"), its end in the
        action log and a word to the surgeon: it had left nothing, and the tab showed the
        result before it as if nothing had been asked."""
        actions, session = self.actions, self.session
        assert actions is not None and session is not None
        started = interrupted_run(actions.entries())
        if started is None:
            return
        what, _, count = started.detail.rpartition(", ")
        points = int(count.split()[0]) if count.split() and count.split()[0].isdigit() else 0
        with self.lock:
            session.log.append(RunEntry(what or started.detail, points, 0.0, 0, INTERRUPTED, cancelled=True,
                                        note=INTERRUPTED))
        self.changed(Change.LOG)
        self.record(None, Act.FINISHED, f"{INTERRUPTED}: the server stopped during the run started {started.time}")
        said = (f"The registration started at {started.time[11:19]} UTC ({started.detail}) was interrupted: the "
                "server stopped while it ran, and it left no result. The result on show is the one before it; "
                "register again.")
        self._say(said)
        self.notify("Session", said, error=True)

    def _say(self, line: str):
        if self.log is not None:
            self.log(line)

    def _start_up(self, on_loaded, on_ready):
        stage = _Stage()

        def on_progress(desc, fraction):
            if desc != stage.name:
                stage.name, stage.t0, stage.f0 = desc, time.monotonic(), fraction or 0.0
                self._say(f"  {desc}")  # a step's percentage stays on its bar: the terminal gets its name once
            eta = ""
            elapsed = time.monotonic() - stage.t0
            # the rate since this step was first heard of: a step made ahead is first heard part-way
            if fraction is not None and fraction - stage.f0 > 0.02 and fraction < 1 and elapsed > 1.0:
                eta = f", about {_duration(elapsed * (1 - fraction) / (fraction - stage.f0))} left"
            pct = f" — {100 * fraction:.0f} %" if fraction is not None else ""
            self.set_stage(f"{stage.what}: {desc}{pct}{eta}", fraction)

        def begin(what):
            stage.what = what
            self._say(what)
            self.set_stage(what)

        t0 = time.monotonic()
        listener = progress.add_listener(on_progress)
        try:
            begin("Simulating the intraoperative scene (true deformation, stylus sweep, ultrasound; "
                  "cached after the first start)")
            ahead = None
            if not is_simulated(self.scene, self.cache_root):
                # the registration mesh and basis need only the preoperative liver: they are made
                # beside the scene's simulation (docs/decisions/viewer.md, "The first start")
                ahead = Ahead(self.preop.liver, self.edge, self.k, self.cache_root)
            sd = load_scene_data(self.scene, self.cache_root, self.edge)
            folder = Path(self.session_dir) if self.session_dir else default_folder(sd)
            session, planes = open_session(folder, sd)
            if session.note:
                self._say(session.note)
                self.notify("Session", session.note)
            loaded = Loaded(sd, session, planes)
            actions = ActionLog(folder)
            with self.lock:
                self.sd, self.session, self.planes, self.actions = sd, session, planes, actions
            self._interrupted()
            self.changed(Change.SCENE)
            on_loaded(loaded)
            begin(f"Building the registration model (mesh at {self.edge:g} mm, basis of k = {self.k} "
                  f"control points; cached after the first start)")
            if ahead is not None:
                ahead.wait()  # its remaining steps are the ones reported now
            model, _ = prepare(sd.case, self.edge, self.k, self.cache_root)
            ready = Ready(model, truth_at_nodes(sd, model))
            on_ready(ready)
            ready_line = f"Ready. {len(model.basis.nodes):,} nodes, k = {self.k}. Session: {session.folder}"
            self.set_stage(ready_line, 1.0)
            self._say(f"{ready_line} ({_duration(time.monotonic() - t0)} after start)")
            self.changed(Change.MODEL)
        except NavappError as exc:
            self._fail(str(exc))
        except Exception as exc:  # a bug: one line here, the traceback kept for the report (serve writes it)
            self.failed_traceback = traceback.format_exc()
            self._fail(f"{exc.__class__.__name__}: {exc}")
        finally:
            progress.remove_listener(listener)
            self.ready.set()
            # the tabs' status again, now that start-up is over: "Ready." was shown before ``ready``
            # was set, and a tab open during start-up kept its progress bar, full, under it
            self.each_view(lambda v: v.refresh(Change.STATUS))

    def _fail(self, message: str):
        self.failed = message
        self.set_stage(f"Error: {message}", 0.0)
        self.notify("navapp", message, error=True)


@dataclass
class _Stage:
    """The start-up stage being reported: what it does, the progress step, when it began."""

    what: str = ""
    name: str = ""
    t0: float = field(default_factory=time.monotonic)
    f0: float = 0.0  # the step's fraction when it was first heard of


class Ahead:
    """The registration model's mesh and basis (``mesh_and_basis``, as ``prepare`` asks for
    them) made on a thread of their own, into the cache: the mesher runs in a child process
    and the basis mostly in PARDISO, so they use the core the simulation leaves. Silent
    (``progress.aside``) until ``wait``; a failure is left for ``prepare``, which does the
    work again and says what went wrong in its one line."""

    def __init__(self, liver, edge: float, k: int, cache_root):
        self.heard = threading.Event()

        def run():
            with progress.aside(self.heard):
                try:
                    mesh_and_basis(liver, edge, k, cache_root)
                except Exception:  # prepare repeats the work and reports it
                    pass

        self.thread = threading.Thread(target=run, name="navapp-model-ahead", daemon=True)
        self.thread.start()

    def wait(self):
        """Report the work's remaining steps from now on, and wait for it to end."""
        self.heard.set()
        self.thread.join()


def truth_at_nodes(sd: SceneData, model) -> np.ndarray | None:
    """The true intraoperative positions of the model's nodes (M, 3) mm, tracker space,
    asked of the scene's truth field; None without one (no truth, or truth measured only
    at points of its own): the viewer's true error is measured at the nodes."""
    truth = sd.case.truth
    return truth.at(model.basis.nodes) if isinstance(truth, TruthField) else None


def _refresh(what: Change):
    return lambda v: v.refresh(what)


def _duration(seconds: float) -> str:
    seconds = max(0.0, seconds)
    if seconds < 90:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.0f} min"
