"""Stylus digitisation: while recording, keep stylus tip positions at a set rate.

The digitiser belongs to the app session, not to a connection: a dropped and reopened
OpenIGTLink connection (or a restarted PLUS server) changes nothing that was recorded, and
recording simply resumes when samples flow again. Thread-safe: the client thread feeds it,
the app reads it.
"""

import threading

import numpy as np

from .events import StylusSample


class Digitiser:
    def __init__(self, rate_hz: float = 10.0):
        if rate_hz <= 0:
            raise ValueError("rate_hz must be positive")
        self.rate_hz = float(rate_hz)
        self._lock = threading.Lock()
        self._recording = False
        self._label = "anterior"
        self._points: list = []
        self._times: list = []
        self._labels: list = []
        self._due: float | None = None

    # ------------------------------------------------------------------ control
    def start(self, label: str = "anterior"):
        """Start recording; points carry ``label`` (a navapp feature name: anterior,
        falciform, ridge_left, ridge_right, fiducials)."""
        with self._lock:
            self._recording, self._label, self._due = True, label, None

    def stop(self):
        with self._lock:
            self._recording = False

    @property
    def recording(self) -> bool:
        return self._recording

    def clear(self, label: str | None = None):
        with self._lock:
            keep = [i for i, lab in enumerate(self._labels) if label is not None and lab != label]
            self._points = [self._points[i] for i in keep]
            self._times = [self._times[i] for i in keep]
            self._labels = [self._labels[i] for i in keep]

    def undo(self, n: int = 1):
        """Drop the last ``n`` recorded points."""
        with self._lock:
            for lst in (self._points, self._times, self._labels):
                del lst[max(0, len(lst) - n):]

    # ------------------------------------------------------------------ data
    def feed(self, sample: StylusSample) -> bool:
        """Offer one stylus sample; True when it was recorded. The schedule runs on the
        samples' own timestamps: one point per 1/rate_hz seconds on average (a 25 Hz stream
        digitised at 10 Hz keeps 10 points a second, not every third)."""
        period = 1.0 / self.rate_hz
        with self._lock:
            if not self._recording:
                return False
            t = sample.t_sent
            if self._due is not None and t < self._due:
                return False
            self._due = self._due + period if (self._due is not None and t - self._due < period) else t + period
            self._points.append(np.array(sample.tip, float))
            self._times.append(t)
            self._labels.append(self._label)
            return True

    def points(self, label: str | None = None) -> np.ndarray:
        """(N, 3) mm, Reference frame, in recording order."""
        with self._lock:
            pts = [p for p, lab in zip(self._points, self._labels, strict=True) if label is None or lab == label]
        return np.array(pts, float).reshape(-1, 3)

    def timestamps(self) -> np.ndarray:
        with self._lock:
            return np.array(self._times, float)

    def labels(self) -> list:
        with self._lock:
            return list(self._labels)

    def features(self) -> dict:
        """label → (N, 3) points: the stylus part of ``register()``'s data."""
        with self._lock:
            out: dict[str, list] = {}
            for p, lab in zip(self._points, self._labels, strict=True):
                out.setdefault(lab, []).append(p)
        return {k: np.array(v) for k, v in out.items()}

    def __len__(self):
        return len(self._points)
