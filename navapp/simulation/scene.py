"""Scenes: what to simulate, declared in TOML (``navapp/scenes/*.toml``, shipped in the package).

Only what a scene declares is simulated: no iUS section or image without ``[ius]``
planes, no nonlinear solve unless ``deformation.large = true``, no effect that is not
listed under ``[[effects]]``. Schema errors are one line naming the key.

Example::

    name = "phantom0-L"
    [anatomy]
    phantom = 0              # or: case = "path/to/case"   (its preop/ part)
    [deformation]
    release = "L"            # supporting ligaments released: "L", "N" (none) or "R"
    gravity_tilt_deg = 25.0  # gravity tilted from posterior toward the released side
    large = false            # true: neo-Hookean, Newton
    mesh_edge_mm = 3.5       # the truth's own (finer) mesh
    pressure_pa = 0.0        # inward pressure on the anterior surface (insufflation)
    head_up_deg = 0.0        # reverse Trendelenburg: gravity turned this far toward inferior
    # transpose_from = {phantom = 3, mesh_edge_mm = 5.0}
    #   the loads above deform reference phantom 3 instead, and its displacement is carried
    #   onto this liver through an inexact correspondence (transpose.py)
    [stylus]                 # a source in every scene (``sources/stylus.py``)
    coverage = 0.2           # fraction of the anterior surface the swaths cover
    [ius]                    # a source in every scene (``sources/ius.py``)
    planes = 16              # 8 vertical + 8 lateral; 0 for none
    [[effects]]
    kind = "tracking_noise"
    sd_mm = 0.5
    [laparoscope]            # a registered data source's own table (``sources``): enables it
    distance_mm = 120.0
"""

import tomllib
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path

from ..defaults import N_PLANES
from ..errors import InputError
from ..mechanics.supports import REGIONS, RELEASES
from .effects import Effect
from .sources import registered

EFFECT_PARAMS = {
    "tracking_noise": {"sd_mm": float},
    "calibration_error": {"rotation_deg": float, "translation_mm": float},
    "probe_compression": {"depth_mm": float, "radius_mm": float},
    "contour_jitter": {"sd_px": float},
    "dropout": {"fraction": float},
    # every intraoperative point (data, truth targets and surfaces, probe poses) moved by one
    # rigid transform about the data centroid: the tracker frame is not the preoperative one
    "tracker_offset": {"rotation_deg": float, "translation_mm": float},
    # live streams only (navapp replay, the viewer's live re-registration):
    "latency": {"ms": float},  # every tracker/image message sent this late after the moment it describes
    "auto_segmentation": {"sd_px": float},  # live frames' contours designated automatically, with this error
}


@dataclass(frozen=True)
class Transposition:
    """Where a transposed truth comes from (``simulation/transpose.py``): the reference
    phantom, deformed by the scene's loads on its own tet mesh of ``mesh_edge_mm``."""

    phantom: int
    mesh_edge_mm: float = 5.0


_TRANSPOSE_KEYS = {"phantom": int, "mesh_edge_mm": float}

TOOL_SITES = ("anterior", "inferior")
SUPPORTS = tuple(s.value for s in REGIONS)  # what may hold the liver, one home: ``mechanics.supports``


@dataclass(frozen=True)
class ToolSpec:
    """A scene's ``[tool]``: where the indentation is (``site``, a point ``at`` mm near it),
    its footprint radius and depth (mm) and how it is applied (``truth.ToolLoad``)."""

    site: str
    at: tuple
    radius_mm: float
    depth_mm: float
    load: str = "displacement"


_TOOL_KEYS = {"site": str, "at": list, "radius_mm": float, "depth_mm": float, "load": str}


