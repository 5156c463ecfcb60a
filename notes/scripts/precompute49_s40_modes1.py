"""python precompute49_s40_modes1.py MESH.npz ORDER...: point_load_modes on MKL's default threads (d) or one (1), alternated; wall, CPU."""
import sys, time, json, os, numpy as np
from contextlib import nullcontext
from navapp.anatomy.tets import TetMesh
from navapp.mechanics import basis as B
from navapp.mechanics.sparse import one_mkl_thread
from navapp.mechanics.fem import stiffness, Material
from navapp.mechanics.controlpoints import place_control_points
with np.load(sys.argv[1]) as a: mesh = TetMesh(a["nodes"], a["tets"])
surface = np.unique(mesh.boundary_faces())
K = stiffness(mesh.nodes, mesh.tets, Material()); control = place_control_points(mesh.nodes, surface, 45, 0)
ref = {}
for w in sys.argv[2:]:
    c, t = time.process_time(), time.perf_counter()
    with one_mkl_thread() if w == "1" else nullcontext():
        U, R = B.point_load_modes(K, control, 5.0)
    row = {"mkl": w, "wall": round(time.perf_counter() - t, 2), "cpu": round(time.process_time() - c, 2), "load": round(os.getloadavg()[0], 1)}
    ref.setdefault(w, U)
    if len(ref) == 2: row["max_rel_diff"] = float(np.abs(ref["1"] - ref["d"]).max() / np.abs(ref["d"]).max())
    print(json.dumps(row), flush=True)
