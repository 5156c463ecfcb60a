"""The viewer's link to a tracker: a ``tracking.TrackingClient`` (OpenIGTLink, e.g. a PLUS
server or ``navapp replay``) pumped into the shared state as messages arrive. No viser here.

``Live`` is the room the panels and the other rooms talk to (it exists without a tracker:
then it refuses with the reason); ``LiveLink`` is the connection, whose pump asks each
source's showing side (``app.sources``: one module per tracked tool, one for every point
source) what to draw and which points join the session; ``LiveFollower`` the
re-registration on every frame.

- The stylus tip moves live in every browser (at most every ``sources.stylus.TIP_MIN_S``).
- While digitising is on, the client's ``Digitiser`` records points at the configured
  rate in the client thread; the pump moves them into the session (saved at once), so a
  dropped connection or a browser reload loses nothing.
- The latest ultrasound frame is kept; "Freeze" turns it into a plane of the session
  (image saved as PNG beside session.json) that can be drawn on in the 2D view like any
  other plane.
- "Re-register on every frame" (``LiveFollower``): each new frame's contours (designated
  automatically when the scene declares ``auto_segmentation``) join the kept data and the
  model is re-registered warm-started from the last state (``registration.live``),
  in a thread of its own so the tip never waits for it; frames that arrive while an update
  runs are skipped, the newest one is taken next.
- A data source's POINT messages (``features.SOURCED``: a laparoscope's depth points) join
  the session's data as they arrive.
- The pump wakes on every stylus, frame or source message (not on a timer), so a tracker message
  reaches the browsers within milliseconds.
"""

from __future__ import annotations

import logging
import statistics
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from ..fitwarning import one_line
from ..registration.live import LiveRegistration, merge
from ..registration.pipeline import Registration
from ..simulation.scenedata import auto_segmentation, segment_frame
from ..simulation.ultrasound import PlaneData
from ..tracking.client import TrackingClient
from ..tracking.config import TrackingConfig
from ..tracking.events import ProbeSample
from .core import Core
from .imaging import Imaging
from .shown import Shown
from .slicer import Slicer
from .sources import Wiring
from .sources import build as build_sources
from .sources.ius import ProbeShown, probe_pose_from_image
from .sources.stylus import StylusShown
from .state import (
    CARRIED,
    Action,
    Change,
    ClientState,
    RegisteredState,
    RunEntry,
    RunKind,
    Undone,
    checked_by,
    held_of,
    supports_words,
)
from .worker import viewer_options

log = logging.getLogger(__name__)

PUMP_HZ = 20.0  # status refresh and digitiser collection; tip and frames go out as they arrive
VIEW_MIN_S = 1.0 / 15  # live registrations shown at most this often (the model mesh is large)
NO_TRACKER = "No tracker connected (navapp serve --igtl HOST:PORT)."


