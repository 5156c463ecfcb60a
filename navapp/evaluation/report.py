"""Table II report: a Markdown table in the paper's layout beside the paper's numbers, and
the TRE distribution per data level (like the paper's Fig. 7) as a PNG."""

from collections import defaultdict
from pathlib import Path

import numpy as np

from .table2 import LEVELS, PAPER, read_results


def summarise(rows):
    """{case: {level: (mean, sd, n)}} and {level: (mean, sd, n)} over all registrations."""
    by = defaultdict(lambda: defaultdict(list))
    for r in rows:
        by[r["case"]][r["level"]].append(float(r["tre_mean_mm"]))
    per_case = {c: {lv: (np.mean(v), np.std(v), len(v)) for lv, v in d.items()} for c, d in by.items()}
    overall = {}
    for lv in LEVELS:
        v = [x for d in by.values() for x in d.get(lv, [])]
        if v:
            overall[lv] = (float(np.mean(v)), float(np.std(v)), len(v))
    return per_case, overall


def markdown(rows) -> str:
    per_case, overall = summarise(rows)
    levels = [lv for lv in LEVELS if lv in overall]
    head = "| case | " + " | ".join(levels) + " |\n|---|" + "---|" * len(levels) + "\n"
    body = ""
    for c in sorted(per_case):
        cells = [f"{per_case[c][lv][0]:.1f} ± {per_case[c][lv][1]:.1f}" if lv in per_case[c] else "" for lv in levels]
        body += f"| {c} | " + " | ".join(cells) + " |\n"
    body += "| **average (navapp)** | " + " | ".join(f"**{overall[lv][0]:.1f} ± {overall[lv][1]:.1f}**" for lv in levels) + " |\n"
    body += "| paper (Table II) | " + " | ".join(f"{PAPER[lv][0]:.1f}" for lv in levels) + " |\n"
    secs = [float(r["seconds"]) for r in rows if r["level"] != "rigid"]
    n = {lv: overall[lv][2] for lv in levels}
    foot = (f"\nMean target registration error (mm) over every registration of a level (mean ± sd); "
            f"registrations per level: {', '.join(f'{lv} {n[lv]}' for lv in levels)}. "
            f"Deformable registration time: median {np.median(secs):.2f} s, mean {np.mean(secs):.2f} s.\n")
    return head + body + foot


def plot_levels(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    _, overall = summarise(rows)
    levels = [lv for lv in LEVELS if lv in overall]
    data = [[float(r["tre_mean_mm"]) for r in rows if r["level"] == lv] for lv in levels]
    fig, ax = plt.subplots(figsize=(8, 4), dpi=110)
    ax.boxplot(data, tick_labels=levels, showfliers=True)
    ax.plot(range(1, len(levels) + 1), [PAPER[lv][0] for lv in levels], "r^", label="paper (mean)")
    ax.set_ylabel("mean TRE per registration (mm)")
    ax.set_title("TRE by data level (like the paper's Fig. 7)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def write_report(results_csv, out_dir):
    rows = read_results(results_csv)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "table2.md").write_text("# Table II on simulated cases\n\n" + markdown(rows))
    plot_levels(rows, out / "tre_by_level.png")
    return out / "table2.md"
