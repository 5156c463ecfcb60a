"""Validation of the truth-free error estimate (``registration.uncertainty``) against the
simulated truth: ``navapp study error-estimate``.

Every study case is registered at the levels S, S + 1, S + 2, S + 3 (``combos`` seeded
random plane choices each), S + all and CBCT, the way Table II registers them; at every
mesh node (the cases' targets are the mesh nodes) the estimate's d and σ are recorded
beside the true error. The calibration ê = a + b·d + c·σ + e·d·m (m: median d over the
nodes) and its band are fitted on the calibration livers' cases only — in every case set
given (e.g. the direct gravity cases and the transposed ones) — and judged on the cases of
the other livers, per set and per level: Pearson r between ê and the true error (pooled
over the level's registrations, and the median of per-registration r), r of d alone and σ
alone, and the fraction of nodes whose true error lies in the band. A liver is identified
by its preoperative surface file (``liver_id``), so no liver is in both the fit and the
validation whatever the cases are called.

The band is widened until it holds the nominal coverage on the calibration liver's cases
at every level of every set (``fit_band``). A set may take part in the band only
(``band_only``: the local-load cases, tool*): ê's coefficients, which also rank the
suggested next planes, are fitted on the other sets. ``liver_rotation`` repeats the
calibration with each liver in turn and judges the others. The band and the tables count
only registrations whose answer is deformable (``Registration.deformed``): the viewer shows
no band for a rigid answer.
"""

import csv
import hashlib
import itertools
import json
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy.optimize import nnls

from .. import progress
from ..anatomy.caseio import read_case
from ..defaults import EDGE_MM, K
from ..errors import InputError, NavappError
from ..geometry.tre import point_errors
from ..registration.pipeline import prepare, register, rigid_starts
from ..registration.uncertainty import Calibration, estimate_error
from ..simulation.levels import fixed_planes, has_planes, plane_count, study_data, stylus_only_pose

# the levels the estimate is calibrated and validated at (module doc), of ``simulation.levels.LEVELS``
ESTIMATE_LEVELS = ("S", "S+1", "S+2", "S+3", "S+all", "CBCT")
NOMINAL = 0.9  # band coverage asked of the calibration
FIT_NODES = 2000  # nodes per registration in the fit (every registration counts the same)


@dataclass
class Sample:
    case: str
    level: str
    planes: tuple
    d: np.ndarray  # (M,) mm
    sigma: np.ndarray  # (M,) mm
    err: np.ndarray  # (M,) true error, mm
    seconds: float  # the estimate's time at all M nodes
    liver: str = ""  # ``liver_id`` of the case: which preoperative liver it registers
    deformed: bool = True  # the answer is the deformable fit (the viewer shows a band only then)


def liver_id(case_dir) -> str:
    """Which liver a case is (12 hex digits): a hash of its preoperative surface,
    ``preop/liver.ply``. Cases of one anatomy share it whatever deformation they simulate
    (phantom0-L and lap0-R are the same liver); the split into calibration and validation
    cases is made on it."""
    path = Path(case_dir) / "preop" / "liver.ply"
    if not path.is_file():

        raise InputError("no preoperative liver surface (preop/liver.ply)", Path(case_dir))
    return hashlib.sha1(path.read_bytes()).hexdigest()[:12]


def plane_choices(level, n_planes, combos, rng):
    if level == "S+all" or not has_planes(level):
        return [fixed_planes(level, n_planes)]
    m = plane_count(level)
    allc = list(itertools.combinations(range(n_planes), m))
    return [allc[i] for i in sorted(rng.choice(len(allc), min(combos, len(allc)), replace=False))]


