"""The transposed-case sections of results/table2.md from results/table2_lap.csv.

    python scripts/table2_lap_report.py [CSV] [OUT_MD]

The CSV may hold a quick run (two plane choices per S + n level, ``--quick``) and a full
run that stopped early (it is resumable): the quick subset is tabulated over every case,
and the full design over the cases whose 701 registrations are all present.
Writes OUT_MD (default results/table2_lap_sections.md) and results/table2_lap_by_level.png.
"""

import argparse
from collections import Counter
from pathlib import Path

from navapp.evaluation.report import markdown, plot_levels
from navapp.evaluation.table2 import read_results, scenarios

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("csv", nargs="?", type=Path, default=Path("results/table2_lap.csv"), help="the transposed cases' rows")
ap.add_argument("out", nargs="?", type=Path, default=Path("results/table2_lap_sections.md"),
                help="the sections written")
args = ap.parse_args()
csv, out = args.csv, args.out
if not csv.is_file():
    ap.error(f"{csv}: no such results file")
rows = read_results(csv)
quick = {(lv, "-".join(map(str, p))) for lv, p in scenarios(quick=True)}
sub = [r for r in rows if (r["level"], r["planes"]) in quick]
full_n = len(scenarios())
counts = Counter(r["case"] for r in rows)
complete = sorted(c for c, n in counts.items() if n >= full_n)
text = ("### Quick design on all nine cases\n\n"
        "Every level once per case; S + 1, S + 2, S + 3 with two plane choices each "
        "(`--quick`, 11 registrations per case).\n\n" + markdown(sub) + "\n![TRE by level](table2_lap_by_level.png)\n")
plot_levels(sub, csv.parent / "table2_lap_by_level.png")
if complete:
    text += (f"\n### Full design (all 16 / 120 / 560 plane combinations) on {len(complete)} of the nine cases\n\n"
             + markdown([r for r in rows if r["case"] in complete]))
else:
    text += "\n### Full design\n\nNo case has all 701 registrations yet.\n"
out.write_text(text)
print(f"{len(rows)} rows, quick subset {len(sub)}, complete cases {complete}")
