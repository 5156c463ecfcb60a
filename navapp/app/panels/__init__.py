"""One browser tab's view: its GUI panels and 3D scene nodes, built when the tab connects
and refreshed from the shared state (``core.Core``) through the rooms. Each panel is a
module of its own."""

from __future__ import annotations

import inspect
import threading
import time
from html import escape

import numpy as np
from viser import NotificationHandle

from ..access import OBSERVING, Role
from ..core import ON_CONNECT
from ..framing import DOCK_2D_PX, Screen, dock_width
from ..runs import clip_words
from ..state import Change, ClientState
from .accuracy import AccuracyPanel
from .guide import GuidePanel
from .layers import LayersPanel
from .registration import RegistrationPanel
from .session import SessionPanel
from .stylus import StylusPanel
from .tracking import TrackingPanel
from .ultrasound import UltrasoundPanel

OBSERVER_NOTE = "this view shows everything live and changes nothing."
PIN_CHARS = 90  # of the pose warning in the box pinned over the 3D view (title and all fit its 200 px)
DISTANCE_TEXT_S = 0.2  # tumour-distance text refreshed at most this often while a tracked tip moves


class ClientView:
    """Everything one browser sees. ``refresh(what)`` is called after shared changes (``Change``)."""

    def __init__(self, app, client, cs: ClientState):  # app: server.App, the rooms
        self.app, self.core, self.client, self.cs = app, app.core, client, cs
        # one thread at a time changes this tab's panels and nodes (``Core.each_view`` and
        # ``refresh_view`` take it): after a reload the connect, the refresher and the 2D view's
        # resume refreshed one view at once, a node re-added by one was removed under the other
        # ("Cannot assign to 'visible' on a removed PointCloudHandle"), and every later refresh
        # of the tab failed at the first panel, so the run table never showed another run
        self.lock = threading.RLock()
        self._dist_shown = 0.0
        g = client.gui
        self.status = g.add_markdown("")
        self.bar = g.add_progress_bar(0.0, animated=True)
        self.alert = g.add_html("", visible=False)  # a lost tool: above every panel, not in a folder
        self.pose_alert = g.add_html("", visible=False)  # the registered pose is not to be believed
        # the same two warnings pinned over the 3D view: the panel's banner scrolls away with the
        # panel, and a surgeon working at the bottom of it (the run table) would not see it
        self._pinned: dict[str, NotificationHandle] = {}  # "lost" / "pose" -> viser NotificationHandle
        self._errors: dict[str, NotificationHandle] = {}  # title -> the red box showing it
        if cs.role is Role.OBSERVER:
            g.add_markdown(f"**Observer link**: {OBSERVER_NOTE}")
        self.layers = LayersPanel(self)  # first: the others show their nodes through it
        self.guide = GuidePanel(self)
        self.stylus = StylusPanel(self)
        self.tracking = TrackingPanel(self)
        self.ultrasound = UltrasoundPanel(self)
        self.registration = RegistrationPanel(self)
        self.accuracy = AccuracyPanel(self)
        self.session = SessionPanel(self)
        self.panels = (self.layers, self.guide, self.stylus, self.tracking, self.ultrasound, self.registration,
                       self.accuracy, self.session)
        self.screen: Screen | None = None  # the 3D canvas, once the browser has reported its size
        self._framed: np.ndarray | None = None  # where the camera was put to frame the liver
        self._dock = DOCK_2D_PX[0]  # the 2D view's dock width as last set
        client.camera.on_update(lambda cam: self.camera_changed())

    # ------------------------------------------------------------------ the window
    def camera_changed(self):
        """The browser reported its camera. The 3D canvas is the window less the docked 2D view
        (viser lays the dock beside it; the control panel floats over it), so the window is the
        canvas plus the dock — once the dock is laid out, which may be before or after the first
        report: each new canvas size docks the 2D view for the window it implies (a report
        before the layout overestimates it for a moment; the layout's own report corrects it).
        Each new canvas size also frames the liver between the panels again, unless the surgeon
        has moved the camera since it was last framed."""
        with self.lock:
            self._camera_moved()

    def _camera_moved(self):
        cam = self.client.camera
        ratio = self.cs.pixel_ratio  # viser reports the canvas in device pixels (``ClientState.pixel_ratio``)
        w, h = int(round((cam.image_width or 0) / ratio)), int(round((cam.image_height or 0) / ratio))
        if w <= 0 or h <= 0 or (self.screen is not None and (w, h) == (self.screen.width_px, self.screen.height_px)):
            return
        dock = dock_width(w + self._dock) if self.ultrasound.cb_2d.value else self._dock
        if dock != self._dock:
            self._dock = dock
            self.ultrasound.dock(dock)
        moved = self._framed is not None and np.linalg.norm(np.asarray(cam.position) - self._framed) > 1.0
        self.screen = Screen(w, h)
        if not moved:
            self.layers.look("Reset")
            self._framed = np.asarray(cam.position, float)

    # ------------------------------------------------------------------ from the App
    def refresh_all(self):
        with self.lock:
            for what in ON_CONNECT:
                self.refresh(what)

    def refresh(self, what: Change):
        with self.lock:
            self._refresh(what)

    def _refresh(self, what: Change):
        if what is Change.STATUS:
            core = self.core
            self.status.content = f"**{core.stage}**"
            done = core.ready.is_set() and core.failed is None
            self.bar.visible = not done
            if core.stage_fraction is None:
                self.bar.animated, self.bar.value = True, 100.0
            else:
                self.bar.animated, self.bar.value = False, 100.0 * core.stage_fraction
            return
        failed = None
        for p in self.panels:
            try:
                p.refresh(what)
            except Exception as exc:  # one panel's failure does not leave the others stale
                failed = failed or exc
        if what is Change.LIVE:
            self._alert()
        if what in (Change.LIVE, Change.RESULT):
            self._pose_alert()
        if failed is not None:
            raise failed

    def _alert(self):
        link = self.app.live.link
        lost = link.lost if link is not None else None
        if lost is None:
            self.alert.visible = False
            self._pin("lost", None)
            return
        html = (f"<div style='background:#c00;color:#fff;font-weight:600;padding:8px;border-radius:4px'>"
                f"⚠ {escape(lost)}</div>")
        if self.alert.content != html:
            self.alert.content = html
        self.alert.visible = True
        self._pin("lost", ("⚠ Tracking lost", lost))

    def _pose_alert(self):
        res = self.core.result
        if res is None or not res.pose_warning:
            self.pose_alert.visible = False
            self._pin("pose", None)
            return
        html = (f"<div style='background:#c00;color:#fff;padding:8px;border-radius:4px'><b>⚠ Registered pose not "
                f"to be believed</b> ({escape(res.run)}): {escape(res.pose_warning)}. Re-register and live "
                f"re-registration will not continue from it.</div>")
        if self.pose_alert.content != html:
            self.pose_alert.content = html
        self.pose_alert.visible = True
        # the pinned box is cut at 200 px, centred: the whole text (two doubts, live re-registration)
        # showed its middle, the title scrolled out of it; the banner above the panels keeps it whole
        said = clip_words(res.pose_warning, PIN_CHARS)
        self._pin("pose", (f"⚠ Registered pose not to be believed ({res.run})",
                           f"{said}{' ' if said.endswith('…') else '. '}Re-register and live re-registration will "
                           "not continue from it. The whole text is at the top of the panel."))

    def _pin(self, key: str, text: tuple[str, str] | None):
        """A red notification over the 3D view while ``text`` (title, body) holds; removed
        when it is None. It has no close button: it goes when the condition goes."""
        note = self._pinned.get(key)
        if text is None:
            if note is not None:
                self._pinned.pop(key)
                note.remove()
            return
        title, body = text
        if note is None:
            self._pinned[key] = self.client.add_notification(title, body, with_close_button=False,
                                                             auto_close_seconds=None, color="red")
        elif (note.title, note.body) != (title, body):
            note.title, note.body = title, body

    def edits(self, cb):
        """``cb`` for a control that changes the shared data; an observer's use of it is
        refused and said so (``access.Role``). Controls of the tab's own view (layers, camera,
        colour scale, the plane it shows) are not wrapped: an observer uses them."""
        if self.cs.role is not Role.OBSERVER:
            return cb
        if inspect.iscoroutinefunction(cb):
            async def refused_in_order(_event):
                self.refuse()
            return refused_in_order
        return lambda _event: self.refuse()

    def refuse(self):
        self.notify("Observer link", OBSERVING, error=True)

    def notify(self, title, body, error=False):
        if error:
            # a red box stays until closed: the next one with the same title replaces it (one per
            # registration piled up over the 3D view, each saying what the panel already holds)
            old = self._errors.pop(title, None)
            if old is not None:
                old.remove()
            self._errors[title] = self.client.add_notification(title, body, color="red", auto_close_seconds=None)
        else:
            self.client.add_notification(title, body, auto_close_seconds=6.0)

    def withdraw(self, title):
        """Remove the red box of this title, if shown (``notify``)."""
        old = self._errors.pop(title, None)
        if old is not None:
            old.remove()

    def show_stylus(self, pos):
        self.layers.show_stylus(pos)
        self.stylus.show_tip(pos)

    def show_live_tip(self, tip):
        self.layers.show_stylus(tip)
        if tip is None:
            self.stylus.dist.content = "Stylus not tracked: no distances."
            self._dist_shown = 0.0
            return
        now = time.monotonic()
        if now - self._dist_shown >= DISTANCE_TEXT_S:  # the tip moves at tracker rate; text needs less
            self._dist_shown = now
            self.stylus.dist.content = "  \n".join(self.app.shown.target_distance_lines(tip))

    def show_live_frame(self, frame):
        link = self.app.live.link
        if frame is None:  # the probe's stream is lost: its plane is not drawn where it was last seen
            if self.tracking.follow.value:
                self.layers.lose_live_probe()
            return
        if self.tracking.follow.value and link is not None:
            plane = link.frozen_plane(-1)
            if plane is not None:
                self.layers.show_plane(plane)

    def show_live_registration(self, geom, error):
        self.layers.show_registered(geom, error=self.app.shown.surface_error(self.cs, error)
                                    if error is not None else None)

    def show_update(self, u, geom):  # u: worker.Update
        run = self.core.run
        err = run.error if run is not None else None
        self.layers.show_registered(geom, error=self.app.shown.surface_error(self.cs, err) if err is not None else None,
                                    animate=True)
        self.registration.show_update(u)