class LiveLink:
    """The connection: the tracking client, and one shown source per received source
    (``app.sources``: the stylus, the iUS probe, each point source) that its pump asks, in
    ``features.TABLE``'s order, what to draw and which points join the session."""

    def __init__(self, live: Live, config: TrackingConfig):
        self.live, self.core = live, live.core
        self.config = config
        self._wake = threading.Event()
        self.client = TrackingClient(config, on_event=self._on_event)
        self.follower = LiveFollower(self)
        self.sources = build_sources(Wiring(self.client, config, self.core, self.follower.new_frame))
        self.stylus = _one(self.sources, StylusShown)
        self.probe = _one(self.sources, ProbeShown)
        self._stop = threading.Event()
        self._collect_lock = threading.Lock()
        self._thread: threading.Thread | None = None

    def start(self) -> LiveLink:
        self.client.start()
        self._thread = threading.Thread(target=self._pump, daemon=True, name="navapp-live")
        self._thread.start()
        self.follower.start()
        return self

    def stop(self):
        self._stop.set()
        self._wake.set()
        self.follower.stop()
        self.client.stop()

    @property
    def tip(self) -> np.ndarray | None:
        """Where the stylus tip is drawn now (``StylusShown.tip``)."""
        return self.stylus.tip

    @property
    def lost(self) -> str | None:
        """Why the stylus, once seen, is not shown now: the viewer's red banner (``StylusShown.lost``)."""
        return self.stylus.lost

    @property
    def frame(self) -> ProbeSample | None:
        """The latest tracked ultrasound frame on show (``ProbeShown.frame``)."""
        return self.probe.frame

    def frozen_plane(self, index) -> PlaneData | None:
        """The latest frame as a plane of the session, or None (no frame yet)."""
        return self.probe.frozen_plane(index)

    def _on_event(self, ev):
        # called in the client thread: a wake-up only (a point source keeps its points until taken)
        if any([s.wakes(ev) for s in self.sources]):
            self._wake.set()

    @property
    def recording(self) -> bool:
        return self.stylus.recording

    def set_recording(self, on: bool, label="anterior"):
        self.stylus.record(on, label)
        if not on:
            self._collect()  # what was recorded up to now is in the session before the switch reads off

    def status_lines(self) -> list[str]:
        c = self.client
        lines = [(f"{'connected to' if c.connected else 'waiting for'} {c.connection.address}"
                  f" (connections so far: {c.connects})")]
        for dev, st in c.status().items():
            age = "never" if st.age_s is None else f"{st.age_s * 1000:.0f} ms ago"
            rate = f", {c.rate_hz(dev):.0f}/s" if st.state == "seen" else ""
            lines.append(f"{dev}: **{st.state}** ({age}{rate})")
        return lines

    def _collect(self):
        with self._collect_lock:  # the pump and a switch-off both collect: each point once
            for source in self.sources:
                for pts, labels in source.taken():
                    self.live.add_points(pts, labels)

    def _pump(self):
        last_status = last_collect = 0.0
        while not self._stop.is_set():
            self._wake.wait(1.0 / PUMP_HZ)
            self._wake.clear()
            now = time.monotonic()
            status = self.client.status()
            urgent = False
            for source in self.sources:  # each in turn, whatever the one before found
                urgent = source.show(now, status) or urgent
            if now - last_collect >= 1.0 / PUMP_HZ:
                last_collect = now
                self._collect()
            if now - last_status > 0.5 or urgent:  # twice a second (ages grow), or at once when a source asks
                last_status = now
                for source in self.sources:
                    source.age(status)
                self.core.each_view(lambda v: v.refresh(Change.LIVE))


def _one(sources, kind):
    """The one shown source of type ``kind`` (the stylus's, the probe's: the viewer has panels of theirs)."""
    return next(s for s in sources if isinstance(s, kind))


