# ruff: noqa: B023  (closures used within the loop iteration that defines them)
"""Where the declared answer at S loses against LIBR held at the given pose (issue 46, session 35).

Per declared case at level S: no correction, the declared answer shown, its deformable fit and its
rigid pose, and LIBR held at the given pose without a prior (``rigid`` = the given pose,
``LMOptions(pose=False)``, the issue's comparison), each one's true mean TRE, with the held-out
prediction (no truth) of each.

    python notes/scripts/declared_s_loss.py CASES > notes/declared_s_loss_SET.jsonl
"""

import json
import sys
import warnings

import numpy as np

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import declared_prior
from navapp.geometry.interpolation import interpolation_matrix
from navapp.registration.libr import LMOptions
from navapp.registration.pipeline import _given, prepare, register
from navapp.simulation.levels import data_level

progress.QUIET = True
warnings.simplefilter("ignore")
levels = [a.split("=", 1)[1] for a in sys.argv[1:] if a.startswith("--levels=")]
levels = levels[0].split(",") if levels else ["S"]
for case_dir in [a for a in sys.argv[1:] if not a.startswith("--")]:
    case = read_case(case_dir)
    model, _ = prepare(case)
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
    prior = declared_prior(case_dir, case)

    def tre(p):
        return round(float(np.linalg.norm(p - x1, axis=1).mean()), 3)

    for level in levels:
        data = data_level(case_dir, "S", case=case) if level == "S" else case.intraop
        reg = register(model, data, pose_prior=prior)
        held = register(model, data, rigid=_given(), options=LMOptions(pose=False))
        s, hs = reg.support, held.support
        print(json.dumps({
            "case": case_dir.rstrip("/").split("/")[-1], "level": level, "prior": [prior.sd_mm, prior.sd_deg],
            "identity": tre(x0), "shown": tre(reg.transform(x0, B=B)), "deformed": reg.deformed,
            "deformable": tre(reg.transform(x0, beta=reg.libr.beta, B=B)), "rigid": tre(reg.rigid.apply(x0)),
            "kept_given": None if reg.pose_evidence is None else reg.pose_evidence.kept_given,
            "sd_settled": round(reg.pose_prior.feature_sd_mm, 3),
            "heldout": None if s is None else [round(s.rigid_mm, 3), round(s.deformable_mm, 3)],
            "held_given": tre(held.transform(x0, beta=held.libr.beta, B=B)), "held_shown": tre(held.transform(x0, B=B)),
            "held_heldout": None if hs is None else [round(hs.rigid_mm, 3), round(hs.deformable_mm, 3)],
            "held_corr_sigma": None if hs is None or hs.sigma_mm is None else
            [round(hs.correction_mm, 3), round(hs.sigma_mm, 3)],
            "warned": bool(reg.warnings)}), flush=True)
