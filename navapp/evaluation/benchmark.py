"""Benchmarks: commands that print numbers (never timed unit tests).

``navapp bench precompute``: mesh + basis wall time, peak memory, cache-load time, over
element sizes and k. ``navapp bench register``: registration time on the demo case
(stylus swath + iUS planes), per-iteration cost breakdown, warm-started re-registration
after adding a plane, and TRE.
"""

import json
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _peak_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def precompute_one(edge: float, k: int) -> dict:
    """Run in a fresh process (cold cache dir) so that peak memory is this run's alone."""
    from .. import cache
    from ..anatomy.meshing import cached_tetmesh
    from ..anatomy.phantom import make_phantom
    from ..mechanics.basis import BasisSettings, load_or_compute_basis

    root = Path(tempfile.mkdtemp(prefix="navapp-bench-"))
    t0 = time.perf_counter()
    liver = make_phantom(0).liver
    mesh, rep = cached_tetmesh(liver, edge, root)
    basis, _ = load_or_compute_basis(mesh, BasisSettings(k=k), cache_root=root)
    total = time.perf_counter() - t0
    t1 = time.perf_counter()
    cached_tetmesh(liver, edge, root)
    load_or_compute_basis(mesh, BasisSettings(k=k), cache_root=root)
    reload = time.perf_counter() - t1
    del cache
    return {"edge_mm": edge, "k": k, "nodes": basis.M, "surface_nodes": len(basis.surface),
            "seconds": {"mesh": round(rep["seconds"], 2), **{s: round(v, 2) for s, v in basis.timings.items()}},
            "total_seconds": round(total, 2), "cache_load_seconds": round(reload, 3), "peak_memory_mb": round(_peak_mb())}


def bench_precompute(edges, ks):
    rows = []
    for edge in edges:
        for k in ks:
            out = subprocess.run([sys.executable, "-m", "navapp.evaluation.benchmark", "precompute-one", str(edge), str(k)],
                                 capture_output=True, text=True, check=True)
            row = json.loads(out.stdout.strip().splitlines()[-1])
            print(json.dumps(row), flush=True)
            rows.append(row)
    return rows


def bench_register(repeats=5, planes=3, k=45, edge=4.0):
    from ..registration.libr import LMOptions
    from ..registration.pipeline import prepare, register, tre_stats
    from ..simulation.demo import demo_case

    case = demo_case(registration_edge=edge, planes=planes)
    fewer = demo_case(registration_edge=edge, planes=planes - 1)
    model, _ = prepare(case, edge, k)
    x0, x1 = case.targets[:, :3], case.targets[:, 3:]
    times, rigid_s, iters = [], [], []
    for _ in range(repeats):
        reg = register(model, case.intraop)
        times.append(reg.seconds["rigid"] + reg.seconds["deformable"])
        rigid_s.append(reg.seconds["rigid"])
        iters.append(reg.libr.iterations)
    per_iter = {s: round(1000 * v / max(reg.libr.iterations, 1), 2) for s, v in reg.libr.timings.items()}
    base = register(model, fewer.intraop)
    t = time.perf_counter()
    warm = register(model, case.intraop, beta0=base.libr.beta, rigid=base.rigid)
    warm_s = time.perf_counter() - t
    quick = register(model, case.intraop, options=LMOptions(max_iterations=15))
    out = {
        "nodes": model.basis.M, "k": model.basis.k, "planes": planes,
        "points": {n: len(p) for n, p in reg.data_model_frame.items()},
        "median_seconds": round(statistics.median(times), 3), "min_seconds": round(min(times), 3),
        "median_rigid_icp_seconds": round(statistics.median(rigid_s), 3),
        "iterations": iters[0], "stop_reason": reg.libr.stop_reason, "per_iteration_ms": per_iter,
        "warm_start_after_adding_plane": {"seconds": round(warm_s, 3), "iterations": warm.libr.iterations,
                                          "tre_mm": round(tre_stats(warm.transform(x0), x1)["mean_mm"], 2)},
        "tre_mm": {"rigid": round(tre_stats(reg.rigid.apply(x0), x1)["mean_mm"], 2),
                   "deformable": round(tre_stats(reg.transform(x0), x1)["mean_mm"], 2),
                   "deformable_15_iterations": round(tre_stats(quick.transform(x0), x1)["mean_mm"], 2)},
    }
    print(json.dumps(out), flush=True)
    return out


if __name__ == "__main__" and len(sys.argv) == 4 and sys.argv[1] == "precompute-one":
    from .. import progress

    progress.QUIET = True
    print(json.dumps(precompute_one(float(sys.argv[2]), int(sys.argv[3]))))
