"""Read and write case folders (docs/design.md §3). Units mm.

Every problem with the input raises ``InputError`` naming the file and the problem in one
line; nothing malformed is loaded silently.
"""

import io
import tomllib
import warnings
from dataclasses import dataclass, field
from numbers import Real
from pathlib import Path

import numpy as np
import tomli_w
import trimesh

from ..errors import InputError
from ..features import NAMES
from .model import REGION_NAMES, VESSELS, Centerline, PreopModel, polyline_tangents
from .targets import TARGETS_DIR, read_targets, write_targets
from .truth import FIELD_FILE, POINT_COLUMNS, POINTS_FILE, Truth, TruthField, TruthPoints, read_field

LIVER_SIZE_MM = (40.0, 400.0)  # plausible range of a liver's largest extent, for the units check
SUPPORTS_FILE = "supports.csv"  # preop/: points where the organ is held (x,y,z mm, preoperative frame)
SUPPORT_REACH_MM = 10.0  # a support point farther than this from the liver surface is refused


@dataclass
class Case:
    """One registration problem: the preoperative model, intraoperative point clouds
    (feature → (N, 3) mm, tracker space) and optionally the truth (``anatomy.truth``: a
    field known everywhere, or measured point pairs)."""

    preop: PreopModel
    intraop: dict = field(default_factory=dict)
    truth: Truth | None = None
    settings: dict = field(default_factory=dict)

    @property
    def name(self) -> str:
        return self.settings.get("name", self.preop.name)

    def need_truth(self) -> Truth:
        """The case's truth; raises InputError when it has none (``truth/field.npz`` or
        ``truth/targets.csv``)."""
        if self.truth is None:
            raise InputError(f"case {self.name!r} has no truth/{FIELD_FILE} or truth/{POINTS_FILE}: "
                             "this needs the true intraoperative positions")
        return self.truth


# ---------------------------------------------------------------- case.toml

CASE_SETTINGS: dict = {
    "name": str,  # the case's name (default: the folder's)
    "units": str,  # "mm", the only unit
    "scene": str,  # the scene a simulated case came from
    "frame": {"case": str, "source": str, "source_to_case": list, "files": dict, "file_frames": dict},  # navapp import
    # the intraoperative data's frame is registered to the preoperative one, to within these
    # standard deviations per axis (``registration.prior.PosePrior``); absent or known = false: unknown
    # where the organ is held (``mechanics.supports.HeldSupports``): the registration's basis vanishes there
    "intraop": {"pose": {"known": bool, "sd_mm": Real, "sd_deg": Real},
                "supports": {"held": str, "release": str, "stiffness_pa_per_mm": Real}},
}
"""Every key case.toml may hold, with its type; a table's keys are listed in a dict. Keys
navapp does not read are refused: a setting that is silently ignored looks honoured."""

COMMAND_OPTIONS = {"k": "--k", "edge": "--edge", "edge_mm": "--edge", "max_iterations": "--max-iterations"}


def check_settings(settings: dict, path, schema: dict | None = None, prefix: str = ""):
    """Refuse, in one line naming the key, a case.toml key not in ``CASE_SETTINGS``, a
    value of the wrong type, or a number out of the range of its name (``navapp.schema``)."""
    from ..schema import check

    schema = CASE_SETTINGS if schema is None else schema
    for key, value in settings.items():
        name = f"{prefix}{key}"
        if key not in schema:
            hint = ""
            leaf = key if not isinstance(value, dict) else next(iter(value), key)
            if key in COMMAND_OPTIONS or leaf in COMMAND_OPTIONS:
                option = COMMAND_OPTIONS.get(key) or COMMAND_OPTIONS[leaf]
                hint = f"; the registration's {key if key in COMMAND_OPTIONS else leaf} is the command's {option}"
            known = ", ".join(sorted(schema))
            raise InputError(f"unknown key {name!r} (known: {known}){hint}", path)
        kind = schema[key]
        if isinstance(kind, dict):
            if not isinstance(value, dict):
                raise InputError(f"{name} must be a table", path)
            check_settings(value, path, kind, f"{name}.")
            continue
        if not isinstance(value, kind):
            raise InputError(f"{name} must be a {kind.__name__}, got {value!r}", path)
        check(name, value, path)


