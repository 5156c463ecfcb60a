"""Import a patient's anatomy from where surgical models come from: 3D Slicer's surface
exports (STL, OBJ, PLY, VTK/VTP) or label maps (NIfTI, NRRD, Slicer's ``.seg.nrrd``, DICOM
SEG: ``labelmaps``), one file per structure or one for all.

``import_case`` reads, converts to navapp's frame (``frames``), cleans (``cleanup``), adds
region labels and vessel centerlines where the user gave none (``autolabel``,
``skeleton``), and writes a case folder whose ``case.toml`` records the source frame and
the transform into navapp's. Every problem is one ``InputError`` line naming the file.
"""

import contextlib
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from ..errors import InputError, NavappError
from ..geometry.transforms import apply, homogeneous
from . import frames
from .cleanup import clean_surface, outside_distance
from .labelmaps import (
    LABELMAP_SUFFIXES,
    STRUCTURE_WORDS,
    LabelMap,
    StructureMask,
    check_same_grid,
    is_labelmap,
    read_labelmap,
    recognise_folder,
    resolve_label,
    stem,
    structure_mask,
)
from .model import REGION_NAMES, VESSELS, PreopModel
from .surface_io import SURFACE_SUFFIXES, read_any_surface

__all__ = ["LABELMAP_SUFFIXES", "SURFACE_SUFFIXES", "ImportReport", "LabelMap", "Source", "import_case",
           "mask_surface", "read_any_surface", "read_labelmap", "slicer_frame"]

OUTSIDE_WARN_FRACTION = 0.01  # warn when more than 1 % of a vessel's vertices lie outside the liver
VESSEL_MARGIN_MM = 15.0
"""The model holds a vessel within this of the liver's surface and cuts off the rest: the
portal trunk at the hilum stays, the extrahepatic portal vein, the IVC and a splenic vein
beyond go; the FE model has no tissue out there to move them with (docs/decisions/anatomy.md)."""


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


# ---------------------------------------------------------------- label maps → surfaces

LIVER_SURFACE_EDGE_MM = 2.5
"""A label map's liver is decimated to triangles of about this edge (the FE mesh's edge is
4 mm and Gmsh remeshes the surface: finer input buys no accuracy, only time) …"""
LIVER_MAX_FACES = 60_000
"""… and to at most this many triangles (a 2 l liver at 2.5 mm has ~40k)."""
VESSEL_SURFACE_EDGE_MM = 1.0  # vessels keep their small branches
VESSEL_MAX_FACES = 60_000
SMOOTH_ITERATIONS = 10
LIVER_CLOSING_MM = 3.0
"""Vessel voxels within this closing of a liver mask count as liver: masks that leave the
vessels out of the liver (a label map with liver 1, vessels 2) would give it tunnels."""


def mask_surface(sm: StructureMask, edge: float, max_faces: int, timings: dict | None = None,
                 smooth_iterations: int = SMOOTH_ITERATIONS) -> trimesh.Trimesh:
    """The closed surface of a cropped mask in navapp's frame, mm.

    Marching cubes at the voxel grid (in index space, then through the affine, so oblique
    and anisotropic volumes come out right), Taubin smoothing (λ/μ: it removes the voxel
    staircase without the shrinkage of plain Laplacian smoothing), then quadric decimation
    to triangles of about ``edge`` mm and at most ``max_faces``.
    """
    from skimage.measure import marching_cubes

    timings = {} if timings is None else timings
    with _timed(timings, "marching_cubes"):
        v, f, _, _ = marching_cubes(sm.mask.astype(np.float32), 0.5)
        v = apply(sm.affine, v)
        f = np.asarray(f)[:, ::-1] if frames.mirrors(sm.affine) else np.asarray(f)
        mesh = trimesh.Trimesh(v, f[:, ::-1], process=False)  # skimage winds inward for "inside = high"
    with _timed(timings, "smoothing"):
        trimesh.smoothing.filter_taubin(mesh, lamb=0.5, nu=0.53, iterations=smooth_iterations)
    with _timed(timings, "decimation"):
        # never below 200 triangles, and never asked for more than there are (a mask of a few
        # voxels: the decimator refuses, a traceback)
        target = max(min(int(mesh.area / (np.sqrt(3) / 4 * edge ** 2)), max_faces), 200)
        if target < len(mesh.faces):
            mesh = mesh.simplify_quadric_decimation(face_count=target)
    return mesh


