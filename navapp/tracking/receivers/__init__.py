"""The receiving side of the tracked data sources, one home: each source's OpenIGTLink
messages turned into the typed events of ``tracking.events`` and its latest kept.

The client (``tracking.client``) knows no tool: it checks every message (CRC, type, order),
hands it to the receiver that ``takes`` its type and device, counts it, tells the watchdog,
lets the receiver ``keep`` the event, and passes it on. The receivers are found from
``features.TABLE`` as the simulated sources are (``simulation.sources``): a source with a
module here (``receivers/<source>.py`` defining ``make(config, digitiser)``) is received by
it — the stylus's tip stream and its digitiser, the iUS probe's pose and frames; any other
source with features in ``features.SOURCED`` by ``points.PointsReceiver``: POINT messages
named as its features, in Reference or, tracked (``[tools.<source>] pose``), in the tool's
frame placed by its TRANSFORM (a tracked laparoscope's depth points). Fiducials
(``features.HAND_WIRED``) are not received. The protocol: ``base.Receiver``.
"""

import importlib
import importlib.util

from ...features import SOURCED, TABLE
from ..config import TrackingConfig
from ..digitiser import Digitiser
from .base import Event, Message, Receiver
from .points import PointsReceiver, make_points

__all__ = ["Event", "Message", "Receiver", "PointsReceiver", "build"]


def build(config: TrackingConfig, digitiser: Digitiser) -> tuple[Receiver, ...]:
    """One receiver per received source, in ``features.TABLE``'s order of sources."""
    out: list[Receiver] = []
    for source in dict.fromkeys(f.source for f in TABLE):
        module = f"{__name__}.{source}"
        if source not in ("base", "points") and importlib.util.find_spec(module) is not None:
            out.append(importlib.import_module(module).make(config, digitiser))
        elif any(f.source == source and f.name in SOURCED for f in TABLE):
            out.append(make_points(source, config))
    return tuple(out)
