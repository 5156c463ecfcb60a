"""Probe (nothing in navapp changed by it): is the band's lower-edge miss on the declared local-load
answers the residual scale s = Ω / (R − p), which a misfit the basis cannot make (the dent) inflates
everywhere? For each registration whose answer is deformable (shown with a band), σ of α given the
pose recomputed with s read robustly: s × (1.4826 · median |f| / weighted RMS of f)², the scale the
declared prior already reads (``pipeline._robust_sd``), the energy's spread recomputed at that scale;
the band [lower · ê_base, upper edge as today] judged at the truth targets before and after.

    python notes/scripts/band_robust_scale_probe.py CASE... > notes/band_robust_scale_probe.jsonl
"""

import json
import sys
import warnings
from dataclasses import replace

import numpy as np

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import declared_prior
from navapp.geometry.interpolation import interpolation_matrix
from navapp.registration.objective import evaluate
from navapp.registration.pipeline import prepare, register
from navapp.registration.uncertainty import DEFAULT_CALIBRATION as CAL
from navapp.registration.uncertainty import (
    POSE_BAND,
    covariance_factor,
    default_weights,
    energy_spread,
    estimate_error,
    information,
    point_jacobian,
    point_sigma,
)
from navapp.simulation.levels import data_level

progress.QUIET = True
warnings.simplefilter("ignore")
for case_dir in sys.argv[1:]:
    name = case_dir.rstrip("/").split("/")[-1]
    case = read_case(case_dir)
    model, _ = prepare(case)
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
    for level in ("S", "S+all"):
        data = data_level(case_dir, "S", case=case) if level == "S" else case.intraop
        reg = register(model, data, pose_prior=declared_prior(case_dir, case))
        if not reg.deformed:
            continue
        est = estimate_error(reg, points=x0, B=B)
        err = np.linalg.norm(est.positions - x1, axis=1)
        w = default_weights()
        ev = evaluate(model, reg.data_model_frame, reg.libr.beta, w, jacobian=False)
        f, wt = ev.f[:-1], ev.w[:-1]
        ratio = (1.4826 * np.median(np.abs(f))) ** 2 / (np.sum(wt * f ** 2) / np.sum(wt))
        info = information(model, reg.data_model_frame, reg.libr.beta, w)
        robust = replace(info, scale=info.scale * ratio)
        _, G = point_jacobian(model, reg.libr.beta, B)
        n = G.shape[-1] - 6
        H = robust.matrix() + energy_spread(model, robust)
        sigma = point_sigma(G[:, :, :n], factor=covariance_factor(robust, H[:n, :n]))
        base = CAL.predict(est.distance_mm, sigma, est.spread_mm)
        lower = CAL.lower * base
        upper = np.sqrt((CAL.upper * base) ** 2 + (POSE_BAND * est.pose_sigma_mm) ** 2)
        pred = np.sqrt(base ** 2 + est.pose_sigma_mm ** 2)
        print(json.dumps({"case": name, "level": level, "ratio": round(float(ratio), 4),
                          "in_band": round(float(((err >= est.lower_mm) & (err <= est.upper_mm)).mean()), 3),
                          "in_band_robust": round(float(((err >= lower) & (err <= upper)).mean()), 3),
                          "under_upper_robust": round(float((err <= upper).mean()), 3),
                          "sigma": round(float(est.sigma_mm.mean()), 3), "sigma_robust": round(float(sigma.mean()), 3),
                          "pred": round(float(est.predicted_mm.mean()), 2), "pred_robust": round(float(pred.mean()), 2),
                          "true": round(float(err.mean()), 2)}), flush=True)
