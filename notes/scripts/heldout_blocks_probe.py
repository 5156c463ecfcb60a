"""Issue 47: why the held-out blocks choose the supported basis over better forces (tool1-a, tool2-b,
tooldraw3_1-b, tooldraw3_2-b in session 31). Per block of ``choose_deformation``: its points, its
distance from the other blocks' points, and the held-out RMS (mm) of no deformation, the basis's
fold fit and the forces' fold fit at the chosen λ.

    python notes/scripts/heldout_blocks_probe.py CASE_DIR...
"""
import sys
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import declared_prior, declared_supports
from navapp.registration.forces import (
    ForceOptions,
    SurfaceForces,
    _basis_surface,
    surface_points,
)
from navapp.registration.libr import LMOptions, register_libr
from navapp.registration.pipeline import prepare, register
from navapp.registration.support import SupportOptions, blocks_of
from navapp.simulation.levels import data_level

for arg in sys.argv[1:]:
    case_dir = Path(arg)
    case = read_case(case_dir)
    model, _ = prepare(case, **declared_supports(case))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        reg = register(model, data_level(case_dir, "S", case=case), pose_prior=declared_prior(case_dir, case),
                       surface_forces=True)
    fc = reg.forces
    local, o = reg.data_model_frame, ForceOptions()
    points = surface_points(local)
    labels = blocks_of({"surface": points}, o.blocks)["surface"]
    sf = SurfaceForces(model.basis)
    pf = sf.responses(points, o.sites)
    print(case_dir.name, "answer", fc.answer.value, "λ", fc.energy_weight, "held-out none/basis/forces",
          round(fc.none_mm, 3), fc.basis_mm and round(fc.basis_mm, 3), round(min(fc.forces_mm.values()), 3))
    # the fold fits' settings as the choice's: the declared prior as the fit left it (its scale may differ)
    lm = replace(LMOptions(), max_iterations=SupportOptions.iterations,
                 weights=replace(LMOptions().weights, pose_prior=reg.pose_prior))
    names = [k for k in local if len(local[k]) and k in ("anterior", "posterior", "falciform", "ridge_left",
                                                          "ridge_right")]
    sizes = np.cumsum([0] + [len(local[k]) for k in names])
    for b in range(o.blocks):
        held, train = np.flatnonzero(labels == b), np.flatnonzero(labels != b)
        if not len(held) or not len(train):
            continue
        gap = float(np.median(cKDTree(points[train]).query(points[held])[0]))
        keep = labels != b
        data = {k: local[k][keep[sizes[i]:sizes[i + 1]]] for i, k in enumerate(names)}
        fitted = register_libr(model, data, None, lm, None, None)
        ub = _basis_surface(model, fitted.beta, sf.all_surface)
        fw = sf.fit_weights(pf, fc.energy_weight, train, replace(o, energy_weight=fc.energy_weight))
        uf = pf.Xs[:, fw.index] @ fw.w
        rms = [float(np.sqrt(np.mean(sf.distances(points[held], u)[0] ** 2)))
               for u in (np.zeros_like(ub), ub, uf)]
        print(f"  block {b}: {len(held)} points, median {gap:.1f} mm from the others; held-out RMS none "
              f"{rms[0]:.2f}, basis {rms[1]:.2f}, forces {rms[2]:.2f} mm", flush=True)
    sf.close()
