"""The viewer's link to a tracker: a ``tracking.TrackingClient`` (OpenIGTLink, e.g. a PLUS
server or ``navapp replay``) pumped into the App a few times a second. No viser here.

- The stylus tip moves live in every browser (at most ``TIP_HZ`` updates a second).
- While digitising is on, the client's ``Digitiser`` records points at the configured
  rate in the client thread; the pump moves them into the session (saved at once), so a
  dropped connection or a browser reload loses nothing.
- The latest ultrasound frame is kept; "Freeze" turns it into a plane of the session
  (image saved as PNG beside session.json) that can be drawn on in the 2D view like any
  other plane.
"""

import threading
import time

import numpy as np

from ..simulation.ultrasound import PlaneData
from ..tracking.client import TrackingClient
from ..tracking.config import TrackingConfig

PUMP_HZ = 20.0
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
        self.client = TrackingClient(config)
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
        return self

    def stop(self):
        self._stop.set()
        self.client.stop()

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
        lines = [f"{'connected to' if c.connected else 'waiting for'} {c.connection.address}"
                 f" (connections so far: {c.connects})"]
        for dev, st in c.status().items():
            age = "never" if st.age_s is None else f"{st.age_s * 1000:.0f} ms ago"
            lines.append(f"{dev}: **{st.state}** ({age}, {c.rate_hz(dev):.0f}/s)")
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
        last_status = 0.0
        while not self._stop.is_set():
            s = self.client.latest_stylus
            if s is not None and (self.tip is None or not np.array_equal(s.tip, self.tip)):
                self.tip = np.array(s.tip, float)
                self.app.each_view(lambda v: v.show_live_tip(self.tip))
            f = self.client.latest_frame
            if f is not None and f is not self.frame:
                self.frame = f
                self.app.each_view(lambda v, f=f: v.show_live_frame(f))
            self._collect()
            now = time.monotonic()
            if now - last_status > 0.5:
                last_status = now
                self.app.each_view(lambda v: v.refresh("live"))
            time.sleep(1.0 / PUMP_HZ)

    def frozen_plane(self, index) -> PlaneData | None:
        """The latest frame as a plane of the session, or None (no frame yet)."""
        f = self.frame
        if f is None:
            return None
        img = np.asarray(f.image)
        T, _ = probe_pose_from_image(f.image_to_reference, img.shape[1], img.shape[0])
        return PlaneData(index, "live", T, {}, img.astype(np.uint8))
