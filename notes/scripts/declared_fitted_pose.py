"""Issue 46, session 39: every declared registration of the local-load cases (both levels) — the
answer shown, its lines, and where the answer is rigid its ``PoseEvidence``, the unshown deformable
fit's TRE, the deformable fit's own τ, θ (its move from the given pose and its TRE without the
deformation) and the Mahalanobis d² of the given pose under the rigid fit's posterior and prior.

    python notes/scripts/declared_fitted_pose.py OUT.jsonl CASE...
"""
import json
import sys
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import _case_facts, declared_prior
from navapp.geometry.interpolation import interpolation_matrix
from navapp.registration.pipeline import _settings, prepare, register
from navapp.registration.rigid import after, beta_pose
from navapp.registration.uncertainty import organ_nodes, pose_covariance
from navapp.simulation.levels import data_level

progress.QUIET = True
warnings.simplefilter("ignore")
out = open(sys.argv[1], "a")
for case_dir in sys.argv[2:]:
    case_dir = Path(case_dir)
    case = read_case(case_dir)
    model, _ = prepare(case)
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
    prior = declared_prior(case_dir, case)
    facts = _case_facts(case_dir, case, model.basis.nodes)
    n = model.basis.Ju.shape[1]; c = model.centroid
    tre = lambda p: float(np.linalg.norm(p - x1, axis=1).mean())
    for level in ("S", "S+all"):
        data = data_level(case_dir, "S", case=case) if level == "S" else case.intraop
        reg = register(model, data, pose_prior=prior)
        ev = reg.pose_evidence
        row = dict(case=case_dir.name, level=level, pre=facts["pre_aligned"], deformed=reg.deformed,
                   tre_shown=tre(reg.transform(x0, B=B)), tre_ident=tre(x0),
                   lines=[w.kind.name for w in reg.warnings])
        if ev is not None:
            row.update(ev.as_dict())
            if reg.libr is not None:
                row["tre_libr"] = tre(reg.transform(x0, beta=reg.libr.beta, B=B))
                lp = after(reg.rigid, beta_pose(reg.libr.beta, c))
                row["tre_libr_pose"] = tre(lp.apply(x0))
                nodes = organ_nodes(model); x = model.basis.nodes[nodes]
                row["libr_pose_moved"] = float(np.linalg.norm(lp.apply(x) - x, axis=1).mean())
                row["rigid_moved"] = float(np.linalg.norm(reg.rigid.apply(x) - x, axis=1).mean())
            zero = np.zeros(n + 6)
            options, _ = _settings(None, None)
            wts = replace(options.weights, pose_prior=reg.pose_prior)
            cov = pose_covariance(model, reg.data_model_frame, zero, wts)
            cen = np.asarray(reg.pose_prior.centre)
            row["d2"] = float(cen @ np.linalg.solve(cov, cen))
            pcov = pose_covariance(model, {}, zero, wts)
            row["d2_prior"] = float(cen @ np.linalg.solve(pcov, cen))
            row["sd_F"] = reg.pose_prior.feature_sd_mm
        out.write(json.dumps(row) + "\n"); out.flush()
        print(row, flush=True)
