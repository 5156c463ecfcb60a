"""Issue 47: declared supports that are wrong. A case whose scene held the organ at one support
(e.g. the ligaments) registered at S with another declared (``--declare posterior``) and surface
forces, beside the undeclared answer (the free-floating basis, the pose declared: the loads
study's ``libr-declared``).

    python notes/scripts/wrong_supports.py OUT.jsonl DECLARE CASE_DIR...

One JSON line per case: mean TRE (mm) of no correction, the undeclared answer, the wrong-supports
answer (and each of its candidates), its held-out RMS per candidate, the free basis's held-out
RMS where the check ran, whether it warned, its warnings, and seconds."""
import json
import sys
import time
import warnings
from pathlib import Path

from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import declared_prior
from navapp.geometry.interpolation import interpolation_matrix
from navapp.geometry.tre import mean_tre
from navapp.registration.pipeline import prepare, register
from navapp.simulation.levels import data_level

out, declare = Path(sys.argv[1]), sys.argv[2]
for arg in sys.argv[3:]:
    case_dir = Path(arg)
    case = read_case(case_dir)
    free, _ = prepare(case)
    wrong, _ = prepare(case, supports=declare)
    x0, x1 = case.need_truth().tre_points(free.basis.nodes)
    B = interpolation_matrix(free.basis.nodes, free.basis.tets, x0)
    data = data_level(case_dir, "S", case=case)
    prior = declared_prior(case_dir, case)

    def tre(p, x1=x1):
        return round(mean_tre(p, x1), 3)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t = time.perf_counter()
        undeclared = register(free, data, pose_prior=prior)
        t_free = time.perf_counter() - t
        t = time.perf_counter()
        reg = register(wrong, data, pose_prior=prior, surface_forces=True)
        t_wrong = time.perf_counter() - t
    fc = reg.forces
    row = {"case": case_dir.name, "declared": declare, "identity": tre(x0),
           "undeclared": tre(undeclared.transform(x0, B=B)), "undeclared_warned": bool(undeclared.warnings),
           "wrong": tre(reg.transform(x0, B=B)), "wrong_none": tre(reg.rigid.apply(x0)),
           "wrong_basis": tre(reg.transform(x0, beta=reg.libr.beta, B=B)),
           "wrong_forces": None if fc is None else tre(reg.rigid.apply(x0 + B @ fc.u)),
           **({} if fc is None else fc.as_dict()), "warned": bool(reg.warnings), "warnings": reg.warnings,
           "seconds_undeclared": round(t_free, 1), "seconds_wrong": round(t_wrong, 1),
           "stage_seconds": {k: round(v, 1) for k, v in reg.seconds.items()}}
    with out.open("a") as fh:
        fh.write(json.dumps(row) + "\n")
    print(json.dumps(row), flush=True)
