"""Probe: the choice between today's basis and the Kelvin-extended one
(``local_modes_probe.py``), with the sources placed inside each fold of the cross-validation,
so that no held-out block has a say in where its modes go.

Per registration: today's registration (its pose and LM settings), the data in the model frame,
the same five spatial blocks as ``support.check_support``; per block, today's basis and the
extended one (sources from the training data's own fit) are fitted to the other four blocks
and the held-out RMS of each is kept. JSON lines appended to OUT, one per registration:
``folds`` = [deformable held-out RMS with today's basis, with the extended one], mm.

    python notes/scripts/local_modes_folds.py OUT.jsonl CASE [CASE ...]
"""

import json
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

from navapp.registration.libr import register_libr
from navapp.registration.model import deform, usable_data
from navapp.registration.objective import evaluate
from navapp.registration.pipeline import _settings, register
from navapp.registration.support import SupportOptions, blocks_of, pooled_rms

sys.path.insert(0, str(Path(__file__).parent))
from local_modes_probe import each_case, each_level, extend_under, surface_points  # noqa: E402


def extended_for(model, case, beta, train):
    """The model extended under the training data its own fit (``beta``) leaves off, or None."""
    b = model.basis
    n = len(beta) - 6
    _, x = deform(b.nodes, (b.Ju @ beta[:n]).reshape(-1, 3), beta, model.centroid)
    return extend_under(model, case, x, surface_points(train))[0]


def folds(model, case, data, reg):
    settings = SupportOptions()
    options, _ = _settings(None, None)
    if reg.rigid.kept:
        options = replace(options, pose=False)
    fold = replace(options, max_iterations=min(options.max_iterations, settings.iterations))
    local = {k: reg.rigid.inverse(p) for k, p in usable_data(model, data).items()}
    labels = blocks_of(local, settings.blocks)
    base, ext, weight = [], [], []
    for blk in range(settings.blocks):
        train = {k: p[labels[k] != blk] for k, p in local.items() if (labels[k] != blk).any()}
        held = {k: p[labels[k] == blk] for k, p in local.items() if (labels[k] == blk).any()}
        if not held or not train:
            continue
        fit = register_libr(model, train, None, fold, None, None)
        r1 = pooled_rms(evaluate(model, held, fit.beta, options.weights, jacobian=False).features, held)
        m2 = extended_for(model, case, fit.beta, train)
        if m2 is None:
            r2 = r1
        else:
            fit2 = register_libr(m2, train, None, fold, None, None)
            r2 = pooled_rms(evaluate(m2, held, fit2.beta, options.weights, jacobian=False).features, held)
        base.append(r1)
        ext.append(r2)
        weight.append(sum(len(p) for p in held.values()))
    return [round(float(np.average(base, weights=weight)), 3), round(float(np.average(ext, weights=weight)), 3)]


def main(out_path, cases):
    with open(out_path, "a") as out:
        for c, case, model in each_case(cases):
            for level, data in each_level(c, case):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    t = time.perf_counter()
                    reg = register(model, data, deform=True)
                    row = {"case": c.name, "level": level,
                           "held_out": None if reg.support is None else round(reg.support.deformable_mm, 3),
                           "folds": folds(model, case, data, reg), "s": round(time.perf_counter() - t, 1)}
                print(json.dumps(row), file=out, flush=True)
                print(row, flush=True)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])
