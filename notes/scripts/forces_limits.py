"""Issue 47, session 34: what limits the surface-forces answer on a local-load case at S.

    python notes/scripts/forces_limits.py OUT.jsonl CASE_DIR...

For each case (supports and pose declared as the scene made them, as ``libr-forces``), one
JSON line of whole-organ mean TRE (mm) of the forces fitted to all the surface data:
- ``lam``: at each λ of ``forces.ENERGY_WEIGHTS`` (which λ would have been best);
- ``tight``: at each λ with the stopping rule tightened (tol 1e-6, 100 iterations);
- ``true_pose``: the data taken to the model frame by the true pose instead of the fitted one;
- ``dense``: noise-free points of the true deformed surface spread over the whole unheld
  surface (as many as the scan has), fitted at each λ, the true pose: what the supported
  linear model can express when the data span the organ;
- ``supports``: the true displacement at the nodes the model holds (mm; 0 if the truth held
  the same part) and at the truth's own held nodes' nearest model nodes.
"""
import json
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

from navapp.anatomy.caseio import read_case
from navapp.anatomy.tets import TetMesh
from navapp.evaluation.loads import declared_prior, declared_supports
from navapp.geometry.transforms import apply
from navapp.geometry.tre import mean_tre
from navapp.mechanics.supports import held_nodes
from navapp.registration.forces import ENERGY_WEIGHTS, ForceOptions, SurfaceForces, spread_sites, surface_points
from navapp.registration.pipeline import prepare, register
from navapp.simulation.levels import data_level


def run(case_dir: Path) -> dict:
    case = read_case(case_dir)
    sup = declared_supports(case)
    model, _ = prepare(case, **sup)
    truth = case.need_truth()
    x0, x1 = truth.tre_points(model.basis.nodes)
    data = data_level(case_dir, "S", case=case)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        reg = register(model, data, pose_prior=declared_prior(case_dir, case))
    sf = SurfaceForces(model.basis)

    def tre_u(u, pose):
        return round(mean_tre(pose(x0 + u), x1), 3)

    def fits(points, pose, options=None):
        options = options or ForceOptions()
        pf = sf.responses(points, options.sites)
        res = {}
        for lam in ENERGY_WEIGHTS:
            wf = sf.fit_weights(pf, lam, None, replace(options, energy_weight=lam))
            res[f"{lam:g}"] = [tre_u(sf.field(pf, wf), pose), round(wf.rms_mm, 3), wf.iterations]
        return res

    T = np.asarray(truth.offset, float)

    def true_pose(x):
        return apply(T, x)

    pts = surface_points(reg.data_model_frame)
    row = {"case": case_dir.name, "supports": sup["supports"], "points": len(pts),
           "identity": round(mean_tre(x0, x1), 3),
           "rigid_fitted": round(mean_tre(reg.rigid.apply(x0), x1), 3),
           "pose_gap_mm": round(float(np.abs(reg.rigid.apply(x0) - true_pose(x0)).max()), 3)}
    row["lam"] = fits(pts, reg.rigid.apply)
    row["tight"] = fits(pts, reg.rigid.apply, ForceOptions(tol=1e-6, iterations=100))
    Tinv = np.linalg.inv(T)
    pts_true = surface_points({k: apply(Tinv, np.asarray(v, float)) for k, v in data.items()})
    row["true_pose"] = fits(pts_true, true_pose)
    mesh = TetMesh(model.basis.nodes, model.basis.tets)
    held = held_nodes(mesh, sup["supports"], sup["release"])
    free_surface = np.setdiff1d(model.basis.surface, held)
    xs = model.basis.nodes[free_surface]
    on = xs[spread_sites(xs, len(pts))]
    row["dense"] = fits(on + truth.displacement(on), true_pose)
    u_held = np.linalg.norm(truth.displacement(model.basis.nodes[held]), axis=1)
    t_held = np.flatnonzero(np.linalg.norm(truth.u, axis=1) == 0)
    row["supports_check"] = {"model_held": len(held), "true_u_at_model_held_max_mm": round(float(u_held.max()), 3),
                             "true_u_at_model_held_mean_mm": round(float(u_held.mean()), 3),
                             "truth_held": len(t_held)}
    sf.close()
    row["seconds"] = round(time.perf_counter() - t0, 1)
    return row


out = Path(sys.argv[1])
for arg in sys.argv[2:]:
    row = run(Path(arg))
    with out.open("a") as fh:
        fh.write(json.dumps(row) + "\n")
    print(json.dumps(row), flush=True)
