"""python precompute49_s40_var.py SURFACE.npz ANGLE VARIANT [THREADS]: one Gmsh run, CPU/wall + quality."""
import sys, time, json, resource, numpy as np
import gmsh
surf, angle, variant = sys.argv[1], float(sys.argv[2]), sys.argv[3]
threads = int(sys.argv[4]) if len(sys.argv) > 4 else 1
edge = 4.0
with np.load(surf) as a: v, f = a["vertices"], a["faces"]
c0, t0 = time.process_time(), time.perf_counter()
gmsh.initialize(interruptible=False)
gmsh.option.setNumber("General.Terminal", 0)
gmsh.option.setNumber("General.NumThreads", threads)
gmsh.option.setNumber("Mesh.RandomSeed", 0)
gmsh.model.add("liver")
s = gmsh.model.addDiscreteEntity(2)
gmsh.model.mesh.addNodes(2, s, np.arange(1, len(v) + 1), np.asarray(v, float).ravel())
gmsh.model.mesh.addElementsByType(s, 2, [], (np.asarray(f) + 1).ravel())
gmsh.model.mesh.classifySurfaces(np.radians(angle), True, True, np.pi)
gmsh.model.mesh.createGeometry()
surfaces = [t for _, t in gmsh.model.getEntities(2)]
loop = gmsh.model.geo.addSurfaceLoop(surfaces)
gmsh.model.geo.addVolume([loop])
gmsh.model.geo.synchronize()
for k_, val in [("Mesh.MeshSizeMin", edge), ("Mesh.MeshSizeMax", edge), ("Mesh.MeshSizeFromCurvature", 0),
                ("Mesh.MeshSizeExtendFromBoundary", 0), ("Mesh.Algorithm", 6), ("Mesh.Algorithm3D", 10 if variant.startswith("hxt") else 1),
                ("Mesh.Optimize", 1), ("Mesh.OptimizeNetgen", 1 if variant == "netgen" else 0)]:
    gmsh.option.setNumber(k_, val)
if variant == "thr":
    gmsh.option.setNumber("Mesh.OptimizeThreshold", 0.5)
stage = {}
t = time.perf_counter(); c = time.process_time()
gmsh.model.mesh.generate(2); stage["surf"] = (round(time.process_time()-c,2), round(time.perf_counter()-t,2))
t = time.perf_counter(); c = time.process_time()
gmsh.model.mesh.generate(3); stage["vol"] = (round(time.process_time()-c,2), round(time.perf_counter()-t,2))
tags, coords, _ = gmsh.model.mesh.getNodes()
etypes, _, enodes = gmsh.model.mesh.getElements(3)
gmsh.finalize()
cpu, wall = time.process_time() - c0, time.perf_counter() - t0
tet_tags = np.asarray(enodes[list(etypes).index(4)], np.int64).reshape(-1, 4)
index = np.full(int(tags.max()) + 1, -1, np.int64); index[tags.astype(np.int64)] = np.arange(len(tags))
from navapp.anatomy.meshing import _tidy, quality_report
m = _tidy(coords.reshape(-1, 3), index[tet_tags]); q = quality_report(m)
print(json.dumps({"surf": surf, "angle": angle, "variant": variant, "threads": threads, "cpu": round(cpu, 2), "wall": round(wall, 2), "stage": stage,
                  "nodes": q["nodes"], "min_dih": round(q["min_dihedral_deg"], 2), "below5": q["tets_below_5deg"], "inv": q["inverted"], "mean_rr": round(q["mean_radius_ratio"], 3), "min_rr": round(q["min_radius_ratio"],3), "hash": __import__("hashlib").md5(m.nodes.tobytes()+m.tets.tobytes()).hexdigest()[:8]}))
