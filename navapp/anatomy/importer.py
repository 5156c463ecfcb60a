"""Import a patient's anatomy from where surgical models come from: 3D Slicer's surface
exports (STL, OBJ, PLY, VTK/VTP) or a label map (NIfTI, NRRD, Slicer's ``.seg.nrrd``).

``import_case`` reads, converts to navapp's frame (``frames``), cleans (``cleanup``), adds
region labels and vessel centerlines where the user gave none (``autolabel``,
``skeleton``), and writes a case folder whose ``case.toml`` records the source frame and
the transform into navapp's. Every problem is one ``InputError`` line naming the file.
"""

import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from ..errors import InputError, NavappError
from . import frames
from .cleanup import clean_surface, vessels_outside
from .model import REGION_NAMES, VESSELS, PreopModel

SURFACE_SUFFIXES = (".ply", ".stl", ".obj", ".vtk", ".vtp")
LABELMAP_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".seg.nrrd", ".nhdr")
LIVER_SURFACE_EDGE_MM = 2.0  # a label map's liver is decimated to this edge (half the FE edge: Gmsh remeshes)
VESSEL_SURFACE_EDGE_MM = 1.0  # vessels keep their small branches
OUTSIDE_WARN_FRACTION = 0.01  # warn when more than 1 % of a vessel's vertices lie outside the liver


def _suffix(path: Path) -> str:
    name = path.name.lower()
    for s in (".seg.nrrd", ".nii.gz"):
        if name.endswith(s):
            return s
    return path.suffix.lower()


# ---------------------------------------------------------------- surfaces