# ---------------------------------------------------------------- CSV

def read_csv(path: Path, columns: tuple[str, ...], integer_last: bool = False, points: bool = False) -> np.ndarray:
    """Read a numeric CSV with exactly ``columns`` (an optional header naming them).

    Returns (N, len(columns)) floats. Raises InputError for an empty file, a wrong number of
    columns, a header that names other columns, non-numeric cells, NaN or infinity, and
    with ``integer_last`` (a branch id) for a last column that is not whole numbers. With
    ``points`` (data points to register), the row count is checked against the memory
    budget before the numbers are parsed. Memory: the result plus numpy's parse buffer
    (a 300 MB file of 10 million points takes about 0.3 GB, not the 3.5 GB of Python
    lists a row-by-row parse took).
    """
    path = Path(path)
    try:
        header_at, first, rows = _scan(path)
    except OSError as exc:
        raise InputError(f"cannot read ({exc.strerror})", path) from None
    if first is None:
        raise InputError("file is empty", path)
    cells = [c.strip().lower() for c in first.split(",")]
    skip = 0
    if not _is_number(cells[0]):
        if tuple(cells) != tuple(columns):
            raise InputError(f"header is {_clip(','.join(cells))!r}, expected {','.join(columns)!r}", path)
        skip, rows = header_at + 1, rows - 1
        if rows == 0:
            raise InputError("file has a header but no rows", path)
    if points:
        from ..budget import check_points

        check_points(rows, path)
    n = len(columns)
    try:
        out = np.loadtxt(path, delimiter=",", comments="#", skiprows=skip, ndmin=2, dtype=float, encoding="utf-8")
    except ValueError:
        _first_bad_row(path, columns, skip)  # raises, naming the row
        raise InputError("not a numeric CSV", path) from None
    if out.shape[1] != n:
        raise InputError(f"row 1 has {out.shape[1]} columns, expected {n} ({','.join(columns)})", path)
    bad = ~np.isfinite(out).all(axis=1)
    if bad.any():
        raise InputError(f"row {int(np.argmax(bad)) + 1} has a NaN or infinite value", path)
    if integer_last and not np.all(out[:, -1] == np.round(out[:, -1])):
        raise InputError(f"column {columns[-1]!r} must hold whole numbers", path)
    return out


def _data_lines(path: Path):
    """(physical line index, text) of each line that is not blank or a comment, streamed."""
    with open(path, encoding="utf-8", errors="replace") as f:
        for i, ln in enumerate(f):
            if ln.strip() and not ln.lstrip().startswith("#"):
                yield i, ln


def _scan(path: Path):
    """(line index of the first data line, its text, number of data lines), reading the
    file once in constant memory."""
    at, first, count = 0, None, 0
    for i, ln in _data_lines(path):
        if first is None:
            at, first = i, ln
        count += 1
    return at, first, count


def _first_bad_row(path: Path, columns: tuple[str, ...], skip: int):
    """Raise InputError naming the first row numpy could not parse (rows counted from 1
    after the header, blank and comment lines not counted)."""
    n = len(columns)
    lineno = 0
    for i, ln in _data_lines(path):
        if i < skip:
            continue
        lineno += 1
        cells = [c.strip() for c in ln.split(",")]
        if len(cells) != n:
            raise InputError(f"row {lineno} has {len(cells)} columns, expected {n} ({','.join(columns)})", path)
        if not all(_is_number(c) for c in cells):
            raise InputError(f"row {lineno} is not numeric: {_clip(ln.strip())!r}", path)


def _clip(text: str, n: int = 60) -> str:
    return text if len(text) <= n else text[: n - 1] + "…"


