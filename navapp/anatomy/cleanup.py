"""Clean-up of a triangle surface as users' exports come: duplicate vertices, specks,
inward winding, several pieces, holes and self-intersections.

``clean_surface`` repairs what can be repaired without guessing (merging exact duplicates,
dropping specks, orienting the triangles outward) and says so in its report; what cannot
be repaired without guessing (holes, non-manifold edges, self-intersections, two large
pieces) is refused with an ``InputError`` naming the file and the problem in one line. The
surface it returns is the one every later stage sees: the mesher is never handed a copy
other than the one that was checked.
"""

from dataclasses import dataclass, field

import numpy as np
import trimesh

from ..errors import InputError
from ..geometry.triangles import self_intersecting_faces

SPECK_FRACTION = 0.01
"""A piece whose area is below this fraction of the largest piece's is a speck: dropped
with a warning. Above it, a second piece is a second organ and the surface is refused."""

MERGE_DECIMALS = 6
"""Vertices equal when rounded to 1e-6 mm are one vertex (STL stores each triangle's
corners separately, as float32: exact duplicates)."""


@dataclass
class CleanupReport:
    """What ``clean_surface`` did. ``vertex_map`` (V_in,) gives each input vertex's index in
    the cleaned surface, −1 where it was dropped (so per-vertex labels can follow)."""

    vertices_in: int
    faces_in: int
    vertices_out: int = 0
    faces_out: int = 0
    merged_vertices: int = 0
    dropped_faces: int = 0  # degenerate or duplicated triangles
    specks: list = field(default_factory=list)  # (triangles, largest extent mm) per dropped piece
    reoriented: bool = False  # triangles wound inconsistently were made consistent
    flipped: bool = False  # the whole surface faced inward and was turned outward
    vertex_map: np.ndarray | None = None
    warnings: list = field(default_factory=list)

    @property
    def changed(self) -> bool:
        return bool(self.merged_vertices or self.dropped_faces or self.specks or self.reoriented or self.flipped
                    or self.vertices_out != self.vertices_in)

    def lines(self) -> list[str]:
        """One human-readable line per action taken."""
        out = []
        if self.merged_vertices:
            out.append(f"merged {self.merged_vertices} duplicate vertices")
        if self.dropped_faces:
            out.append(f"dropped {self.dropped_faces} degenerate or duplicate triangles")
        for n, size in self.specks:
            out.append(f"dropped a speck of {n} triangles ({size:.2g} mm across)")
        if self.reoriented:
            out.append("made the triangle winding consistent")
        if self.flipped:
            out.append("turned the surface outward (it faced inward)")
        return out


def merge_duplicates(vertices: np.ndarray, faces: np.ndarray):
    """Merge equal vertices (to ``MERGE_DECIMALS``) and drop triangles that collapse or
    repeat. Returns (vertices (V', 3), faces (F', 3), vertex_map (V,), dropped_faces)."""
    key = np.round(np.asarray(vertices, float), MERGE_DECIMALS)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    # keep vertices in input order so a clean file comes back unchanged
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    vmap = rank[inverse.ravel()]
    v = np.asarray(vertices, float)[first[order]]
    f = vmap[np.asarray(faces)]
    ok = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    f = f[ok]
    _, keep = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
    keep = np.sort(keep)
    return v, f[keep], vmap, int(len(faces) - len(keep))


def _pieces(faces: np.ndarray) -> list[np.ndarray]:
    """Face indices of each edge-connected piece, most triangles first."""
    groups = trimesh.graph.connected_components(trimesh.graph.face_adjacency(faces), nodes=np.arange(len(faces)),
                                                min_len=1)
    return sorted((np.asarray(g) for g in groups), key=len, reverse=True)


def _crossing(v, f, path, what):
    # a spatial hash over the triangles: any size is checked, in bounded memory
    return self_intersecting_faces(v, f)


