"""``results/robustness.md`` and its plot from the robustness study's CSV rows."""

import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from ..defaults import EDGE_MM, K
from .robustness import BASELINE, CONDITIONS, DEFAULT, OFFSETS, SUCCESS_RATIO, read_rows, run_robustness


def with_reference(rows: list[dict]) -> list[dict]:
    """Rows with ``ratio`` = TRE / the same method's zero-offset clean TRE on the same case
    and draw (same plane triple), and ``success`` = ratio ≤ SUCCESS_RATIO. Rows without
    their reference are dropped."""
    ref = {(r["case"], r["method"], r["draw"]): float(r["tre_mm"]) for r in rows
           if r["condition"] == "clean" and float(r["angle_deg"]) == 0.0}
    out = []
    for r in rows:
        key = (r["case"], r["method"], r["draw"])
        if key in ref:
            ratio = float(r["tre_mm"]) / ref[key]
            out.append(dict(r, ratio=ratio, success=ratio <= SUCCESS_RATIO))
    return out


def _pct(x) -> str:
    return f"{100 * np.mean(x):.1f} %" if len(x) else "–"


def _offset_label(a, s) -> str:
    return f"{a:g}° / {s:g} mm"


def summary_tables(rows: list[dict], methods: list[str]) -> str:
    """Markdown tables: success rate by offset, TRE, label-noise effect, time, warnings."""
    rows = with_reference(rows)
    by = defaultdict(list)
    for r in rows:
        by[(r["method"], r["condition"], float(r["angle_deg"]))].append(r)
    conds = [c for c in CONDITIONS if any(r["condition"] == c for r in rows)]
    offs = [o for o in OFFSETS if any(float(r["angle_deg"]) == o[0] for r in rows)]
    lines = ["### Success rate (TRE ≤ 1.2 × the method's zero-offset, clean-label TRE)", "",
             "| method | labels | " + " | ".join(_offset_label(*o) for o in offs) + " | up to 15° / 30 mm |",
             "|---|---|" + "---|" * (len(offs) + 1)]
    for m in methods:
        for c in conds:
            cells = [_pct([r["success"] for r in by[(m, c, o[0])]]) for o in offs]
            upto = [r["success"] for o in offs if o[0] <= 15 for r in by[(m, c, o[0])]]
            lines.append(f"| {m} | {c} | " + " | ".join(cells) + f" | **{_pct(upto)}** |")
    lines += ["", "### TRE (mm): median [90th percentile] over cases × draws", "",
              "| method | labels | " + " | ".join(_offset_label(*o) for o in offs) + " |",
              "|---|---|" + "---|" * len(offs)]
    for m in methods:
        for c in conds:
            cells = []
            for o in offs:
                t = [float(r["tre_mm"]) for r in by[(m, c, o[0])]]
                cells.append(f"{np.median(t):.2f} [{np.percentile(t, 90):.2f}]" if t else "–")
            lines.append(f"| {m} | {c} | " + " | ".join(cells) + " |")
    # label noise at zero offset, paired by case and draw
    lines += ["", "### What label noise costs at zero offset (TRE with noisy labels − clean TRE, mm)", "",
              "| method | labels | median | 90th percentile | max |", "|---|---|---|---|---|"]
    clean0 = {(r["case"], r["method"], r["draw"]): float(r["tre_mm"]) for r in rows
              if r["condition"] == "clean" and float(r["angle_deg"]) == 0}
    for m in methods:
        for c in conds:
            if c == "clean":
                continue
            d = [float(r["tre_mm"]) - clean0[(r["case"], m, r["draw"])] for r in by[(m, c, 0.0)]]
            if d:
                lines.append(f"| {m} | {c} | {np.median(d):+.2f} | {np.percentile(d, 90):+.2f} | {np.max(d):+.2f} |")
    lines += ["", "### Time per registration (s; every row is S + 3 planes)", "",
              "| method | median | 90th percentile | median rigid stage | ICP starts | registrations |",
              "|---|---|---|---|---|---|"]
    for m in methods:
        mr = [r for r in rows if r["method"] == m]
        if not mr:
            continue
        sec = [float(r["seconds"]) for r in mr]
        rig = [float(r["rigid_seconds"]) for r in mr]
        basins = [float(r["starts"] or 1) for r in mr]
        lines.append(f"| {m} | {np.median(sec):.3f} | {np.percentile(sec, 90):.3f} | {np.median(rig):.3f} | "
                     f"{np.median(basins):.0f} | {len(mr)} |")
    # variants run on fewer draws: compared with the default on exactly the same rows
    base = {(r["case"], r["condition"], r["draw"], r["angle_deg"]): r for r in rows if r["method"] == DEFAULT}
    paired = [m for m in methods if m not in (DEFAULT, BASELINE)]
    if paired and base:
        lines += ["", f"### Variants against {DEFAULT}, paired on the same rows (case, labels, draw, offset)", "",
                  f"| variant | rows | success, variant | success, {DEFAULT} | median TRE − {DEFAULT} (mm) | "
                  f"90th pct of the difference | worst | median s, variant / {DEFAULT} |",
                  "|---|---|---|---|---|---|---|---|"]
        for m in paired:
            pairs = [(r, base[k]) for r in rows if r["method"] == m
                     for k in [(r["case"], r["condition"], r["draw"], r["angle_deg"])] if k in base]
            if not pairs:
                continue
            d = [float(a["tre_mm"]) - float(b["tre_mm"]) for a, b in pairs]
            lines.append(f"| {m} | {len(pairs)} | {_pct([a['success'] for a, _ in pairs])} | "
                         f"{_pct([b['success'] for _, b in pairs])} | {np.median(d):+.3f} | "
                         f"{np.percentile(d, 90):+.3f} | {np.max(d):+.2f} | "
                         f"{np.median([float(a['seconds']) for a, _ in pairs]):.3f} / "
                         f"{np.median([float(b['seconds']) for _, b in pairs]):.3f} |")
    lines += ["", "### Poor-fit warnings (share of registrations with a flagged feature)", "",
              "| method | " + " | ".join(conds) + " |", "|---|" + "---|" * len(conds)]
    for m in methods:
        cells = [_pct([bool(r["flagged"]) for r in rows if r["method"] == m and r["condition"] == c]) for c in conds]
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(rows: list[dict], methods: list[str], path: Path) -> Path:
    """Success rate and TRE ratio against the offset, per method and label condition."""
    from matplotlib.figure import Figure  # no pyplot: no global backend or figure state

    rows = with_reference(rows)
    offs = [o for o in OFFSETS if any(float(r["angle_deg"]) == o[0] for r in rows)]
    conds = [c for c in CONDITIONS if any(r["condition"] == c for r in rows)]
    fig = Figure(figsize=(12, 4.5))
    ax1, ax2 = fig.subplots(1, 2)
    styles = {"clean": "-", "shifted": "--", "mislabelled": ":"}
    x = np.arange(len(offs))
    for i, m in enumerate(methods):
        for c in conds:
            y = [100 * np.mean([r["success"] for r in rows if r["method"] == m and r["condition"] == c
                                and float(r["angle_deg"]) == o[0]] or [np.nan]) for o in offs]
            ax1.plot(x, y, styles.get(c, "-"), color=f"C{i}", marker="o", label=f"{m}, {c}")
        data = [[r["ratio"] for r in rows if r["method"] == m and float(r["angle_deg"]) == o[0]] for o in offs]
        width = 0.8 / len(methods)
        ax2.boxplot(data, positions=x + (i - (len(methods) - 1) / 2) * width, widths=width * 0.9,
                    patch_artist=True, boxprops={"facecolor": f"C{i}", "alpha": 0.5}, showfliers=True,
                    flierprops={"markersize": 3})
        ax2.plot([], [], color=f"C{i}", lw=8, alpha=0.5, label=m)
    for ax in (ax1, ax2):
        ax.set_xticks(x, [_offset_label(*o).replace(" / ", "\n") for o in offs])
        ax.set_xlabel("initial offset (rotation / translation)")
    ax1.set_ylabel("success rate (%)")
    ax1.set_title("TRE ≤ 1.2 × zero-offset clean TRE")
    ax1.legend(fontsize=8, loc="lower left")
    ax2.axhline(SUCCESS_RATIO, color="k", lw=0.8, ls="--")
    ax2.set_ylabel("TRE / zero-offset clean TRE")
    ax2.set_title("all label conditions")
    ax2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path


