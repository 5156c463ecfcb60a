"""Issue 47, session 40: what the choice of λ costs the surface forces, read off one run.

    python notes/scripts/forces_lambda_hindsight.py OUT.jsonl CASE_DIR...
    python notes/scripts/forces_lambda_hindsight.py --rules OUT.jsonl

Per case at S (supports and pose declared as the scene made them, as ``libr-forces``): the
registration with surface forces, and — from the same run — the forces' fit to every block at
each λ as ``choose_deformation`` makes it (with the pose term), its TRE; and the held-out RMS of
the forces at each λ on interleaved folds (the points dealt at random to as many folds as
blocks, the pose held as the blocks' fits hold it). ``--rules`` reads the rows: the answer shown
(the one-standard-error rule on the blocks), the blocks' least λ, the interleaved folds' rule
and least, the interleaved folds' least among the λ the blocks admit (one paired SE), and the
best λ in hindsight — each with the answer the choice among no deformation, the basis and the
forces would then show (docs/decisions/local-loads.md, "interior nodes")."""

import json
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import declared_prior, declared_supports
from navapp.geometry.interpolation import interpolation_matrix
from navapp.geometry.tre import mean_tre
from navapp.registration import forces as F
from navapp.registration import pipeline as PL
from navapp.registration.rigid import beta_pose
from navapp.simulation.levels import data_level

FIT = F.SurfaceForces.fit_weights
CHOOSE = PL.choose_deformation


def interleaved(forces, pf, points, options, weights, pose) -> dict:
    """λ → each interleaved fold's held-out RMS (mm), the pose held at the all-data fit's."""
    dealt = np.random.default_rng(0).permutation(len(points)) % options.blocks
    res = {}
    for lam in weights:
        o = replace(options, energy_weight=lam)
        q = None if pose is None else FIT(forces, pf, lam, None, o, pose).q
        rms = []
        for b in range(options.blocks):
            held, train = np.flatnonzero(dealt == b), np.flatnonzero(dealt != b)
            fw = FIT(forces, pf, lam, train, o, pose, held_q=q)
            us = F._posed_surface(forces, pf.Xs[:, fw.index] @ fw.w, fw.q, pose)
            rms.append(float(np.sqrt(np.mean(forces.distances(points[held], us)[0] ** 2))))
        res[f"{lam:g}"] = rms
    return {"random_folds_mm": res, "random_counts": [int(np.sum(dealt == b)) for b in range(options.blocks)]}


def run_case(case_dir: Path) -> dict:
    case = read_case(case_dir)
    model, _ = prepare_model(case)
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
    data = data_level(case_dir, "S", case=case)
    full, extra = {}, {}

    def fit_weights(self, pf, lam, train=None, options=None, pose=None, rigid_only=False, held_q=None):
        wf = FIT(self, pf, lam, train, options, pose, rigid_only, held_q)
        if train is None and held_q is None and not rigid_only:  # the forces fitted to every block
            full[lam] = (self.field(pf, wf), wf.q, wf.rms_mm)
        return wf

    def choose(forces, model, local, basis_beta, libr_options, options=None, weights=F.ENERGY_WEIGHTS,
               cancel=None, free=None, pose=None):
        options = options or F.ForceOptions()
        choice = CHOOSE(forces, model, local, basis_beta, libr_options, options, weights, cancel, free, pose)
        points = F.surface_points(local)
        extra.update(interleaved(forces, forces.responses(points, options.sites), points, options, weights, pose))
        return choice

    F.SurfaceForces.fit_weights, PL.choose_deformation = fit_weights, choose
    t = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            reg = PL.register(model, data, pose_prior=declared_prior(case_dir, case), surface_forces=True)
    finally:
        F.SurfaceForces.fit_weights, PL.choose_deformation = FIT, CHOOSE
    fc = reg.forces

    def tre_of(u, q):
        moved = x0 + B @ u
        if q is not None:
            moved = beta_pose(q, model.centroid).apply(moved)
        return round(mean_tre(reg.rigid.apply(moved), x1), 3)

    return {"case": case_dir.name, "identity": round(mean_tre(x0, x1), 3),
            "none": round(mean_tre(reg.rigid.apply(x0), x1), 3),
            "basis": round(mean_tre(reg.transform(x0, beta=reg.libr.beta, B=B), x1), 3),
            "shown": round(mean_tre(reg.transform(x0, B=B), x1), 3), "answer": fc.answer.value,
            "energy_weight": fc.energy_weight, "heldout_none_mm": fc.none_mm, "heldout_basis_mm": fc.basis_mm,
            "heldout_free_mm": fc.free_mm,
            "heldout_forces_blocks_mm": {f"{k:g}": [float(x) for x in v] for k, v in fc.forces_blocks_mm.items()},
            "block_points": [int(c) for c in fc.block_points],
            "forces_by_lambda": {f"{k:g}": tre_of(u, q) for k, (u, q, _) in full.items()},
            "rms_by_lambda": {f"{k:g}": round(r, 3) for k, (_, _, r) in full.items()},
            "warned": bool(reg.warnings), **extra, "seconds_total": round(time.perf_counter() - t, 1)}


