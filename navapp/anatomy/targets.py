"""Preoperative tumour targets: what the surgeon is aiming for.

A case folder holds them under ``preop/targets/``: one closed surface per file (any
surface format the importer reads: PLY, STL, OBJ, VTK, VTP; the target is named by the
file's stem), and/or CSV files of point targets, one per row, ``name,x,y,z`` with an
optional ``radius_mm`` column (a row with a radius is a sphere of that radius, without
one a bare point). Units mm, the case's (preoperative) frame.

Surfaces go through the importer's reader and ``cleanup.clean_surface`` like a liver
(closed, manifold, outward, not self-intersecting); a target whose centre lies outside
the liver is refused. Every problem is one ``InputError`` line naming the file.

Targets are carried through a registration as points (``target_points`` /
``with_points`` / ``map_targets``): the caller supplies the map, e.g.
``Registration.transform`` — the one implementation of the paper's eq. 8.
"""

import warnings
from pathlib import Path

import numpy as np
import trimesh

from ..errors import InputError
from .model import Target
from .surface_io import SURFACE_SUFFIXES, read_any_surface, suffix_of

TARGETS_DIR = "targets"  # under preop/
POINTS_FILE = "points.csv"  # what ``write_targets`` names the point targets' file
CSV_COLUMNS = ("name", "x", "y", "z")
SPHERE_SUBDIVISIONS = 3  # a CSV sphere becomes an icosphere of 642 vertices, 1,280 triangles
OUTSIDE_WARN_FRACTION = 0.05  # warn when more of a target's surface than this lies outside the liver
TARGET_SURFACE_TOLERANCE_MM = 1.0
"""A target vertex within this of the liver's surface is not outside it: surfaces made from
masks of one scan (a tumour at the border and the organ around it) differ by a fraction of
a voxel where they share a face."""


def from_surface(name: str, mesh: trimesh.Trimesh, source=None) -> Target:
    """A target from a closed, outward surface (its centre is the volume centroid)."""
    return Target(name, np.asarray(mesh.center_mass, float), mesh, None if source is None else str(source))


def sphere(name: str, centre, radius_mm: float, source=None) -> Target:
    """A spherical target: an icosphere of ``radius_mm`` about ``centre``."""
    m = trimesh.creation.icosphere(SPHERE_SUBDIVISIONS, radius=float(radius_mm))
    m = trimesh.Trimesh(m.vertices + np.asarray(centre, float), m.faces, process=False)
    return Target(name, np.asarray(centre, float).copy(), m, None if source is None else str(source))


# ---------------------------------------------------------------- reading

def read_points_csv(path, to_case=None) -> list[Target]:
    """Point targets from ``name,x,y,z[,radius_mm]`` (header required); ``to_case``
    (4, 4) an optional rigid transform of the points into the case frame."""
    from ..geometry.transforms import apply

    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read ({getattr(exc, 'strerror', None) or exc})", path) from None
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise InputError("file is empty", path)
    header = tuple(c.strip().lower() for c in lines[0].split(","))
    if header not in (CSV_COLUMNS, CSV_COLUMNS + ("radius_mm",)):
        raise InputError(f"header is {','.join(header)[:60]!r}, expected 'name,x,y,z' or 'name,x,y,z,radius_mm'",
                         path)
    if len(lines) == 1:
        raise InputError("file has a header but no rows", path)
    out = []
    for lineno, ln in enumerate(lines[1:], start=1):
        cells = [c.strip() for c in ln.split(",")]
        if len(cells) != len(header):
            raise InputError(f"row {lineno} has {len(cells)} columns, expected {len(header)} ({','.join(header)})",
                             path)
        name = cells[0]
        if not name:
            raise InputError(f"row {lineno} has no name", path)
        try:
            xyz = np.array([float(c) for c in cells[1:4]])
            radius = float(cells[4]) if len(cells) == 5 and cells[4] else None
        except ValueError:
            raise InputError(f"row {lineno} is not numeric: {ln.strip()[:60]!r}", path) from None
        if not np.all(np.isfinite(xyz)) or (radius is not None and not np.isfinite(radius)):
            raise InputError(f"row {lineno} has a NaN or infinite value", path)
        if radius is not None and radius <= 0:
            raise InputError(f"row {lineno}: radius_mm must be positive (leave it empty for a point target)", path)
        if to_case is not None:
            xyz = apply(to_case, xyz[None])[0]
        out.append(sphere(name, xyz, radius, path) if radius is not None else Target(name, xyz, None, str(path)))
    return out


def read_target_file(path, to_case=None) -> list[Target]:
    """The targets of one file: a CSV of points, or one closed surface named by the stem.

    ``to_case`` (4, 4): a transform into the case frame applied first (the importer's
    source frame → navapp's); a mirroring transform reverses the winding.
    """
    from ..geometry.transforms import apply
    from . import frames
    from .cleanup import clean_surface

    path = Path(path)
    if suffix_of(path) == ".csv":
        return read_points_csv(path, to_case)
    if suffix_of(path) not in SURFACE_SUFFIXES:
        raise InputError(f"not a target file navapp reads (a surface: {', '.join(SURFACE_SUFFIXES)}; "
                         "or points: .csv)", path)
    mesh = read_any_surface(path)
    if to_case is not None:
        faces = np.asarray(mesh.faces)[:, ::-1] if frames.mirrors(to_case) else mesh.faces
        mesh = trimesh.Trimesh(apply(to_case, mesh.vertices), faces, process=False)
    clean, rep = clean_surface(mesh, path, closed=True, what="target surface")
    for line in rep.warnings:
        warnings.warn(f"{path}: {line}", stacklevel=3)
    name = path.name[: -len(suffix_of(path))]
    return [from_surface(name, clean, path)]


