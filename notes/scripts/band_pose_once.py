"""The declared band before and after the pose is counted once (issue 46, item 4), from the same
registrations: each case registered with its pose declared as its scene made it
(``loads.declared_prior``), at S and S + all; the estimate at the truth targets as
``uncertainty.estimate_error`` makes it now (the calibrated term takes the deformation's σ given
the pose, the pose joins by its posterior σ_pose) and as it was (the calibrated term took the
data-only σ of every β, α, τ and θ, with σ_pose joined beside it). One JSON line per
registration: the fraction of targets whose true error (of the deformable fit the estimate is
of) lies in [lower, upper], now and before; whether that fit is the answer shown (``deformed``:
only then does the viewer show a band); the predicted error over the organ a warning quotes
(``OrganError``) and the shown answer's true mean error.

    python notes/scripts/band_pose_once.py /work/cases3/tooldraw3_* > notes/band_pose_once_draw3.jsonl
    python notes/scripts/band_pose_once.py /work/cases/tool* > notes/band_pose_once_study.jsonl
"""

import json
import sys
import warnings

import numpy as np

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import declared_prior
from navapp.geometry.interpolation import interpolation_matrix
from navapp.registration.pipeline import prepare, register
from navapp.registration.uncertainty import (
    POSE_BAND,
    covariance_factor,
    estimate_error,
    information,
    point_jacobian,
    point_sigma,
)
from navapp.simulation.levels import data_level

progress.QUIET = True
warnings.simplefilter("ignore")
for case_dir in sys.argv[1:]:
    case = read_case(case_dir)
    model, _ = prepare(case)
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
    for level in ("S", "S+all"):
        data = data_level(case_dir, "S", case=case) if level == "S" else case.intraop
        reg = register(model, data, pose_prior=declared_prior(case_dir, case))
        est = estimate_error(reg, points=x0, B=B)
        err = np.linalg.norm(est.positions - x1, axis=1)
        shown = np.linalg.norm(reg.transform(x0, B=B) - x1, axis=1)
        # before: the data-only σ of every β in the calibrated term (the same weights as ``estimate_error``)
        info = information(reg.model, reg.data_model_frame, reg.libr.beta)
        _, G = point_jacobian(reg.model, reg.libr.beta, B)
        cal = est.calibration
        base = cal.predict(est.distance_mm, point_sigma(G, factor=covariance_factor(info)), est.spread_mm)
        ps = est.pose_sigma_mm
        lo, hi = base * cal.lower, np.sqrt((base * cal.upper) ** 2 + (POSE_BAND * ps) ** 2)
        print(json.dumps({
            "case": case_dir.rstrip("/").split("/")[-1], "level": level, "deformed": reg.deformed,
            "in_band": round(float(((err >= est.lower_mm) & (err <= est.upper_mm)).mean()), 3),
            "in_band_before": round(float(((err >= lo) & (err <= hi)).mean()), 3),
            "below_upper": round(float((err <= est.upper_mm).mean()), 3),
            "mean_pred": round(float(est.predicted_mm.mean()), 2),
            "mean_pred_before": round(float(np.sqrt(base ** 2 + ps ** 2).mean()), 2),
            "mean_sigma": round(float(est.sigma_mm.mean()), 2), "mean_pose_sigma": round(float(ps.mean()), 2),
            "mean_true": round(float(err.mean()), 2), "mean_shown": round(float(shown.mean()), 2),
            "organ_quoted": None if reg.organ is None else round(reg.organ.mean_mm, 2),
            "warned": bool(reg.warnings)}), flush=True)
