"""The live update's compiled kernels, one thread against their builds split between two
(``threads.split_kernels``), on the inputs one live update of the demo gives them (stylus +
3 planes kept, the frames of ``navapp bench live``): wall and CPU ms per update's calls, and
whether the answers are the same bits (issue 49, session 40):

    python notes/scripts/live_split_kernels.py [--repeats 200]

Prints one JSON line per kernel and the load average. Every call is split here, also those
under ``threads.SPLIT_MIN`` points that the registration keeps on one thread.
"""

import argparse
import json
import os
import time
from dataclasses import replace

import numpy as np

import navapp.geometry.bvh as bvh
import navapp.registration.jacobian_compiled as jc
from navapp.defaults import EDGE_MM, K
from navapp.evaluation.live_bench import _poses
from navapp.registration.live import LiveRegistration
from navapp.registration.pipeline import prepare, register
from navapp.simulation.levels import data_level
from navapp.simulation.scene import demo_scene
from navapp.simulation.scenedata import load_scene_data, segment_frame
from navapp.threads import split_kernels

parser = argparse.ArgumentParser()
parser.add_argument("--repeats", type=int, default=200)
args = parser.parse_args()
# (session 40 also split the pose columns, U·α and the refit: 0.16–0.25 ms an update each, and
# slower split, notes/live_split_kernels_s40.jsonl at 37fd2e2; dropped)
KERNELS = {"alpha_columns": (jc, "alpha_columns", "alpha_columns_split"),
           "closest": (bvh, "closest", "closest_split")}
recorded: dict = {k: [] for k in KERNELS}
on = [False]


def recording(name, fn):
    def call(*a):
        if on[0]:
            recorded[name].append([np.array(x, copy=True) if isinstance(x, np.ndarray) else x for x in a])
        return fn(*a)
    return call


originals = {name: getattr(mod, one) for name, (mod, one, _) in KERNELS.items()}
for name, (mod, one, _) in KERNELS.items():
    setattr(mod, one, recording(name, originals[name]))
sd = load_scene_data(demo_scene(), edge=EDGE_MM)
base = data_level(sd.case_dir, "S+planes", planes=range(3), case=sd.case)
model, _ = prepare(sd.case, EDGE_MM, K)
cold = register(model, base)
live = LiveRegistration(replace(model, cache=model.cache.copy()), base, threads=1)
live.last = cold
frames = [f for f in (segment_frame(sd, 5000 + i, p) for i, p in enumerate(_poses(sd, 3, 12, 8))) if f]
for f in frames[:-1]:
    live.update(f)
on[0] = True
live.update(frames[-1])
on[0] = False
for name, (mod, one, split) in KERNELS.items():
    setattr(mod, one, originals[name])
    calls = recorded[name]
    fns = {"one": originals[name], "split": getattr(mod, split)}
    times: dict = {"one": ([], []), "split": ([], [])}
    answers = {}
    for r in range(args.repeats):
        for way in (("one", "split") if r % 2 else ("split", "one")):
            copies = [[x.copy() if isinstance(x, np.ndarray) else x for x in a] for a in calls]
            with split_kernels(2 if way == "split" else 1):
                t, c = time.perf_counter(), time.process_time()
                if name == "closest" and way == "split":  # fills the caller's arrays
                    results = []
                    for a in copies:
                        out = (np.empty(len(a[0]), np.int64), np.empty((len(a[0]), 3)))
                        fns[way](*a, *out)
                        results.append(out)
                else:
                    results = [fns[way](*a) for a in copies]
                times[way][0].append(time.perf_counter() - t)
                times[way][1].append(time.process_time() - c)
            answers[way] = (copies, results)
    same = all(np.array_equal(x, y) for a, b in zip(answers["one"][0], answers["split"][0], strict=True)
               for x, y in zip(a, b, strict=True) if isinstance(x, np.ndarray))
    for a, b in zip(answers["one"][1], answers["split"][1], strict=True):  # returned arrays (the search's, refit's)
        if a is not None:
            same &= all(np.array_equal(x, y) for x, y in zip(a if isinstance(a, tuple) else (a,),
                                                               b if isinstance(b, tuple) else (b,), strict=True))
    print(json.dumps({"kernel": name, "calls_per_update": len(calls),
                      "points": [len(a[0]) for a in calls][:12],
                      **{f"{way}_{k}_ms": round(1000 * float(np.median(times[way][i])), 3)
                         for way in times for i, k in enumerate(("wall", "cpu"))},
                      "same_bits": bool(same), "load": [round(x, 2) for x in os.getloadavg()]}), flush=True)