def collect_case(case_dir, levels=ESTIMATE_LEVELS, combos=3, seed=0, edge=EDGE_MM, k=K) -> list[Sample]:
    """Register one case at every level and record d, σ and the true error per mesh node."""


    case_dir = Path(case_dir)
    case = read_case(case_dir)
    model, _ = prepare(case, edge, k)
    x1 = case.need_truth().at(model.basis.nodes)  # the truth at every node (measured points: InputError)
    n_planes = len([p for p in (case_dir / "intraop" / "us").glob("plane_??") if p.is_dir()])
    stylus = study_data(case_dir, "S", case=case)
    starts = rigid_starts(model, stylus)  # shared by S and S + planes (``register``'s ``starts``)
    rng = np.random.default_rng(seed + sum(map(ord, case_dir.name)))
    out = []
    for level in levels:
        for planes in plane_choices(level, n_planes, combos, rng):
            data = study_data(case_dir, level, planes, case=case, stylus=stylus)
            reg = register(model, data, starts=starts if stylus_only_pose(level) else None)
            t = time.perf_counter()
            est = estimate_error(reg)
            sec = time.perf_counter() - t
            err = point_errors(est.positions, x1)
            out.append(Sample(case_dir.name, level, planes, est.distance_mm, est.sigma_mm, err, sec,
                              liver_id(case_dir), reg.deformed))
    return out


def fit_calibration(samples: list[Sample], coverage=NOMINAL, seed=0, name="") -> Calibration:
    """ê = a + b·d + c·σ + e·d·m by non-negative least squares on the pooled samples
    (``FIT_NODES`` random nodes of each registration; m = the registration's median d over
    all its nodes), each registration's rows weighted by 1 / (its mean true error)² so that
    the fit is on relative errors and cases with errors several times larger (the
    transposed ones) do not set the coefficients alone; then the band factors: the
    (1 ± coverage)/2 quantiles of true / ê over the same nodes."""
    D, S, E, Mm, W = _fit_rows(samples, np.random.default_rng(seed))
    A = np.column_stack([np.ones_like(D), D, S, D * Mm])
    (a, b, c, e), _ = nnls(A * W[:, None], E * W)
    cal = Calibration(float(a), float(b), float(c), float(e), coverage=coverage, fitted_on=name)
    lo, hi = _band_quantiles(cal, D, S, E, Mm, coverage)
    return replace(cal, lower=lo, upper=hi)


def _fit_rows(samples: list[Sample], rng) -> tuple[np.ndarray, ...]:
    """d, σ, true error, m (the registration's median d over all its nodes) and the weight
    1 / (its mean true error) at ``FIT_NODES`` random nodes of each registration, pooled."""
    parts: tuple[list, list, list, list, list] = ([], [], [], [], [])
    for s in samples:
        i = rng.choice(len(s.err), min(FIT_NODES, len(s.err)), replace=False)
        w = 1.0 / max(float(np.mean(s.err)), 1e-6)
        for part, v in zip(parts, (s.d[i], s.sigma[i], s.err[i], np.full(len(i), np.median(s.d)),
                                   np.full(len(i), w)), strict=True):
            part.append(v)
    return tuple(np.concatenate(p) for p in parts)


def _band_quantiles(cal: Calibration, D, S, E, Mm, coverage) -> tuple[float, float]:
    ratio = E / np.maximum(cal.predict(D, S, Mm), 1e-9)
    lo, hi = np.quantile(ratio, [(1 - coverage) / 2, (1 + coverage) / 2])
    return float(lo), float(hi)


def fit_band(cal: Calibration, sample_sets: list[list[Sample]], coverage=NOMINAL) -> Calibration:
    """Widen ``cal``'s band until it holds ``coverage`` of every set's samples at every
    level: per set and level the (1 ± coverage)/2 quantiles of true / ê over all the
    registrations' nodes, the band [smallest lower, largest upper] (it contains each
    group's own band, so it holds at least ``coverage`` of each). ê's coefficients are
    kept; empty sets are skipped. A liver's registrations have the same nodes, so every
    registration of a group counts the same."""
    lo, hi = cal.lower, cal.upper
    for samples in sample_sets:
        for level in dict.fromkeys(s.level for s in samples):
            group = [s for s in samples if s.level == level]
            D, S, E = (np.concatenate([getattr(s, a) for s in group]) for a in ("d", "sigma", "err"))
            Mm = np.concatenate([np.full(len(s.d), np.median(s.d)) for s in group])
            q_lo, q_hi = _band_quantiles(cal, D, S, E, Mm, coverage)
            lo, hi = min(lo, q_lo), max(hi, q_hi)
    return replace(cal, lower=lo, upper=hi)


