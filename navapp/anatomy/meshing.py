"""Tetrahedral meshing of the liver surface with Gmsh (GPL-2.0-or-later, pip wheel).

The input surface (e.g. marching-cubes output) is re-parametrised and remeshed by Gmsh at
the requested edge length before the volume is filled with 3D Delaunay and optimised, so
the tet quality does not depend on the quality of the triangles the user supplied.
"""

import time
from dataclasses import dataclass

import numpy as np
import trimesh

from ..errors import NavappError


@dataclass
class TetMesh:
    """Linear tetrahedral mesh. nodes (M, 3) mm, tets (E, 4) int with positive volume."""

    nodes: np.ndarray
    tets: np.ndarray

    def boundary_faces(self) -> np.ndarray:
        """(F, 3) outward-oriented boundary triangles."""
        return boundary_faces(self.tets, self.nodes)

    def surface_nodes(self) -> np.ndarray:
        return np.unique(self.boundary_faces())


def tet_volumes(nodes, tets):
    """Signed volumes (E,) mm^3; positive for right-handed vertex order."""
    a, b, c, d = (nodes[tets[:, i]] for i in range(4))
    return np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) / 6.0


def boundary_faces(tets, nodes):
    """Faces used by exactly one tet, oriented with outward normals."""
    local = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
    faces = tets[:, local].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, idx, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    # for a positively oriented tet these local faces wind outward, so boundary faces do too
    return faces[idx[counts == 1]]


def dihedral_angles(nodes, tets):
    """(E, 6) interior dihedral angles in degrees."""
    p = nodes[tets]
    faces = [(1, 2, 3, 0), (0, 3, 2, 1), (0, 1, 3, 2), (0, 2, 1, 3)]
    normals = []
    for i, j, k, _ in faces:
        n = np.cross(p[:, j] - p[:, i], p[:, k] - p[:, i])
        normals.append(n / np.linalg.norm(n, axis=1, keepdims=True))
    out = []
    for a in range(4):
        for b in range(a + 1, 4):
            c = np.einsum("ij,ij->i", normals[a], normals[b])
            out.append(180.0 - np.degrees(np.arccos(np.clip(c, -1, 1))))
    return np.column_stack(out)


def radius_ratio(nodes, tets):
    """Normalised radius ratio 3 r_in / r_circ in (0, 1]; 1 for the regular tet."""
    p = nodes[tets]
    vol = np.abs(tet_volumes(nodes, tets))
    areas = 0.0
    for i, j, k in [(1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1)]:
        areas = areas + 0.5 * np.linalg.norm(np.cross(p[:, j] - p[:, i], p[:, k] - p[:, i]), axis=1)
    r_in = 3 * vol / areas
    a = p[:, 1] - p[:, 0]
    b = p[:, 2] - p[:, 0]
    c = p[:, 3] - p[:, 0]
    num = (np.einsum("ij,ij->i", a, a)[:, None] * np.cross(b, c) + np.einsum("ij,ij->i", b, b)[:, None] * np.cross(c, a)
           + np.einsum("ij,ij->i", c, c)[:, None] * np.cross(a, b))
    r_circ = np.linalg.norm(num, axis=1) / (12 * vol)
    return 3 * r_in / r_circ


def quality_report(mesh: TetMesh) -> dict:
    """Node/element counts and quality figures of a tet mesh."""
    vol = tet_volumes(mesh.nodes, mesh.tets)
    dih = dihedral_angles(mesh.nodes, mesh.tets)
    rr = radius_ratio(mesh.nodes, mesh.tets)
    edges = np.concatenate([mesh.nodes[mesh.tets[:, i]] - mesh.nodes[mesh.tets[:, j]]
                            for i in range(4) for j in range(i + 1, 4)])
    return {
        "nodes": int(len(mesh.nodes)),
        "elements": int(len(mesh.tets)),
        "surface_nodes": int(len(mesh.surface_nodes())),
        "inverted": int((vol <= 0).sum()),
        "min_dihedral_deg": float(dih.min()),
        "max_dihedral_deg": float(dih.max()),
        "tets_below_5deg": int((dih.min(1) < 5).sum()),
        "min_radius_ratio": float(rr.min()),
        "mean_radius_ratio": float(rr.mean()),
        "mean_edge_mm": float(np.linalg.norm(edges, axis=1).mean()),
        "volume_mm3": float(vol.sum()),
    }


