"""What accuracy costs in time: the same data registered at several settings, each row
giving the seconds spent and the TRE reached, and the Pareto front of (time, TRE).

``lm_sweep`` varies only the solve (LM iteration cap and stopping tolerance) on one
registration model, so it runs in seconds and serves the viewer's settings panel; the
study command (``navapp study cost``) adds the settings that need a new basis (k, mesh
edge) and the amount of data (planes).
"""

import csv
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .. import progress
from ..anatomy.caseio import read_case
from ..anatomy.meshing import cached_tetmesh
from ..defaults import EDGE_MM, N_PLANES, K
from ..geometry.interpolation import interpolation_matrix
from ..geometry.tre import mean_tre
from ..registration.libr import LMOptions
from ..registration.pipeline import prepare, register
from ..simulation.levels import data_level, plus_planes
from .distribute import ResultsCSV, check_scheduler, run_tasks
from .peers import cpd_register, icp_register

LM_CAPS = (0, 1, 2, 4, 8, 16, 100)  # 0 = rigid only
LM_RTOLS = (1e-1, 1e-2, 1e-3)


@dataclass
class CostRow:
    label: str
    seconds: float  # wall time of the registration (rigid ICP included)
    tre_mean_mm: float
    iterations: int
    settings: dict


def run_setting(model, data, x0, x1, label, options: LMOptions | None = None, deform=True, B=None,
                **settings) -> CostRow:
    """Register ``data`` once; TRE of the registered preoperative points ``x0`` (T, 3)
    against their true positions ``x1`` (T, 3), mm. ``B``: x0's interpolation matrix."""
    t = time.perf_counter()
    reg = register(model, data, deform=deform, options=options)
    sec = time.perf_counter() - t
    tre = mean_tre(reg.transform(x0, B=B), x1)
    return CostRow(label, sec, tre, reg.libr.iterations if reg.libr else 0, settings)


def _cap_label(cap: int) -> str:
    return f"{cap} it" if cap else "rigid"


def _rtol_label(rtol: float) -> str:
    return f"rtol {rtol:g}"


def lm_sweep(model, data, x0, x1, caps=LM_CAPS, rtols=LM_RTOLS, cancel=None, on_row=None, B=None,
             base: LMOptions | None = None) -> list[CostRow]:
    """Rows for each iteration cap (at the default tolerance) and each tolerance (no cap).
    ``cancel`` (threading.Event) stops between settings; ``on_row`` sees each row as it lands;
    ``B``: x0's interpolation matrix, if the caller has it; ``base``: the fit's other options
    (the viewer's robust weights: its sweep is of its own fit)."""
    base = base or LMOptions()
    plan = [(_cap_label(c), replace(base, max_iterations=max(c, 1)), c > 0, {"max_iterations": c}) for c in caps]
    plan += [(_rtol_label(r), replace(base, rtol=r), True, {"rtol": r}) for r in rtols]
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0) if B is None else B
    rows = []
    for label, opt, deform, settings in plan:
        if cancel is not None and cancel.is_set():
            break
        row = run_setting(model, data, x0, x1, label, opt, deform, B, **settings)
        rows.append(row)
        if on_row is not None:
            on_row(row)
    return rows


def pareto_front(seconds, errors) -> np.ndarray:
    """Boolean mask (N,) of the points no other point beats in both time and error
    (ties kept); the front a user picks a setting from."""
    t, e = np.asarray(seconds, float), np.asarray(errors, float)
    keep = np.ones(len(t), bool)
    for i in range(len(t)):
        dominated = (t <= t[i]) & (e <= e[i]) & ((t < t[i]) | (e < e[i]))
        keep[i] = not dominated.any()
    return keep


# ---------------------------------------------------------------- navapp study cost

COST_COLUMNS = ("case", "sweep", "level", "method", "edge_mm", "k", "setting", "planes", "nodes",
                "precompute_s", "register_s", "tre_mean_mm", "iterations")
KS = (15, 30, 45, 60, 90)
EDGES = (6.0, 4.0, 3.0)
PLANE_COUNTS = (0, 1, 2, 4, 8, N_PLANES)
SWEEP_LEVELS = {"S": (), "S+3": (0, 5, 10), "S+all": tuple(range(N_PLANES))}  # data levels of the k and edge sweeps
DEFAULT_EDGE, DEFAULT_K = EDGE_MM, K