def clean_surface(mesh: trimesh.Trimesh, path=None, closed=True,
                  what="surface") -> tuple[trimesh.Trimesh, CleanupReport]:
    """Repair what is safe to repair, refuse the rest.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        As read, unprocessed: (V, 3) float vertices in mm, (F, 3) int faces.
    path : path-like, optional
        Named in every message.
    closed : bool
        A liver must bound a volume: one piece (specks dropped), watertight, manifold,
        consistently wound, facing outward, not self-intersecting. Vessel surfaces
        (``closed=False``) are only merged and freed of specks.
    what : str
        What the surface is, for messages ("liver surface").

    Returns
    -------
    (trimesh.Trimesh, CleanupReport)
        The cleaned surface (``process=False``: exactly these arrays) and what was done.
    """
    v0 = np.asarray(mesh.vertices, float)
    f0 = np.asarray(mesh.faces, np.int64)
    if len(f0) == 0:
        raise InputError("holds no triangles", path)
    if not np.all(np.isfinite(v0)):
        raise InputError("has NaN or infinite vertex coordinates", path)
    rep = CleanupReport(vertices_in=len(v0), faces_in=len(f0))
    v, f, vmap, rep.dropped_faces = merge_duplicates(v0, f0)
    rep.merged_vertices = len(v0) - len(v)
    if len(f) == 0:
        raise InputError("holds only degenerate triangles", path)

    pieces = _pieces(f)
    large = np.ones(len(pieces), bool)
    if len(pieces) > 1:
        area = trimesh.triangles.area(v[f])
        sizes = np.array([area[p].sum() for p in pieces])
        # by area, not by triangle count: a finely triangulated speck can have more triangles
        # than a coarse organ
        large = sizes >= SPECK_FRACTION * sizes.max()
    if closed and large.sum() > 1:
        bad = _crossing(v, f, path, what)
        if len(bad):
            raise InputError(f"{what} is self-intersecting ({len(bad)} triangles cross another)", path)
        ml = [abs(trimesh.Trimesh(v, f[pieces[i]]).volume) / 1000 for i in np.flatnonzero(large)]
        raise InputError(f"{what} has {int(large.sum())} large separate pieces "
                         f"({', '.join(f'{x:.3g} ml' for x in ml[:4])}); "
                         f"{'a liver' if what.startswith('liver') else 'it'} must be one piece", path)
    # several large pieces are kept in a vessel tree (segmented from CT it often comes so: the
    # portal trunk apart from its branches); only specks are dropped
    if not large.all():
        keep = np.concatenate([pieces[i] for i in np.flatnonzero(large)])
        for i in np.flatnonzero(~large):
            pv = v[np.unique(f[pieces[i]])]
            rep.specks.append((len(pieces[i]), float(np.ptp(pv, axis=0).max())))
        f = f[np.sort(keep)]
        used = np.unique(f)
        remap = np.full(len(v), -1)
        remap[used] = np.arange(len(used))
        v, f = v[used], remap[f]
        vmap = np.where(vmap >= 0, remap[vmap], -1)
        n = len(rep.specks)
        rep.warnings.append(f"dropped {n} tiny separate piece{'s' * (n > 1)} "
                            f"(at most {max(s for _, s in rep.specks):.2g} mm across)")

    out = trimesh.Trimesh(v, f, process=False)
    if closed:
        edges = np.sort(out.edges, axis=1)
        _, counts = np.unique(edges, axis=0, return_counts=True)
        if (counts == 1).any():
            raise InputError(f"{what} has holes ({int((counts == 1).sum())} open edges): it must be closed", path)
        if (counts > 2).any():
            raise InputError(f"{what} has {int((counts > 2).sum())} non-manifold edges (shared by more than "
                             "two triangles)", path)
        if not out.is_winding_consistent:
            trimesh.repair.fix_winding(out)
            if not out.is_winding_consistent:
                raise InputError(f"{what} cannot be wound consistently (is it a one-sided surface?)", path)
            rep.reoriented = True
            rep.warnings.append("triangle winding was inconsistent: made consistent")
        extent = float(np.ptp(out.vertices, axis=0).max())
        if abs(out.volume) <= 1e-9 * extent ** 3:  # a closed surface folded flat: nothing inside
            raise InputError(f"{what} encloses no volume (it is flat)", path)
        if out.volume < 0:
            out = trimesh.Trimesh(out.vertices, out.faces[:, ::-1], process=False)
            rep.flipped = True
            rep.warnings.append("the surface faced inward (negative volume): turned outward")
        bad = _crossing(out.vertices, out.faces, path, what)
        if len(bad):
            raise InputError(f"{what} is self-intersecting ({len(bad)} triangles cross another)", path)
    rep.vertices_out, rep.faces_out = len(out.vertices), len(out.faces)
    rep.vertex_map = vmap
    return out, rep


def vessels_outside(liver: trimesh.Trimesh, vessel: trimesh.Trimesh, voxel: float = 1.0,
                    beyond_mm: float = 0.0) -> tuple[float, float]:
    """Fraction of ``vessel``'s vertices outside the closed ``liver``, and the largest
    distance (mm) of those from the liver's vertices; (0, 0) when all lie inside.

    Inside is read off a ``voxel`` mm inside grid of the liver (trimesh's ray-based
    ``contains`` needs gigabytes for a vessel tree), so a vertex within a voxel of the
    surface may go either way: this is a warning's test, not a measurement. With
    ``beyond_mm`` > 0, a vertex counts as outside only when it lies farther than that from
    the liver's surface (distances to the surface, not its vertices): a tumour at the
    border has a face on the organ's surface, which is not a tumour outside the organ.
    """
    from scipy.spatial import cKDTree

    from .skeleton import voxelize

    inside, origin = voxelize(liver, voxel)
    ijk = np.round((np.asarray(vessel.vertices) - origin) / voxel).astype(int)
    ok = np.all((ijk >= 0) & (ijk < inside.shape), axis=1)
    is_in = np.zeros(len(ijk), bool)
    is_in[ok] = inside[tuple(ijk[ok].T)]
    if is_in.all():
        return 0.0, 0.0
    out = np.asarray(vessel.vertices)[~is_in]
    if beyond_mm > 0:
        _, distance, _ = trimesh.proximity.closest_point(liver, out)
        far = distance > beyond_mm
        if not far.any():
            return 0.0, 0.0
        return float(far.sum() / len(is_in)), float(distance.max())
    distance, _ = cKDTree(liver.vertices).query(out)
    return float((~is_in).mean()), float(distance.max())


def outside_distance(liver: trimesh.Trimesh, surface: trimesh.Trimesh, voxel: float = 1.0) -> np.ndarray:
    """(V,) how far (mm) each vertex of ``surface`` lies outside the closed ``liver``: its
    distance to the liver's surface where a ``voxel`` mm inside grid puts it outside (see
    ``vessels_outside``), 0 where inside."""
    from .skeleton import voxelize

    inside, origin = voxelize(liver, voxel)
    pts = np.asarray(surface.vertices, float)
    ijk = np.round((pts - origin) / voxel).astype(int)
    ok = np.all((ijk >= 0) & (ijk < inside.shape), axis=1)
    is_in = np.zeros(len(ijk), bool)
    is_in[ok] = inside[tuple(ijk[ok].T)]
    out = np.zeros(len(pts))
    if not is_in.all():
        _, out[~is_in], _ = trimesh.proximity.closest_point(liver, pts[~is_in])
    return out