def band_coverage(err, predicted, lower: float, upper: float) -> float:
    """The fraction of points whose true error lies in the band [ê·lower, ê·upper]
    (edges included); err, predicted (P,) mm."""
    err, predicted = np.asarray(err, float), np.asarray(predicted, float)
    return float(((err >= predicted * lower) & (err <= predicted * upper)).mean())


def _r(x, y):
    if len(x) < 3 or np.std(x) == 0 or np.std(y) == 0:
        return float("nan")
    return float(np.corrcoef(x, y)[0, 1])


def validate(samples: list[Sample], cal: Calibration) -> list[dict]:
    """Per level: r of ê (pooled, median per registration), of d and σ alone, band coverage."""
    rows = []
    for level in ESTIMATE_LEVELS + ("all",):
        ss = [s for s in samples if s.level == level or level == "all"]
        if not ss:
            continue
        d, sg, e = (np.concatenate([getattr(s, a) for s in ss]) for a in ("d", "sigma", "err"))
        each = [cal.predict(s.d, s.sigma, np.median(s.d)) for s in ss]
        p = np.concatenate(each)
        rows.append({"level": level, "cases": _cases(ss), "registrations": len(ss), "nodes": len(e),
                     "r_pred": _r(p, e),
                     "r_pred_median_per_reg": float(np.median([_r(q, s.err) for q, s in zip(each, ss, strict=True)])),
                     "r_distance": _r(d, e), "r_sigma": _r(sg, e),
                     "coverage": band_coverage(e, p, cal.lower, cal.upper),
                     "below_upper": float((e <= p * cal.upper).mean()), "mean_pred_mm": float(p.mean()),
                     "mean_true_mm": float(e.mean())})
    return rows


def split_and_fit(collected: dict, calibration_livers, coverage=NOMINAL,
                  band_only=()) -> tuple[Calibration, dict, list, list]:
    """Fit on the samples of ``calibration_livers`` (``liver_id`` values) in every set and
    judge each set's other livers with it.

    Parameters
    ----------
    collected : {set label: [Sample]}
    calibration_livers : the livers to fit on; every other liver validates.
    band_only : labels of sets ê's coefficients are not fitted on; the band is widened
        to hold ``coverage`` on their calibration-liver samples too, as on every set's
        (``fit_band``: at every level of every set).

    Only samples whose answer is deformable (``Sample.deformed``) are fitted and judged.

    Returns
    -------
    (calibration, {table name: validate rows}, calibration samples, validation samples).
    Raises NavappError when a liver would be both fitted and validated or a side is empty.
    """
    livers = set(calibration_livers)
    shown = {label: [s for s in v if s.deformed] for label, v in collected.items()}
    calib = [s for v in shown.values() for s in v if s.liver in livers]
    held = [s for v in shown.values() for s in v if s.liver not in livers]
    fit_on = [s for label, v in shown.items() if label not in band_only for s in v if s.liver in livers]
    if not fit_on or not held:
        raise NavappError("error-estimate needs cases of at least two livers (calibrated on the first case's liver, "
                          "validated on the others)")
    if {s.liver for s in calib} & {s.liver for s in held}:  # the split above makes this impossible; keep it so
        raise NavappError("error-estimate: a liver is in both the calibration and the validation cases")
    cal = fit_calibration(fit_on, coverage=coverage, name="+".join(sorted({s.case for s in fit_on})))
    cal = fit_band(cal, [[s for s in v if s.liver in livers] for v in shown.values()], coverage)
    if band_only:
        cal = replace(cal, fitted_on=cal.fitted_on + "; band also on "
                      + "+".join(sorted({s.case for label in band_only for s in shown.get(label, [])
                                         if s.liver in livers})))
    tables = {}
    for label, samples in shown.items():
        for part, ss in (("calibration cases (fit)", [s for s in samples if s.liver in livers]),
                         ("validation cases (held out)", [s for s in samples if s.liver not in livers])):
            if ss:
                tables[f"{label}: {part}"] = validate(ss, cal)
    return cal, tables, calib, held


