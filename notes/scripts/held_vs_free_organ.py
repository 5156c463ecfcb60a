"""Issue 47, session 39: how far a held answer is from the undeclared one over the organ and at the
targets (mean |x_held - x_free|), beside each answer's predicted error over the organ (``OrganError``)
and the supports' check, per case and level, the pose declared as the scene made it.

    python notes/scripts/held_vs_free_organ.py OUT.jsonl CASE...
"""
import json
import sys
import warnings
from pathlib import Path

import numpy as np

from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import declared_prior
from navapp.geometry.interpolation import interpolation_matrix
from navapp.geometry.tre import mean_tre
from navapp.registration.pipeline import prepare, register
from navapp.registration.uncertainty import organ_nodes
from navapp.simulation.levels import data_level
from navapp.simulation.scene import load_scene

WRONG = {"ligaments": "posterior", "posterior": "ligaments", "bare_area": "posterior"}
out = open(sys.argv[1], "a")
for c in map(Path, sys.argv[2:]):
    case = read_case(c); scene = load_scene(case.settings["scene"])
    free, _ = prepare(case)
    x0, x1 = case.need_truth().tre_points(free.basis.nodes)
    B = interpolation_matrix(free.basis.nodes, free.basis.tets, x0)
    nodes = organ_nodes(free)
    Bn = interpolation_matrix(free.basis.nodes, free.basis.tets, free.basis.nodes[nodes])
    models = {"none": free, "right": prepare(case, supports=scene.supports)[0], "wrong": prepare(case, supports=WRONG[scene.supports])[0]}
    prior = declared_prior(c, case)
    for level in ("S", "S+all"):
        data = data_level(c, "S", case=case) if level == "S" else case.intraop
        regs = {}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for how, m in models.items():
                regs[how] = register(m, data, pose_prior=prior)
        pos = {h: r.transform(free.basis.nodes[nodes], B=Bn) for h, r in regs.items()}
        post = {h: r.transform(x0, B=B) for h, r in regs.items()}
        for how in ("right", "wrong"):
            r = regs[how]
            d_org = float(np.linalg.norm(pos[how] - pos["none"], axis=1).mean())
            d_tgt = float(np.linalg.norm(post[how] - post["none"], axis=1).mean())
            row = dict(case=c.name, level=level, supports=how, tre=round(mean_tre(post[how], x1),3),
                       tre_none=round(mean_tre(post["none"], x1),3), deformed=r.deformed, none_deformed=regs["none"].deformed,
                       d_organ=round(d_org,3), d_targets=round(d_tgt,3),
                       organ_err=None if r.organ is None else round(r.organ.mean_mm,3),
                       none_organ_err=None if regs["none"].organ is None else round(regs["none"].organ.mean_mm,3),
                       warned=bool(r.warnings), held=None if r.held is None else r.held.as_dict())
            print(json.dumps(row), flush=True); out.write(json.dumps(row)+"\n"); out.flush()
