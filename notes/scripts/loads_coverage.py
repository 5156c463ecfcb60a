"""The predicted-error band on the local-load cases: the default calibration (fitted on
liver 0's cases: ê on phantom 0 and lap 0, the band also on tool0-*; judge it on tool1-*
and tool2-*) at every truth target of each tool case, at S and S + all,
with today's default registration. One JSON line per registration: the fraction of
targets whose true error lies in the band (``coverage``), under its upper edge for the
deformable answer (``below_upper``) and for the answer shown (``below_upper_shown``: the
rigid pose where the deformation was not supported), and the mean predicted, deformable
and shown errors (mm).

    python notes/scripts/loads_coverage.py TOOL/tool1-* TOOL/tool2-* > notes/loads_coverage.jsonl
    python notes/scripts/loads_coverage.py --declared TOOL/tool* > results/loads_coverage_declared.jsonl

``--declared``: each case registered with its pose declared as its scene made it
(``loads.declared_prior``). ``in_band`` is the fraction of targets whose true error lies in
[lower, upper] of the estimate (the pose's σ joined, ``uncertainty.estimate_error``);
``organ_quoted``: the predicted error over the organ a warning quotes (``OrganError``), beside
``mean_shown``, the true mean error of the answer shown.
"""

import json
import sys
import warnings

import numpy as np

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.evaluation.error_estimate import band_coverage
from navapp.evaluation.loads import declared_prior
from navapp.geometry.interpolation import interpolation_matrix
from navapp.registration.pipeline import prepare, register
from navapp.registration.uncertainty import DEFAULT_CALIBRATION as CAL
from navapp.registration.uncertainty import estimate_error
from navapp.simulation.levels import data_level

progress.QUIET = True
warnings.simplefilter("ignore")
declared = "--declared" in sys.argv
for case_dir in [a for a in sys.argv[1:] if a != "--declared"]:
    case = read_case(case_dir)
    model, _ = prepare(case)
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
    for level in ("S", "S+all"):
        data = data_level(case_dir, "S", case=case) if level == "S" else case.intraop
        reg = register(model, data, pose_prior=declared_prior(case_dir, case) if declared else None)
        est = estimate_error(reg, points=x0, B=B)
        err = np.linalg.norm(est.positions - x1, axis=1)
        shown = np.linalg.norm(reg.transform(x0, B=B) - x1, axis=1)
        print(json.dumps({"case": case_dir.rstrip("/").split("/")[-1], "level": level, "deformed": reg.deformed,
                          "coverage": round(band_coverage(err, est.predicted_mm, CAL.lower, CAL.upper), 3),
                          "below_upper": round(float((err <= est.upper_mm).mean()), 3),
                          "below_upper_shown": round(float((shown <= est.upper_mm).mean()), 3),
                          "mean_pred": round(float(est.predicted_mm.mean()), 2),
                          "mean_true": round(float(err.mean()), 2),
                          "mean_shown": round(float(shown.mean()), 2),
                          "in_band": round(float(((err >= est.lower_mm) & (err <= est.upper_mm)).mean()), 3),
                          "shown_in_band": round(float(((shown >= est.lower_mm) & (shown <= est.upper_mm)).mean()), 3),
                          "mean_pose_sigma": round(float(est.pose_sigma_mm.mean()), 2),
                          "organ_quoted": None if reg.organ is None else round(reg.organ.mean_mm, 2),
                          "declared": declared}), flush=True)