def tetrahedralise(surface: trimesh.Trimesh, edge: float = 4.0, seed: int = 0) -> TetMesh:
    """Tet mesh of the solid bounded by ``surface`` with target edge length ``edge`` mm.

    Steps: classify the triangles into smooth patches (40° feature angle) and rebuild a
    parametrised geometry from them; remesh the surface with Frontal-Delaunay at ``edge``;
    fill with 3D Delaunay; optimise (Gmsh's default plus Netgen's optimiser). Orphan
    nodes are dropped and tets oriented positively.
    """
    import gmsh

    if not surface.is_watertight:
        raise NavappError("liver surface is not watertight: cannot mesh its volume")
    if edge <= 0:
        raise NavappError("edge length must be positive")
    initialised = gmsh.isInitialized()
    if not initialised:
        gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.option.setNumber("Mesh.RandomSeed", seed)
        gmsh.model.add("liver")
        v = np.asarray(surface.vertices, float)
        f = np.asarray(surface.faces)
        s = gmsh.model.addDiscreteEntity(2)
        gmsh.model.mesh.addNodes(2, s, np.arange(1, len(v) + 1), v.ravel())
        gmsh.model.mesh.addElementsByType(s, 2, [], (f + 1).ravel())
        gmsh.model.mesh.classifySurfaces(np.radians(40), True, True, np.pi)
        gmsh.model.mesh.createGeometry()
        surfaces = [t for _, t in gmsh.model.getEntities(2)]
        loop = gmsh.model.geo.addSurfaceLoop(surfaces)
        gmsh.model.geo.addVolume([loop])
        gmsh.model.geo.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMin", edge)
        gmsh.option.setNumber("Mesh.MeshSizeMax", edge)
        gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
        gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
        gmsh.option.setNumber("Mesh.Algorithm", 6)
        gmsh.option.setNumber("Mesh.Algorithm3D", 1)
        gmsh.option.setNumber("Mesh.Optimize", 1)
        gmsh.option.setNumber("Mesh.OptimizeNetgen", 1)
        gmsh.model.mesh.generate(3)
        tags, coords, _ = gmsh.model.mesh.getNodes()
        etypes, _, enodes = gmsh.model.mesh.getElements(3)
    except Exception as exc:  # gmsh raises bare Exception with its own message
        raise NavappError(f"Gmsh failed to mesh the liver: {exc}") from None
    finally:
        gmsh.model.remove()
        if not initialised:
            gmsh.finalize()
    if 4 not in list(etypes):
        raise NavappError("Gmsh produced no tetrahedra (is the surface closed and not self-intersecting?)")
    tet_tags = np.asarray(enodes[list(etypes).index(4)], np.int64).reshape(-1, 4)
    index = np.full(int(tags.max()) + 1, -1, np.int64)
    index[tags.astype(np.int64)] = np.arange(len(tags))
    tets = index[tet_tags]
    nodes = coords.reshape(-1, 3)
    used = np.unique(tets)
    remap = np.full(len(nodes), -1, np.int64)
    remap[used] = np.arange(len(used))
    nodes, tets = nodes[used], remap[tets]
    neg = tet_volumes(nodes, tets) < 0
    tets[neg] = tets[neg][:, [0, 2, 1, 3]]
    return TetMesh(nodes=np.ascontiguousarray(nodes), tets=np.ascontiguousarray(tets))


def mesh_liver(surface: trimesh.Trimesh, edge: float = 4.0) -> tuple[TetMesh, dict]:
    """Mesh and report: returns the mesh and its quality report with ``seconds``."""
    t0 = time.perf_counter()
    mesh = tetrahedralise(surface, edge)
    report = quality_report(mesh)
    report["edge_mm"] = edge
    report["seconds"] = round(time.perf_counter() - t0, 3)
    return mesh, report


MESHER_VERSION = "gmsh-delaunay-netgen-1"


def cached_tetmesh(surface: trimesh.Trimesh, edge: float = 4.0, cache_root=None) -> tuple[TetMesh, dict]:
    """``mesh_liver`` through the content-addressed cache (key: surface, edge, mesher)."""
    from .. import cache, progress

    root = cache.cache_dir() if cache_root is None else cache_root
    key = cache.content_key(MESHER_VERSION, np.asarray(surface.vertices, float), np.asarray(surface.faces), float(edge))
    path = root / f"mesh-{key}.npz"
    hit = cache.load(path)
    if hit is not None:
        mesh = TetMesh(hit["nodes"], hit["tets"])
        report = quality_report(mesh)
        report.update(edge_mm=edge, seconds=0.0, cached=True)
        return mesh, report
    with progress.stage(f"meshing at {edge:g} mm (Gmsh)"):
        mesh, report = mesh_liver(surface, edge)
    report["cached"] = False
    cache.save(path, {"nodes": mesh.nodes, "tets": mesh.tets})
    return mesh, report
