"""Issue 47, session 42: what the surface forces' held-out choice saw, per case and level.

    python notes/scripts/forces_choice_probe.py OUT.jsonl LEVEL CASE_DIR...

LEVEL: S or S+all (``evaluation.loads``' levels). Per case, the registration ``libr-forces``
makes (supports and pose declared as the scene made them, the free-floating model as the
supports' check) and, from the same run: the TRE of each candidate (no deformation at the rigid
stage's pose, the held basis's fit, the forces fitted to every block at each λ — with the pose as
the choice fitted or held it), the held-out RMS of each (blocks' point-weighted mean, and per
block), the free-floating basis's held-out RMS, the λ the one-standard-error rule took, the
forces' pose evidence, the answer shown and its warnings; and the undeclared registration's TRE
on the same data (``libr-declared``). ``forces_by_lambda``' "λ held" key: the answer's fit at the
given pose (only the chosen λ's; a λ whose pose is not told apart is scored held, but its TRE here
is the fitted pose's). Session 42's run, on the code before its changes: notes/forces_choice_nh_s42.jsonl."""

import json
import sys
import time
import warnings
from pathlib import Path

from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import declared_prior, declared_supports
from navapp.geometry.interpolation import interpolation_matrix
from navapp.geometry.tre import mean_tre
from navapp.registration import forces as F
from navapp.registration import pipeline as PL
from navapp.registration.rigid import beta_pose
from navapp.simulation.levels import data_level

FIT = F.SurfaceForces.fit_weights


def run_case(case_dir: Path, level: str) -> dict:
    case = read_case(case_dir)
    free, _ = PL.prepare(case)
    model, _ = PL.prepare(case, **declared_supports(case))
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
    data = data_level(case_dir, "S", case=case) if level == "S" else case.intraop
    prior = declared_prior(case_dir, case)
    full = {}

    def fit_weights(self, pf, lam, train=None, options=None, pose=None, rigid_only=False, held_q=None):
        wf = FIT(self, pf, lam, train, options, pose, rigid_only, held_q)
        if train is None and not rigid_only:  # the forces fitted to every block (the last one per λ: the answer's)
            full[lam, held_q is not None] = (self.field(pf, wf), wf.q, wf.rms_mm)
        return wf

    F.SurfaceForces.fit_weights = fit_weights
    t = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            reg = PL.register(model, data, pose_prior=prior, surface_forces=True, undeclared=free)
    finally:
        F.SurfaceForces.fit_weights = FIT
    sec = time.perf_counter() - t
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        und = PL.register(free, data, pose_prior=prior)
    fc = reg.forces

    def tre_of(u, q):
        moved = x0 + B @ u
        if q is not None:
            moved = beta_pose(q, model.centroid).apply(moved)
        return round(mean_tre(reg.rigid.apply(moved), x1), 3)

    row = {"case": case_dir.name, "level": level, "identity": round(mean_tre(x0, x1), 3),
           "undeclared": round(mean_tre(und.transform(x0, B=B), x1), 3),
           "undeclared_warned": bool(und.warnings), "shown": round(mean_tre(reg.transform(x0, B=B), x1), 3),
           "warnings": [w.text for w in reg.warnings], "seconds": round(sec, 1)}
    if fc is None:
        row["answer"] = "no forces stage"
        return row
    row.update({"answer": fc.answer.value, "none": round(mean_tre(reg.rigid.apply(x0), x1), 3),
                "basis": round(mean_tre(reg.transform(x0, beta=reg.libr.beta, B=B), x1), 3),
                **fc.as_dict(), "block_points": [int(c) for c in fc.block_points],
                "forces_by_lambda": {f"{k:g}{' held' if h else ''}": tre_of(u, q)
                                     for (k, h), (u, q, _) in full.items()},
                "rms_by_lambda": {f"{k:g}{' held' if h else ''}": round(r, 3) for (k, h), (_, _, r) in full.items()}})
    return row


if __name__ == "__main__":
    out, level = Path(sys.argv[1]), sys.argv[2]
    for arg in sys.argv[3:]:
        row = run_case(Path(arg), level)
        with out.open("a") as fh:
            fh.write(json.dumps(row) + "\n")
        print(json.dumps(row), flush=True)
