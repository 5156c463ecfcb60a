"""``navapp bench live``: the viewer's re-registration per new ultrasound frame, measured.

On the demo liver (phantom 0, 4 mm, k = 45) with the stylus data + 3 iUS planes kept, the
probe glides through further plane poses; each frame's contours are designated by the
scene's declared automatic segmentation (``simulation.scenedata.segment_frame``, as the
viewer does) and the model is re-registered warm-started (``registration.live.LiveRegistration``).
The variants run on the same frames, interleaved frame by frame in one run (machines of
this kind differ 2–3× in speed, and load moves absolute times: compare within a run):

- ``default``: what the viewer does — one LM iteration per frame (the next frame continues
  from there, so the fit converges across frames), BLAS/OpenMP/MKL limited to one thread, the
  compiled kernels split between two threads where that has been faster lately
  (``LiveRegistration``'s ``SecondCore``; ``split_share``: the updates that were split);
- ``converged_one_thread``: LM to convergence on every frame, one thread;
- ``converged_as_installed``: the same with the thread pools as installed and the kernels
  split among all cores;
- ``default_before``: ``default`` as before issue 49's hierarchy and compiled Jacobian
  (``before_path``: the surfaces searched by the k-d tree's candidate triangles, the
  Jacobian's α columns by SciPy and NumPy): before and after side by side, on
  the same frames under the same load (``before_after``: per-update ratios, per-stage ms);
- ``default_cold_search``: ``default`` with every surface search begun at the hierarchy's
  root (``objective.cold_search``), as before LM's searches started from the last
  iteration's triangles (session 38): ``before_after_warm_search``, the same figures;
- ``default_search_whole``: ``default`` with a contour feature the new frame adds to searched
  whole again (``objective.search_whole``), as before the kept planes' points of it, searched at
  the same β by the last update's final evaluation, kept their rows (session 39):
  ``before_after_kept_points``, the same figures;
- ``default_one_thread``: ``default`` on one thread (as before session 40's second core), and
  ``default_always_split``: ``default`` with every update split between two threads, whether
  or not that is faster: ``before_after_second_core`` and ``before_after_always_split``.

Each variant has its own copy of the model's cache: variants that reach the same β
(before and after give the same bits) would otherwise reuse each other's evaluations.

Prints one JSON line: ms per update (median, distribution, share within 33 ms = one frame
at 30 Hz), LM iterations, where the time goes per iteration (closest points against the
rest), the segmentation's ms per frame, the TRE after the last frame per variant, and the
one-thread / as-installed ratio.
"""

import json
import statistics
import time
from contextlib import contextmanager, nullcontext
from dataclasses import replace

import numpy as np
from threadpoolctl import threadpool_info

from ..defaults import EDGE_MM, K
from ..geometry.closest import kd_search
from ..geometry.interpolation import interpolation_matrix
from ..geometry.transforms import interpolate_pose
from ..geometry.tre import mean_tre
from ..registration.live import LiveRegistration
from ..registration.objective import cold_search, numpy_jacobian, search_whole
from ..registration.pipeline import prepare, register
from ..simulation.levels import data_level
from ..simulation.scene import demo_scene
from ..simulation.scenedata import auto_segmentation, load_scene_data, segment_frame

DEFAULT = {"threads": 2, "iterations_per_frame": 1}  # the viewer's (``LiveRegistration``'s defaults)
VARIANTS: dict[str, dict] = {"default": DEFAULT,
            "converged_one_thread": {"threads": 1, "iterations_per_frame": None},
            "converged_as_installed": {"threads": None, "iterations_per_frame": None},
            "default_before": DEFAULT, "default_cold_search": DEFAULT, "default_search_whole": DEFAULT,
            "default_one_thread": {**DEFAULT, "threads": 1},
            "default_always_split": {**DEFAULT, "adapt": False}}
# the switch a "before" variant runs under
SWITCH = {"default_before": "before_path", "default_cold_search": "cold_search", "default_search_whole": "search_whole"}
# (before, after, the pair's key in the output)
PAIRS = [("default_before", "default", "before_after"),
         ("default_cold_search", "default", "before_after_warm_search"),
         ("default_search_whole", "default", "before_after_kept_points"),
         ("default_one_thread", "default", "before_after_second_core"),
         ("default_one_thread", "default_always_split", "before_after_always_split")]
FRAME_MS = 1000.0 / 30  # one frame at 30 Hz


@contextmanager
def before_path():
    """Within it, LM runs as before the refitted hierarchy and the compiled Jacobian (the k-d
    search, SciPy/NumPy's α columns): the benches' "before". JᵀWJ's symmetric product and the
    cheaper statistics are not undone (the same answers within rounding)."""
    with kd_search(), numpy_jacobian():
        yield


def _switch(variant):
    """The path a variant runs on (``SWITCH``)."""
    if variant not in SWITCH:
        return nullcontext()
    return {"before_path": before_path, "cold_search": cold_search, "search_whole": search_whole}[SWITCH[variant]]()


def _poses(sd, first_plane, count, per_transit):
    """``count`` probe poses gliding from plane ``first_plane`` through the next ones."""
    poses = [p.probe_to_tracker for p in sd.planes]
    out: list[np.ndarray] = []
    i = first_plane
    while len(out) < count:
        a, b = poses[i % len(poses)], poses[(i + 1) % len(poses)]
        out += [interpolate_pose(a, b, j / per_transit) for j in range(per_transit)]
        i += 1
    return out[:count]


