"""What the undeclared pose comparison (``pose.prefer_given``) sees, and what a posterior in its
place would decide (docs/decisions/registration.md, "The undeclared pose choice: one line per decision, and
what no summary of the two fits can decide"). Every registration that reaches the comparison
prints one JSON line: both fits' pooled RMS, their strain energy f_E, the rule's decision, and
the posterior gain per data point (−2 log of the posterior ratio given : ICP ÷ N; positive
favours ICP's pose), as its two parts:

- data: Σ_F n_F (r_given² − r_ICP²) / σ_F², each feature on its own noise σ_F = the better of
  the two fits' RMS (floored at 0.01 mm);
- energy: N w_E (f_E,given² − f_E,ICP²) / Σ_F w_F σ_stated,F² — Ω's strain-energy term on the
  scale the weights were stated for (Ω's data term with every residual at its stated noise,
  ``quality.EXPECTED_NOISE_MM``, stands for N points).

A posterior rule "ICP's pose when the gain exceeds given_ratio² − 1 (0.32)" reduces to today's
pooled-RMS rule for one feature without strain energy.

    python notes/scripts/pose_posterior_probe.py hard EDGE K       # the hard-case suite's data
    python notes/scripts/pose_posterior_probe.py dent              # tests/test_local_loads.py's deep dent
    python notes/scripts/pose_posterior_probe.py loads CASE [...]  # local-load cases, method libr (S, then S + all)

The two fits are read from ``register``'s own frame when it builds ``PoseFits`` (a probe, not an
API: it breaks if those local names change).
"""

import json
import sys
import warnings
from pathlib import Path

import numpy as np

from navapp import progress
from navapp.registration import pipeline
from navapp.registration.quality import EXPECTED_NOISE_MM

progress.QUIET = True
warnings.simplefilter("ignore")
SEEN: list[dict] = []
_POSE_FITS = pipeline.PoseFits


def posterior_gain(fitted: dict, given: dict, weights) -> tuple[float, float]:
    n_total, data, stated = 0, 0.0, 0.0
    for name, st in fitted.items():
        if "rms_mm" not in st or "rms_mm" not in given.get(name, {}) or not st["n"]:
            continue
        rf, rg, n = st["rms_mm"], given[name]["rms_mm"], st["n"]
        data += n * (rg * rg - rf * rf) / max(min(rf, rg), 0.01) ** 2
        n_total += n
        stated += weights.features.get(name, 1.0) * (weights.unit_m * EXPECTED_NOISE_MM.get(name, 1.0)) ** 2
    if not n_total:
        return 0.0, 0.0
    fe_f, fe_g = fitted["strain_energy"]["f_E_pa"], given["strain_energy"]["f_E_pa"]
    return data / n_total, weights.energy * (fe_g ** 2 - fe_f ** 2) / stated


def spy(fitted_rms, given_rms, shift):
    frame = sys._getframe(1).f_locals
    res, at_given, options = frame["result"], frame["at_given"], frame["options"]
    data, energy = posterior_gain(res.features, at_given.features, options.weights)
    SEEN.append({"fitted_rms_mm": round(fitted_rms, 4), "given_rms_mm": round(given_rms, 4),
                 "shift_mm": round(shift, 2), "fE_fitted_pa": round(res.features["strain_energy"]["f_E_pa"], 3),
                 "fE_given_pa": round(at_given.features["strain_energy"]["f_E_pa"], 3),
                 "rule": "given" if given_rms <= 1.15 * fitted_rms else "ICP",
                 "gain_data": round(data, 4), "gain_energy": round(energy, 4),
                 "posterior": "given" if data + energy <= 1.15 ** 2 - 1 else "ICP"})
    return _POSE_FITS(fitted_rms, given_rms, shift)


pipeline.PoseFits = spy


def report(name, **extra):
    for row in SEEN:
        print(json.dumps({"case": name, **extra, **row}), flush=True)
    SEEN.clear()


what = sys.argv[1]
if what == "hard":
    from navapp.evaluation.hard import CASES, _register_once, make_setup

    setup = make_setup(edge=float(sys.argv[2]), k=int(sys.argv[3]))
    for case in CASES:
        _register_once(case, setup)
        report(case.name)
elif what == "dent":
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))
    from test_local_loads import _dented_scan

    from navapp.anatomy.meshing import cached_tetmesh
    from navapp.anatomy.phantom import make_phantom
    from navapp.mechanics.basis import BasisSettings, load_or_compute_basis
    from navapp.registration.model import build_model

    ph = make_phantom(0)
    basis, _ = load_or_compute_basis(cached_tetmesh(ph.liver, 12.0, None)[0], BasisSettings(k=12))
    fid = basis.nodes[np.random.default_rng(5).choice(basis.M, 6, replace=False)]  # as tests' small_model
    model = build_model(basis, ph, fiducials=fid)
    pipeline.register(model, _dented_scan(ph.liver.vertices, model, 45.0, 35.0, far_mm=80.0)[0])
    report("deep dent (tests/test_local_loads.py)")
else:
    from navapp.evaluation import loads

    for case_dir in map(Path, sys.argv[2:]):
        loads.run_case(case_dir, methods=("libr",))
        report(case_dir.name)
