"""Intraoperative data sources as rooms: the protocol a source implements and the registry
that finds it.

A source is one module here, ``navapp/simulation/sources/<name>.py``, defining ``SOURCE``
(a ``SimulatedSource``: its name and its functions), plus the rows of ``features.TABLE``
whose ``source`` is ``<name>``.
Nothing else lists it: the registry finds the module from the table, the scene parser
reads the source's own ``[<name>]`` table through it, the simulator asks it for its points,
the viewer's session keeps them (``SceneData.sourced``, ``features.SOURCED``) and draws them by their feature's
colour, and live points arrive as an OpenIGTLink POINT message whose device name is the
feature's name (``tracking.client``; pyigtl 0.3 decodes no POLYDATA). Its points enter the registration as
the data of its features, by the feature's kind, target and weight.

A source is either in every scene (``always``: the stylus, then the iUS planes; its table
optional, its defaults otherwise), drawing on the scene's own random stream in the order it
always has, or enabled by its table and drawing on a stream of its own (the laparoscope), so
that enabling it leaves every other draw of the scene as it was.

A tracked imaging source (the iUS probe) also simulates one ``frame`` at a pose chosen after
the simulation: a free plane the user placed, or a live frame's automatic segmentation
(``scenedata.acquire_free_plane``, ``scenedata.segment_frame``).

Received, every source has one home too, ``navapp/tracking/receivers`` (a tracked source's
points may arrive in its own frame, placed by its pose: ``[tools.<source>]`` in the tracking
config); shown, ``navapp/app/sources`` (the stylus's tip and its digitised points, the probe's
tracked frames: ``features.TRACKED``; every point source's points by one generic module);
fiducials have no module (``features.HAND_WIRED``); see docs/decisions/sources.md, "Data sources
as rooms" and sessions 34 and 35.
"""

import importlib
import importlib.util
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cache
from typing import Any

import numpy as np
import trimesh

from ...anatomy.model import PreopModel
from ...features import TABLE
from ..effects import Ledger


@dataclass(frozen=True)
class Sight:
    """What a simulated source may see of the truth: the deformed liver surface in tracker
    space (mm), its preoperative model (the same vertices and faces, its regions) and the
    ledger the simulation marks what ran in."""

    liver: trimesh.Trimesh
    preop: PreopModel
    ledger: Ledger
    vessels: dict[str, trimesh.Trimesh] = field(default_factory=dict)  # "portal", "hepatic", deformed, if any
    effects: tuple = ()  # the scene's declared acquisition effects (``effects.Effect``)
    seed: int = 0  # the scene's seed (a tracked frame's own stream, the planes' placement)


@dataclass
class Acquired:
    """A source's simulated acquisition: points per feature (tracker mm, (N, 3) each), what
    the simulation report says of it (JSON-able) and, for a tracked imaging source, the frames
    it acquired (``ultrasound.PlaneData``: pose, features, image; written by the source)."""

    points: dict[str, np.ndarray]
    report: Any = field(default_factory=dict)
    frames: list = field(default_factory=list)


@dataclass(frozen=True)
class SimulatedSource:
    """An intraoperative data source the simulator can acquire from the truth.

    ``name`` is both the ``features.TABLE`` ``source`` of the features it feeds and the
    scene TOML table that enables it; a scene without that table simulates nothing of it.
    ``always``: in every scene (its table optional), on the scene's own random stream.
    ``parse(table, path)``: the source's settings from its scene table (a frozen dataclass of
    plain values, hashed into the scene's cache key); a bad table raises ``InputError`` in one
    line naming the key. ``acquire(spec, sight, rng)``: the ``Acquired`` points on the deformed
    truth (``Sight``).
    ``acquires_effects``: the source applies the scene's tracking noise and dropout itself (a
    tracked frame: per frame, through its pose; the laparoscope: one rigid error of its pose
    per view); otherwise the simulator applies them to its points and reports how many each
    feature kept. A tracked tool's report holds ``tool_to_tracker`` (4 × 4 mm, the pose the
    tracker reported when it acquired), which ``navapp replay`` sends as the tool's TRANSFORM
    with the points in its frame when the tracking config makes the source tracked.
    ``frame(spec, sight, index, probe_to_tracker, live)``: a tracked imaging source's one frame
    at a pose chosen after the simulation (``PlaneData``), or None.
    ``report_key``: its entry's key in ``truth/report.json`` (its name unless it had another
    before sources were rooms: the iUS planes' ``planes``).
    """

    name: str
    always: bool
    parse: Callable[[dict, Any], Any]
    acquire: Callable[[Any, Sight, np.random.Generator], Acquired]
    acquires_effects: bool = False
    frame: Callable[..., Any] | None = None
    report_key: str = ""

    @property
    def report_as(self) -> str:
        """Its entry's key in ``truth/report.json``."""
        return self.report_key or self.name


def features_of(source: str) -> tuple[str, ...]:
    """The features ``source`` feeds (its rows of ``features.TABLE``)."""
    return tuple(f.name for f in TABLE if f.source == source)


@cache
def registered() -> dict[str, SimulatedSource]:
    """Source name → its ``SOURCE``, for every ``features.TABLE`` source that has a module here."""
    out: dict[str, SimulatedSource] = {}
    for name in dict.fromkeys(f.source for f in TABLE):
        module = f"{__name__}.{name}"
        if importlib.util.find_spec(module) is not None:
            out[name] = importlib.import_module(module).SOURCE
    return out