def _pct(xs, q):
    return round(float(np.percentile(xs, q)), 1)


def _last(live: LiveRegistration):
    assert live.last is not None  # every variant started from the cold registration
    return live.last


def bench_live(frames=40, planes=3, k=K, edge=EDGE_MM, per_transit=8, truth_edge=None):
    """``truth_edge``: the mesh the demo scene is simulated on, mm (default the scene's)."""
    scene = demo_scene()
    sd = load_scene_data(scene if truth_edge is None else replace(scene, mesh_edge_mm=truth_edge), edge=edge)
    if auto_segmentation(sd.scene) is None:
        raise ValueError("the demo scene declares no automatic segmentation of live frames")
    base = data_level(sd.case_dir, "S+planes", planes=range(planes), case=sd.case)
    model, _ = prepare(sd.case, edge, k)
    t = time.perf_counter()
    cold = register(model, base)  # where the surgeon switches re-registration on
    cold_s = time.perf_counter() - t
    live = {}
    for name, kw in VARIANTS.items():
        live[name] = LiveRegistration(replace(model, cache=model.cache.copy()), base, **kw)
        live[name].last = cold
    rows: dict[str, list[dict]] = {name: [] for name in VARIANTS}
    seg_ms, frame_pts = [], []
    for i, pose in enumerate(_poses(sd, planes, frames, per_transit)):
        t = time.perf_counter()
        feats = segment_frame(sd, 5000 + i, pose)
        seg_ms.append(1000 * (time.perf_counter() - t))
        if not feats:
            continue
        frame_pts.append(sum(len(v) for v in feats.values()))
        names = list(VARIANTS) if i % 2 == 0 else list(reversed(VARIANTS))  # interleaved: load hits all alike
        for name in names:
            with _switch(name):
                t = time.perf_counter()
                reg = live[name].update(feats)
                wall = 1000 * (time.perf_counter() - t)
            rows[name].append({"ms": wall, "iterations": reg.libr.iterations, "split": live[name].split[-1],
                               "stages_ms": {s: 1000 * v for s, v in reg.libr.timings.items()},
                               "outside_lm_ms": wall - 1000 * reg.seconds.get("deformable", wall / 1000)})
    x0, x1 = sd.case.need_truth().tre_points(model.basis.nodes)  # the demo scene is simulated: its truth is known
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
    out = {"liver": "demo (phantom 0)", "nodes": model.basis.M, "k": model.basis.k, "kept_planes": planes,
           "updates": len(rows["default"]), "frame_points_median": int(np.median(frame_pts)),
           "kept_points": int(sum(len(v) for v in base.values())), "cold_start_s": round(cold_s, 3),
           "segmentation_ms_median": round(statistics.median(seg_ms), 1)}
    for name, rs in rows.items():
        ms = [r["ms"] for r in rs]
        its = [r["iterations"] for r in rs]
        n_it = max(sum(its), 1)
        stages = {s: sum(r["stages_ms"][s] for r in rs) / n_it for s in rs[0]["stages_ms"]}
        per_it = sum(r["ms"] - r["outside_lm_ms"] for r in rs) / n_it
        pi = {**{s: round(v, 2) for s, v in stages.items()}, "total": round(per_it, 2),
              "other": round(per_it - sum(stages.values()), 2)}
        pi["closest_points_share"] = round((pi.get("closest", 0) + pi.get("kdtree", 0)) / max(pi["total"], 1e-9), 2)
        out[name] = {"median_ms": round(statistics.median(ms), 1), "p10_ms": _pct(ms, 10), "p90_ms": _pct(ms, 90),
                     "min_ms": round(min(ms), 1), "max_ms": round(max(ms), 1),
                     "within_one_frame_at_30hz": round(float(np.mean(np.array(ms) <= FRAME_MS)), 2),
                     "iterations_median": statistics.median(its), "per_iteration_ms": pi,
                     "outside_lm_ms_median": round(statistics.median(r["outside_lm_ms"] for r in rs), 1),
                     "split_share": round(float(np.mean([r["split"] for r in rs])), 2),
                     "tre_after_last_frame_mm": round(mean_tre(_last(live[name]).transform(x0, B=B), x1),
                                                      2)}
    a, b = rows["converged_one_thread"], rows["converged_as_installed"]
    ratios = [x["ms"] / y["ms"] for x, y in zip(a, b, strict=True)]
    out["one_thread_over_installed"] = {"median_of_ratios": round(statistics.median(ratios), 3)}
    for before, after, key in PAIRS:
        pairs = [x["ms"] / y["ms"] for x, y in zip(rows[before], rows[after], strict=True)]
        stages = {s: [out[before]["per_iteration_ms"][s], out[after]["per_iteration_ms"][s]]
                  for s in out[after]["per_iteration_ms"] if s != "closest_points_share"}
        tre = [out[v]["tre_after_last_frame_mm"] for v in (before, after)]
        out[key] = {"variants": [before, after],
                               "before_over_after_median": round(statistics.median(pairs), 3),
                               "median_ms": [out[before]["median_ms"], out[after]["median_ms"]],
                               "per_iteration_ms": stages, "tre_after_last_frame_mm": tre}
    out["thread_pools"] = [{k: p.get(k) for k in ("internal_api", "num_threads")} for p in threadpool_info()]
    print(json.dumps(out), flush=True)
    return out
