# ruff: noqa: B023  (closures used within the loop iteration that defines them)
"""The declared rigid stage's candidate poses judged by the deformable posterior (issue 46, session 35).

``pipeline._declared_rigid`` takes, among the given pose and the multi-start ICP poses within
the prior's reach, the one with the lowest *rigid* Ω (data and prior). Here each candidate is also
carried through the deformable fit (stiff first, then the true weights, the prior at the same
scale, pose free) and its Ω there — the posterior of the answer itself: data, strain energy,
prior — recorded beside both answers' true mean TRE.

    python notes/scripts/declared_pose_posterior.py CASES > notes/declared_pose_posterior_SET.jsonl
"""

import json
import sys
import warnings
from dataclasses import replace

import numpy as np
from scipy.spatial.transform import Rotation

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import declared_prior
from navapp.geometry.interpolation import interpolation_matrix
from navapp.registration.libr import register_libr
from navapp.registration.model import usable_data
from navapp.registration.objective import HUBER_MM
from navapp.registration.pipeline import (
    PRIOR_REACH,
    SCALE_ROUNDS,
    _noise_floor,
    _rigid_features,
    _robust_sd,
    _settings,
    deform_points,
    prepare,
)
from navapp.registration.rigid import basin_representatives, multi_start_icp, start_poses
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
    n = model.basis.Ju.shape[1]
    c = model.centroid

    def tre(beta):
        return round(float(np.linalg.norm(deform_points(model.basis, c, beta, x0, B) - x1, axis=1).mean()), 3)

    for level in levels:
        data = usable_data(model, data_level(case_dir, "S", case=case) if level == "S" else case.intraop)
        options, init = _settings(None, None)
        floor = _noise_floor(data)
        huber = {name: HUBER_MM for name in data}
        rigid_only = replace(options, deform=False, pose=True)

        def fit(beta0, current, rounds=SCALE_ROUNDS):
            for _ in range(rounds):
                fitted = register_libr(model, data, beta0, replace(rigid_only, weights=replace(
                    options.weights, huber_mm=huber, pose_prior=current)), None, None)
                sd = max(_robust_sd(model, data, fitted.beta, options.weights), floor)
                settled = abs(sd - current.feature_sd_mm) < 0.1 * current.feature_sd_mm
                current = replace(current, feature_sd_mm=sd)
                if settled:
                    break
            return fitted, current

        def beta_of(pose):
            b = np.zeros(n + 6)
            b[n:n + 3] = pose.t - c + pose.R @ c
            b[n + 3:] = Rotation.from_matrix(pose.R).as_euler("XYZ")
            return b

        best, scale = fit(None, replace(prior, centre=(0.0,) * 6))
        cands = [("given", fit(best.beta, scale, rounds=1)[0])]
        features = _rigid_features(init)
        turn = min(init.start_angle_deg, 2.0 * prior.sd_deg)
        poses = start_poses(model, {k: v for k, v in data.items() if k in features} or data, turn, False)
        starts = multi_start_icp(model, data, poses, options.weights, mode=init.icp, features=features,
                                 robust=init.rigid_robust)
        for i, rep in enumerate(basin_representatives(starts)[:init.max_candidates]):
            b = beta_of(rep.fitted)
            reach = np.concatenate([b[n:n + 3] / prior.sd_mm, b[n + 3:] / prior.sd_rad])
            if np.abs(reach).max() > PRIOR_REACH or np.allclose(b, 0.0):
                continue
            cands.append((f"icp{i}", fit(b, scale, rounds=1)[0]))
        with_prior = replace(options, weights=replace(options.weights, pose_prior=scale))
        stiff = replace(with_prior, weights=replace(with_prior.weights, energy=with_prior.weights.energy * 3.0))
        rows = []
        for name, r in cands:
            b0 = register_libr(model, data, r.beta, stiff, None, None).beta
            d = register_libr(model, data, b0, with_prior, None, None)
            rows.append({"cand": name, "omega_rigid": r.omega, "tre_rigid": tre(r.beta), "omega_def": d.omega,
                         "tre_def": tre(d.beta)})
        print(json.dumps({"case": case_dir.rstrip("/").split("/")[-1], "level": level, "scale": scale.feature_sd_mm,
                          "prior": [prior.sd_mm, prior.sd_deg], "candidates": rows}), flush=True)
