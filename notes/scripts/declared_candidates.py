"""Per case and level, with the pose declared: the three candidate answers (the given pose, the
rigid fit within the prior, the deformable fit), each one's true mean TRE, held-out evidence
and the rigid answer's predicted pose error over the organ (posterior σ_pose, no truth).

    python notes/scripts/declared_candidates.py CASES/tool* > notes/declared_candidates.jsonl
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
from navapp.registration.pipeline import _noise_floor, _robust_sd, prepare, register
from navapp.registration.support import pooled_rms
from navapp.registration.uncertainty import default_weights, organ_nodes, point_jacobian, point_sigma, pose_covariance
from navapp.simulation.levels import data_level

progress.QUIET = True
warnings.simplefilter("ignore")
levels = [a.split("=", 1)[1] for a in sys.argv[1:] if a.startswith("--levels=")]
levels = levels[0].split(",") if levels else ["S", "S+all"]
for case_dir in [a for a in sys.argv[1:] if not a.startswith("--")]:
    case = read_case(case_dir)
    model, _ = prepare(case)
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
    prior = declared_prior(case_dir, case)
    for level in levels:
        data = data_level(case_dir, "S", case=case) if level == "S" else case.intraop
        reg = register(model, data, pose_prior=prior)
        n = reg.model.basis.Ju.shape[1]
        tre = lambda p, x1=x1: float(np.linalg.norm(p - x1, axis=1).mean())  # noqa: E731
        w = default_weights()
        given_rms = pooled_rms(evaluate(reg.model, data, np.zeros(n + 6), w, jacobian=False).features)
        rigid_rms = pooled_rms(evaluate(reg.model, reg.data_model_frame, np.zeros(n + 6), w, jacobian=False).features)
        local = reg.data_model_frame
        sd_r = max(_robust_sd(reg.model, local, np.zeros(n + 6), w), _noise_floor(local))
        nodes = organ_nodes(reg.model)
        _, G = point_jacobian(reg.model, np.zeros(n + 6), nodes=nodes)
        out = {}
        for tag, sd in (("rigid_scale", sd_r), ("settled_scale", reg.pose_prior.feature_sd_mm)):
            pp = replace(reg.pose_prior, feature_sd_mm=sd)
            cov = pose_covariance(reg.model, local, np.zeros(n + 6), replace(w, pose_prior=pp))
            out[tag] = round(float(point_sigma(G[:, :, -6:], cov=cov).mean()), 2)
        # the prior alone (no data): the given pose's own predicted pose error
        cov0 = pose_covariance(reg.model, {}, np.zeros(n + 6), replace(w, pose_prior=reg.pose_prior))
        sup = reg.support
        print(json.dumps({
            "case": case_dir.rstrip("/").split("/")[-1], "level": level,
            "prior": [prior.sd_mm, prior.sd_deg], "deformed": reg.deformed, "warnings": reg.warnings,
            "tre_given": round(tre(x0), 3), "tre_rigid": round(tre(reg.rigid.apply(x0)), 3),
            "tre_deformable": None if reg.libr is None else round(tre(reg.transform(x0, beta=reg.libr.beta, B=B)), 3),
            "tre_shown": round(tre(reg.transform(x0, B=B)), 3),
            "rms_given": round(given_rms, 3), "rms_rigid": round(rigid_rms, 3),
            "heldout_rigid": None if sup is None else round(sup.rigid_mm, 3),
            "heldout_deformable": None if sup is None else round(sup.deformable_mm, 3),
            "blocks": None if sup is None else [[round(b.rigid_mm, 2), round(b.deformable_mm, 2), b.points]
                                                for b in sup.blocks],
            "sigma_pose_rigid": out, "sigma_pose_prior": round(float(point_sigma(G[:, :, -6:], cov=cov0).mean()), 2),
            "sd_rigid_stage": round(sd_r, 3), "sd_settled": round(reg.pose_prior.feature_sd_mm, 3),
            "organ": None if reg.organ is None else round(reg.organ.mean_mm, 2)}), flush=True)