DESIGN = """Every row registers one simulated study case at S + 3 planes (a seeded random plane
triple per case and draw) after moving all its data by a rigid offset: a rotation of the
given angle about a random axis through the data centroid and a translation of the given
length in a random direction (the truth targets move with it; the solver sees only the
data). Label conditions: **clean**; **shifted** — each salient feature (falciform, both
ridges) slid as a whole 5–10 mm along the true surface; **mislabelled** — 10 % of each
salient feature's points swapped with the nearest anterior points. A registration
*succeeds* when its TRE is at most 1.2 × the same method's zero-offset, clean-label TRE on
the same case and plane triple, so label noise that hurts counts as a failure. Methods:
**single-icp** — one exact point-to-point ICP from the tracker pose, least squares (the
path before multi-start ICP); **default** — today's default: multi-start point-to-plane
ICP (tracker pose, ±15° about each axis, principal axes), distinct poses screened by two
LIBR iterations and chosen by Ω, finished by the exact ICP; in both ICPs the falciform and
ridge points carry Huber factors with δ = 2 × their feature's median residual; Huber δ = 1
mm on the salient features in LIBR; a first LIBR fit at 3 × the strain-energy weight, then
the true weight from there (continuation); a flagged fit retried from the other poses;
**multistart** — the first multi-start default (the same without the robust ICP and the
continuation); **default-no-continuation** and **default-plain-icp** — the default without
one of the two, at zero offset only (the rigid stage makes the result offset-independent),
compared with "default" on the same rows. Times are wall-clock on a shared 2-core machine
with two registrations running at once and other users' jobs alongside (load average 2–6
during the run): compare methods within this table, not with the benchmarks.

The committed rows: `run_robustness(cases, "results/robustness.csv", methods=M, draws=D,
workers=2, offsets=O)` (what `navapp study robustness` calls with single-icp and default,
4 draws, all offsets) for M = (single-icp, default), D = 4 (`navapp study robustness
--cases study-cases/* --workers 2`); M = (multistart,), D = 4; M =
(default-no-continuation, default-plain-icp), D = 4, O = 0° only. Cases from
`scripts/simulate_study.py` on the meshes of commit 7703fca. Variants of the first default
measured earlier on older meshes (point-to-point starts, iUS posterior points in ICP, no
Huber, continuation at 10 ×) are in the history of this file (commit 8a12042) and in
docs/decisions/registration.md.

"""


