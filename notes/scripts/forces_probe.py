"""Probe: the libr-forces method on one case at S (issue 47): held-out scores, answer, TRE."""
import sys
import time
import warnings
from pathlib import Path

from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import declared_prior, declared_supports
from navapp.geometry.interpolation import interpolation_matrix
from navapp.geometry.tre import mean_tre
from navapp.registration.pipeline import prepare, register
from navapp.simulation.levels import data_level

case_dir = Path(sys.argv[1])
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
print(case_dir.name, "identity", round(mean_tre(x0, x1), 3), "answer", fc.answer.value,
      "tre", round(mean_tre(reg.transform(x0, B=B), x1), 3), "sec", round(sec, 1), fc.as_dict(),
      {k: round(v, 1) for k, v in reg.seconds.items()},
      None if fc.fit is None else (fc.fit.iterations, round(fc.fit.rms_mm, 3)), flush=True)