def read_any_surface(path) -> trimesh.Trimesh:
    """A triangle surface from PLY, STL (binary or ASCII), OBJ, or VTK/VTP, unprocessed
    (vertices exactly as stored; ``cleanup.clean_surface`` merges them).

    Returns a ``trimesh.Trimesh`` with (V, 3) float vertices and (F, 3) int faces.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("no such file", path)
    suffix = _suffix(path)
    if suffix not in SURFACE_SUFFIXES:
        raise InputError(f"not a surface format navapp reads ({', '.join(SURFACE_SUFFIXES)})", path)
    if suffix == ".vtk":
        return _read_vtk(path)
    if suffix == ".vtp":
        return _read_vtp(path)
    try:
        mesh = trimesh.load(path, file_type=suffix[1:], process=False, force="mesh")
    except Exception as exc:  # trimesh raises many types for a bad file
        raise InputError(f"not a readable {suffix[1:].upper()} triangle mesh ({_short(exc)})", path) from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError("holds no triangles", path)
    return mesh


def _read_vtk(path: Path) -> trimesh.Trimesh:
    import meshio

    try:
        m = meshio.read(path)
    except Exception as exc:  # meshio raises many types for a bad file
        raise InputError(f"not a readable VTK file ({_short(exc)})", path) from None
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
        raise InputError(f"not a readable VTP file ({_short(exc)})", path) from None
    faces = np.asarray(poly.faces).reshape(-1, 4)[:, 1:]
    return trimesh.Trimesh(np.asarray(poly.points, float), faces, process=False)


def _short(exc: Exception) -> str:
    lines = str(exc).strip().splitlines()
    text = lines[0] if lines else type(exc).__name__
    return text if len(text) <= 80 else text[:79] + "…"


def slicer_frame(path) -> str | None:
    """The frame 3D Slicer wrote into a surface file's header ("LPS" or "RAS"), if any:
    Slicer names it in the STL solid name, an OBJ/PLY comment or the VTK header line."""
    try:
        with Path(path).open("rb") as fh:
            head = fh.read(512).decode("latin-1")
    except OSError:
        return None
    for frame in ("LPS", "RAS"):
        if f"SPACE={frame}" in head.upper():
            return frame
    return None


# ---------------------------------------------------------------- label maps

@dataclass
class LabelMap:
    """A label volume: ``labels`` (I, J, K) int, ``affine`` (4, 4) voxel index → mm in
    ``frame``, ``names`` label value → segment name (Slicer's segmentations carry them)."""

    labels: np.ndarray
    affine: np.ndarray
    frame: str
    names: dict = field(default_factory=dict)

    @property
    def spacing(self) -> np.ndarray:
        return np.linalg.norm(self.affine[:3, :3], axis=0)


def read_labelmap(path) -> LabelMap:
    """NIfTI (nibabel; its affine is RAS) or NRRD / ``.seg.nrrd`` (pynrrd; ``space``,
    ``space directions`` and ``space origin`` give the frame and the affine)."""
    path = Path(path)
    if not path.is_file():
        raise InputError("no such file", path)
    suffix = _suffix(path)
    if suffix in (".nii", ".nii.gz"):
        import nibabel

        try:
            img: Any = nibabel.load(str(path))  # a spatial image (dataobj, affine)
            data = np.asarray(img.dataobj)
        except Exception as exc:  # nibabel raises many types for a bad file
            raise InputError(f"not a readable NIfTI image ({_short(exc)})", path) from None
        if data.ndim != 3:
            raise InputError(f"is {data.ndim}-D; a label map is 3-D", path)
        return LabelMap(_integer_labels(data, path), np.asarray(img.affine, float), "RAS")
    if suffix in (".nrrd", ".seg.nrrd", ".nhdr"):
        return _read_nrrd(path)
    raise InputError(f"not a label-map format navapp reads ({', '.join(LABELMAP_SUFFIXES)})", path)


_NRRD_SPACES = {"left-posterior-superior": "LPS", "right-anterior-superior": "RAS", "LPS": "LPS", "RAS": "RAS",
                "left-anterior-superior": "LAS", "LAS": "LAS"}


def _read_nrrd(path: Path) -> LabelMap:
    import nrrd

    try:
        data, header = nrrd.read(str(path))
    except Exception as exc:  # pynrrd raises many types for a bad file
        raise InputError(f"not a readable NRRD file ({_short(exc)})", path) from None
    space = header.get("space")
    if space not in _NRRD_SPACES:
        raise InputError(f"NRRD space {space!r} is not one navapp knows (LPS or RAS)", path)
    directions = np.asarray(header.get("space directions"), dtype=object)
    rows = [np.asarray(r, float) for r in directions if r is not None and not _is_none(r)]
    if len(rows) != 3:
        raise InputError("NRRD has no 3-D 'space directions'", path)
    if data.ndim == 4:
        # Slicer's segmentation with overlapping segments: one layer per axis-0 entry
        layer_axis = next(i for i, r in enumerate(directions) if r is None or _is_none(r))
        data = np.moveaxis(data, layer_axis, 0)
    elif data.ndim != 3:
        raise InputError(f"NRRD is {data.ndim}-D; a label map is 3-D", path)
    affine = np.eye(4)
    affine[:3, :3] = np.column_stack(rows)
    affine[:3, 3] = np.asarray(header.get("space origin", np.zeros(3)), float)
    names: dict[Any, str] = {}
    i = 0
    while f"Segment{i}_Name" in header:
        layer = int(header.get(f"Segment{i}_Layer", 0))
        value = int(header.get(f"Segment{i}_LabelValue", i + 1))
        names[(layer, value) if data.ndim == 4 else value] = header[f"Segment{i}_Name"]
        i += 1
    if data.ndim == 4:
        # flatten layers into distinct label values so that each segment is one value
        flat = np.zeros(data.shape[1:], np.int32)
        renamed = {}
        for n, ((layer, value), name) in enumerate(sorted(names.items()), start=1):
            flat[np.asarray(data[layer]) == value] = n
            renamed[n] = name
        return LabelMap(flat, affine, _NRRD_SPACES[space], renamed)
    return LabelMap(_integer_labels(data, path), affine, _NRRD_SPACES[space], names)


def _is_none(row) -> bool:
    return isinstance(row, str) or bool(np.ndim(row) == 1 and np.all(np.isnan(np.asarray(row, float))))


def _integer_labels(data: np.ndarray, path) -> np.ndarray:
    data = np.asarray(data)
    if not np.issubdtype(data.dtype, np.integer):
        if not np.all(np.isfinite(data)) or not np.all(data == np.round(data)):
            raise InputError("holds non-integer values: a label map holds whole-number labels", path)
        data = data.astype(np.int32)
    return data


def label_surface(lm: LabelMap, value: int, edge: float, smooth_iterations: int = 10, path=None) -> trimesh.Trimesh:
    """The closed surface of ``lm.labels == value`` in ``lm.frame`` mm.

    Marching cubes at the voxel grid (in index space, then through the affine, so oblique
    and anisotropic volumes come out right), Taubin smoothing (λ/μ: it removes the voxel
    staircase without the shrinkage of plain Laplacian smoothing), then quadric decimation
    to triangles of about ``edge`` mm.
    """
    from skimage.measure import marching_cubes

    mask = lm.labels == value
    if not mask.any():
        known = ", ".join(str(int(x)) for x in np.unique(lm.labels) if x != 0)
        raise InputError(f"has no voxel with label {value} (labels present: {known or 'none'})", path)
    padded = np.pad(mask, 1).astype(np.float32)
    v, f, _, _ = marching_cubes(padded, 0.5)
    v = frames.apply(lm.affine, v - 1.0)
    if frames.mirrors(lm.affine):
        f = f[:, ::-1]
    mesh = trimesh.Trimesh(v, f[:, ::-1], process=True)  # skimage winds inward for "inside = high"
    if mesh.is_watertight and mesh.volume < 0:
        mesh.invert()
    trimesh.smoothing.filter_taubin(mesh, lamb=0.5, nu=0.53, iterations=smooth_iterations)
    target = int(mesh.area / (np.sqrt(3) / 4 * edge ** 2))
    if target < len(mesh.faces):
        mesh = mesh.simplify_quadric_decimation(face_count=max(target, 200))
    return mesh


# ---------------------------------------------------------------- the import

@dataclass
class ImportReport:
    """What ``import_case`` did: lines for the user, and the frame conversion."""

    frame: str
    to_case: np.ndarray  # (4, 4) source frame → navapp's (LAS)
    lines: list = field(default_factory=list)
    warnings: list = field(default_factory=list)


def import_case(out, liver=None, portal=None, hepatic=None, labelmap=None, labels=None, frame=None,
                falciform=None, regions=None, centerlines=None, name=None, overwrite=False, targets=None):
    """Write a case folder's ``preop/`` from a patient's files.

    Parameters
    ----------
    out : path-like
        The case folder to write.
    liver, portal, hepatic : path-like, optional
        Surfaces (PLY, STL, OBJ, VTK, VTP). ``liver`` is required unless ``labelmap`` is given.
    labelmap : path-like, optional
        A label map (NIfTI, NRRD, ``.seg.nrrd``); ``labels`` maps "liver", "portal",
        "hepatic" to label values (Slicer segment names are matched when not given).
    frame : {"LPS", "RAS", "LAS"}, optional
        The frame of the surfaces. Label maps carry their own. Without it, a 3D Slicer
        header comment is read; otherwise the import refuses to guess.
    falciform : (2, 3) array, optional
        Two landmark points (source frame, mm) on the falciform ligament's line.
    regions, centerlines : dict, optional
        Files the user has: ``regions`` a ``regions.csv`` path; ``centerlines`` vessel →
        ``<vessel>_centerline.csv`` path. They win over the automatic ones.
    name : str, optional
        The case name (default: the folder's name).
    targets : list of path-like, optional
        Tumour targets (``anatomy.targets``): closed surfaces (any format above; named by
        the file's stem) or CSVs of points ``name,x,y,z[,radius_mm]``, in the frame of the
        other files; written to ``preop/targets/``.

    Returns
    -------
    ImportReport
    """
    from . import caseio
    from .autolabel import auto_regions
    from .skeleton import vessel_centerline

    out = Path(out)
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise InputError("exists and is not empty (choose another --out, or --overwrite)", out)
    surfaces: dict[str, trimesh.Trimesh] = {}
    paths: dict[str, Path] = {}
    source_frame = None
    if labelmap is not None:
        lm = read_labelmap(labelmap)
        source_frame = lm.frame
        wanted = _label_values(lm, labels, labelmap)
        for organ, value in wanted.items():
            edge = LIVER_SURFACE_EDGE_MM if organ == "liver" else VESSEL_SURFACE_EDGE_MM
            surfaces[organ] = label_surface(lm, value, edge, path=labelmap)
            paths[organ] = Path(labelmap)
    for organ, p in (("liver", liver), ("portal", portal), ("hepatic", hepatic)):
        if p is None:
            continue
        p = Path(p)
        surfaces[organ] = read_any_surface(p)
        paths[organ] = p
        f = (frame or slicer_frame(p))
        if f is None:
            raise InputError("its frame is unknown: give --frame LPS (3D Slicer's default for STL/OBJ export) "
                             "or --frame RAS", p)
        if labelmap is None:
            if source_frame is not None and f.upper() != source_frame:
                raise InputError(f"is in {f.upper()} but the other surfaces are in {source_frame}", p)
            source_frame = f.upper()
    if "liver" not in surfaces:
        raise InputError("no liver: give --liver FILE or a --labelmap with a liver label")
    assert source_frame is not None  # every surface above either had a frame or raised
    M = frames.to_case(source_frame)
    rep = ImportReport(frame=source_frame, to_case=M)
    rep.lines.append(f"frame: {source_frame} → navapp's {frames.CASE_FRAME} (+x left, +y anterior, +z superior)")

    cleaned = {}
    for organ, mesh in surfaces.items():
        v = frames.apply(M, mesh.vertices)
        fcs = np.asarray(mesh.faces)[:, ::-1] if frames.mirrors(M) else np.asarray(mesh.faces)
        what = "liver surface" if organ == "liver" else f"{organ} surface"
        clean, crep = clean_surface(trimesh.Trimesh(v, fcs, process=False), paths[organ], closed=organ == "liver",
                                    what=what)
        for line in crep.lines():
            rep.lines.append(f"{paths[organ].name} ({organ}): {line}")
        rep.warnings += [f"{paths[organ]}: {w}" for w in crep.warnings]
        cleaned[organ] = clean
    liver_mesh = cleaned["liver"]
    caseio.check_liver_size(liver_mesh, paths["liver"])
    model = PreopModel(liver=liver_mesh, name=name or out.name)
    for vessel in VESSELS:
        if vessel not in cleaned:
            continue
        setattr(model, vessel, cleaned[vessel])
        fraction, far = vessels_outside(liver_mesh, cleaned[vessel])
        if fraction > OUTSIDE_WARN_FRACTION:
            rep.warnings.append(f"{paths[vessel]}: {100 * fraction:.0f} % of the {vessel} vertices lie outside the "
                                f"liver (up to {far:.0f} mm): check the segmentation or the frame")

    if targets:
        from .targets import check_targets, read_target_file

        for p in targets:
            f = slicer_frame(p)
            if f is not None and f != source_frame:
                raise InputError(f"is in {f} but the other files are in {source_frame}", p)
            model.targets += read_target_file(p, to_case=M)
        check_targets(model.targets, liver_mesh)
        for t in model.targets:
            rep.lines.append(f"target {t.name}: {t.diameter_mm:.1f} mm across, centre "
                             f"({', '.join(f'{x:.1f}' for x in t.centre)}) mm")

    user_centerlines = dict(centerlines or {})
    for vessel in VESSELS:
        if vessel in user_centerlines:
            continue
        vessel_mesh = model.vessel(vessel)
        if vessel_mesh is None:
            continue
        try:
            cl = vessel_centerline(vessel_mesh)
        except (ValueError, NavappError) as exc:
            rep.warnings.append(f"{paths[vessel]}: no centerline could be extracted ({exc})")
            continue
        setattr(model, f"{vessel}_centerline", cl)
        rep.lines.append(f"{vessel} centerline: {int(cl.branch.max()) + 1} branches, {len(cl.points)} points "
                         "(skeleton of the vessel volume)")
    if regions is None:
        lmk = None if falciform is None else frames.apply(M, np.asarray(falciform, float).reshape(2, 3))
        labelled = auto_regions(liver_mesh, falciform=lmk)
        model.regions = labelled.codes
        counts = np.bincount(labelled.codes, minlength=len(REGION_NAMES))
        rep.lines.append("regions (automatic): " + ", ".join(f"{n} {c}" for n, c in zip(REGION_NAMES, counts,
                                                                                            strict=True)))
        rep.warnings += labelled.warnings

    out.mkdir(parents=True, exist_ok=True)
    caseio.write_preop(model, out)
    if regions is not None:
        caseio.read_regions(regions, len(liver_mesh.vertices))  # refuse a file that does not fit, in one line
        (out / "preop" / "regions.csv").write_text(Path(regions).read_text())
    for vessel, p in user_centerlines.items():
        (out / "preop" / f"{vessel}_centerline.csv").write_text(Path(p).read_text())
    settings = {"name": model.name, "units": "mm",
                "frame": {"case": frames.CASE_FRAME, "source": source_frame,
                          "source_to_case": [[float(x) for x in row] for row in M],
                          "files": {k: str(v) for k, v in paths.items()}}}
    caseio.write_settings(out, settings)
    rep.lines.append(f"liver: {len(liver_mesh.vertices)} vertices, {liver_mesh.volume / 1000:.0f} ml")
    return rep


def _label_values(lm: LabelMap, labels: dict | None, path) -> dict:
    """organ → label value: given, or Slicer segment names matched, or 1/2/3."""
    if labels:
        return {k: int(v) for k, v in labels.items()}
    found = {}
    for value, seg in lm.names.items():
        low = str(seg).lower()
        for organ, keys in (("liver", ("liver",)), ("portal", ("portal", "pv")), ("hepatic", ("hepatic", "hv"))):
            if any(k in low for k in keys) and organ not in found:
                found[organ] = int(value)
    if "liver" in found:
        return found
    present = [int(x) for x in np.unique(lm.labels) if x != 0]
    if present == [1] or not present:
        return {"liver": 1}
    if not lm.names:
        warnings.warn(f"{path}: no segment names; taking label 1 as liver, 2 portal, 3 hepatic", stacklevel=2)
        return {k: v for k, v in (("liver", 1), ("portal", 2), ("hepatic", 3)) if v in present}
    raise InputError("no segment named like 'liver': give --labels liver=N,portal=N,hepatic=N", path)