def _plan(ks, edges, edge0, k0):
    """(sweep, edge, k) model configurations, the default (edge0, k0) first (it serves the
    LM, planes and peer sweeps too)."""
    out = [("default", edge0, k0)]
    out += [("k", edge0, k) for k in ks if k != k0]
    out += [("edge", e, k0) for e in edges if e != edge0]
    return out


def _planned_keys(case, ks, edges, caps, rtols, plane_counts, peers, edge0, k0) -> dict:
    """The row keys each model configuration (sweep, edge, k) of ``cost_case`` produces,
    known before anything is computed (so that a resumed study skips whole configurations)."""
    def key(sweep, level, method, edge, k, setting):
        return (case, sweep, level, method, float(edge), int(k), setting)

    out = {}
    for sweep, edge, k in _plan(ks, edges, edge0, k0):
        keys = {key("k" if sweep == "default" else sweep, lv, "LIBR", edge, k, "default") for lv in SWEEP_LEVELS}
        if sweep == "default":
            keys |= {key("edge", lv, "LIBR", edge, k, "default") for lv in SWEEP_LEVELS}
            for lv in ("S", "S+3"):
                keys |= {key("lm", lv, "LIBR" if c else "rigid ICP", edge, k, _cap_label(c)) for c in caps}
                keys |= {key("lm", lv, "LIBR", edge, k, _rtol_label(r)) for r in rtols}
            keys |= {key("planes", plus_planes(m), "LIBR", edge, k, "default") for m in plane_counts}
            if peers:
                keys |= {key("peers", lv, m, edge, k, "default") for lv in SWEEP_LEVELS for m in ("rigid ICP", "CPD")}
        out[(sweep, edge, k)] = keys
    return out


def cost_case(case_dir, ks=KS, edges=EDGES, caps=LM_CAPS, rtols=LM_RTOLS, plane_counts=PLANE_COUNTS,
              peers=True, done=frozenset(), edge0=DEFAULT_EDGE, k0=DEFAULT_K, tre_edge=EDGE_MM) -> list[dict]:
    """All cost-study rows of one simulated case that are not in ``done`` (row keys, see
    ``_row_key``). Work whose rows are all done is not redone: a model configuration with
    nothing left is neither precomputed nor registered, and within one only the missing
    registrations run.

    Precompute seconds are measured cold (mesh + basis in an empty temporary cache), once
    per (edge, k); registration seconds are one run each, rigid ICP included. Every
    configuration's TRE is taken at the same points: the nodes of the liver meshed at
    ``tre_edge`` mm (the default registration mesh's)."""


    case_dir = Path(case_dir)
    plan = _planned_keys(case_dir.name, ks, edges, caps, rtols, plane_counts, peers, edge0, k0)
    todo = {cfg: keys - set(done) for cfg, keys in plan.items()}
    if not any(todo.values()):
        return []
    with progress.quiet():  # a study step (often in a worker process): no bars of its own
        return _cost_case(case_dir, todo, caps, rtols, plane_counts, peers, tre_edge)


