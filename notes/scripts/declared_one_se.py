"""The declared answer's deformable-against-rigid verdict, per registration: the held-out RMS of
both answers, the paired gain and its standard error (``support.paired_gain``), which rule decided
(``Support.paired``), and the answer's mean TRE and lines — the ``libr-declared`` registration of
``navapp study loads`` (``loads.run_case``'s arguments), at S and S + all. One JSON line each.

    python notes/scripts/declared_one_se.py [--levels=S] CASE... > notes/declared_one_se.jsonl

(At S + all the vessel contours are interior data: the rule there is the 10 % margin, unchanged.)
"""

import json
import sys
import warnings

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import LOAD_LEVELS, declared_prior
from navapp.geometry.interpolation import interpolation_matrix
from navapp.geometry.tre import mean_tre
from navapp.registration.pipeline import prepare, register
from navapp.registration.support import paired_gain
from navapp.simulation.levels import data_level

progress.QUIET = True
warnings.simplefilter("ignore")
levels = next((a.split("=", 1)[1].split(",") for a in sys.argv[1:] if a.startswith("--levels=")), LOAD_LEVELS)
for case_dir in [a for a in sys.argv[1:] if not a.startswith("--")]:
    case = read_case(case_dir)
    model, _ = prepare(case)
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
    for level in levels:
        data = data_level(case_dir, "S", case=case) if level == "S" else case.intraop
        reg = register(model, data, pose_prior=declared_prior(case_dir, case))
        s = reg.support
        gain, se = paired_gain(s.blocks) if s is not None and s.blocks else (None, None)
        row = {"case": str(case_dir).rstrip("/").split("/")[-1],
               "level": level, "tre_mean_mm": round(mean_tre(reg.transform(x0, B=B), x1), 3),
               "answer": "deformable" if reg.deformed else "rigid", "warned": bool(reg.warnings),
               "lines": [w.text for w in reg.warnings]}
        if s is not None:
            row.update(heldout_rigid_mm=round(s.rigid_mm, 3), heldout_deformable_mm=round(s.deformable_mm, 3),
                       gain_mm=round(gain, 3), se_mm=round(se, 3), paired=s.paired, predicts=s.predicts,
                       margin_verdict=s.deformable_mm < (1 - s.margin) * s.rigid_mm)
        if reg.libr is not None and not reg.deformed:  # the deformable fit the verdict turned away
            row["fit_tre_mean_mm"] = round(mean_tre(reg.transform(x0, beta=reg.libr.beta, B=B), x1), 3)
        print(json.dumps(row), flush=True)
