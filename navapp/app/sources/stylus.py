"""The tracked stylus, shown: its tip drawn as it moves, a red banner while it is lost, and
the points its digitiser records moved into the session."""

import numpy as np

from ...tracking.events import StylusSample, ToolStatus
from ...tracking.receivers.stylus import StylusSettings
from ..state import Change
from .base import Wiring, shows

TIP_MIN_S = 1.0 / 60  # at most this often per browser: a 100 Hz tracker would flood the websockets


class StylusShown:
    """The stylus's ``LiveSource``. ``tip``: where it is drawn now (None: not tracked now, or
    never seen); ``lost``: why the stylus, once seen, is not shown now (the viewer's red
    banner), else None. The digitiser records in the client's thread at the configured rate;
    ``taken`` hands on what it recorded since."""

    source = "stylus"

    def __init__(self, wiring: Wiring):
        self.client, self.core = wiring.client, wiring.core
        self.device = wiring.config.tool("stylus", StylusSettings).device
        self.tip: np.ndarray | None = None
        self.lost: str | None = None
        self.recorded = 0  # digitiser points already taken
        self._last_tip = 0.0
        self._last_state: str | None = None

    @property
    def recording(self) -> bool:
        return self.client.digitiser.recording

    def record(self, on: bool, label: str = "anterior") -> None:
        """Digitise the tip's points under the feature ``label`` while on (the digitiser
        samples them at its rate in the client's thread; ``taken`` hands them on)."""
        d = self.client.digitiser
        if on:
            d.start(label)
        else:
            d.stop()

    def wakes(self, event: object) -> bool:
        return isinstance(event, StylusSample)

    def show(self, now: float, status: dict[str, ToolStatus]) -> bool:
        s = self.client.latest_stylus
        # the latest sample stays there after the tracker stops: only a tool the watchdog
        # calls seen is drawn or measured from, so a stale pose never comes back
        st = status.get(self.device)
        fresh = self.client.fresh(self.source, status)
        moved = s is not None and (self.tip is None or not np.array_equal(s.tip, self.tip))
        if s is not None and fresh and moved and now - self._last_tip >= TIP_MIN_S:
            self._last_tip = now
            self.tip = np.array(s.tip, float)
            if self.lost is not None:
                self.lost = None
                self.core.each_view(lambda v: v.refresh(Change.LIVE))
            self.core.each_view(shows("show_live_tip", self.tip))
        elif not fresh and self.tip is not None:
            self.tip = None  # a lost tool is not shown where it was last seen, nor measured from
            self.lost = lost_line(self.device, st)
            self.core.each_view(lambda v: v.show_live_tip(None))
            self.core.each_view(lambda v: v.refresh(Change.LIVE))
        state = st.state if st is not None else None
        # at once when the stylus goes from stale to missing (else the periodic refresh: the age grows)
        urgent = self.lost is not None and state != self._last_state
        self._last_state = state
        return urgent

    def age(self, status: dict[str, ToolStatus]) -> None:
        if self.lost is not None:
            self.lost = lost_line(self.device, status.get(self.device))  # stale becomes missing; the age grows

    def taken(self) -> list[tuple[np.ndarray, list[str]]]:
        d = self.client.digitiser
        pts, labels = d.points(), d.labels()
        if len(pts) <= self.recorded:
            return []
        new, new_labels = pts[self.recorded:], labels[self.recorded:len(pts)]
        self.recorded = len(pts)
        return [(new, new_labels)]


def lost_line(device: str, st: ToolStatus | None) -> str:
    """The banner's words for a stylus not seen now (``st``: its ToolStatus, or None)."""
    state = st.state if st is not None else "missing"
    age = "" if st is None or st.age_s is None else f", last seen {st.age_s:.1f} s ago"
    return f"Stylus {'lost' if state == 'missing' else 'not tracked'} ({device}: {state}{age}): not shown, " \
           f"no tumour distances."


def make(wiring: Wiring) -> StylusShown:
    return StylusShown(wiring)
