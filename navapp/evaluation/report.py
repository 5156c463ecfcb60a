"""Table II report: a Markdown table in the paper's layout beside the paper's numbers, and
the TRE distribution per data level (like the paper's Fig. 7) as a PNG."""

from collections import defaultdict
from pathlib import Path

import numpy as np

from ..anatomy.caseio import read_case
from ..defaults import EDGE_MM, K
from ..geometry.tre import point_errors
from ..registration.pipeline import prepare, register
from ..simulation.levels import LEVELS, case_planes, fixed_planes, study_data
from .table2 import PAPER, read_results


def summarise(rows):
    """{case: {level: (mean, sd, n)}} and {level: (mean, sd, n)} over all registrations."""
    by: dict = defaultdict(lambda: defaultdict(list))
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
    means = (f"**{overall[lv][0]:.1f} ± {overall[lv][1]:.1f}**" for lv in levels)
    body += "| **average (navapp)** | " + " | ".join(means) + " |\n"
    # a source level (S+laparoscope) has no column in the paper
    paper = (f"{PAPER[lv][0]:.1f}" if lv in PAPER else "—" for lv in levels)
    body += "| paper (Table II) | " + " | ".join(paper) + " |\n"
    secs = [float(r["seconds"]) for r in rows if r["level"] != "rigid"]
    n = {lv: overall[lv][2] for lv in levels}
    foot = (f"\nMean target registration error (mm) over every registration of a level (mean ± sd); "
            f"registrations per level: {', '.join(f'{lv} {n[lv]}' for lv in levels)}. "
            f"Deformable registration time: median {np.median(secs):.2f} s, mean {np.mean(secs):.2f} s.\n")
    return head + body + foot


def plot_levels(rows, path):
    from matplotlib.figure import Figure  # no pyplot: no global backend or figure state

    _, overall = summarise(rows)
    levels = [lv for lv in LEVELS if lv in overall]
    data = [[float(r["tre_mean_mm"]) for r in rows if r["level"] == lv] for lv in levels]
    fig = Figure(figsize=(8, 4), dpi=110)
    ax = fig.subplots()
    ax.boxplot(data, tick_labels=levels, showfliers=True)
    ax.plot(range(1, len(levels) + 1), [PAPER[lv][0] if lv in PAPER else np.nan for lv in levels], "r^",
            label="paper (mean)")
    ax.set_ylabel("mean TRE per registration (mm)")
    ax.set_title("TRE by data level (like the paper's Fig. 7)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)


def write_report(results_csv, out_dir, case_dirs=()):
    """table2.md + tre_by_level.png, and with ``case_dirs`` tre_vs_distance.png (S + all)."""
    rows = read_results(results_csv)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    text = "# Table II on simulated cases\n\n" + markdown(rows)
    text += "\n![TRE by level](tre_by_level.png)\n"
    plot_levels(rows, out / "tre_by_level.png")
    if case_dirs:
        r = distance_plot(case_dirs, out / "tre_vs_distance.png")
        text += (f"\nS + all planes: per-target TRE against distance to the nearest data point, "
                 f"Pearson r = {r:.2f}.\n\n![TRE vs distance](tre_vs_distance.png)\n")
    (out / "table2.md").write_text(text)
    return out / "table2.md"


def distance_plot(case_dirs, path, level="S+all", edge=EDGE_MM, k=K) -> float:
    """Per-target TRE against the distance from the target's true position to the nearest
    intraoperative data point, pooled over cases at ``level`` (like the paper's Fig. 5d).
    Returns Pearson's r."""
    from matplotlib.figure import Figure  # no pyplot: no global backend or figure state
    from scipy.spatial import cKDTree
    from scipy.stats import pearsonr


    dist, err = [], []
    for d in case_dirs:
        case = read_case(d)
        model, _ = prepare(case, edge, k)
        data = study_data(d, level, fixed_planes(level, case_planes(d)), case=case)
        reg = register(model, data)
        x0, x1 = case.need_truth().tre_points(model.basis.nodes)
        pts = np.vstack(list(data.values()))
        dist.append(cKDTree(pts).query(x1)[0])
        err.append(point_errors(reg.transform(x0), x1))
    d_all, e_all = np.concatenate(dist), np.concatenate(err)
    r = float(pearsonr(d_all, e_all)[0])
    fig = Figure(figsize=(6, 4.5), dpi=110)
    ax = fig.subplots()
    ax.hexbin(d_all, e_all, gridsize=50, bins="log", cmap="viridis")
    ax.set_xlabel("distance to nearest data point (mm)")
    ax.set_ylabel("target registration error (mm)")
    ax.set_title(f"{level}: TRE vs distance to data, Pearson r = {r:.2f} ({len(d_all):,} targets)")
    fig.tight_layout()
    fig.savefig(path)
    return r
