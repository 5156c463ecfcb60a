"""The cost study's report: TRE against time with the Pareto front, TRE against k per data
level (like the paper's Fig. 9), and Markdown tables (settings and peers)."""

import csv
from collections import defaultdict
from pathlib import Path

import numpy as np

from .cost import DEFAULT_EDGE, DEFAULT_K, SWEEP_LEVELS, pareto_front


def _rows(path):
    with Path(path).open() as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        for k in ("edge_mm", "precompute_s", "register_s", "tre_mean_mm"):
            r[k] = float(r[k])
        for k in ("k", "planes", "nodes", "iterations"):
            r[k] = int(r[k])
    return rows


def _mean_by(rows, key):
    """Average TRE, registration and precompute seconds over cases for each key(row)."""
    groups = defaultdict(list)
    for r in rows:
        groups[key(r)].append(r)
    return {g: {"tre": float(np.mean([r["tre_mean_mm"] for r in rs])),
                "reg": float(np.mean([r["register_s"] for r in rs])),
                "pre": float(np.mean([r["precompute_s"] for r in rs])),
                "nodes": int(np.mean([r["nodes"] for r in rs])), "n": len(rs)} for g, rs in groups.items()}


def plot_time(rows, path, level="S+3"):
    """Left: TRE against registration seconds for every setting at one data level (k, edge,
    LM cap/tolerance, peers), Pareto front drawn. Right: TRE against precompute seconds
    (k and edge settings)."""
    import matplotlib.ticker
    from matplotlib.figure import Figure  # no pyplot: no global backend or figure state

    fig = Figure(figsize=(11, 4.2), dpi=110)
    a, b = fig.subplots(1, 2)
    sel = [r for r in rows if r["level"] == level and r["sweep"] in ("k", "edge", "lm", "peers")]
    pts = _mean_by(sel, lambda r: (r["sweep"], r["method"], r["edge_mm"], r["k"], r["setting"]))
    style = {"k": ("o", "C0"), "edge": ("s", "C1"), "lm": ("^", "C2"), "peers": ("D", "C3")}
    for (sweep, method, edge, k, setting), v in pts.items():
        m, c = style[sweep]
        a.scatter(v["reg"], v["tre"], marker=m, color=c, s=30)
        label = {"k": f"k={k}", "edge": f"{edge:g} mm", "lm": setting, "peers": method}[sweep]
        a.annotate(label, (v["reg"], v["tre"]), fontsize=7, xytext=(3, 3), textcoords="offset points")
    keys = list(pts)
    t = np.array([pts[g]["reg"] for g in keys])
    e = np.array([pts[g]["tre"] for g in keys])
    front = pareto_front(t, e)
    o = np.argsort(t[front])
    a.plot(t[front][o], e[front][o], "k--", lw=1, label="Pareto front")
    for s, (m, c) in style.items():
        label = {"k": f"k ({DEFAULT_EDGE:g} mm)", "edge": f"mesh edge (k {DEFAULT_K})", "lm": "LM cap / tolerance",
                 "peers": "peers"}[s]
        a.scatter([], [], marker=m, color=c, label=label)
    a.set_xscale("log")
    a.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
    a.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    a.set_xticks([0.1, 0.2, 0.5, 1, 2, 5, 10])
    a.set_xlabel("registration seconds (mean over cases)")
    a.set_ylabel("mean TRE (mm)")
    a.set_title(f"{level}: accuracy against registration time")
    a.legend(fontsize=7)
    pre = _mean_by([r for r in rows if r["level"] == level and r["sweep"] in ("k", "edge") and r["method"] == "LIBR"],
                   lambda r: (r["edge_mm"], r["k"]))
    for (edge, k), v in sorted(pre.items()):
        b.scatter(v["pre"], v["tre"], color="C0" if edge == 4.0 else "C1")
        b.annotate(f"{edge:g} mm, k={k}", (v["pre"], v["tre"]), fontsize=7, xytext=(3, 3), textcoords="offset points")
    b.set_xlabel("precompute seconds, cold (mesh + basis)")
    b.set_ylabel("mean TRE (mm)")
    b.set_title(f"{level}: accuracy against precompute time")
    fig.tight_layout()
    fig.savefig(path)


