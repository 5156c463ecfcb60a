"""Tetrahedral meshing of the liver surface: Gmsh first, fTetWild when Gmsh cannot.

Gmsh (GPL-2.0-or-later, pip wheel) re-parametrises and remeshes the input surface at the
requested edge length before filling the volume, so tet quality does not depend on the
triangles the user supplied; re-parametrisation can fail or hang on sharp or unevenly
triangulated surfaces, so every attempt runs in a child process under a wall-clock limit
and fTetWild (pytetwild wheel), which needs no parametrisation, is the last resort. Every
mesh returned meets the quality floor: no inverted tet, no dihedral angle under 5°.
"""

import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from ..defaults import EDGE_MM
from ..errors import NavappError
from .manifold import boundary_defects, mend_pinches
from .tets import TetMesh, tet_volumes  # TetMesh re-exported: its home is tets.py


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


@dataclass(frozen=True)
class MeshAttempt:
    """One way of meshing: ``method`` "gmsh" (remesh the surface on re-parametrised patches
    split at ``feature_angle`` degrees, then Delaunay + Netgen optimisation) or "ftetwild"
    (envelope-based: never needs a parametrisation); ``limit`` s of wall clock at most."""

    method: str
    feature_angle: float = 40.0
    limit: float | None = None  # None: scaled to the expected mesh (``attempt_limit``)
    edge_scale: float = 1.0  # the attempt meshes at edge × edge_scale


ATTEMPTS = (
    MeshAttempt("gmsh", 40.0),
    MeshAttempt("gmsh", 60.0),
    MeshAttempt("gmsh", 90.0),
    MeshAttempt("ftetwild"),
    MeshAttempt("ftetwild", edge_scale=0.85),
)
"""Tried in order until one passes the quality floor. Gmsh at 40° gives the meshes navapp
was measured with; larger angles make fewer, larger patches, which is what lets
re-parametrisation succeed on sharp or unevenly triangulated surfaces; fTetWild is the
fallback that cannot fail on a valid closed surface, tried a second time on a slightly
finer edge because its boundary can come out pinched beyond mending (choices and timings:
docs/decisions.md, "Meshing any liver" and "Pinched boundaries")."""

def attempt_limit(attempt: MeshAttempt, surface: trimesh.Trimesh, edge: float) -> float:
    """Seconds one attempt may take: its own ``limit``, else 30 s plus 3 ms per expected
    node (Gmsh) or 300 s plus 20 ms per expected node (fTetWild) (volume / (1.24 edge³) nodes, measured on the
    phantoms), so that a large liver at a fine edge is not cut short."""
    if attempt.limit is not None:
        return attempt.limit
    expected = abs(float(surface.volume)) / (1.24 * edge ** 3)
    if attempt.method == "gmsh":
        return 30.0 + 0.003 * expected
    return 300.0 + 0.02 * expected  # fTetWild's time grows with the input surface too


MIN_DIHEDRAL_DEG = 5.0  # the quality floor: no tet with a dihedral angle below this
MESH_TIME_LIMIT = 1200.0  # s of wall clock for all attempts together ($NAVAPP_MESH_TIMEOUT)


def time_limit() -> float:
    """The meshing wall-clock limit in seconds: ``$NAVAPP_MESH_TIMEOUT`` or the default."""
    try:
        return float(os.environ.get("NAVAPP_MESH_TIMEOUT", MESH_TIME_LIMIT))
    except ValueError:
        value = os.environ["NAVAPP_MESH_TIMEOUT"]
        raise NavappError(f"NAVAPP_MESH_TIMEOUT={value!r} is not a number of seconds") from None


def tetrahedralise(surface: trimesh.Trimesh, edge: float = EDGE_MM, seed: int = 0, limit: float | None = None,
                   attempts=ATTEMPTS) -> TetMesh:
    """Tet mesh of the solid bounded by ``surface`` with target edge length ``edge`` mm.

    ``attempts`` are tried in order, each in a child process that is killed when it
    overruns its share of ``limit`` seconds (Gmsh cannot be interrupted from Python and
    has been seen to hang on sharp surfaces). The first mesh with no inverted tet and no
    dihedral angle under ``MIN_DIHEDRAL_DEG`` is returned, its nodes (M, 3) mm and tets
    (E, 4) positively oriented (``mesh_liver`` also reports what was tried). Raises ``NavappError``
    in one line when every attempt failed or the time ran out.
    """
    mesh, _ = _mesh_with_log(surface, edge, seed, limit, attempts)
    return mesh