class LiveFollower:
    """Re-registration on every new frame while ``on`` (see the module doc). The kept data
    are the session's (stylus, live points, planes, drawn contours), re-read whenever the
    session changes; the frame's own features are those the declared automatic
    segmentation designates (none without it: then each update re-fits the kept data)."""

    def __init__(self, link: LiveLink):
        self.link, self.live, self.core = link, link.live, link.core
        self.on = False
        self.reg: LiveRegistration | None = None
        self.frames = 0  # frames registered
        self.skipped = 0  # frames that arrived while an update ran
        self.ms: deque = deque(maxlen=2000)  # wall time per update
        self.last_error: str | None = None
        self._version: int | None = None  # Core.version the kept data were read at
        self._last_frame: ProbeSample | None = None
        self._pending = 0
        self._first = False  # switched on, nothing registered since (``_step``)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="navapp-live-registration")

    def start(self):
        self._thread.start()

    def stop(self):
        self._stop.set()
        self._wake.set()

    @property
    def segmentation_px(self) -> float | None:
        sd = self.core.sd
        return None if sd is None else auto_segmentation(sd.scene)

    def set(self, on: bool) -> str | None:
        core = self.core
        if on:
            if core.model is None:
                return "Still preparing the registration model."
            if sum(len(v) for v in core.data().values()) < 3 and self.segmentation_px is None:
                return "Collect data first: the scene declares no automatic segmentation of live frames."
            self.last_error = None
            self._first = True  # before ``on``: the thread's next pass registers at once
            self.on = True
            self._wake.set()
            return None
        was, self.on = self.on, False
        if was:
            self._wake.set()  # the thread converges the fit and stores it
        return None

    def new_frame(self):
        if self.on:
            self._pending += 1
            self._wake.set()

    def summary(self) -> str:
        if self.last_error is not None and not self.on:
            # said where the frame count is: the panel said "Not re-registered on live frames
            # yet" beside a switch gone off, and the red box with the reason could be closed
            return f"Stopped: {self.last_error}" + (f" (after {self.frames} frames)" if self.frames else "")
        if not self.frames:
            return "Not re-registered on live frames yet."
        ms = list(self.ms)
        # the basis a live update fits (the result's it continued from): said, as the stated
        # supports change only the next fresh registration's
        held = None if self.reg is None else held_of(self.reg.model)
        model = "" if held is None else f", {supports_words(held)}"
        return (f"{self.frames} frames re-registered{model}, {statistics.median(ms):.0f} ms median "
                f"(max {max(ms):.0f} ms), {self.skipped} frames skipped while busy")

    def _base(self):
        core = self.core
        if core.version != self._version or self.reg is None:
            self._version = core.version
            data = core.data()
            if self.reg is None:
                model, _ = core.need_model()
                doubt = core.result.pose_warning if core.result is not None else None
                last = core.last_reg if core.last_reg is not None and core.last_reg.libr is not None else None
                # the result on show's own model (held at the supports stated when it was fitted), as
                # a warm start's: its β means nothing in another basis
                self.reg = LiveRegistration(last.model if last is not None and not doubt else model, data,
                                            options=viewer_options())
                if doubt:  # never continued from a pose nobody should believe: a fresh fit, and said so
                    core.notify("Live re-registration", "Starts afresh, not from the result on show: " + doubt,
                                error=True)
                elif last is not None:
                    self.reg.last = last  # continue from the result on show
            else:
                self.reg.base = merge(data)

    def _run(self):
        while not self._stop.is_set():
            self._wake.wait(0.5)
            self._wake.clear()
            if self._stop.is_set():
                return
            self._step()

    def _step(self):
        """One pass of the follower's thread: settle once switched off, else register the
        newest frame; the first pass after switching on registers even without a new frame."""
        if not self.on:
            if self.reg is not None and self.reg.frame is not None:
                self._settle()
            return
        f = self.link.frame
        fresh = f is not None and f is not self._last_frame
        # not "has the fit a last state": a fit continued from the result on show, or left by
        # an update that raised, has one before this switch-on registered anything, and the
        # follower then waited for a frame that a still probe never sends
        if not fresh and not self._first:
            return
        self._first = False
        self.skipped += max(self._pending - 1, 0)
        self._pending = 0
        self._last_frame = f
        try:
            self._update(f)
        except Exception as exc:  # shown, and the follower switches off
            log.error("live re-registration stopped", exc_info=True)  # the developer's trace, in the server's log
            self.on = False
            if self.reg is not None:  # nothing to settle: converging on the same data raised the same again
                self.reg.frame = None
            self.last_error = f"{exc.__class__.__name__}: {exc}"
            self.core.notify("Live re-registration stopped", self.last_error, error=True)

    def _update(self, f):
        self._base()
        assert self.reg is not None  # made by _base
        features = {}
        if f is not None and self.segmentation_px is not None:
            sd, _ = self.core.need_scene()
            img = np.asarray(f.image)
            T, _ = probe_pose_from_image(f.image_to_reference, img.shape[1], img.shape[0])
            features = segment_frame(sd, 100_000 + self.frames, T)
        t = time.perf_counter()
        reg = self.reg.update(features)
        self.ms.append(1000 * (time.perf_counter() - t))
        self.frames += 1
        self.live.show_registration(reg, final=False)

    def _settle(self):
        """The follower was switched off: converge on the last frame's data and keep it."""
        live_reg = self.reg
        assert live_reg is not None  # only called once it registered a frame
        try:
            reg = live_reg.settle()
            self.live.show_registration(reg, final=True, summary=self.summary())
        except Exception as exc:
            self.core.notify("Live re-registration", f"{exc.__class__.__name__}: {exc}", error=True)
        live_reg.frame = None


@dataclass
class LivePoints(Action):
    live: Live
    before: int  # live points before the recording

    def undo(self, cs):
        if self.live.recording:
            return "Stop digitising first."
        del self.live.core.need_session().live_points[self.before:]
        return Undone.DONE