@dataclass
class Scene:
    """What to simulate (a scene TOML, ``navapp/scenes/*.toml``): the anatomy (a phantom
    index or a case folder), the true deformation (ligament release, gravity tilt, linear or
    neo-Hookean, truth mesh edge mm, E Pa, pressure Pa, or a transposition), the
    data sources (``sources``: the stylus and the iUS planes in every scene) and the
    acquisition effects."""

    name: str
    phantom: int | None = 0
    case: Path | None = None
    release: str = "N"
    gravity_tilt_deg: float = 25.0
    large: bool = False
    mesh_edge_mm: float = 3.5
    truth_E_pa: float = 5000.0
    pressure_pa: float = 0.0
    head_up_deg: float = 0.0
    transpose_from: "Transposition | None" = None
    gravity: bool = True
    supports: str = "ligaments"
    tool: "ToolSpec | None" = None
    effects: list = field(default_factory=list)
    seed: int = 0
    source: Path | None = None
    # [pose]: the case says its data's frame is registered to the preoperative one, to within
    # these standard deviations (case.toml [intraop.pose]); None: the scene's tracker offset's own
    # size (its translation_mm, rotation_deg), or ``DECLARED_POSE`` for data in the preoperative frame
    pose_declared: bool = False
    pose_sd_mm: float | None = None
    pose_sd_deg: float | None = None
    # the registered data sources it enables (``sources``): source name → its parsed table;
    # the sources in every scene (``always``: the stylus) are here whether or not it has their table
    sources: dict = field(default_factory=dict)

    @property
    def planes(self) -> int:
        """The number of preset iUS planes (``[ius] planes``; ``sources/ius.py``)."""
        spec = self.sources.get("ius")
        return 0 if spec is None else int(spec.planes)

    def with_planes(self, planes: int) -> "Scene":
        """This scene with ``planes`` preset iUS planes (its ``[ius] planes``), every other
        setting as it was."""
        return replace(self, sources={**self.sources, "ius": registered()["ius"].parse({"planes": planes},
                                                                                      self.source)})

    def declared_pose(self) -> tuple[float, float] | None:
        """(sd_mm, sd_deg) the case declares (``[pose]``), or None (an unknown frame)."""
        if not self.pose_declared:
            return None
        offset = next((e.params for e in self.effects if e.kind == "tracker_offset"), None)
        mm, deg = DECLARED_POSE if offset is None else (offset["translation_mm"], offset["rotation_deg"])
        return (self.pose_sd_mm or max(mm, 0.1), self.pose_sd_deg or max(deg, 0.1))


DECLARED_POSE = (1.5, 1.5)
"""(sd_mm, sd_deg) a scene with ``[pose] declared = true`` and no tracker offset declares by
default: a fiducial registration's few millimetres and degrees."""


_SECTIONS: dict[str, dict[str, type]] = {
    "anatomy": {"phantom": int, "case": str},
    "deformation": {"release": str, "gravity_tilt_deg": float, "large": bool, "mesh_edge_mm": float,
                    "truth_E_pa": float, "pressure_pa": float, "head_up_deg": float,
                    "transpose_from": dict, "gravity": bool, "supports": str},
    "pose": {"declared": bool, "sd_mm": float, "sd_deg": float},
}


def _typed(value, kind, key, path):
    if kind is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if kind is int and isinstance(value, int) and not isinstance(value, bool):
        return value
    if isinstance(value, kind):
        return value
    raise InputError(f"{key} must be a {kind.__name__}, got {value!r}", path)


def _transposition(table: dict, path) -> Transposition:
    for key in table:
        if key not in _TRANSPOSE_KEYS:
            known = ", ".join(_TRANSPOSE_KEYS)
            raise InputError(f"unknown key deformation.transpose_from.{key} (known: {known})", path)
    if "phantom" not in table:
        raise InputError("deformation.transpose_from needs phantom (the reference liver's index)", path)
    values = {k: _typed(v, _TRANSPOSE_KEYS[k], f"deformation.transpose_from.{k}", path) for k, v in table.items()}
    if values["phantom"] < 0:
        raise InputError("deformation.transpose_from.phantom must be >= 0", path)
    if values.get("mesh_edge_mm", 1.0) <= 0:
        raise InputError("deformation.transpose_from.mesh_edge_mm must be positive", path)
    return Transposition(**values)


