# ruff: noqa: B023  (closures used within the loop iteration that defines them)
"""The declared answer at S with the pose prior's weight s_P divided by N (issue 46, session 35):
the data read as N independent observations per feature instead of one. Per case and N: the
shown answer's and the deformable fit's true mean TRE, and the held-out prediction (no truth).

    python notes/scripts/prior_weight_probe.py N1,N2,... CASES > notes/prior_weight_probe.jsonl
"""

import json
import sys
import warnings

import numpy as np

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import declared_prior
from navapp.geometry.interpolation import interpolation_matrix
from navapp.registration import prior as prior_mod
from navapp.registration.pipeline import prepare, register
from navapp.simulation.levels import data_level

progress.QUIET = True
warnings.simplefilter("ignore")
ns = [float(x) for x in sys.argv[1].split(",")]
scale = prior_mod.PosePrior.scale
for case_dir in sys.argv[2:]:
    case = read_case(case_dir)
    model, _ = prepare(case)
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
    prior = declared_prior(case_dir, case)
    data = data_level(case_dir, "S", case=case)
    for N in ns:
        prior_mod.PosePrior.scale = lambda self, unit_m=1e-3, N=N: scale(self, unit_m) / N
        reg = register(model, data, pose_prior=prior)
        s = reg.support
        tre = lambda p: round(float(np.linalg.norm(p - x1, axis=1).mean()), 3)  # noqa: E731
        print(json.dumps({"case": case_dir.rstrip("/").split("/")[-1], "N": N, "shown": tre(reg.transform(x0, B=B)),
                          "deformable": tre(reg.transform(x0, beta=reg.libr.beta, B=B)), "deformed": reg.deformed, "warned": bool(reg.warnings),
                          "heldout": None if s is None else [round(s.rigid_mm, 3), round(s.deformable_mm, 3)],
                          "blocks": None if s is None else [[round(b.rigid_mm, 3), round(b.deformable_mm, 3), b.points]
                                                            for b in s.blocks]}), flush=True)
