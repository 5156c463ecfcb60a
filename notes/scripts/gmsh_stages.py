"""Gmsh on phantom N at 4 mm, stage by stage (CPU s): classify, geometry, 1D/2D/3D, then
Gmsh's optimiser and Netgen's, with the tet quality after each (issue 49, session 32).
Usage: python notes/scripts/gmsh_stages.py PHANTOM ANGLE OPTIMISE NETGEN"""
import sys
import time

import gmsh
import numpy as np

from navapp.anatomy.meshing import _tidy, quality_report
from navapp.anatomy.phantom import make_phantom

liver = make_phantom(int(sys.argv[1]) if len(sys.argv)>1 else 0).liver
edge = 4.0; angle = float(sys.argv[2]) if len(sys.argv)>2 else 40.0
opt = int(sys.argv[3]) if len(sys.argv)>3 else 1; netgen = int(sys.argv[4]) if len(sys.argv)>4 else 1
v = np.asarray(liver.vertices); f = np.asarray(liver.faces)
print("faces", len(f))
T = time.process_time
gmsh.initialize(interruptible=False)
gmsh.option.setNumber("General.Terminal", 0); gmsh.option.setNumber("General.NumThreads", 1)
gmsh.model.add("l"); s = gmsh.model.addDiscreteEntity(2)
gmsh.model.mesh.addNodes(2, s, np.arange(1, len(v)+1), v.ravel())
gmsh.model.mesh.addElementsByType(s, 2, [], (f+1).ravel())
t=T(); gmsh.model.mesh.classifySurfaces(np.radians(angle), True, True, np.pi); print("classify", T()-t)
t=T(); gmsh.model.mesh.createGeometry(); print("createGeometry", T()-t, len(gmsh.model.getEntities(2)), "patches")
loop = gmsh.model.geo.addSurfaceLoop([t for _, t in gmsh.model.getEntities(2)]); gmsh.model.geo.addVolume([loop]); gmsh.model.geo.synchronize()
for k, val in [("Mesh.MeshSizeMin", edge), ("Mesh.MeshSizeMax", edge), ("Mesh.MeshSizeFromCurvature", 0), ("Mesh.MeshSizeExtendFromBoundary", 0), ("Mesh.Algorithm", 6), ("Mesh.Algorithm3D", 1), ("Mesh.Optimize", 0), ("Mesh.OptimizeNetgen", 0)]:
    gmsh.option.setNumber(k, val)
t=T(); gmsh.model.mesh.generate(1); print("1D", T()-t)
t=T(); gmsh.model.mesh.generate(2); print("2D", T()-t)
t=T(); gmsh.model.mesh.generate(3); print("3D", T()-t)
def q(tag):
    tags, coords, _ = gmsh.model.mesh.getNodes(); et, _, en = gmsh.model.mesh.getElements(3)
    tt = np.asarray(en[list(et).index(4)], np.int64).reshape(-1, 4)
    idx = np.full(int(tags.max())+1, -1, np.int64); idx[tags.astype(np.int64)] = np.arange(len(tags))
    m = _tidy(coords.reshape(-1,3), idx[tt]); r = quality_report(m)
    print(tag, r["nodes"], r["elements"], "min dih", round(r["min_dihedral_deg"],2), "below5", r["tets_below_5deg"], "meanRR", round(r["mean_radius_ratio"],4), "minRR", round(r["min_radius_ratio"],4))
q("raw")
if opt:
    t=T(); gmsh.model.mesh.optimize(""); print("optimize", T()-t); q("opt")
if netgen:
    t=T(); gmsh.model.mesh.optimize("Netgen"); print("netgen", T()-t); q("netgen")
