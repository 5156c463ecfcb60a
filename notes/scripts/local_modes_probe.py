"""Probe, not the pipeline: local modes where the data say the surface moved (issue 22, item 3).

Today's registration is fitted first. Where at least MIN_POINTS of the liver-surface data stay more
than OFF_MM off the deformed fit's surface, up to MAX_SOURCES k-means centres of those points each
get a Kelvin point-load source (the displacement of an infinite elastic body under a point
force, regularised over EPS_MM) DEPTH_MM inside the undeformed surface under them. That is 3 modes
per source, force in x, y, z, scaled to 5 mm at most like the control-point modes. They are
appended to J_u; the strain-energy matrix (eq. 13) is extended over them; the model is
registered again with today's guards. The placement and the extension are the package's
(``registration.local_modes``, here with the probe's constants). The truth is read only after both fits.
The constants were set before the first run and not tuned.

    python notes/scripts/local_modes_probe.py OUT.jsonl CASE [CASE ...]
"""

import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.geometry.interpolation import interpolation_matrix
from navapp.geometry.tre import mean_tre
from navapp.registration.local_modes import LocalModeOptions, sources_under, with_sources
from navapp.registration.model import DATA_TO_MODEL
from navapp.registration.pipeline import prepare, register
from navapp.simulation.levels import data_level

OFF_MM, MIN_POINTS, DEPTH_MM, MAX_SOURCES = 2.5, 8, 10.0, 2  # EPS_MM, MODE_MM: the package's (5, 5 mm)


def surface_points(data):
    """The liver-surface data (stylus and its regions), (N, 3) mm."""
    return np.vstack([p for k, p in data.items() if DATA_TO_MODEL[k] not in ("portal", "hepatic", "fiducials")
                      and "centerline" not in k and "contour" not in k])


def extended_model(model, case, reg, data):
    """The model with Kelvin modes under the data the first fit left off, and how many
    sources (None, 0 when the fit left too few points off)."""
    x = reg.transform(model.basis.nodes, beta=reg.libr.beta)  # the deformed fit, whatever the answer shown
    return extend_under(model, case, x, surface_points(data))


def extend_under(model, case, x, pts):
    """The model with Kelvin modes under the surface points ``pts`` (N, 3) mm that lie more
    than OFF_MM off the fitted surface, whose nodes are at ``x`` (M, 3) mm in the same
    frame (``registration.local_modes``, the probe's constants); and how many sources
    (None, 0 when too few points are off)."""
    opts = LocalModeOptions(off_mm=OFF_MM, min_points=MIN_POINTS, depth_mm=DEPTH_MM, max_sources=MAX_SOURCES)
    nodes, sources = sources_under(model, x, pts, opts)
    if not len(nodes):
        return None, 0
    return with_sources(model, nodes, sources, opts), len(nodes)


def each_case(cases):
    """(case folder, Case, registration model) per case, progress bars off."""
    progress.QUIET = True
    for c in cases:
        case = read_case(c)
        yield Path(c), case, prepare(case)[0]


def each_level(case_dir, case):
    """(level, data): the stylus sweep alone (S), then every intraoperative feature (S + all)."""
    for level in ("S", "S+all"):
        yield level, data_level(case_dir, "S", case=case) if level == "S" else case.intraop


def main(out_path, cases):
    with open(out_path, "a") as out:
        for c, case, model in each_case(cases):
            x0, x1 = case.need_truth().tre_points(model.basis.nodes)
            B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)

            def tre(reg, fit=False, x0=x0, x1=x1, B=B):
                pred = reg.transform(x0, beta=reg.libr.beta, B=B) if fit else reg.transform(x0, B=B)
                return round(mean_tre(pred, x1), 3)

            def held_out(reg):  # the cross-validation's held-out RMS, deformable and rigid (mm)
                s = reg.support
                return None if s is None else [round(s.deformable_mm, 3), round(s.rigid_mm, 3)]

            for level, data in each_level(c, case):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # collected from the Registration instead
                    t = time.perf_counter()
                    reg = register(model, data, deform=True)
                    row = {"case": c.name, "level": level, "tre": tre(reg), "tre_fit": tre(reg, True),
                           "answer": "deformable" if reg.deformed else "rigid", "warned": bool(reg.warnings),
                           "held_out": held_out(reg), "s": round(time.perf_counter() - t, 2)}
                    t = time.perf_counter()
                    extended, row["added"] = extended_model(model, case, reg, data)
                    if extended is not None:
                        reg2 = register(extended, data, deform=True)
                        row.update(tre2=tre(reg2), tre2_fit=tre(reg2, True), warned2=bool(reg2.warnings),
                                   held_out2=held_out(reg2),
                                   answer2="deformable" if reg2.deformed else "rigid",
                                   first2=reg2.warnings[0][:60] if reg2.warnings else "")
                    row["s2"] = round(time.perf_counter() - t, 2)
                print(json.dumps(row), file=out, flush=True)
                print(row, flush=True)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])
