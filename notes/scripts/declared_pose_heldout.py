# ruff: noqa: B023  (closures used within the loop iteration that defines them)
"""The declared rigid answer's two poses held out (issue 46, session 35): per held-out block, the
RMS of the pose fitted within the prior to the other blocks, and of the given pose (no fit), with
both poses' true mean TRE, where ``register`` shows a rigid answer with a declared pose.

    python notes/scripts/declared_pose_heldout.py --levels=S,S+all CASES > notes/declared_pose_heldout.jsonl
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
from navapp.registration.libr import register_libr
from navapp.registration.model import usable_data
from navapp.registration.objective import evaluate
from navapp.registration.pipeline import _declared_rigid, _settings, prepare, register
from navapp.registration.support import SupportOptions, blocks_of, pooled_rms
from navapp.simulation.levels import data_level

progress.QUIET = True
warnings.simplefilter("ignore")
levels = [a.split("=", 1)[1] for a in sys.argv[1:] if a.startswith("--levels=")]
levels = levels[0].split(",") if levels else ["S", "S+all"]
for case_dir in [a for a in sys.argv[1:] if not a.startswith("--")]:
    case = read_case(case_dir)
    model, _ = prepare(case)
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    prior = declared_prior(case_dir, case)
    n = model.basis.Ju.shape[1]
    c = model.centroid
    for level in levels:
        data = usable_data(model, data_level(case_dir, "S", case=case) if level == "S" else case.intraop)
        reg = register(model, data, pose_prior=prior)
        if reg.deformed or reg.pose_evidence is None:
            continue
        options, init = _settings(None, None)
        moved, centred, _ = _declared_rigid(model, data, prior, options, init, None)
        options = replace(options, weights=replace(options.weights, pose_prior=centred))
        local = {k: moved.inverse(p) for k, p in data.items()}
        inv = moved.inverse  # the given pose seen from the moved frame: x ↦ moved⁻¹(x)
        Rg = moved.R.T
        tg = -moved.R.T @ moved.t
        bg = np.zeros(n + 6)
        bg[n:n + 3] = tg - c + Rg @ c
        bg[n + 3:] = Rotation.from_matrix(Rg).as_euler("XYZ")
        labels = blocks_of(local, SupportOptions.blocks)
        fold = replace(options, max_iterations=SupportOptions.iterations, deform=False)
        blocks = []
        for b in range(SupportOptions.blocks):
            train = {k: p[labels[k] != b] for k, p in local.items() if (labels[k] != b).any()}
            held = {k: p[labels[k] == b] for k, p in local.items() if (labels[k] == b).any()}
            pose = register_libr(model, train, None, fold, None, None).beta
            fitted = pooled_rms(evaluate(model, held, pose, options.weights, jacobian=False).features, held)
            given = pooled_rms(evaluate(model, held, bg, options.weights, jacobian=False).features, held)
            blocks.append([round(fitted, 3), round(given, 3), int(sum(len(p) for p in held.values()))])
        tre = lambda p: round(float(np.linalg.norm(p - x1, axis=1).mean()), 3)  # noqa: E731
        ev = reg.pose_evidence
        print(json.dumps({"case": case_dir.rstrip("/").split("/")[-1], "level": level, "identity": tre(x0),
                          "fitted": tre(moved.apply(x0)), "shown": tre(reg.transform(x0)),
                          "kept_given": ev.kept_given, "warned": bool(reg.warnings), "blocks": blocks}), flush=True)
