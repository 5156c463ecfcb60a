"""A data source's points, shown: POINT messages named as its features (``features.SOURCED``:
a tracked laparoscope's depth points) join the session's data as they arrive."""

import threading

import numpy as np

from ...features import TABLE
from ...tracking.events import SourcePoints, ToolStatus
from .base import Wiring


class PointsShown:
    """The ``LiveSource`` of every source whose features arrive as points (``points.PointsReceiver``
    receives them): nothing to draw of its own — its points become session data (``taken``),
    drawn then by their feature's colour as every data point."""

    def __init__(self, source: str, wiring: Wiring):
        self.source = source
        self._features = frozenset(f.name for f in TABLE if f.source == source)
        self._lock = threading.Lock()  # the client's thread appends, the pump takes
        self._got: list[SourcePoints] = []

    def wakes(self, event: object) -> bool:
        if isinstance(event, SourcePoints) and event.feature in self._features:
            with self._lock:
                self._got.append(event)
            return True
        return False

    def show(self, now: float, status: dict[str, ToolStatus]) -> bool:
        return False

    def age(self, status: dict[str, ToolStatus]) -> None:
        pass

    def taken(self) -> list[tuple[np.ndarray, list[str]]]:
        with self._lock:
            got, self._got = self._got, []
        return [(ev.points, [ev.feature] * len(ev.points)) for ev in got]

