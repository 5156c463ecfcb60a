"""What the user entered in the viewer, kept so that nothing is lost: stylus points
collected, planes added, contours drawn, registrations run.

The session folder is a complete case folder (docs/design.md §3: case.toml, preop/, intraop/,
truth/targets.csv), so ``navapp register SESSION`` reproduces a registration from it, plus
``session.json`` holding what the case format has no place for (contours in image pixels,
which planes were added, free probe poses, the log of registrations). Every change is
written at once, atomically; a browser reload or a server restart restores it. No viser here.
"""

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from ..anatomy.caseio import write_csv, write_preop, write_settings
from ..errors import InputError
from ..features import NAMES as FEATURE_NAMES
from ..features import STYLUS as STYLUS_FEATURES
from ..simulation.scenedata import SceneData, acquire_free_plane, scene_key
from ..simulation.ultrasound import PlaneData
from .contours import Contour, contour_points
from .state import RunEntry

SESSION_VERSION = 1


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
    live_points: list = field(default_factory=list)  # [[x, y, z, feature]] digitised with a tracked stylus
    live_planes: list = field(default_factory=list)  # [{"index", "pose", "png"}] frozen tracked frames

    # ------------------------------------------------------------ data
    def data(self, sd: SceneData, planes: dict, surface_only=False) -> dict:
        """Registration data {feature: (N, 3) mm}: digitised stylus points, then (unless
        ``surface_only``) every added plane's segmentation and every drawn contour.
        ``planes``: plane index → PlaneData (presets and free planes)."""
        parts: dict[str, list] = {}

        def add(name, pts):
            if len(pts):
                parts.setdefault(name, []).append(np.asarray(pts, float).reshape(-1, 3))

        n = min(self.stylus_count, len(sd.stylus_path))
        for name in STYLUS_FEATURES:
            add(name, sd.stylus_path[:n][sd.stylus_labels[:n] == name])
        for x, y, z, name in self.live_points:
            add(name, [x, y, z])
        if not surface_only:
            for i in self.planes_added:
                for name, pts in planes[i].features.items():
                    add(name, pts)
            for c in self.contours:
                for name, pts in contour_points(sd.probe, planes[c.plane].probe_to_tracker, c).items():
                    add(name, pts)
        return {k: np.vstack(v) for k, v in parts.items()}

    # ------------------------------------------------------------ persistence
    def to_json(self) -> dict:
        return {"version": SESSION_VERSION, "scene_key": self.key, "stylus_count": self.stylus_count,
                "planes_added": self.planes_added, "contours": [c.to_json() for c in self.contours],
                "free_planes": self.free_planes, "log": [e.to_json() for e in self.log], "result": self.result,
                "live_points": self.live_points, "live_planes": self.live_planes}

    def save(self, sd: SceneData, planes: dict):
        """Write session.json and the case folder's intraop/ (atomically, file by file)."""
        self.folder.mkdir(parents=True, exist_ok=True)
        if not (self.folder / "preop" / "liver.ply").exists():
            write_settings(self.folder, {"name": f"session-{sd.scene.name}", "units": "mm"})
            write_preop(sd.case.preop, self.folder)
            if sd.case.targets is not None:
                (self.folder / "truth").mkdir(exist_ok=True)
                write_csv(self.folder / "truth" / "targets.csv", sd.case.targets, ("x0", "y0", "z0", "x1", "y1", "z1"))
        idir = self.folder / "intraop"
        idir.mkdir(exist_ok=True)
        data = self.data(sd, planes)
        for name in FEATURE_NAMES:
            path = idir / f"{name}.csv"
            if name in data:
                tmp = path.with_suffix(".csv.tmp")
                write_csv(tmp, data[name], ("x", "y", "z"))
                os.replace(tmp, path)
            elif path.exists():
                path.unlink()
        tmp = self.folder / "session.json.tmp"
        tmp.write_text(json.dumps(self.to_json(), indent=1))
        os.replace(tmp, self.folder / "session.json")


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
    path = folder / "session.json"
    if not path.exists():
        return Session(folder, key), planes
    try:
        d = json.loads(path.read_text())
        if d.get("scene_key") != key:
            raise InputError("this session folder belongs to another scene (pass a different --session)", folder)
        s = Session(folder, key, int(d["stylus_count"]), [int(i) for i in d["planes_added"]],
                    [Contour.from_json(c) for c in d["contours"]], list(d["free_planes"]),
                    [RunEntry.from_json(e) for e in d["log"]],
                    d.get("result"),
                    [[float(a), float(b), float(c), str(f)] for a, b, c, f in d.get("live_points", [])],
                    list(d.get("live_planes", [])))
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(f"damaged session.json ({exc.__class__.__name__}: {exc}); move it away to start afresh",
                         path) from None
    for fp in s.free_planes:
        planes[fp["index"]] = acquire_free_plane(sd, fp["index"], np.array(fp["pose"]))
    for lp in s.live_planes:
        from skimage.io import imread

        png = folder / lp["png"]
        if not png.exists():
            raise InputError(f"session.json refers to a frozen frame {lp['png']} that is missing", path)
        planes[lp["index"]] = PlaneData(lp["index"], "live", np.array(lp["pose"]), {}, imread(png))
    bad = [i for i in s.planes_added if i not in planes] + [c.plane for c in s.contours if c.plane not in planes]
    if bad:
        raise InputError(f"session.json refers to planes {sorted(set(bad))} that this scene does not have", path)
    return s, planes


def export(folder: Path, reg, sd: SceneData, data: dict) -> list[Path]:
    """Write the registered liver and vessels (PLY and legacy VTK, which 3D Slicer reads)
    and the registration data (CSV per feature) into ``folder``; returns the files."""
    import meshio

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    preop = sd.case.preop
    for name, mesh in (("liver", preop.liver), ("portal", preop.portal), ("hepatic", preop.hepatic)):
        if mesh is None:
            continue
        v = reg.transform(mesh.vertices)
        out = trimesh.Trimesh(v, mesh.faces, process=False)
        out.export(folder / f"registered_{name}.ply", encoding="binary")
        meshio.write(folder / f"registered_{name}.vtk", meshio.Mesh(v, [("triangle", np.asarray(mesh.faces))]),
                     binary=False)
        written += [folder / f"registered_{name}.ply", folder / f"registered_{name}.vtk"]
    for name, pts in data.items():
        write_csv(folder / f"data_{name}.csv", pts, ("x", "y", "z"))
        written.append(folder / f"data_{name}.csv")
    (folder / "exported.json").write_text(json.dumps({"time": time.strftime("%Y-%m-%d %H:%M:%S"),
                                                      "files": [p.name for p in written]}, indent=1))
    return written
