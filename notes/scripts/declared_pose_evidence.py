"""With the pose declared, one level: the TRE of the answer shown, whether it deformed, its
``PoseEvidence`` (the fitted pose's move against its posterior σ_pose) and its lines.

    python notes/scripts/declared_pose_evidence.py S+all /work/cases/tool0-c /work/cases/tool2-g
"""

import sys
import warnings

import numpy as np

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import declared_prior
from navapp.registration.pipeline import prepare, register
from navapp.simulation.levels import data_level

progress.QUIET = True
warnings.simplefilter("ignore")
level = sys.argv[1]
for case_dir in sys.argv[2:]:
    case = read_case(case_dir)
    model, _ = prepare(case)
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    data = data_level(case_dir, "S", case=case) if level == "S" else case.intraop
    reg = register(model, data, pose_prior=declared_prior(case_dir, case))
    tre = float(np.linalg.norm(reg.transform(x0) - x1, axis=1).mean())
    evidence = reg.pose_evidence.as_dict() if reg.pose_evidence is not None else None
    print(case_dir.rstrip("/").split("/")[-1], level, "shown", round(tre, 3), "D", reg.deformed, evidence,
          reg.warnings, flush=True)