def prepare_model(case):
    return PL.prepare(case, **declared_supports(case))


def admitted(blocks: dict, counts: np.ndarray) -> list:
    """The λ within one paired standard error of the blocks' best (``forces.one_standard_error``'s set)."""
    p = counts / counts.sum()
    mean = {k: float(p @ v) for k, v in blocks.items()}
    best = min(mean, key=lambda k: (mean[k], -k))
    ok = []
    for k, v in blocks.items():
        d = v - blocks[best]
        e = float(p @ d)
        if e <= float(np.sqrt(len(p) / max(len(p) - 1, 1) * np.sum(p ** 2 * (d - e) ** 2))):
            ok.append(k)
    return ok


def rules(path: str) -> None:
    rows = [json.loads(line) for line in open(path)]
    total: dict[str, float] = {}
    worse: dict[str, list] = {}
    for r in rows:
        counts = np.array(r["block_points"], float)
        blocks = {float(k): np.array(v) for k, v in r["heldout_forces_blocks_mm"].items()}
        mean = {k: float(np.average(v, weights=counts)) for k, v in blocks.items()}
        dealt = np.array(r["random_counts"], float)
        folds = {float(k): np.array(v) for k, v in r["random_folds_mm"].items()}
        fmean = {k: float(np.average(v, weights=dealt)) for k, v in folds.items()}
        by_lam = {float(k): v for k, v in r["forces_by_lambda"].items()}

        def shown(lam, r=r, mean=mean, by_lam=by_lam):
            scores = {"none": r["heldout_none_mm"], "forces": mean[lam]}
            if r["heldout_basis_mm"] is not None:
                scores["basis"] = r["heldout_basis_mm"]
            a = min(scores, key=lambda a: (scores[a], a != "none"))  # a tie: no deformation
            return {"none": r["none"], "basis": r["basis"], "forces": by_lam[lam]}[a]

        lam = {"blocks 1-SE (shown)": F.one_standard_error(blocks, counts),
               "blocks least": min(mean, key=lambda k: (mean[k], -k)),
               "interleaved 1-SE": F.one_standard_error(folds, dealt),
               "interleaved least": min(fmean, key=fmean.get),
               "interleaved least, blocks admit": min(admitted(blocks, counts), key=lambda k: fmean[k])}
        res = {"identity": r["identity"], "shown": r["shown"], **{k: shown(v) for k, v in lam.items()},
               "forces, best λ in hindsight": min(by_lam.values())}
        for k, v in res.items():
            total[k] = total.get(k, 0.0) + v
            if v > r["identity"]:
                worse.setdefault(k, []).append(r["case"])
        print(r["case"], {k: round(v, 3) for k, v in res.items()}, {k: f"{v:g}" for k, v in lam.items()})
    n = len(rows)
    print(n, "cases, mean TRE mm (× no correction):",
          {k: f"{v / n:.3f} ({v / total['identity']:.3f})" for k, v in total.items()})
    print("worse than no correction:", worse)


if __name__ == "__main__":
    if sys.argv[1] == "--rules":
        rules(sys.argv[2])
    else:
        for arg in sys.argv[2:]:
            row = run_case(Path(arg))
            with Path(sys.argv[1]).open("a") as fh:
                fh.write(json.dumps(row) + "\n")
            print(json.dumps(row), flush=True)
