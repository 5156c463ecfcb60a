"""information() timed on one case's declared registrations, S and S + all (median of 9 calls each):
the robust scale's per-feature medians against the tree before them (run with each tree on PYTHONPATH).

    python notes/scripts/information_timing.py CASE
"""
import sys
import time
import warnings

import numpy as np

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import declared_prior
from navapp.registration.pipeline import prepare, register
from navapp.registration.uncertainty import default_weights, information
from navapp.simulation.levels import data_level

progress.QUIET = True
warnings.simplefilter("ignore")
case_dir = sys.argv[1]
case = read_case(case_dir)
model, _ = prepare(case)
for level in ("S", "S+all"):
    data = data_level(case_dir, "S", case=case) if level == "S" else case.intraop
    reg = register(model, data, pose_prior=declared_prior(case_dir, case))
    ts = []
    for _ in range(9):
        t = time.perf_counter()
        information(model, reg.data_model_frame, reg.libr.beta, default_weights())
        ts.append(time.perf_counter() - t)
    print(level, "information() median of 9: %.1f ms" % (1e3 * np.median(ts)))
