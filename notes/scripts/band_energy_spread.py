"""The predicted-error band with the strain energy over its own posterior spread (issue 46, item 4,
session 34), before and after, from the same registrations: each local-load case registered once
per level (S, S + all), its pose declared as its scene made it (``loads.declared_prior``; with
``--undeclared``, no prior), and the estimate at the truth targets made twice — as
``uncertainty.estimate_error`` makes it now (H = data + the energy's Laplace curvature + its
curvature over the posterior spread, ``energy_spread``) and as it was (``energy_spread`` taken
as nothing). One JSON line per registration: the fraction of targets whose true error (of the
deformable fit the estimate is of) lies in [lower, upper], and under the upper edge; whether that
fit is the answer shown (``deformed``: only then does the viewer show a band); mean ê, σ and the
true error; the predicted error over the organ (``OrganError``, what a warning quotes) and the
shown answer's true mean error; the answer's warning lines (now).

    python notes/scripts/band_energy_spread.py [--undeclared] CASE... > OUT.jsonl
"""

import json
import sys
import warnings

import numpy as np

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import declared_prior
from navapp.geometry.interpolation import interpolation_matrix
from navapp.registration import uncertainty
from navapp.registration.pipeline import prepare, register
from navapp.simulation.levels import data_level

progress.QUIET = True
warnings.simplefilter("ignore")
args = sys.argv[1:]
declared = "--undeclared" not in args
spread = uncertainty.energy_spread


def none(model, info):
    return np.zeros((len(info.beta), len(info.beta)))


def estimates(reg, x0, B, x1):
    out = {}
    for key, fn in (("before", none), ("after", spread)):
        uncertainty.energy_spread = fn
        try:
            est = uncertainty.estimate_error(reg, points=x0, B=B)
            organ = uncertainty.organ_error(reg)
        finally:
            uncertainty.energy_spread = spread
        err = np.linalg.norm(est.positions - x1, axis=1)
        out[key] = {"in_band": round(float(((err >= est.lower_mm) & (err <= est.upper_mm)).mean()), 3),
                    "below_upper": round(float((err <= est.upper_mm).mean()), 3),
                    "above_lower": round(float((err >= est.lower_mm).mean()), 3),
                    "mean_pred": round(float(est.predicted_mm.mean()), 2),
                    "mean_sigma": round(float(est.sigma_mm.mean()), 2),
                    "organ_quoted": round(organ.mean_mm, 2), "organ_warning": organ.warning is not None,
                    "mean_true": round(float(err.mean()), 2)}
    return out


for case_dir in [a for a in args if not a.startswith("--")]:
    case = read_case(case_dir)
    model, _ = prepare(case)
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
    for level in ("S", "S+all"):
        data = data_level(case_dir, "S", case=case) if level == "S" else case.intraop
        reg = register(model, data, pose_prior=declared_prior(case_dir, case) if declared else None)
        shown = np.linalg.norm(reg.transform(x0, B=B) - x1, axis=1)
        row = {"case": case_dir.rstrip("/").split("/")[-1], "level": level, "declared": declared,
               "deformed": reg.deformed, "mean_shown": round(float(shown.mean()), 2),
               "warnings": [w.kind.value for w in reg.warnings]}
        if reg.libr is not None:
            row.update(estimates(reg, x0, B, x1))
        print(json.dumps(row), flush=True)
