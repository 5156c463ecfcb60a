"""Would refitting ê on the calibration liver's local-load cases close the band's lower edge?
(issue 46, item 4, session 34: a probe for the next step, nothing in navapp changed by it.)

Collect: each case registered with its pose declared (``loads.declared_prior``) at S and S + all;
per truth target d, σ (as ``estimate_error`` makes it now), σ_pose, m and the true error of the
deformable fit, saved to an .npz per registration. Judge: ê's coefficients and band refitted
(as ``error_estimate.fit_calibration`` does) on the deformable answers of liver 0's cases (tool0-*,
tooldraw3_0-*; the calibration liver), the band of each other registration made as
``estimate_error`` makes it (σ_pose in quadrature, the upper edge with ``POSE_BAND``), against the
default calibration on the same registrations.

    python notes/scripts/band_refit_probe.py collect OUT_DIR CASE...
    python notes/scripts/band_refit_probe.py judge OUT_DIR
"""

import sys
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.optimize import nnls

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.evaluation.error_estimate import liver_id
from navapp.evaluation.loads import declared_prior
from navapp.geometry.interpolation import interpolation_matrix
from navapp.registration.pipeline import prepare, register
from navapp.registration.uncertainty import DEFAULT_CALIBRATION, POSE_BAND, Calibration, estimate_error
from navapp.simulation.levels import data_level

progress.QUIET = True
warnings.simplefilter("ignore")
mode, out = sys.argv[1], Path(sys.argv[2])
if mode == "collect":
    out.mkdir(parents=True, exist_ok=True)
    for case_dir in sys.argv[3:]:
        case = read_case(case_dir)
        model, _ = prepare(case)
        x0, x1 = case.need_truth().tre_points(model.basis.nodes)
        B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
        for level in ("S", "S+all"):
            data = data_level(case_dir, "S", case=case) if level == "S" else case.intraop
            reg = register(model, data, pose_prior=declared_prior(case_dir, case))
            if reg.libr is None:
                continue
            est = estimate_error(reg, points=x0, B=B)
            name = Path(case_dir).name
            np.savez(out / f"{name}_{level}.npz", d=est.distance_mm, sigma=est.sigma_mm, pose=est.pose_sigma_mm,
                     m=est.spread_mm, err=np.linalg.norm(est.positions - x1, axis=1), deformed=reg.deformed,
                     liver=liver_id(case_dir), case=name, level=level)
            print(name, level, flush=True)
    sys.exit(0)

regs = [dict(np.load(f)) for f in sorted(out.glob("*.npz"))]
fit = [r for r in regs if str(r["case"]).startswith(("tool0-", "tooldraw3_0-")) and bool(r["deformed"])]
held = [r for r in regs if not str(r["case"]).startswith(("tool0-", "tooldraw3_0-"))]
# as ``error_estimate.fit_calibration`` (NNLS on relative errors, the band the (1 ± 0.9)/2 quantiles
# of true / ê), with m each registration's own (median d over the mesh nodes, not over its targets)
rows = [np.column_stack([np.ones_like(r["d"]), r["d"], r["sigma"], r["d"] * float(r["m"]), r["err"],
                         np.full(len(r["d"]), 1.0 / max(float(r["err"].mean()), 1e-6))]) for r in fit]
A = np.vstack(rows)
coef, _ = nnls(A[:, :4] * A[:, 5:6], A[:, 4] * A[:, 5])
refit = Calibration(*map(float, coef), fitted_on="liver 0 local loads, declared")
ratio = A[:, 4] / np.maximum(A[:, :4] @ coef, 1e-9)
lo, hi = np.quantile(ratio, [0.05, 0.95])
refit = replace(refit, lower=float(lo), upper=float(hi))
print(f"refit on {len(fit)} registrations: a {refit.a:.4f} b {refit.b:.5f} c {refit.c:.4f} e {refit.e:.6f} "
      f"band [{refit.lower:.4f}, {refit.upper:.4f}]")
for cal, label in ((DEFAULT_CALIBRATION, "default"), (refit, "refit")):
    for level in ("S", "S+all"):
        for shown in (False, True):
            cover = []
            for r in held:
                if r["level"] != level or (shown and not bool(r["deformed"])):
                    continue
                base = cal.predict(r["d"], r["sigma"], float(r["m"]))
                lo, hi = base * cal.lower, np.sqrt((base * cal.upper) ** 2 + (POSE_BAND * r["pose"]) ** 2)
                cover.append(float(((r["err"] >= lo) & (r["err"] <= hi)).mean()))
            print(f"{label:7s} {level:6s} {'shown' if shown else 'all':5s} n={len(cover):2d} "
                  f"in band {np.mean(cover):.3f}, ≥ 90 % in {sum(c >= 0.9 for c in cover)}")
