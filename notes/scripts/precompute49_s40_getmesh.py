"""python precompute49_s40_getmesh.py SURFACE.npz OUT.npz: the planned mesh of a surface at 4 mm (cached under /tmp/s49c/cache), saved as nodes and tets."""
import sys, numpy as np, trimesh
from pathlib import Path
from navapp.anatomy.meshing import cached_tetmesh
with np.load(sys.argv[1]) as a: s = trimesh.Trimesh(a["vertices"], a["faces"], process=False)
m, r = cached_tetmesh(s, 4.0, Path("/tmp/s49c/cache"))
np.savez(sys.argv[2], nodes=m.nodes, tets=m.tets); print(r["nodes"], r["method"], r["seconds"])