def _timed(timings: dict, stage: str):

    @contextlib.contextmanager
    def run():
        t0 = time.perf_counter()
        try:
            yield
        finally:
            timings[stage] = timings.get(stage, 0.0) + time.perf_counter() - t0
    return run()


# ---------------------------------------------------------------- liver-likeness

LIVER_ML = (600.0, 4000.0)
"""An adult liver holds 0.6–4 l; outside it, the import warns (wrong mask, wrong units)."""
MIN_SOLIDITY = 0.4
"""A liver fills 0.75–0.8 of its convex hull (the phantoms; real livers 0.6–0.9), a vessel
tree 0.1–0.25: below this the "liver" is refused as tree-like."""
OUTSIDE_REFUSE_FRACTION = 0.5
"""A vessel with more than half its surface outside the liver is refused: the files are of
different patients or frames, or swapped."""


def check_liver_like(volume_ml: float, solidity: float, path, warn: list):
    """Refuse a tree-like "liver", warn about one that is not liver-sized; one line each."""
    if solidity < MIN_SOLIDITY:
        raise InputError(f"is not liver-shaped: it fills {100 * solidity:.0f} % of its convex hull (a liver fills "
                         f"60-90 %, a vessel tree 10-25 %; {volume_ml:.0f} ml): is this a vessel mask given as the "
                         "liver?", path)
    lo, hi = LIVER_ML
    if not lo <= volume_ml <= hi:
        warn.append(f"{path}: the liver holds {volume_ml:.0f} ml, outside an adult liver's {lo / 1000:.1f}-"
                    f"{hi / 1000:.0f} l: check that this is the liver mask (and its units)")


def mask_solidity(sm: StructureMask) -> float:
    """Voxel volume over the convex hull of the voxel centres (a mask's solidity)."""
    from scipy import ndimage
    from scipy.spatial import ConvexHull

    edge = sm.mask & ~ndimage.binary_erosion(sm.mask)
    pts = apply(sm.affine, np.argwhere(edge).astype(float))
    if len(pts) < 4:
        return 0.0
    try:
        hull = ConvexHull(pts)
    except Exception:  # flat or degenerate: no volume
        return 0.0
    # the hull of the voxel centres misses half a voxel all round: compare like with like
    inner = float(np.sum(ndimage.binary_erosion(sm.mask))) * sm.voxel_ml * 1000.0
    full = float(sm.mask.sum()) * sm.voxel_ml * 1000.0
    return min(1.0, 0.5 * (inner + full) / max(hull.volume, 1e-9))


def fill_liver(liver: StructureMask, others: list[StructureMask]) -> StructureMask:
    """The liver mask with enclosed cavities filled, and the voxels of ``others`` (vessel
    masks on the same grid) that the liver closes over added (``LIVER_CLOSING_MM``)."""
    from scipy import ndimage

    mask = liver.mask.copy()
    spacing = np.linalg.norm(liver.affine[:3, :3], axis=0)
    extra = np.zeros_like(mask)
    for o in others:
        # o's crop index → liver crop index (same grid: a whole-voxel shift, maybe permuted)
        P = np.linalg.inv(liver.affine) @ o.affine
        if not np.allclose(P[:3, :3], np.round(P[:3, :3]), atol=1e-3):
            continue
        ijk = np.round(apply(P, np.argwhere(o.mask).astype(float))).astype(int)
        ok = np.all((ijk >= 0) & (ijk < mask.shape), axis=1)
        extra[tuple(ijk[ok].T)] = True
    if extra.any():
        r = np.maximum(np.round(LIVER_CLOSING_MM / spacing).astype(int), 1)
        ball = _ellipsoid(r)
        padded = np.pad(mask, r.max())
        closed = ndimage.binary_closing(padded, structure=ball)[tuple(slice(r.max(), -r.max()) for _ in range(3))]
        mask |= extra & closed
    mask = ndimage.binary_fill_holes(mask)
    return StructureMask(mask, liver.affine, liver.path, liver.label)


