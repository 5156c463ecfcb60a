"""The Live tracking panel (shown when ``navapp serve --igtl HOST:PORT``): connection and
per-tool status (seen / stale / missing, as SlicerIGT's Watchdog), digitising with the
tracked stylus while a switch is on, the live image, and freezing a frame to draw on."""

from ...features import STYLUS
from ..actions import Act
from ..state import Change


class TrackingPanel:
    def __init__(self, view):
        self.view, self.app, self.cs = view, view.app, view.cs
        g = view.client.gui
        self.folder = g.add_folder("Live tracking (OpenIGTLink)", visible=self.app.live.config is not None)
        with self.folder:
            self.status = g.add_markdown("Not connected.")
            self.label = g.add_dropdown("Digitise as", STYLUS)
            self.record = g.add_checkbox("Digitise (record while on)", False)
            self.count = g.add_markdown("")
            self.follow = g.add_checkbox("Show the live image", True)
            self.freeze = g.add_button("Freeze this frame as a plane (to draw on)")
            self.live_reg = g.add_checkbox("Re-register on every frame", False,
                                           hint="each new frame's contours join the data kept and the model is "
                                                "re-registered from the last state; off: converged and kept")
            self.live_summary = g.add_markdown("")
            self.slicer = g.add_markdown("")
        # what each switch last showed of the app's state: a refresh moves a switch only when that
        # state changed since. viser sets a switch's value when the browser toggles it and runs the
        # callback later, in a thread of its own; a refresh in between (the pump's, every 0.5 s) saw
        # the switch differ from the state it had not yet been told of, set it back, and the
        # callback then read it off: "Re-register on every frame" (or Digitise) stayed off, and the
        # panel said "Not re-registered on live frames yet" for good (CI's live browser test)
        self._shown_recording = self._shown_following = False
        self.record.on_update(view.edits(lambda e: self._record()))
        self.freeze.on_click(view.edits(lambda e: self._freeze()))
        self.live_reg.on_update(view.edits(lambda e: self._live_reg()))

    def _record(self):
        on = bool(self.record.value)
        was = self.app.live.recording
        if self.app.live.link is not None and was == on:
            return  # the echo of a refresh
        err = self.app.live.set_recording(on, self.label.value, self.cs)
        if err:
            self.view.notify("Live tracking", err, error=True)
        elif was != on:
            self.app.core.record(self.cs, Act.RECORDING, f"on ({self.label.value})" if on else "off")

    def _live_reg(self):
        on = bool(self.live_reg.value)
        if self.app.live.link is not None and self.app.live.following == on:
            return  # the echo of a refresh
        err = self.app.live.set_follow(on)
        if err:
            self.live_reg.value = False
            self.view.notify("Live tracking", err, error=True)
        else:
            self.app.core.record(self.cs, Act.FOLLOW, "on" if on else "off")

    def _freeze(self):
        err = self.app.live.freeze_frame(self.cs)
        if err:
            self.view.notify("Live tracking", err, error=True)
        else:
            self.app.core.record(self.cs, Act.FROZEN, f"as plane {self.cs.plane}")

    def refresh(self, what):
        live = self.app.live.link
        if live is None:
            return
        self.folder.visible = True
        if what in (Change.LIVE, Change.DATA):
            self.status.content = "  \n".join(live.status_lines())
            session = self.app.core.session
            n = len(session.live_points) if session else 0
            self.count.content = f"{n} points digitised with the tracked stylus" + \
                (" — **recording**" if live.recording else "")
            if live.recording != self._shown_recording:
                self._shown_recording = live.recording
                self.record.value = live.recording
            f = live.follower
            if f.on != self._shown_following:
                self._shown_following = f.on
                self.live_reg.value = f.on
            seg = f.segmentation_px
            self.live_summary.content = f.summary() + (
                f"  \nContours of live frames: automatic (simulated segmentation, {seg:g} px error)"
                if seg is not None else "  \nLive frames carry no contours until drawn on (no automatic segmentation)")
            slicer = self.app.slicer
            r = slicer.sender
            if r is not None:
                state = "connected" if r.connected else "waiting for Slicer"
                self.slicer.content = (f"3D Slicer (OpenIGTLink, port {r.port}): {state}, {r.sent} messages sent "
                                       f"or queued" + (f" — {slicer.error}" if slicer.error else ""))
