"""Issue 47, session 43: would the held-out surface data pick the forces held at the free-floating
basis's own pose (its LIBR fit from the rigid stage, no prior: β's τ, θ) over the answer shown?
The candidate is scored on the choice's own blocks at the chosen λ; ``--leaky``: the pose fitted
to every block (as the choice fits the forces' pose), else refitted to each fold's training
blocks. The truth is read only for the TRE columns.

    python notes/scripts/forces_free_pose_probe.py [--leaky] OUT.csv CASE_DIR...

Columns: case, answer shown, its held-out RMS (mm), the forces' held-out RMS at their own pose,
the candidate's held-out RMS, TRE shown, TRE of the candidate (mm), λ, |τ| of the free pose (mm)."""
import sys, csv, warnings
from dataclasses import replace
from pathlib import Path
import numpy as np
from navapp.anatomy.caseio import read_case
from navapp.geometry.interpolation import interpolation_matrix
from navapp.geometry.tre import tre_stats
from navapp.evaluation.loads import declared_prior, declared_supports, _init
from navapp.registration.pipeline import prepare, register, _settings
from navapp.registration.libr import register_libr
from navapp.registration.forces import SurfaceForces, surface_points, ForceOptions, PoseTerm, _posed_surface, Answer
from navapp.registration.rigid import after, beta_pose
from navapp.registration.support import blocks_of
from navapp.features import LIVER_SURFACE
from navapp.simulation.levels import data_level
warnings.simplefilter("ignore")
leaky = sys.argv[1] == "--leaky"
args = sys.argv[2:] if leaky else sys.argv[1:]
out = open(args[0], "a")
for cd in args[1:]:
    case_dir = Path(cd); case = read_case(case_dir)
    model, _ = prepare(case); sup = prepare(case, **declared_supports(case))[0]
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
    data = data_level(case_dir, "S", case=case)
    prior = declared_prior(case_dir, case)
    reg = register(sup, data, deform=True, init=_init("libr-forces"), pose_prior=prior, surface_forces=True, undeclared=model)
    fc = reg.forces; lam = fc.energy_weight
    tre_ans = tre_stats(reg.transform(x0, B=B), x1).mean_mm
    local = reg.data_model_frame
    opts = _settings(None, _init("libr-forces"))[0]
    opts = replace(opts, weights=replace(opts.weights, pose_prior=None))
    bf = register_libr(model, local, None, opts)
    qf = np.asarray(bf.beta[-6:])
    sf = SurfaceForces(sup.basis); pts = surface_points(local)
    o = replace(ForceOptions(), energy_weight=lam); pf = sf.responses(pts, o.sites)
    term = PoseTerm.of(reg.pose_prior, sup.centroid) if reg.pose_prior is not None else None
    labels = blocks_of({"surface": pts}, o.blocks)["surface"]
    folds = [(np.flatnonzero(labels == b), np.flatnonzero(labels != b)) for b in range(o.blocks)]
    folds = [(h, t) for h, t in folds if len(h) and len(h) < len(pts)]
    counts = np.array([len(h) for h, _ in folds])
    hv = []
    names = [k for k in local if k in LIVER_SURFACE and len(local[k])]
    sizes = np.cumsum([0] + [len(local[k]) for k in names])
    others = {k: p for k, p in local.items() if k not in names}
    for b, (h, t) in enumerate(folds):
        keep = labels != b
        dat = {**others, **{k: local[k][keep[sizes[i]:sizes[i + 1]]] for i, k in enumerate(names) if keep[sizes[i]:sizes[i + 1]].any()}}
        qb = qf if leaky else np.asarray(register_libr(model, dat, None, opts).beta[-6:])
        fw = sf.fit_weights(pf, lam, t, o, term, held_q=qb)
        us = _posed_surface(sf, pf.Xs[:, fw.index] @ fw.w, fw.q, term)
        hv.append(np.sqrt(np.mean(sf.distances(pts[h], us)[0] ** 2)))
    held_free = float(np.average(hv, weights=counts))
    wf = sf.fit_weights(pf, lam, None, o, term, held_q=qf)
    u = sf.field(pf, wf)
    pred = after(reg.rigid, beta_pose(qf, sup.centroid)).apply(x0 + B @ u)
    tre_free = tre_stats(pred, x1).mean_mm
    shown = {Answer.NONE: fc.none_mm, Answer.BASIS: fc.basis_mm, Answer.FORCES: fc.forces_mm[lam]}[fc.answer]
    sf.close()
    row = [case_dir.name, fc.answer.value, round(shown, 3), round(fc.forces_mm[lam], 3), round(held_free, 3),
           round(tre_ans, 3), round(tre_free, 3), lam, round(float(np.linalg.norm(qf[:3])), 2)]
    print(*row, flush=True); out.write(",".join(map(str, row)) + "\n"); out.flush()