def write_robustness_report(results, out_dir, preamble: str = DESIGN) -> Path:
    """``robustness.md`` (and ``robustness.png``) in ``out_dir`` from the CSV ``results``."""
    rows = read_rows(results)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    methods = list(dict.fromkeys(r["method"] for r in rows))
    # the figure compares the baseline with the default; the variants are in the tables
    png = plot(rows, [m for m in (BASELINE, DEFAULT) if m in methods] or methods, out_dir / "robustness.png")
    md = out_dir / "robustness.md"
    md.write_text("# Robustness to the starting pose and to imprecise labels\n\n" + preamble
                  + summary_tables(rows, methods) + f"\n\n![robustness]({png.name})\n")
    return md


def run_study(cases, results: Path, report: Path, workers: int = 1, quick: bool = False, scheduler=None,
              edge: float = EDGE_MM, k: int = K) -> dict:
    """``navapp study robustness``: run (or resume) the design into ``results`` (CSV), then
    write the report into ``report``; returns what it did (printed as JSON by the CLI).

    Methods "single-icp" (one ICP from the tracker pose) and "default", 4 draws,
    one worker by default (the rows carry timings); ``quick``: one draw and the 0°, 15° and
    20° offsets; ``scheduler``: a Dask scheduler's address (``run_robustness``).
    """

    offsets = tuple(o for o in OFFSETS if o[0] in (0.0, 15.0, 20.0)) if quick else OFFSETS
    t0 = time.perf_counter()
    n = run_robustness(cases, results, draws=1 if quick else 4, workers=workers, offsets=offsets, scheduler=scheduler,
                       edge=edge, k=k)
    md = write_robustness_report(results, report)
    return {"registrations_run": n, "seconds": round(time.perf_counter() - t0, 1), "results": str(results),
            "report": str(md)}
