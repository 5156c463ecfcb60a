"""Benchmarks: commands that print numbers (never timed unit tests).

``navapp bench precompute``: mesh + basis wall time, peak memory, cache-load time, over
element sizes and k; ``--volume-ml`` scales phantom 0 (real livers of 1.2–2 l are larger
than the phantoms), ``--relax both`` adds the exact relaxation and the local one's error.
``navapp bench register``: registration time on the demo case (stylus swath + iUS planes),
per-iteration cost breakdown, warm-started re-registration after adding a plane, and TRE.
"""

import json
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from dataclasses import replace
from pathlib import Path

import numpy as np

from .. import cache
from ..anatomy.caseio import read_case
from ..anatomy.meshing import cached_tetmesh
from ..anatomy.phantom import make_phantom
from ..defaults import EDGE_MM, K
from ..errors import NavappError
from ..geometry.tre import tre_stats
from ..mechanics.basis import BasisSettings, basis_key, load_or_compute_basis
from ..mechanics.fem import Material
from ..mechanics.sparse import backend
from ..registration.libr import LMOptions
from ..registration.objective import cold_search
from ..registration.pipeline import prepare, register
from ..simulation.levels import data_level
from ..simulation.scene import demo_scene
from ..simulation.scenedata import simulated_case_dir
from .live_bench import before_path


