"""Issue 46, session 39: the declared rigid fit's move judged at two scales of its own residuals —
the robust one the rigid stage reads (1.4826 × median) and their mean square — beside the true
mean TRE of the fitted and the given pose. One registration's rigid stage per CASE:LEVEL.

    python notes/scripts/declared_misfit_scale.py OUT.jsonl CASE:S+all ...
"""
import json
import sys
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import declared_prior
from navapp.registration.model import usable_data
from navapp.registration.objective import evaluate
from navapp.registration.pipeline import _declared_rigid, _settings, prepare
from navapp.registration.uncertainty import misfit_sd_mm, pose_evidence
from navapp.simulation.levels import data_level

progress.QUIET = True
warnings.simplefilter("ignore")
out = open(sys.argv[1], "a")
for spec in sys.argv[2:]:
    case_dir, level = spec.rsplit(":", 1)
    case_dir = Path(case_dir)
    case = read_case(case_dir)
    model, _ = prepare(case)
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    prior = declared_prior(case_dir, case)
    data = usable_data(model, data_level(case_dir, "S", case=case) if level == "S" else case.intraop)
    options, init = _settings(None, None)
    tre = lambda p: float(np.linalg.norm(p - x1, axis=1).mean())
    pose, centred, _ = _declared_rigid(model, data, prior, options, init, None)
    local = {k: pose.inverse(p) for k, p in data.items()}
    n = model.basis.Ju.shape[1]
    zero = np.zeros(n + 6)
    ev = evaluate(model, local, zero, replace(options.weights, pose_prior=None), jacobian=False)
    f = ev.f[:-1]
    rob = float(1.4826 * np.median(np.abs(f))); ms = float(np.sqrt(np.mean(f ** 2)))
    pe = pose_evidence(model, local, pose, centred, options.weights)
    row = dict(case=case_dir.name, level=level, tre_ident=tre(x0), tre_fit=tre(pose.apply(x0)), moved=pe.moved_mm,
               sigma=pe.sigma_mm, sdF=centred.feature_sd_mm, robust=rob, rms=ms)
    ms_centred = replace(centred, feature_sd_mm=max(ms, centred.feature_sd_mm))
    row["sigma_ms"] = pose_evidence(model, local, pose, ms_centred, options.weights).sigma_mm
    row["misfit_sigma_mm"] = pe.misfit_sigma_mm  # the same, as ``register`` computes it
    assert abs(misfit_sd_mm(model, local, options.weights) - ms) < 1e-9
    out.write(json.dumps(row) + "\n"); out.flush(); print(row, flush=True)
