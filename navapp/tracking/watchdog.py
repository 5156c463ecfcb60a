"""Per-device freshness, like SlicerIGT's Watchdog: "seen" while messages keep coming,
"stale" when the last one is older than ``stale_s``, "missing" when it is older than
``missing_s`` or none ever came."""

import threading
import time

from .events import ToolStatus


class Watchdog:
    def __init__(self, devices, stale_s: float, missing_s: float, clock=time.monotonic):
        self.devices = list(devices)
        self.stale_s, self.missing_s = stale_s, missing_s
        self.clock = clock
        self._last: dict[str, float] = {}
        self._reported: dict[str, str] = {}
        self._lock = threading.Lock()

    def seen(self, device: str, t: float | None = None):
        with self._lock:
            self._last[device] = self.clock() if t is None else t

    def status(self, now: float | None = None) -> dict:
        """device → ToolStatus, for every watched device."""
        now = self.clock() if now is None else now
        out = {}
        with self._lock:
            for d in self.devices:
                last = self._last.get(d)
                if last is None:
                    out[d] = ToolStatus(d, "missing", None)
                    continue
                age = max(0.0, now - last)
                state = "seen" if age <= self.stale_s else ("stale" if age <= self.missing_s else "missing")
                out[d] = ToolStatus(d, state, age)
        return out

    def changes(self, now: float | None = None) -> list:
        """The ToolStatus of each device whose state changed since the last call."""
        out = []
        for d, s in self.status(now).items():
            if self._reported.get(d) != s.state:
                self._reported[d] = s.state
                out.append(s)
        return out