def join_touching_targets(liver: StructureMask, target: StructureMask) -> tuple[StructureMask, float, int]:
    """The liver mask joined with the pieces of ``target`` (a tumour mask on the same grid)
    that touch it (a face-neighbouring voxel), and the volume (ml) and number of pieces added.

    The public CT segmentation sets (the Medical Segmentation Decathlon's liver and
    hepatic-vessel tasks, LiTS) label the liver and its tumours apart: the liver label leaves
    the tumours out, and a tumour at the border notches it. The tumour is part of the organ
    that deforms, so the organ is the union; a tumour that does not touch the liver label is
    left out (it is checked as a target like any other)."""
    from scipy import ndimage

    P = np.linalg.inv(liver.affine) @ target.affine
    if not np.allclose(P[:3, :3], np.round(P[:3, :3]), atol=1e-3):
        return liver, 0.0, 0
    pieces, n = ndimage.label(target.mask)
    idx = np.argwhere(pieces)
    ijk = np.round(apply(P, idx.astype(float))).astype(int)  # in the liver crop's index
    piece_of = pieces[tuple(idx.T)]
    steps = np.vstack([np.eye(3, dtype=int), -np.eye(3, dtype=int)])
    touching = np.zeros(n + 1, bool)
    for step in steps:
        q = ijk + step
        ok = np.all((q >= 0) & (q < liver.mask.shape), axis=1)
        hit = np.zeros(len(q), bool)
        hit[ok] = liver.mask[tuple(q[ok].T)]
        touching[piece_of[hit]] = True
    join = touching[piece_of]
    if not join.any():
        return liver, 0.0, 0
    add = ijk[join]
    # the tumour may reach past the liver's box: grow the crop (one empty voxel all round)
    lo = np.minimum(add.min(0) - 1, 0)
    hi = np.maximum(add.max(0) + 2, liver.mask.shape)
    mask = np.zeros(tuple(hi - lo), bool)
    shape = liver.mask.shape
    mask[-lo[0]:-lo[0] + shape[0], -lo[1]:-lo[1] + shape[1], -lo[2]:-lo[2] + shape[2]] = liver.mask
    before = int(mask.sum())
    mask[tuple((add - lo).T)] = True
    shift = homogeneous(np.eye(3), lo)
    added_ml = (int(mask.sum()) - before) * liver.voxel_ml
    return (StructureMask(mask, liver.affine @ shift, liver.path, liver.label), added_ml,
            int(touching.sum()))


def clip_to_liver(vessel: StructureMask, liver: StructureMask, within_mm: float) -> tuple[StructureMask, float]:
    """The voxels of ``vessel`` inside the liver or within ``within_mm`` of it (same grid),
    and the volume (ml) dropped: TotalSegmentator's portal vein comes with the splenic vein,
    which runs 10-15 cm outside the liver."""
    from scipy import ndimage
    from scipy.spatial import cKDTree

    P = np.linalg.inv(liver.affine) @ vessel.affine
    idx = np.argwhere(vessel.mask)
    ijk = np.round(apply(P, idx.astype(float))).astype(int)
    ok = np.all((ijk >= 0) & (ijk < liver.mask.shape), axis=1)
    inside = np.zeros(len(idx), bool)
    inside[ok] = liver.mask[tuple(ijk[ok].T)]
    rim = liver.mask & ~ndimage.binary_erosion(liver.mask)
    d, _ = cKDTree(apply(liver.affine, np.argwhere(rim).astype(float))).query(
        apply(vessel.affine, idx[~inside].astype(float)), distance_upper_bound=within_mm)
    keep = inside.copy()
    keep[~inside] = np.isfinite(d)
    mask = np.zeros_like(vessel.mask)
    mask[tuple(idx[keep].T)] = True
    return StructureMask(mask, vessel.affine, vessel.path, vessel.label), float((~keep).sum()) * vessel.voxel_ml


def _ellipsoid(r: np.ndarray) -> np.ndarray:
    """Structuring element: the voxels within an ellipsoid of semi-axes ``r`` voxels."""
    g = np.indices(tuple(int(x) for x in 2 * r + 1)).astype(float)
    return np.sum([((g[k] - r[k]) / r[k]) ** 2 for k in range(3)], axis=0) <= 1.0


# ---------------------------------------------------------------- sources

