"""What the user entered in the viewer, kept so that nothing is lost: stylus points
collected, planes added, contours drawn, registrations run.

The session folder is a complete case folder (docs/design.md §3: case.toml, preop/, intraop/,
truth/), so ``navapp register SESSION`` reproduces a registration from it, plus
``session.json`` holding what the case format has no place for (contours in image pixels,
which planes were added, free probe poses, the log of registrations). Every change is
written at once, atomically, the first one as a whole folder renamed into place; a browser
reload or a server restart restores it, and a folder found incomplete at start (a kill
during an earlier navapp's first save) is completed and said so. No viser here.
"""

import glob
import json
import os
import shutil
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..anatomy.caseio import SUPPORTS_FILE, write_csv, write_preop, write_settings, write_truth
from ..anatomy.model import VESSELS
from ..errors import InputError
from ..features import NAMES, SOURCED, STYLUS
from ..mechanics.supports import Supports, case_supports
from ..outputs import replace_folder, replaced
from ..registration.prior import declared_pose
from ..simulation.scenedata import SceneData, acquire_free_plane, scene_key
from ..simulation.ultrasound import PlaneData
from .actions import FILE as ACTIONS_FILE
from .contours import Contour, Origin, OriginKind, contour_points
from .palette import DRAWABLE
from .state import PoseFrame, RunEntry, StatedPose, StatedSupports

SESSION_VERSION = 1
LIVE_FEATURES = STYLUS + SOURCED  # a live point's: the tracked stylus's, or a source's (``app.live``)


@dataclass
class Session:
    folder: Path
    key: str  # the scene it belongs to
    stylus_count: int = 0  # how many points of the stylus sweep have been digitised
    planes_added: list = field(default_factory=list)  # plane indices whose (auto) segmentation is data
    contours: list = field(default_factory=list)  # [Contour] drawn by hand
    free_planes: list = field(default_factory=list)  # [{"index": i, "pose": 4×4 list}]
    log: list[RunEntry] = field(default_factory=list)  # one row per registration run
    result: dict | None = None  # the registered model on show (RegisteredState.to_json), restored on restart
    # [[x, y, z, feature]] digitised with a tracked stylus, or received from a source (``features.SOURCED``)
    live_points: list = field(default_factory=list)
    live_planes: list = field(default_factory=list)  # [{"index", "pose", "png"}] frozen tracked frames
    # [[x, y, z, feature]] data points the user removed (a stylus or segmentation point the fit
    # left far off); a drawn contour's point is removed as its vertex instead
    excluded: list = field(default_factory=list)
    written: bool = False  # the folder holds the whole case (after the first save, or when opened)
    note: str | None = None  # one line on what opening the folder found and did, for the user
    # what the surgeon stated of the pose of the data (Registration panel); None: the case's own declaration
    pose: StatedPose | None = None
    # where the surgeon stated the organ is held (Registration panel); None: the case's own declaration
    supports: StatedSupports | None = None

    # ------------------------------------------------------------ data
    def data(self, sd: SceneData, planes: dict, surface_only=False) -> dict:
        """Registration data {feature: (N, 3) mm}: digitised stylus points, then (unless
        ``surface_only``) every added plane's segmentation and every drawn contour, less the
        points the user removed. ``planes``: plane index → PlaneData (presets and free planes)."""
        return self.data_with_origins(sd, planes, surface_only)[0]

    def data_with_origins(self, sd: SceneData, planes: dict, surface_only=False,
                          left_out: list | None = None) -> tuple[dict, dict]:
        """``data`` and, per feature, each point's ``contours.Origin`` (same order).
        ``left_out``: appended the drawn vertices left out (``contours.StrayVertex``)."""
        parts: dict[str, list] = {}
        whence: dict[str, list] = {}
        gone = {(str(f), *np.round([x, y, z], 6)) for x, y, z, f in self.excluded}

        def add(name, pts, origins):
            pts = np.asarray(pts, float).reshape(-1, 3)
            keep = [i for i, p in enumerate(pts) if not gone or (name, *np.round(p, 6)) not in gone]
            if keep:
                parts.setdefault(name, []).append(pts[keep])
                whence.setdefault(name, []).extend(origins[i] for i in keep)

        n = min(self.stylus_count, len(sd.stylus_path))
        for name in STYLUS:
            pts = sd.stylus_path[:n][sd.stylus_labels[:n] == name]
            add(name, pts, [Origin(OriginKind.STYLUS)] * len(pts))
        for name, pts in sd.sourced.items():  # a source's points are data as soon as it sees them
            add(name, pts, [Origin(OriginKind.SOURCE)] * len(pts))
        for x, y, z, name in self.live_points:
            add(name, [x, y, z], [Origin(OriginKind.LIVE)])
        if not surface_only:
            for i in self.planes_added:
                for name, pts in planes[i].features.items():
                    add(name, pts, [Origin(OriginKind.PLANE, plane=i)] * len(pts))
            for c in self.contours:
                origins: dict = {}
                for name, pts in contour_points(sd.probe, planes[c.plane].probe_to_tracker, c, origins,
                                                left_out).items():
                    add(name, pts, origins[name])
        return {k: np.vstack(v) for k, v in parts.items()}, whence

    def stated_pose(self, sd: SceneData) -> StatedPose:
        """The pose of the data as stated in the viewer, else as the case declares it."""
        return self.pose if self.pose is not None else StatedPose.of_case(declared_pose(sd.case.settings))

    def stated_supports(self, sd: SceneData) -> StatedSupports:
        """Where the organ is held as stated in the viewer, else as the case declares it."""
        return self.supports if self.supports is not None else _case_supports(sd)

    # ------------------------------------------------------------ persistence
    def to_json(self) -> dict:
        return {"version": SESSION_VERSION, "scene_key": self.key, "stylus_count": self.stylus_count,
                "planes_added": self.planes_added, "contours": [c.to_json() for c in self.contours],
                "free_planes": self.free_planes, "log": [e.to_json() for e in self.log], "result": self.result,
                "live_points": self.live_points, "live_planes": self.live_planes, "excluded": self.excluded,
                "pose": None if self.pose is None else self.pose.to_json(),
                "supports": None if self.supports is None else self.supports.to_json()}

    def save(self, sd: SceneData, planes: dict):
        """Write session.json and the case folder's intraop/. The first save writes the whole
        case into a folder beside this one and renames it into place, so that a session folder
        is never half a case (a kill during it leaves the temporary folder, which the next
        start removes); later ones write file by file, each atomically, session.json last."""
        if self.written:
            _write_data(self, self.folder, sd, planes)
            return
        tmp = _sibling(self.folder, "new")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        try:
            _write_case(tmp, sd)
            _write_data(self, tmp, sd, planes)
            # files the session refers to that were written into the folder before its first save
            # (a frozen tracked frame's PNG): the renamed-in folder replaces that one whole, and the
            # first frame frozen in a fresh session was lost with it (a restart then refused the session)
            if (self.folder / ACTIONS_FILE).is_file():  # the action log (``actions``), fsync'd as it is there
                shutil.copy2(self.folder / ACTIONS_FILE, tmp / ACTIONS_FILE)
                with open(tmp / ACTIONS_FILE, "rb+") as f:
                    os.fsync(f.fileno())
            for lp in self.live_planes:
                src = self.folder / lp["png"]
                if src.is_file():
                    (tmp / lp["png"]).parent.mkdir(parents=True, exist_ok=True)
                    shutil.copy2(src, tmp / lp["png"])
            _into_place(tmp, self.folder)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        self.written = True