def _mesh_with_log(surface, edge, seed, limit, attempts):
    if edge <= 0:
        raise NavappError("edge length must be positive")
    if not surface.is_watertight:
        raise NavappError("liver surface is not watertight: cannot mesh its volume")
    limit = time_limit() if limit is None else float(limit)
    deadline = time.monotonic() + limit
    log = []
    v = np.asarray(surface.vertices, float)
    f = np.asarray(surface.faces, np.int64)
    gmsh_hung = False
    for attempt in attempts:
        remaining = deadline - time.monotonic()
        if remaining <= 1.0:
            break
        if gmsh_hung and attempt.method == "gmsh":
            continue  # a Gmsh hang is a property of the surface, not of the angle
        t0 = time.perf_counter()
        try:
            nodes, tets = _run_attempt(v, f, edge * attempt.edge_scale, seed, attempt,
                                       min(attempt_limit(attempt, surface, edge), remaining))
        except _AttemptFailed as exc:
            log.append({"method": _label(attempt), "outcome": str(exc), "seconds": round(time.perf_counter() - t0, 1)})
            gmsh_hung |= exc.timed_out and attempt.method == "gmsh"
            continue
        mesh = _tidy(nodes, tets)
        mesh, mended = _closed_manifold(mesh)
        if mesh is None:
            log.append({"method": _label(attempt), "seconds": round(time.perf_counter() - t0, 1),
                        "outcome": f"boundary not a closed manifold ({mended})"})
            continue
        q = quality_report(mesh)
        entry = {"method": _label(attempt), "seconds": round(time.perf_counter() - t0, 1), "nodes": q["nodes"],
                 "min_dihedral_deg": round(q["min_dihedral_deg"], 2)}
        if mended:
            entry["mended"] = mended
        if q["inverted"] or q["tets_below_5deg"] or q["min_dihedral_deg"] < MIN_DIHEDRAL_DEG:
            entry["outcome"] = (f"below the quality floor ({q['inverted']} inverted, {q['tets_below_5deg']} tets "
                                f"under {MIN_DIHEDRAL_DEG:g}°)")
            log.append(entry)
            continue
        entry["outcome"] = "ok"
        log.append(entry)
        return mesh, log
    return _give_up(log, limit, deadline)


def _give_up(log, limit, deadline):
    if time.monotonic() >= deadline - 1.0:
        raise NavappError(f"meshing did not finish within {limit:g} s (tried: "
                          f"{'; '.join(e['method'] + ': ' + e['outcome'] for e in log) or 'nothing'}); "
                          "raise NAVAPP_MESH_TIMEOUT or simplify the surface")
    raise NavappError("could not mesh the liver: " + "; ".join(f"{e['method']}: {e['outcome']}" for e in log))


def _label(attempt: MeshAttempt) -> str:
    scale = "" if attempt.edge_scale == 1.0 else f" at {attempt.edge_scale:g} × edge"
    return (f"gmsh {attempt.feature_angle:g}°" if attempt.method == "gmsh" else attempt.method) + scale


def _closed_manifold(mesh: TetMesh):
    """(mesh, what was mended) with every pinch of its boundary opened, or (None, why)
    when mending could not make the boundary one closed manifold (``manifold.py``)."""
    defects = boundary_defects(mesh)
    if defects.ok:
        return mesh, ""
    before = float(tet_volumes(mesh.nodes, mesh.tets).sum())
    mended, removed = mend_pinches(mesh)
    left = boundary_defects(mended)
    if not left.ok:
        return None, f"{defects.describe()}; still {left.describe()} after removing {removed} tets"
    lost = 1.0 - float(tet_volumes(mended.nodes, mended.tets).sum()) / before
    return mended, f"{defects.describe()}: opened by removing {removed} tets ({100 * lost:.2g} % of the volume)"


class _AttemptFailed(Exception):
    def __init__(self, message, timed_out=False):
        super().__init__(message)
        self.timed_out = timed_out