@dataclass
class Source:
    """Where one structure comes from: a surface file, or a label map and its label
    (a value, a segment name, or None: the only label, or the segment named like it)."""

    path: Path
    label: int | str | None = None
    clip_mm: float | None = None  # keep only the voxels within this of the liver (a mask)

    @property
    def is_labelmap(self) -> bool:
        return is_labelmap(self.path)

    def __str__(self) -> str:
        return f"{self.path}" if self.label is None else f"{self.path}:{self.label}"


def parse_source(item) -> Source:
    """``FILE`` or ``FILE:LABEL`` (label value or segment name) → ``Source``."""
    if isinstance(item, Source):
        return item
    text = str(item)
    p = Path(text)
    if not p.exists() and ":" in text:
        head, _, tail = text.rpartition(":")
        if tail and "/" not in tail and "\\" not in tail and Path(head).exists():
            return Source(Path(head), int(tail) if tail.isdigit() else tail)
    return Source(p)


@dataclass
class ImportReport:
    """What ``import_case`` did: lines for the user, and the frame conversion; ``seconds``
    the time of each stage."""

    frame: str
    to_case: np.ndarray  # (4, 4) source frame → navapp's (LAS)
    lines: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    seconds: dict = field(default_factory=dict)


def import_case(out, liver=None, portal=None, hepatic=None, labelmap=None, labels=None, frame=None,
                falciform=None, regions=None, centerlines=None, name=None, overwrite=False, targets=None):
    """Write a case folder's ``preop/`` from a patient's files.

    Parameters
    ----------
    out : path-like
        The case folder to write.
    liver, portal, hepatic : path-like or str, optional
        One structure each: a surface (PLY, STL, OBJ, VTK, VTP) or a label map (NIfTI,
        NRRD, ``.seg.nrrd``, DICOM SEG), ``"FILE:LABEL"`` naming the label value or segment
        (default: the file's only label, or its segment named like the structure).
    labelmap : path-like, optional
        One label map holding several structures (``labels`` maps "liver", "portal",
        "hepatic" to values; segment names are matched when not given), or a folder of
        one mask per structure (TotalSegmentator's output; recognised by file names).
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
    targets : list, optional
        Tumour targets (``anatomy.targets``): closed surfaces (named by the file's stem),
        CSVs of points ``name,x,y,z[,radius_mm]``, or label maps (``FILE[:LABEL]``: one
        target per connected piece), in the frame of the other files; written to
        ``preop/targets/``.

    Returns
    -------
    ImportReport
    """

    from . import caseio
    from .autolabel import auto_regions
    from .skeleton import vessel_centerline

    t_start = time.perf_counter()
    out = Path(out)
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise InputError("exists and is not empty (choose another --out, or --overwrite)", out)
    timings: dict[str, float] = {}
    early: list[str] = []
    sources: dict[str, Source] = {}
    for organ, item in (("liver", liver), ("portal", portal), ("hepatic", hepatic)):
        if item is not None:
            sources[organ] = parse_source(item)
    target_sources = [parse_source(t) for t in (targets or [])]
    maps: dict[Path, LabelMap] = {}  # every label map is read once
    if labelmap is not None:
        lm_path = Path(labelmap)
        if lm_path.is_dir():
            found, tfiles, lines = recognise_folder(lm_path)
            early += [f"{lm_path.name}/{line}" for line in lines]
            for organ, p in found.items():
                clip = PORTAL_CLIP_MM if stem(p).lower() == "portal_vein_and_splenic_vein" else None
                _add_source(sources, organ, Source(p, clip_mm=clip), lm_path)
                early.append(f"{lm_path.name}/: {p.name} is the {organ}")
            target_sources += [Source(p) for p in tfiles]
        else:
            with _timed(timings, "read"):
                lm = maps[lm_path] = read_labelmap(lm_path)
            for organ, value in _label_values(lm, labels, lm_path).items():
                _add_source(sources, organ, Source(lm_path, value), lm_path)
    if "liver" not in sources:
        raise InputError("no liver: give --liver FILE (a surface or a mask) or a --labelmap with a liver label")

    # all label maps must lie on the liver's grid (one scan)
    def read_map(p: Path) -> LabelMap:
        if p not in maps:
            with _timed(timings, "read"):
                maps[p] = read_labelmap(p)
            first = maps.get(sources["liver"].path) if sources["liver"].is_labelmap else None
            ref = first if first is not None else next(iter(maps.values()))
            if ref is not maps[p]:
                check_same_grid(ref, maps[p])
        return maps[p]

    masks: dict[str, StructureMask] = {}
    for organ in ("liver", *VESSELS):
        src = sources.get(organ)
        if src is not None and src.is_labelmap:
            lm = read_map(src.path)
            with _timed(timings, "read"):
                masks[organ] = structure_mask(lm, resolve_label(lm, organ, src.label))
    frames_of: dict[str, str] = {}
    surfaces: dict[str, trimesh.Trimesh] = {}  # in navapp's frame
    if "liver" in masks:
        with _timed(timings, "read"):
            for src in target_sources:
                if not src.is_labelmap:
                    continue
                lm = read_map(src.path)
                tumour = structure_mask(lm, resolve_label(lm, "target", src.label))
                masks["liver"], ml, n = join_touching_targets(masks["liver"], tumour)
                if ml > 0:
                    early.append(f"{sources['liver'].path.name} (liver): its label leaves out the tumour "
                                 f"{src.path.name}:{tumour.label} ({n} piece{'s' * (n > 1)} touching it, {ml:.1f} ml "
                                 "beyond the liver label, as the Decathlon and LiTS label them): the organ is the "
                                 "union of both, the tumour kept as a target")
        with _timed(timings, "checks"):
            check_liver_like(masks["liver"].volume_ml, mask_solidity(masks["liver"]), sources["liver"].path, early)
            masks["liver"] = fill_liver(masks["liver"], [masks[v] for v in VESSELS if v in masks])
            for v in VESSELS:
                clip = sources[v].clip_mm if v in masks else None
                if clip is not None:
                    masks[v], dropped = clip_to_liver(masks[v], masks["liver"], clip)
                    if not masks[v].mask.any():
                        raise InputError(f"no voxel of the {v} lies within {clip:g} mm of the liver", sources[v].path)
                    early.append(f"{sources[v].path.name} ({v}): kept within {clip:g} mm of the liver "
                                 f"({dropped:.0f} ml outside dropped: the splenic vein)")
    for organ in ("liver", *VESSELS):
        src = sources.get(organ)
        if src is None:
            continue
        if organ in masks:
            frames_of[organ] = maps[src.path].frame
            edge, cap = ((LIVER_SURFACE_EDGE_MM, LIVER_MAX_FACES) if organ == "liver"
                         else (VESSEL_SURFACE_EDGE_MM, VESSEL_MAX_FACES))
            surfaces[organ] = mask_surface(masks[organ], edge, cap, timings)
            continue
        with _timed(timings, "read"):
            mesh = read_any_surface(src.path)
        f = frame or slicer_frame(src.path)
        if f is None:
            raise InputError("its frame is unknown: give --frame LPS (3D Slicer's default for STL/OBJ export) "
                             "or --frame RAS", src.path)
        frames_of[organ] = f.upper()
        M = frames.to_case(f)
        fcs = np.asarray(mesh.faces)[:, ::-1] if frames.mirrors(M) else np.asarray(mesh.faces)
        surfaces[organ] = trimesh.Trimesh(apply(M, mesh.vertices), fcs, process=False)
    source_frame = frames_of["liver"]
    M = frames.to_case(source_frame)
    rep = ImportReport(frame=source_frame, to_case=M, seconds=timings)
    rep.lines.append(f"frame: {source_frame} → navapp's {frames.CASE_FRAME} (+x left, +y anterior, +z superior)")
    for organ, f in frames_of.items():
        if f != source_frame:
            rep.lines.append(f"{sources[organ].path.name} ({organ}): frame {f} → navapp's {frames.CASE_FRAME}")
    rep.lines += [line for line in early if ": the liver holds" not in line]
    rep.warnings += [line for line in early if ": the liver holds" in line]

    cleaned = {}
    for organ, mesh in surfaces.items():
        path = sources[organ].path
        what = "liver surface" if organ == "liver" else f"{organ} surface"
        with _timed(timings, "cleanup"):
            try:
                clean, crep = clean_surface(mesh, path, closed=organ == "liver", what=what)
            except InputError:
                if organ not in masks:
                    raise
                # a surface navapp made: decimated too far somewhere; mesh it again finer
                mesh = mask_surface(masks[organ], LIVER_SURFACE_EDGE_MM / 2, 4 * LIVER_MAX_FACES, timings)
                clean, crep = clean_surface(mesh, path, closed=True, what=what)
        for line in crep.lines():
            rep.lines.append(f"{path.name} ({organ}): {line}")
        rep.warnings += [f"{path}: {w}" for w in crep.warnings]
        cleaned[organ] = clean
    liver_mesh = cleaned["liver"]
    with _timed(timings, "checks"):
        caseio.check_liver_size(liver_mesh, sources["liver"].path)
        if "liver" not in masks:
            warn: list[str] = []
            check_liver_like(liver_mesh.volume / 1000.0, liver_mesh.volume / max(liver_mesh.convex_hull.volume, 1e-9),
                             sources["liver"].path, warn)
            rep.warnings += warn
    model = PreopModel(liver=liver_mesh, name=name or out.name)
    for vessel in VESSELS:
        if vessel not in cleaned:
            continue
        with _timed(timings, "checks"):
            out_mm = outside_distance(liver_mesh, cleaned[vessel])
        path = sources[vessel].path
        fraction, far = float((out_mm > 0).mean()), float(out_mm.max())
        if fraction > OUTSIDE_REFUSE_FRACTION:
            raise InputError(f"{100 * fraction:.0f} % of the {vessel} surface lies outside the liver "
                             f"({sources['liver'].path.name}; up to {far:.0f} mm): not this liver's {vessel} vein, "
                             "another frame, or the files swapped", path)
        if fraction > OUTSIDE_WARN_FRACTION:
            rep.warnings.append(f"{path}: {100 * fraction:.0f} % of the {vessel} vertices lie outside the "
                                f"liver (up to {far:.0f} mm): check the segmentation or the frame")
        beyond = out_mm > VESSEL_MARGIN_MM
        if beyond.any():
            with _timed(timings, "cleanup"):
                cleaned[vessel] = _crop_vessel(cleaned[vessel], ~beyond, path, vessel)
            rep.lines.append(f"{path.name} ({vessel}): kept within {VESSEL_MARGIN_MM:g} mm of the liver, "
                             f"{int(beyond.sum())} of {len(beyond)} vertices cut off (up to {far:.0f} mm out: "
                             "the model cannot move what lies outside the organ)")
        setattr(model, vessel, cleaned[vessel])

    if target_sources:
        from .targets import check_targets, read_target_file

        with _timed(timings, "targets"):
            for src in target_sources:
                if src.is_labelmap:
                    model.targets += _mask_targets(read_map(src.path), src)
                    continue
                f = slicer_frame(src.path)
                if f is not None and f != source_frame:
                    raise InputError(f"is in {f} but the other files are in {source_frame}", src.path)
                model.targets += read_target_file(src.path, to_case=M)
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
        with _timed(timings, "centerlines"):
            try:
                cl = vessel_centerline(vessel_mesh, voxel=centerline_voxel(vessel_mesh))
            except (ValueError, NavappError) as exc:
                rep.warnings.append(f"{sources[vessel].path}: no centerline could be extracted ({exc})")
                continue
        setattr(model, f"{vessel}_centerline", cl)
        rep.lines.append(f"{vessel} centerline: {int(cl.branch.max()) + 1} branches, {len(cl.points)} points "
                         "(skeleton of the vessel volume)")
    if regions is None:
        with _timed(timings, "regions"):
            lmk = None if falciform is None else apply(M, np.asarray(falciform, float).reshape(2, 3))
            labelled = auto_regions(liver_mesh, falciform=lmk)
        model.regions = labelled.codes
        counts = np.bincount(labelled.codes, minlength=len(REGION_NAMES))
        rep.lines.append("regions (automatic): " + ", ".join(f"{n} {c}" for n, c in zip(REGION_NAMES, counts,
                                                                                            strict=True)))
        rep.warnings += labelled.warnings

    with _timed(timings, "write"):
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
                              "files": {k: str(v) for k, v in sources.items()},
                              "file_frames": dict(frames_of)}}
        caseio.write_settings(out, settings)
    rep.lines.append(f"liver: {len(liver_mesh.vertices)} vertices, {len(liver_mesh.faces)} triangles, "
                     f"{liver_mesh.volume / 1000:.0f} ml")
    timings["total"] = time.perf_counter() - t_start
    return rep


