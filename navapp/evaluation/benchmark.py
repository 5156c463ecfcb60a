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
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext
from dataclasses import replace
from pathlib import Path

import numpy as np
import trimesh

from .. import cache
from ..anatomy.caseio import read_case
from ..anatomy.meshing import cached_tetmesh, netgen_always
from ..anatomy.phantom import make_phantom
from ..defaults import EDGE_MM, K
from ..errors import NavappError
from ..geometry.tre import mean_tre
from ..mechanics.basis import BasisSettings, basis_key, load_or_compute_basis, relax_as_before
from ..mechanics.fem import Material
from ..mechanics.sparse import backend
from ..registration.libr import LMOptions
from ..registration.objective import cold_search
from ..registration.pipeline import prepare, register
from ..registration.support import sequential_folds
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


@contextmanager
def before_precompute():
    """Within it, the precompute runs as at session 40's start: every Gmsh mesh with
    Netgen's pass, no HXT attempt first on a CT label map's staircase (``meshing.netgen_always``);
    the relaxation's tiles one after another (``basis.relax_as_before``). The bench's "before"
    (process-wide)."""
    with netgen_always(), relax_as_before():
        yield


def precompute_one(edge: float, k: int, volume_ml: float | None = None, relax: str = "local",
                   mesh_from: str | None = None, surface_file: str | None = None, before: bool = False) -> dict:
    """Run in a fresh process (cold cache dir) so that peak memory is this run's alone.
    ``relax``: "local" (the default subdomain) or "exact" (whole-mesh relaxation).
    ``mesh_from``: a cached mesh file to start from (Gmsh does not give the same mesh twice,
    and exact and local bases are compared on one mesh); its row then has no mesh time.
    ``surface_file``: the liver surface (.npz, vertices and faces) in place of phantom 0.
    ``before``: run as at session 40's start (``before_precompute``)."""

    settings = BasisSettings(k=k) if relax == "local" else BasisSettings(k=k, relax_layers=None)
    root = Path(tempfile.mkdtemp(prefix="navapp-bench-"))
    if mesh_from:
        shutil.copy(mesh_from, root)
    if surface_file:
        with np.load(surface_file) as f:
            liver = trimesh.Trimesh(f["vertices"], f["faces"], process=False)
    else:
        liver = make_phantom(0).liver
        if volume_ml:
            liver = scaled_liver(liver, volume_ml)
    with before_precompute() if before else nullcontext():
        t0 = time.perf_counter()  # mesh + basis, as a case with its liver surface would take
        mesh, rep = cached_tetmesh(liver, edge, root)
        basis, _ = load_or_compute_basis(mesh, settings, cache_root=root)
        total = time.perf_counter() - t0
        t1 = time.perf_counter()
        cached_tetmesh(liver, edge, root)
        t2 = time.perf_counter()
        load_or_compute_basis(mesh, settings, cache_root=root)
        t3 = time.perf_counter()
    return {"variant": "before" if before else "after",
            "edge_mm": edge, "k": k, "volume_ml": round(liver.volume / 1000.0), "relax": relax,
            "relax_layers": settings.relax_layers, "nodes": basis.M, "surface_nodes": len(basis.surface),
            # which sparse solver and which mesher attempt: SuperLU in place of PARDISO is 5-10x the modes' time
            "solver": backend(), "mesher": "reused" if mesh_from else rep.get("method"),
            "mesher_why": "reused" if mesh_from else rep["mesher"]["why"],
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


def _precompute_child(edge, k, how, volume_ml, surface_file=None, mesh_from=None, before=False) -> dict:
    """``precompute_one`` in a fresh process; adds ``process_cpu_seconds``, the child's CPU
    with its mesher workers', and ``process_seconds``, its wall time (imports included)."""
    cmd = [sys.executable, "-m", "navapp.evaluation.benchmark", "precompute-one", str(edge), str(k), how,
           str(volume_ml or 0)]
    if mesh_from:
        cmd += ["--mesh-from", mesh_from]
    if surface_file:
        cmd += ["--surface", surface_file]
    if before:
        cmd.append("--before")
    used = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    out = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t
    now = resource.getrusage(resource.RUSAGE_CHILDREN)
    if out.returncode != 0:
        raise NavappError(f"precompute-one failed: {(out.stderr.strip().splitlines() or [''])[-1]}")
    row = json.loads(out.stdout.strip().splitlines()[-1])
    row["process_cpu_seconds"] = round(now.ru_utime + now.ru_stime - used.ru_utime - used.ru_stime, 2)
    row["process_seconds"] = round(wall, 2)
    return row


def _drop_files(row: dict):
    shutil.rmtree(Path(row.pop("basis_file")).parent, ignore_errors=True)
    row.pop("mesh_file")


def bench_precompute(edges, ks, volume_ml=None, relax="local", repeats=1, labelmap=False, phantom=0):
    """Per (edge, k): ``repeats`` pairs of fresh-process runs, before session 40's changes
    (``before_precompute``) and after, alternated (before first in even pairs); one JSON
    line per run, then per (edge, k) the medians side by side (a table and a JSON line:
    whole-process wall and CPU, mesh + basis, each stage; the median of the per-pair ratios).
    ``labelmap``: the liver as an import of its CT label map gives it (``ctcase.imported_liver``),
    made once; ``phantom``: which phantom's liver (scaled to ``volume_ml`` when given).
    With relax="both" (no before/after): the local basis, then the exact one on the same mesh
    (its row without mesh time), with the local one's per-mode error against exact."""
    rows = []
    with tempfile.TemporaryDirectory(prefix="navapp-bench-surface-") as tmp:
        surface_file = None
        if labelmap or phantom:
            liver = make_phantom(phantom).liver
            liver = scaled_liver(liver, volume_ml) if volume_ml else liver
            if labelmap:
                from ..anatomy.ctcase import imported_liver

                liver = imported_liver(liver)
            surface_file = str(Path(tmp, "liver.npz"))
            np.savez(surface_file, vertices=liver.vertices, faces=liver.faces)
        for edge in edges:
            for k in ks:
                if relax == "both":
                    local = _precompute_child(edge, k, "local", volume_ml, surface_file)
                    exact = _precompute_child(edge, k, "exact", volume_ml, surface_file, local["mesh_file"])
                    exact["mode_error_vs_local"] = mode_errors(local["basis_file"], exact["basis_file"])
                    for row in (local, exact):
                        _drop_files(row)
                        rows.append(row)
                        print(json.dumps(row), flush=True)
                    continue
                pairs: dict[str, list[dict]] = {"before": [], "after": []}
                for i in range(repeats):
                    for variant in (("before", "after") if i % 2 == 0 else ("after", "before")):
                        row = _precompute_child(edge, k, relax, volume_ml, surface_file, before=variant == "before")
                        _drop_files(row)
                        row["run"] = i
                        pairs[variant].append(row)
                        rows.append(row)
                        print(json.dumps(row), flush=True)
                summary = before_after_summary(pairs)
                print(precompute_table(summary), flush=True)
                print(json.dumps(summary), flush=True)
    return rows


def _stage_seconds(row: dict) -> dict:
    s = {n: v for n, v in row["seconds"].items() if isinstance(v, (int, float))}
    return {**s, "mesh + basis": row["total_seconds"], "process wall": row["process_seconds"],
            "process cpu": row["process_cpu_seconds"]}


def before_after_summary(pairs: dict[str, list[dict]]) -> dict:
    """Medians before and after of each stage and of the whole process, and the median of
    the per-pair ratios after / before (wall and CPU of the whole process)."""
    before, after = pairs["before"], pairs["after"]
    first = after[0]
    stages = {v: [_stage_seconds(r) for r in rs] for v, rs in pairs.items()}
    names = list(dict.fromkeys(n for v in stages.values() for r in v for n in r))
    med = {v: {n: round(statistics.median(r[n] for r in rs if n in r), 2) for n in names if any(n in r for r in rs)}
           for v, rs in stages.items()}
    ratio = {what: round(statistics.median(a[what] / b[what] for a, b in zip(after, before, strict=True)), 3)
             for what in ("process_seconds", "process_cpu_seconds", "total_seconds")}
    return {"before_after": {"runs": len(after), "edge_mm": first["edge_mm"], "k": first["k"],
                             "volume_ml": first["volume_ml"], "relax": first["relax"],
                             "nodes": [before[0]["nodes"], first["nodes"]],
                             "mesher": [before[0]["mesher_why"], first["mesher_why"]],
                             "median_seconds": med, "after_over_before_median": ratio}}


def precompute_table(summary: dict) -> str:
    """The medians before and after as a text table, one stage a row."""
    s = summary["before_after"]
    med = s["median_seconds"]
    lines = [f"precompute at {s['edge_mm']:g} mm, k = {s['k']}, {s['volume_ml']} ml, {s['nodes'][1]} nodes: "
             f"medians of {s['runs']} runs each (s)", f"{'stage':<16}{'before':>10}{'after':>10}"]
    for name in med["after"]:
        lines.append(f"{name:<16}{med['before'].get(name, float('nan')):>10.2f}{med['after'][name]:>10.2f}")
    r = s["after_over_before_median"]
    lines.append(f"after / before, median of pairs: process wall {r['process_seconds']:.3f}, "
                 f"process cpu {r['process_cpu_seconds']:.3f}")
    return "\n".join(lines)


def bench_register(repeats=5, planes=3, k=K, edge=EDGE_MM, truth_edge=None):
    """Demo scene, stylus data + the first ``planes`` iUS planes; then one more plane
    added and the fit warm-started from the previous state. The fresh registration is also
    run as before issue 49's hierarchy and compiled Jacobian (``live_bench.before_path``),
    alternated with it repeat by repeat, each on its own
    copy of the model's cache: ``before_after`` holds the medians (CPU and wall) and the TREs
    of each. A third variant, ``cold_search``, is the new path with every surface search begun
    at the hierarchy's root (``objective.cold_search``: as before LM's searches started from
    the last iteration's triangles, session 38), and a fourth, ``sequential_folds``, the new
    path with the cross-validation's folds one after another in one thread, and the rest of
    the fresh registration in turn with them (``support.sequential_folds``: as before they shared
    the cores, sessions 40–41; "before" has them so too), in the same rotation. Both threads'
    CPU counts (the process's), so CPU over wall says how much ran at once. ``truth_edge``: the
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
    variants = ("before", "cold_search", "sequential_folds", "after")
    stages: dict[str, dict[str, dict[str, list]]] = {v: {} for v in variants}  # variant → stage → cpu, wall
    models = {v: model if v == "after" else replace(model, cache=model.cache.copy()) for v in variants}
    switch: dict[str, Callable[[], AbstractContextManager]] = {"before": _before_register, "cold_search": cold_search,
                                                                "sequential_folds": sequential_folds,
                                                                "after": nullcontext}
    paired: dict[str, dict[str, list]] = {v: {"cpu": [], "wall": [], "tre": []} for v in variants}
    for i in range(repeats):
        for variant in (variants if i % 2 == 0 else variants[::-1]):
            with switch[variant]():
                c, t = time.process_time(), time.perf_counter()
                r = register(models[variant], data)
                paired[variant]["cpu"].append(time.process_time() - c)
                paired[variant]["wall"].append(time.perf_counter() - t)
            paired[variant]["tre"].append(round(mean_tre(r.transform(x0), x1), 4))
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
                          "tre_warm_mm": round(mean_tre(warm.transform(x0), x1), 2),
                          "tre_cold_mm": round(mean_tre(cold.transform(x0), x1), 2)},
        "tre_mm": {"rigid": round(mean_tre(reg.rigid.apply(x0), x1), 2),
                   "deformable": round(mean_tre(reg.transform(x0), x1), 2),
                   "deformable_5_iterations": round(mean_tre(quick.transform(x0), x1), 2)},
    }
    print(stage_table(out["stages"]), flush=True)
    print(json.dumps(out), flush=True)
    return out


@contextmanager
def _before_register() -> Iterator[None]:
    """A fresh registration as before issue 49: LM's earlier search and Jacobian
    (``before_path``) and the folds one after another (``sequential_folds``)."""
    with before_path(), sequential_folds():
        yield


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


if __name__ == "__main__" and len(sys.argv) >= 6 and sys.argv[1] == "precompute-one":
    import argparse

    from .. import progress

    progress.QUIET = True
    ap = argparse.ArgumentParser(prog="python -m navapp.evaluation.benchmark precompute-one")
    ap.add_argument("edge", type=float)
    ap.add_argument("k", type=int)
    ap.add_argument("relax", choices=("local", "exact"))
    ap.add_argument("volume_ml", type=float)
    ap.add_argument("--mesh-from")
    ap.add_argument("--surface")
    ap.add_argument("--before", action="store_true")
    a = ap.parse_args(sys.argv[2:])
    print(json.dumps(precompute_one(a.edge, a.k, a.volume_ml or None, a.relax, a.mesh_from, a.surface, a.before)))