def _run_attempt(v, f, edge, seed, attempt: MeshAttempt, limit: float):
    """Run one attempt in ``python -m navapp.anatomy.mesh_worker`` (a fresh interpreter:
    forking a process with viser's threads is unsafe, and spawn would re-run the caller's
    script) and kill it if it overruns ``limit`` seconds."""
    with tempfile.TemporaryDirectory(prefix="navapp-mesh-") as tmp:
        src, dst = Path(tmp, "in.npz"), Path(tmp, "out.npz")
        np.savez(src, vertices=v, faces=f, edge=edge, seed=seed, method=attempt.method,
                 feature_angle=attempt.feature_angle)
        # fTetWild writes a debug file (__tracked_surface.stl) into its working directory:
        # run it in the temporary one, with navapp importable from there
        package_root = str(Path(__file__).resolve().parents[2])
        env = dict(os.environ, OMP_NUM_THREADS="1",
                   PYTHONPATH=os.pathsep.join(filter(None, [package_root, os.environ.get("PYTHONPATH")])))
        command = [sys.executable, "-m", "navapp.anatomy.mesh_worker", str(src), str(dst), str(os.getpid())]
        proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env, cwd=tmp)
        try:
            _, err = proc.communicate(timeout=limit)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
            raise _AttemptFailed(f"stopped after {limit:.0f} s", timed_out=True) from None
        if not dst.exists():
            tail = err.decode(errors="replace").strip().splitlines()
            raise _AttemptFailed(tail[-1] if tail else f"the mesher exited with status {proc.returncode}")
        with np.load(dst) as out:
            if "error" in out:
                raise _AttemptFailed(str(out["error"]))
            return out["nodes"], out["tets"]


def gmsh_mesh(v: np.ndarray, f: np.ndarray, edge: float, seed: int = 0, feature_angle: float = 40.0):
    """Gmsh in this process: classify the triangles into smooth patches at
    ``feature_angle`` degrees and rebuild a parametrised geometry; remesh the surface with
    Frontal-Delaunay at ``edge``; fill with 3D Delaunay; optimise (Gmsh's default plus
    Netgen's). Returns raw (nodes (N, 3), tets (E, 4)); raises ``NavappError``."""
    import gmsh

    initialised = gmsh.isInitialized()
    if not initialised:
        gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.option.setNumber("Mesh.RandomSeed", seed)
        gmsh.model.add("liver")
        s = gmsh.model.addDiscreteEntity(2)
        gmsh.model.mesh.addNodes(2, s, np.arange(1, len(v) + 1), np.asarray(v, float).ravel())
        gmsh.model.mesh.addElementsByType(s, 2, [], (np.asarray(f) + 1).ravel())
        gmsh.model.mesh.classifySurfaces(np.radians(feature_angle), True, True, np.pi)
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
        raise NavappError(f"Gmsh failed: {exc}") from None
    finally:
        gmsh.model.remove()
        if not initialised:
            gmsh.finalize()
    if 4 not in list(etypes):
        raise NavappError("Gmsh produced no tetrahedra")
    tet_tags = np.asarray(enodes[list(etypes).index(4)], np.int64).reshape(-1, 4)
    index = np.full(int(tags.max()) + 1, -1, np.int64)
    index[tags.astype(np.int64)] = np.arange(len(tags))
    return coords.reshape(-1, 3), index[tet_tags]


FTETWILD_EDGE_FACTOR = 1.4
"""fTetWild's ideal edge that gives Gmsh's node count at the same ``edge``: measured on
phantom 0 at 4 mm, factor 1.0 gave 35,950 nodes (Gmsh 18,563), 1.4 gave 18,032."""


def ftetwild_mesh(v: np.ndarray, f: np.ndarray, edge: float):
    """fTetWild (MPL-2.0, via the pytetwild wheel) in this process: an envelope-based
    tetrahedralisation that needs no surface parametrisation, so it meshes any closed
    surface; the boundary stays within 1e-3 of the bounding-box diagonal of the input.
    Returns raw (nodes (N, 3), tets (E, 4))."""
    wrapper = _pytetwild_wrapper()
    nodes, tets = wrapper.tetrahedralize_mesh(
        np.asarray(v, np.float64), np.asarray(f, np.uint32), True, False, 0.05, FTETWILD_EDGE_FACTOR * float(edge),
        1e-3, 10.0, False, 1,
        80, 6, True, False, False, np.empty((0, 3)), np.empty((0, 4), np.int32), np.empty(0))
    return np.asarray(nodes, float), np.asarray(tets, np.int64)


