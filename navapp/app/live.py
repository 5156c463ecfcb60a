"""The viewer's link to a tracker: a ``tracking.TrackingClient`` (OpenIGTLink, e.g. a PLUS
server or ``navapp replay``) pumped into the App a few times a second. No viser here.

- The stylus tip moves live in every browser (at most ``TIP_HZ`` updates a second).
- While digitising is on, the client's ``Digitiser`` records points at the configured
  rate in the client thread; the pump moves them into the session (saved at once), so a
  dropped connection or a browser reload loses nothing.
- The latest ultrasound frame is kept; "Freeze" turns it into a plane of the session
  (image saved as PNG beside session.json) that can be drawn on in the 2D view like any
  other plane.
- "Re-register on every frame" (``LiveFollower``): each new frame's contours (designated
  automatically when the scene declares ``auto_segmentation``) join the kept data and the
  model is re-registered warm-started from the last state (``tracking.LiveRegistration``),
  in a thread of its own so the tip never waits for it; frames that arrive while an update
  runs are skipped, the newest one is taken next.
- The pump wakes on every stylus or frame message (not on a timer), so a tracker message
  reaches the browsers within milliseconds.
"""

import statistics
import threading
import time
from collections import deque

import numpy as np

from ..simulation.scenedata import auto_segmentation, segment_frame
from ..simulation.ultrasound import PlaneData
from ..tracking.client import TrackingClient
from ..tracking.config import TrackingConfig
from ..tracking.events import ProbeSample, StylusSample
from ..tracking.live import LiveRegistration, merge

PUMP_HZ = 20.0  # status refresh and digitiser collection; tip and frames go out as they arrive
TIP_MIN_S = 1.0 / 60  # at most this often per browser: a 100 Hz tracker would flood the websockets
VIEW_MIN_S = 1.0 / 15  # live registrations shown at most this often (the model mesh is large)
LIVE_PLANE_BASE = 1000  # indices of frozen live frames start here


def probe_pose_from_image(image_to_reference, width_px, height_px) -> tuple[np.ndarray, float]:
    """navapp's ProbeToTracker (4×4, rigid: x lateral, y plane normal, z depth, origin at
    the centre of the probe face) and the pixel spacing (mm) of a frame whose
    ImageToReference maps (col, row, 0, 1) to mm; inverse of ``Probe.image_to_probe``."""
    m = np.asarray(image_to_reference, float)
    a, b, o = m[:3, 0], m[:3, 1], m[:3, 3]
    s = float(np.linalg.norm(a))
    x = a / s
    z = b / np.linalg.norm(b)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2] = x, y, z
    T[:3, 3] = o + a * (width_px - 1) / 2.0
    return T, s


class LiveLink:
    def __init__(self, app, config: TrackingConfig):
        self.app = app
        self.config = config
        self._wake = threading.Event()
        self.client = TrackingClient(config, on_event=self._on_event)
        self.follower = LiveFollower(self)
        self.tip = None
        self.frame = None  # latest ProbeSample
        self.recorded = 0  # digitiser points already moved into the session
        self._stop = threading.Event()
        self._collect_lock = threading.Lock()
        self._thread = None

    def start(self):
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

    def _on_event(self, ev):
        if isinstance(ev, (StylusSample, ProbeSample)):  # called in the client thread: only a wake-up
            self._wake.set()

    @property
    def recording(self) -> bool:
        return self.client.digitiser.recording

    def set_recording(self, on: bool, label="anterior"):
        d = self.client.digitiser
        if on:
            d.start(label)
        else:
            d.stop()
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
            pts = self.client.digitiser.points()
            labels = self.client.digitiser.labels()
            if len(pts) > self.recorded:
                new, new_labels = pts[self.recorded:], labels[self.recorded:len(pts)]
                self.recorded = len(pts)
                self.app.add_live_points(new, new_labels)

    def _pump(self):
        last_status = last_tip = last_collect = 0.0
        while not self._stop.is_set():
            self._wake.wait(1.0 / PUMP_HZ)
            self._wake.clear()
            now = time.monotonic()
            s = self.client.latest_stylus
            moved = s is not None and (self.tip is None or not np.array_equal(s.tip, self.tip))
            if moved and now - last_tip >= TIP_MIN_S:
                last_tip = now
                self.tip = np.array(s.tip, float)
                self.app.each_view(lambda v: v.show_live_tip(self.tip))
            f = self.client.latest_frame
            if f is not None and f is not self.frame:
                self.frame = f
                self.app.each_view(lambda v, f=f: v.show_live_frame(f))
                self.follower.new_frame()
            if now - last_collect >= 1.0 / PUMP_HZ:
                last_collect = now
                self._collect()
            if now - last_status > 0.5:
                last_status = now
                st = self.client.status().get(self.config.stylus)
                if self.tip is not None and (st is None or st.state == "missing"):
                    self.tip = None  # a lost tool is not shown where it was last seen, nor measured from
                    self.app.each_view(lambda v: v.show_live_tip(None))
                self.app.each_view(lambda v: v.refresh("live"))

    def frozen_plane(self, index) -> PlaneData | None:
        """The latest frame as a plane of the session, or None (no frame yet)."""
        f = self.frame
        if f is None:
            return None
        img = np.asarray(f.image)
        T, _ = probe_pose_from_image(f.image_to_reference, img.shape[1], img.shape[0])
        return PlaneData(index, "live", T, {}, img.astype(np.uint8))