@dataclass(frozen=True)
class RotationCell:
    """One held-out (set, level) cell of ``liver_rotation``: the band calibrated on
    ``calibrated_on``'s liver, judged on the other livers' registrations."""
    calibrated_on: str  # the calibration liver's first case in the first set
    lower: float
    upper: float
    set: str
    level: str
    registrations: int
    coverage: float  # fraction of the held-out nodes inside the band


def liver_rotation(collected: dict, band_only=(), coverage=NOMINAL) -> list[RotationCell]:
    """``split_and_fit`` with each liver in turn as the calibration liver (every liver with
    deformable registrations in a set ê is fitted on), each held-out (set, level) cell's
    band coverage: whether the band's rule, not one split's luck, holds on livers it was
    not fitted on."""
    fitted = [s for label, v in collected.items() if label not in band_only for s in v if s.deformed]
    livers = list(dict.fromkeys(s.liver for s in fitted))
    out = []
    for liver in livers:
        cal, tables, _, _ = split_and_fit(collected, [liver], coverage, band_only)
        name = next(s.case for s in fitted if s.liver == liver)
        for label in collected:  # each set's held-out table, by the name split_and_fit gives it
            rows = tables.get(f"{label}: validation cases (held out)", [])
            out += [RotationCell(name, cal.lower, cal.upper, label, r["level"], r["registrations"], r["coverage"])
                    for r in rows if r["level"] != "all"]
    return out


def rotation_markdown(cells: list[RotationCell], coverage=NOMINAL) -> str:
    """One row per calibration liver: its band, the held-out cells at or above ``coverage``
    and the lowest cell."""
    text = [f"\n## Every liver in turn\n\nThe calibration repeated with each liver as the calibration liver "
            f"(`liver_rotation`), each other liver's registrations judged per set and level: the cells holding "
            f"{coverage:.0%} or more, and the lowest.\n\n| calibrated on the liver of | band | cells ≥ {coverage:.0%} "
            "| lowest cell |\n|---|---|---|---|\n"]
    for name in dict.fromkeys(c.calibrated_on for c in cells):
        cc = [c for c in cells if c.calibrated_on == name]
        low = min(cc, key=lambda c: c.coverage)
        text.append(f"| {name} | [{cc[0].lower:.3f} ê, {cc[0].upper:.3f} ê] | "
                    f"{sum(c.coverage >= coverage for c in cc)} of {len(cc)} | "
                    f"{low.coverage:.1%} ({low.set}, {low.level}) |\n")
    return "".join(text)


def collect_sets(sets: dict, combos=3, seed=0, edge=EDGE_MM, k=K) -> dict:
    """{label: case_dirs} → {label: [Sample]} (``collect_case`` on every case, with progress)."""
    collected: dict = {}
    with progress.bar(sum(len(v) for v in sets.values()), "error estimate: cases", "case") as pb:
        for label, dirs in sets.items():
            collected[label] = []
            for d in dirs:
                collected[label] += collect_case(d, combos=combos, seed=seed, edge=edge, k=k)
                pb.update(1)
    return collected


def run_study(sets: dict, out_dir, combos=3, seed=0, band_only=(), collected: dict | None = None,
              edge=EDGE_MM, k=K):
    """Collect every set's cases ({label: case_dirs}; or take ``collected``, as
    ``collect_sets`` returns it), fit on the first case's liver in all sets
    (``split_and_fit``; sets in ``band_only`` widen the band only), validate on the other
    livers, write ``error_estimate.md`` and ``error_estimate.csv`` in ``out_dir``. ``edge``, ``k``:
    the registration model (mm, control points)."""
    if collected is None:
        collected = collect_sets(sets, combos, seed, edge, k)
    first = next(iter(sets.values()))[0]
    cal, tables, calib, held = split_and_fit(collected, [liver_id(first)], band_only=band_only)
    secs = [s.seconds for v in collected.values() for s in v]
    rigid = {label: sum(not s.deformed for s in v) for label, v in collected.items()}
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fitted = {k: getattr(cal, k) for k in ("a", "b", "c", "e", "lower", "upper")}
    cols = ("set", "level", "cases", "registrations", "nodes", "r_pred", "r_pred_median_per_reg", "r_distance",
            "r_sigma", "coverage", "below_upper", "mean_pred_mm", "mean_true_mm", *fitted)
    with (out / "error_estimate.csv").open("w", newline="") as f:  # every row carries the calibration it judges
        w = csv.DictWriter(f, cols)
        w.writeheader()
        for name, rows in tables.items():
            for r in rows:
                w.writerow({"set": name, **{k: (round(v, 4) if isinstance(v, float) else v) for k, v in r.items()},
                            **{k: f"{v:.6g}" for k, v in fitted.items()}})
    rotation = rotation_markdown(liver_rotation(collected, band_only))
    (out / "error_estimate.md").write_text(markdown(tables, cal, calib, held, secs, sets, band_only, rigid)
                                           + rotation)
    return cal, tables


