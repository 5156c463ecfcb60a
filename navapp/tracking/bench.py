"""``navapp bench live``: warm-started re-registration per new ultrasound frame on the demo
liver (phantom 0, 4 mm, k = 45) with the stylus data + 3 iUS planes kept, the probe then
gliding through further plane poses; each frame's contours come from the simulated
segmentation (the scene's declared effects: tracking noise). Prints one JSON line:
ms per update (median, distribution), LM iterations, where the time goes per iteration
(closest points against the rest), and the same updates with BLAS/OpenMP/MKL limited to
one thread (threadpoolctl) against as installed, interleaved frame by frame in one run, as
a ratio. A third variant, ``one_iteration``, caps LM at one iteration per frame (one
thread): the next frame continues from there, so the fit converges across frames; its TRE
after the last frame is reported beside the default's.
"""

import json
import statistics
import time

import numpy as np
from threadpoolctl import threadpool_info, threadpool_limits

from .live import merge
from .replay import interpolate_pose


def _frames(sd, first_plane, count, per_transit):
    """Features of ``count`` frames of the probe gliding from plane ``first_plane`` on."""
    from ..simulation.scenedata import acquire_free_plane

    poses = [p.probe_to_tracker for p in sd.planes]
    out = []
    i = first_plane
    while len(out) < count:
        a, b = poses[i % len(poses)], poses[(i + 1) % len(poses)]
        for j in range(per_transit):
            if len(out) == count:
                break
            pose = interpolate_pose(a, b, j / per_transit)
            out.append(acquire_free_plane(sd, 5000 + len(out), pose).features)
        i += 1
    return [f for f in out if f]


def _pct(xs, q):
    return float(np.percentile(xs, q))


def bench_live(frames=40, planes=3, k=45, edge=4.0, per_transit=8):
    from ..mechanics.interpolation import interpolation_matrix
    from ..registration.libr import LMOptions
    from ..registration.pipeline import prepare, register, tre_stats
    from ..simulation.levels import data_level
    from ..simulation.scene import demo_scene
    from ..simulation.scenedata import load_scene_data

    sd = load_scene_data(demo_scene(), edge=edge)
    base = data_level(sd.case_dir, "S+planes", planes=range(planes), case=sd.case)
    model, _ = prepare(sd.case, edge, k)
    feats = _frames(sd, planes, frames, per_transit)
    state = register(model, base)  # cold start on the kept data
    cold_s = state.seconds["rigid"] + state.seconds["deformable"]
    rows = {"installed": [], "one_thread": [], "one_iteration": []}
    one = LMOptions(max_iterations=1)
    quick = state
    for i, frame in enumerate(feats):
        data = merge(base, frame)
        order = ("installed", "one_thread") if i % 2 == 0 else ("one_thread", "installed")
        results = {}
        for how in (*order, "one_iteration"):
            ctx = threadpool_limits(1) if how != "installed" else None
            prev = quick if how == "one_iteration" else state
            if ctx:
                ctx.__enter__()
            try:
                t = time.perf_counter()
                reg = register(model, data, beta0=prev.libr.beta, rigid=prev.rigid,
                               options=one if how == "one_iteration" else None)
                wall = time.perf_counter() - t
            finally:
                if ctx:
                    ctx.__exit__(None, None, None)
            tim = dict(reg.libr.timings)
            rows[how].append({"ms": 1000 * wall, "iterations": reg.libr.iterations,
                              "stages_ms": {s: 1000 * v for s, v in tim.items()},
                              "outside_lm_ms": 1000 * (wall - reg.seconds.get("deformable", wall))})
            results[how] = reg
        state = results["one_thread"]  # both start from the same state; either result will do
        quick = results["one_iteration"]
    x0, x1 = sd.case.targets[:, :3], sd.case.targets[:, 3:]
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
    out = {"liver": "demo (phantom 0)", "nodes": model.basis.M, "k": model.basis.k, "kept_planes": planes,
           "updates": len(feats), "frame_points_median": int(np.median([sum(len(v) for v in f.values()) for f in feats])),
           "kept_points": int(sum(len(v) for v in base.values())), "cold_start_s": round(cold_s, 3)}
    for how, rs in rows.items():
        ms = [r["ms"] for r in rs]
        its = [r["iterations"] for r in rs]
        n_it = max(sum(its), 1)
        stages = {s: sum(r["stages_ms"][s] for r in rs) / n_it for s in rs[0]["stages_ms"]}
        per_it_total = sum((r["ms"] - r["outside_lm_ms"]) for r in rs) / n_it
        out[how] = {
            "median_ms": round(statistics.median(ms), 1), "p10_ms": round(_pct(ms, 10), 1),
            "p90_ms": round(_pct(ms, 90), 1), "max_ms": round(max(ms), 1), "min_ms": round(min(ms), 1),
            "within_33ms": round(float(np.mean(np.array(ms) <= 33.0)), 2),
            "iterations_median": statistics.median(its),
            "per_iteration_ms": {**{s: round(v, 2) for s, v in stages.items()}, "total": round(per_it_total, 2),
                                 "other": round(per_it_total - sum(stages.values()), 2)},
            "outside_lm_ms_median": round(statistics.median(r["outside_lm_ms"] for r in rs), 1),
        }
        pi = out[how]["per_iteration_ms"]
        pi["closest_points_share"] = round((pi["closest"] + pi["kdtree"]) / max(pi["total"], 1e-9), 2)
    out["tre_after_last_frame_mm"] = {how: round(tre_stats(r.transform(x0, B=B), x1)["mean_mm"], 2)
                                      for how, r in (("default", state), ("one_iteration", quick))}
    ratios = [a["ms"] / b["ms"] for a, b in zip(rows["one_thread"], rows["installed"])]
    out["one_thread_over_installed"] = {"median_of_ratios": round(statistics.median(ratios), 3),
                                        "ratio_of_medians": round(out["one_thread"]["median_ms"]
                                                                  / out["installed"]["median_ms"], 3)}
    out["thread_pools"] = [{k: p.get(k) for k in ("internal_api", "num_threads")} for p in threadpool_info()]
    print(json.dumps(out), flush=True)
    return out