class Live:
    """The tracker side of the viewer: digitising with the tracked stylus, freezing frames,
    live re-registration. Without a tracker (``link`` None) every action says so."""

    def __init__(self, core: Core, shown: Shown, slicer: Slicer, imaging: Imaging, config: TrackingConfig | None):
        self.core, self.shown, self.slicer, self.imaging = core, shown, slicer, imaging
        self.config = config  # connect once the scene is ready (``connect``)
        self.link: LiveLink | None = None
        self._record_start: int | None = None  # live points before the recording in progress (its undo point)
        self._record_owner: ClientState | None = None  # the tab that switched it on: the recording is its action
        self._shown = 0.0  # when a live registration was last drawn

    def connect(self):
        if self.config is not None:
            self.link = LiveLink(self, self.config).start()
            self.core.changed(Change.LIVE)

    def stop(self):
        if self.link is not None:
            self.link.stop()

    @property
    def recording(self) -> bool:
        return self.link is not None and self.link.recording

    @property
    def following(self) -> bool:
        """Live re-registration is on."""
        return self.link is not None and self.link.follower.on

    @property
    def tip(self) -> np.ndarray | None:
        return self.link.tip if self.link is not None else None

    def add_points(self, pts, labels):
        """Points the tracked stylus digitised (tracker mm) become session data at once."""
        core = self.core
        with core.lock:
            live_points = core.need_session().live_points
            for p, lab in zip(np.asarray(pts, float), labels, strict=True):
                live_points.append([float(p[0]), float(p[1]), float(p[2]), str(lab)])
        core.changed(Change.DATA)

    def set_recording(self, on: bool, label: str = "anterior", cs: ClientState | None = None) -> str | None:
        """Digitise with the tracked stylus while on; the recording is an undoable action of
        ``cs``, the tab that switched it on (None: of nobody's)."""
        link, core = self.link, self.core
        if link is None:
            return NO_TRACKER
        session = core.need_session()
        with core.lock:
            if on and not link.recording:
                self._record_start, self._record_owner = len(session.live_points), cs
        link.set_recording(on, label)
        if not on:
            with core.lock:
                start, self._record_start = self._record_start, None
                owner, self._record_owner = self._record_owner, None
                if owner is not None and start is not None and len(session.live_points) > start:
                    owner.current().undo.append(LivePoints(self, start))
        core.changed(Change.LIVE)
        return None

    def set_follow(self, on: bool) -> str | None:
        """Re-register on every new tracked frame while on; switched off, the fit is
        converged on the last frame's data and kept as the result."""
        link, core = self.link, self.core
        if link is None:
            return NO_TRACKER
        if on and core.worker is not None and core.worker.busy:
            return "A registration is running; wait for it or cancel it."
        err = link.follower.set(on)
        core.changed(Change.LIVE)
        return err

    def show_registration(self, reg: Registration, final: bool, summary: str = ""):
        """A live re-registration (``LiveFollower``): shown at most ``VIEW_MIN_S`` apart
        while the probe moves, sent to Slicer, and kept as the result when ``final``."""
        core, shown = self.core, self.shown
        beta = reg.libr.beta if reg.libr is not None else None
        now = time.monotonic()
        checked = checked_by(core.result, reg, warm=True)
        reg.carry(checked, CARRIED)  # before anything shows its warnings: Slicer, the row
        self.slicer.send(reg, throttle=not final)
        if not final and now - self._shown < VIEW_MIN_S:
            return
        self._shown = now
        err = shown.node_error(reg.rigid, beta, reg.model)
        predicted = shown.predict(reg, checked) if final else (None, [])  # ~0.1 s: not on every frame
        state = RegisteredState(RunKind.LIVE.label, reg.rigid, beta, err, *predicted,
                                data_model_frame=reg.data_model_frame, pose_warning=one_line(reg.pose_doubts),
                                checked=checked, model=core.kept_model(reg.model))
        flipped = (core.result.pose_warning if core.result is not None else None) != state.pose_warning
        with core.lock:
            core.result, core.last_reg = state, reg
            if core.worker is not None:
                core.worker.last = reg  # a warm start continues from here
            if final:
                session = core.need_session()
                session.result = state.to_json()
                points = int(sum(len(v) for v in core.data().values()))
                entry = RunEntry.of(RunKind.LIVE, reg, points, sum(reg.seconds.values()), err, live=summary)
                entry.targets_mm = shown.target_errors(reg.rigid, beta, reg.model)
                session.log.append(entry)
                core.shown_runs[len(session.log) - 1] = (state, reg, [])
        if final:
            core.changed(Change.RESULT)
            return
        if flipped:  # the red pose warning comes and goes with the live result
            core.changed(Change.LIVE)
        geom = shown.geometry(reg.rigid, beta)
        core.each_view(lambda v: v.show_live_registration(geom, err))

    def freeze_frame(self, cs: ClientState) -> str | None:
        """The latest tracked ultrasound frame becomes a plane of the session (to draw on)."""
        link, core = self.link, self.core
        if link is None:
            return NO_TRACKER
        index = link.probe.freeze()
        if isinstance(index, str):
            return index
        self.imaging.show(cs, index)
        core.changed(Change.DATA)
        return None
