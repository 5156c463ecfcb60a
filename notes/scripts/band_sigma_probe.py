"""Where the declared band's predicted error comes from, at S: ê and its σ (the LM covariance of
α, τ, θ from the data alone, as ``uncertainty.estimate_error`` has it), and σ again with the
declared prior's rows joined to H (the full posterior) — mean over the truth targets, mm.

    python notes/scripts/band_sigma_probe.py /work/cases3/tooldraw3_0-a /work/cases3/tooldraw3_1-c
"""

import sys
import warnings

import numpy as np

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import declared_prior
from navapp.geometry.interpolation import interpolation_matrix
from navapp.registration.pipeline import prepare, register
from navapp.registration.uncertainty import (
    covariance_factor,
    default_weights,
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
    reg = register(model, data_level(case_dir, "S", case=case), pose_prior=declared_prior(case_dir, case))
    est = estimate_error(reg, points=x0, B=B)
    true = np.linalg.norm(est.positions - x1, axis=1).mean()
    m, data, beta = reg.model, reg.data_model_frame, reg.libr.beta
    n = len(beta) - 6
    info = information(m, data, beta, default_weights())
    _, G = point_jacobian(m, beta, B)
    Jp = reg.pose_prior.jacobian(n)
    H = info.matrix() + reg.pose_prior.scale(default_weights().unit_m) * Jp.T @ Jp
    posterior = point_sigma(G, factor=covariance_factor(info, H)).mean()
    print(case_dir.rstrip("/").split("/")[-1], "S", f"true {true:.2f}", f"predicted {est.predicted_mm.mean():.2f}",
          f"sigma {est.sigma_mm.mean():.2f}", f"d {est.distance_mm.mean():.1f}", f"m {est.spread_mm:.1f}",
          f"sigma_pose {est.pose_sigma_mm.mean():.2f}", f"sigma with the prior's rows {posterior:.2f}", flush=True)
