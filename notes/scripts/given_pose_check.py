"""Where the rule that holds the given pose when ICP's answer is in doubt (``pose.prefer_given``)
changes a registration of the study cases: Table II's CBCT and iCT rows (the levels whose rigid
stage is not the shared stylus ICP) and the robustness design's trials of one draw (every
offset and label condition). One JSON line per registration: the pose's source and TRE; where
the rule took the given pose, the TRE with the rule off too (docs/decisions/local-loads.md, "Local loads").

    python notes/scripts/given_pose_check.py STUDY_CASE [STUDY_CASE ...] > given_pose.jsonl
"""

import json
import sys
import warnings
from pathlib import Path

import numpy as np

from navapp import progress
from navapp.anatomy.caseio import read_case, read_surface
from navapp.evaluation.robustness import design, trial_data
from navapp.geometry.interpolation import interpolation_matrix
from navapp.registration import pipeline
from navapp.simulation.levels import study_data

progress.QUIET = True
warnings.simplefilter("ignore")
RULE = pipeline.prefer_given


def tre(reg, x0, x1, B) -> float:
    return float(np.linalg.norm(reg.transform(x0, B=B) - x1, axis=1).mean())


def check(model, data, x0, x1, B, **where):
    pipeline.prefer_given = RULE
    reg = pipeline.register(model, data)
    src = reg.pose_choice.source.value if reg.pose_choice else None
    row = {**where, "source": src, "tre_mm": round(tre(reg, x0, x1, B), 3)}
    if src == "given-fits":
        pipeline.prefer_given = lambda *a, **k: None
        row["tre_rule_off_mm"] = round(tre(pipeline.register(model, data), x0, x1, B), 3)
        pipeline.prefer_given = RULE
    print(json.dumps(row), flush=True)


for case_dir in map(Path, sys.argv[1:]):
    case = read_case(case_dir)
    model, _ = pipeline.prepare(case)
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
    for level in ("CBCT", "iCT"):
        check(model, study_data(case_dir, level, case=case), x0, x1, B, case=case_dir.name, level=level)
    surface, _ = read_surface(case_dir / "truth" / "liver.ply", closed=False)
    surface = surface[0] if isinstance(surface, tuple) else surface
    for trial in design([case_dir.name], draws=1):
        data, move, _ = trial_data(case_dir, case, trial, surface)
        check(model, data, x0, move(x1), B, case=case_dir.name, level="robustness", condition=trial.condition,
              angle_deg=trial.angle_deg)