class LiveFollower:
    """Re-registration on every new frame while ``on`` (see the module doc). The kept data
    are the session's (stylus, live points, planes, drawn contours), re-read whenever the
    session changes; the frame's own features are those the declared automatic
    segmentation designates (none without it: then each update re-fits the kept data)."""

    def __init__(self, link: LiveLink):
        self.link, self.app = link, link.app
        self.on = False
        self.reg: LiveRegistration | None = None
        self.frames = 0  # frames registered
        self.skipped = 0  # frames that arrived while an update ran
        self.ms: deque = deque(maxlen=2000)  # wall time per update
        self.last_error: str | None = None
        self._version = None
        self._last_frame = None
        self._pending = 0
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
        sd = self.app.sd
        return None if sd is None else auto_segmentation(sd.scene)

    def set(self, on: bool) -> str | None:
        app = self.app
        if on:
            if app.model is None:
                return "Still preparing the registration model."
            if sum(len(v) for v in app.data("all").values()) < 3 and self.segmentation_px is None:
                return "Collect data first: the scene declares no automatic segmentation of live frames."
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
        if not self.frames:
            return "Not re-registered on live frames yet."
        ms = list(self.ms)
        return (f"{self.frames} frames re-registered, {statistics.median(ms):.0f} ms median "
                f"(max {max(ms):.0f} ms), {self.skipped} frames skipped while busy")

    def _base(self):
        app = self.app
        if app.version != self._version or self.reg is None:
            self._version = app.version
            data = app.data("all")
            if self.reg is None:
                self.reg = LiveRegistration(app.model, data)
                if app.last_reg is not None and app.last_reg.libr is not None:
                    self.reg.last = app.last_reg  # continue from the result on show
            else:
                self.reg.base = merge(data)

    def _run(self):
        while not self._stop.is_set():
            self._wake.wait(0.5)
            self._wake.clear()
            if self._stop.is_set():
                return
            if not self.on:
                if self.reg is not None and self.reg.frame is not None:
                    self._settle()
                continue
            f = self.link.frame
            fresh = f is not None and f is not self._last_frame
            if not fresh and self.reg is not None and self.reg.last is not None:
                continue  # nothing new; the first pass registers the kept data even without a frame
            self.skipped += max(self._pending - 1, 0)
            self._pending = 0
            self._last_frame = f
            try:
                self._update(f)
            except Exception as exc:  # shown, and the follower switches off
                self.on = False
                self.last_error = f"{exc.__class__.__name__}: {exc}"
                self.app.notify("Live re-registration stopped", self.last_error, error=True)

    def _update(self, f):
        app = self.app
        self._base()
        features = {}
        if f is not None and self.segmentation_px is not None:
            img = np.asarray(f.image)
            T, _ = probe_pose_from_image(f.image_to_reference, img.shape[1], img.shape[0])
            features = segment_frame(app.sd, 100_000 + self.frames, T)
        t = time.perf_counter()
        reg = self.reg.update(features)
        self.ms.append(1000 * (time.perf_counter() - t))
        self.frames += 1
        app.show_live_registration(reg, final=False)

    def _settle(self):
        """The follower was switched off: converge on the last frame's data and keep it."""
        try:
            reg = self.reg.settle()
            self.app.show_live_registration(reg, final=True, summary=self.summary())
        except Exception as exc:
            self.app.notify("Live re-registration", f"{exc.__class__.__name__}: {exc}", error=True)
        self.reg.frame = None
