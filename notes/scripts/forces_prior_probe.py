"""Issue 47, session 43: the forces' objective split into data + energy and the pose prior's term,
at the pose the joint fit reaches and at the truth's pose held, per λ; and where the joint fit
lands with the prior's weight 1000× smaller (a near-flat prior). The truth is read only here.

    python notes/scripts/forces_prior_probe.py CASE_DIR..."""
import sys, json, warnings
from dataclasses import replace
from pathlib import Path
import numpy as np
from navapp.anatomy.caseio import read_case
from navapp.geometry.interpolation import interpolation_matrix
from navapp.geometry.tre import tre_stats
from navapp.evaluation.loads import declared_prior, declared_supports, _init
from navapp.registration.pipeline import prepare, register
from navapp.registration.forces import SurfaceForces, surface_points, ForceOptions, PoseTerm
from navapp.registration.rigid import RigidResult, after, beta_pose, pose_params
from navapp.simulation.levels import data_level
warnings.simplefilter("ignore")
for cd in sys.argv[1:]:
    case_dir = Path(cd); case = read_case(case_dir)
    sup = prepare(case, **declared_supports(case))[0]
    x0, x1 = case.need_truth().tre_points(sup.basis.nodes)
    B = interpolation_matrix(sup.basis.nodes, sup.basis.tets, x0)
    data = data_level(case_dir, "S", case=case)
    prior = declared_prior(case_dir, case)
    reg = register(sup, data, deform=True, init=_init("libr-forces"), pose_prior=prior, surface_forces=True,
                   undeclared=prepare(case)[0])
    rep = json.loads((case_dir / "truth" / "report.json").read_text())
    T = np.array(rep.get("tracker_offset", np.eye(4)))
    inv = RigidResult(reg.rigid.R.T, -reg.rigid.R.T @ reg.rigid.t, 0, 0.0)
    c = sup.centroid
    q_t = pose_params(after(inv, RigidResult(T[:3, :3], T[:3, 3], 0, 0.0)), c)
    sf = SurfaceForces(sup.basis); pts = surface_points(reg.data_model_frame)
    pf = sf.responses(pts, ForceOptions().sites)
    term = PoseTerm.of(reg.pose_prior, c)
    flat = replace(term, weight=term.weight * 1e-3)
    nodes = sup.basis.nodes
    Tt = RigidResult(T[:3, :3], T[:3, 3], 0, 0.0)
    def tre(wf):
        u = sf.field(pf, wf); r = after(reg.rigid, beta_pose(wf.q, c))
        return tre_stats(r.apply(x0 + B @ u), x1).mean_mm, float(np.linalg.norm(r.apply(nodes) - Tt.apply(nodes), axis=1).mean())
    print(case_dir.name, "chosen λ", reg.forces.energy_weight)
    for lam in (0.01, 0.1, 1.0, 10.0):
        o = replace(ForceOptions(), energy_weight=lam)
        a = sf.fit_weights(pf, lam, None, o, term)
        t = sf.fit_weights(pf, lam, None, o, term, held_q=q_t)
        f = sf.fit_weights(pf, lam, None, o, flat)
        print(f"  λ={lam:<5} fit: data+energy {a.phi - term.value(a.q):.3f} prior {term.value(a.q):.3f} TRE/pose-off {tre(a)[0]:.2f}/{tre(a)[1]:.2f} | "
              f"truth pose: data+energy {t.phi:.3f} prior {term.value(q_t):.3f} TRE {tre(t)[0]:.2f} | "
              f"prior/1000: data+energy {f.phi - flat.value(f.q):.3f} TRE/pose-off {tre(f)[0]:.2f}/{tre(f)[1]:.2f}", flush=True)
    sf.close()
