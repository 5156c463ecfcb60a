"""python precompute49_s40_chain.py SURFACE.npz [EDGE]: the planned chain on a surface, its log."""
import sys, json, numpy as np, trimesh
from navapp.anatomy.meshing import mesh_liver, plan_mesh
with np.load(sys.argv[1]) as a: s = trimesh.Trimesh(a["vertices"], a["faces"], process=False)
edge = float(sys.argv[2]) if len(sys.argv) > 2 else 4.0
plan = plan_mesh(s, edge)
m, r = mesh_liver(s, edge, plan=plan)
print(json.dumps({"surf": sys.argv[1], "plan": plan.key(), "why": r["mesher"]["why"], "attempts": r["attempts"], "nodes": r["nodes"], "min_dih": round(r["min_dihedral_deg"], 2)}))
