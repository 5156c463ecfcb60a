"""What the strain energy's spread (``uncertainty.energy_spread``) costs: one case registered
(default k), then ``energy_spread`` alone and ``estimate_error`` at the liver's surface nodes
(what the viewer colours) with and without it, each the median of ``REPEATS`` runs.

    python notes/scripts/spread_timing.py CASE [LEVEL]
"""

import sys
import time
import warnings

import numpy as np

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.registration import uncertainty
from navapp.registration.pipeline import prepare, register
from navapp.simulation.levels import data_level
from navapp.threads import limit_threads

REPEATS = 7
progress.QUIET = True
warnings.simplefilter("ignore")
case_dir = sys.argv[1]
level = sys.argv[2] if len(sys.argv) > 2 else "S"
case = read_case(case_dir)
model, _ = prepare(case)
reg = register(model, data_level(case_dir, level, case=case) if level != "S+all" else case.intraop)
spread = uncertainty.energy_spread


def median_seconds(fn) -> float:
    out = []
    for _ in range(REPEATS):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return float(np.median(out))


info = uncertainty.information(reg.model, reg.data_model_frame, reg.libr.beta)
with limit_threads(1):  # as ``estimate_error`` runs it
    alone = median_seconds(lambda: spread(reg.model, info))
print(f"p = {len(info.beta)}: energy_spread {1e3 * alone:.1f} ms")
for key, fn in (("without", lambda model, info: np.zeros((len(info.beta), len(info.beta)))), ("with", spread)):
    uncertainty.energy_spread = fn
    try:
        sec = median_seconds(lambda: uncertainty.estimate_error(reg, nodes=reg.model.basis.surface))
    finally:
        uncertainty.energy_spread = spread
    print(f"estimate_error at {len(reg.model.basis.surface)} surface nodes, {key} the spread: {1e3 * sec:.0f} ms")
