"""Per data feature, the mean square of a registration's residuals over their robust variance
((1.4826 × median |f|)²), at S and S + all: how heavy the tail a misfit leaves is (a dent the basis
cannot make: tens; noise: about one). ``declared``: the pose declared as the scene made it
(``loads.declared_prior``); ``undeclared``: ``register``'s default.

    python notes/scripts/residual_tails.py declared|undeclared CASE...
"""

import sys
import warnings

import numpy as np

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import declared_prior
from navapp.registration.objective import evaluate
from navapp.registration.pipeline import prepare, register
from navapp.registration.uncertainty import default_weights, information
from navapp.simulation.levels import data_level

progress.QUIET = True
warnings.simplefilter("ignore")
declared = sys.argv[1] == "declared"
for case_dir in sys.argv[2:]:
    case = read_case(case_dir)
    model, _ = prepare(case)
    for level in ("S", "S+all"):
        data = data_level(case_dir, "S", case=case) if level == "S" else case.intraop
        reg = register(model, data, pose_prior=declared_prior(case_dir, case) if declared else None)
        if reg.libr is None:
            continue
        ev = evaluate(model, reg.data_model_frame, reg.libr.beta, default_weights(), jacobian=False)
        start, parts = 0, []
        for name, _f, _S, q, _rows, _local in ev.terms:
            f, w = ev.f[start:start + len(q)], ev.w[start:start + len(q)]
            start += len(q)
            robust = max((1.4826 * np.median(np.abs(f))) ** 2, 1e-12)
            parts.append(f"{name} {np.sum(w * f ** 2) / np.sum(w) / robust:.1f}")
        info = information(model, reg.data_model_frame, reg.libr.beta)
        print(case_dir.rstrip("/").split("/")[-1], level, "deformable" if reg.deformed else "rigid",
              f"robust s / s {info.robust_scale / info.scale:.3f};", ", ".join(parts), flush=True)
