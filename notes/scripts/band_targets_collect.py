"""Per-target arrays of the error estimate on the local-load cases, with the pose declared as
each scene made it (``loads.declared_prior``), at S and S + all: one ``.npz`` per registration
in OUT (true error of the deformable fit and of the answer shown, d, σ, m, σ_pose, ê, the band)
and one JSON line per registration on stdout (the answer, its lines, its TRE). Judge band rules
offline from these (``band_targets_judge.py``) without registering again.

    python notes/scripts/band_targets_collect.py OUT CASE...
    python notes/scripts/band_targets_collect.py --both OUT CASE...

``--both``: also the estimate with s read from the mean square alone (as before session 38's
robust reading), from the same registration, into OUT_mean_square (the registrations are the
same either way: nothing decides on the estimate before the answer is chosen).
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
from navapp.geometry.interpolation import interpolation_matrix
from navapp.registration import uncertainty
from navapp.registration.pipeline import prepare, register
from navapp.registration.uncertainty import estimate_error
from navapp.simulation.levels import data_level

progress.QUIET = True
warnings.simplefilter("ignore")
both = "--both" in sys.argv
args = [a for a in sys.argv[1:] if a != "--both"]
out = Path(args[0])
out.mkdir(parents=True, exist_ok=True)
plain_out = Path(f"{out}_mean_square")
if both:
    plain_out.mkdir(parents=True, exist_ok=True)
robust_information = uncertainty.information


def mean_square_information(*a, **k):
    return replace(robust_information(*a, **k), robust_scale=None)


for case_dir in args[1:]:
    name = case_dir.rstrip("/").split("/")[-1]
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
        np.savez(out / f"{name}_{level}.npz", err=err, shown=shown, d=est.distance_mm, sigma=est.sigma_mm,
                 m=est.spread_mm, pose_sigma=est.pose_sigma_mm, pred=est.predicted_mm, lower=est.lower_mm,
                 upper=est.upper_mm)
        if both:
            uncertainty.information = mean_square_information
            try:
                plain = estimate_error(reg, points=x0, B=B)
            finally:
                uncertainty.information = robust_information
            np.savez(plain_out / f"{name}_{level}.npz", err=np.linalg.norm(plain.positions - x1, axis=1), shown=shown,
                     d=plain.distance_mm, sigma=plain.sigma_mm, m=plain.spread_mm, pose_sigma=plain.pose_sigma_mm,
                     pred=plain.predicted_mm, lower=plain.lower_mm, upper=plain.upper_mm)
        sup = reg.support
        print(json.dumps({"case": name, "level": level, "deformed": reg.deformed,
                          "tre_shown": round(float(shown.mean()), 3), "tre_fit": round(float(err.mean()), 3),
                          "noise_scale": est.noise_scale,
                          "lines": [w.text for w in reg.warnings],
                          "kinds": [str(w.kind) for w in reg.warnings],
                          "organ": None if reg.organ is None else reg.organ.as_dict(),
                          "evidence": None if reg.pose_evidence is None else reg.pose_evidence.as_dict(),
                          "support": None if sup is None else {k: (round(v, 4) if isinstance(v, float) else v)
                                                               for k, v in vars(sup).items()
                                                               if isinstance(v, (float, int, bool, str))}}),
              flush=True)
