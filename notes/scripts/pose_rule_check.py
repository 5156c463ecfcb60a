"""Which pose the rigid stage answers with (``pose.choose_pose``: given, local or fitted)
on every trial of the robustness design (offsets, label noise), one JSON line per trial:
where it says "fitted" the guarded registration is the unguarded one (docs/decisions/local-loads.md,
"Local loads").

    python notes/scripts/pose_rule_check.py STUDY_CASE [STUDY_CASE ...] > pose_rule.jsonl
"""

import json
import sys
import warnings
from pathlib import Path

from navapp import progress
from navapp.anatomy.caseio import read_case, read_surface
from navapp.evaluation.robustness import design, trial_data
from navapp.registration.pipeline import prepare, register

progress.QUIET = True
warnings.simplefilter("ignore")
for case_dir in map(Path, sys.argv[1:]):
    case = read_case(case_dir)
    model, _ = prepare(case)
    surface, _ = read_surface(case_dir / "truth" / "liver.ply", closed=False)
    surface = surface[0] if isinstance(surface, tuple) else surface
    for trial in design([case_dir.name], draws=4):
        data, _, _ = trial_data(case_dir, case, trial, surface)
        c = register(model, data, deform=False).pose_choice
        print(json.dumps({"case": trial.case, "condition": trial.condition, "draw": trial.draw,
                          "angle_deg": trial.angle_deg, "source": c.source.value if c else None,
                          "moved_mm": None if c is None or c.moved_mm is None else round(c.moved_mm, 2),
                          "on_model": {k.value: round(v, 3) for k, v in c.on_model.items()} if c else None}),
              flush=True)
