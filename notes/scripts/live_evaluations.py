"""CPU time of each evaluation of a live update (the viewer's default path: one LM iteration a
frame, one thread) on the demo liver with the stylus and 3 planes kept, the frames of ``navapp
bench live``: the new frame's first evaluation, its Jacobian, the held trial and the accepted
state's. Two variants alternated frame by frame in one process, each on its own copy of the
model's cache: today's path and ``objective.search_whole`` (a feature the frame adds to searched
whole again, as before session 39):

    python notes/scripts/live_evaluations.py [--frames 40] [--rounds 3]

Prints one JSON line per variant: median CPU ms per update of each part, and whether the two
variants' fits were the same bits after every frame.
"""

import argparse
import collections
import json
import statistics
import time
from contextlib import nullcontext
from dataclasses import replace

import numpy as np

import navapp.registration.libr as libr
import navapp.registration.objective as objective
from navapp.defaults import EDGE_MM, K
from navapp.evaluation.live_bench import _poses
from navapp.registration.live import LiveRegistration
from navapp.registration.pipeline import prepare, register
from navapp.simulation.levels import data_level
from navapp.simulation.scene import demo_scene
from navapp.simulation.scenedata import load_scene_data, segment_frame

parser = argparse.ArgumentParser()
parser.add_argument("--frames", type=int, default=40)
parser.add_argument("--rounds", type=int, default=3)
args = parser.parse_args()
sd = load_scene_data(demo_scene(), edge=EDGE_MM)
base = data_level(sd.case_dir, "S+planes", planes=range(3), case=sd.case)
model, _ = prepare(sd.case, EDGE_MM, K)
cold = register(model, base)
frames = [f for f in (segment_frame(sd, 5000 + i, p) for i, p in enumerate(_poses(sd, 3, args.frames, 8))) if f]
variants = {"today": nullcontext, "search_whole": objective.search_whole}
live = {v: LiveRegistration(replace(model, cache=model.cache.copy()), base, threads=1, iterations_per_frame=1)
        for v in variants}
parts: dict = {v: collections.defaultdict(list) for v in variants}
plain_evaluate, plain_jacobian = libr.evaluate, objective.add_jacobian
now: list = []


def timed_evaluate(*a, **kw):
    """LM's ``evaluate``, each kind timed apart (the first evaluation's Jacobian apart from it)."""
    jacobian = kw.get("jacobian", True)
    kind = "first" if jacobian else ("held" if kw.get("frozen") is not None else "accepted")
    c = time.process_time()
    ev = plain_evaluate(*a, **{**kw, "jacobian": False})
    now[-1][kind].append(time.process_time() - c)
    if jacobian:
        c = time.process_time()
        ev = plain_jacobian(a[0], ev, kw.get("alpha_columns", True))
        now[-1]["first_jacobian"].append(time.process_time() - c)
    return ev


libr.evaluate = timed_evaluate
same = True
for r in range(args.rounds):
    for v in variants:
        live[v].last = cold
    for i, f in enumerate(frames):
        regs = {}
        for v in (list(variants) if (i + r) % 2 == 0 else list(reversed(variants))):
            now.append(parts[v])
            c = time.process_time()
            with variants[v]():
                regs[v] = live[v].update(f)
            if i:  # the first update loads the compiled code
                parts[v]["update"].append(time.process_time() - c)
            now.pop()
        a, b = (regs[v].libr for v in variants)
        same = same and np.array_equal(a.beta, b.beta) and a.omega == b.omega and a.features == b.features
for v, p in parts.items():
    print(json.dumps({"variant": v, "updates": len(p["update"]), "same_fits": same,
                      "cpu_median_ms": {k: round(1000 * statistics.median(x), 3) for k, x in p.items()}}), flush=True)
