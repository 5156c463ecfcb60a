"""The declared answers' verdicts on a new draw without the whole loads study: per case and level
the reference (no correction's TRE; for an offset frame the guarded rigid answer's, as
``loads.verdicts``) beside the answer ``band_targets_collect.py`` recorded (its TRE, whether it
carries a line), then per level the set mean over no correction's, within / warned / silently worse.

    python notes/scripts/declared_verdicts.py COLLECTED.jsonl CASE...
"""
import json
import sys
import warnings
from pathlib import Path

import numpy as np

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import _case_facts
from navapp.geometry.interpolation import interpolation_matrix
from navapp.registration.pipeline import prepare, register
from navapp.simulation.levels import data_level

progress.QUIET = True
warnings.simplefilter("ignore")
rows = {(r["case"], r["level"]): r for r in map(json.loads, open(sys.argv[1]))}
out = []
for case_dir in sys.argv[2:]:
    case_dir = Path(case_dir)
    case = read_case(case_dir)
    model, _ = prepare(case)
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    facts = _case_facts(case_dir, case, model.basis.nodes)
    ident = float(np.linalg.norm(x0 - x1, axis=1).mean())
    for level in ("S", "S+all"):
        ref = round(ident, 3)
        if not facts["pre_aligned"]:
            data = data_level(case_dir, "S", case=case) if level == "S" else case.intraop
            B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
            reg = register(model, data, deform=False)
            ref = round(float(np.linalg.norm(reg.transform(x0, B=B) - x1, axis=1).mean()), 3)
        r = rows[(case_dir.name, level)]
        out.append((case_dir.name, level, facts["pre_aligned"], ident, ref, r["tre_shown"], bool(r["lines"]),
                    r["deformed"]))
        print(*out[-1], flush=True)
for level in ("S", "S+all"):
    o = [x for x in out if x[1] == level]
    within = [x for x in o if x[5] <= x[4] + 1e-9]
    print(level, "set mean", round(np.mean([x[5] for x in o]), 3), "identity", round(np.mean([x[3] for x in o]), 3),
          "ratio", round(np.mean([x[5] for x in o]) / np.mean([x[3] for x in o]), 3),
          "within", len(within), "of", len(o), "warned of those", sum(x[6] for x in within),
          "worse warned", sum(x[6] for x in o if x not in within),
          "silently worse", sum(not x[6] for x in o if x not in within))