def _cost_case(case_dir, todo, caps, rtols, plane_counts, peers, tre_edge) -> list[dict]:

    case = read_case(case_dir)
    x0, x1 = case.need_truth().tre_points(cached_tetmesh(case.preop.liver, tre_edge)[0].nodes)
    levels = {name: data_level(case_dir, "S+planes", planes=pl, case=case) for name, pl in SWEEP_LEVELS.items()}
    rows: list[dict] = []

    def row(sweep, level, method, edge, k, setting, planes, nodes, pre, reg_s, tre, its):
        r = {"case": case_dir.name, "sweep": sweep, "level": level, "method": method, "edge_mm": edge, "k": k,
             "setting": setting, "planes": planes, "nodes": nodes, "precompute_s": round(pre, 2),
             "register_s": round(reg_s, 4), "tre_mean_mm": round(tre, 4), "iterations": its}
        if _row_key(r) in want:
            rows.append(r)

    def missing(sweep, level, method, edge, k, setting="default"):
        return (case_dir.name, sweep, level, method, float(edge), int(k), setting) in want

    for (sweep, edge, k), want in todo.items():
        if not want:
            continue  # every row of this model configuration is done: no precompute, no registration
        with tempfile.TemporaryDirectory(prefix="navapp-cost-") as tmp:
            t = time.perf_counter()
            model, _ = prepare(case, edge, k, cache_root=Path(tmp))
            pre = time.perf_counter() - t
        nodes = len(model.basis.nodes)
        B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
        for level, data in levels.items():
            first = "k" if sweep == "default" else sweep
            if not (missing(first, level, "LIBR", edge, k) or (sweep == "default" and missing("edge", level, "LIBR",
                                                                                                 edge, k))):
                continue
            r = run_setting(model, data, x0, x1, "default", B=B)
            row(first, level, "LIBR", edge, k, "default", len(SWEEP_LEVELS[level]), nodes, pre, r.seconds,
                r.tre_mean_mm, r.iterations)
            if sweep == "default":
                row("edge", level, "LIBR", edge, k, "default", len(SWEEP_LEVELS[level]), nodes, pre, r.seconds,
                    r.tre_mean_mm, r.iterations)
        if sweep != "default":
            continue
        for level in ("S", "S+3"):
            lm_caps = [c for c in caps if missing("lm", level, "LIBR" if c else "rigid ICP", edge, k, _cap_label(c))]
            lm_rtols = [r for r in rtols if missing("lm", level, "LIBR", edge, k, _rtol_label(r))]
            if not lm_caps and not lm_rtols:
                continue
            for r in lm_sweep(model, levels[level], x0, x1, lm_caps, lm_rtols, B=B):
                row("lm", level, "LIBR" if r.iterations or r.label != "rigid" else "rigid ICP", edge, k, r.label,
                    len(SWEEP_LEVELS[level]), nodes, pre, r.seconds, r.tre_mean_mm, r.iterations)
        for m in plane_counts:
            if not missing("planes", plus_planes(m), "LIBR", edge, k):
                continue
            planes = tuple(np.linspace(0, N_PLANES - 1, m).round().astype(int)) if m else ()
            data = data_level(case_dir, "S+planes", planes=planes, case=case)
            r = run_setting(model, data, x0, x1, "default", B=B)
            row("planes", plus_planes(m), "LIBR", edge, k, "default", m, nodes, pre, r.seconds, r.tre_mean_mm,
                r.iterations)
        if peers:
            for level, data in levels.items():
                for method, peer in (("rigid ICP", icp_register), ("CPD", cpd_register)):
                    if not missing("peers", level, method, edge, k):
                        continue
                    res = peer(model, data, x0)
                    tre = mean_tre(res.moved, x1)
                    row("peers", level, res.method, edge, k, "default", len(SWEEP_LEVELS[level]), nodes, 0.0,
                        res.seconds, tre, 0)
    return rows


def _row_key(r) -> tuple:
    return (r["case"], r["sweep"], r["level"], r["method"], float(r["edge_mm"]), int(r["k"]), r["setting"])


def run_cost_study(case_dirs, results_csv, workers=1, quick=False, scheduler=None, **settings) -> int:
    """Run (or resume) the cost study over ``case_dirs``, one process per case; appends
    rows to ``results_csv``. Returns the number of new rows. ``quick``: k ∈ {15, 45},
    edges {6, 4}, fewer LM settings, no CPD; ``settings`` override ``cost_case``'s.
    ``scheduler``: a Dask scheduler's address (checked before any work); each case runs on
    one of its workers (their timings are then that worker's)."""


    results_csv = Path(results_csv)
    done = set()
    if results_csv.exists():
        with results_csv.open() as f:
            done = {_row_key(r) for r in csv.DictReader(f)}
    kw: dict = {"done": frozenset(done)}
    if quick:
        kw.update(ks=(15, 45), edges=(6.0, 4.0), caps=(0, 2, 100), rtols=(1e-1,), plane_counts=(0, 2), peers=False)
    kw.update(settings)
    if scheduler:
        check_scheduler(scheduler)
    new = 0
    with ResultsCSV(results_csv, COST_COLUMNS) as out, progress.bar(len(case_dirs), "cost study", "case") as pb:
        for rows in run_tasks(_cost_task, [(c, kw) for c in case_dirs], scheduler, workers):
            out.write(rows)
            new += len(rows)
            pb.update(1)
    return new


def _cost_task(case_dir, kw):
    """``cost_case`` with its settings as one argument (``run_tasks`` passes positions)."""
    return cost_case(case_dir, **kw)
