"""The receiving side of the tracked data sources, one home: each source's OpenIGTLink
messages turned into the typed events of ``tracking.events`` and its latest kept.

The client (``tracking.client``) knows no tool: it checks every message (CRC, type, order),
hands it to the receiver that ``takes`` its type and device, counts it, tells the watchdog,
lets the receiver ``keep`` the event, and passes it on. The receivers are found from
``features.TABLE`` as the simulated sources are (``simulation.sources``): a source with a
module here (``receivers/<source>.py``: its settings dataclass, their parser and ``make``;
``modules``) is received by it — the stylus's tip stream and its digitiser, the iUS probe's
pose and frames; any other source with features in ``features.SOURCED`` by ``points.PointsReceiver``: POINT messages
named as its features, in Reference or, tracked (``[tools.<source>] pose``), in the tool's
frame placed by its TRANSFORM (a tracked laparoscope's depth points). Fiducials
(``features.HAND_WIRED``) are not received. The protocols: ``base.Receiver``, ``base.ToolSettings``.
"""

import importlib
import importlib.util
from collections.abc import Iterable
from types import ModuleType

from ...features import SOURCED, TABLE
from . import points
from .base import Event, Message, Receiver, Shared, ToolSettings
from .points import PointsReceiver

__all__ = ["Event", "Message", "Receiver", "Shared", "ToolSettings", "PointsReceiver", "modules", "defaults",
           "build"]


def modules() -> dict[str, ModuleType]:
    """Each received source's receiver module, in ``features.TABLE``'s order of sources:
    ``receivers/<source>.py`` when there is one, else ``points`` for a source with features
    in ``features.SOURCED``. Each defines ``KEYS`` and ``TABLES`` (its part of the tracking
    TOML file), ``parse(source, data, path)`` and ``default(source)`` (its settings) and
    ``make(settings, shared)`` (its receiver)."""
    out: dict[str, ModuleType] = {}
    for source in dict.fromkeys(f.source for f in TABLE):
        module = f"{__name__}.{source}"
        if source not in ("base", "points") and importlib.util.find_spec(module) is not None:
            out[source] = importlib.import_module(module)
        elif any(f.source == source and f.name in SOURCED for f in TABLE):
            out[source] = points
    return out


def defaults() -> tuple[ToolSettings, ...]:
    """Every received source's default settings (PLUS's names; points in Reference)."""
    return tuple(m.default(source) for source, m in modules().items())


def build(tools: Iterable[ToolSettings], shared: Shared) -> tuple[Receiver, ...]:
    """One receiver per source's settings in ``tools``, in their order."""
    found = modules()
    return tuple(found[s.source].make(s, shared) for s in tools)
