"""Probe: does a larger k make the dent? Each case at S and at S + all, today's guarded
registration with each k given; the truth is read after the fit. JSON lines appended to OUT.

    python notes/scripts/k_probe.py OUT 45,90 CASE [CASE ...]
"""

import json
import sys
import time
import warnings
from pathlib import Path

from navapp import progress
from navapp.anatomy.caseio import read_case
from navapp.defaults import EDGE_MM
from navapp.geometry.interpolation import interpolation_matrix
from navapp.geometry.tre import tre_stats
from navapp.registration.pipeline import prepare, register
from navapp.simulation.levels import data_level


def main(out_path: str, ks: str, cases: list[str]) -> None:
    progress.QUIET = True
    with open(out_path, "a") as out:
        for c in cases:
            case = read_case(c)
            for level in ("S", "S+all"):
                data = data_level(Path(c), "S", case=case) if level == "S" else case.intraop
                for k in (int(k) for k in ks.split(",")):
                    t0 = time.perf_counter()
                    model, _ = prepare(case, EDGE_MM, k)
                    prepare_s = time.perf_counter() - t0  # from the cache after the first case of a liver
                    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
                    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")  # collected from the Registration instead
                        t = time.perf_counter()
                        reg = register(model, data, deform=True)
                        sec = time.perf_counter() - t
                    st = tre_stats(reg.transform(x0, B=B), x1)
                    row = {"case": Path(c).name, "level": level, "k": k, "tre": round(st.mean_mm, 3),
                           "answer": "deformable" if reg.deformed else "rigid", "warned": bool(reg.warnings),
                           "first": reg.warnings[0][:70] if reg.warnings else "", "seconds": round(sec, 2),
                           "prepare_s": round(prepare_s, 1)}
                    print(json.dumps(row), file=out, flush=True)
                    print(row, flush=True)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], sys.argv[3:])