def _cases(samples) -> str:
    return ", ".join(sorted({s.case for s in samples}))


def markdown(tables, cal, calib, held, secs, sets, band_only=(), rigid=None) -> str:
    cases = _cases
    text = ["# A registration-error estimate without the truth\n\n",
            "Per mesh node, from what the registration knows: d = distance from the node's registered position to the "
            "nearest data point, and σ = the LM covariance at the solution, s·H⁻¹ (H the LM normal matrix with the "
            "strain-energy curvature, s = Ω/(R − p)), propagated through the closed-form ∂x/∂β of eq. 8. Predicted "
            f"error ê = a + b·d + c·σ + e·d·m (m = the median of d over the mesh nodes: how sparse the data are), "
            f"band [ê·{cal.lower:.3f}, ê·{cal.upper:.3f}] for a nominal "
            f"{cal.coverage:.0%} of nodes.\n\n",
            f"Calibration (non-negative least squares on relative errors: each registration's {FIT_NODES} sampled "
            f"nodes weighted by 1/(its mean true error)²) on {cases(calib)}: "
            f"a = {cal.a:.4f} mm, b = {cal.b:.5f}, c = {cal.c:.4f}, e = {cal.e:.6f} /mm. Validated on {cases(held)}: "
            "no liver is in both (livers told apart by their preoperative surface). Levels as in Table II; "
            "S + 1/2/3: seeded random plane choices per case. "
            "r: Pearson r between predicted and true per-node error pooled over the level's registrations "
            "(median over registrations beside it); coverage: fraction of nodes whose true error lies in the band; "
            "below upper: fraction under the band's upper edge.\n"]
    if band_only:
        text.append(f"\nê's coefficients are fitted on {', '.join(k for k in sets if k not in band_only)} only; the "
                    f"band is then widened until it holds {cal.coverage:.0%} of the calibration liver's nodes at "
                    f"every level of every set, {', '.join(band_only)} included (per set and level the quantiles "
                    "of true / ê; the band spans the smallest lower and the largest upper factor).\n")
    if rigid and any(rigid.values()):
        text.append("\nRegistrations whose answer is the rigid pose alone (the deformation not supported from a kept "
                    "pose: the viewer shows no band) are left out: "
                    + "; ".join(f"{k}: {v}" for k, v in rigid.items()) + ".\n")
    for name, rows in tables.items():
        text.append(f"\n## {name}\n\n| level | registrations | r (ê) | median r per registration | r (d only) | "
                    "r (σ only) | coverage | below upper | mean ê (mm) | mean true (mm) |\n"
                    "|---|---|---|---|---|---|---|---|---|---|\n")
        for r in rows:
            text.append(f"| {r['level']} | {r['registrations']} | {r['r_pred']:.2f} | "
                        f"{r['r_pred_median_per_reg']:.2f} | "
                        f"{r['r_distance']:.2f} | {r['r_sigma']:.2f} | {r['coverage']:.0%} | {r['below_upper']:.0%} | "
                        f"{r['mean_pred_mm']:.2f} | {r['mean_true_mm']:.2f} |\n")
    text.append(f"\nThe estimate at every mesh node (≈16–19k) takes median {np.median(secs) * 1e3:.0f} ms "
                f"(max {np.max(secs) * 1e3:.0f} ms) per registration on this shared machine.\n")
    text.append("\nCases: " + "; ".join(f"{k}: {', '.join(Path(d).name for d in v)}" for k, v in sets.items()) + "\n")
    return "".join(text)


