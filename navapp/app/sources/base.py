"""What every shown source shares: the protocol it implements and what it is wired to."""

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ...tracking.client import TrackingClient
from ...tracking.config import TrackingConfig
from ...tracking.events import ToolStatus
from ..core import Core


@dataclass(frozen=True)
class Wiring:
    """What a shown source is given by the viewer's link to the tracker (``live.LiveLink``):
    the client whose receivers keep its latest, the tracking config (its device names), the
    views (``Core.each_view``, ``Core.changed``) and ``new_frame``, the live
    re-registration's cue that a fresh tracked frame is on show."""

    client: TrackingClient
    config: TrackingConfig
    core: Core
    new_frame: Callable[[], None]


class LiveSource(Protocol):
    """The showing side of one tracked data source (a ``features.TABLE`` ``source``).

    ``wakes(event)``: called in the client's thread for every event it passes on: True for an
    event of this source's, which wakes the viewer's pump at once (a source that delivers
    points keeps them until ``taken``). ``show(now, status)``: in the pump, what its receiver
    keeps now goes to the views (``status``: the watchdog's ``ToolStatus`` per device; a lost
    tool is taken off the views, not drawn where it was last seen); True when the live panels
    must be refreshed at once rather than at the next periodic refresh. ``age(status)``: the
    periodic refresh — restate what grows old (a lost tool's age). ``taken()``: its points
    (tracker mm, (N, 3)) and their features received since the last call, each once; the link
    calls it under one lock and adds them to the session in the sources' order.
    """

    source: str

    def wakes(self, event: object) -> bool: ...

    def show(self, now: float, status: dict[str, ToolStatus]) -> bool: ...

    def age(self, status: dict[str, ToolStatus]) -> None: ...

    def taken(self) -> list[tuple[np.ndarray, list[str]]]: ...


def shows(method: str, arg):
    """``fn(view)`` calling the view's ``method(arg)`` (bound now, not when called)."""
    return lambda v: getattr(v, method)(arg)