def _write_case(folder: Path, sd: SceneData):
    """The case part of a session folder, all from the scene: case.toml, preop/, truth/."""
    write_settings(folder, _settings(sd, None))
    write_preop(sd.case.preop, folder)
    if sd.case.truth is not None:
        write_truth(sd.case.truth, folder)


def _case_supports(sd: SceneData) -> StatedSupports:
    """Where the case declares its organ held (case.toml and preop/supports.csv)."""
    return StatedSupports.of_case(case_supports(sd.case.settings, points=sd.case.preop.support_points))


def _settings(sd: SceneData, stated: StatedPose | None, supports: StatedSupports | None = None) -> dict:
    """case.toml: the name, the units, the pose of the data and where the organ is held, as
    stated (the case's own declarations until the viewer states them), so that ``navapp register
    SESSION`` starts from what the viewer knew. A pose known from the previous registration has no
    place there (the command has no previous registration): it is written unknown."""
    stated = stated or StatedPose.of_case(declared_pose(sd.case.settings))
    held = (supports or _case_supports(sd)).held
    settings: dict = {"name": _case_name(sd), "units": "mm"}
    intraop: dict = {}
    if stated.frame is PoseFrame.GIVEN:
        intraop["pose"] = {"known": True, "sd_mm": float(stated.sd_mm), "sd_deg": float(stated.sd_deg)}
    if held is not None:
        # the points stay in preop/supports.csv (written with the preoperative model)
        intraop["supports"] = {k: v for k, v in held.as_dict().items() if k != "points"}
    if intraop:
        settings["intraop"] = intraop
    return settings


