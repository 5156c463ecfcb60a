"""python one.py SURFACE.npz EDGE: mesh + basis of the surface in a fresh cache (whichever navapp is on PYTHONPATH)."""
import json, sys, tempfile, time, shutil
import numpy as np, trimesh
from pathlib import Path
from navapp import progress
progress.QUIET = True
from navapp.anatomy.meshing import cached_tetmesh
from navapp.mechanics.basis import BasisSettings, load_or_compute_basis
with np.load(sys.argv[1]) as f:
    liver = trimesh.Trimesh(f["vertices"], f["faces"], process=False)
root = Path(tempfile.mkdtemp(prefix="navapp-p49b-"))
t0 = time.perf_counter(); c0 = time.process_time()
mesh, rep = cached_tetmesh(liver, float(sys.argv[2]), root)
basis, _ = load_or_compute_basis(mesh, BasisSettings(), cache_root=root)
out = {"nodes": basis.M, "why": rep["mesher"]["why"], "mesh_s": rep["seconds"], "basis": {k: round(v, 2) for k, v in basis.timings.items()},
       "total_s": round(time.perf_counter() - t0, 2), "cpu_in_process": round(time.process_time() - c0, 2),
       "Ju0": float(basis.Ju[:, 0] @ basis.Ju[:, 0]), "mesh_md5": __import__("hashlib").md5(mesh.nodes.tobytes() + mesh.tets.tobytes()).hexdigest()[:10], "Ju_md5": __import__("hashlib").md5(basis.Ju.tobytes()).hexdigest()[:10]}
shutil.rmtree(root)
print(json.dumps(out))
