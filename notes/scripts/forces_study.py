"""Issue 47: surface forces (``register(surface_forces=True)``, the loads study's ``libr-forces``)
at S on local-load cases, supports and pose declared as the scene made them.

    python notes/scripts/forces_study.py OUT.jsonl CASE_DIR...

One JSON line per case: mean TRE (mm) of no correction (identity), of the three candidates
(the declared rigid pose without deformation, the supported basis's LIBR fit, the surface
forces at their held-out λ), of the answer shown, the held-out RMS of each, and seconds.
With NAVAPP_FORCES_BY_LAMBDA=1 also the forces fitted to all the data at every λ
(``forces_by_lambda``: a second factorisation, outside ``seconds_total``), from which the
answer of another rule for λ can be read off the same run."""
import json
import os
import sys
import time
import warnings
from pathlib import Path

from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import declared_prior, declared_supports
from navapp.geometry.interpolation import interpolation_matrix
from navapp.geometry.tre import mean_tre
from navapp.registration.forces import ENERGY_WEIGHTS, SurfaceForces, surface_points
from navapp.registration.pipeline import prepare, register
from navapp.registration.rigid import beta_pose
from navapp.simulation.levels import data_level

out = Path(sys.argv[1])
for arg in sys.argv[2:]:
    case_dir = Path(arg)
    case = read_case(case_dir)
    model, _ = prepare(case, **declared_supports(case))
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
    data = data_level(case_dir, "S", case=case)
    t = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        reg = register(model, data, pose_prior=declared_prior(case_dir, case), surface_forces=True)
    sec = time.perf_counter() - t
    fc = reg.forces

    def forces_at(p, fc=fc, reg=reg, model=model, B=B):
        moved = p + B @ fc.u
        if fc.pose is not None:  # the forces' own rigid part (session 37)
            moved = beta_pose(fc.pose, model.centroid).apply(moved)
        return reg.rigid.apply(moved)

    def tre(p, x1=x1):
        return round(mean_tre(p, x1), 3)

    row = {"case": case_dir.name, "identity": tre(x0), "none": tre(reg.rigid.apply(x0)),
           "basis": tre(reg.transform(x0, beta=reg.libr.beta, B=B)),
           "forces": tre(forces_at(x0)), "shown": tre(reg.transform(x0, B=B)),
           "answer": fc.answer.value, "warned": bool(reg.warnings), **fc.as_dict(),
           "fit_iterations": fc.fit.iterations, "fit_rms_mm": round(fc.fit.rms_mm, 3), "seconds_total": round(sec, 1),
           "stage_seconds": {k: round(v, 1) for k, v in reg.seconds.items()}}
    if os.environ.get("NAVAPP_FORCES_BY_LAMBDA") == "1":
        sf = SurfaceForces(model.basis)
        pf = sf.responses(surface_points(reg.data_model_frame))
        row["forces_by_lambda"] = {f"{lam:g}": tre(reg.rigid.apply(x0 + B @ sf.field(pf, sf.fit_weights(pf, lam))))
                                   for lam in ENERGY_WEIGHTS}
        sf.close()
    with out.open("a") as fh:
        fh.write(json.dumps(row) + "\n")
    print(json.dumps(row), flush=True)
