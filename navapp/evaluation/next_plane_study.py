"""The suggested next plane (``registration.next_plane``) against the simulated truth on the
study cases: ``navapp study next-plane``.

Per case, starting from S, the best of the case's remaining recorded probe poses
(``intraop/us/planes.json``: the poses, never the images' truth) is suggested from the
current registration (``registration.next_plane.suggest_planes``), its plane's data are
added, the case is registered again as Table II registers it (ICP on the stylus data
once, LIBR from the rigid pose), and so on for three planes (greedy). Each suggested
combination is then placed among all 16 / 120 / 560 combinations of a Table II CSV of the
same cases (rank 1 = lowest mean TRE), beside the average over all combinations (the
paper's S + n rows).
"""

import csv
import json
import time
from collections import defaultdict
from dataclasses import replace
from pathlib import Path

import numpy as np

from .. import progress
from ..anatomy.caseio import read_case, read_csv
from ..defaults import EDGE_MM, K
from ..errors import InputError, NavappError
from ..geometry.tre import mean_tre
from ..registration.next_plane import anterior_surface_mask, suggest_planes
from ..registration.pipeline import prepare, register, rigid_starts
from ..registration.uncertainty import DEFAULT_CALIBRATION as cal
from ..registration.uncertainty import estimate_error
from ..simulation.levels import data_level, plus_planes
from .error_estimate import table2_part
from .table2 import read_results

COLUMNS = ("case", "level", "planes", "tre_mean_mm", "tre_table2_mm", "rank", "combinations", "percentile",
           "level_mean_mm", "level_best_mm", "level_worst_mm", "score_mm", "suggest_seconds", "spearman_step",
           "expected_presence", "expected_median_mm", "expected_count_ratio", "rank_fresh", "spearman_fresh")


def compare_expected(candidates, plane_ids, case_dir) -> dict:
    """How the expected features of the candidates (tracker frame) compare with what each
    recorded plane really imaged (``intraop/us/plane_XX``): the fraction of (plane,
    contour/far-wall feature) pairs where both agree on presence, the median over pairs
    present in both of the median distance from each acquired point to the expected
    points, and the median ratio expected pixel count / acquired points."""
    from scipy.spatial import cKDTree


    agree, dist, ratio = [], [], []
    for c in candidates:
        pdir = Path(case_dir) / "intraop" / "us" / f"plane_{plane_ids[c.index]:02d}"
        for name in ("portal_contour", "hepatic_contour", "posterior"):
            f = pdir / f"{name}.csv"
            got = read_csv(f, ("x", "y", "z")) if f.exists() else np.zeros((0, 3))
            exp = c.features.get(name, np.zeros((0, 3)))
            agree.append((len(got) > 0) == (len(exp) > 0))
            if len(got) and len(exp):
                dist.append(float(np.median(cKDTree(exp).query(got)[0])))
                ratio.append(c.pixels[name] / len(got))
    return {"expected_presence": round(float(np.mean(agree)), 3),
            "expected_median_mm": round(float(np.median(dist)), 3) if dist else None,
            "expected_count_ratio": round(float(np.median(ratio)), 3) if ratio else None}


def recorded_poses(case_dir) -> list[tuple[str, np.ndarray]]:
    """The case's recorded probe poses (orientation, 4×4 ProbeToTracker) from intraop/us/planes.json."""

    path = Path(case_dir) / "intraop" / "us" / "planes.json"
    try:
        meta = json.loads(path.read_text())
        return [(p["orientation"], np.asarray(p["probe_to_tracker"], float).reshape(4, 4)) for p in meta["planes"]]
    except OSError:
        raise InputError("no recorded probe poses (a simulated case has them)", path) from None
    except (ValueError, KeyError, TypeError):
        raise InputError("not a planes file (expected planes: [{orientation, probe_to_tracker 4×4}])", path) from None


def _table(rows):
    """case → level → {planes tuple: TRE}."""
    out: dict = defaultdict(lambda: defaultdict(dict))
    for r in rows:
        out[r["case"]][r["level"]][tuple(int(p) for p in r["planes"].split("-") if p)] = float(r["tre_mean_mm"])
    return out