def _is_number(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def write_csv(path: Path, data: np.ndarray, columns: tuple[str, ...], integer_last=False):
    """Write with a header; floats with repr precision so that a read gives the same bits."""
    buf = io.StringIO()
    buf.write(",".join(columns) + "\n")
    for row in np.asarray(data):
        cells = [repr(float(x)) for x in row]
        if integer_last:
            cells[-1] = str(int(row[-1]))
        buf.write(",".join(cells) + "\n")
    Path(path).write_text(buf.getvalue())


# ---------------------------------------------------------------- meshes

def read_surface(path: Path, closed: bool, what: str = "surface"):
    """Read a PLY triangle surface and clean it (``cleanup.clean_surface``): duplicates
    merged, specks dropped, winding made outward; holes, non-manifold edges,
    self-intersections and several large pieces refused in one line. Returns
    (trimesh.Trimesh, CleanupReport); what the repairs changed is warned about, naming
    the file, so the mesher always gets exactly the surface that was checked."""
    from .cleanup import clean_surface

    path = Path(path)
    try:
        mesh = trimesh.load(path, file_type="ply", process=False, force="mesh")
    except Exception as exc:  # trimesh raises many types for a bad file
        raise InputError(f"not a readable PLY triangle mesh ({exc})", path) from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError("holds no triangles", path)
    from ..budget import check_triangles

    check_triangles(len(mesh.faces), path)  # before the clean-up, whose checks grow with the triangles
    clean, report = clean_surface(mesh, path, closed=closed, what=what)
    clean.metadata["file_path"] = str(path)  # named by the mesher's errors
    for line in report.warnings:
        warnings.warn(f"{path}: {line}", stacklevel=3)
    return clean, report


def check_liver_size(mesh: trimesh.Trimesh, path: Path):
    """Refuse a liver whose largest extent is not that of a liver in mm (units check)."""
    size = float(mesh.extents.max())
    lo, hi = LIVER_SIZE_MM
    if size < lo:
        hint = " (metres? case folders are in mm)" if size < 1.0 else ""
        raise InputError(f"largest extent is {size:.3g}, too small for a liver in mm{hint}", path)
    if size > hi:
        raise InputError(f"largest extent is {size:.3g}, too large for a liver in mm (micrometres?)", path)


# ---------------------------------------------------------------- case folders

def read_case(folder) -> Case:
    """Read a case folder (docs/design.md §3).

    Parameters
    ----------
    folder : str or Path
        holds ``preop/liver.ply`` (required) and optionally ``case.toml``, the vessels
        (``preop/{portal,hepatic}.ply`` and ``_centerline.csv``), ``preop/fiducials.csv``,
        ``preop/regions.csv``, ``preop/targets/``, ``preop/supports.csv`` (points on the
        surface where the organ is held), ``intraop/<feature>.csv`` (the names of
        ``navapp.features.NAMES``) and the truth: ``truth/field.npz`` (a simulated case)
        or ``truth/targets.csv`` (measured point pairs).

    Returns
    -------
    Case
        ``preop``: the model, mm, preoperative frame; ``intraop``: feature → (N, 3) points,
        mm, tracker space; ``truth``: ``read_truth``'s, or None.
        Missing optional files are simply absent from the result.

    Raises
    ------
    InputError
        naming the file and the problem in one line (units, non-finite values, a liver of
        the wrong size for millimetres, a surface that is not closed, …).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("no such case folder", folder)
    settings = {}
    toml = folder / "case.toml"
    if toml.exists():
        try:
            settings = tomllib.loads(toml.read_text())
        except tomllib.TOMLDecodeError as exc:
            raise InputError(f"invalid TOML ({exc})", toml) from None
        check_settings(settings, toml)
        pose = settings.get("intraop", {}).get("pose", {})
        if pose.get("known", False) and not all(isinstance(pose.get(k), Real) and pose[k] > 0
                                                for k in ("sd_mm", "sd_deg")):
            raise InputError("[intraop.pose] known = true needs sd_mm and sd_deg, both positive (the given pose's "
                             "standard deviations, mm and degrees)", toml)
        units = settings.get("units", "mm")
        if units != "mm":
            raise InputError(f"units = {units!r}; case folders are in millimetres (units = \"mm\")", toml)
    pre = folder / "preop"
    liver_path = pre / "liver.ply"
    if not liver_path.exists():
        raise InputError("missing: every case needs preop/liver.ply", liver_path)
    liver, cleaned = read_surface(liver_path, closed=True, what="liver surface")
    check_liver_size(liver, liver_path)
    model = PreopModel(liver=liver, name=settings.get("name", folder.name))
    for v in VESSELS:
        p = pre / f"{v}.ply"
        if p.exists():
            vessel, _ = read_surface(p, closed=False, what=f"{v} surface")
            setattr(model, v, vessel)
        p = pre / f"{v}_centerline.csv"
        if p.exists():
            data = read_csv(p, ("x", "y", "z", "branch"), integer_last=True)
            cl = Centerline(points=data[:, :3], branch=data[:, 3].astype(int))
            counts = np.unique(cl.branch, return_counts=True)[1]
            if (counts < 2).any():
                raise InputError("a branch has a single point: no tangent is defined", p)
            if (np.linalg.norm(polyline_tangents(cl.points, cl.branch), axis=1) == 0).any():
                raise InputError("consecutive duplicate points: no tangent is defined", p)
            setattr(model, f"{v}_centerline", cl)
    fp = pre / "fiducials.csv"
    if fp.exists():
        model.fiducials = read_csv(fp, ("x", "y", "z"))
    rp = pre / "regions.csv"
    if rp.exists():
        codes = read_regions(rp, cleaned.vertices_in)
        if cleaned.changed:
            # labels were written per vertex of the file as it was: carry them to the cleaned surface
            kept = cleaned.vertex_map >= 0
            moved = np.zeros(len(liver.vertices), int)
            moved[cleaned.vertex_map[kept]] = codes[kept]
            codes = moved
        model.regions = codes
    tdir = pre / TARGETS_DIR
    if tdir.is_dir():
        model.targets = read_targets(tdir, liver)
    sp_ = pre / SUPPORTS_FILE
    if sp_.exists():
        model.support_points = read_support_points(sp_, liver)
    intraop = {}
    idir = folder / "intraop"
    if idir.is_dir():
        for p in sorted(idir.iterdir()):
            if p.suffix != ".csv":
                continue
            if p.stem not in NAMES:  # the allowed ``intraop/<feature>.csv`` stems
                warnings.warn(f"{p}: unknown feature {p.stem!r} ignored (known: {', '.join(NAMES)})", stacklevel=2)
                continue
            intraop[p.stem] = read_csv(p, ("x", "y", "z"), points=True)
    return Case(preop=model, intraop=intraop, truth=read_truth(folder), settings=settings)


def read_support_points(path: Path, liver: trimesh.Trimesh) -> np.ndarray:
    """``preop/supports.csv``: (P, 3) mm, each within ``SUPPORT_REACH_MM`` of the liver surface
    (a point off it is refused in one line: it names no part of the surface)."""
    pts = read_csv(path, ("x", "y", "z"))
    _, dist, _ = trimesh.proximity.closest_point(liver, pts)
    far = np.flatnonzero(dist > SUPPORT_REACH_MM)
    if len(far):
        i = int(far[np.argmax(dist[far])])
        raise InputError(f"{len(far)} of {len(pts)} support points are not on the liver surface: row {i + 1} is "
                         f"{dist[i]:.1f} mm from it (at most {SUPPORT_REACH_MM:g} mm; preoperative frame, mm)", path)
    return pts


def read_truth(folder) -> Truth | None:
    """The truth of case folder ``folder``: ``truth/field.npz`` (the simulator's field)
    when present, else ``truth/targets.csv``'s measured pairs, else None. A folder holding
    both is read as the field: the csv beside it is an older simulator's sample of it."""
    tdir = Path(folder) / "truth"
    if (tdir / FIELD_FILE).exists():
        return read_field(tdir / FIELD_FILE)
    if (tdir / POINTS_FILE).exists():
        pairs = read_csv(tdir / POINTS_FILE, POINT_COLUMNS)
        return TruthPoints(pairs[:, :3], pairs[:, 3:])
    return None


def write_truth(truth: Truth, folder):
    """``truth/field.npz`` or ``truth/targets.csv`` in case folder ``folder``."""
    if isinstance(truth, TruthField):
        truth.write(folder)
        return
    (Path(folder) / "truth").mkdir(parents=True, exist_ok=True)
    write_csv(Path(folder) / "truth" / POINTS_FILE, np.column_stack([truth.x0, truth.x1]), POINT_COLUMNS)


def read_regions(path: Path, n_vertices: int) -> np.ndarray:
    """One label per liver.ply vertex (optional header ``label``) → (V,) codes."""
    lines = [ln.strip() for ln in Path(path).read_text().splitlines() if ln.strip()]
    if lines and lines[0].lower() == "label":
        lines = lines[1:]
    if not lines:
        raise InputError("file is empty", path)
    if len(lines) != n_vertices:
        raise InputError(f"has {len(lines)} labels but liver.ply has {n_vertices} vertices", path)
    lookup = {n: i for i, n in enumerate(REGION_NAMES)}
    unknown = sorted({ln for ln in lines if ln not in lookup})
    if unknown:
        raise InputError(f"unknown label(s) {', '.join(map(repr, unknown[:5]))}; "
                         f"known: {', '.join(REGION_NAMES)}", path)
    return np.array([lookup[ln] for ln in lines], int)


def write_preop(model: PreopModel, folder):
    """Write the ``preop/`` part of a case folder (and a minimal case.toml if absent)."""
    folder = Path(folder)
    pre = folder / "preop"
    pre.mkdir(parents=True, exist_ok=True)
    model.liver.export(pre / "liver.ply", encoding="binary")
    for v in VESSELS:
        mesh = model.vessel(v)
        if mesh is not None:
            mesh.export(pre / f"{v}.ply", encoding="binary")
        cl = model.centerline(v)
        if cl is not None:
            write_csv(pre / f"{v}_centerline.csv", np.column_stack([cl.points, cl.branch]), ("x", "y", "z", "branch"),
                      True)
    if model.fiducials is not None:
        write_csv(pre / "fiducials.csv", model.fiducials, ("x", "y", "z"))
    if model.regions is not None:
        (pre / "regions.csv").write_text("label\n" + "\n".join(REGION_NAMES[c] for c in model.regions) + "\n")
    if model.targets:
        write_targets(model.targets, pre / TARGETS_DIR)
    if model.support_points is not None:
        write_csv(pre / SUPPORTS_FILE, model.support_points, ("x", "y", "z"))
    if not (folder / "case.toml").exists():
        write_settings(folder, {"name": model.name, "units": "mm"})


def write_settings(folder, settings: dict, name: str = "case.toml"):
    Path(folder, name).write_text(tomli_w.dumps(settings))


def write_case(case: Case, folder):
    """Write a whole case folder: case.toml, preop/, intraop/, truth/."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rest = {k: v for k, v in case.settings.items() if k not in ("name", "units")}
    settings = {"name": case.name, "units": "mm", **rest}
    write_settings(folder, settings)
    write_preop(case.preop, folder)
    if case.intraop:
        idir = folder / "intraop"
        idir.mkdir(exist_ok=True)
        for name, pts in case.intraop.items():
            if name not in NAMES:
                raise InputError(f"unknown feature {name!r}")
            write_csv(idir / f"{name}.csv", pts, ("x", "y", "z"))
    if case.truth is not None:
        write_truth(case.truth, folder)
