"""Where the declared estimate's σ comes from (issue 46, item 4): the LM covariance at the
deformable fit split into its parts, mean over the truth targets, mm — the data-only covariance
of every β as the estimate had it (``sigma``), its α and pose (τ, θ) blocks, the posterior with the
declared prior's rows joined to H at the data's own scale s (so that they say exactly the declared
σ), α given the pose (α's block of H: what the estimate now takes), and σ_pose (``pose_covariance``).

    python notes/scripts/band_sigma_split.py LEVEL CASE... (LEVEL: S or S+all)
"""
import sys
import time
import warnings

import numpy as np

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import declared_prior
from navapp.geometry.interpolation import interpolation_matrix
from navapp.registration.pipeline import prepare, register
from navapp.registration.uncertainty import (
    covariance,
    default_weights,
    estimate_error,
    information,
    point_jacobian,
    point_sigma,
)
from navapp.simulation.levels import data_level

progress.QUIET = True
warnings.simplefilter("ignore")
level = sys.argv[1]
for case_dir in sys.argv[2:]:
    t0 = time.time()
    case = read_case(case_dir)
    model, _ = prepare(case)
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
    data = data_level(case_dir, "S", case=case) if level == "S" else case.intraop
    reg = register(model, data, pose_prior=declared_prior(case_dir, case))
    t1 = time.time()
    est = estimate_error(reg, points=x0, B=B)
    err = np.linalg.norm(est.positions - x1, axis=1)
    m, dat, beta = reg.model, reg.data_model_frame, reg.libr.beta
    n = len(beta) - 6
    w = default_weights()
    info = information(m, dat, beta, w)
    _, G = point_jacobian(m, beta, B)
    C = covariance(info)  # data only, every β

    def sig(Gs, Cs):
        return point_sigma(Gs, cov=Cs).mean()

    Ga, Gp = G[:, :, :n], G[:, :, n:]
    H, s = info.matrix(), info.scale
    Jp = reg.pose_prior.jacobian(n)
    Cpost = covariance(info, H + s * Jp.T @ Jp)  # the prior's rows at the data's scale: its declared σ
    Ccond = s * np.linalg.pinv(H[:n, :n])  # α given the pose
    print(case_dir.rstrip("/").split("/")[-1], level, f"deformed {reg.deformed} reg {t1 - t0:.0f}s",
          f"true {err.mean():.2f} pred {est.predicted_mm.mean():.2f} d {est.distance_mm.mean():.1f}",
          f"m {est.spread_mm:.1f} | data-only sigma {sig(G, C):.2f}: alpha-part {sig(Ga, C[:n, :n]):.2f}",
          f"pose-part {sig(Gp, C[n:, n:]):.2f} | posterior(s): full {sig(G, Cpost):.2f}",
          f"alpha {sig(Ga, Cpost[:n, :n]):.2f} pose {sig(Gp, Cpost[n:, n:]):.2f}",
          f"| alpha|pose {sig(Ga, Ccond):.2f} | sigma_pose {est.pose_sigma_mm.mean():.2f}",
          f"| organ {None if reg.organ is None else round(reg.organ.mean_mm, 2)}", flush=True)
