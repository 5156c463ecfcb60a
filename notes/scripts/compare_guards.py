"""Table II's quick design registered twice, without and with the guards against local loads,
paired row by row: what the kept pose and the cross-validated deformation change on the
study cases (they must not get worse).

    python notes/scripts/compare_guards.py CASE [CASE ...] [--out notes/guards_table2.csv]

Per case: rigid, S, two S + 1/2/3 plane choices (seeded as ``table2.scenarios(quick=True)``),
S + all, CBCT, iCT. Prints per level the mean TRE both ways and how often the guarded
answer fell back to rigid.
"""

import argparse
import csv
import json
from pathlib import Path

import numpy as np

from navapp import progress
from navapp.evaluation.table2 import LEVELS, run_chunk, scenarios
from navapp.registration.pipeline import RobustOptions

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("cases", type=Path, nargs="+")
ap.add_argument("--out", type=Path, default=Path("notes/guards_table2.csv"))
args = ap.parse_args()
progress.QUIET = True
rows = []
args.out.parent.mkdir(parents=True, exist_ok=True)
for c in args.cases:
    items = scenarios(quick=True)
    before = run_chunk(c, items, init=RobustOptions.unguarded())
    after = run_chunk(c, items, init=RobustOptions())
    for b, a in zip(before, after, strict=True):
        rows.append({"case": b["case"], "level": b["level"], "planes": b["planes"], "unguarded_mm": b["tre_mean_mm"],
                     "guarded_mm": a["tre_mean_mm"], "unguarded_s": b["seconds"], "guarded_s": a["seconds"]})
    print(json.dumps({"case": c.name, "rows": len(before)}), flush=True)
    with args.out.open("w", newline="") as fh:  # after every case: a long run keeps what it has
        w = csv.DictWriter(fh, list(rows[0]))
        w.writeheader()
        w.writerows(rows)
for level in LEVELS:
    lv = [r for r in rows if r["level"] == level]
    u = np.mean([r["unguarded_mm"] for r in lv])
    g = np.mean([r["guarded_mm"] for r in lv])
    secs = [round(float(np.median([r[k] for r in lv])), 3) for k in ("unguarded_s", "guarded_s")]
    print(json.dumps({"level": level, "n": len(lv), "unguarded_mm": round(float(u), 3),
                      "guarded_mm": round(float(g), 3),
                      "changed": sum(abs(r["guarded_mm"] - r["unguarded_mm"]) > 1e-3 for r in lv), "median_s": secs}))
