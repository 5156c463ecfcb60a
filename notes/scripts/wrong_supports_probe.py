"""Wrong declared supports against right and none (issue 47: "a posterior support declared where
the scene held the ligaments"), and what the free basis's held-out RMS on the same folds says.

    python notes/scripts/wrong_supports_probe.py OUT.jsonl CASE...

Per case and level (S, S+all), the pose declared as the scene made it: LIBR on the free basis,
on the basis held at the scene's supports, and at wrong ones (ligaments → posterior, posterior →
ligaments, bare_area → posterior). Each row: TRE mean (and no correction's), answer, warnings, the
answer's held-out RMS (its cross-validation) and the supports' test against the free basis
(``Registration.held``: since session 39 also the organ's change from the free answer and what
the held-out data bear out).
"""

import json
import sys
import time
import warnings
from pathlib import Path

from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import LOAD_LEVELS, declared_prior
from navapp.geometry.interpolation import interpolation_matrix
from navapp.geometry.tre import mean_tre
from navapp.registration.pipeline import prepare, register
from navapp.simulation.levels import data_level
from navapp.simulation.scene import load_scene

WRONG = {"ligaments": "posterior", "posterior": "ligaments", "bare_area": "posterior"}


def main(out, cases):
    with open(out, "a") as fh:
        for c in cases:
            c = Path(c)
            case = read_case(c)
            scene = load_scene(case.settings["scene"])
            free, _ = prepare(case)
            x0, x1 = case.need_truth().tre_points(free.basis.nodes)
            B = interpolation_matrix(free.basis.nodes, free.basis.tets, x0)
            models = {"none": free, "right": prepare(case, supports=scene.supports)[0],
                      "wrong": prepare(case, supports=WRONG[scene.supports])[0]}
            prior = declared_prior(c, case)
            for level in LOAD_LEVELS:
                data = data_level(c, "S", case=case) if level == "S" else case.intraop
                for how, model in models.items():
                    t = time.perf_counter()
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        reg = register(model, data, pose_prior=prior)
                    sec = time.perf_counter() - t
                    row = {"case": c.name, "level": level, "supports": how, "held": model.basis.settings.supports,
                           "scene": scene.supports, "tre": round(mean_tre(reg.transform(x0, B=B), x1), 3),
                           "identity": round(mean_tre(x0, x1), 3),
                           "deformed": reg.deformed, "warnings": [w.text for w in reg.warnings],
                           "seconds": round(sec, 2)}
                    s = reg.support
                    if s is not None:
                        row.update(rigid_heldout=round(s.rigid_mm, 4), deformable_heldout=round(s.deformable_mm, 4),
                                   shown_heldout=round(s.deformable_mm if reg.deformed else s.rigid_mm, 4))
                    if reg.held is not None:
                        row["held_check"] = reg.held.as_dict()
                    print(json.dumps(row), flush=True)
                    fh.write(json.dumps(row) + "\n")
                    fh.flush()


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])