def table2_part(rows: list[dict]) -> str:
    """The error-estimate lines of results/table2.md from error_estimate.csv's rows (dicts
    of strings): per held-out set, Pearson r and band coverage per level; the calibration
    cases' ranges in one sentence."""
    def levels(name):
        return [r for r in rows if r["set"] == name and r["level"] != "all"]

    def span(vals, fmt):
        lo, hi = fmt(min(vals)), fmt(max(vals))
        return lo if lo == hi else f"{lo}–{hi}"

    def cases_of(name):
        return sorted({c.strip() for r in rows if r["set"] == name and r.get("cases") for c in r["cases"].split(",")})

    names = list(dict.fromkeys(r["set"] for r in rows))
    first = rows[0] if rows else {}
    if first.get("a"):
        fit = (f" (a = {float(first['a']):.3g} mm, b = {float(first['b']):.3g}, c = {float(first['c']):.3g}, "
               f"e = {float(first['e']):.2g} /mm; band [{float(first['lower']):.3g} ê, {float(first['upper']):.3g} ê])")
    else:
        fit = ""
    calib = sorted({c for n in names if "calibration" in n for c in cases_of(n)})
    where = f" ({', '.join(calib)})" if calib else ""
    out = ["Predicted per-node error ê = a + b·d + c·σ + e·d·m (d: distance to the data, σ: LM covariance through "
           f"J_u, m: median d) with a band for a nominal 90 %, calibrated{fit} on the cases of one liver in every "
           f"case set{where} and judged on the other livers' cases (details in error_estimate.md).\n\n"]
    for name in names:
        if "calibration" in name:
            continue
        rr = levels(name)
        cases = f" ({', '.join(cases_of(name))})" if cases_of(name) else ""
        label = name.replace(" (held out)", "")
        out.append(f"{label}{cases}: Pearson r (ê vs true per-node error, pooled over the level's registrations) "
                   "and band coverage:\n\n")
        out.append("| | " + " | ".join(r["level"] for r in rr) + " |\n|---|" + "---|" * len(rr) + "\n")
        out.append("| r | " + " | ".join(f"{float(r['r_pred']):.2f}" for r in rr) + " |\n")
        out.append("| coverage | " + " | ".join(f"{float(r['coverage']):.0%}" for r in rr) + " |\n\n")
    fits = [n for n in names if "calibration" in n]
    if fits:
        parts = []
        for name in fits:
            rr = levels(name)
            parts.append(f"{name.split(':')[0]}: r {span([float(r['r_pred']) for r in rr], '{:.2f}'.format)}, "
                         f"coverage {span([float(r['coverage']) for r in rr], '{:.0%}'.format)}")
        out.append("On the calibration cases (all levels) — " + "; ".join(parts) + ".\n\n")
    return "".join(out)


def set_label(case_dirs) -> str:
    """A set's name in the report: its cases' common folder (e.g. study-cases-lap)."""
    parents = {Path(d).resolve().parent.name for d in case_dirs}
    return parents.pop() if len(parents) == 1 else "cases"


def study_command(case_dirs, args):
    """``navapp study error-estimate``: writes <report>/error_estimate.md and .csv. The
    calibration livers: the first case's liver, in ``--cases``, ``--with-cases`` and
    ``--band-cases`` (the last widen the band only)."""

    sets = {set_label(case_dirs): list(case_dirs)}
    band_only = []
    for more, only in ((getattr(args, "with_cases", None), False), (getattr(args, "band_cases", None), True)):
        if more:
            label = set_label(more)
            label = label if label not in sets else f"{label} ({len(sets) + 1})"
            sets[label] = list(more)
            if only:
                band_only.append(label)
    # --quick: one plane combination per level and case, not three
    cal, _ = run_study(sets, args.report, combos=1 if getattr(args, "quick", False) else 3,
                       band_only=tuple(band_only), edge=args.edge, k=args.k)
    print(json.dumps({"report": str(Path(args.report) / "error_estimate.md"), "calibration": cal.__dict__}))
