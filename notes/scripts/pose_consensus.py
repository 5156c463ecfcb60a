"""How much of the surface data lies on the model at the given pose (G), at the trimmed fit
from it (T) and at the multi-start ICP's pose (I), with each pose's rigid TRE, and LIBR's
TRE from T with the pose fixed and free: the measurements behind ``pose.POSE_RULE``
(docs/decisions/local-loads.md, "Local loads").

    python notes/scripts/pose_consensus.py S|S+all CASE [CASE ...]

f1, f2: fraction of the surface points within 1 and 2 mm of the model; med: their median
distance (mm); moved: how far the trimmed fit moved the data (RMS mm).
"""

import sys
import warnings
from dataclasses import replace

import numpy as np

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.geometry.interpolation import interpolation_matrix
from navapp.geometry.tre import mean_tre
from navapp.registration.pipeline import RobustOptions, prepare, register
from navapp.registration.pose import _distances, trimmed_pose
from navapp.registration.rigid import RigidResult
from navapp.simulation.levels import data_level

progress.QUIET = True
warnings.simplefilter("ignore")
given = RigidResult(np.eye(3), np.zeros(3), 0, 0.0)
level = sys.argv[1]
for case_dir in sys.argv[2:]:
    case = read_case(case_dir)
    model, _ = prepare(case)
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
    data = data_level(case_dir, "S", case=case) if level == "S" else case.intraop
    icp = register(model, data, deform=False, init=RobustOptions.unguarded()).rigid
    trimmed, moved = trimmed_pose(model, data, given)
    out = [case_dir.rstrip("/").split("/")[-1], level, f"moved={moved:.1f}"]
    for name, pose in (("G", given), ("T", trimmed), ("I", icp)):
        d = _distances(model, data, pose)
        tre = mean_tre(pose.apply(x0), x1)
        out.append(f"{name}: f1={np.mean(d < 1):.2f} f2={np.mean(d < 2):.2f} med={np.median(d):.2f} tre={tre:.2f}")
    for name, kept in (("LT-fix", True), ("LT-free", False)):
        reg = register(model, data, rigid=replace(trimmed, kept=kept), init=RobustOptions.unguarded())
        out.append(f"{name}={mean_tre(reg.transform(x0, B=B), x1):.2f}")
    print(" | ".join(out), flush=True)
