"""Reading a triangle surface from any format navapp accepts (PLY, STL, OBJ, VTK, VTP), for
the importer and the tumour targets alike. Bad files raise ``InputError`` in one line."""

from pathlib import Path

import numpy as np
import trimesh

from ..errors import InputError, short_error

SURFACE_SUFFIXES = (".ply", ".stl", ".obj", ".vtk", ".vtp")


def suffix_of(path: Path) -> str:
    """The format suffix, two-part ones (.seg.nrrd, .nii.gz) whole, lower case."""
    name = path.name.lower()
    for s in (".seg.nrrd", ".nii.gz"):
        if name.endswith(s):
            return s
    return path.suffix.lower()


def read_any_surface(path) -> trimesh.Trimesh:
    """A triangle surface from PLY, STL (binary or ASCII), OBJ, or VTK/VTP, unprocessed
    (vertices exactly as stored; ``cleanup.clean_surface`` merges them).

    Returns a ``trimesh.Trimesh`` with (V, 3) float vertices and (F, 3) int faces.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("no such file", path)
    suffix = suffix_of(path)
    if suffix not in SURFACE_SUFFIXES:
        raise InputError(f"not a surface format navapp reads ({', '.join(SURFACE_SUFFIXES)})", path)
    if suffix == ".vtk":
        return _read_vtk(path)
    if suffix == ".vtp":
        return _read_vtp(path)
    try:
        mesh = trimesh.load(path, file_type=suffix[1:], process=False, force="mesh")
    except Exception as exc:  # trimesh raises many types for a bad file
        raise InputError(f"not a readable {suffix[1:].upper()} triangle mesh ({short_error(exc)})", path) from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError("holds no triangles", path)
    return mesh


def _read_vtk(path: Path) -> trimesh.Trimesh:
    from meshio import vtk

    try:
        # the format's reader itself: meshio.read prints the reader's error and calls
        # sys.exit(1) when the only format it tried fails (an empty .vtk ended the command)
        m = vtk.read(str(path))
    except Exception as exc:  # meshio raises many types for a bad file
        raise InputError(f"not a readable VTK file ({short_error(exc)})", path) from None
    tris = [c.data for c in m.cells if c.type == "triangle"]
    if not tris:
        kinds = sorted({c.type for c in m.cells})
        raise InputError(f"holds no triangles (cells: {', '.join(kinds) or 'none'})", path)
    return trimesh.Trimesh(np.asarray(m.points, float)[:, :3], np.concatenate(tris), process=False)


def _read_vtp(path: Path) -> trimesh.Trimesh:
    """VTK XML PolyData: meshio has no reader for it, VTK has (through pyvista, optional:
    VTK is 0.6 GB, too much to require for one file format)."""
    try:
        import pyvista
    except ImportError:
        raise InputError("reading VTP needs pyvista (pip install pyvista); or export the model as VTK, STL or "
                         "OBJ", path) from None
    try:
        poly = pyvista.read(path).triangulate()
    except Exception as exc:  # VTK raises many types for a bad file
        raise InputError(f"not a readable VTP file ({short_error(exc)})", path) from None
    faces = np.asarray(poly.faces).reshape(-1, 4)[:, 1:]
    return trimesh.Trimesh(np.asarray(poly.points, float), faces, process=False)
