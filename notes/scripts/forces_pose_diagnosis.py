"""Issue 47, session 43: is the surface forces' answer wrong in its pose or its deformation, and
is the forces' objective Φ lower at the truth-like pose than where the fit stops? The truth (the
tracker offset, the TRE) is read here only, never by the solver.

    python notes/scripts/forces_pose_diagnosis.py CASE_DIR [S|S+all]

Prints the undeclared guarded LIBR's TRE and pose error ("pose-off": mean over the mesh nodes of
|rigid part x − true offset x|, mm), the libr-forces registration's choice, and the forces at the
chosen λ fitted (a) as the pipeline does, (b) with the pose free from q = 0, from the undeclared
answer's pose and from the truth's (``fit_weights(q0=)``), (c) with the pose held at those poses;
Φ is the whole objective (data + energy + the prior's term, the term added for held poses), then
the held-out RMS of the forces with the pose held at each (the choice's own folds)."""
import sys, json, warnings
from dataclasses import replace
from pathlib import Path
import numpy as np
from navapp.anatomy.caseio import read_case
from navapp.geometry.interpolation import interpolation_matrix
from navapp.geometry.tre import tre_stats
from navapp.evaluation.loads import declared_prior, declared_supports, _init
from navapp.registration.pipeline import prepare, register
from navapp.registration.forces import SurfaceForces, surface_points, ForceOptions, PoseTerm, Answer
from navapp.registration.rigid import RigidResult, after, beta_pose, pose_params
from navapp.simulation.levels import data_level
warnings.simplefilter("ignore")

case_dir = Path(sys.argv[1]); level = sys.argv[2] if len(sys.argv) > 2 else "S"
case = read_case(case_dir)
model, _ = prepare(case)
sup = prepare(case, **declared_supports(case))[0]
x0, x1 = case.need_truth().tre_points(model.basis.nodes)
B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
data = data_level(case_dir, "S", case=case) if level == "S" else case.intraop
prior = declared_prior(case_dir, case)
rep = json.loads((case_dir / "truth" / "report.json").read_text())
T = np.array(rep.get("tracker_offset", np.eye(4)))
Ttrue = RigidResult(T[:3, :3], T[:3, 3], 0, 0.0)
c = sup.centroid
nodes = sup.basis.nodes

def posed(r):  # mean over nodes of |r x - Ttrue x|
    return float(np.linalg.norm(r.apply(nodes) - Ttrue.apply(nodes), axis=1).mean())

def tre(pred): return tre_stats(pred, x1).mean_mm

libr = register(model, data, deform=True, init=_init("libr"))
reg = register(sup, data, deform=True, init=_init("libr-forces"), pose_prior=prior, surface_forces=True, undeclared=model)
pose_l = after(libr.rigid, beta_pose(libr.libr.beta, model.centroid)) if libr.deformed else libr.rigid
fc = reg.forces
print(f"{case_dir.name} {level}: libr TRE {tre(libr.transform(x0, B=B)):.2f} pose-off {posed(pose_l):.2f}; "
      f"forces-reg TRE {tre(reg.transform(x0, B=B)):.2f} answer {fc.answer.value} none {fc.none_mm:.3f} "
      f"basis {fc.basis_mm} forces {fc.forces_mm} free {fc.free_mm} lam {fc.energy_weight}")
print("  rigid stage pose-off", round(posed(reg.rigid), 2), " kept_given",
      None if fc.pose_evidence is None else fc.pose_evidence.kept_given)
pose_b = after(reg.rigid, beta_pose(reg.libr.beta, sup.centroid))
print("  basis answer pose-off", round(posed(pose_b), 2), "TRE", round(tre(reg.transform(x0, beta=reg.libr.beta, B=B)), 2))
q_ans = fc.pose
print("  forces pose-off", round(posed(after(reg.rigid, beta_pose(np.r_[q_ans], c))), 2))
inv = RigidResult(reg.rigid.R.T, -reg.rigid.R.T @ reg.rigid.t, 0, 0.0)
q_l = pose_params(after(inv, pose_l), c)
q_t = pose_params(after(inv, Ttrue), c)
sf = SurfaceForces(sup.basis)
local = reg.data_model_frame
pts = surface_points(local)
o = replace(ForceOptions(), energy_weight=fc.energy_weight)
pf = sf.responses(pts, o.sites)
term = PoseTerm.of(reg.pose_prior, sup.centroid)
def report(name, wf, held=False):
    u = sf.field(pf, wf)
    moved = x0 + B @ u
    r = after(reg.rigid, beta_pose(wf.q, c))
    phi = wf.phi + (term.value(wf.q) if held else 0.0)
    print(f"  {name:28s} Φ {phi:.4f} prior term {term.value(wf.q):.4f} rms {wf.rms_mm:.3f} pose-off {posed(r):.2f} TRE {tre(r.apply(moved)):.2f} "
          f"|τ| {np.linalg.norm(wf.q[:3]):.1f} θ° {np.degrees(np.linalg.norm(wf.q[3:])):.1f}")
lam = fc.energy_weight
kept = fc.pose_evidence.kept_given
report("answer (refit as pipeline)", sf.fit_weights(pf, lam, None, o, term, held_q=fc.pose if kept else None), kept)
report("free from q=0", sf.fit_weights(pf, lam, None, o, term))
report("free from libr pose", sf.fit_weights(pf, lam, None, o, term, q0=q_l))
report("held at libr pose", sf.fit_weights(pf, lam, None, o, term, held_q=q_l), True)
report("free from truth pose", sf.fit_weights(pf, lam, None, o, term, q0=q_t))
report("held at truth pose", sf.fit_weights(pf, lam, None, o, term, held_q=q_t), True)
report("held at given pose", sf.fit_weights(pf, lam, None, o, term, held_q=term.centre), True)
print("  prior centre", np.round(term.centre, 3), "sd", np.round(term.sd, 3), "weight", term.weight)
print("  q_libr", np.round(q_l, 3), " q_truth", np.round(q_t, 3))
# held-out: the forces with the pose held at q (fitted per fold), scored as choose_deformation does
from navapp.registration.support import blocks_of
from navapp.registration.forces import _posed_surface
labels = blocks_of({"surface": pts}, o.blocks)["surface"]
folds = [(np.flatnonzero(labels == b), np.flatnonzero(labels != b)) for b in range(o.blocks)]
folds = [(h, t) for h, t in folds if len(h) and len(h) < len(pts)]
counts = np.array([len(h) for h, _ in folds])
def heldout(q, lam2):
    o2 = replace(o, energy_weight=lam2); out = []
    for h, t in folds:
        fw = sf.fit_weights(pf, lam2, t, o2, term, held_q=q)
        us = _posed_surface(sf, pf.Xs[:, fw.index] @ fw.w, fw.q, term)
        out.append(np.sqrt(np.mean(sf.distances(pts[h], us)[0] ** 2)))
    return float(np.average(out, weights=counts))
qa = fc.pose
for lam2 in (0.1, 1.0, 10.0):
    print(f"  held-out λ={lam2}: at answer pose {heldout(qa, lam2):.3f}  at libr pose {heldout(q_l, lam2):.3f}  at truth pose {heldout(q_t, lam2):.3f}  at rigid stage {heldout(np.zeros(6), lam2):.3f}")