def plot_k(rows, path):
    """Mean TRE against k for each data level (4 mm mesh), like the paper's Fig. 9."""
    from matplotlib.figure import Figure  # no pyplot: no global backend or figure state

    fig = Figure(figsize=(6, 4), dpi=110)
    ax = fig.subplots()
    sel = _mean_by([r for r in rows if r["sweep"] == "k" and r["method"] == "LIBR"], lambda r: (r["level"], r["k"]))
    for level in SWEEP_LEVELS:
        ks = sorted(k for (lv, k) in sel if lv == level)
        if ks:
            ax.plot(ks, [sel[(level, k)]["tre"] for k in ks], "o-", label=level)
    ax.set_xlabel("control points k")
    ax.set_ylabel("mean TRE (mm)")
    ax.set_title("TRE against k per data level (like the paper's Fig. 9)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)


def write_cost_report(results_csv, out_dir) -> Path:
    rows = _rows(results_csv)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    plot_time(rows, out / "cost_tre_vs_time.png")
    plot_k(rows, out / "cost_tre_vs_k.png")
    cases = sorted({r["case"] for r in rows})
    md = [f"# What accuracy costs in time\n\nCases: {', '.join(cases)} (means over cases). "
          "Precompute = cold mesh + basis; registration = one run, rigid ICP included.\n"]
    md.append("## Model size (k, mesh edge)\n\n"
              "| edge mm | k | nodes | precompute s | level | TRE mm | registration s |\n|---|---|---|---|---|---|---|")
    sel = _mean_by([r for r in rows if r["sweep"] in ("k", "edge") and r["method"] == "LIBR"],
                   lambda r: (r["edge_mm"], r["k"], r["level"]))
    for (edge, k, level), v in sorted(sel.items(), key=lambda x: (-x[0][0], x[0][1], x[0][2])):
        md.append(f"| {edge:g} | {k} | {v['nodes']:,} | {v['pre']:.1f} | {level} | {v['tre']:.2f} | {v['reg']:.2f} |")
    at = f"{DEFAULT_EDGE:g} mm, k = {DEFAULT_K}"  # the sweeps other than k and edge run at the defaults
    md.append(f"\n## Solver settings ({at})\n\n| level | setting | TRE mm | registration s |\n|---|---|---|---|")
    sel = _mean_by([r for r in rows if r["sweep"] == "lm"], lambda r: (r["level"], r["setting"]))
    for (level, setting), v in sorted(sel.items(), key=lambda x: (x[0][0], x[1]["reg"])):
        md.append(f"| {level} | {setting} | {v['tre']:.2f} | {v['reg']:.3f} |")
    md.append(f"\n## Amount of data ({at})\n\n| planes | TRE mm | registration s |\n|---|---|---|")
    sel = _mean_by([r for r in rows if r["sweep"] == "planes"], lambda r: r["planes"])
    for m, v in sorted(sel.items()):
        md.append(f"| {m} | {v['tre']:.2f} | {v['reg']:.2f} |")
    base = {(r["edge_mm"], r["k"]) for r in rows if r["sweep"] == "peers"}  # the default model
    peers = _mean_by([r for r in rows if r["sweep"] in ("peers", "k") and (r["edge_mm"], r["k"]) in base],
                     lambda r: (r["method"], r["level"]))
    if base:
        edge, k = sorted(base)[0]
        md.append(f"\n## Peers on the same data ({edge:g} mm, k = {k})\n\n| method | {' | '.join(SWEEP_LEVELS)} |\n"
                  f"|---|{'---|' * len(SWEEP_LEVELS)}")
        for method in ("rigid ICP", "CPD", "LIBR"):
            cells = [f"{peers[(method, lv)]['tre']:.2f} mm, {peers[(method, lv)]['reg']:.2f} s"
                     if (method, lv) in peers else "—" for lv in SWEEP_LEVELS]
            md.append(f"| {method} | " + " | ".join(cells) + " |")
        md.append("\nCPD uses only the surface data (it has no model of vessel contours or centerlines); "
                  "its surface displacement is carried inside by thin-plate splines.")
    md.append("\n![TRE against time](cost_tre_vs_time.png)\n\n![TRE against k](cost_tre_vs_k.png)\n")
    path = out / "cost.md"
    path.write_text("\n".join(md))
    return path
