"""CPU and wall time per live update of the viewer's default path (``LiveRegistration``'s
defaults: one LM iteration per frame; since session 40 the kernels split between two threads
where that has been faster lately) on the demo liver with the stylus and 3 planes kept, the frames of ``navapp bench
live`` — one variant only, so that two versions of navapp can be run as separate processes
and alternated (issue 49's before/after):

    python notes/scripts/live_updates.py [--frames 40]

Prints one JSON line: medians and p90 over the updates (after the first), CPU ms per update,
the per-iteration stages of the last update, β's pose part and the mean TRE after the last frame.
"""

import argparse
import json
import os
import statistics
import time
from dataclasses import replace

import numpy as np

from navapp.defaults import EDGE_MM, K
from navapp.evaluation.live_bench import _poses
from navapp.geometry.interpolation import interpolation_matrix
from navapp.geometry.tre import mean_tre
from navapp.registration.live import LiveRegistration
from navapp.registration.pipeline import prepare, register
from navapp.simulation.levels import data_level
from navapp.simulation.scene import demo_scene
from navapp.simulation.scenedata import load_scene_data, segment_frame

parser = argparse.ArgumentParser()
parser.add_argument("--frames", type=int, default=40)
args = parser.parse_args()
sd = load_scene_data(demo_scene(), edge=EDGE_MM)
base = data_level(sd.case_dir, "S+planes", planes=range(3), case=sd.case)
model, _ = prepare(sd.case, EDGE_MM, K)
cold = register(model, base)
live = LiveRegistration(replace(model, cache=model.cache.copy()), base, iterations_per_frame=1)
live.last = cold
frames = [f for f in (segment_frame(sd, 5000 + i, p) for i, p in enumerate(_poses(sd, 3, args.frames, 8))) if f]
live.update(frames[0])  # the first update loads the compiled code
wall, cpu, stages = [], [], {}
for f in frames[1:]:
    t, c = time.perf_counter(), time.process_time()
    reg = live.update(f)
    wall.append(1000 * (time.perf_counter() - t))
    cpu.append(1000 * (time.process_time() - c))
    for k, v in reg.libr.timings.items():
        stages[k] = stages.get(k, 0.0) + 1000 * v / max(reg.libr.iterations, 1)
x0, x1 = sd.case.need_truth().tre_points(model.basis.nodes)  # the demo is simulated: its truth is known
B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
print(json.dumps({"updates": len(wall), "median_ms": round(statistics.median(wall), 2),
                  "p90_ms": round(float(np.percentile(wall, 90)), 2),
                  "cpu_median_ms": round(statistics.median(cpu), 2),
                  "cpu_p90_ms": round(float(np.percentile(cpu, 90)), 2),
                  "stages_mean_ms": {k: round(v / len(wall), 2) for k, v in stages.items()},
                  "pose_after_last": [round(float(x), 6) for x in reg.libr.beta[-6:]],
                  "tre_after_last_mm": round(mean_tre(reg.transform(x0, B=B), x1), 4),
                  "split_share": round(float(np.mean(getattr(live, "split", [False])[1:])), 2),
                  "load": [round(x, 2) for x in os.getloadavg()]}), flush=True)
