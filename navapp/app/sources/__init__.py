"""The showing side of the tracked data sources, one home: what the viewer does with what each
source's receiver keeps — draws it, says when it is lost, and moves its points into the session.

The third room of a source, after its simulation (``simulation.sources``) and its receiving
(``tracking.receivers``), found from ``features.TABLE`` as they are: a source with a module
here (``app/sources/<source>.py`` defining ``make(wiring)``) is shown by it — the stylus's tip,
its lost banner and the digitiser's points (``stylus.py``); the iUS probe's latest frame, drawn
on the probe, frozen as a plane and followed by the live re-registration (``ius.py``); any
other source with features in ``features.SOURCED`` by ``points.PointsShown``: its POINT
messages' points join the session's data as they arrive, drawn by their feature's colour as
every data point (a tracked laparoscope's depth points). A new point source needs nothing
here. The protocol: ``base.LiveSource``. No viser here: the views draw (``show_live_tip``,
``show_live_frame``), the panels read what the sources keep.
"""

import importlib
import importlib.util

from ...features import SOURCED, TABLE
from .base import LiveSource, Wiring
from .points import PointsShown

__all__ = ["LiveSource", "PointsShown", "Wiring", "build"]


def build(wiring: Wiring) -> tuple[LiveSource, ...]:
    """One shown source per received source, in ``features.TABLE``'s order of sources (the
    stylus first: its digitised points join the session before a source's in one collection)."""
    out: list[LiveSource] = []
    for source in dict.fromkeys(f.source for f in TABLE):
        module = f"{__name__}.{source}"
        if source not in ("base", "points") and importlib.util.find_spec(module) is not None:
            out.append(importlib.import_module(module).make(wiring))
        elif any(f.source == source and f.name in SOURCED for f in TABLE):
            out.append(PointsShown(source, wiring))
    return tuple(out)