def _write_data(s: Session, folder: Path, sd: SceneData, planes: dict):
    """intraop/ (the registration data the session holds), case.toml and session.json, each
    file atomically."""
    # the temporary files' names are fixed: a kill leaves them where ``_complete`` looks for them
    with replaced(folder / "case.toml", "case.toml.tmp") as tmp:
        write_settings(tmp.parent, _settings(sd, s.pose, s.supports), name=tmp.name)
    _write_support_points(folder, (s.supports or _case_supports(sd)).held)
    idir = folder / "intraop"
    idir.mkdir(exist_ok=True)
    data = s.data(sd, planes)
    for name in NAMES:
        path = idir / f"{name}.csv"
        if name in data:
            with replaced(path, f"{name}.csv.tmp") as tmp:
                write_csv(tmp, data[name], ("x", "y", "z"))
        elif path.exists():
            path.unlink()
    with replaced(folder / "session.json", "session.json.tmp") as tmp:
        tmp.write_text(json.dumps(s.to_json(), indent=1))


def _write_support_points(folder: Path, held):
    """preop/supports.csv as the stated supports read it: their points where they are held at
    points, else no such file (``navapp register SESSION`` refuses a case whose points file its
    declaration does not read)."""
    path = folder / "preop" / SUPPORTS_FILE
    if held is not None and held.held is Supports.POINTS:
        path.parent.mkdir(exist_ok=True)
        with replaced(path, f"{SUPPORTS_FILE}.tmp") as tmp:
            write_csv(tmp, np.asarray(held.points, float), ("x", "y", "z"))
    elif path.exists():
        path.unlink()


def _case_name(sd: SceneData) -> str:
    return f"session-{sd.scene.name}"


def _sibling(folder: Path, what: str) -> Path:
    """A temporary folder beside ``folder`` (same file system: renames are atomic), named by
    this process so that the next start can tell a dead one's."""
    return folder.parent / f".{folder.name}.{what}-{os.getpid()}"


def _into_place(tmp: Path, folder: Path):
    # a non-empty folder here is an interrupted first save found at start (open_session): it
    # held nothing session.json recorded, so the new folder replaces it whole
    old = _sibling(folder, "old")
    shutil.rmtree(old, ignore_errors=True)
    replace_folder(tmp, folder, old)


def _remove_dead_siblings(folder: Path):
    """Temporary folders beside ``folder`` left by a process that died mid-save."""
    if not folder.parent.is_dir():
        return
    for p in folder.parent.glob(f".{glob.escape(folder.name)}.*-*"):
        what, _, pid = p.name[len(folder.name) + 2:].rpartition("-")
        if what in ("new", "old") and pid.isdigit() and not _alive(int(pid)):
            shutil.rmtree(p, ignore_errors=True)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _complete(s: Session, sd: SceneData, planes: dict) -> list[str]:
    """Make ``s.folder`` hold what its session.json says: the case from the scene and the
    intraop data from the session (a kill could leave preop/ half written by an earlier
    navapp, or intraop/ a save ahead of session.json). Returns the files that were missing
    or different, now replaced, each atomically; anything else in the folder is kept."""
    tmp = _sibling(s.folder, "new")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    fixed = []
    try:
        _write_case(tmp, sd)
        _write_data(s, tmp, sd, planes)
        (tmp / "session.json").unlink()  # the record itself was read: it is what the rest must match
        held = {p.name for p in (tmp / "intraop").iterdir()}
        for new in sorted(p for p in tmp.rglob("*") if p.is_file()):
            rel = new.relative_to(tmp)
            old = s.folder / rel
            if not old.is_file() or old.read_bytes() != new.read_bytes():
                fixed.append(str(rel))
                old.parent.mkdir(parents=True, exist_ok=True)
                os.replace(new, old)
        idir = s.folder / "intraop"
        for stale in sorted(idir.iterdir()) if idir.is_dir() else []:  # data the session no longer holds
            if stale.suffix == ".tmp" or (stale.suffix == ".csv" and stale.name not in held):
                stale.unlink()
                if stale.suffix == ".csv":
                    fixed.append(f"intraop/{stale.name} (not in session.json)")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return fixed


def default_folder(sd: SceneData) -> Path:
    """``$NAVAPP_SESSIONS`` or ``~/navapp-sessions``, one sub-folder per scene."""
    root = Path(os.environ.get("NAVAPP_SESSIONS", Path.home() / "navapp-sessions"))
    return root / f"{sd.scene.name}-{scene_key(sd.scene, sd.edge)}"