def _point(value, key, path) -> tuple:
    if not (isinstance(value, list) and len(value) == 3
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
        raise InputError(f"{key} must be three numbers [x, y, z] (mm), got {value!r}", path)
    return tuple(float(v) for v in value)


def _tool(table, path) -> ToolSpec:
    if not isinstance(table, dict):
        raise InputError("[tool] must be a table", path)
    for key in table:
        if key not in _TOOL_KEYS:
            raise InputError(f"unknown key tool.{key} (known: {', '.join(_TOOL_KEYS)})", path)
    missing = {"site", "at", "radius_mm", "depth_mm"} - set(table)
    if missing:
        raise InputError(f"[tool] needs {', '.join(sorted(missing))}", path)
    scalars = {k: _typed(v, _TOOL_KEYS[k], f"tool.{k}", path) for k, v in table.items() if k != "at"}
    spec = ToolSpec(site=scalars["site"], at=_point(table["at"], "tool.at", path), radius_mm=scalars["radius_mm"],
                    depth_mm=scalars["depth_mm"], load=scalars.get("load", "displacement"))
    if spec.site not in TOOL_SITES:
        raise InputError(f"tool.site must be one of {', '.join(TOOL_SITES)}, got {spec.site!r}", path)
    if not 2.0 <= spec.radius_mm <= 40.0:
        raise InputError(f"tool.radius_mm must be between 2 and 40, got {spec.radius_mm:g}", path)
    if not 0.0 < spec.depth_mm <= 80.0:
        raise InputError(f"tool.depth_mm must be in (0, 80], got {spec.depth_mm:g}", path)
    if spec.load not in ("displacement", "pressure"):
        raise InputError(f"tool.load must be \"displacement\" or \"pressure\", got {spec.load!r}", path)
    return spec


def parse_scene(data: dict, path=None) -> Scene:
    """Validate a scene dictionary (as loaded from TOML)."""
    known = {"name", "seed", "effects", "tool", *_SECTIONS, *registered()}
    for key in data:
        if key not in known:
            raise InputError(f"unknown key {key!r} (known: {', '.join(sorted(known))})", path)
    scene = Scene(name=_typed(data.get("name", Path(path).stem if path else "scene"), str, "name", path),
                  seed=_typed(data.get("seed", 0), int, "seed", path), source=Path(path) if path else None)
    for section, keys in _SECTIONS.items():
        table = data.get(section, {})
        if not isinstance(table, dict):
            raise InputError(f"[{section}] must be a table", path)
        for key, value in table.items():
            if key not in keys:
                raise InputError(f"unknown key {section}.{key} (known: {', '.join(keys)})", path)
            if keys[key] is dict:
                if not isinstance(value, dict):
                    raise InputError(f"{section}.{key} must be a table, e.g. {{phantom = 3}}", path)
                value = _transposition(value, path)
            else:
                value = _typed(value, keys[key], f"{section}.{key}", path)
            attr = f"pose_{key}" if section == "pose" else key
            setattr(scene, attr, Path(value) if key == "case" else value)
    if "tool" in data:
        scene.tool = _tool(data["tool"], path)
    for name, source in registered().items():
        if name in data or source.always:
            scene.sources[name] = source.parse(data.get(name, {}), path)
    if scene.supports not in SUPPORTS:
        raise InputError(f"deformation.supports must be one of {', '.join(SUPPORTS)}, got {scene.supports!r}", path)
    if scene.tool is not None and scene.transpose_from is not None:
        raise InputError("a [tool] presses on this liver's own truth: it cannot be combined with "
                         "deformation.transpose_from", path)
    if scene.tool is not None and scene.tool.load == "displacement" and scene.large:
        raise InputError("tool.load = \"displacement\" needs the linear truth (large = false); "
                         "use load = \"pressure\"", path)
    if "case" in data.get("anatomy", {}):
        scene.phantom = None
    if scene.release not in RELEASES:
        raise InputError(f"deformation.release must be \"L\", \"N\" or \"R\", got {scene.release!r}", path)
    if any(v is not None and v <= 0 for v in (scene.pose_sd_mm, scene.pose_sd_deg)):
        raise InputError("pose.sd_mm and pose.sd_deg must be positive (standard deviations, mm and degrees)", path)
    if scene.mesh_edge_mm <= 0 or scene.truth_E_pa <= 0:
        raise InputError("deformation.mesh_edge_mm and deformation.truth_E_pa must be positive", path)
    if not 0.0 <= scene.gravity_tilt_deg <= 90.0:
        raise InputError(f"deformation.gravity_tilt_deg must be between 0 and 90, got {scene.gravity_tilt_deg:g}",
                         path)
    if not -90.0 < scene.head_up_deg < 90.0:
        raise InputError("deformation.head_up_deg must be between -90 and 90", path)
    if scene.pressure_pa < 0:
        raise InputError("deformation.pressure_pa must be >= 0 (an inward pressure on the anterior surface)", path)
    effects = data.get("effects", [])
    if not isinstance(effects, list):
        raise InputError("effects must be an array of tables ([[effects]])", path)
    for i, e in enumerate(effects):
        kind = e.get("kind") if isinstance(e, dict) else None
        if not isinstance(kind, str) or kind not in EFFECT_PARAMS:  # a list or table is no kind (a traceback)
            raise InputError(f"effects[{i}].kind must be one of {', '.join(EFFECT_PARAMS)}, got {kind!r}", path)
        params = {}
        for key, value in e.items():
            if key == "kind":
                continue
            if key not in EFFECT_PARAMS[kind]:
                raise InputError(f"unknown key effects[{i}].{key} for {kind} "
                                 f"(known: {', '.join(EFFECT_PARAMS[kind])})", path)
            params[key] = _typed(value, EFFECT_PARAMS[kind][key], f"effects[{i}].{key}", path)
        missing = set(EFFECT_PARAMS[kind]) - set(params)
        if missing:
            raise InputError(f"effects[{i}] ({kind}) needs {', '.join(sorted(missing))}", path)
        scene.effects.append(Effect(kind, params))
    from ..schema import check_tables  # ranges by key name: effect keys added later are covered too

    check_tables(data, path)
    return scene


DEMO_SCENE = {  # the built-in demo scene; navapp/scenes/demo.toml says the same (a test checks)
    "name": "demo", "seed": 1,
    "anatomy": {"phantom": 0},
    "deformation": {"release": "L", "gravity_tilt_deg": 25.0, "large": False, "mesh_edge_mm": 3.5,
                    "truth_E_pa": 5000.0},
    "stylus": {"coverage": 0.2},
    "ius": {"planes": N_PLANES},
    "effects": [{"kind": "tracking_noise", "sd_mm": 0.3}, {"kind": "auto_segmentation", "sd_px": 1.0}],
}


def demo_scene() -> Scene:
    """The built-in demo scene (phantom 0, stylus, 16 iUS planes; ``navapp/scenes/demo.toml``)."""
    return parse_scene(DEMO_SCENE, "demo.toml")


def load_scene(path) -> Scene:
    """Read a scene TOML; a relative ``anatomy.case`` is resolved against the file's folder.
    Raises InputError (one line) for a missing file, invalid TOML or an unknown key."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise InputError("no such scene file", path) from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"invalid TOML ({exc})", path) from None
    scene = parse_scene(data, path)
    if scene.case is not None and not scene.case.is_absolute():
        scene.case = (path.parent / scene.case).resolve()
    return scene


def scene_dir() -> Path:
    """The scenes shipped inside the package (demo and the nine study scenes)."""
    return Path(str(resources.files("navapp") / "scenes"))


SCENE_SETS = {"direct": "phantom*-*.toml", "lap": "lap*-*.toml", "tool": "tool*-*.toml"}
"""The study scene sets: ``direct`` (each liver deformed by its own elastic model under
gravity), ``lap`` (laparoscopic loading of a reference liver, transposed) and ``tool``
(a local tool indentation of a liver held at its supports, partial surface data)."""


def study_scenes(which: str = "direct") -> list[Path]:
    """The study scenes of a set (``SCENE_SETS``), sorted by name."""
    if which not in SCENE_SETS:
        raise InputError(f"unknown scene set {which!r} (known: {', '.join(SCENE_SETS)})")
    return sorted(scene_dir().glob(SCENE_SETS[which]))
