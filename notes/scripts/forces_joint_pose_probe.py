"""Issue 47, session 37: the surface forces with the declared pose fitted alongside them.

    python notes/scripts/forces_joint_pose_probe.py OUT.jsonl CASE_DIR...

Per case at S (supports and pose declared as the scene made them, as ``libr-forces``): the
whole-organ mean TRE (mm) of the forces fitted to all the surface data at every λ, deformed from
the rigid stage's pose (``fit_weights`` without ``pose``) and with the rigid part of eq. 8 fitted
with them under the declared prior (``pose=PoseTerm``), and the pose's own TRE in each."""
import json
import sys
import warnings
from pathlib import Path

from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import declared_prior, declared_supports
from navapp.geometry.interpolation import interpolation_matrix
from navapp.geometry.tre import mean_tre
from navapp.registration.forces import ENERGY_WEIGHTS, PoseTerm, SurfaceForces, surface_points
from navapp.registration.pipeline import prepare, register
from navapp.registration.rigid import after, beta_pose
from navapp.simulation.levels import data_level


def run(case_dir: Path, level: str) -> dict:
    case = read_case(case_dir)
    model, _ = prepare(case, **declared_supports(case))
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
    data = data_level(case_dir, level, case=case)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        reg = register(model, data, pose_prior=declared_prior(case_dir, case))
    row = {"case": case_dir.name, "level": level, "identity": round(mean_tre(x0, x1), 3),
           "rigid": round(mean_tre(reg.rigid.apply(x0), x1), 3)}
    sf = SurfaceForces(model.basis)
    pts = surface_points({k: reg.rigid.inverse(p) for k, p in data.items()})
    pf = sf.responses(pts)
    term = PoseTerm.of(reg.pose_prior, model.centroid)
    for name, pose in (("forces", None), ("forces_pose", term)):
        row[name] = {}
        for lam in ENERGY_WEIGHTS:
            wf = sf.fit_weights(pf, lam, pose=pose)
            whole = reg.rigid if wf.q is None else after(reg.rigid, beta_pose(wf.q, model.centroid))
            row[name][f"{lam:g}"] = [round(mean_tre(whole.apply(x0 + B @ sf.field(pf, wf)), x1), 3),
                                     round(mean_tre(whole.apply(x0), x1), 3), round(wf.rms_mm, 3)]
    sf.close()
    return row


out = Path(sys.argv[1])
level = "S"
for arg in sys.argv[2:]:
    if arg.startswith("--level="):
        level = arg.split("=", 1)[1]
        continue
    row = run(Path(arg), level)
    with out.open("a") as fh:
        fh.write(json.dumps(row) + "\n")
    print(json.dumps(row), flush=True)