def _pytetwild_wrapper():
    """pytetwild's compiled module. Its package ``__init__`` imports pyvista (with VTK,
    ~0.6 GB) although its metadata lists pyvista as optional; navapp needs only the
    compiled fTetWild binding, so it loads that directly when pyvista is absent."""
    try:
        from pytetwild import PyfTetWildWrapper

        return PyfTetWildWrapper
    except ImportError:
        pass
    import glob
    import importlib.machinery
    import importlib.util

    spec = importlib.util.find_spec("pytetwild")
    if spec is None or not spec.submodule_search_locations:
        raise NavappError("the fallback mesher needs pytetwild (pip install pytetwild)")
    found = glob.glob(os.path.join(spec.submodule_search_locations[0], "PyfTetWildWrapper*"))
    found = [p for p in found if not p.endswith(".pyi")]
    if not found:
        raise NavappError("pytetwild is installed without its compiled fTetWild module")
    loader = importlib.machinery.ExtensionFileLoader("pytetwild.PyfTetWildWrapper", found[0])
    wrapper_spec = importlib.util.spec_from_loader(loader.name, loader)
    if wrapper_spec is None:
        raise NavappError("pytetwild's compiled fTetWild module cannot be loaded")
    module = importlib.util.module_from_spec(wrapper_spec)
    loader.exec_module(module)
    return module


def _tidy(nodes, tets) -> TetMesh:
    """Drop orphan nodes, orient every tet positively."""
    used = np.unique(tets)
    remap = np.full(len(nodes), -1, np.int64)
    remap[used] = np.arange(len(used))
    nodes, tets = nodes[used], remap[tets]
    neg = tet_volumes(nodes, tets) < 0
    tets[neg] = tets[neg][:, [0, 2, 1, 3]]
    return TetMesh(nodes=np.ascontiguousarray(nodes, float), tets=np.ascontiguousarray(tets))


def mesh_liver(surface: trimesh.Trimesh, edge: float = EDGE_MM, limit: float | None = None) -> tuple[TetMesh, dict]:
    """Mesh and report: returns the mesh and its quality report with ``seconds``,
    ``method`` (the attempt that succeeded) and ``attempts`` (what was tried)."""
    t0 = time.perf_counter()
    mesh, log = _mesh_with_log(surface, edge, 0, limit, ATTEMPTS)
    report = quality_report(mesh)
    report["edge_mm"] = edge
    report["method"] = log[-1]["method"]
    report["attempts"] = log
    report["seconds"] = round(time.perf_counter() - t0, 3)
    return mesh, report


# gmsh 40/60/90° then fTetWild twice, each with pinches mended, checked against the floor
MESHER_VERSION = "mesh-chain-4"


def cached_tetmesh(surface: trimesh.Trimesh, edge: float = EDGE_MM, cache_root=None) -> tuple[TetMesh, dict]:
    """``mesh_liver`` through the content-addressed cache (key: surface, edge, mesher)."""
    from .. import cache, progress

    root = cache.cache_dir() if cache_root is None else cache_root
    key = cache.content_key(MESHER_VERSION, np.asarray(surface.vertices, float), np.asarray(surface.faces), float(edge))
    path = root / f"mesh-{key}.npz"
    hit = cache.load(path)
    if hit is not None:
        mesh = TetMesh(hit["nodes"], hit["tets"])
        # the report is stored with the mesh: recomputing it was most of a cached reload
        report = json.loads(str(hit["report"])) if "report" in hit else quality_report(mesh)
        report.update(edge_mm=edge, seconds=0.0, cached=True)
        return mesh, report
    with progress.stage(f"meshing the liver at {edge:g} mm"):
        try:
            mesh, report = mesh_liver(surface, edge)
        except NavappError as exc:
            source = surface.metadata.get("file_path")
            raise NavappError(f"{source}: {exc}" if source else str(exc)) from None
    report["cached"] = False
    cache.save(path, {"nodes": mesh.nodes, "tets": mesh.tets, "report": np.array(json.dumps(report))})
    return mesh, report
