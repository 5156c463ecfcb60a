"""Issue 46's Done-when per set and level for ``libr-declared`` rows of a loads CSV: set mean TRE,
× no correction, within the reference (``loads.verdicts``), warned of those, worse and warned,
silently worse; and which cases.

    python notes/scripts/declared_done_when.py NAME RESULTS.csv [NAME RESULTS.csv ...]
"""
import csv
import sys

import numpy as np

from navapp.evaluation.loads import verdicts


def load(p):
    rows = list(csv.DictReader(open(p)))
    for r in rows:
        r["tre_mean_mm"] = float(r["tre_mean_mm"]); r["warned"] = r["warned"] == "True"; r["pre_aligned"] = r["pre_aligned"] == "True"
    return rows
def table(rows, name):
    v = verdicts(rows, "libr-declared")
    by = {(r["case"], r["level"], r["method"]): r for r in rows}
    for level in ("S", "S+all"):
        vv = {k: x for k, x in v.items() if k[1] == level}
        mean = np.mean([x["tre"] for x in vv.values()]); ident = np.mean([by[(c, level, "identity")]["tre_mean_mm"] for c, _ in vv])
        within = [k for k, x in vv.items() if x["ok"]]
        ww = [k[0] for k in within if vv[k]["warned"]]
        worse = [k for k, x in vv.items() if not x["ok"]]
        print(f"| {name} | {level} | {mean:.2f} | {mean/ident:.3f} | {len(within)} of {len(vv)} | {len(ww)} ({100*len(ww)/len(within):.0f} %) | {sum(vv[k]['warned'] for k in worse)} | {sum(vv[k]['silent_worse'] for k in worse)} |")
        print("   warned within:", ww, " worse:", [(k[0], vv[k]['tre'], vv[k]['reference'], vv[k]['warned']) for k in worse])
for name, p in zip(sys.argv[1::2], sys.argv[2::2]):
    table(load(p), name)
