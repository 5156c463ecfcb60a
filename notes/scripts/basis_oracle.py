"""Can the basis represent a case's true displacement? The least-squares projection of the
truth at the TRE targets onto the free and the held basis's modes (and modes + a small rigid
motion), mean error over the targets; and how far the surface data lie from the largest
displacement (issue 47, session 38: the `-b` cases).

    python notes/scripts/basis_oracle.py CASE_DIR...
"""
import sys, warnings
import numpy as np
from pathlib import Path
from navapp.anatomy.caseio import read_case
from navapp.registration.pipeline import prepare
from navapp.geometry.interpolation import interpolation_matrix
from navapp.simulation.scene import load_scene
from navapp.simulation.levels import data_level
from scipy.spatial import cKDTree
for c in sys.argv[1:]:
    c = Path(c)
    case = read_case(c)
    scene = load_scene(case.settings["scene"])
    free, _ = prepare(case)
    x0, x1 = case.need_truth().tre_points(free.basis.nodes)
    B = interpolation_matrix(free.basis.nodes, free.basis.tets, x0)
    d = x1 - x0
    data = data_level(c, "S", case=case)
    pts = np.vstack(list(data.values()))
    for name, model in (("free", free), ("held", prepare(case, supports=scene.supports, release=scene.release)[0])):
        J = model.basis.modes_at(B)  # (P, 3, n)
        P, _, n = J.shape
        # rigid: small rotation about centroid + translation
        r = x0 - x0.mean(0)
        R = np.zeros((P, 3, 6)); R[:, :, :3] = np.eye(3)
        for a in range(3):
            e = np.zeros(3); e[a] = 1; R[:, :, 3 + a] = np.cross(e, r)
        A = J.reshape(3 * P, n)
        AR = np.concatenate([J, R], axis=2).reshape(3 * P, n + 6)
        for label, M in (("modes", A), ("modes+rigid", AR)):
            coef, *_ = np.linalg.lstsq(M, d.ravel(), rcond=None)
            res = (d.ravel() - M @ coef).reshape(-1, 3)
            print(c.name, name, label, "oracle TRE", round(float(np.linalg.norm(res, axis=1).mean()), 2),
                  "identity", round(float(np.linalg.norm(d, axis=1).mean()), 2), flush=True)
        # distance from the data patch to the largest true displacement
    big = x0[np.argmax(np.linalg.norm(d, axis=1))]
    print(c.name, "data points", len(pts), "nearest data to the largest displacement (mm)",
          round(float(cKDTree(pts).query(big)[0]), 1))
