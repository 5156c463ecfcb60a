"""Does the strain energy's spread (``uncertainty.energy_spread``, session 34) move σ on the
cases the error estimate was calibrated on? One calibration case registered at every level of
``navapp study error-estimate`` (one plane combination each, as ``--quick``), σ at every mesh node
with and without the spread, the true error beside; then ê's coefficients fitted on each
(``error_estimate.fit_calibration``, the same non-negative least squares on relative errors).

    python notes/scripts/spread_calibration_case.py CASE
"""

import sys
import warnings

import numpy as np

from navapp import progress
from navapp.evaluation import error_estimate as ee
from navapp.registration import uncertainty

progress.QUIET = True
warnings.simplefilter("ignore")
spread = uncertainty.energy_spread
collected = {}
for key, fn in (("before", lambda model, info: np.zeros((len(info.beta), len(info.beta)))), ("after", spread)):
    uncertainty.energy_spread = fn
    ee.estimate_error = uncertainty.estimate_error  # the module's own name, bound at import
    try:
        collected[key] = ee.collect_case(sys.argv[1], combos=1)
    finally:
        uncertainty.energy_spread = spread
for b, a in zip(collected["before"], collected["after"], strict=True):
    print(f"{b.level:6s} deformed {b.deformed!s:5s} mean σ {b.sigma.mean():.3f} → {a.sigma.mean():.3f} mm "
          f"(median ratio {np.median(a.sigma / b.sigma):.3f}), true error {b.err.mean():.2f} / {a.err.mean():.2f} mm")
for key, samples in collected.items():
    cal = ee.fit_calibration(samples)
    print(f"{key}: a {cal.a:.4f} b {cal.b:.5f} c {cal.c:.4f} e {cal.e:.6f} band [{cal.lower:.4f}, {cal.upper:.4f}]")
