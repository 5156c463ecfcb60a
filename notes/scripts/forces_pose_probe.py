"""Issue 47, session 34: do the surface forces lose the tracker offset that the basis corrects?

    python notes/scripts/forces_pose_probe.py OUT.jsonl CASE_DIR...

``libr-forces`` deforms from the rigid stage's pose; the basis's answer carries its own rigid
part (τ, θ of β, eq. 8) on top. Per case (supports and pose declared as the scene made them),
whole-organ mean TRE (mm) of the rigid stage's pose alone, of that pose with the basis fit's
rigid part (``rigid.beta_pose``), and of the forces fitted to all the surface data at every
λ in each of the two frames."""
import json
import sys
import warnings
from pathlib import Path

from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import declared_prior, declared_supports
from navapp.geometry.interpolation import interpolation_matrix
from navapp.geometry.tre import mean_tre
from navapp.registration.forces import ENERGY_WEIGHTS, SurfaceForces, surface_points
from navapp.registration.pipeline import prepare, register
from navapp.registration.rigid import after, beta_pose
from navapp.simulation.levels import data_level


def run(case_dir: Path) -> dict:
    case = read_case(case_dir)
    model, _ = prepare(case, **declared_supports(case))
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
    data = data_level(case_dir, "S", case=case)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        reg = register(model, data, pose_prior=declared_prior(case_dir, case))
    whole = after(reg.rigid, beta_pose(reg.libr.beta, model.centroid))
    row = {"case": case_dir.name, "identity": round(mean_tre(x0, x1), 3),
           "rigid": round(mean_tre(reg.rigid.apply(x0), x1), 3),
           "rigid_with_basis_pose": round(mean_tre(whole.apply(x0), x1), 3),
           "basis": round(mean_tre(reg.transform(x0, beta=reg.libr.beta, B=B), x1), 3)}
    sf = SurfaceForces(model.basis)
    for name, pose in (("forces_at_rigid", reg.rigid), ("forces_at_basis_pose", whole)):
        pts = surface_points({k: pose.inverse(p) for k, p in data.items()})
        pf = sf.responses(pts)
        row[name] = {f"{lam:g}": round(mean_tre(pose.apply(x0 + B @ sf.field(pf, sf.fit_weights(pf, lam))),
                                                 x1), 3) for lam in ENERGY_WEIGHTS}
    sf.close()
    return row


out = Path(sys.argv[1])
for arg in sys.argv[2:]:
    row = run(Path(arg))
    with out.open("a") as fh:
        fh.write(json.dumps(row) + "\n")
    print(json.dumps(row), flush=True)
