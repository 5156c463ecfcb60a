"""What a cheaper cross-validation would cost in accuracy (issue 49, session 35): not navapp's rule.

The fresh registration's cross-validation (``support.check_support``) fits each of five folds
from β = 0, deformably and rigidly: about 0.55 s of a 0.9 s registration (CPU, demo). Two cheaper
folds are measured against it here, on every deformable row of Table II's quick design of the
case folders given (``scenarios(quick=True)``):

- ``linear``: one factorisation's worth — the full fit's evaluation at its answer β̂ with its
  Jacobian (the one the error estimate also forms), each fold's training rows reweighted as the
  fold would weigh them (w_F / N_F with N_F the training count), one Gauss–Newton step from β̂ on
  them (correspondences held), and the held-out block evaluated at the step's end with exact
  closest points; the rigid fold likewise, one pose-only step from the rigid pose on the β = 0
  evaluation's rows.
- ``warm``: each fold's deformable LM fit started from β̂ (the full fit's answer and, by the
  model's kept evaluations, its correspondences) instead of β = 0, the rigid folds as today.

Prints one JSON line per row: the exact and the cheaper Support's held-out RMS (rigid,
deformable), verdict (``predicts``) and CPU seconds.

    python notes/scripts/linear_folds_probe.py OUT.jsonl CASE_DIR [CASE_DIR ...]
"""

import json
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.defaults import EDGE_MM, K
from navapp.evaluation.loads import LOAD_LEVELS
from navapp.evaluation.table2 import scenarios
from navapp.features import SALIENT
from navapp.geometry.tre import mean_tre
from navapp.registration.libr import _solve, register_libr
from navapp.registration.model import DATA_TO_MODEL
from navapp.registration.objective import evaluate
from navapp.registration.pipeline import _settings, prepare, register
from navapp.registration.support import Block, SupportOptions, _summary, blocks_of, pooled_rms
from navapp.simulation.levels import case_planes, case_source_levels, data_level, study_data
from navapp.threads import limit_threads


def _step(model, ev, keep_rows, counts, free, options):
    """One Gauss–Newton step at ``ev`` on the rows ``keep_rows`` (bool over the data rows),
    each data feature's rows reweighted by N_F / N_F,train (w_F / N_F of the training fit)."""
    n = model.basis.Ju.shape[1]
    w = ev.w.copy()
    at = 0
    for name, _feat, _S, q, rows, _local in ev.terms:
        r = slice(at, at + len(q))
        kept_points = np.unique(rows[keep_rows[r]]).size
        w[r] = np.where(keep_rows[r], w[r] * counts[name] / max(kept_points, 1), 0.0)
        at += len(q)
    J = ev.J[:, free]
    Js = J * np.sqrt(w)[:, None]
    A = Js.T @ Js
    g = -(J.T @ (w * ev.f))
    if options.energy_curvature and free[:n].any():
        A[:n, :n] += ev.w[-1] * ev.f[-1] * model.basis.energy / model.basis.M
    step = np.zeros(len(ev.beta))
    step[free] = _solve(A, g)
    return ev.beta + step


def _row_blocks(ev, labels):
    """Block label of every residual row (the data rows; prior and energy rows: -2)."""
    out = np.full(len(ev.f), -2)
    at = 0
    for name, _feat, _S, q, rows, _local in ev.terms:
        out[at:at + len(q)] = labels[name][rows]
        at += len(q)
    return out