CENTERLINE_VOXEL_MM = 0.5
CENTERLINE_MAX_VOXELS = 6_000_000
"""The vessel volume is thinned at 0.5 mm voxels (``skeleton``: a fifth of the smallest
radius), coarser where that grid would pass this many voxels (a CT's vessel tree spans
15 cm: 0.5 mm would be 27M voxels, 10 s and 0.6 GB for the skeleton alone)."""


def centerline_voxel(vessel: trimesh.Trimesh) -> float:
    ext = np.asarray(vessel.extents, float) + 4 * CENTERLINE_VOXEL_MM
    n = float(np.prod(ext / CENTERLINE_VOXEL_MM))
    return CENTERLINE_VOXEL_MM * max(1.0, (n / CENTERLINE_MAX_VOXELS) ** (1.0 / 3.0))


PORTAL_CLIP_MM = 15.0
"""TotalSegmentator's portal_vein_and_splenic_vein mask is kept within this of the liver:
the portal trunk at the hilum stays, the splenic vein goes."""
MIN_TARGET_ML = 0.05  # pieces of a tumour mask smaller than this are specks


def _crop_vessel(vessel: trimesh.Trimesh, keep: np.ndarray, path, name: str) -> trimesh.Trimesh:
    """The triangles of ``vessel`` whose three corners are kept (``keep`` (V,) bool), its
    specks dropped."""
    faces = np.asarray(vessel.faces)[keep[np.asarray(vessel.faces)].all(axis=1)]
    if not len(faces):
        raise InputError(f"no part of the {name} lies within {VESSEL_MARGIN_MM:g} mm of the liver", path)
    used = np.unique(faces)
    remap = np.full(len(vessel.vertices), -1)
    remap[used] = np.arange(len(used))
    cut = trimesh.Trimesh(np.asarray(vessel.vertices)[used], remap[faces], process=False)
    clean, _ = clean_surface(cut, path, closed=False, what=f"{name} surface")
    return clean


