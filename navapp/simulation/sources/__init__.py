"""Intraoperative data sources as rooms: the protocol a source implements and the registry
that finds it.

A source is one module here, ``navapp/simulation/sources/<name>.py``, defining ``SOURCE``
(a ``SimulatedSource``: its name and its two functions), plus the rows of ``features.TABLE``
whose ``source`` is ``<name>``.
Nothing else lists it: the registry finds the module from the table, the scene parser
reads the source's own ``[<name>]`` table through it, the simulator asks it for its points,
the viewer's session keeps them (``SceneData.sourced``, ``features.SOURCED``) and draws them by their feature's
colour, and live points arrive as an OpenIGTLink POINT message whose device name is the
feature's name (``tracking.client``; pyigtl 0.3 decodes no POLYDATA). Its points enter the registration as
the data of its features, by the feature's kind, target and weight.

A source is either in every scene (``always``: the stylus; its table optional, its defaults
otherwise), drawing on the scene's own random stream in the order it always has, or enabled
by its table and drawing on a stream of its own (the laparoscope), so that enabling it
leaves every other draw of the scene as it was.

The stylus is simulated through this protocol, but received, kept and shown by hand (its
tracked tip, the digitiser, the viewer's sweep: ``features.HAND_WIRED``); the ultrasound
planes are still wired by hand throughout (``simulate.py``, ``scenedata.py``,
``app/live.py``); see docs/decisions.md, "Data sources as rooms" and "session 34".
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


@dataclass
class Acquired:
    """A source's simulated acquisition: points per feature (tracker mm, (N, 3) each) and
    what the simulation report says of it (JSON-able)."""

    points: dict[str, np.ndarray]
    report: dict[str, Any] = field(default_factory=dict)


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
    """

    name: str
    always: bool
    parse: Callable[[dict, Any], Any]
    acquire: Callable[[Any, Sight, np.random.Generator], Acquired]


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
