"""The tracked stylus: swaths across the anterior surface (or one contiguous patch), as a
surgeon sweeps the stylus tip, until the requested fraction of the anterior area is covered.

The stylus is in every scene (its ``[stylus]`` table optional, these defaults otherwise) and
draws on the scene's own random stream before the iUS planes, as it did before sources
were rooms: a scene simulates to the same files as then. The swath and patch geometry is
``simulation/stylus.py``.

In a scene (every key optional; these are the defaults)::

    [stylus]
    coverage = 0.2           # fraction of the anterior surface the swaths cover
    pattern = "swaths"       # or "patch": one contiguous partial scan around ``at``
    points = 500             # a patch's point count
    at = [x, y, z]           # a patch's centre (mm); needed with pattern = "patch"
"""

from dataclasses import dataclass

import numpy as np

from ...errors import InputError
from ...features import STYLUS
from ...mechanics.controlpoints import nodal_areas
from ..stylus import surface_patch, swath_pattern, thin
from . import Acquired, Sight, SimulatedSource

NAME = "stylus"
PATTERNS = ("swaths", "patch")


@dataclass(frozen=True)
class StylusSpec:
    """A scene's ``[stylus]``. The field names are those the scene's own fields had, so a
    scene's cache and session keys are as before (``scenedata._scene_params``)."""

    coverage: float = 0.2
    pattern: str = "swaths"
    points: int = 500
    patch_at: tuple[float, float, float] | None = None


_KEYS: dict[str, type] = {"coverage": float, "pattern": str, "points": int, "at": list}


def _value(key: str, value, path):
    kind = _KEYS[key]
    if kind is list:
        if not (isinstance(value, list) and len(value) == 3
                and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
            raise InputError(f"stylus.{key} must be three numbers [x, y, z] (mm), got {value!r}", path)
        return tuple(float(v) for v in value)
    if kind is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if kind is int and isinstance(value, int) and not isinstance(value, bool):
        return value
    if kind is str and isinstance(value, str):
        return value
    raise InputError(f"stylus.{key} must be a {kind.__name__}, got {value!r}", path)


def parse(table, path) -> StylusSpec:
    """A scene's ``[stylus]`` table; one ``InputError`` line for anything wrong."""
    if not isinstance(table, dict):
        raise InputError("[stylus] must be a table", path)
    values = {}
    for key, value in table.items():
        if key not in _KEYS:
            raise InputError(f"unknown key stylus.{key} (known: {', '.join(_KEYS)})", path)
        values["patch_at" if key == "at" else key] = _value(key, value, path)
    spec = StylusSpec(**values)
    if spec.pattern not in PATTERNS:
        raise InputError(f"stylus.pattern must be \"swaths\" or \"patch\", got {spec.pattern!r}", path)
    if spec.pattern == "patch" and spec.patch_at is None:
        raise InputError("stylus.pattern = \"patch\" needs stylus.at = [x, y, z] (the patch centre, mm)", path)
    if not 10 <= spec.points <= 100000:
        raise InputError(f"stylus.points must be between 10 and 100000, got {spec.points}", path)
    if not 0.0 < spec.coverage <= 1.0:
        raise InputError("stylus.coverage must be in (0, 1]", path)
    return spec


def acquire(spec: StylusSpec, sight: Sight, rng: np.random.Generator) -> Acquired:
    """The digitised points per stylus feature (named after the liver-surface regions they
    are digitised on), and the fraction of the stylus regions' area covered."""
    sight.ledger.mark("stylus")
    preop = sight.preop
    v, faces = preop.liver.vertices, preop.liver.faces
    areas = nodal_areas(v, faces, np.arange(len(v)))
    regions = np.any([preop.region_mask(n) for n in STYLUS], axis=0)
    seen = sight.liver.vertices  # the deformed surface, vertex for vertex
    if spec.pattern == "patch":
        sight.ledger.mark("surface_patch")
        if spec.patch_at is None:
            raise ValueError("a patch pattern needs stylus.at")
        _, pick, bary, covered = surface_patch(v, faces, spec.patch_at, spec.coverage, float(areas[regions].sum()),
                                               spec.points, rng)
        coverage = covered / float(areas[regions].sum())
        clouds = {"anterior": np.einsum("pk,pkj->pj", bary, seen[faces[pick]])}
    else:
        idx, coverage, _ = swath_pattern(v, areas, regions, spec.coverage, rng)
        clouds = {label: thin(seen[idx[preop.region_mask(label)[idx]]]) for label in STYLUS}
    return Acquired(clouds, {"coverage_of_anterior": round(coverage, 3)})


SOURCE = SimulatedSource(NAME, always=True, parse=parse, acquire=acquire)
