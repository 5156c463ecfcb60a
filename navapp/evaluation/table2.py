"""The paper's Table II design on simulated cases (§III): every case registered at every
data level — rigid, S, S + 1 plane (16 choices), S + 2 (120), S + 3 (560), S + all 16,
CBCT, iCT — and, for a case with a registered data source's points (``simulation.sources``),
S + that source ("S+laparoscope"), with one CSV row per registration, appended as results
arrive so that a rerun skips what is done.

Work is cut into chunks of scenarios of one case (a chunk loads that case's cached basis
once); chunks run on local processes, or on a Dask distributed cluster with
``scheduler=ADDRESS`` (no home-made task distribution).
"""

import csv
import itertools
import os
import time
from pathlib import Path

import numpy as np

from .. import progress
from ..anatomy.caseio import read_case
from ..defaults import EDGE_MM, N_PLANES, K
from ..geometry.interpolation import interpolation_matrix
from ..geometry.tre import tre_stats
from ..registration.pipeline import prepare, register, rigid_starts
from ..simulation.levels import (  # noqa: F401 (LEVELS: Table II's rows)
    LEVELS,
    case_planes,
    case_source_levels,
    fixed_planes,
    plus_planes,
    study_data,
    stylus_only_pose,
)
from .distribute import DASK_CONNECT_S, ResultsCSV, check_scheduler, dask_client, run_tasks  # noqa: F401

PAPER = {"rigid": (13.8, None), "S": (11.4, None), "S+1": (9.0, None), "S+2": (7.4, None), "S+3": (6.4, None),
         "S+all": (3.9, None), "CBCT": (4.5, None), "iCT": (2.8, None)}  # mean TRE (mm) over the paper's 9 cases
COLUMNS = ("case", "level", "planes", "tre_mean_mm", "tre_sd_mm", "tre_max_mm", "iterations", "stop_reason", "seconds")


def scenarios(n_planes=N_PLANES, quick=False, rng_seed=0, sources=()):
    """(level, planes) pairs of the design; ``quick`` keeps two choices per plane level;
    ``sources``: the source levels of a case that has their data (``case_source_levels``).
    A case with fewer planes than ``N_PLANES`` (a laparoscopic case without ultrasound) has
    the plane levels it can: none of them without planes."""
    out: list[tuple[str, tuple[int, ...]]] = [("rigid", ()), ("S", ())]
    for m in (1, 2, 3):
        combos = list(itertools.combinations(range(n_planes), m))
        if quick and len(combos) > 2:
            rng = np.random.default_rng(rng_seed + m)
            combos = [combos[i] for i in sorted(rng.choice(len(combos), 2, replace=False))]
        out += [(plus_planes(m), c) for c in combos]
    last = ("S+all",) * (n_planes > 0) + tuple(sources) + ("CBCT", "iCT")
    out += [(level, fixed_planes(level, n_planes)) for level in last]
    return out


def _key(case, level, planes):
    return (case, level, "-".join(map(str, planes)))


@progress.quiet()  # scoped: it also runs in the caller's process (cache warming) and must not silence it
def run_chunk(case_dir, items, edge=EDGE_MM, k=K, init=None):
    """Register one case at the given (level, planes) items; returns CSV rows (dicts).
    ``init``: the registration's ``RobustOptions`` (default: the pipeline's)."""

    case_dir = Path(case_dir)
    case = read_case(case_dir)
    model, _ = prepare(case, edge, k)
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)  # once: it costs as much as a registration
    # The multi-start ICP sees only the stylus features (registration/rigid.py), which are
    # the same for S and every S + planes scenario of a case: it runs once per chunk and its
    # time is added to each of those rows, so "seconds" stays a whole registration. The rest
    # of the rigid stage (screening, pose rules) runs per row: a row equals ``register``'s.
    t = time.perf_counter()
    stylus = study_data(case_dir, "S", case=case)
    starts = rigid_starts(model, stylus, init=init)
    icp_sec = time.perf_counter() - t
    rows = []
    for level, planes in items:
        data = study_data(case_dir, level, planes, case=case, stylus=stylus)
        # with the iUS posterior wall in the rigid fit, the planes change the rigid features too
        shared = stylus_only_pose(level) and not (init is not None and init.rigid_posterior)
        t = time.perf_counter()
        reg = register(model, data, deform=level != "rigid", init=init, starts=starts if shared else None)
        sec = time.perf_counter() - t + (icp_sec if shared else 0.0)
        tre = tre_stats(reg.transform(x0, B=B), x1)
        rows.append({"case": case_dir.name, "level": level, "planes": "-".join(map(str, planes)),
                     "tre_mean_mm": round(tre.mean_mm, 4), "tre_sd_mm": round(tre.sd_mm, 4),
                     "tre_max_mm": round(tre.max_mm, 4), "iterations": reg.libr.iterations if reg.libr else 0,
                     "stop_reason": reg.libr.stop_reason if reg.libr else "rigid", "seconds": round(sec, 4)})
    return rows


def read_results(path):
    path = Path(path)
    if not path.exists():
        return []
    with path.open() as f:
        return list(csv.DictReader(f))


def run_table2(case_dirs, results, workers=None, scheduler=None, quick=False, chunk=40, edge=EDGE_MM, k=K):
    """Run (or resume) the design over ``case_dirs``; appends rows to ``results`` (CSV).
    ``scheduler``: a Dask scheduler's address, checked before any work."""
    results = Path(results)
    done = {_key(r["case"], r["level"], tuple(int(p) for p in r["planes"].split("-") if p))
            for r in read_results(results)}
    todo = []
    for d in case_dirs:
        design = scenarios(case_planes(d), quick=quick, sources=case_source_levels(d))
        items = [s for s in design if _key(Path(d).name, *s) not in done]
        todo += [(str(d), items[i:i + chunk], edge, k) for i in range(0, len(items), chunk)]
    total = sum(len(t[1]) for t in todo)
    if not total:
        return 0
    if scheduler:
        check_scheduler(scheduler)
    # warm every case's cache once, serially, so parallel workers never race to compute it
    for d in case_dirs:
        run_chunk(d, [], edge, k)
    with ResultsCSV(results, COLUMNS) as out, progress.bar(total, "Table II registrations", "reg") as pb:
        for rows in run_tasks(run_chunk, todo, scheduler, workers or os.cpu_count()):
            out.write(rows)
            pb.update(len(rows))
    return total
