"""The laparoscopic reference deformation, linear against neo-Hookean: one JSON line per release.

    python notes/scripts/lap_reference_nh.py [--E PA] [--pressure PA] [--tilt DEG] [--head-up DEG]

Reference phantom 3 at the lap scenes' mesh edge, loads as navapp/scenes/lap0-{L,N,R}.toml
declare them (each overridable, for calibration); prints per release the neo-Hookean
solve's load increments, Newton iterations and seconds, its range of J = det F, and the
mean / max of |u| (both models) and of |u_NH − u_lin| (mm), over the reference nodes.
"""

import argparse
import dataclasses
import json
import time

import numpy as np

from navapp import progress
from navapp.anatomy.meshing import cached_tetmesh
from navapp.anatomy.phantom import make_phantom
from navapp.simulation.scene import load_scene, study_scenes
from navapp.simulation.simulate import scene_loading
from navapp.simulation.truth import NeoHookean, solve_linear, solve_neo_hookean

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("--E", type=float, help="Young's modulus, Pa (default: the scene's)")
ap.add_argument("--pressure", type=float, help="anterior pressure, Pa")
ap.add_argument("--tilt", type=float, help="gravity tilt toward the released side, degrees")
ap.add_argument("--head-up", type=float, help="head-up tilt, degrees")
ap.add_argument("--releases", default="LNR")
args = ap.parse_args()
progress.QUIET = True
scenes = {load_scene(p).release: load_scene(p) for p in study_scenes("lap") if p.stem.startswith("lap0")}
for rel in args.releases:
    sc = scenes[rel]
    over = {"truth_E_pa": args.E, "pressure_pa": args.pressure, "gravity_tilt_deg": args.tilt,
            "head_up_deg": args.head_up}
    sc = dataclasses.replace(sc, **{k: v for k, v in over.items() if v is not None})
    loading, material = scene_loading(sc)
    mesh, _ = cached_tetmesh(make_phantom(sc.transpose_from.phantom).liver, sc.transpose_from.mesh_edge_mm)
    t0 = time.perf_counter()
    lin = solve_linear(mesh, loading, material)
    t_lin = time.perf_counter() - t0
    log = []
    t0 = time.perf_counter()
    nh = solve_neo_hookean(mesh, loading, material, report=lambda t, i, r, log=log: log.append((t, i, r)))
    t_nh = time.perf_counter() - t0
    increments = sorted({t for t, _, _ in log})
    converged = sorted({t for t, _, r in log if r < 1e-8})
    J = np.linalg.det(NeoHookean(mesh.nodes, mesh.tets, material).deformation_gradient(nh))

    def stats(v):
        d = np.linalg.norm(v, axis=1)
        return {"mean": round(float(d.mean()), 2), "max": round(float(d.max()), 2)}

    print(json.dumps({
        "release": rel, "E_pa": sc.truth_E_pa, "pressure_pa": sc.pressure_pa, "tilt_deg": sc.gravity_tilt_deg,
        "head_up_deg": sc.head_up_deg, "nodes": len(mesh.nodes), "tets": len(mesh.tets),
        "increments_tried": len(increments), "converged_loads": [round(t, 4) for t in converged],
        "newton_iterations": len(log), "seconds_nh": round(t_nh, 1), "seconds_linear": round(t_lin, 1),
        "J": [round(float(J.min()), 3), round(float(J.max()), 3)],
        "u_linear_mm": stats(lin), "u_nh_mm": stats(nh), "u_nh_minus_linear_mm": stats(nh - lin)}), flush=True)
