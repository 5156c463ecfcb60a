"""The two meshers' calls, Gmsh and fTetWild, each in the calling process.

They live apart from ``meshing`` (the chain, the quality floor, the cache) because each
meshing attempt runs them in a fresh interpreter (``mesh_worker``): this module imports
NumPy and the mesher alone, where ``meshing``'s trimesh, SciPy and the rest cost the worker
about a CPU second per attempt before any meshing.
"""

import os

import numpy as np

from ..errors import NavappError

VOLUME_MESHERS = ("delaunay", "hxt")
"""Gmsh's volume stage: "delaunay" (3D Delaunay, then Gmsh's optimiser and Netgen's: the meshes
navapp was measured with) or "hxt" (Gmsh's HXT Delaunay on one thread, then Gmsh's optimiser
alone: about a quarter of the CPU, a min dihedral of 12–14° instead of 18–22°; docs/decisions/speed.md,
"Issue 49, session 40")."""


def gmsh_mesh(v: np.ndarray, f: np.ndarray, edge: float, seed: int = 0, feature_angle: float = 40.0,
              volume: str = "delaunay"):
    """Gmsh in this process: classify the triangles into smooth patches at
    ``feature_angle`` degrees and rebuild a parametrised geometry; remesh the surface with
    Frontal-Delaunay at ``edge``; fill the volume (``volume``, one of ``VOLUME_MESHERS``) and
    optimise. Returns raw (nodes (N, 3), tets (E, 4)); raises ``NavappError``."""
    if volume not in VOLUME_MESHERS:
        raise NavappError(f"unknown Gmsh volume mesher {volume!r}")
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
        gmsh.option.setNumber("Mesh.Algorithm3D", 10 if volume == "hxt" else 1)
        gmsh.option.setNumber("Mesh.Optimize", 1)
        gmsh.option.setNumber("Mesh.OptimizeNetgen", 0 if volume == "hxt" else 1)
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