def open_session(folder: Path, sd: SceneData) -> tuple[Session, dict]:
    """The session stored in ``folder`` (a new one if there is none) and the planes it
    uses (presets + its free planes re-simulated from their stored poses).

    Raises InputError when the folder holds a session of another scene, or a damaged one."""
    folder = Path(folder)
    key = scene_key(sd.scene, sd.edge)
    planes = {p.index: p for p in sd.planes}
    _remove_dead_siblings(folder)
    path = folder / "session.json"
    if not path.exists():
        s = Session(folder, key)
        if folder.is_dir() and any(folder.iterdir()):
            if not _cut_short(folder, sd):
                raise InputError("this folder holds files but no session.json, so it is not a navapp session: "
                                 "pass a new or empty folder with --session", folder)
            s.save(sd, planes)
            s.note = (f"{folder}: its first save had been cut short (no session.json, so nothing entered was "
                      f"recorded in it): written again as a new session")
        return s, planes
    try:
        d = json.loads(path.read_text())
        if not isinstance(d, dict):
            raise ValueError(f"a JSON {type(d).__name__} where a session's record (an object) belongs")
        if d.get("scene_key") != key:
            raise InputError("this session folder belongs to another scene (pass a different --session)", folder)
        s = Session(folder, key, _count(d["stylus_count"], "stylus_count"),
                    [_count(i, "planes_added") for i in _list(d["planes_added"], "planes_added")],
                    [_contour(c, sd.probe) for c in _list(d["contours"], "contours")],
                    [_plane(f, "free_planes") for f in _list(d["free_planes"], "free_planes")],
                    [RunEntry.from_json(e) for e in _list(d["log"], "log")],
                    _record(d.get("result")),
                    [_point(p, "live_points", LIVE_FEATURES) for p in _list(d.get("live_points", []), "live_points")],
                    [_plane(f, "live_planes", png=True) for f in _list(d.get("live_planes", []), "live_planes")],
                    [_point(p, "excluded", NAMES) for p in _list(d.get("excluded", []), "excluded")],
                    pose=None if d.get("pose") is None else StatedPose.from_json(d["pose"]),
                    supports=None if d.get("supports") is None else StatedSupports.from_json(d["supports"]))
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise InputError(f"damaged session.json ({exc.__class__.__name__}: {exc}); move it away to start afresh",
                         path) from None
    for fp in s.free_planes:
        planes[fp["index"]] = acquire_free_plane(sd, fp["index"], np.array(fp["pose"]))
    for lp in s.live_planes:
        from skimage.io import imread

        png = folder / lp["png"]
        if not png.is_file():
            raise InputError(f"session.json refers to a frozen frame {lp['png']} that is missing", path)
        try:
            image = imread(png)
        except Exception as exc:  # imageio/PIL raise many types for a file that is not an image
            raise InputError(f"the frozen frame {lp['png']} is not a readable image ({exc.__class__.__name__})",
                             path) from None
        if image.shape != (sd.probe.height_px, sd.probe.width_px):
            raise InputError(f"the frozen frame {lp['png']} is {image.shape}, not the probe's "
                             f"{sd.probe.height_px} × {sd.probe.width_px} grey image", path)
        planes[lp["index"]] = PlaneData(lp["index"], "live", np.array(lp["pose"]), {}, image)
    bad = [i for i in s.planes_added if i not in planes] + [c.plane for c in s.contours if c.plane not in planes]
    if bad:
        raise InputError(f"session.json refers to planes {sorted(set(bad))} that this scene does not have", path)
    s.written = True
    fixed = _complete(s, sd, planes)
    if fixed:
        listed = ", ".join(fixed[:4]) + (f" and {len(fixed) - 4} more" if len(fixed) > 4 else "")
        s.note = (f"{folder}: the session folder was incomplete ({listed} missing or cut short): completed from "
                  f"the scene and session.json")
    return s, planes


# ---------------------------------------------------------------- session.json's values, checked
# (a hand-edited or damaged record was a traceback, or silently wrong data: a negative
# stylus_count took the sweep's points from its end)

def _list(v, what: str) -> list:
    if not isinstance(v, list):
        raise ValueError(f"{what} is a {type(v).__name__}, not a list")
    return v