def _spearman(score, tre):
    from scipy.stats import spearmanr

    if len(score) < 3:
        return float("nan")
    return float(spearmanr(score, -np.asarray(tre)).statistic)


def criteria() -> dict:
    """The scores compared: the default (ê = a + b·d + c·σ + e·d·m) and its distance and
    covariance parts alone."""

    return {"ê (default)": cal, "d only": replace(cal, c=0.0), "σ only": replace(cal, b=0.0, e=0.0)}


def fresh_single_planes(case_dir, edge=EDGE_MM, k=K) -> dict:
    """Mean TRE of S + each single plane registered now (as Table II registers), so that
    the S + 1 rank does not depend on a CSV made by an older registration: {plane: TRE}."""

    case_dir = Path(case_dir)
    case = read_case(case_dir)
    model, _ = prepare(case, edge, k)
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    starts = rigid_starts(model, data_level(case_dir, "S", case=case))  # shared: the stylus's
    out = {}
    for i in range(len(recorded_poses(case_dir))):
        reg = register(model, data_level(case_dir, "S+planes", planes=(i,), case=case), starts=starts)
        out[i] = mean_tre(reg.transform(x0), x1)
    return out


def run_case(case_dir, table, steps=3, edge=EDGE_MM, k=K, calibration=None, fresh=None) -> list[dict]:
    """Greedy suggestions from S on one case; ``fresh``: ``fresh_single_planes`` of the case
    (adds the S + 1 rank among this run's own single-plane registrations)."""

    case_dir = Path(case_dir)
    case = read_case(case_dir)
    model, _ = prepare(case, edge, k)
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    poses = recorded_poses(case_dir)
    stylus = data_level(case_dir, "S", case=case)
    starts = rigid_starts(model, stylus)  # shared: every registration here has the stylus's
    reg = register(model, stylus, starts=starts)
    chosen, rows = [], []
    known = table.get(case_dir.name, {})
    for m in range(1, steps + 1):
        remaining = [i for i in range(len(poses)) if i not in chosen]
        sugg = suggest_planes(reg, poses=[poses[i] for i in remaining], calibration=calibration)
        best = sugg.best
        chosen.append(remaining[best.index])
        level = plus_planes(m)
        # how well the one-step score ranks the candidates (Spearman ρ of score against
        # −TRE of S + chosen-so-far + candidate, from the Table II CSV)
        cand_tre = [known.get(level, {}).get(tuple(sorted(chosen[:-1] + [remaining[c.index]])))
                    for c in sugg.candidates]
        ok = [t is not None for t in cand_tre]
        rho = _spearman([c.score_mm for c, o in zip(sugg.candidates, ok, strict=True) if o],
                        [t for t in cand_tre if t is not None]) if all(ok) else float("nan")
        data = data_level(case_dir, "S+planes", planes=tuple(sorted(chosen)), case=case)
        reg = register(model, data, starts=starts)
        tre = mean_tre(reg.transform(x0), x1)
        combo = tuple(sorted(chosen))
        level_tres = known.get(level, {})
        ref = level_tres.get(combo)
        row = {"case": case_dir.name, "level": level, "planes": "-".join(map(str, combo)),
               "tre_mean_mm": round(tre, 4), "tre_table2_mm": ref, "rank": None, "combinations": len(level_tres),
               "percentile": None, "level_mean_mm": None, "level_best_mm": None, "level_worst_mm": None,
               "score_mm": round(best.score_mm, 4), "suggest_seconds": round(sugg.seconds, 3),
               "spearman_step": None if np.isnan(rho) else round(rho, 3)}
        if m == 1:  # the expected features against what the planes really showed, from S
            row.update(compare_expected(sugg.candidates, remaining, case_dir))
            if fresh:
                v = np.array(list(fresh.values()))
                row["rank_fresh"] = int(1 + np.sum(v < fresh[chosen[0]]))
                row["spearman_fresh"] = round(_spearman([c.score_mm for c in sugg.candidates],
                                                        [fresh[remaining[c.index]] for c in sugg.candidates]), 3)
        if level_tres:
            v = np.array(list(level_tres.values()))
            t = ref if ref is not None else tre
            rank = int(1 + np.sum(v < t))
            row.update(rank=rank, percentile=round(100.0 * (rank - 1) / len(v), 1), level_mean_mm=round(v.mean(), 4),
                       level_best_mm=round(v.min(), 4), level_worst_mm=round(v.max(), 4))
        rows.append(row)
    return rows


