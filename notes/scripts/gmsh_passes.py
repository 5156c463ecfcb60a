"""Gmsh on phantom N at 4 mm with one variant of the volume and its optimisation passes
(netgen: today's; opt: Gmsh's optimiser alone; thr: its threshold 0.5; reloc: + Relocate3D;
hxt: the HXT volume mesher); prints CPU s, nodes and quality (issue 49, session 32).
Usage: python notes/scripts/gmsh_passes.py PHANTOM VARIANT"""
import sys
import time

import gmsh
import numpy as np

from navapp.anatomy.meshing import _tidy, quality_report
from navapp.anatomy.phantom import make_phantom

liver = make_phantom(int(sys.argv[1])).liver
edge = 4.0; variant = sys.argv[2]
v = np.asarray(liver.vertices); f = np.asarray(liver.faces)
T = time.process_time
t0=T()
gmsh.initialize(interruptible=False)
gmsh.option.setNumber("General.Terminal", 0); gmsh.option.setNumber("General.NumThreads", 1)
gmsh.model.add("l"); s = gmsh.model.addDiscreteEntity(2)
gmsh.model.mesh.addNodes(2, s, np.arange(1, len(v)+1), v.ravel())
gmsh.model.mesh.addElementsByType(s, 2, [], (f+1).ravel())
gmsh.model.mesh.classifySurfaces(np.radians(40), True, True, np.pi)
gmsh.model.mesh.createGeometry()
loop = gmsh.model.geo.addSurfaceLoop([t for _, t in gmsh.model.getEntities(2)]); gmsh.model.geo.addVolume([loop]); gmsh.model.geo.synchronize()
a3 = 10 if "hxt" in variant else 1
for k, val in [("Mesh.MeshSizeMin", edge), ("Mesh.MeshSizeMax", edge), ("Mesh.MeshSizeFromCurvature", 0), ("Mesh.MeshSizeExtendFromBoundary", 0), ("Mesh.Algorithm", 6), ("Mesh.Algorithm3D", a3), ("Mesh.Optimize", 1), ("Mesh.OptimizeNetgen", 1 if "netgen" in variant else 0)]:
    gmsh.option.setNumber(k, val)
if "thr" in variant: gmsh.option.setNumber("Mesh.OptimizeThreshold", 0.5)
t=T(); gmsh.model.mesh.generate(3); g=T()-t
if "reloc" in variant: gmsh.model.mesh.optimize("Relocate3D")
if "lap" in variant: gmsh.model.mesh.optimize("Laplace2D")
def q(tag):
    tags, coords, _ = gmsh.model.mesh.getNodes(); et, _, en = gmsh.model.mesh.getElements(3)
    tt = np.asarray(en[list(et).index(4)], np.int64).reshape(-1, 4)
    idx = np.full(int(tags.max())+1, -1, np.int64); idx[tags.astype(np.int64)] = np.arange(len(tags))
    m = _tidy(coords.reshape(-1,3), idx[tt]); r = quality_report(m)
    print(tag, "cpu", round(T()-t0,2), "gen", round(g,2), r["nodes"], r["elements"], "min dih", round(r["min_dihedral_deg"],2), "below5", r["tets_below_5deg"], "meanRR", round(r["mean_radius_ratio"],4), "minRR", round(r["min_radius_ratio"],4), "meanedge", round(r["mean_edge_mm"],3))
q(variant)
