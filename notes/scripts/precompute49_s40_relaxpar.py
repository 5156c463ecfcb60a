"""python precompute49_s40_relaxpar.py MESH.npz ORDER...: relax_modes alone with 1 or 2 workers, alternated; wall, CPU."""
import sys, time, json, numpy as np, os
from navapp import progress
progress.QUIET = True
from navapp.anatomy.tets import TetMesh
from navapp.mechanics import basis as B
from navapp.mechanics.fem import stiffness, Material
from navapp.mechanics.controlpoints import geodesic_tiles, nodal_areas, place_control_points
with np.load(sys.argv[1]) as a: mesh = TetMesh(a["nodes"], a["tets"])
faces = mesh.boundary_faces(); surface = np.unique(faces)
K = stiffness(mesh.nodes, mesh.tets, Material())
control = place_control_points(mesh.nodes, surface, 45, 0)
tiles = geodesic_tiles(mesh.nodes, faces, surface, control); areas = nodal_areas(mesh.nodes, faces, surface)
U, R = B.point_load_modes(K, control, 5.0, np.zeros(0, int))
ref = {}
for w in map(int, sys.argv[2:]):
    c, t = time.process_time(), time.perf_counter()
    Ju = B.relax_modes(K, U, R, control, surface, tiles, areas, layers=6, held=np.zeros(0, int), workers=w)
    row = {"workers": w, "wall": round(time.perf_counter() - t, 2), "cpu": round(time.process_time() - c, 2), "load": os.getloadavg()[0]}
    if w in ref: row["same_bits_as_before"] = bool(np.array_equal(ref[w], Ju))
    ref.setdefault(w, Ju)
    if len(ref) == 2: row["1v2_max_diff"] = float(np.abs(ref[1] - ref[2]).max())
    print(json.dumps(row), flush=True)