def check_targets(targets: list[Target], liver: trimesh.Trimesh):
    """Refuse a target whose centre lies outside the liver, and two targets with one name;
    warn when a surface reaches more than ``OUTSIDE_WARN_FRACTION`` outside the liver."""
    from ..geometry.targets_distance import winding_numbers
    from .cleanup import vessels_outside

    seen: dict[str, str | None] = {}  # name → the file that defined it
    for t in targets:
        if t.name in seen:
            raise InputError(f"target {t.name!r} is also defined in {seen[t.name]}: target names must differ",
                             t.source)
        seen[t.name] = t.source
    if not targets:
        return
    inside = winding_numbers(np.array([t.centre for t in targets]), liver.vertices, liver.faces) > 0.5
    for t, ok in zip(targets, inside, strict=True):
        if not ok:
            what = "point" if t.surface is None else "centre"
            c = ", ".join(f"{x:.1f}" for x in t.centre)
            raise InputError(f"target {t.name!r}: its {what} ({c}) mm lies outside the liver "
                             "(check the file's frame and units)", t.source)
        if t.surface is not None:
            # within a voxel of the surface either way (a tumour at the border shares the organ's surface)
            fraction, far = vessels_outside(liver, t.surface, beyond_mm=TARGET_SURFACE_TOLERANCE_MM)
            if fraction > OUTSIDE_WARN_FRACTION:
                warnings.warn(f"{t.source}: {100 * fraction:.0f} % of target {t.name!r} lies outside the liver "
                              f"(up to {far:.0f} mm)", stacklevel=3)


def read_targets(folder, liver: trimesh.Trimesh | None = None) -> list[Target]:
    """Every target under ``folder`` (a case's ``preop/targets/``), in file-name order;
    with ``liver``, checked against it (``check_targets``). Files of other kinds are
    warned about and skipped."""

    folder = Path(folder)
    targets = []
    for p in sorted(folder.iterdir()):
        if p.is_dir() or p.name.startswith("."):
            continue
        if suffix_of(p) not in SURFACE_SUFFIXES + (".csv",):
            warnings.warn(f"{p}: not a target file (surfaces: {', '.join(SURFACE_SUFFIXES)}; points: .csv): ignored",
                          stacklevel=2)
            continue
        targets += read_target_file(p)
    if liver is not None:
        check_targets(targets, liver)
    return targets


def write_targets(targets: list[Target], folder):
    """Write targets into ``folder`` (``preop/targets/``): a surface as ``<name>.ply``,
    point targets together in ``points.csv``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    points = [t for t in targets if t.surface is None]
    for t in targets:
        if t.surface is not None:
            if "/" in t.name or "\\" in t.name or t.name.startswith("."):
                raise InputError(f"target name {t.name!r} cannot be a file name")
            t.surface.export(folder / f"{t.name}.ply", encoding="binary")
    if points:
        rows = ["name,x,y,z"] + [",".join([t.name] + [repr(float(x)) for x in t.centre]) for t in points]
        (folder / POINTS_FILE).write_text("\n".join(rows) + "\n")


# ---------------------------------------------------------------- carrying targets through a map

def target_points(targets: list[Target]) -> np.ndarray:
    """All points to map, stacked (P, 3): each surface's vertices, then every centre."""
    parts = [np.asarray(t.surface.vertices, float) for t in targets if t.surface is not None]
    parts.append(np.array([t.centre for t in targets], float).reshape(-1, 3))
    return np.vstack(parts)


def with_points(targets: list[Target], points) -> list[Target]:
    """The targets with their points replaced by ``points`` (the layout of
    ``target_points``): surfaces keep their triangles, centres are the mapped centres."""
    points = np.asarray(points, float)
    out, i = [], 0
    for t in targets:
        if t.surface is not None:
            n = len(t.surface.vertices)
            out.append(Target(t.name, np.empty(3), trimesh.Trimesh(points[i:i + n], t.surface.faces, process=False),
                              t.source))  # centre set below
            i += n
        else:
            out.append(Target(t.name, np.empty(3), None, t.source))
    for t in out:
        t.centre = points[i].copy()
        i += 1
    if i != len(points):
        raise ValueError(f"{len(points)} points given, the targets have {i}")
    return out


def map_targets(targets: list[Target], fn) -> list[Target]:
    """Targets carried through ``fn``: (P, 3) mm → (P, 3) mm, e.g. ``reg.transform`` (or
    ``lambda p: reg.transform(p, beta, B)`` with ``B`` the interpolation matrix of
    ``target_points(targets)``, built once, when the same targets are mapped often)."""
    if not targets:
        return []
    return with_points(targets, fn(target_points(targets)))