def peak_memory_mb() -> float:
    """Peak resident memory of this process so far, MB (Linux ru_maxrss is in kB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def scaled_liver(liver, volume_ml: float):
    """The surface scaled uniformly about its centroid to ``volume_ml`` (ml = 1000 mm³):
    a real liver of 1.2–2 l meshes to 19k–27k nodes at 4 mm, the phantoms to fewer."""
    s = (1000.0 * volume_ml / liver.volume) ** (1.0 / 3.0)
    out = liver.copy()
    c = liver.center_mass
    out.vertices = c + s * (liver.vertices - c)
    return out


def precompute_one(edge: float, k: int, volume_ml: float | None = None, relax: str = "local",
                   mesh_from: str | None = None) -> dict:
    """Run in a fresh process (cold cache dir) so that peak memory is this run's alone.
    ``relax``: "local" (the default subdomain) or "exact" (whole-mesh relaxation).
    ``mesh_from``: a cached mesh file to start from (Gmsh does not give the same mesh twice,
    and exact and local bases are compared on one mesh); its row then has no mesh time."""

    settings = BasisSettings(k=k) if relax == "local" else BasisSettings(k=k, relax_layers=None)
    root = Path(tempfile.mkdtemp(prefix="navapp-bench-"))
    if mesh_from:
        shutil.copy(mesh_from, root)
    liver = make_phantom(0).liver
    if volume_ml:
        liver = scaled_liver(liver, volume_ml)
    t0 = time.perf_counter()  # mesh + basis, as a case with its liver surface would take
    mesh, rep = cached_tetmesh(liver, edge, root)
    basis, _ = load_or_compute_basis(mesh, settings, cache_root=root)
    total = time.perf_counter() - t0
    t1 = time.perf_counter()
    cached_tetmesh(liver, edge, root)
    t2 = time.perf_counter()
    load_or_compute_basis(mesh, settings, cache_root=root)
    t3 = time.perf_counter()
    return {"edge_mm": edge, "k": k, "volume_ml": round(liver.volume / 1000.0), "relax": relax,
            "relax_layers": settings.relax_layers, "nodes": basis.M, "surface_nodes": len(basis.surface),
            # which sparse solver and which mesher attempt: SuperLU in place of PARDISO is 5-10x the modes' time
            "solver": backend(), "mesher": "reused" if mesh_from else rep.get("method"),
            "seconds": {"mesh": "reused" if mesh_from else round(rep["seconds"], 2),
                        **{s: round(v, 2) for s, v in basis.timings.items()}},
            "total_seconds": round(total, 2), "peak_memory_mb": round(peak_memory_mb()),
            "cache_load_seconds": {"mesh": round(t2 - t1, 3), "basis": round(t3 - t2, 3), "total": round(t3 - t1, 3)},
            "basis_file": str(root / f"{basis_key(mesh, settings, Material())}.npz"),
            "mesh_file": str(next(root.glob("mesh-*.npz")))}


def mode_errors(fast_file, exact_file) -> dict:
    """Per-mode relative error ‖Ju_fast − Ju_exact‖/‖Ju_exact‖ (one per column): median, max."""

    fast, exact = cache.load(Path(fast_file)), cache.load(Path(exact_file))
    if fast is None or exact is None:
        raise NavappError(f"basis cache entry missing: {fast_file if fast is None else exact_file}")
    a, b = fast["Ju"], exact["Ju"]
    e = np.linalg.norm(a - b, axis=0) / np.linalg.norm(b, axis=0)
    return {"median": float(f"{np.median(e):.3g}"), "max": float(f"{e.max():.3g}")}


def bench_precompute(edges, ks, volume_ml=None, relax="local"):
    """One row per (edge, k, relaxation). With relax="both" the local basis is computed,
    then the exact one on the same mesh (its row without mesh time), and the local row
    also reports its per-mode error against exact."""
    rows = []
    for edge in edges:
        for k in ks:
            pair: dict[str, dict] = {}
            for how in (("local", "exact") if relax == "both" else (relax,)):
                cmd = [sys.executable, "-m", "navapp.evaluation.benchmark", "precompute-one", str(edge), str(k), how,
                       str(volume_ml or 0)]
                if pair:
                    cmd.append(pair["local"]["mesh_file"])
                out = subprocess.run(cmd, capture_output=True, text=True, check=True)
                pair[how] = row = json.loads(out.stdout.strip().splitlines()[-1])
                rows.append(row)
            if len(pair) == 2:
                pair["exact"]["mode_error_vs_local"] = mode_errors(pair["local"]["basis_file"],
                                                                   pair["exact"]["basis_file"])
            for row in pair.values():
                shutil.rmtree(Path(row.pop("basis_file")).parent, ignore_errors=True)
                row.pop("mesh_file")
                print(json.dumps(row), flush=True)
    return rows


def bench_register(repeats=5, planes=3, k=K, edge=EDGE_MM, truth_edge=None):
    """Demo scene, stylus data + the first ``planes`` iUS planes; then one more plane
    added and the fit warm-started from the previous state. The fresh registration is also
    run as before issue 49's hierarchy and compiled Jacobian (``live_bench.before_path``),
    alternated with it repeat by repeat, each on its own
    copy of the model's cache: ``before_after`` holds the medians (CPU and wall) and the TREs
    of each. A third variant, ``cold_search``, is the new path with every surface search begun
    at the hierarchy's root (``objective.cold_search``: as before LM's searches started from
    the last iteration's triangles, session 38), in the same rotation. ``truth_edge``: the
    mesh the scene is simulated on, mm (default the scene's)."""

    scene = demo_scene()
    # the simulated scene from navapp's cache (as ``bench live`` and the viewer take it):
    # the benchmark times registrations, not the simulation
    folder = simulated_case_dir(scene if truth_edge is None else replace(scene, mesh_edge_mm=truth_edge))
    case = read_case(folder)
    data = data_level(folder, "S+planes", planes=range(planes), case=case)
    more = data_level(folder, "S+planes", planes=range(planes + 1), case=case)
    model, _ = prepare(case, edge, k)
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    times, rigid_s, support_s, iters = [], [], [], []
    variants = ("before", "cold_search", "after")
    stages: dict[str, dict[str, dict[str, list]]] = {v: {} for v in variants}  # variant → stage → cpu, wall
    models = {v: model if v == "after" else replace(model, cache=model.cache.copy()) for v in variants}
    switch: dict[str, Callable[[], AbstractContextManager]] = {"before": before_path, "cold_search": cold_search,
                                                                "after": nullcontext}
    paired: dict[str, dict[str, list]] = {v: {"cpu": [], "wall": [], "tre": []} for v in variants}
    for i in range(repeats):
        for variant in (variants if i % 2 == 0 else variants[::-1]):
            with switch[variant]():
                c, t = time.process_time(), time.perf_counter()
                r = register(models[variant], data)
                paired[variant]["cpu"].append(time.process_time() - c)
                paired[variant]["wall"].append(time.perf_counter() - t)
            paired[variant]["tre"].append(round(tre_stats(r.transform(x0), x1)["mean_mm"], 4))
            for name, st in r.stages.items():
                lap = stages[variant].setdefault(name, {"cpu": [], "wall": []})
                lap["cpu"].append(st.cpu)
                lap["wall"].append(st.wall)
            if variant == "after":
                reg = r
        assert reg.libr is not None  # deformable registration
        times.append(reg.seconds["rigid"] + reg.seconds["deformable"])
        rigid_s.append(reg.seconds["rigid"])
        # the cross-validation of a fresh deformation (``support``): the guard's cost, apart
        support_s.append(reg.seconds.get("support", 0.0))
        iters.append(reg.libr.iterations)
    libr = reg.libr
    assert libr is not None
    per_iter = {s: round(1000 * v / max(libr.iterations, 1), 2) for s, v in libr.timings.items()}
    warm_times = []
    for _ in range(repeats):
        t = time.perf_counter()
        warm = register(model, more, beta0=libr.beta, rigid=reg.rigid)
        warm_times.append(time.perf_counter() - t)
    warm_iterations = warm.libr.iterations if warm.libr is not None else 0
    cold = register(model, more)
    quick = register(model, data, options=LMOptions(max_iterations=5))
    out = {
        "before_after": {v: {"median_cpu_seconds": round(statistics.median(d["cpu"]), 3),
                             "median_wall_seconds": round(statistics.median(d["wall"]), 3),
                             "tre_mm": sorted(set(d["tre"]))} for v, d in paired.items()},
        # the fresh registration's stages (``Registration.stages``), median CPU and wall seconds
        "stages": {v: {name: {"cpu": round(statistics.median(lap["cpu"]), 4),
                              "wall": round(statistics.median(lap["wall"]), 4)} for name, lap in st.items()}
                   for v, st in stages.items()},
        "nodes": model.basis.M, "k": model.basis.k, "planes": planes,
        "points": {n: len(p) for n, p in reg.data_model_frame.items()},
        "median_seconds": round(statistics.median(times), 3), "min_seconds": round(min(times), 3),
        "median_rigid_icp_seconds": round(statistics.median(rigid_s), 3),
        "median_support_seconds": round(statistics.median(support_s), 3),
        "median_with_support_seconds": round(statistics.median(np.add(times, support_s)), 3),
        "iterations": iters[0], "stop_reason": libr.stop_reason, "per_iteration_ms": per_iter,
        "add_one_plane": {"warm_median_seconds": round(statistics.median(warm_times), 4),
                          "warm_min_seconds": round(min(warm_times), 4), "warm_iterations": warm_iterations,
                          "cold_seconds": round(cold.seconds["rigid"] + cold.seconds["deformable"], 3),
                          "tre_warm_mm": round(tre_stats(warm.transform(x0), x1)["mean_mm"], 2),
                          "tre_cold_mm": round(tre_stats(cold.transform(x0), x1)["mean_mm"], 2)},
        "tre_mm": {"rigid": round(tre_stats(reg.rigid.apply(x0), x1)["mean_mm"], 2),
                   "deformable": round(tre_stats(reg.transform(x0), x1)["mean_mm"], 2),
                   "deformable_5_iterations": round(tre_stats(quick.transform(x0), x1)["mean_mm"], 2)},
    }
    print(stage_table(out["stages"]), flush=True)
    print(json.dumps(out), flush=True)
    return out


def stage_table(stages: dict) -> str:
    """The fresh registration's stages as a text table: median CPU and wall ms per stage for
    each variant, and the sum of those medians (about the whole ``register`` call)."""
    variants = list(stages)
    names = list(dict.fromkeys(n for v in variants for n in stages[v]))
    c = max(14, *(len(v) + 7 for v in variants))  # a column wider than its name: the heads stay apart
    head = "stage (median ms)".ljust(20) + "".join(f"{v + ' cpu':>{c}}{v + ' wall':>{c}}" for v in variants)
    lines = [head]
    for name in [*names, "sum"]:
        cells = []
        for v in variants:
            if name == "sum":
                cpu, wall = (sum(s[k] for s in stages[v].values()) for k in ("cpu", "wall"))
            else:
                s = stages[v].get(name, {"cpu": 0.0, "wall": 0.0})
                cpu, wall = s["cpu"], s["wall"]
            cells.append(f"{1000 * cpu:{c}.1f}{1000 * wall:{c}.1f}")
        lines.append(name.ljust(20) + "".join(cells))
    return "\n".join(lines)


if __name__ == "__main__" and len(sys.argv) in (6, 7) and sys.argv[1] == "precompute-one":
    from .. import progress

    progress.QUIET = True
    vol = float(sys.argv[5]) or None
    mesh_from = sys.argv[6] if len(sys.argv) == 7 else None
    print(json.dumps(precompute_one(float(sys.argv[2]), int(sys.argv[3]), vol, sys.argv[4], mesh_from)))
