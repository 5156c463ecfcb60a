"""The band on the declared local-load registrations, before and after a change to the estimate,
from the arrays ``band_targets_collect.py`` wrote (same cases, two runs): per level, the mean over
registrations of the fraction of targets whose true error (of the deformable fit the estimate
describes) lies in [lower, upper], over every registration and over those shown with a band (the
deformable answers); the share under the upper edge; how many registrations hold ≥ 90 %; mean ê;
the lowest ratio of the organ error quoted to the answer's true mean error (deformable answers);
and every registration whose answer, TRE or lines changed.

    python notes/scripts/band_targets_judge.py BEFORE_DIR BEFORE.jsonl AFTER_DIR AFTER.jsonl
"""

import json
import sys
from pathlib import Path

import numpy as np


def load(folder: str, lines: str) -> dict:
    rows = [json.loads(x) for x in Path(lines).read_text().splitlines() if x.strip()]
    out = {}
    for r in rows:
        z = np.load(Path(folder) / f"{r['case']}_{r['level']}.npz")
        out[r["case"], r["level"]] = (r, {k: z[k] for k in z.files})
    return out


before, after = load(sys.argv[1], sys.argv[2]), load(sys.argv[3], sys.argv[4])
keys = [k for k in before if k in after]
for level in ("S", "S+all"):
    for kind in ("all", "shown"):
        ks = [k for k in keys if k[1] == level and (kind == "all" or after[k][0]["deformed"])]
        if not ks:
            continue
        cells = []
        for run in (before, after):
            cov = [float(((z["err"] >= z["lower"]) & (z["err"] <= z["upper"])).mean()) for _, z in (run[k] for k in ks)]
            up = [float((z["err"] <= z["upper"]).mean()) for _, z in (run[k] for k in ks)]
            pred = [float(z["pred"].mean()) for _, z in (run[k] for k in ks)]
            cells.append((np.mean(cov), np.mean(up), sum(c >= 0.9 for c in cov), np.mean(pred)))
        (c0, u0, n0, p0), (c1, u1, n1, p1) = cells
        print(f"{level:5s} {kind:5s} n={len(ks):2d}  in band {c0:.3f} → {c1:.3f}  under upper {u0:.3f} → {u1:.3f}  "
              f"≥ 90 %: {n0} → {n1}  mean ê {p0:.2f} → {p1:.2f}  mean true "
              f"{np.mean([after[k][1]['err'].mean() for k in ks]):.2f}")
        if kind == "shown":
            for k in ks:
                zb, za = before[k][1], after[k][1]
                cb = float(((zb["err"] >= zb["lower"]) & (zb["err"] <= zb["upper"])).mean())
                ca = float(((za["err"] >= za["lower"]) & (za["err"] <= za["upper"])).mean())
                print(f"    {k[0]:16s} {cb:.3f} → {ca:.3f}  ê {zb['pred'].mean():.2f} → {za['pred'].mean():.2f}  "
                      f"true {za['err'].mean():.2f}")
ratios = []
for k in keys:
    r = after[k][0]
    if r["deformed"] and r["organ"] is not None:
        ratios.append((r["organ"]["mean_mm"] / r["tre_shown"], k))
if ratios:
    low = min(ratios)
    print(f"lowest organ error quoted / true mean error (deformable answers): {low[0]:.2f} {low[1]}")
for k in keys:
    rb, ra = before[k][0], after[k][0]
    if (rb["deformed"], rb["tre_shown"], rb["lines"]) != (ra["deformed"], ra["tre_shown"], ra["lines"]):
        print("changed:", k, rb["deformed"], "→", ra["deformed"], rb["tre_shown"], "→", ra["tre_shown"],
              [t[:50] for t in rb["lines"]], "→", [t[:50] for t in ra["lines"]])