def _mask_targets(lm: LabelMap, src: Source):
    """One target per connected piece of the label in a mask (named after the file)."""
    from scipy import ndimage

    from .targets import from_surface

    sm = structure_mask(lm, resolve_label(lm, "target", src.label))
    pieces, n = ndimage.label(sm.mask)
    sizes = np.bincount(pieces.ravel())[1:] * sm.voxel_ml
    keep = [k + 1 for k in np.argsort(-sizes) if sizes[k] >= MIN_TARGET_ML]
    base = stem(src.path)
    out = []
    for rank, k in enumerate(keep, start=1):
        piece = StructureMask(pieces == k, sm.affine, sm.path, sm.label)
        mesh = mask_surface(piece, VESSEL_SURFACE_EDGE_MM, VESSEL_MAX_FACES)
        clean, _ = clean_surface(mesh, src.path, closed=True, what="target surface")
        out.append(from_surface(base if len(keep) == 1 else f"{base}_{rank}", clean, src.path))
    return out


def _add_source(sources: dict, organ: str, src: Source, where):
    if organ in sources:
        raise InputError(f"gives the {organ} ({src}) but it was also given as {sources[organ]}: give each structure "
                         "once", where)
    sources[organ] = src


def _label_values(lm: LabelMap, labels: dict | None, path) -> dict:
    """organ → label value: given, or segment names matched, or 1/2/3."""
    if labels:
        return {k: int(v) for k, v in labels.items()}
    found = {}
    for value, seg in sorted(lm.names.items()):
        low = str(seg).lower()
        for organ, keys in STRUCTURE_WORDS.items():
            if any(k in low for k in keys) and organ not in found:
                found[organ] = int(value)
                break
    if "liver" in found:
        return found
    present = lm.values()
    if present == [1] or not present:
        return {"liver": 1}
    if not lm.names:
        warnings.warn(f"{path}: no segment names; taking label 1 as liver, 2 portal, 3 hepatic", stacklevel=2)
        return {k: v for k, v in (("liver", 1), ("portal", 2), ("hepatic", 3)) if v in present}
    raise InputError("no segment named like 'liver': give --labels liver=N,portal=N,hepatic=N", path)