def cheap_supports(model, data, options, beta_hat, settings: SupportOptions | None = None):
    """(linear Support, its CPU s), (warm Support, its CPU s) on the same blocks as the exact one."""
    settings = settings or SupportOptions()
    labels = blocks_of(data, settings.blocks)
    n = model.basis.Ju.shape[1]
    fold = replace(options, max_iterations=min(options.max_iterations, settings.iterations))
    free_def = np.ones(n + 6, bool)
    if not options.pose:
        free_def[n:] = False
    free_rigid = np.zeros(n + 6, bool)
    free_rigid[n:] = options.pose
    zero = np.zeros(n + 6)
    counts = {k: len(p) for k, p in data.items()}
    inside = any(DATA_TO_MODEL[k] not in ("liver", "fiducials", *SALIENT) for k in data)
    margin = settings.margin_interior if inside else settings.margin
    with limit_threads(1):
        c = time.process_time()
        ev = evaluate(model, data, beta_hat, options.weights, jacobian=True)
        ev0 = evaluate(model, data, zero, options.weights, jacobian=True, alpha_columns=False)
        rb, rb0 = _row_blocks(ev, labels), _row_blocks(ev0, labels)
        blocks = []
        for b in range(settings.blocks):
            held = {k: p[labels[k] == b] for k, p in data.items() if (labels[k] == b).any()}
            if not held or len(held) == 0:
                continue
            beta_b = _step(model, ev, (rb != b)[:len(ev.f)], counts, free_def, options)
            pose_b = _step(model, ev0, (rb0 != b), counts, free_rigid, options) if options.pose else zero
            rigid = pooled_rms(evaluate(model, held, pose_b, options.weights, jacobian=False).features, held)
            deformed = pooled_rms(evaluate(model, held, beta_b, options.weights, jacobian=False).features, held)
            pts = np.vstack(list(held.values()))
            blocks.append(Block(pts.mean(0), len(pts), rigid, deformed))
        linear = (_summary(blocks, margin, 0.0), time.process_time() - c)
    c = time.process_time()
    blocks = []
    for b in range(settings.blocks):
        train = {k: p[labels[k] != b] for k, p in data.items() if (labels[k] != b).any()}
        held = {k: p[labels[k] == b] for k, p in data.items() if (labels[k] == b).any()}
        if not held or not train:
            continue
        fit = register_libr(model, train, beta_hat, fold)
        pose = zero if not options.pose else register_libr(model, train, None, replace(fold, deform=False)).beta
        rigid = pooled_rms(evaluate(model, held, pose, options.weights, jacobian=False).features, held)
        deformed = pooled_rms(evaluate(model, held, fit.beta, options.weights, jacobian=False).features, held)
        pts = np.vstack(list(held.values()))
        blocks.append(Block(pts.mean(0), len(pts), rigid, deformed))
    warm = (_summary(blocks, margin, 0.0), time.process_time() - c)
    return linear, warm


def _rows(case_dir, case):
    """(level, planes, data) of a case: Table II's quick design, or a tool case's two load levels
    (the local-load study's stylus swath "S" and the case's own intraoperative data)."""
    if (Path(case_dir) / "truth").is_dir() and Path(case_dir).name.startswith("tool"):
        for level in LOAD_LEVELS:
            yield level, (), data_level(case_dir, "S", case=case) if level == "S" else case.intraop
        return
    for level, planes in scenarios(case_planes(case_dir), quick=True, sources=case_source_levels(case_dir)):
        if level != "rigid":
            yield level, planes, study_data(case_dir, level, planes, case=case)


def main(out_path, case_dirs):
    progress.QUIET = True
    with open(out_path, "a") as out:
        for case_dir in case_dirs:
            case = read_case(case_dir)
            model, _ = prepare(case, EDGE_MM, K)
            x0, x1 = case.need_truth().tre_points(model.basis.nodes)
            for level, planes, data in _rows(case_dir, case):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    reg = register(model, data)
                if reg.libr is None or reg.support is None:
                    continue
                options, _init = _settings(None, None)
                if reg.rigid.kept:
                    options = replace(options, pose=False)
                local = reg.data_model_frame
                exact, exact_s = reg.support, reg.stages["support"].cpu  # the register's own
                (lin, lin_s), (warm, warm_s) = cheap_supports(model, local, options, reg.libr.beta)
                # the TRE each verdict would show: from a kept pose an unsupported deformation shows
                # the pose alone (``Registration.deformed``); the σ weighing does not depend on the folds
                tre = {"deformable": mean_tre(reg.transform(x0, beta=reg.libr.beta), x1),
                       "rigid": mean_tre(reg.rigid.apply(x0), x1)}
                row = {"case": Path(case_dir).name, "level": level,
                       "planes": "-".join(map(str, planes)), "kept_pose": reg.rigid.kept,
                       "shown_tre_mm": round(mean_tre(reg.transform(x0), x1), 4)}
                for tag, s, sec in (("exact", exact, exact_s), ("linear", lin, lin_s), ("warm", warm, warm_s)):
                    deformed = not reg.rigid.kept or (s.predicts and exact.significant)
                    row[tag] = {"rigid_mm": round(s.rigid_mm, 4), "deformable_mm": round(s.deformable_mm, 4),
                                "predicts": s.predicts, "cpu_s": round(sec, 3),
                                "tre_mm": round(tre["deformable" if deformed else "rigid"], 4),
                                "blocks": [[round(b.rigid_mm, 3), round(b.deformable_mm, 3)] for b in s.blocks]}
                print(json.dumps(row), file=out, flush=True)
                print(json.dumps({k: (v if not isinstance(v, dict) else {kk: vv for kk, vv in v.items()
                                                                         if kk != "blocks"}) for k, v in row.items()}),
                      flush=True)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])