def benchmark(case_dir, repeats=5, edge=EDGE_MM, k=K) -> dict:
    """Seconds for one suggestion over 16 automatic candidates (``candidate_poses``) from the
    S registration of ``case_dir``: median and all runs."""

    case = read_case(case_dir)
    model, _ = prepare(case, edge, k)
    reg = register(model, data_level(case_dir, "S", case=case))
    anterior = anterior_surface_mask(model, case.preop)
    times, est_times, surf_times = [], [], []
    for _ in range(repeats):
        t = time.perf_counter()
        sugg = suggest_planes(reg, anterior=anterior, count=8)
        times.append(time.perf_counter() - t)
        t = time.perf_counter()
        estimate_error(reg)
        est_times.append(time.perf_counter() - t)
        t = time.perf_counter()
        estimate_error(reg, nodes=model.basis.surface)
        surf_times.append(time.perf_counter() - t)
    return {"case": Path(case_dir).name, "candidates": len(sugg.candidates), "median_s": float(np.median(times)),
            "runs_s": [round(x, 3) for x in times], "estimate_median_s": float(np.median(est_times)),
            "surface_estimate_median_s": float(np.median(surf_times)), "nodes": int(model.basis.M),
            "surface_nodes": len(model.basis.surface)}


def run_study(sets: dict, out_dir, steps=3, bench_case=None, repeats=5, edge=EDGE_MM, k=K):
    """``sets``: {label: (case_dirs, table2 CSV)}. Every criterion of ``criteria()`` on every
    case; writes next_plane.md and next_plane.csv."""
    all_rows: dict = {}  # (set label, criterion) → rows
    crit = criteria()
    n = sum(len(d) for d, _ in sets.values()) * len(crit)
    with progress.bar(n, "next plane: cases × criteria", "case") as pb:
        for label, (dirs, csv_path) in sets.items():
            table = _table(read_results(csv_path))
            fresh = {Path(d).name: fresh_single_planes(d, edge, k) for d in dirs}
            for cname, cal in crit.items():
                all_rows[label, cname] = []
                for d in dirs:
                    all_rows[label, cname] += run_case(d, table, steps, edge, k, calibration=cal,
                                                       fresh=fresh[Path(d).name])
                    pb.update(1)
    bench = benchmark(bench_case, repeats, edge, k) if bench_case else None
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with (out / "next_plane.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, ("set", "criterion") + COLUMNS)
        w.writeheader()
        for (label, cname), rows in all_rows.items():
            for r in rows:
                w.writerow({"set": label, "criterion": cname, **r})
    (out / "next_plane.md").write_text(markdown(all_rows, sets, bench))
    return all_rows, bench


def summary(rows) -> dict:
    """level → numbers of the suggested combinations over the cases (ranks from the CSV)."""
    out = {}
    for level in ("S+1", "S+2", "S+3"):
        rr = [r for r in rows if r["level"] == level]
        if not rr:
            continue
        tre = [r["tre_table2_mm"] if r["tre_table2_mm"] is not None else r["tre_mean_mm"] for r in rr]
        have = [(t, r) for t, r in zip(tre, rr, strict=True) if r["rank"] is not None]
        rhos = [r["spearman_step"] for r in rr if r["spearman_step"] is not None]
        out[level] = {
            "tre": float(np.mean(tre)), "own_tre": float(np.mean([r["tre_mean_mm"] for r in rr])),
            "mean_all": float(np.mean([r["level_mean_mm"] for _, r in have])) if have else None,
            "best": float(np.mean([r["level_best_mm"] for _, r in have])) if have else None,
            "worst": float(np.mean([r["level_worst_mm"] for _, r in have])) if have else None,
            "median_rank": float(np.median([r["rank"] for _, r in have])) if have else None,
            "combinations": have[0][1]["combinations"] if have else 0,
            "percentile": float(np.mean([r["percentile"] for _, r in have])) if have else None,
            "better": sum(t < r["level_mean_mm"] for t, r in have), "cases": len(have),
            "rho": float(np.median(rhos)) if rhos else None,
            "rank_fresh": [r["rank_fresh"] for r in rr if r.get("rank_fresh") is not None],
            "rho_fresh": [r["spearman_fresh"] for r in rr if r.get("spearman_fresh") is not None]}
    return out


def _fmt(x, f="{:.2f}"):
    return "–" if x is None or (isinstance(x, float) and np.isnan(x)) else f.format(x)


def markdown(all_rows, sets, bench) -> str:
    text = ["# The next best ultrasound plane\n\n",
            "Greedy: from S, the best of the case's remaining 16 recorded probe poses by the expected drop of the mean "
            "predicted error (the registered model cut by the candidate's plane gives the expected contours and far "
            "wall; their Jacobian rows join the LM normal matrix; ê = a + b·d + c·σ + e·d·m, "
            "results/error_estimate.md), then registered with that plane's data as Table II registers, and again. "
            "Rank: place of the suggested "
            "combination's mean TRE among all combinations of that level in the Table II CSV (1 = best of 16 / 120 / "
            "560); percentile 0 = best. ρ: Spearman correlation, over the candidates of that step, between the score "
            "and the TRE each would have given (from the CSV).\n"]
    labels = list(dict.fromkeys(label for label, _ in all_rows))
    names = list(dict.fromkeys(c for _, c in all_rows))
    for label in labels:
        text.append(f"\n## {label} (ranks from {sets[label][1]})\n\n")
        text.append("| criterion | level | suggested: mean TRE (mm) | (this run) | all combinations: mean (paper's "
                    "row) | best | worst | median rank | mean percentile | suggested better than the average | "
                    "median ρ |\n|---|---|---|---|---|---|---|---|---|---|---|\n")
        for cname in names:
            for level, v in summary(all_rows[label, cname]).items():
                text.append(f"| {cname} | {level} | {v['tre']:.2f} | {v['own_tre']:.2f} | {_fmt(v['mean_all'])} | "
                            f"{_fmt(v['best'])} | "
                            f"{_fmt(v['worst'])} | {_fmt(v['median_rank'], '{:.0f}')} of {v['combinations']} | "
                            f"{_fmt(v['percentile'], '{:.0f}')} % | {v['better']} of {v['cases']} cases | "
                            f"{_fmt(v['rho'])} |\n")
        for cname in names:
            v = summary(all_rows[label, cname]).get("S+1")
            if v and v["rank_fresh"]:
                text.append(f"\n{cname}, S + 1 against this run's own registration of S + each single plane (not the "
                            f"CSV): ranks {', '.join(map(str, v['rank_fresh']))} of 16 (median "
                            f"{np.median(v['rank_fresh']):.0f}), median ρ {np.median(v['rho_fresh']):.2f}.\n")
        rows = all_rows[label, names[0]]
        first = [r for r in rows if r["level"] == "S+1" and r.get("expected_presence") is not None]
        if first:
            med = [r["expected_median_mm"] for r in first if r["expected_median_mm"] is not None]
            rat = [r["expected_count_ratio"] for r in first if r["expected_count_ratio"] is not None]
            text.append(f"\nExpected features against the planes' real data, from the S registration (16 planes × "
                        f"portal, hepatic contours and far wall per case): presence agrees in "
                        f"{np.mean([r['expected_presence'] for r in first]):.0%} of pairs; acquired points lie a "
                        f"median {np.median(med):.2f} mm from the expected section (median over cases); expected "
                        f"pixels / acquired points: median {np.median(rat):.2f}.\n")
        text.append(f"\nPer case ({names[0]}); TRE: this run's registration, Table II CSV TRE: the CSV's row for the "
                    "same planes (the rank uses the CSV's):\n\n| case | level | planes | TRE (mm) | Table II CSV TRE | "
                    "rank | all: mean | score (mm) | suggest (s) |\n|---|---|---|---|---|---|---|---|---|\n")
        for r in rows:
            text.append(f"| {r['case']} | {r['level']} | {r['planes']} | {r['tre_mean_mm']:.2f} | "
                        f"{_fmt(r['tre_table2_mm'])} | {_fmt(r['rank'], '{}')} of {r['combinations']} | "
                        f"{_fmt(r['level_mean_mm'])} | {r['score_mm']:.3f} | {r['suggest_seconds']:.2f} |\n")
    if bench:
        text.append(f"\nSpeed: one suggestion over {bench['candidates']} automatic candidates on the registered "
                    f"{bench['case']} liver ({bench['nodes']} nodes) at S: median {bench['median_s']:.2f} s over "
                    f"{len(bench['runs_s'])} runs ({', '.join(map(str, bench['runs_s']))} s); the error estimate at "
                    f"every node: median {bench['estimate_median_s'] * 1e3:.0f} ms, at the {bench['surface_nodes']} "
                    "surface nodes "
                    f"(the app's colour map): median {bench['surface_estimate_median_s'] * 1e3:.0f} ms. Shared 2-core "
                    "machine (`navapp study next-plane`).\n")
    return "".join(text)


def study_command(case_dirs, results, report, with_cases=None, with_results=None, edge=EDGE_MM, k=K):
    """``navapp study next-plane``: writes <report>/next_plane.md and .csv; ranks from
    ``results`` (Table II CSV of ``case_dirs``) and ``with_results`` for ``with_cases``."""
    sets = {"study cases": (list(case_dirs), Path(results))}
    if with_cases:
        if not with_results:

            raise NavappError("--with-cases needs --with-results (their Table II CSV) for the ranks")
        sets["second set"] = (list(with_cases), Path(with_results))
    for _, csv_path in sets.values():
        if not csv_path.exists():

            raise InputError("no Table II results to rank against (run `navapp study table2` first)", csv_path)
    run_study(sets, report, bench_case=case_dirs[0], edge=edge, k=k)
    print(json.dumps({"report": str(Path(report) / "next_plane.md")}))



def table2_section(results_dir="results") -> str:
    """The short section on the error estimate and the suggested planes for the end of
results/table2.md, from
    error_estimate.csv, next_plane.csv and (when present) next_plane_lap.csv in
    ``results_dir``. Append it after ``report.write_report`` has (re)written table2.md."""

    res = Path(results_dir)
    with (res / "error_estimate.csv").open() as f:
        ee = list(csv.DictReader(f))
    with (res / "next_plane.csv").open() as f:
        npl = list(csv.DictReader(f))
    if (res / "next_plane_lap.csv").exists():
        with (res / "next_plane_lap.csv").open() as f:
            npl += [dict(r, set="laparoscopic cases") for r in csv.DictReader(f)]
    out = ["\n\n## Error estimate without the truth, and suggested planes\n\n",
           "Details: [error_estimate.md](error_estimate.md), [next_plane.md](next_plane.md) "
           "(`navapp study error-estimate`, `navapp study next-plane`).\n\n", table2_part(ee)]
    levels = ("S+1", "S+2", "S+3")
    for s in dict.fromkeys(r["set"] for r in npl):
        rows = [r for r in npl if r["set"] == s and r["criterion"] == "ê (default)"]
        source = ("results/table2_lapnh.csv, the nine transposed cases" if s == "laparoscopic cases"
                  else "results/table2.csv, the nine phantom cases")
        out.append(f"Suggested planes, greedy from S ({s}; TRE and ranks from {source}):\n\n"
                   "| level | mean TRE, suggested | mean TRE, all combinations (the paper-style row) | "
                   "median rank of the suggestion | suggestion better than the average |\n|---|---|---|---|---|\n")
        for lv in levels:
            rr = [r for r in rows if r["level"] == lv and r["rank"]]
            if not rr:
                continue
            tre = [float(r["tre_table2_mm"] or r["tre_mean_mm"]) for r in rr]
            better = sum(t < float(r["level_mean_mm"]) for t, r in zip(tre, rr, strict=True))
            out.append(f"| S + {lv[2]} suggested | {np.mean(tre):.2f} | "
                       f"{np.mean([float(r['level_mean_mm']) for r in rr]):.2f} | "
                       f"{np.median([int(r['rank']) for r in rr]):.0f} of {rr[0]['combinations']} | "
                       f"{better} of {len(rr)} cases |\n")
        out.append("\n")
    return "".join(out)
