"""Summarise ``band_energy_spread.py``'s lines: per level, the mean over registrations of the
fraction of targets in the band (all registrations with a deformable fit, and those whose
answer is that fit: only they are shown with a band), before and after; under the upper edge;
mean ê; the organ-error warnings that changed; the lowest quoted organ error over the shown
answer's true mean error.

    python notes/scripts/band_energy_spread_summary.py FILE.jsonl...
"""

import json
import sys

import numpy as np

rows = [json.loads(line) for f in sys.argv[1:] for line in open(f)]
for level in ("S", "S+all"):
    at = [r for r in rows if r["level"] == level and "before" in r]
    shown = [r for r in at if r["deformed"]]
    for name, group in (("all", at), ("shown", shown)):
        if not group:
            continue
        line = [f"{level:6s} {name:5s} n={len(group):2d}"]
        for key in ("in_band", "below_upper", "above_lower", "mean_pred", "mean_sigma"):
            b = np.mean([r["before"][key] for r in group])
            a = np.mean([r["after"][key] for r in group])
            line.append(f"{key} {b:.3f}→{a:.3f}")
        line.append("≥ 90 %: {}→{}".format(*(sum(r[k]["in_band"] >= 0.9 for r in group) for k in ("before", "after"))))
        print("  ".join(line))
    flips = [(r["case"], r["before"]["organ_warning"], r["after"]["organ_warning"]) for r in at
             if r["before"]["organ_warning"] != r["after"]["organ_warning"]]
    print(f"{level:6s} organ warnings changed: {flips}")
    ratio = [(r["after"]["organ_quoted"] / r["mean_shown"], r["case"]) for r in shown]
    if ratio:
        print(f"{level:6s} lowest quoted / true (shown): {min(ratio)[0]:.2f} ({min(ratio)[1]})")