def _count(v, what: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < 0:
        raise ValueError(f"{what}: {v!r} is not a whole number ≥ 0")
    return v


def _point(v, what: str, features) -> list:
    if not isinstance(v, list) or len(v) != 4 or v[3] not in features:
        raise ValueError(f"{what}: {v!r} is not [x, y, z, feature]")
    xyz = [float(a) for a in v[:3]]
    if not np.all(np.isfinite(xyz)):
        raise ValueError(f"{what}: {v!r} is not a finite point")
    return [*xyz, str(v[3])]


def _pose(v, what: str) -> list:
    a = np.asarray(v, float)
    if a.shape != (4, 4) or not np.all(np.isfinite(a)) or not np.allclose(a[3], [0, 0, 0, 1]) \
            or not np.allclose(a[:3, :3] @ a[:3, :3].T, np.eye(3), atol=1e-6):
        raise ValueError(f"{what}: a pose that is not a 4 × 4 rigid transform")
    return a.tolist()


def _plane(v, what: str, png: bool = False) -> dict:
    if not isinstance(v, dict):
        raise ValueError(f"{what}: {v!r} is not an object")
    out = {"index": _count(v["index"], f"{what} index"), "pose": _pose(v["pose"], what)}
    if png:
        if not isinstance(v["png"], str) or not v["png"]:
            raise ValueError(f"{what}: png {v['png']!r} is not a file name")
        out["png"] = v["png"]
    return out


def _contour(v, probe) -> Contour:
    if not isinstance(v, dict):
        raise ValueError(f"contours: {v!r} is not an object")
    c = Contour.from_json(v)
    _count(c.plane, "contour plane")
    if c.feature not in DRAWABLE.values() or not all(len(p) == 2 for p in c.vertices) \
            or not isinstance(v["closed"], bool):
        raise ValueError(f"contours: {v!r} is not a drawn contour")
    # a vertex is a pixel of the image, as the 2D view accepts a click (``drawing``): one far
    # outside it would be rasterised into millions of points
    if not all(0 <= col < probe.width_px and 0 <= row < probe.height_px for col, row in c.vertices):
        raise ValueError(f"contours: a vertex of {v!r} lies outside the {probe.width_px} × {probe.height_px} image")
    return c


def _record(v) -> dict | None:
    if v is not None and not isinstance(v, dict):
        raise ValueError(f"result is a {type(v).__name__}, not an object")
    return v


SESSION_ENTRIES = {"case.toml", "preop", "truth", "intraop", "session.json.tmp", ACTIONS_FILE}  # what a save writes


def _cut_short(folder: Path, sd: SceneData) -> bool:
    """Whether ``folder`` (no session.json) is this scene's session whose first save was cut
    short (an earlier navapp wrote the case in place): only what a save writes, and a
    case.toml, if readable, naming this scene's session. A case folder of the user's (navapp
    import) has another name, so it is refused, never overwritten."""
    if not {p.name for p in folder.iterdir()} <= SESSION_ENTRIES:
        return False
    try:
        name = tomllib.loads((folder / "case.toml").read_text()).get("name")
    except (OSError, ValueError):  # absent, or cut short itself
        return True
    return name == _case_name(sd)


def export(folder: Path, reg, sd: SceneData, data: dict) -> list[Path]:
    """Write the registered liver and vessels (PLY and legacy VTK, which 3D Slicer reads)
    and the registration data (CSV per feature) into ``folder``, which appears whole or not
    at all (``outputs.staged``: an export cut short left half its files beside the last
    one's); returns the files."""
    from ..outputs import folder_lock, staged, write_registered

    folder = Path(folder)
    preop = sd.case.preop
    with folder_lock(folder), staged(folder) as tmp:
        written = write_registered(tmp, reg.transform, {n: getattr(preop, n) for n in ("liver", *VESSELS)},
                                   prefix="registered_", vtk=True)
        for name, pts in data.items():
            write_csv(tmp / f"data_{name}.csv", pts, ("x", "y", "z"))
            written.append(tmp / f"data_{name}.csv")
        (tmp / "exported.json").write_text(json.dumps({"time": time.strftime("%Y-%m-%d %H:%M:%S"),
                                                       "files": [p.name for p in written]}, indent=1))
    return [folder / p.name for p in written]


TABS_FILE = "tabs.json"  # each tab's own work (``write_tabs``): its plane, contour in progress, undo


def write_tabs(folder: Path, tabs: dict) -> None:
    """Write ``tabs`` (token → a tab's JSON, ``tabs.Tab``) into the session folder atomically:
    a server killed mid-contour gives the tab its plane, its unfinished contour and its undo
    history back when it reconnects (they were in memory only, and the tab fell back to plane 1)."""
    if not folder.is_dir():
        return
    with replaced(folder / TABS_FILE, f".{TABS_FILE}.{os.getpid()}.tmp") as tmp:
        tmp.write_text(json.dumps(tabs))


def read_tabs(folder: Path) -> dict:
    """``write_tabs``' dict, or {} (none written, or unreadable: the tabs start afresh)."""
    try:
        d = json.loads((folder / TABS_FILE).read_text())
    except (OSError, ValueError):
        return {}
    return d if isinstance(d, dict) else {}
